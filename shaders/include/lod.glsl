// Level-of-detail helpers shared by the feedback and visible passes.
#ifndef LOD_GLSL
#define LOD_GLSL

// LOD of a footprint with texel-space derivatives dx, dy under anisotropic
// filtering of at most `max_anisotropy` samples (EXT_texture_filter_anisotropic):
// the major axis is shortened by the number of samples, at most log2(max_anisotropy) levels.
float anisotropic_lod(vec2 dx, vec2 dy, float max_anisotropy) {
    float px = length(dx);
    float py = length(dy);
    float p_max = max(px, py);
    float p_min = min(px, py);
    if (p_max <= 0.0) {
        return 0.0;
    }
    // The small allowance keeps rounding noise in an isotropic footprint
    // (ratio 1.0000001) from doubling the sample count and dropping a level.
    float n = clamp(ceil(p_max / max(p_min, 1e-20) - 1.0 / 1024.0), 1.0, max_anisotropy);
    return log2(p_max / n);
}

#endif
