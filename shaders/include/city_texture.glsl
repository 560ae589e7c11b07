// Sampling a dataset texture from the sparse cache (paper §3.6-3.7).
// Requires citystream.glsl and GL_ARB_sparse_texture2; declares the cache
// images, the texture data and the colormap at their fixed bindings in set 0.
#ifndef CITY_TEXTURE_GLSL
#define CITY_TEXTURE_GLSL

layout(set = 0, binding = BINDING_CACHE_IMAGE0) uniform sampler2DArray cache_image0;
layout(set = 0, binding = BINDING_CACHE_IMAGE1) uniform sampler2DArray cache_image1;
layout(std430, set = 0, binding = BINDING_TEXTURE_DATA) readonly buffer TextureTable { TextureData texture_data[]; };
layout(std430, set = 0, binding = BINDING_COLORMAP) readonly buffer Colormap { uint colormap[]; };

vec4 colormap_colour(uint texture_id) {
    return unpackUnorm4x8(colormap[texture_id]);
}

// Samples `texture_id` at `uv` (repeating) and level `lod`, clamped to the
// finest resident level, since lavapipe has no sparseTextureClampARB
// (shaderResourceMinLod). Returns false, leaving `colour` untouched, when the
// texture is not sampleable or the texels read are not resident; the caller
// then shows the City Colormap colour.
bool sample_city_texture(uint texture_id, vec2 uv, float lod, out vec4 colour) {
    TextureData t = texture_data[texture_id];
    colour = vec4(0.0);
    if (t.state != TEXTURE_SAMPLEABLE || t.mip_count == 0u) {
        return false;
    }
    float level = clamp(max(lod, float(t.lowest_mip)), 0.0, float(t.mip_count - 1u));
    // Wrap inside the texture's own region: repeated UVs never reach a neighbour.
    vec2 layer_uv = fract(uv) * t.uv_transform.xy + t.uv_transform.zw;
    vec3 coord = vec3(layer_uv, float(t.layer));
    vec4 texel;
    int code;
    if (t.image == 0u) {
        code = sparseTextureLodARB(cache_image0, coord, level, texel);
    } else {
        code = sparseTextureLodARB(cache_image1, coord, level, texel);
    }
    if (!sparseTexelsResidentARB(code)) {
        return false;
    }
    colour = texel;
    return true;
}

#endif
