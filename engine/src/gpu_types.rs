//! Rust mirrors of the GPU-visible structs in `shaders/include/citystream.glsl`.
//!
//! Each struct is `#[repr(C)]` + `Pod` with the std430 layout glslang gives
//! its GLSL twin; `tests::layouts_match_spirv` reads the member offsets and
//! array strides glslang wrote into the SPIR-V and compares them.

use bytemuck::{Pod, Zeroable};

/// Binding of the mesh pipeline's texture array (`BINDING_MESH_TEXTURES`).
pub const BINDING_MESH_TEXTURES: u32 = 0;
/// Binding of the probe's sparse image (`BINDING_PROBE_TEXTURE`).
pub const BINDING_PROBE_TEXTURE: u32 = 0;
/// Binding of the probe's points (`BINDING_PROBE_POINTS`).
pub const BINDING_PROBE_POINTS: u32 = 1;
/// Binding of the probe's results (`BINDING_PROBE_RESULTS`).
pub const BINDING_PROBE_RESULTS: u32 = 2;

/// Binding of the per-mesh feedback array in the compaction pass.
pub const BINDING_COMPACT_SPARSE: u32 = 0;
/// Binding of the dense compacted entries.
pub const BINDING_COMPACT_DENSE: u32 = 1;
/// Binding of the compaction counter.
pub const BINDING_COMPACT_COUNTER: u32 = 2;
/// `FEEDBACK_UNSEEN`: `MeshFeedback::min_mip` of a mesh no fragment wrote.
pub const FEEDBACK_UNSEEN: u32 = u32::MAX;

/// `MeshFeedback`: per-mesh minimum mip level and summed weight (fixed point).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct MeshFeedback {
    /// Finest needed mip level, or [`FEEDBACK_UNSEEN`].
    pub min_mip: u32,
    /// Summed weight.
    pub weight: u32,
}

/// `FeedbackEntry`: one compacted record (mip level, weight, mesh id).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, PartialOrd, Ord, Pod, Zeroable)]
pub struct FeedbackEntry {
    /// Finest needed mip level.
    pub mip: u32,
    /// Summed weight.
    pub weight: u32,
    /// Mesh index.
    pub mesh_id: u32,
}

/// `FeedbackCounter`: entries appended and entries that did not fit.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct FeedbackCounter {
    /// Entries that passed τ (may exceed the capacity).
    pub count: u32,
    /// Entries that passed τ but found no room.
    pub dropped: u32,
}

/// `CompactPush`: push constants of the compaction pass.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct CompactPush {
    /// Meshes in the sparse array.
    pub mesh_count: u32,
    /// Minimum weight kept.
    pub tau: u32,
    /// Entries the dense array holds.
    pub capacity: u32,
    /// Padding.
    pub pad0: u32,
}

/// Binding of the culling pass's mesh bounds ([`MeshBounds`], one per mesh).
pub const BINDING_CULL_BOUNDS: u32 = 22;
/// Binding of the culling pass's index ranges (first index and count per mesh).
pub const BINDING_CULL_RANGES: u32 = 23;
/// Binding of the culling pass's per-mesh flags (`CULL_*` bits).
pub const BINDING_CULL_FLAGS: u32 = 24;
/// Binding of the culling pass's per-chunk index counts, then first indices.
pub const BINDING_CULL_GROUPS: u32 = 25;
/// Binding of a culled list's two indexed indirect draws (the list's; every mesh's on overflow).
pub const BINDING_CULL_DRAWS: u32 = 26;
/// Binding of a culled list's [`CullCounter`].
pub const BINDING_CULL_COUNTER: u32 = 27;
/// Binding of a view's depth pyramid (levels packed, farthest depth per texel).
pub const BINDING_CULL_PYRAMID: u32 = 28;
/// Binding of the culling pass's chunk bounds (one [`MeshBounds`] per 64 meshes).
pub const BINDING_CULL_CHUNK_BOUNDS: u32 = 29;
/// Binding of the culling pass's per-chunk frustum results (one per view).
pub const BINDING_CULL_CHUNK_FLAGS: u32 = 30;
/// Binding of the city's index buffer, read by the culling pass.
pub const BINDING_CULL_CITY_INDICES: u32 = 31;
/// Binding of a culled list's index buffer.
pub const BINDING_CULL_INDICES: u32 = 32;

/// Culling phases (`CullPush::phase`), as in `city_cull.comp`.
pub const CULL_PHASE_FRUSTUM: u32 = 0;
/// Occlusion against the depth pyramid.
pub const CULL_PHASE_OCCLUSION: u32 = 1;
/// Indices listed per chunk.
pub const CULL_PHASE_COUNT: u32 = 2;
/// First index per chunk, and the draws.
pub const CULL_PHASE_SCAN: u32 = 3;
/// The listed meshes' indices copied into the list's buffer.
pub const CULL_PHASE_EMIT: u32 = 4;
/// One level of the depth pyramid.
pub const CULL_PHASE_PYRAMID: u32 = 5;

