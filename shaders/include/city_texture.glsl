// Sampling a dataset texture from the sparse cache (paper §3.6-3.7).
// Requires citystream.glsl and GL_ARB_sparse_texture2; declares the cache
// images, the texture data and the colormap at their fixed bindings in set CITYSTREAM_SET.
// Defining CITYSTREAM_NO_SPARSE gives the texture-array cache's variant: plain
// sampling, no GL_ARB_sparse_texture2 (a device without sparse residency has no
// shaderResourceResidency); its table never names a level that is not loaded.
#ifndef CITY_TEXTURE_GLSL
#define CITY_TEXTURE_GLSL

#include "texture_table.glsl"

layout(set = CITYSTREAM_SET, binding = BINDING_CACHE_IMAGES) uniform sampler2DArray cache_images[CACHE_IMAGE_SLOTS];
layout(std430, set = CITYSTREAM_SET, binding = BINDING_COLORMAP) readonly buffer Colormap { uint colormap[]; };

// The image a texture lives in varies between fragments of one draw, and
// indexing a sampler array by a value that is not dynamically uniform needs
// a device feature; a switch with constant indices needs none.
#ifdef CITYSTREAM_NO_SPARSE
// Every texel of a fully bound array layer is resident: the code sparse
// sampling would return for a resident read.
#define CITYSTREAM_CACHE_READ(i) texel = textureLod(cache_images[i], coord, lod); return 0;
#define CITYSTREAM_TEXELS_RESIDENT(code) true
#else
#define CITYSTREAM_CACHE_READ(i) return sparseTextureLodARB(cache_images[i], coord, lod, texel);
#define CITYSTREAM_TEXELS_RESIDENT(code) sparseTexelsResidentARB(code)
#endif
int cache_sparse_lod(uint image, vec3 coord, float lod, out vec4 texel) {
    switch (int(image)) {
        case 1: CITYSTREAM_CACHE_READ(1)
        case 2: CITYSTREAM_CACHE_READ(2)
        case 3: CITYSTREAM_CACHE_READ(3)
        case 4: CITYSTREAM_CACHE_READ(4)
        case 5: CITYSTREAM_CACHE_READ(5)
        case 6: CITYSTREAM_CACHE_READ(6)
        case 7: CITYSTREAM_CACHE_READ(7)
        default: CITYSTREAM_CACHE_READ(0)
    }
}
#undef CITYSTREAM_CACHE_READ

// Every cache image has the same layer size.
vec2 cache_layer_texels() {
    return vec2(textureSize(cache_images[0], 0).xy);
}

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
    vec2 region_texels = t.uv_transform.xy * cache_layer_texels();
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
    int code = cache_sparse_lod(t.image, coord, fine, texel);
    if (!CITYSTREAM_TEXELS_RESIDENT(code)) {
        return false;
    }
    if (blend > 0.0 && coarse > fine) {
        vec4 coarse_texel;
        code = cache_sparse_lod(t.image, coord, coarse, coarse_texel);
        if (!CITYSTREAM_TEXELS_RESIDENT(code)) {
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
