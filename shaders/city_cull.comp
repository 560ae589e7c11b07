#version 460
#extension GL_GOOGLE_include_directive : require
#include "citystream.glsl"

// GPU culling of the city's meshes (engine/src/cull.rs), in phases chosen by
// push.phase, one dispatch each:
//   FRUSTUM    per chunk of CULL_CHUNK meshes (its box, then each mesh's): CULL_IN_FRUSTUM,
//              and CULL_PREVIOUS from last frame's CULL_NEXT;
//   OCCLUSION  per chunk (its box, then each mesh's in the frustum): CULL_UNOCCLUDED and
//              CULL_NEXT against the depth pyramid;
//   COUNT      per chunk of CULL_CHUNK meshes: the indices of its listed meshes;
//   SCAN       one workgroup: each chunk's first index (exclusive prefix sum), and the draws;
//   EMIT       per chunk: its listed meshes' indices copied into the list's index buffer;
//   PYRAMID    per texel of one level of the depth pyramid, from the level below.
// A list is the meshes whose flags match (mask, want). Their indices are copied in mesh
// order into the list's own index buffer and drawn with one indexed draw, so the culled
// passes rasterise in the order of the single unculled draw. A list whose indices do not
// fit its buffer draws every mesh instead (the second draw, otherwise empty).
layout(local_size_x = 256) in;

// The mesh bounds and the city's indices may be larger than one binding addresses
// (maxStorageBufferRange): each is an array of windows, element k its k-th window.
layout(std430, set = 0, binding = BINDING_CULL_BOUNDS) readonly buffer Bounds { MeshBounds b[]; } bounds_windows[CULL_WINDOWS];
layout(std430, set = 0, binding = BINDING_CULL_CHUNK_BOUNDS) readonly buffer ChunkBounds { MeshBounds chunk_bounds[]; };
layout(std430, set = 0, binding = BINDING_CULL_RANGES) readonly buffer Ranges { uvec2 ranges[]; };
layout(std430, set = 0, binding = BINDING_CULL_FLAGS) buffer Flags { uint flags[]; };
layout(std430, set = 0, binding = BINDING_CULL_CHUNK_FLAGS) buffer ChunkFlags { uint chunk_in_frustum[]; };
layout(std430, set = 0, binding = BINDING_CULL_GROUPS) buffer Groups { uint group_indices[]; };
layout(std430, set = 0, binding = BINDING_CULL_DRAWS) buffer Draws { uint draws[]; };
layout(std430, set = 0, binding = BINDING_CULL_CITY_INDICES) readonly buffer CityIndices { uint i[]; } index_windows[CULL_WINDOWS];
layout(std430, set = 0, binding = BINDING_CULL_INDICES) writeonly buffer ListIndices { uint list_indices[]; };
layout(std430, set = 0, binding = BINDING_CULL_COUNTER) buffer Counter { CullCounter counter; };
layout(std430, set = 0, binding = BINDING_CULL_PYRAMID) buffer Pyramid { float pyramid[]; };
layout(push_constant) uniform Push { CullPush push; };

// Relative slack of the plane and depth tests: the vertex stage computes the same
// products in another order, so a vertex on a boundary may land a rounding step outside.
const float SLACK = 1.0 / 4096.0;
// Absolute slack of the depth test (depth is reversed: near / distance). Near the eye
// depth falls as steeply as a standard projection's rises, so this is the slack culling
// always had in metres there; it also covers the ground pass's relative depth bias (at
// most 2e-6 of a depth of at most 1).
const float DEPTH_SLACK = 1.0 / 262144.0;
// Slack of the pixel footprint: rasterisers snap vertices to 1/256 pixel or finer.
const float PIXEL_SLACK = 1.0 / 16.0;

shared uint partial[256];

