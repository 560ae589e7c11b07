// Sampling a dataset texture from the sparse cache (paper §3.6-3.7).
// Requires citystream.glsl and GL_ARB_sparse_texture2; declares the cache
// images, the texture data and the colormap at their fixed bindings in set CITYSTREAM_SET.
#ifndef CITY_TEXTURE_GLSL
#define CITY_TEXTURE_GLSL

#include "texture_table.glsl"

layout(set = CITYSTREAM_SET, binding = BINDING_CACHE_IMAGE0) uniform sampler2DArray cache_image0;
layout(set = CITYSTREAM_SET, binding = BINDING_CACHE_IMAGE1) uniform sampler2DArray cache_image1;
layout(std430, set = CITYSTREAM_SET, binding = BINDING_COLORMAP) readonly buffer Colormap { uint colormap[]; };

vec4 colormap_colour(uint texture_id) {
    return unpackUnorm4x8(colormap[texture_id]);
}

// Samples `texture_id` at `uv` (repeating) and level `lod`, clamped to the
// finest resident level, since lavapipe has no sparseTextureClampARB
// (shaderResourceMinLod). Returns false, leaving `colour` zero, when the
// texture is not sampleable or the texels read are not resident; the caller
// then shows the City Colormap colour. `level` is the level sampled.
bool sample_city_texture_level(uint texture_id, vec2 uv, float lod, out vec4 colour, out float level) {
    TextureData t = texture_data[texture_id];
    colour = vec4(0.0);
    level = 0.0;
    if (t.state != TEXTURE_SAMPLEABLE || t.mip_count == 0u) {
        return false;
    }
    level = clamp(max(lod, float(t.lowest_mip)), 0.0, float(t.mip_count - 1u));
    // Wrap inside the texture's own region: repeated UVs never reach a
    // neighbour. Clamping half a texel of the coarser level sampled inside the
    // region keeps linear filtering from bleeding across its edge.
    vec2 region_texels = t.uv_transform.xy * vec2(textureSize(cache_image0, 0).xy);
    if (t.image != 0u) {
        region_texels = t.uv_transform.xy * vec2(textureSize(cache_image1, 0).xy);
    }
    vec2 half_texel = 0.5 * exp2(ceil(level)) / max(region_texels, vec2(1.0));
    vec2 inside = clamp(fract(uv), min(half_texel, vec2(0.5)), max(1.0 - half_texel, vec2(0.5)));
    vec2 layer_uv = inside * t.uv_transform.xy + t.uv_transform.zw;
    // The two levels are sampled separately at whole LODs and blended here
    // (the cache sampler uses NEAREST mip selection): lavapipe (Mesa 25.0.7)
    // reports sparse reads with LINEAR mip filtering at an integral LOD as
    // non-resident even when both levels are bound and filled.
    vec3 coord = vec3(layer_uv, float(t.layer));
    float fine = floor(level);
    float coarse = min(fine + 1.0, float(t.mip_count - 1u));
    float blend = level - fine;
    vec4 texel;
    int code;
    if (t.image == 0u) {
        code = sparseTextureLodARB(cache_image0, coord, fine, texel);
    } else {
        code = sparseTextureLodARB(cache_image1, coord, fine, texel);
    }
    if (!sparseTexelsResidentARB(code)) {
        return false;
    }
    if (blend > 0.0 && coarse > fine) {
        vec4 coarse_texel;
        if (t.image == 0u) {
            code = sparseTextureLodARB(cache_image0, coord, coarse, coarse_texel);
        } else {
            code = sparseTextureLodARB(cache_image1, coord, coarse, coarse_texel);
        }
        if (!sparseTexelsResidentARB(code)) {
            return false;
        }
        texel = mix(texel, coarse_texel, blend);
    }
    colour = texel;
    return true;
}

bool sample_city_texture(uint texture_id, vec2 uv, float lod, out vec4 colour) {
    float level;
    return sample_city_texture_level(texture_id, uv, lod, colour, level);
}

#endif
