#version 460
#extension GL_GOOGLE_include_directive : require
#include "citystream.glsl"

// Vertex stage of a texture-atlas tree's visible pass: as city.vert, but a mesh drawn with
// a node's atlas samples it at its vertices' root-atlas coordinates through that node's
// texture matrix (docs/ATLAS_TREE.md), so one vertex buffer serves every level.
layout(location = 0) in vec3 in_position;
layout(location = 1) in vec3 in_normal;
layout(location = 2) in vec2 in_uv;
layout(location = 3) in uint in_mesh_id;

layout(push_constant) uniform Push { CityDrawPush push; };
layout(std430, set = 0, binding = BINDING_CITY_MESHES) readonly buffer CityMeshes { CityMeshInfo city_meshes[]; };
layout(std430, set = 0, binding = BINDING_CITY_ORIGINS) readonly buffer CityOrigins { CityOrigin city_origins[]; };
layout(std430, set = 0, binding = BINDING_TREE_ATLAS_UVS) readonly buffer AtlasUvs { vec2 atlas_uvs[]; };
layout(std430, set = 0, binding = BINDING_TREE_UV_TRANSFORMS) readonly buffer UvTransforms { vec4 uv_transforms[]; };

invariant gl_Position;

layout(location = 0) out vec2 out_uv;
layout(location = 1) out vec3 out_normal;
layout(location = 2) flat out uint out_mesh_id;

void main() {
    gl_Position = city_clip_position(push, in_position, city_origins[city_meshes[in_mesh_id].origin]);
    vec4 transform = uv_transforms[in_mesh_id];
    // The draw is indexed with no vertex offset: gl_VertexIndex is the vertex's place in
    // the vertex buffer, where the atlas coordinates are laid out alike.
    out_uv = transform.x == 0.0 ? in_uv : atlas_uvs[gl_VertexIndex] * transform.x - transform.yz;
    out_normal = in_normal;
    out_mesh_id = in_mesh_id;
}
