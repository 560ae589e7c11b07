#version 460
#extension GL_GOOGLE_include_directive : require
#include "citystream.glsl"

// Vertex stage of every city pass (depth pre-pass, feedback and visible).
layout(location = 0) in vec3 in_position;
layout(location = 1) in vec3 in_normal;
layout(location = 2) in vec2 in_uv;
layout(location = 3) in uint in_mesh_id;

layout(push_constant) uniform Push { CityDrawPush push; };
layout(std430, set = 0, binding = BINDING_CITY_MESHES) readonly buffer CityMeshes { CityMeshInfo city_meshes[]; };
layout(std430, set = 0, binding = BINDING_CITY_ORIGINS) readonly buffer CityOrigins { CityOrigin city_origins[]; };

// Identical depth in the pre-pass and the passes that test against it.
invariant gl_Position;

layout(location = 0) out vec2 out_uv;
layout(location = 1) out vec3 out_normal;
layout(location = 2) flat out uint out_mesh_id;

void main() {
    gl_Position = city_clip_position(push, in_position, city_origins[city_meshes[in_mesh_id].origin]);
    out_uv = in_uv;
    out_normal = in_normal;
    out_mesh_id = in_mesh_id;
}