/// Per-mesh flag: passed the occlusion test last frame.
pub const CULL_PREVIOUS: u32 = 1;
/// Per-mesh flag: its bounds meet the view frustum.
pub const CULL_IN_FRUSTUM: u32 = 2;
/// Per-mesh flag: in the frustum and not behind the early phase's depth.
pub const CULL_UNOCCLUDED: u32 = 4;

/// `MeshBounds`: a mesh's world-space box; `low[3] != 0` marks it unbounded (never culled).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct MeshBounds {
    /// Smallest corner; w: 1 when the mesh has non-finite positions.
    pub low: [f32; 4],
    /// Largest corner; w unused.
    pub high: [f32; 4],
}

/// `CullPush`: push constants of the culling pass.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct CullPush {
    /// The view's view-projection, column-major.
    pub view_proj: [[f32; 4]; 4],
    /// Depth target width and height, pyramid levels, unused.
    pub pyramid: [u32; 4],
    /// Meshes culled.
    pub mesh_count: u32,
    /// `CULL_PHASE_*`.
    pub phase: u32,
    /// A mesh is listed when `flags & mask == want`.
    pub mask: u32,
    /// See `mask`; the level built by the pyramid phase.
    pub want: u32,
    /// Indices the list's buffer holds.
    pub capacity: u32,
    /// Chunks of 64 meshes.
    pub group_count: u32,
    /// Indices of the whole city (the overflow draw).
    pub city_indices: u32,
    /// log2 of the meshes per window of the bounds (bits 0..8) and of the indices per
    /// window of the city's index buffer (bits 8..16); see [`CULL_WINDOWS`].
    pub window_shifts: u32,
}

/// Windows the culling pass views the mesh bounds and the city's index buffer through
/// (array bindings of [`BINDING_CULL_BOUNDS`] and [`BINDING_CULL_CITY_INDICES`]): each
/// window at most the device's `maxStorageBufferRange` (128 MiB on lavapipe), so a city of
/// up to 8 such windows of either (33 M meshes, 268 M indices on lavapipe) is culled.
pub const CULL_WINDOWS: u32 = 8;

/// `CullCounter`: what a culled list holds.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct CullCounter {
    /// Indices of its meshes.
    pub indices: u32,
    /// 1 when they did not fit the list's buffer (every mesh is drawn instead).
    pub overflowed: u32,
    /// Meshes listed.
    pub meshes: u32,
    /// Padding.
    pub pad0: u32,
}

/// Binding of the cache images in passes that sample city textures: an
/// array of [`CACHE_IMAGE_SLOTS`] combined image samplers, indexed by
/// [`TextureData::image`].
pub const BINDING_CACHE_IMAGES: u32 = 10;
/// Elements of the [`BINDING_CACHE_IMAGES`] array: the most sparse images
/// the cache may create over all formats. Eight leaves room under the
/// sixteen samplers per stage every Vulkan device offers for a host's own.
pub const CACHE_IMAGE_SLOTS: u32 = 8;
/// Binding of the per-texture [`TextureData`] table.
pub const BINDING_TEXTURE_DATA: u32 = 12;
/// Binding of the City Colormap (RGBA8 packed in a `uint` per texture).
pub const BINDING_COLORMAP: u32 = 13;
/// Binding of the texture probe's points.
pub const BINDING_TEXTURE_PROBE_POINTS: u32 = 14;
/// Binding of the texture probe's results.
pub const BINDING_TEXTURE_PROBE_RESULTS: u32 = 15;
/// `TEXTURE_NOT_SAMPLEABLE`.
pub const TEXTURE_NOT_SAMPLEABLE: u32 = 0;
/// `TEXTURE_SAMPLEABLE`.
pub const TEXTURE_SAMPLEABLE: u32 = 1;

/// `TextureData`: where a dataset texture lives in the cache.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct TextureData {
    /// xy: scale, zw: offset (texture UV to layer UV).
    pub uv_transform: [f32; 4],
    /// Cache image: the element of the `BINDING_CACHE_IMAGES` array.
    pub image: u32,
    /// Array layer.
    pub layer: u32,
    /// Finest resident level.
    pub lowest_mip: u32,
    /// [`TEXTURE_SAMPLEABLE`] or [`TEXTURE_NOT_SAMPLEABLE`].
    pub state: u32,
    /// Levels the cache holds for this texture.
    pub mip_count: u32,
    /// Padding.
    pub pad0: u32,
    /// Padding.
    pub pad1: u32,
    /// Padding.
    pub pad2: u32,
}

