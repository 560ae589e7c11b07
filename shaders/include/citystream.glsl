// Every GPU-visible struct and binding number of citystream, in one place.
// The Rust side mirrors these structs in engine/src/gpu_types.rs; a test
// reads the offsets glslang emits into SPIR-V and compares them.
#ifndef CITYSTREAM_GLSL
#define CITYSTREAM_GLSL

// The descriptor set of the streamed-texture bindings (cache images,
// texture table, colormap, mesh feedback). A host defines it before the
// first include to place them in a set of its choosing.
#ifndef CITYSTREAM_SET
#define CITYSTREAM_SET 0
#endif

// ---- Descriptor set 0: mesh rendering -------------------------------------
#define BINDING_MESH_TEXTURES 0      // sampler2DArray: ordinary texture array

// ---- Descriptor set 0: sparse residency probe ----------------------------
#define BINDING_PROBE_TEXTURE 0      // sampler2DArray: sparse image
#define BINDING_PROBE_POINTS 1       // ProbePoint[]
#define BINDING_PROBE_RESULTS 2      // ProbeResult[]

// ---- Descriptor set 0: feedback compaction (paper §3.3) -----------------
#define BINDING_COMPACT_SPARSE 0     // MeshFeedback[], one per mesh, reset after reading
#define BINDING_COMPACT_DENSE 1      // FeedbackEntry[], appended
#define BINDING_COMPACT_COUNTER 2    // FeedbackCounter

// ---- City texturing: shared by every pass that samples cached textures -----
#define BINDING_CACHE_IMAGES 10      // sampler2DArray[CACHE_IMAGE_SLOTS]: the sparse cache images, indexed by TextureData.image
#define CACHE_IMAGE_SLOTS 8          // elements of BINDING_CACHE_IMAGES (unused ones repeat image 0)
#define BINDING_TEXTURE_DATA 12      // TextureData[], one per dataset texture
#define BINDING_COLORMAP 13          // uint[], the City Colormap, RGBA8 packed, one per texture

// ---- Feedback pass (paper §3.2): set 0 also holds BINDING_TEXTURE_DATA --------
#define BINDING_FEEDBACK_MESHES 16    // MeshFeedback[], written with atomics
#define BINDING_CITY_MESHES 17        // CityMeshInfo[], one per mesh (every city pass)
#define BINDING_CITY_ORIGINS 33       // CityOrigin[], the local origins CityMeshInfo::origin indexes

// ---- Visible pass of a texture-atlas tree (docs/ATLAS_TREE.md) -------------
#define BINDING_TREE_ATLAS_UVS 18     // vec2[], per drawn vertex: its coordinates in the root atlas
#define BINDING_TREE_UV_TRANSFORMS 19 // vec4[], per mesh: x = atlas scale (0: own texture coordinates), yz = offset

// ---- Ground layer: the flexible clipmap's tiles (engine/src/ground.rs) -----
#define BINDING_GROUND_TILES 20       // sampler2DArray: clip-level tiles; layer = level slot * side² + tile slot
#define BINDING_GROUND_TILE_MAP 21    // GroundTileEntry[], one per layer: the tile it holds, if resident

// ---- GPU culling (engine/src/cull.rs): set 0 of the culling pass -----------
#define BINDING_CULL_BOUNDS 22        // MeshBounds[], one per mesh, world space
#define BINDING_CULL_RANGES 23        // uvec2[], one per mesh: first index and index count in the city's index buffer
#define BINDING_CULL_FLAGS 24         // uint[], one per mesh and view: CULL_* bits
#define BINDING_CULL_GROUPS 25        // uint[], one per chunk of CULL_CHUNK meshes: its listed indices, then its first index
#define BINDING_CULL_DRAWS 26         // DrawIndexedIndirectCommand[2] (5 uints each): the list's, and every mesh's on overflow
#define BINDING_CULL_COUNTER 27       // CullCounter: what the list holds
#define BINDING_CULL_PYRAMID 28       // float[]: the view's depth pyramid, levels packed from level 0 (the depth
                                      // target itself, row by row); each level halves, rounding up, and holds the
                                      // farthest depth of the texels below it
#define BINDING_CULL_CHUNK_BOUNDS 29  // MeshBounds[], one per chunk of CULL_CHUNK meshes: the union of their boxes
#define BINDING_CULL_CHUNK_FLAGS 30   // uint[], one per chunk and view: whether its box meets the frustum
#define BINDING_CULL_CITY_INDICES 31  // uint[]: the city's index buffer, every mesh's triangles in mesh order
#define BINDING_CULL_INDICES 32       // uint[]: a list's index buffer, its meshes' indices in mesh order

