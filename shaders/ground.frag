#version 460
#extension GL_GOOGLE_include_directive : require
#include "citystream.glsl"

// The ground pass (flexible clipmap): the level a pixel's footprint needs, or the finest
// coarser one the tile map says is resident there; blended toward the next coarser level
// by the footprint's fraction and near the edge of a resident region, so neither a level
// change nor a window edge shows as a seam.
layout(push_constant) uniform Push { GroundPush push; };
layout(set = 0, binding = BINDING_GROUND_TILES) uniform sampler2DArray tiles;
layout(std430, set = 0, binding = BINDING_GROUND_TILE_MAP) readonly buffer TileMap {
    GroundTileEntry entries[];
};

layout(location = 0) in vec2 in_ground;
layout(location = 0) out vec4 out_colour;

// Width of the band at a resident region's edge blended toward the coarser level, in tiles.
const float EDGE_BAND = 0.125;

// a mod n, n > 0, for negative a too (GLSL leaves % of negatives undefined).
int floor_mod(int a, int n) {
    int r = abs(a) % n;
    return (a < 0 && r != 0) ? n - r : r;
}

float tile_metres(int scale) {
    return push.params.y * exp2(float(scale));
}

ivec2 tile_of(vec2 p, int scale) {
    return ivec2(floor(p / tile_metres(scale)));
}

// The layer holding tile t of `scale` when it is resident there, else -1.
int resident_layer(ivec2 t, int scale) {
    int side = push.levels.z;
    int level_slot = floor_mod(scale, push.levels.w);
    int layer = (level_slot * side + floor_mod(t.y, side)) * side + floor_mod(t.x, side);
    GroundTileEntry e = entries[layer];
    bool held = e.resident != 0u && e.scale == scale && e.x == t.x && e.z == t.y;
    return held ? layer : -1;
}

vec4 sample_tile(vec2 p, int scale, int layer) {
    vec2 uv = p / tile_metres(scale) - vec2(tile_of(p, scale));
    // Clamp to the tile's texel centres: its neighbours live in other layers.
    float half_texel = 0.5 / push.params.w;
    uv = clamp(uv, vec2(half_texel), vec2(1.0 - half_texel));
    return textureLod(tiles, vec3(uv, float(layer)), 0.0);
}

// How far toward the coarser level p blends because a neighbour tile of `scale` on the
// near side is not resident: 1 at the shared edge, 0 a band's width inside.
float edge_weight(vec2 p, int scale) {
    ivec2 t = tile_of(p, scale);
    vec2 f = p / tile_metres(scale) - vec2(t);
    ivec2 toward = ivec2(f.x < 0.5 ? -1 : 1, f.y < 0.5 ? -1 : 1);
    vec2 distance = min(f, 1.0 - f);
    float weight = 0.0;
    if (resident_layer(t + ivec2(toward.x, 0), scale) < 0) {
        weight = max(weight, 1.0 - smoothstep(0.0, EDGE_BAND, distance.x));
    }
    if (resident_layer(t + ivec2(0, toward.y), scale) < 0) {
        weight = max(weight, 1.0 - smoothstep(0.0, EDGE_BAND, distance.y));
    }
    return weight;
}

void main() {
    vec2 p = in_ground;
    int finest = push.levels.x;
    int count = push.levels.y;
    // A pixel's footprint on the ground, in texels of the finest level, as a level.
    float footprint = max(length(dFdx(p)), length(dFdy(p)));
    float finest_texel = tile_metres(finest) / push.params.w;
    float lod = log2(max(footprint / finest_texel, 1e-6));
    // NaN (degenerate derivatives) reads as the finest level: clamp leaves NaN undefined.
    lod = lod >= 0.0 ? min(lod, float(count - 1)) : 0.0;
    int wanted = clamp(int(floor(lod)), 0, count - 1);
    int level = -1;
    int layer = -1;
    for (int i = wanted; i < count; ++i) {
        layer = resident_layer(tile_of(p, finest + i), finest + i);
        if (layer >= 0) {
            level = i;
            break;
        }
    }
    if (level < 0) {
        out_colour = vec4(push.fallback.rgb, 1.0);
        return;
    }
    vec4 colour = sample_tile(p, finest + level, layer);
    float coarser = level == wanted ? fract(lod) : 0.0;
    coarser = max(coarser, edge_weight(p, finest + level));
    if (coarser > 0.0 && level + 1 < count) {
        int scale = finest + level + 1;
        int above = resident_layer(tile_of(p, scale), scale);
        if (above >= 0) {
            colour = mix(colour, sample_tile(p, scale, above), coarser);
        }
    }
    out_colour = vec4(mix(push.fallback.rgb, colour.rgb, colour.a), 1.0);
}