/// `TextureProbePoint`: one sampling request of the texture probe.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct TextureProbePoint {
    /// Texture UV.
    pub uv: [f32; 2],
    /// Requested level of detail.
    pub lod: f32,
    /// Dataset texture id.
    pub texture: u32,
}

/// Binding of the per-mesh feedback array in the feedback pass.
pub const BINDING_FEEDBACK_MESHES: u32 = 16;
/// Binding of the per-mesh `CityMeshInfo` array in the city passes (their vertex stage reads
/// each mesh's local origin, the fragment stages its texture).
pub const BINDING_CITY_MESHES: u32 = 17;
/// Binding of the `CityOrigin` array the city passes' vertex stage reads.
pub const BINDING_CITY_ORIGINS: u32 = 33;
/// Binding of the per-vertex root-atlas coordinates in a texture-atlas tree's visible pass.
pub const BINDING_TREE_ATLAS_UVS: u32 = 18;
/// Binding of the per-mesh texture matrices (`[scale, offset x, offset y, 0]`, scale 0 for
/// the mesh's own coordinates) in a texture-atlas tree's visible pass.
pub const BINDING_TREE_UV_TRANSFORMS: u32 = 19;
/// Binding of the ground layer's tile array (`sampler2DArray`).
pub const BINDING_GROUND_TILES: u32 = 20;
/// Binding of the ground layer's tile map ([`GroundTileEntry`] per tile-array layer).
pub const BINDING_GROUND_TILE_MAP: u32 = 21;
/// `FEEDBACK_MIP_ONE`: a mip level is stored as `round(level * 256)`.
pub const FEEDBACK_MIP_ONE: f32 = 256.0;
/// `FEEDBACK_WEIGHT_ONE`: a weight is stored as `round(W * 8)`.
pub const FEEDBACK_WEIGHT_ONE: f32 = 8.0;
/// Largest feedback target (pixels) for which the 32-bit weight sum provably
/// cannot overflow: 4096² fragments × 17 (largest W) × 8 < 2³².
pub const FEEDBACK_MAX_PIXELS: u64 = 4096 * 4096;
/// `FEEDBACK_ANISOTROPY` (A_m).
pub const FEEDBACK_ANISOTROPY: f32 = 16.0;
/// `SAMPLE_ANISOTROPY` (A_s).
pub const SAMPLE_ANISOTROPY: f32 = 8.0;

/// `CityDrawPush`: push constants of a city pass, set once per pass (one
/// draw covers every mesh).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct CityDrawPush {
    /// Column-major view-projection matrix of positions relative to the eye: rotation and
    /// projection, no translation ([`crate::city::Camera::relative_view_projection`]).
    pub view_proj: [[f32; 4]; 4],
    /// x: log2 of visible pixels per feedback pixel (subtracted from the
    /// feedback LOD), y: foreground distance, zw: feedback-to-visible NDC scale.
    pub feedback: [f32; 4],
    /// xy: target size in pixels, z: lighting weight, w: 1 = no colormap
    /// blending (direct sampling).
    pub viewport_light: [f32; 4],
    /// xyz: the eye rounded to f32 ([`crate::city::Camera::eye_split`]); w unused.
    pub eye_high: [f32; 4],
    /// xyz: what the rounding left of the eye; w unused.
    pub eye_low: [f32; 4],
}

/// `GroundPush`: push constants of the ground pass (its one quad over the imagery).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct GroundPush {
    /// Column-major view-projection matrix.
    pub view_proj: [[f32; 4]; 4],
    /// Lower corner (x, z) and upper corner of the quad, metres.
    pub area: [f32; 4],
    /// x: ground height, y: tile size at scale 0 (metres), z: depth bias (NDC), w: texels
    /// per tile side.
    pub params: [f32; 4],
    /// x: finest scale drawn, y: levels drawn, z: tiles per cache side, w: level slots.
    pub levels: [i32; 4],
    /// Colour where no patch covers the ground (RGB, 0 to 1).
    pub fallback: [f32; 4],
}

/// `GroundTileEntry`: what one layer of the ground's tile array holds.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct GroundTileEntry {
    /// Tile index along x at its scale.
    pub x: i32,
    /// Tile index along z.
    pub z: i32,
    /// Its scale.
    pub scale: i32,
    /// 1 when the layer holds its texels.
    pub resident: u32,
}

/// `CityMeshInfo`: what the city passes know of one mesh, indexed by the
/// mesh id of its vertices ([`CityVertex::mesh_id`]).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct CityMeshInfo {
    /// Dataset texture id.
    pub texture_id: u32,
    /// Texture width at level 0 (full resolution).
    pub texture_width: u32,
    /// Texture height at level 0.
    pub texture_height: u32,
    /// M_max: coarsest level at full resolution.
    pub max_mip: u32,
    /// Index in the [`CityOrigin`] array of the local origin the mesh's vertex positions are
    /// relative to.
    pub origin: u32,
}