// Per-mesh bits of BINDING_CULL_FLAGS.
#define CULL_PREVIOUS 1u              // passed the occlusion test last frame (drawn in the early phase)
#define CULL_IN_FRUSTUM 2u            // its bounds meet the view frustum
#define CULL_UNOCCLUDED 4u            // in the frustum and not behind the early phase's depth
#define CULL_NEXT 8u                  // CULL_UNOCCLUDED, kept for the next frame's CULL_PREVIOUS

// Phases of the culling pass (CullPush.phase).
#define CULL_PHASE_FRUSTUM 0u
#define CULL_PHASE_OCCLUSION 1u
#define CULL_PHASE_COUNT 2u
#define CULL_PHASE_SCAN 3u
#define CULL_PHASE_EMIT 4u
#define CULL_CHUNK 64u                // meshes per invocation of the count and emit phases
#define CULL_WINDOWS 8                // array elements of BINDING_CULL_BOUNDS and BINDING_CULL_CITY_INDICES
#define CULL_PHASE_PYRAMID 5u         // per texel of level `want` (>= 1): the farthest of the four below it

// A mesh's world-space bounding box; low.w != 0: unbounded (non-finite positions), never culled.
struct MeshBounds {
    vec4 low;
    vec4 high;
};

// Push constants of the culling pass.
struct CullPush {
    mat4 view_proj;
    uvec4 pyramid;          // xy: depth target size in pixels, z: pyramid levels, w: unused
    uint mesh_count;
    uint phase;             // CULL_PHASE_*
    uint mask;              // a mesh is in the list when (flags & mask) == want
    uint want;
    uint capacity;          // indices the list's buffer holds
    uint group_count;       // chunks of CULL_CHUNK meshes
    uint city_indices;      // indices of the whole city (the overflow draw)
    uint window_shifts;     // log2 of meshes per bounds window (bits 0..8), of indices per index window (8..16)
};

// What one list holds.
struct CullCounter {
    uint indices;           // indices of its meshes
    uint overflowed;        // 1: they did not fit its buffer, every mesh is drawn instead
    uint meshes;            // meshes in the list
    uint pad0;
};

// Push constants of the ground pass: one quad over the imagery's area.
struct GroundPush {
    mat4 view_proj;
    vec4 area;              // xy: lower corner (x, z), zw: upper corner, metres in the dataset's frame
    vec4 params;            // x: ground height y, y: ground size of a tile at scale 0 (metres),
                            // z: depth bias toward the viewer (a fraction of the depth), w: texels per tile side
    ivec4 levels;           // x: finest scale drawn, y: levels drawn, z: tiles per cache side,
                            // w: level slots of the tile array (a scale's slot is scale mod w)
    vec4 fallback;          // colour where no patch covers the ground
};

// The tile map: what layer i of the tile array holds. A fragment's tile at a
// scale is resident when the entry of its layer names it and is resident.
struct GroundTileEntry {
    int x;                  // tile index along x at its scale
    int z;                  // along z
    int scale;              // its scale (2^scale grid cells per side)
    uint resident;          // 1: the layer holds its texels
};

// Fixed-point scales of MeshFeedback. A mip level is stored as
// round(level * FEEDBACK_MIP_ONE); a weight W (1..17 per fragment) as
// round(W * FEEDBACK_WEIGHT_ONE). The weight sum cannot overflow 32 bits at
// the largest feedback target the engine allows (FEEDBACK_MAX_PIXELS):
// 4096 * 4096 fragments * 17 * 8 = 2 281 701 376 < 4 294 967 295, even if
// every fragment of the target belonged to one mesh with maximal weight.
#define FEEDBACK_MIP_ONE 256.0
#define FEEDBACK_WEIGHT_ONE 8.0
// Anisotropy of the feedback's mip computation (A_m) and of sampling (A_s), Table 2.
#define FEEDBACK_ANISOTROPY 16.0
#define SAMPLE_ANISOTROPY 8.0

// Push constants of the city passes (depth pre-pass, feedback and visible):
// one set per pass, which draws every mesh with one draw.
struct CityDrawPush {
    mat4 view_proj;
    vec4 feedback;          // x: log2 of visible pixels per feedback pixel (subtracted from the LOD), y: foreground distance,
                            // zw: scale from feedback NDC to visible NDC (margin fragments lie outside [-1, 1])
    vec4 viewport_light;    // xy: target size in pixels, z: lighting weight (0 = unlit),
                            // w: 1 = sample directly without colormap blending (visible pass)
    vec4 eye_high;          // xyz: the eye rounded to f32 (view_proj has no translation)
    vec4 eye_low;           // xyz: what that rounding left of the eye
};