// Element `i` of a windowed array whose windows hold 2^shift elements each. The window is
// picked by a switch: indexing the array directly with a value that differs between
// invocations would need the non-uniform indexing feature.
#define WINDOWED(windows, member, i, shift, T)                                                   \
    T value;                                                                                      \
    uint at = (i) & ((1u << (shift)) - 1u);                                                       \
    switch ((i) >> (shift)) {                                                                     \
        case 0u: value = windows[0].member[at]; break;                                           \
        case 1u: value = windows[1].member[at]; break;                                           \
        case 2u: value = windows[2].member[at]; break;                                           \
        case 3u: value = windows[3].member[at]; break;                                           \
        case 4u: value = windows[4].member[at]; break;                                           \
        case 5u: value = windows[5].member[at]; break;                                           \
        case 6u: value = windows[6].member[at]; break;                                           \
        default: value = windows[7].member[at]; break;                                           \
    }                                                                                             \
    return value;

MeshBounds mesh_bounds(uint m) {
    WINDOWED(bounds_windows, b, m, push.window_shifts & 0xffu, MeshBounds)
}

uint city_index(uint k) {
    WINDOWED(index_windows, i, k, (push.window_shifts >> 8) & 0xffu, uint)
}

uint group_index() {
    return gl_WorkGroupID.x + gl_WorkGroupID.y * gl_NumWorkGroups.x;
}

uvec2 level_size(uint level) {
    uvec2 size = push.pyramid.xy;
    for (uint l = 0u; l < level; ++l) {
        size = (size + 1u) >> 1u;
    }
    return size;
}

uint level_offset(uint level) {
    uvec2 size = push.pyramid.xy;
    uint offset = 0u;
    for (uint l = 0u; l < level; ++l) {
        offset += size.x * size.y;
        size = (size + 1u) >> 1u;
    }
    return offset;
}

float pyramid_texel(uint offset, uvec2 size, uvec2 texel) {
    return pyramid[offset + min(texel.y, size.y - 1u) * size.x + min(texel.x, size.x - 1u)];
}

vec4 corner(MeshBounds b, uint k) {
    vec3 p = vec3((k & 1u) != 0u ? b.high.x : b.low.x,
                  (k & 2u) != 0u ? b.high.y : b.low.y,
                  (k & 4u) != 0u ? b.high.z : b.low.z);
    return push.view_proj * vec4(p, 1.0);
}

// Whether the box can contribute a fragment: false only when every corner lies outside
// one of the clip volume's planes (Vulkan: -w <= x, y <= w, 0 <= z <= w; with reversed
// depth and no far plane z = w is the near plane and z >= 0 holds in front of the eye).
bool in_frustum(MeshBounds b) {
    if (b.low.w != 0.0) {
        return true;
    }
    bool left = true, right = true, bottom = true, top = true, near = true, far = true;
    for (uint k = 0u; k < 8u; ++k) {
        vec4 c = corner(b, k);
        float slack = SLACK * (abs(c.x) + abs(c.y) + abs(c.z) + abs(c.w));
        left = left && c.x < -c.w - slack;
        right = right && c.x > c.w + slack;
        bottom = bottom && c.y < -c.w - slack;
        top = top && c.y > c.w + slack;
        near = near && c.z > c.w + slack;
        far = far && c.z < -slack;
    }
    return !(left || right || bottom || top || near || far);
}

