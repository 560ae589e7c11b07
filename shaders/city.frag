#version 460
#extension GL_GOOGLE_include_directive : require
#ifndef CITYSTREAM_NO_SPARSE
#extension GL_ARB_sparse_texture2 : require
#endif
#include "citystream_host.glsl"

// Visible pass of the city: streamed texture blended with the City
// Colormap by displayed level (Eq. 8), through the same include a host
// renderer uses, then simple lighting.
layout(push_constant) uniform Push { CityDrawPush push; };
layout(std430, set = 0, binding = BINDING_CITY_MESHES) readonly buffer CityMeshes { CityMeshInfo city_meshes[]; };

layout(location = 0) in vec2 in_uv;
layout(location = 1) in vec3 in_normal;
layout(location = 2) flat in uint in_mesh_id;
layout(location = 0) out vec4 out_color;

const vec3 LIGHT_DIR = vec3(0.36, 0.80, 0.48);

void main() {
    CityMeshInfo mesh = city_meshes[in_mesh_id];
    // viewport_light.w = 1: direct sampling, no City Colormap at all (the
    // pop-in comparison of Fig. 7).
    bool direct = push.viewport_light.w != 0.0;
    vec3 colour = citystream_shade(mesh.texture_id, in_uv, uvec2(mesh.texture_width, mesh.texture_height), direct);
    float lambert = 0.35 + 0.65 * max(dot(normalize(in_normal), normalize(LIGHT_DIR)), 0.0);
    out_color = vec4(colour * mix(1.0, lambert, push.viewport_light.z), 1.0);
}
