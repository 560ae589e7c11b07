#version 460
#extension GL_GOOGLE_include_directive : require
#extension GL_ARB_sparse_texture2 : require
#include "citystream_host.glsl"

// Feedback (paper §3.2) of the city passes, through the same include a host
// renderer uses. Early depth testing: occluded fragments never run, so they
// never count.
layout(early_fragment_tests) in;

layout(push_constant) uniform Push { CityDrawPush push; };
layout(std430, set = 0, binding = BINDING_CITY_MESHES) readonly buffer CityMeshes { CityMeshInfo city_meshes[]; };

layout(location = 0) in vec2 in_uv;
layout(location = 1) in vec3 in_normal;
layout(location = 2) flat in uint in_mesh_id;
layout(location = 0) out vec4 out_color;

void main() {
    CityMeshInfo mesh = city_meshes[in_mesh_id];
    vec2 ndc = gl_FragCoord.xy / push.viewport_light.xy * 2.0 - 1.0;
    bool in_view = all(lessThanEqual(abs(ndc * push.feedback.zw), vec2(1.0)));
    // Derivatives are per feedback pixel, which spans 2^feedback.x visible
    // pixels: the visible view needs that many levels finer.
    citystream_write_feedback(in_mesh_id, mesh.texture_id, in_uv, uvec2(mesh.texture_width, mesh.texture_height),
                              push.feedback.x, 1.0 / gl_FragCoord.w, push.feedback.y, in_view);
    out_color = vec4(1.0);
}