/// `CityOrigin`: a local origin in the scene's frame as the city passes' vertex stage takes
/// it, split in two `f32`s as the eye is ([`crate::city::split_f64`]).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct CityOrigin {
    /// xyz: the origin rounded to `f32`; w unused.
    pub high: [f32; 4],
    /// xyz: what that rounding left; w unused.
    pub low: [f32; 4],
}

/// One vertex of a mesh (vertex input, not a GLSL struct).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct Vertex {
    /// Position in scene units, relative to the scene origin.
    pub position: [f32; 3],
    /// Unit normal.
    pub normal: [f32; 3],
    /// Texture coordinate; values outside [0, 1] repeat.
    pub uv: [f32; 2],
}

impl Vertex {
    /// Vertex attributes: (location, format, offset).
    pub fn attributes() -> Vec<(u32, ash::vk::Format, u32)> {
        use ash::vk::Format;
        vec![
            (
                0,
                Format::R32G32B32_SFLOAT,
                std::mem::offset_of!(Vertex, position) as u32,
            ),
            (1, Format::R32G32B32_SFLOAT, std::mem::offset_of!(Vertex, normal) as u32),
            (2, Format::R32G32_SFLOAT, std::mem::offset_of!(Vertex, uv) as u32),
        ]
    }
}

/// One vertex of the city passes: a [`Vertex`] tagged with the id of its
/// mesh, so a single draw covers every mesh (vertex input, not a GLSL struct).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct CityVertex {
    /// Position in scene units, relative to the scene origin.
    pub position: [f32; 3],
    /// Unit normal.
    pub normal: [f32; 3],
    /// Texture coordinate; values outside [0, 1] repeat.
    pub uv: [f32; 2],
    /// Index of the mesh in the city's mesh table.
    pub mesh_id: u32,
}

impl CityVertex {
    /// Vertex attributes: (location, format, offset).
    pub fn attributes() -> Vec<(u32, ash::vk::Format, u32)> {
        use ash::vk::Format;
        vec![
            (
                0,
                Format::R32G32B32_SFLOAT,
                std::mem::offset_of!(CityVertex, position) as u32,
            ),
            (
                1,
                Format::R32G32B32_SFLOAT,
                std::mem::offset_of!(CityVertex, normal) as u32,
            ),
            (2, Format::R32G32_SFLOAT, std::mem::offset_of!(CityVertex, uv) as u32),
            (3, Format::R32_UINT, std::mem::offset_of!(CityVertex, mesh_id) as u32),
        ]
    }
}

/// `DrawPush`: push constants of one mesh draw.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct DrawPush {
    /// Column-major view-projection matrix.
    pub view_proj: [[f32; 4]; 4],
    /// xyz: direction towards the light; w: lighting weight (0 = unlit).
    pub light_dir_weight: [f32; 4],
    /// Multiplies the sampled colour.
    pub tint: [f32; 4],
    /// Texture-array layer of the mesh.
    pub layer: u32,
    /// Padding to 16 bytes.
    pub pad0: u32,
    /// Padding.
    pub pad1: u32,
    /// Padding.
    pub pad2: u32,
}

/// `ProbePoint`: one sampling request of the residency probe.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct ProbePoint {
    /// Normalised texture coordinate.
    pub uv: [f32; 2],
    /// Array layer.
    pub layer: f32,
    /// Explicit level of detail.
    pub lod: f32,
}

/// `ProbeResult`: what the probe read.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct ProbeResult {
    /// The sampled value.
    pub value: [f32; 4],
    /// 1 where the texels were resident.
    pub resident: u32,
    /// The residency code as returned by the driver.
    pub raw_code: i32,
    /// Padding.
    pub pad0: u32,
    /// Padding.
    pub pad1: u32,
}

/// Struct layouts read back from SPIR-V decorations.
pub mod spirv_layout {
    use std::collections::HashMap;

    /// Layout of one struct type as glslang decorated it.
    #[derive(Clone, Debug, Default, PartialEq, Eq)]
    pub struct StructLayout {
        /// (member name, byte offset), in member order.
        pub members: Vec<(String, u32)>,
        /// Array strides of arrays whose element is this struct.
        pub array_strides: Vec<u32>,
    }

    fn string_at(words: &[u32]) -> String {
        let bytes: Vec<u8> = words
            .iter()
            .flat_map(|w| w.to_le_bytes())
            .take_while(|&b| b != 0)
            .collect();
        String::from_utf8_lossy(&bytes).into_owned()
    }