// A local origin in the scene's frame, split in two f32s as the eye is: high = the origin
// rounded to f32, low = what that rounding left (xyz; w unused).
struct CityOrigin {
    vec4 high;
    vec4 low;
};

// Clip position of a city vertex, its position relative to its mesh's local origin. The
// eye is subtracted before the rotation: the origin's and the eye's high parts cancel
// first (both large and near each other, so exactly), then the small position and the low
// parts are added, so positions relative to the camera keep their precision however far
// from the scene's origin the mesh and the camera lie (no translation carried in f32
// through the matrix). `precise` keeps the compiler from fusing or reordering the steps.
// With the origin at zero this is (position - eye_high) - eye_low.
vec4 city_clip_position(CityDrawPush push, vec3 position, CityOrigin origin) {
    precise vec3 relative =
        (position + (origin.high.xyz - push.eye_high.xyz)) + (origin.low.xyz - push.eye_low.xyz);
    return push.view_proj * vec4(relative, 1.0);
}

// What the city passes know of mesh i, at index i of BINDING_CITY_MESHES.
// Every city vertex carries its mesh id (vertex input location 3), passed
// flat to the fragment stage.
struct CityMeshInfo {
    uint texture_id;
    uint texture_width;     // full original resolution, level 0
    uint texture_height;
    uint max_mip;           // M_max: the texture's coarsest level at full resolution
    uint origin;            // index in BINDING_CITY_ORIGINS of the local origin its positions
                            // are relative to
};

// ---- Descriptor set 0: texture probe (samples through TextureData) -------
#define BINDING_TEXTURE_PROBE_POINTS 14   // TextureProbePoint[]
#define BINDING_TEXTURE_PROBE_RESULTS 15  // ProbeResult[]

// TextureData::state values.
#define TEXTURE_NOT_SAMPLEABLE 0u
#define TEXTURE_SAMPLEABLE 1u

// Where a dataset texture lives in the cache; written by the engine between
// frames, read by every pass that samples city textures.
struct TextureData {
    vec4 uv_transform;   // xy: scale, zw: offset, texture UV -> layer UV, valid at every cached mip
    uint image;          // cache image: the element of BINDING_CACHE_IMAGES
    uint layer;          // array layer
    uint lowest_mip;     // finest resident level; meaningful when state == TEXTURE_SAMPLEABLE
    uint state;          // TEXTURE_SAMPLEABLE or TEXTURE_NOT_SAMPLEABLE
    uint mip_count;      // levels the cache holds for this texture
    uint pad0;
    uint pad1;
    uint pad2;
};

// One sampling request of the texture probe.
struct TextureProbePoint {
    vec2 uv;        // texture UV; repeats outside [0, 1)
    float lod;      // requested level of detail
    uint texture;   // dataset texture id
};

// A mesh no fragment wrote this frame.
#define FEEDBACK_UNSEEN 0xFFFFFFFFu

// Per-mesh feedback, combined atomically by the fragment stage: the lowest
// (finest) needed mip level and the summed perceptual weight, both fixed point.
struct MeshFeedback {
    uint min_mip;   // FEEDBACK_UNSEEN when no fragment of the mesh was rasterised
    uint weight;
};

// One compacted entry: (mip level, weight, mesh id), as the paper's records.
struct FeedbackEntry {
    uint mip;
    uint weight;
    uint mesh_id;
};

// Number of entries appended, and how many did not fit the dense array.
struct FeedbackCounter {
    uint count;
    uint dropped;
};

// Push constants of the compaction pass.
struct CompactPush {
    uint mesh_count;
    uint tau;        // minimum weight kept, in the weight's fixed-point units
    uint capacity;   // entries the dense array holds
    uint pad0;
};

// Push constants of the mesh pipeline (one draw per mesh).
struct DrawPush {
    mat4 view_proj;
    vec4 light_dir_weight;  // xyz: direction towards the light; w: 0 = unlit, 1 = fully lit
    vec4 tint;              // multiplies the sampled colour (the City Colormap colour for untextured draws)
    uint layer;             // texture-array layer of this mesh
    uint pad0;
    uint pad1;
    uint pad2;
};

// One sampling request of the residency probe.
struct ProbePoint {
    vec2 uv;
    float layer;
    float lod;
};

// What the probe read at one ProbePoint.
struct ProbeResult {
    vec4 value;
    uint resident;   // 1 where sparseTexelsResidentARB said so
    int raw_code;    // the residency code as the driver returned it
    uint pad0;
    uint pad1;
};

#endif
