// citystream for a renderer's own fragment shaders: write streaming
// feedback for a mesh (paper §3.2) and shade with a streamed texture
// blended with the City Colormap by displayed level (Eq. 8).
//
// Define CITYSTREAM_SET before including to choose the descriptor set of
// the streamer's bindings (default 0); their binding numbers are fixed
// (BINDING_CACHE_IMAGES, BINDING_TEXTURE_DATA, BINDING_COLORMAP,
// BINDING_FEEDBACK_MESHES in citystream.glsl). The shader needs
// GL_ARB_sparse_texture2 for sampling, or, on a device set up for the
// texture-array cache, CITYSTREAM_NO_SPARSE defined instead. See docs/EMBEDDING.md.
#ifndef CITYSTREAM_HOST_GLSL
#define CITYSTREAM_HOST_GLSL

#include "citystream.glsl"
#include "city_texture.glsl"
#include "lod.glsl"

layout(std430, set = CITYSTREAM_SET, binding = BINDING_FEEDBACK_MESHES) buffer CitystreamFeedback {
    MeshFeedback citystream_feedback[];
};

// M_max: the coarsest level of a texture of `size` texels at full resolution.
float citystream_max_level(uvec2 size) {
    return float(findMSB(max(max(size.x, size.y), 1u)));
}

// Records this fragment's needs for mesh `mesh_id` (whose texture is
// `texture_id`, `size` texels at full resolution, sampled at `uv`):
// the mip level under anisotropic filtering (A_m) and the weight
// W = 1 + 8 w_d + 8 w_m, combined per mesh with atomics. `lod_offset` is
// log2 of the visible resolution over this pass's, per axis (2 at a quarter
// of the width and height, 0 at the visible resolution); `view_depth` is the distance along
// the view axis (1 / gl_FragCoord.w); fragments within
// `foreground_distance` weigh more; `in_view` is false for fragments in a
// widened feedback view's margin, which count with W = 1. Use with
// early_fragment_tests (and a depth pre-pass) so occluded fragments never
// count.
void citystream_write_feedback(uint mesh_id, uint texture_id, vec2 uv, uvec2 size, float lod_offset,
                               float view_depth, float foreground_distance, bool in_view) {
    vec2 texels = vec2(size);
    float max_level = citystream_max_level(size);
    float lod = anisotropic_lod(dFdx(uv) * texels, dFdy(uv) * texels, FEEDBACK_ANISOTROPY) - lod_offset;
    lod = clamp(lod, 0.0, max_level);
    float weight = 1.0;
    if (in_view) {
        float c_w = min(view_depth / max(foreground_distance, 1e-6), 1.0);
        float w_d = pow(1.0 - c_w, 4.0);
        TextureData t = texture_data[texture_id];
        float displayed = t.state == TEXTURE_SAMPLEABLE ? max(lod, float(t.lowest_mip)) : max_level;
        float w_m = max_level > 0.0 ? min(displayed / max_level, 1.0) : 0.0;
        weight = 1.0 + 8.0 * w_d + 8.0 * w_m;
    }
    atomicMin(citystream_feedback[mesh_id].min_mip, uint(round(lod * FEEDBACK_MIP_ONE)));
    atomicAdd(citystream_feedback[mesh_id].weight, uint(round(weight * FEEDBACK_WEIGHT_ONE)));
}

// The colour of texture `texture_id` (`size` texels at full resolution) at
// `uv`: the streamed texels at the level the view needs (A_s), clamped to
// the finest resident one, blended with the City Colormap colour by the
// displayed level, c = (1 - M/M_max) c_s + (M/M_max) c_o (Eq. 8); the
// colormap colour alone while nothing is resident. `direct` skips the blend
// (unloaded reads as black, as a non-resident sparse texel does).
vec3 citystream_shade(uint texture_id, vec2 uv, uvec2 size, bool direct) {
    vec2 texels = vec2(size);
    float max_level = citystream_max_level(size);
    float lod = clamp(anisotropic_lod(dFdx(uv) * texels, dFdy(uv) * texels, SAMPLE_ANISOTROPY), 0.0, max_level);
    vec4 c_o = colormap_colour(texture_id);
    vec3 colour = direct ? vec3(0.0) : c_o.rgb;
    vec4 c_s;
    float displayed;
    if (sample_city_texture_level(texture_id, uv, lod, c_s, displayed)) {
        float t = max_level > 0.0 && !direct ? clamp(displayed / max_level, 0.0, 1.0) : 0.0;
        colour = mix(c_s.rgb, c_o.rgb, t);
    }
    return colour;
}

#endif
