#version 460
#extension GL_GOOGLE_include_directive : require
#ifndef CITYSTREAM_NO_SPARSE
#extension GL_ARB_sparse_texture2 : require
#endif
#include "citystream.glsl"
#include "city_texture.glsl"

// Samples dataset textures through the cache exactly as the renderer does
// (texture data, UV transform, LOD clamp, residency, colormap fallback) at
// explicit points, so tests can compare with the source texels.
layout(local_size_x = 64) in;

layout(std430, set = 0, binding = BINDING_TEXTURE_PROBE_POINTS) readonly buffer Points { TextureProbePoint points[]; };
layout(std430, set = 0, binding = BINDING_TEXTURE_PROBE_RESULTS) writeonly buffer Results { ProbeResult results[]; };

void main() {
    uint i = gl_GlobalInvocationID.x;
    if (i >= points.length()) {
        return;
    }
    TextureProbePoint p = points[i];
    vec4 colour;
    bool cached = sample_city_texture(p.texture, p.uv, p.lod, colour);
    results[i].value = cached ? colour : colormap_colour(p.texture);
    results[i].resident = cached ? 1u : 0u;
    results[i].raw_code = 0;
}