    /// Reads every named struct's member offsets and array strides. Returns
    /// one entry per struct name (glslang may emit several types of one name,
    /// all of which are listed).
    pub fn reflect(spirv: &[u32]) -> HashMap<String, Vec<StructLayout>> {
        const OP_NAME: u32 = 5;
        const OP_MEMBER_NAME: u32 = 6;
        const OP_TYPE_STRUCT: u32 = 30;
        const OP_TYPE_ARRAY: u32 = 28;
        const OP_TYPE_RUNTIME_ARRAY: u32 = 29;
        const OP_DECORATE: u32 = 71;
        const OP_MEMBER_DECORATE: u32 = 72;
        const DECORATION_ARRAY_STRIDE: u32 = 6;
        const DECORATION_OFFSET: u32 = 35;

        let mut names: HashMap<u32, String> = HashMap::new();
        let mut member_names: HashMap<(u32, u32), String> = HashMap::new();
        let mut offsets: HashMap<(u32, u32), u32> = HashMap::new();
        let mut structs: Vec<(u32, u32)> = Vec::new(); // (id, member count)
        let mut array_elements: HashMap<u32, u32> = HashMap::new(); // array id -> element type
        let mut strides: HashMap<u32, u32> = HashMap::new(); // array id -> stride

        let mut i = 5; // skip the header
        while i < spirv.len() {
            let count = (spirv[i] >> 16) as usize;
            let opcode = spirv[i] & 0xffff;
            if count == 0 || i + count > spirv.len() {
                break;
            }
            let ops = &spirv[i + 1..i + count];
            match opcode {
                OP_NAME if !ops.is_empty() => {
                    names.insert(ops[0], string_at(&ops[1..]));
                }
                OP_MEMBER_NAME if ops.len() >= 2 => {
                    member_names.insert((ops[0], ops[1]), string_at(&ops[2..]));
                }
                OP_TYPE_STRUCT if !ops.is_empty() => structs.push((ops[0], (ops.len() - 1) as u32)),
                OP_TYPE_ARRAY | OP_TYPE_RUNTIME_ARRAY if ops.len() >= 2 => {
                    array_elements.insert(ops[0], ops[1]);
                }
                OP_DECORATE if ops.len() >= 3 && ops[1] == DECORATION_ARRAY_STRIDE => {
                    strides.insert(ops[0], ops[2]);
                }
                OP_MEMBER_DECORATE if ops.len() >= 4 && ops[2] == DECORATION_OFFSET => {
                    offsets.insert((ops[0], ops[1]), ops[3]);
                }
                _ => {}
            }
            i += count;
        }

        let mut result: HashMap<String, Vec<StructLayout>> = HashMap::new();
        for (id, member_count) in structs {
            let Some(name) = names.get(&id) else { continue };
            let members: Option<Vec<_>> = (0..member_count)
                .map(|m| Some((member_names.get(&(id, m))?.clone(), *offsets.get(&(id, m))?)))
                .collect();
            let Some(members) = members else { continue };
            let array_strides = array_elements
                .iter()
                .filter(|(_, &element)| element == id)
                .filter_map(|(array, _)| strides.get(array).copied())
                .collect();
            result
                .entry(name.clone())
                .or_default()
                .push(StructLayout { members, array_strides });
        }
        result
    }
}

#[cfg(test)]
mod tests {
    use super::spirv_layout::reflect;
    use super::*;
    use std::mem::{offset_of, size_of};

    fn spirv_words(bytes: &[u8]) -> Vec<u32> {
        bytes
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect()
    }

    fn all_layouts() -> std::collections::HashMap<String, Vec<spirv_layout::StructLayout>> {
        let mut all = std::collections::HashMap::new();
        for shader in crate::shaders::ALL {
            for (name, layouts) in reflect(&spirv_words(shader.spirv)) {
                all.entry(name).or_insert_with(Vec::new).extend(layouts);
            }
        }
        all
    }

    fn check(name: &str, rust: &[(&str, usize)], rust_size: usize) {
        let all = all_layouts();
        let layouts = all
            .get(name)
            .unwrap_or_else(|| panic!("struct {name} not found in any shader's SPIR-V"));
        for layout in layouts {
            let gpu: Vec<(&str, usize)> = layout.members.iter().map(|(n, o)| (n.as_str(), *o as usize)).collect();
            assert_eq!(gpu, rust, "member offsets of {name} differ between GLSL and Rust");
            for &stride in &layout.array_strides {
                assert_eq!(
                    stride as usize, rust_size,
                    "array stride of {name} differs from size_of"
                );
            }
        }
        // The struct's size is its last member's end when no array stride says otherwise.
        let (last_name, last_offset) = *rust.last().expect("structs have members");
        assert!(last_offset < rust_size, "{name}.{last_name} lies past the struct size");
    }