// Whether the box may be in front of the depth the pyramid holds: false only when its
// nearest point lies behind the farthest depth of every pixel its projection may cover
// (reversed depth: nearest is greatest).
bool unoccluded(MeshBounds b) {
    if (b.low.w != 0.0) {
        return true;
    }
    vec2 low = vec2(1e30);
    vec2 high = vec2(-1e30);
    float nearest = 0.0;
    for (uint k = 0u; k < 8u; ++k) {
        vec4 c = corner(b, k);
        // A corner at or behind the eye: the projection is unbounded, no test.
        if (c.w <= 1e-6 * (abs(c.x) + abs(c.y) + abs(c.z)) || c.w <= 0.0) {
            return true;
        }
        vec3 ndc = c.xyz / c.w;
        low = min(low, ndc.xy);
        high = max(high, ndc.xy);
        nearest = max(nearest, ndc.z);
    }
    vec2 size = vec2(push.pyramid.xy);
    // Pixels whose centres the projection may cover (a sixteenth of a pixel wider each
    // way for rounding); none: the box cannot produce a fragment.
    vec2 lowest = max(ceil((low * 0.5 + 0.5) * size - 0.5 - PIXEL_SLACK), vec2(0.0));
    vec2 highest = min(floor((high * 0.5 + 0.5) * size - 0.5 + PIXEL_SLACK), size - 1.0);
    if (any(greaterThan(lowest, highest))) {
        return false;
    }
    uvec2 first = uvec2(lowest);
    uvec2 last = uvec2(highest);
    // The finest level at which the rectangle spans at most 5 x 5 texels: coarser levels
    // mix in the far depth (sky) beside a mesh and cull less.
    uint level = 0u;
    while (level + 1u < push.pyramid.z && (((last.x >> level) - (first.x >> level)) > 4u || ((last.y >> level) - (first.y >> level)) > 4u)) {
        ++level;
    }
    uint offset = level_offset(level);
    uvec2 texels = level_size(level);
    float farthest = 1.0;
    for (uint y = first.y >> level; y <= (last.y >> level); ++y) {
        for (uint x = first.x >> level; x <= (last.x >> level); ++x) {
            farthest = min(farthest, pyramid_texel(offset, texels, uvec2(x, y)));
        }
    }
    return nearest + DEPTH_SLACK >= farthest;
}

// Every list requires CULL_IN_FRUSTUM, so a chunk outside the frustum lists nothing and
// its meshes' flags (left as they were) are not read.
bool listed(uint i) {
    return i < push.mesh_count && chunk_in_frustum[i / CULL_CHUNK] != 0u && (flags[i] & push.mask) == push.want;
}

// Inclusive prefix sum of partial[] over the workgroup (Hillis-Steele).
void scan_partial(uint local) {
    for (uint offset = 1u; offset < 256u; offset <<= 1u) {
        barrier();
        uint add = local >= offset ? partial[local - offset] : 0u;
        barrier();
        partial[local] += add;
    }
    barrier();
}

