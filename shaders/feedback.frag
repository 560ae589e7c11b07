#version 460
#extension GL_GOOGLE_include_directive : require
#include "citystream.glsl"
#include "texture_table.glsl"
#include "lod.glsl"

// Feedback (paper §3.2): for every fragment of mesh i, the mip level of its
// texture at full original resolution under anisotropic filtering (A_m = 16)
// and the weight W = 1 + 8 w_d + 8 w_m, combined per mesh with atomics.
// Early depth testing: occluded fragments never run, so they never count.
layout(early_fragment_tests) in;

layout(push_constant) uniform Push { CityDrawPush push; };
layout(std430, set = 0, binding = BINDING_CITY_MESHES) readonly buffer CityMeshes { CityMeshInfo city_meshes[]; };
layout(std430, set = 0, binding = BINDING_FEEDBACK_MESHES) buffer Meshes { MeshFeedback meshes[]; };

layout(location = 0) in vec2 in_uv;
layout(location = 1) in vec3 in_normal;
layout(location = 2) flat in uint in_mesh_id;
layout(location = 0) out vec4 out_color;

void main() {
    CityMeshInfo mesh = city_meshes[in_mesh_id];
    vec2 size = vec2(mesh.texture_width, mesh.texture_height);
    float max_level = float(mesh.max_mip);
    // Derivatives are per feedback pixel, which spans 2^feedback.x visible
    // pixels: the visible view needs that many levels finer.
    float lod = anisotropic_lod(dFdx(in_uv) * size, dFdy(in_uv) * size, FEEDBACK_ANISOTROPY) - push.feedback.x;
    lod = clamp(lod, 0.0, max_level);

    vec2 ndc = gl_FragCoord.xy / push.viewport_light.xy * 2.0 - 1.0;
    bool visible = all(lessThanEqual(abs(ndc * push.feedback.zw), vec2(1.0)));
    float weight = 1.0;
    if (visible) {
        // c_w: view depth over the foreground distance (1/gl_FragCoord.w is clip w, the view depth).
        float c_w = min((1.0 / gl_FragCoord.w) / push.feedback.y, 1.0);
        float w_d = pow(1.0 - c_w, 4.0);
        TextureData t = texture_data[mesh.texture_id];
        float displayed = t.state == TEXTURE_SAMPLEABLE ? max(lod, float(t.lowest_mip)) : max_level;
        float w_m = max_level > 0.0 ? min(displayed / max_level, 1.0) : 0.0;
        weight = 1.0 + 8.0 * w_d + 8.0 * w_m;
    }
    atomicMin(meshes[in_mesh_id].min_mip, uint(round(lod * FEEDBACK_MIP_ONE)));
    atomicAdd(meshes[in_mesh_id].weight, uint(round(weight * FEEDBACK_WEIGHT_ONE)));
    // A view of the requested levels, for debugging: brighter is finer.
    out_color = vec4(vec3(1.0 - lod / 12.0), 1.0);
}