    #[test]
    fn layouts_match_spirv() {
        check(
            "DrawPush",
            &[
                ("view_proj", offset_of!(DrawPush, view_proj)),
                ("light_dir_weight", offset_of!(DrawPush, light_dir_weight)),
                ("tint", offset_of!(DrawPush, tint)),
                ("layer", offset_of!(DrawPush, layer)),
                ("pad0", offset_of!(DrawPush, pad0)),
                ("pad1", offset_of!(DrawPush, pad1)),
                ("pad2", offset_of!(DrawPush, pad2)),
            ],
            size_of::<DrawPush>(),
        );
        assert_eq!(size_of::<DrawPush>(), 112);
        check(
            "ProbePoint",
            &[
                ("uv", offset_of!(ProbePoint, uv)),
                ("layer", offset_of!(ProbePoint, layer)),
                ("lod", offset_of!(ProbePoint, lod)),
            ],
            size_of::<ProbePoint>(),
        );
        check(
            "ProbeResult",
            &[
                ("value", offset_of!(ProbeResult, value)),
                ("resident", offset_of!(ProbeResult, resident)),
                ("raw_code", offset_of!(ProbeResult, raw_code)),
                ("pad0", offset_of!(ProbeResult, pad0)),
                ("pad1", offset_of!(ProbeResult, pad1)),
            ],
            size_of::<ProbeResult>(),
        );
    }

    #[test]
    fn binding_numbers_match_the_glsl_header() {
        let header = include_str!("../../shaders/include/citystream.glsl");
        let defines: std::collections::HashMap<&str, u32> = header
            .lines()
            .filter_map(|line| {
                let mut words = line.split_whitespace();
                (words.next()? == "#define").then_some(())?;
                let name = words.next()?;
                let value = words.next()?.parse().ok()?;
                name.starts_with("BINDING_").then_some((name, value))
            })
            .collect();
        let rust = [
            ("BINDING_MESH_TEXTURES", BINDING_MESH_TEXTURES),
            ("BINDING_PROBE_TEXTURE", BINDING_PROBE_TEXTURE),
            ("BINDING_PROBE_POINTS", BINDING_PROBE_POINTS),
            ("BINDING_PROBE_RESULTS", BINDING_PROBE_RESULTS),
            ("BINDING_COMPACT_SPARSE", BINDING_COMPACT_SPARSE),
            ("BINDING_COMPACT_DENSE", BINDING_COMPACT_DENSE),
            ("BINDING_COMPACT_COUNTER", BINDING_COMPACT_COUNTER),
            ("BINDING_CACHE_IMAGES", BINDING_CACHE_IMAGES),
            ("BINDING_TEXTURE_DATA", BINDING_TEXTURE_DATA),
            ("BINDING_COLORMAP", BINDING_COLORMAP),
            ("BINDING_TEXTURE_PROBE_POINTS", BINDING_TEXTURE_PROBE_POINTS),
            ("BINDING_TEXTURE_PROBE_RESULTS", BINDING_TEXTURE_PROBE_RESULTS),
            ("BINDING_FEEDBACK_MESHES", BINDING_FEEDBACK_MESHES),
            ("BINDING_CITY_MESHES", BINDING_CITY_MESHES),
            ("BINDING_CITY_ORIGINS", BINDING_CITY_ORIGINS),
            ("BINDING_TREE_ATLAS_UVS", BINDING_TREE_ATLAS_UVS),
            ("BINDING_TREE_UV_TRANSFORMS", BINDING_TREE_UV_TRANSFORMS),
            ("BINDING_GROUND_TILES", BINDING_GROUND_TILES),
            ("BINDING_GROUND_TILE_MAP", BINDING_GROUND_TILE_MAP),
            ("BINDING_CULL_BOUNDS", BINDING_CULL_BOUNDS),
            ("BINDING_CULL_RANGES", BINDING_CULL_RANGES),
            ("BINDING_CULL_FLAGS", BINDING_CULL_FLAGS),
            ("BINDING_CULL_GROUPS", BINDING_CULL_GROUPS),
            ("BINDING_CULL_DRAWS", BINDING_CULL_DRAWS),
            ("BINDING_CULL_COUNTER", BINDING_CULL_COUNTER),
            ("BINDING_CULL_PYRAMID", BINDING_CULL_PYRAMID),
            ("BINDING_CULL_CHUNK_BOUNDS", BINDING_CULL_CHUNK_BOUNDS),
            ("BINDING_CULL_CHUNK_FLAGS", BINDING_CULL_CHUNK_FLAGS),
            ("BINDING_CULL_CITY_INDICES", BINDING_CULL_CITY_INDICES),
            ("BINDING_CULL_INDICES", BINDING_CULL_INDICES),
        ];
        assert_eq!(
            defines.len(),
            rust.len(),
            "every GLSL binding needs a Rust twin: {defines:?}"
        );
        for (name, value) in rust {
            assert_eq!(defines.get(name), Some(&value), "{name} differs between GLSL and Rust");
        }
        let slots = header
            .lines()
            .find_map(|line| line.strip_prefix("#define CACHE_IMAGE_SLOTS "))
            .and_then(|rest| rest.split_whitespace().next()?.parse::<u32>().ok());
        assert_eq!(slots, Some(CACHE_IMAGE_SLOTS));
        let windows = header
            .lines()
            .find_map(|line| line.strip_prefix("#define CULL_WINDOWS "))
            .and_then(|rest| {
                rest.split_whitespace()
                    .next()?
                    .trim_end_matches('u')
                    .parse::<u32>()
                    .ok()
            });
        assert_eq!(windows, Some(CULL_WINDOWS));
    }