void main() {
    uint local = gl_LocalInvocationID.x;
    uint group = group_index();
    uint i = group * 256u + local;
    if (push.phase == CULL_PHASE_FRUSTUM) {
        // One invocation per chunk: the chunk's box first, so chunks outside the view
        // cost one test instead of CULL_CHUNK.
        uint chunk = i;
        uint begin = chunk * CULL_CHUNK;
        if (chunk >= push.group_count || begin >= push.mesh_count) {
            return;
        }
        uint end = min(begin + CULL_CHUNK, push.mesh_count);
        bool chunk_in = in_frustum(chunk_bounds[chunk]);
        chunk_in_frustum[chunk] = chunk_in ? 1u : 0u;
        if (!chunk_in) {
            // Its meshes keep last frame's CULL_NEXT until the chunk returns to view: a
            // stale early set costs draws, never correctness.
            return;
        }
        for (uint m = begin; m < end; ++m) {
            uint previous = (flags[m] & CULL_NEXT) != 0u ? CULL_PREVIOUS : 0u;
            bool drawable = ranges[m].y != 0u && in_frustum(mesh_bounds(m));
            flags[m] = previous | (drawable ? CULL_IN_FRUSTUM : 0u);
        }
    } else if (push.phase == CULL_PHASE_OCCLUSION) {
        uint chunk = i;
        uint begin = chunk * CULL_CHUNK;
        if (chunk >= push.group_count || begin >= push.mesh_count) {
            return;
        }
        if (chunk_in_frustum[chunk] == 0u) {
            return;
        }
        uint end = min(begin + CULL_CHUNK, push.mesh_count);
        bool any_in_frustum = false;
        for (uint m = begin; m < end; ++m) {
            any_in_frustum = any_in_frustum || (flags[m] & CULL_IN_FRUSTUM) != 0u;
        }
        // A chunk whose box is hidden hides every mesh box inside it.
        bool chunk_visible = any_in_frustum && unoccluded(chunk_bounds[chunk]);
        for (uint m = begin; m < end; ++m) {
            uint f = flags[m] & (CULL_PREVIOUS | CULL_IN_FRUSTUM);
            if (chunk_visible && (f & CULL_IN_FRUSTUM) != 0u && unoccluded(mesh_bounds(m))) {
                f |= CULL_UNOCCLUDED | CULL_NEXT;
            }
            flags[m] = f;
        }
    } else if (push.phase == CULL_PHASE_COUNT) {
        // One invocation per chunk of CULL_CHUNK meshes, in order: no workgroup barriers,
        // which a CPU rasteriser pays for dearly.
        uint chunk = i;
        uint begin = chunk * CULL_CHUNK;
        if (chunk >= push.group_count || begin >= push.mesh_count) {
            return;
        }
        if (chunk_in_frustum[chunk] == 0u) {
            group_indices[chunk] = 0u;
            return;
        }
        uint end = min(begin + CULL_CHUNK, push.mesh_count);
        uint indices = 0u;
        uint meshes = 0u;
        for (uint m = begin; m < end; ++m) {
            if (listed(m)) {
                indices += ranges[m].y;
                meshes += 1u;
            }
        }
        group_indices[chunk] = indices;
        if (meshes > 0u) {
            atomicAdd(counter.meshes, meshes);
        }
    } else if (push.phase == CULL_PHASE_SCAN) {
        // One workgroup: thread t sums a contiguous range of chunks, the ranges' sums are
        // scanned, and each thread rewrites its range as the chunks' first index.
        uint per_thread = (push.group_count + 255u) / 256u;
        uint begin = min(local * per_thread, push.group_count);
        uint end = min(begin + per_thread, push.group_count);
        uint sum = 0u;
        for (uint g = begin; g < end; ++g) {
            sum += group_indices[g];
        }
        partial[local] = sum;
        scan_partial(local);
        uint first = partial[local] - sum;
        for (uint g = begin; g < end; ++g) {
            uint indices = group_indices[g];
            group_indices[g] = first;
            first += indices;
        }
        if (local == 255u) {
            uint total = partial[255];
            bool overflowed = total > push.capacity;
            counter.indices = total;
            counter.overflowed = overflowed ? 1u : 0u;
            // Draw 0: the compacted list; draw 1: every mesh, when the list did not fit.
            draws[0] = overflowed ? 0u : total;          // indexCount
            draws[1] = overflowed ? 0u : 1u;             // instanceCount
            draws[2] = 0u;                               // firstIndex
            draws[3] = 0u;                               // vertexOffset
            draws[4] = 0u;                               // firstInstance
            draws[5] = push.city_indices;
            draws[6] = overflowed ? 1u : 0u;
            draws[7] = 0u;
            draws[8] = 0u;
            draws[9] = 0u;
        }
    } else if (push.phase == CULL_PHASE_PYRAMID) {
        uint level = push.want;
        uvec2 size = level_size(level);
        if (i < size.x * size.y) {
            uvec2 texel = uvec2(i % size.x, i / size.x);
            uvec2 below = level_size(level - 1u);
            uint from = level_offset(level - 1u);
            uvec2 base = texel * 2u;
            // The texels below, clamped to their level: the odd edge reads its own texel twice.
            // Reversed depth: the farthest is the least.
            float farthest = min(min(pyramid_texel(from, below, base),
                                     pyramid_texel(from, below, base + uvec2(1u, 0u))),
                                 min(pyramid_texel(from, below, base + uvec2(0u, 1u)),
                                     pyramid_texel(from, below, base + uvec2(1u, 1u))));
            pyramid[from + below.x * below.y + i] = farthest;
        }
    } else {
        // Each listed mesh's indices, copied in mesh order to the chunk's first index.
        uint chunk = i;
        uint begin = chunk * CULL_CHUNK;
        if (chunk >= push.group_count || begin >= push.mesh_count || chunk_in_frustum[chunk] == 0u
            || counter.overflowed != 0u) {
            return;
        }
        uint end = min(begin + CULL_CHUNK, push.mesh_count);
        uint to = group_indices[chunk];
        for (uint m = begin; m < end; ++m) {
            if (listed(m)) {
                uvec2 range = ranges[m];
                for (uint k = 0u; k < range.y; ++k) {
                    list_indices[to + k] = city_index(range.x + k);
                }
                to += range.y;
            }
        }
    }
}