    #[test]
    fn feedback_layouts_match_spirv() {
        check(
            "MeshFeedback",
            &[
                ("min_mip", offset_of!(MeshFeedback, min_mip)),
                ("weight", offset_of!(MeshFeedback, weight)),
            ],
            size_of::<MeshFeedback>(),
        );
        check(
            "FeedbackEntry",
            &[
                ("mip", offset_of!(FeedbackEntry, mip)),
                ("weight", offset_of!(FeedbackEntry, weight)),
                ("mesh_id", offset_of!(FeedbackEntry, mesh_id)),
            ],
            size_of::<FeedbackEntry>(),
        );
        check(
            "FeedbackCounter",
            &[
                ("count", offset_of!(FeedbackCounter, count)),
                ("dropped", offset_of!(FeedbackCounter, dropped)),
            ],
            size_of::<FeedbackCounter>(),
        );
        check(
            "CompactPush",
            &[
                ("mesh_count", offset_of!(CompactPush, mesh_count)),
                ("tau", offset_of!(CompactPush, tau)),
                ("capacity", offset_of!(CompactPush, capacity)),
                ("pad0", offset_of!(CompactPush, pad0)),
            ],
            size_of::<CompactPush>(),
        );
        let header = include_str!("../../shaders/include/citystream.glsl");
        assert!(header.contains("#define FEEDBACK_UNSEEN 0xFFFFFFFFu") && FEEDBACK_UNSEEN == 0xFFFF_FFFF);
    }

    #[test]
    fn texture_layouts_match_spirv() {
        check(
            "TextureData",
            &[
                ("uv_transform", offset_of!(TextureData, uv_transform)),
                ("image", offset_of!(TextureData, image)),
                ("layer", offset_of!(TextureData, layer)),
                ("lowest_mip", offset_of!(TextureData, lowest_mip)),
                ("state", offset_of!(TextureData, state)),
                ("mip_count", offset_of!(TextureData, mip_count)),
                ("pad0", offset_of!(TextureData, pad0)),
                ("pad1", offset_of!(TextureData, pad1)),
                ("pad2", offset_of!(TextureData, pad2)),
            ],
            size_of::<TextureData>(),
        );
        check(
            "TextureProbePoint",
            &[
                ("uv", offset_of!(TextureProbePoint, uv)),
                ("lod", offset_of!(TextureProbePoint, lod)),
                ("texture", offset_of!(TextureProbePoint, texture)),
            ],
            size_of::<TextureProbePoint>(),
        );
        let header = include_str!("../../shaders/include/citystream.glsl");
        assert!(header.contains("#define TEXTURE_NOT_SAMPLEABLE 0u") && TEXTURE_NOT_SAMPLEABLE == 0);
        assert!(header.contains("#define TEXTURE_SAMPLEABLE 1u") && TEXTURE_SAMPLEABLE == 1);
    }

    #[test]
    fn ground_layouts_match_spirv_and_fit_128_bytes() {
        check(
            "GroundPush",
            &[
                ("view_proj", offset_of!(GroundPush, view_proj)),
                ("area", offset_of!(GroundPush, area)),
                ("params", offset_of!(GroundPush, params)),
                ("levels", offset_of!(GroundPush, levels)),
                ("fallback", offset_of!(GroundPush, fallback)),
            ],
            size_of::<GroundPush>(),
        );
        assert!(size_of::<GroundPush>() <= 128, "the guaranteed push-constant size");
        check(
            "GroundTileEntry",
            &[
                ("x", offset_of!(GroundTileEntry, x)),
                ("z", offset_of!(GroundTileEntry, z)),
                ("scale", offset_of!(GroundTileEntry, scale)),
                ("resident", offset_of!(GroundTileEntry, resident)),
            ],
            size_of::<GroundTileEntry>(),
        );
    }

    #[test]
    fn city_push_layout_matches_spirv_and_fits_128_bytes() {
        check(
            "CityDrawPush",
            &[
                ("view_proj", offset_of!(CityDrawPush, view_proj)),
                ("feedback", offset_of!(CityDrawPush, feedback)),
                ("viewport_light", offset_of!(CityDrawPush, viewport_light)),
                ("eye_high", offset_of!(CityDrawPush, eye_high)),
                ("eye_low", offset_of!(CityDrawPush, eye_low)),
            ],
            size_of::<CityDrawPush>(),
        );
        check(
            "CityMeshInfo",
            &[
                ("texture_id", offset_of!(CityMeshInfo, texture_id)),
                ("texture_width", offset_of!(CityMeshInfo, texture_width)),
                ("texture_height", offset_of!(CityMeshInfo, texture_height)),
                ("max_mip", offset_of!(CityMeshInfo, max_mip)),
                ("origin", offset_of!(CityMeshInfo, origin)),
            ],
            size_of::<CityMeshInfo>(),
        );
        check(
            "CityOrigin",
            &[
                ("high", offset_of!(CityOrigin, high)),
                ("low", offset_of!(CityOrigin, low)),
            ],
            size_of::<CityOrigin>(),
        );
        // 128 bytes is the push-constant size every Vulkan device guarantees.
        assert!(size_of::<CityDrawPush>() <= 128);
        let header = include_str!("../../shaders/include/citystream.glsl");
        for (name, value) in [
            ("FEEDBACK_MIP_ONE", FEEDBACK_MIP_ONE),
            ("FEEDBACK_WEIGHT_ONE", FEEDBACK_WEIGHT_ONE),
            ("FEEDBACK_ANISOTROPY", FEEDBACK_ANISOTROPY),
            ("SAMPLE_ANISOTROPY", SAMPLE_ANISOTROPY),
        ] {
            assert!(
                header.contains(&format!("#define {name} {value:.1}")),
                "{name} differs from the GLSL header"
            );
        }
    }

    #[test]
    fn cull_layouts_and_constants_match_the_glsl_header() {
        check(
            "MeshBounds",
            &[
                ("low", offset_of!(MeshBounds, low)),
                ("high", offset_of!(MeshBounds, high)),
            ],
            size_of::<MeshBounds>(),
        );
        check(
            "CullPush",
            &[
                ("view_proj", offset_of!(CullPush, view_proj)),
                ("pyramid", offset_of!(CullPush, pyramid)),
                ("mesh_count", offset_of!(CullPush, mesh_count)),
                ("phase", offset_of!(CullPush, phase)),
                ("mask", offset_of!(CullPush, mask)),
                ("want", offset_of!(CullPush, want)),
                ("capacity", offset_of!(CullPush, capacity)),
                ("group_count", offset_of!(CullPush, group_count)),
                ("city_indices", offset_of!(CullPush, city_indices)),
                ("window_shifts", offset_of!(CullPush, window_shifts)),
            ],
            size_of::<CullPush>(),
        );
        assert!(size_of::<CullPush>() <= 128, "the guaranteed push-constant size");
        check(
            "CullCounter",
            &[
                ("indices", offset_of!(CullCounter, indices)),
                ("overflowed", offset_of!(CullCounter, overflowed)),
                ("meshes", offset_of!(CullCounter, meshes)),
                ("pad0", offset_of!(CullCounter, pad0)),
            ],
            size_of::<CullCounter>(),
        );
        let header = include_str!("../../shaders/include/citystream.glsl");
        for (name, value) in [
            ("CULL_PHASE_FRUSTUM", CULL_PHASE_FRUSTUM),
            ("CULL_PHASE_OCCLUSION", CULL_PHASE_OCCLUSION),
            ("CULL_PHASE_COUNT", CULL_PHASE_COUNT),
            ("CULL_PHASE_SCAN", CULL_PHASE_SCAN),
            ("CULL_PHASE_EMIT", CULL_PHASE_EMIT),
            ("CULL_PHASE_PYRAMID", CULL_PHASE_PYRAMID),
            ("CULL_PREVIOUS", CULL_PREVIOUS),
            ("CULL_IN_FRUSTUM", CULL_IN_FRUSTUM),
            ("CULL_UNOCCLUDED", CULL_UNOCCLUDED),
        ] {
            assert!(
                header.contains(&format!("#define {name} {value}u")),
                "{name} differs from the GLSL header"
            );
        }
    }

    #[test]
    fn weight_sum_cannot_overflow_at_the_largest_feedback_target() {
        // Every fragment of the largest target in one mesh, each with the
        // largest weight 1 + 8 + 8, in fixed point.
        let worst = FEEDBACK_MAX_PIXELS * 17 * FEEDBACK_WEIGHT_ONE as u64;
        assert!(worst <= u64::from(u32::MAX), "{worst} overflows the 32-bit weight sum");
        // One more doubling of the target would overflow: the bound is tight enough to mean something.
        assert!(worst * 2 > u64::from(u32::MAX));
    }

    #[test]
    fn reflection_sees_array_strides() {
        let all = all_layouts();
        let probe = &all["ProbeResult"];
        assert!(
            probe.iter().any(|l| !l.array_strides.is_empty()),
            "the runtime array of ProbeResult must carry an ArrayStride"
        );
    }
}
