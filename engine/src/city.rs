//! Rendering a city dataset with streamed textures: the feedback pass
//! (paper §3.2) and the visible pass with City Colormap blending (§3.7).
//!
//! Every pass draws all meshes with one draw call: each mesh gets its own
//! copy of the vertices it uses, tagged with its id ([`CityVertex`]), and
//! the shaders look its texture up in a [`CityMeshInfo`] table. A draw per
//! mesh would cost a state change and draw setup each, which dominates the
//! feedback pass on a CPU rasteriser (multi-draw indirect still pays the
//! per-draw setup there). The feedback
//! pass renders a wider field of view than the visible one into a smaller
//! target; fragments outside the visible frustum count with W = 1 (streaming
//! beyond the viewport edge), and a LOD offset converts its derivatives,
//! taken per feedback pixel, to visible pixels.

use std::sync::Arc;

use ash::vk;
use glam::{DMat4, DVec3, Mat4, Vec3};

use crate::buffer::Buffer;
use crate::commands::{CommandContext, Recording};
use crate::cull::{mesh_bounds, CityCulling, CullList, CullStats, CullView};
use crate::device::Device;
use crate::error::{EngineError, Result};
use crate::feedback::FeedbackCompactor;
use crate::gpu_types::{
    CityDrawPush, CityMeshInfo, CityOrigin, CityVertex, Vertex, BINDING_CITY_MESHES, BINDING_CITY_ORIGINS,
    BINDING_FEEDBACK_MESHES, BINDING_TEXTURE_DATA, FEEDBACK_MAX_PIXELS,
};
use crate::ground::GroundLayer;
use crate::image::memory_barrier;
use crate::pipeline::{BindingSpec, DepthMode, DescriptorPool, DescriptorResource, GraphicsDesc, Pipeline};
use crate::scene::{upload_buffer, upload_geometry};
use crate::shaders;
use crate::target::{RenderTarget, COLOR_FORMAT, DEPTH_FORMAT};
use crate::texture_cache::GpuTextureCache;

/// One mesh as the city passes draw it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CityMesh {
    /// First index.
    pub first_index: u32,
    /// Index count (whole triangles).
    pub index_count: u32,
    /// Added to every index.
    pub vertex_offset: u32,
    /// Dataset texture id.
    pub texture: u32,
    /// Texture width at full resolution.
    pub texture_width: u32,
    /// Texture height at full resolution.
    pub texture_height: u32,
    /// The mesh's local origin in the scene's frame: its vertices' positions are `f32`
    /// relative to it, so a mesh far from the scene's origin keeps its precision (zero: the
    /// positions are relative to the scene's origin).
    pub origin: DVec3,
}

impl CityMesh {
    /// M_max: the coarsest level of the full-resolution mip chain.
    pub fn max_mip(&self) -> u32 {
        31 - self.texture_width.max(self.texture_height).max(1).leading_zeros()
    }

    /// What the city passes' shaders know of it.
    pub fn info(&self, origin: u32) -> CityMeshInfo {
        CityMeshInfo {
            texture_id: self.texture,
            texture_width: self.texture_width,
            texture_height: self.texture_height,
            max_mip: self.max_mip(),
            origin,
        }
    }

    /// A vertex position of this mesh (relative to its origin) in the scene's frame.
    pub fn scene_position(&self, position: [f32; 3]) -> DVec3 {
        self.origin + Vec3::from(position).as_dvec3()
    }
}

/// `point` rounded to `f32` towards −∞ and towards +∞ on each axis (the same where `f32`
/// holds it exactly).
fn round_outwards(point: DVec3) -> ([f32; 3], [f32; 3]) {
    let round = |c: f64| {
        let nearest = c as f32;
        let exact = f64::from(nearest);
        match exact.partial_cmp(&c) {
            Some(std::cmp::Ordering::Greater) => (nearest.next_down(), nearest),
            Some(std::cmp::Ordering::Less) => (nearest, nearest.next_up()),
            _ => (nearest, nearest),
        }
    };
    let [x, y, z] = point.to_array().map(round);
    ([x.0, y.0, z.0], [x.1, y.1, z.1])
}

/// The distinct local origins of `meshes` as the city passes take them (in order of first
/// use), and each mesh's index among them: a city whose meshes share a few origins (one
/// per tile, or the scene's alone) holds each once.
pub(crate) fn origin_table(meshes: &[CityMesh]) -> (Vec<CityOrigin>, Vec<u32>) {
    let mut index_of = std::collections::HashMap::new();
    let mut origins = Vec::new();
    // Meshes come a tile (or a whole scene) at a time: most share the previous mesh's
    // origin, which a comparison finds without hashing millions of meshes at start-up.
    let mut last: Option<([u64; 3], u32)> = None;
    let indices = meshes
        .iter()
        .map(|mesh| {
            let key = mesh.origin.to_array().map(f64::to_bits);
            if let Some((last_key, index)) = last {
                if last_key == key {
                    return index;
                }
            }
            let index = *index_of.entry(key).or_insert_with(|| {
                let (high, low) = split_f64(mesh.origin);
                origins.push(CityOrigin {
                    high: [high[0], high[1], high[2], 0.0],
                    low: [low[0], low[1], low[2], 0.0],
                });
                (origins.len() - 1) as u32
            });
            last = Some((key, index));
            index
        })
        .collect();
    (origins, indices)
}

/// `value` as the shaders take an `f64` point: rounded to `f32`, and what that rounding
/// left, also in `f32` (their sum is the point to about 2⁻⁴⁸ of its magnitude).
pub fn split_f64(value: DVec3) -> ([f32; 3], [f32; 3]) {
    let high = value.as_vec3();
    let low = (value - high.as_dvec3()).as_vec3();
    (high.to_array(), low.to_array())
}

/// The engine's vertices of a dataset's flat position, normal and UV arrays (a scene's or a
/// tile's, one entry per vertex).
fn vertices_of<'a>(
    positions: &'a [[f32; 3]],
    normals: &'a [[f32; 3]],
    uvs: &'a [[f32; 2]],
) -> impl Iterator<Item = Vertex> + 'a {
    positions.iter().zip(normals).zip(uvs).map(|((p, n), uv)| Vertex {
        position: *p,
        normal: *n,
        uv: *uv,
    })
}

impl CityMesh {
    /// A dataset's `mesh` (a scene's or a tile's) as drawn from `first_index` of the city's
    /// indices, each plus `vertex_offset`, its texture's full-resolution extent from `info`,
    /// its positions relative to `origin`.
    fn of_dataset_mesh(
        mesh: &citystream_dataset::Mesh,
        first_index: u32,
        vertex_offset: u32,
        info: &citystream_dataset::TextureInfo,
        origin: DVec3,
    ) -> Self {
        CityMesh {
            first_index,
            index_count: mesh.index_count,
            vertex_offset,
            texture: mesh.texture,
            texture_width: info.width(),
            texture_height: info.height(),
            origin,
        }
    }
}

/// A dataset's vertices in the engine's layout and its meshes with their
/// textures' full-resolution extents, as the city passes draw them.
pub fn city_geometry(dataset: &citystream_dataset::Dataset) -> Result<(Vec<Vertex>, Vec<CityMesh>)> {
    let scene = &dataset.scene;
    let vertices = vertices_of(&scene.positions, &scene.normals, &scene.uvs).collect();
    let meshes = scene
        .meshes
        .iter()
        .enumerate()
        .map(|(m, mesh)| {
            let info = dataset
                .textures
                .info(mesh.texture)
                .map_err(|e| EngineError::InvalidRequest(format!("mesh {m} of {}: {e}", dataset.dir().display())))?;
            // The scene's origin is the frame the camera is given in; a mesh at a local
            // origin (a dataset far larger than a city) is drawn relative to it.
            Ok(CityMesh::of_dataset_mesh(
                mesh,
                mesh.first_index,
                mesh.first_vertex,
                info,
                DVec3::from(scene.offset_of(mesh)),
            ))
        })
        .collect::<Result<Vec<_>>>()?;
    Ok((vertices, meshes))
}

/// A tiled scene's geometry (dataset format 4's tiles, docs/DATASET.md) in the engine's
/// layout: `tiles`' vertices and indices one after another (`tiles[i]` the geometry of
/// `tree.tiles[i]`), the meshes in the order of their global ids, each relative to its
/// tile's origin, given as an offset from `frame_origin` (the frame the camera is given in).
/// The vertices' positions stay as the tiles hold them, so a tile keeps an `f32` position's
/// precision around its own origin however far from `frame_origin` it lies.
pub fn tiled_city_geometry(
    tree: &citystream_dataset::tiles::TileTree,
    tiles: &[citystream_dataset::tile_geometry::TileGeometry],
    textures: &citystream_dataset::TexturePack,
    frame_origin: DVec3,
) -> Result<(Vec<Vertex>, Vec<u32>, Vec<CityMesh>)> {
    let invalid = |what: String| EngineError::InvalidRequest(format!("tiled city: {what}"));
    if let Some(what) = citystream_dataset::tiled::geometry_mismatch(tree, tiles) {
        return Err(invalid(what));
    }
    let mesh_count = usize::try_from(tree.mesh_count()).map_err(|_| invalid("too many meshes".into()))?;
    let mut meshes: Vec<Option<CityMesh>> = vec![None; mesh_count];
    let (mut vertices, mut indices) = (Vec::new(), Vec::new());
    for (t, (record, tile)) in tree.tiles.iter().zip(tiles).enumerate() {
        let origin = DVec3::from(record.origin) - frame_origin;
        let vertex_base = vertices.len() as u64;
        let index_base = indices.len() as u64;
        for (i, mesh) in tile.meshes.iter().enumerate() {
            let id = tree.mesh_ids[record.first_mesh as usize + i] as usize;
            let info = textures
                .info(mesh.texture)
                .map_err(|e| invalid(format!("tile {t}'s mesh {id}: {e}")))?;
            let too_big = || invalid("more than 2^32 vertices or indices".into());
            let slot = meshes
                .get_mut(id)
                .ok_or_else(|| invalid(format!("tile {t}'s mesh {id} is past the {mesh_count} meshes")))?;
            *slot = Some(CityMesh::of_dataset_mesh(
                mesh,
                u32::try_from(index_base + u64::from(mesh.first_index)).map_err(|_| too_big())?,
                u32::try_from(vertex_base + u64::from(mesh.first_vertex)).map_err(|_| too_big())?,
                info,
                origin,
            ));
        }
        vertices.extend(vertices_of(&tile.positions, &tile.normals, &tile.uvs));
        indices.extend_from_slice(&tile.indices);
    }
    let meshes = meshes
        .into_iter()
        .enumerate()
        .map(|(id, mesh)| mesh.ok_or_else(|| invalid(format!("no tile holds mesh {id}"))))
        .collect::<Result<Vec<_>>>()?;
    Ok((vertices, indices, meshes))
}

/// A camera: eye, target and vertical field of view; Vulkan clip space with reversed depth
/// and no far plane (depth 1 at the near plane, falling towards 0 at infinity): a float
/// depth buffer then resolves about `distance × 2⁻²³` at every distance, whatever the near
/// plane, where a standard projection resolves `distance² / near × 2⁻²⁴`.
///
/// The eye and target are `f64`: the city passes get the view's rotation and projection
/// alone and the eye split in two `f32`s ([`Camera::eye_split`]), and subtract the eye from
/// each position before rotating it, so precision follows the camera, not the scene's
/// origin (docs/ARCHITECTURE.md, "Numerical choices").
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Eye position in scene units.
    pub eye: DVec3,
    /// Point looked at.
    pub target: DVec3,
    /// Vertical field of view in radians.
    pub fov_y: f32,
    /// Near plane distance ([`near_plane`] chooses one from the scene and the eye).
    pub near: f32,
}

/// The nearest a near plane comes to the eye, metres.
pub const NEAR_PLANE_MIN: f32 = 0.05;
/// The farthest a near plane lies from an eye inside the scene's bounds, metres: there a
/// wall may stand anywhere, so the plane stays close.
pub const NEAR_PLANE_MAX_INSIDE: f32 = 2.0;

/// The near plane for an eye at `eye` over a scene within `low..high`: half the distance to
/// the scene's bounds from outside them (nothing drawn can be nearer), a quarter of the
/// eye's height above the scene's lowest point from inside (at most
/// [`NEAR_PLANE_MAX_INSIDE`]), never under [`NEAR_PLANE_MIN`]. With reversed depth the
/// plane costs no precision; it only has to lie in front of everything drawn, and the
/// farther it lies, the tighter the Hi-Z culling's depth slack is in metres.
pub fn near_plane(eye: DVec3, low: Vec3, high: Vec3) -> f32 {
    if !(eye.is_finite() && low.is_finite() && high.is_finite()) {
        return NEAR_PLANE_MIN;
    }
    let (low, high) = (low.as_dvec3(), high.as_dvec3());
    let distance = (low - eye).max(eye - high).max(DVec3::ZERO).length();
    let near = if distance > 0.0 {
        0.5 * distance
    } else {
        (0.25 * (eye.y - low.y)).min(f64::from(NEAR_PLANE_MAX_INSIDE))
    };
    (near as f32).max(NEAR_PLANE_MIN)
}

impl Camera {
    /// View-projection for `aspect`, with the field of view widened so that tan(fov/2)
    /// grows by `1 + margin` (0 for the visible view), eye translation included: composed
    /// in `f64` and rounded once. For tests on the host and for the passes that take world
    /// positions (culling's boxes, the ground's quad); the city passes take
    /// [`relative_view_projection`](Self::relative_view_projection).
    pub fn view_projection(&self, aspect: f32, margin: f32) -> Mat4 {
        self.view_projection_f64(aspect, margin).as_mat4()
    }

    /// [`view_projection`](Self::view_projection) in `f64`, unrounded: where a host (or a
    /// test) projects a point exactly.
    pub fn view_projection_f64(&self, aspect: f32, margin: f32) -> DMat4 {
        self.projection(aspect, margin) * DMat4::look_at_rh(self.eye, self.target, self.up())
    }

    /// As [`view_projection`](Self::view_projection) for positions relative to the eye:
    /// rotation and projection, no translation.
    pub fn relative_view_projection(&self, aspect: f32, margin: f32) -> Mat4 {
        let look = DMat4::look_at_rh(DVec3::ZERO, self.target - self.eye, self.up());
        (self.projection(aspect, margin) * look).as_mat4()
    }

    /// The eye as two `f32` triples whose sum is it to `f32`'s precision squared: the
    /// rounded eye and what the rounding left.
    pub fn eye_split(&self) -> ([f32; 3], [f32; 3]) {
        split_f64(self.eye)
    }

    fn up(&self) -> DVec3 {
        if (self.target - self.eye).normalize_or_zero().y.abs() > 0.999 {
            DVec3::Z
        } else {
            DVec3::Y
        }
    }

    fn projection(&self, aspect: f32, margin: f32) -> DMat4 {
        let tan = f64::from((self.fov_y * 0.5).tan()) * (1.0 + f64::from(margin.max(0.0)));
        let mut projection =
            DMat4::perspective_infinite_reverse_rh(2.0 * tan.atan(), f64::from(aspect), f64::from(self.near));
        // Vulkan's clip space has y pointing down.
        projection.y_axis.y = -projection.y_axis.y;
        projection
    }
}

/// The push constants of a city pass seeing through `camera` at `aspect` (widened by
/// `margin`): the relative view-projection and the split eye, the rest zero.
fn city_push(camera: &Camera, aspect: f32, margin: f32) -> CityDrawPush {
    let (high, low) = camera.eye_split();
    CityDrawPush {
        view_proj: camera.relative_view_projection(aspect, margin).to_cols_array_2d(),
        eye_high: [high[0], high[1], high[2], 0.0],
        eye_low: [low[0], low[1], low[2], 0.0],
        ..CityDrawPush::default()
    }
}

/// Options of the feedback pass.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FeedbackView {
    /// Widening of tan(fov/2) beyond the visible view (0.25 = 25 % margin).
    pub margin: f32,
    /// Scene distance within which fragments count as foreground: c_w =
    /// min(depth / foreground, 1). The paper's formula assumes units in which
    /// this is 1; city datasets are in metres, so it is a parameter.
    pub foreground_distance: f32,
}

impl FeedbackView {
    /// Visible pixels spanned by one feedback pixel, per axis: the feedback
    /// covers `1 + margin` times the angle with `feedback_height` pixels.
    pub fn pixel_ratio(&self, visible_height: u32, feedback_height: u32) -> f32 {
        (1.0 + self.margin.max(0.0)) * visible_height as f32 / feedback_height.max(1) as f32
    }

    /// Weight a feedback fragment stands for in visible pixels: the weight
    /// τ is defined per visible fragment (paper Table 2), so feedback weights
    /// are scaled by the area one feedback pixel covers, `pixel_ratio²`.
    pub fn fragment_area(&self, visible_height: u32, feedback_height: u32) -> f32 {
        self.pixel_ratio(visible_height, feedback_height).powi(2)
    }
}

impl Default for FeedbackView {
    fn default() -> Self {
        Self {
            margin: 0.25,
            foreground_distance: 200.0,
        }
    }
}

/// Texture ids [`CityRenderer::record_texture_ids`] can draw: id + 1 in three bytes.
const TEXTURE_ID_LIMIT: u32 = (1 << 24) - 1;

/// The texture a pixel of [`CityRenderer::record_texture_ids`]' image shows; `None` where
/// no city mesh covers it.
pub fn texture_of_id_pixel(rgba: [u8; 4]) -> Option<u32> {
    // Ids from TEXTURE_ID_LIMIT on are refused before they are drawn.
    let id = u32::from(rgba[0]) | (u32::from(rgba[1]) << 8) | (u32::from(rgba[2]) << 16);
    id.checked_sub(1)
}

/// The city pipelines (depth pre-pass, feedback, visible, texture ids), the
/// geometry and the mesh table.
#[derive(Debug)]
pub struct CityRenderer {
    device: Arc<Device>,
    depth_prepass: Pipeline,
    feedback: Pipeline,
    visible: Pipeline,
    texture_ids: Pipeline,
    /// The largest texture id any mesh uses.
    max_texture: u32,
    _pool: DescriptorPool,
    prepass_set: vk::DescriptorSet,
    feedback_set: vk::DescriptorSet,
    visible_set: vk::DescriptorSet,
    texture_id_set: vk::DescriptorSet,
    /// Every mesh's vertices, tagged with its id.
    vertices: Buffer,
    /// Every mesh's triangles, in mesh order, indexing `vertices` directly.
    indices: Buffer,
    index_count: u32,
    /// Read by the shaders through the descriptor sets.
    _mesh_info: Buffer,
    /// The distinct local origins of the meshes (`CityOrigin`s).
    origins: Buffer,
    /// Each mesh's index in `origins`.
    mesh_origins: Vec<u32>,
    meshes: Vec<CityMesh>,
    /// GPU culling, once enabled ([`CityRenderer::enable_culling`]).
    culling: Option<CityCulling>,
    /// Whether the passes draw through `culling` (`--culling on`) or draw every mesh.
    culling_on: bool,
}

pub(crate) fn city_pipeline(
    device: &Arc<Device>,
    vertex: shaders::ShaderSource,
    fragment: shaders::ShaderSource,
    bindings: Vec<BindingSpec>,
    depth: DepthMode,
    color_write: bool,
    name: &str,
) -> Result<Pipeline> {
    Pipeline::graphics(
        device,
        &GraphicsDesc {
            vertex,
            fragment,
            vertex_stride: std::mem::size_of::<CityVertex>() as u32,
            attributes: CityVertex::attributes(),
            color_format: COLOR_FORMAT,
            depth_format: DEPTH_FORMAT,
            cull_mode: vk::CullModeFlags::NONE,
            bindings,
            push_constant_size: std::mem::size_of::<CityDrawPush>() as u32,
            depth,
            color_write,
        },
        name,
    )
}

/// A visible pass's pipeline: the city's fragment shader for the device's backing, depth tested
/// and written, colour written; `vertex` places the meshes (the city's own or a texture-atlas
/// tree's).
pub(crate) fn visible_pipeline(
    device: &Arc<Device>,
    vertex: shaders::ShaderSource,
    bindings: Vec<BindingSpec>,
    name: &str,
) -> Result<Pipeline> {
    let fragment = shaders::for_backing(device, shaders::CITY_FRAG, shaders::CITY_FRAG_ARRAYS);
    city_pipeline(device, vertex, fragment, bindings, DepthMode::TestAndWrite, true, name)
}

/// The geometry of one draw for every mesh: each mesh's vertices (the range
/// its indices use) copied and tagged with its id, and its indices made
/// absolute, in mesh order so triangles rasterise in the same order as one
/// draw per mesh would. Meshes sharing vertices get their own copies.
fn single_draw_geometry(
    vertices: &[Vertex],
    indices: &[u32],
    meshes: &[CityMesh],
) -> Result<(Vec<CityVertex>, Vec<u32>)> {
    let (sources, city_indices) = single_draw_layout(vertices.len(), indices, meshes)?;
    let city_vertices = sources
        .iter()
        .map(|&(mesh_id, source)| {
            let v = &vertices[source as usize];
            CityVertex {
                position: v.position,
                normal: v.normal,
                uv: v.uv,
                mesh_id,
            }
        })
        .collect();
    Ok((city_vertices, city_indices))
}

/// A drawn vertex's mesh and the scene vertex it copies.
pub(crate) type VertexSource = (u32, u32);

/// The layout of [`single_draw_geometry`]: per drawn vertex, its mesh and the source
/// vertex it copies; and the drawn indices. Per-vertex data a pass adds (a texture-atlas
/// tree's root-atlas coordinates) is laid out by the same sources.
pub(crate) fn single_draw_layout(
    vertex_count: usize,
    indices: &[u32],
    meshes: &[CityMesh],
) -> Result<(Vec<VertexSource>, Vec<u32>)> {
    let mut sources = Vec::with_capacity(vertex_count);
    let mut city_indices = Vec::with_capacity(indices.len());
    for (id, mesh) in meshes.iter().enumerate() {
        let outside =
            || EngineError::InvalidRequest(format!("mesh {id} refers to indices or vertices outside the city"));
        let first = mesh.first_index as usize;
        let range = indices
            .get(first..first + mesh.index_count as usize)
            .ok_or_else(outside)?;
        let (Some(&low), Some(&high)) = (range.iter().min(), range.iter().max()) else {
            continue;
        };
        let base = u32::try_from(sources.len())
            .ok()
            .filter(|b| b.checked_add(high - low).is_some())
            .ok_or_else(|| EngineError::InvalidRequest("a city of more than 2^32 vertices".into()))?;
        let start = u64::from(mesh.vertex_offset) + u64::from(low);
        let end = u64::from(mesh.vertex_offset) + u64::from(high);
        if end >= vertex_count as u64 {
            return Err(outside());
        }
        sources.extend((start..=end).map(|source| (id as u32, source as u32)));
        city_indices.extend(range.iter().map(|&i| base + (i - low)));
    }
    Ok((sources, city_indices))
}

impl CityRenderer {
    /// Uploads the geometry and builds the passes over `cache` and `compactor`.
    pub fn new(
        device: &Arc<Device>,
        commands: &mut CommandContext,
        vertices: &[Vertex],
        indices: &[u32],
        meshes: Vec<CityMesh>,
        cache: &GpuTextureCache,
        compactor: &FeedbackCompactor,
    ) -> Result<Self> {
        if meshes.is_empty() {
            return Err(EngineError::InvalidRequest("a city needs at least one mesh".into()));
        }
        if meshes.len() as u64 > u64::from(compactor.mesh_count()) {
            return Err(EngineError::InvalidRequest(format!(
                "{} meshes but feedback for {}",
                meshes.len(),
                compactor.mesh_count()
            )));
        }
        for (m, mesh) in meshes.iter().enumerate() {
            let end = u64::from(mesh.first_index) + u64::from(mesh.index_count);
            // Whole triangles only: in the single draw a stray index would
            // shift every later mesh's triangles.
            let in_range = end <= indices.len() as u64
                && mesh.index_count % 3 == 0
                && indices[mesh.first_index as usize..end as usize]
                    .iter()
                    .all(|&i| u64::from(i) + u64::from(mesh.vertex_offset) < vertices.len() as u64);
            if !in_range || cache.texture_data(mesh.texture).is_none() {
                return Err(EngineError::InvalidRequest(format!(
                    "mesh {m} has a partial triangle or refers to indices, vertices or texture {} outside the city",
                    mesh.texture
                )));
            }
        }
        let fragment = vk::ShaderStageFlags::FRAGMENT;
        // The vertex stage reads each mesh's local origin; the fragment stages its texture.
        let vertex = vk::ShaderStageFlags::VERTEX;
        let mesh_stages = vertex | fragment;
        let feedback = city_pipeline(
            device,
            shaders::CITY_VERT,
            shaders::FEEDBACK_FRAG,
            vec![
                (BINDING_TEXTURE_DATA, vk::DescriptorType::STORAGE_BUFFER, 1, fragment),
                (BINDING_FEEDBACK_MESHES, vk::DescriptorType::STORAGE_BUFFER, 1, fragment),
                (BINDING_CITY_MESHES, vk::DescriptorType::STORAGE_BUFFER, 1, mesh_stages),
                (BINDING_CITY_ORIGINS, vk::DescriptorType::STORAGE_BUFFER, 1, vertex),
            ],
            DepthMode::EqualAfterPrepass,
            true,
            "city feedback pipeline",
        )?;
        // Feedback must count only the nearest surface whatever the draw
        // order, so a depth-only pass runs first (early depth testing alone
        // only rejects fragments behind what was drawn before).
        let depth_prepass = city_pipeline(
            device,
            shaders::CITY_VERT,
            shaders::DEPTH_ONLY_FRAG,
            vec![
                (BINDING_CITY_MESHES, vk::DescriptorType::STORAGE_BUFFER, 1, vertex),
                (BINDING_CITY_ORIGINS, vk::DescriptorType::STORAGE_BUFFER, 1, vertex),
            ],
            DepthMode::TestAndWrite,
            false,
            "city depth pre-pass pipeline",
        )?;
        let (origins, mesh_origins) = origin_table(&meshes);
        let mesh_info: Vec<CityMeshInfo> = meshes.iter().zip(&mesh_origins).map(|(m, &o)| m.info(o)).collect();
        let origins = upload_buffer(
            device,
            commands,
            bytemuck::cast_slice(&origins),
            vk::BufferUsageFlags::STORAGE_BUFFER,
            "city local origins",
        )?;
        let max_texture = meshes.iter().map(|m| m.texture).max().unwrap_or(0);
        let mesh_info = upload_buffer(
            device,
            commands,
            bytemuck::cast_slice(&mesh_info),
            vk::BufferUsageFlags::STORAGE_BUFFER,
            "city mesh info",
        )?;
        let mut cache_descriptors = cache.descriptors().to_vec();
        let mesh_descriptors = [
            (BINDING_CITY_MESHES, DescriptorResource::StorageBuffer(mesh_info.raw())),
            (BINDING_CITY_ORIGINS, DescriptorResource::StorageBuffer(origins.raw())),
        ];
        cache_descriptors.extend(mesh_descriptors);
        let visible_bindings: Vec<BindingSpec> = cache_descriptors
            .iter()
            .map(|(binding, resource)| {
                let stages = match *binding {
                    BINDING_CITY_MESHES => mesh_stages,
                    BINDING_CITY_ORIGINS => vertex,
                    _ => fragment,
                };
                (*binding, resource.descriptor_type(), resource.count(), stages)
            })
            .collect();
        let visible = visible_pipeline(device, shaders::CITY_VERT, visible_bindings, "city visible pipeline")?;
        let texture_ids = city_pipeline(
            device,
            shaders::CITY_VERT,
            shaders::TEXTURE_ID_FRAG,
            vec![
                (BINDING_CITY_MESHES, vk::DescriptorType::STORAGE_BUFFER, 1, mesh_stages),
                (BINDING_CITY_ORIGINS, vk::DescriptorType::STORAGE_BUFFER, 1, vertex),
            ],
            DepthMode::TestAndWrite,
            true,
            "city texture id pipeline",
        )?;
        // One pool for all sets: sized by the visible layout, which has the most bindings.
        let pool = DescriptorPool::new(device, &visible, 4, "city descriptors")?;
        let prepass_set = pool.allocate(&depth_prepass, &mesh_descriptors)?;
        let table = cache_descriptors
            .iter()
            .find(|(b, _)| *b == BINDING_TEXTURE_DATA)
            .map(|(_, r)| *r)
            .ok_or_else(|| EngineError::InvalidRequest("the cache offers no texture table".into()))?;
        let feedback_set = pool.allocate(
            &feedback,
            &[
                (BINDING_TEXTURE_DATA, table),
                (
                    BINDING_FEEDBACK_MESHES,
                    DescriptorResource::StorageBuffer(compactor.mesh_feedback_buffer()),
                ),
                mesh_descriptors[0],
                mesh_descriptors[1],
            ],
        )?;
        let visible_set = pool.allocate(&visible, &cache_descriptors)?;
        let texture_id_set = pool.allocate(&texture_ids, &mesh_descriptors)?;
        let (city_vertices, city_indices) = single_draw_geometry(vertices, indices, &meshes)?;
        let index_count = u32::try_from(city_indices.len())
            .map_err(|_| EngineError::InvalidRequest("a city of more than 2^32 indices".into()))?;
        // The indices also in a storage buffer: culling copies those of the meshes a view shows.
        let (vertices, indices) = upload_geometry(
            device,
            commands,
            &city_vertices,
            &city_indices,
            vk::BufferUsageFlags::STORAGE_BUFFER,
            "city",
        )?;
        Ok(Self {
            device: Arc::clone(device),
            depth_prepass,
            prepass_set,
            feedback,
            visible,
            texture_ids,
            max_texture,
            _pool: pool,
            feedback_set,
            visible_set,
            texture_id_set,
            vertices,
            indices,
            index_count,
            _mesh_info: mesh_info,
            origins,
            mesh_origins,
            meshes,
            culling: None,
            culling_on: false,
        })
    }

    /// Prepares GPU culling ([`crate::cull`]) for this renderer's city and turns it on:
    /// `vertices` and `indices` as given to [`new`](Self::new), `slots` the frames in
    /// flight whose statistics are kept apart.
    pub fn enable_culling(
        &mut self,
        commands: &mut CommandContext,
        vertices: &[Vertex],
        indices: &[u32],
        slots: u32,
    ) -> Result<()> {
        let positions = self
            .meshes
            .iter()
            .enumerate()
            .flat_map(|(id, mesh)| {
                let first = mesh.first_index as usize;
                let range = indices.get(first..first + mesh.index_count as usize).unwrap_or(&[]);
                range.iter().filter_map(move |&i| {
                    let v = vertices.get(i as usize + mesh.vertex_offset as usize)?;
                    Some((id as u32, mesh.scene_position(v.position)))
                })
            })
            // Boxes in the scene's frame, each corner rounded outwards to f32 so that a mesh
            // far from the scene's origin is never culled for a rounding.
            .flat_map(|(id, p)| {
                let (low, high) = round_outwards(p);
                [(id, low), (id, high)]
            });
        let bounds = mesh_bounds(positions, self.meshes.len());
        // Each mesh's indices follow the previous mesh's in the single draw's index buffer.
        let mut next = 0u32;
        let ranges: Vec<[u32; 2]> = self
            .meshes
            .iter()
            .map(|mesh| {
                let range = [next, mesh.index_count];
                next += mesh.index_count;
                range
            })
            .collect();
        self.culling = Some(CityCulling::new(
            &self.device,
            commands,
            &bounds,
            &ranges,
            (self.indices.raw(), self.index_count),
            slots,
        )?);
        self.culling_on = true;
        Ok(())
    }

    /// Turns culling on or off (off: every pass draws every mesh, the path without
    /// culling). Turning it on needs [`enable_culling`](Self::enable_culling) first.
    pub fn set_culling(&mut self, on: bool) -> Result<()> {
        if on && self.culling.is_none() {
            return Err(EngineError::InvalidRequest(
                "culling turned on before enable_culling prepared it".into(),
            ));
        }
        self.culling_on = on;
        Ok(())
    }

    /// Whether the passes cull.
    pub fn culling(&self) -> bool {
        self.culling_on
    }

    fn active_culling(&self) -> Option<&CityCulling> {
        self.culling.as_ref().filter(|_| self.culling_on)
    }

    /// Records, before this renderer's next visible pass, a copy of its visible view's
    /// culling state into `other` (a renderer of the same city, such as the error
    /// reference): `other`'s next visible pass then draws the same meshes in the same
    /// phases, so that where both hold the same texels their images agree bit for bit
    /// (depth ties go to the mesh drawn first). Nothing to copy where neither culls.
    pub fn record_share_visible_culling(&self, rec: Recording<'_>, other: &CityRenderer) -> Result<()> {
        match (self.active_culling(), other.active_culling()) {
            (Some(from), Some(into)) => from.record_copy_flags(rec, CullView::Visible, into),
            (None, None) => Ok(()),
            _ => Err(EngineError::InvalidRequest(
                "visible culling shared between a renderer that culls and one that does not".into(),
            )),
        }
    }

    /// Makes the culling recorded next write its statistics into frame slot `slot`
    /// (below the `slots` given to [`enable_culling`](Self::enable_culling)); read them
    /// with [`cull_stats`](Self::cull_stats) once that frame completed.
    pub fn set_cull_slot(&self, slot: u32) -> Result<()> {
        match &self.culling {
            Some(culling) => culling.set_slot(slot),
            None => Ok(()),
        }
    }

    /// What the culling of the frame recorded into `slot` drew, once it completed;
    /// `None` without culling.
    pub fn cull_stats(&self, slot: u32) -> Result<Option<CullStats>> {
        match self.active_culling() {
            Some(culling) => culling.stats(slot).map(Some),
            None => Ok(None),
        }
    }

    /// The meshes drawn.
    pub fn meshes(&self) -> &[CityMesh] {
        &self.meshes
    }

    /// What the city passes know of each mesh, as the renderer uploaded it (its texture and
    /// the index of its local origin in [`origins_buffer`](Self::origins_buffer)).
    pub(crate) fn mesh_infos(&self) -> Vec<CityMeshInfo> {
        self.meshes
            .iter()
            .zip(&self.mesh_origins)
            .map(|(m, &o)| m.info(o))
            .collect()
    }

    /// The `CityOrigin` array the city passes' vertex stage reads.
    pub(crate) fn origins_buffer(&self) -> vk::Buffer {
        self.origins.raw()
    }

    /// Draws every mesh in one draw with `pipeline` (whose vertex input is [`CityVertex`]).
    pub(crate) fn draw_all(&self, rec: Recording<'_>, pipeline: &Pipeline, set: vk::DescriptorSet, base: CityDrawPush) {
        self.draw(rec, pipeline, set, base, None);
    }

    /// Draws the meshes of a culled list (`Some`), or every mesh in one draw.
    fn draw(
        &self,
        rec: Recording<'_>,
        pipeline: &Pipeline,
        set: vk::DescriptorSet,
        base: CityDrawPush,
        list: Option<(&CityCulling, CullView, CullList)>,
    ) {
        let cmd = rec.raw();
        pipeline.bind(rec, set);
        // SAFETY: cmd is recording inside rendering; buffers are live.
        unsafe {
            self.device
                .raw()
                .cmd_bind_vertex_buffers(cmd, 0, &[self.vertices.raw()], &[0]);
            self.device
                .raw()
                .cmd_bind_index_buffer(cmd, self.indices.raw(), 0, vk::IndexType::UINT32);
        }
        pipeline.push(rec, &base);
        match list {
            Some((culling, view, list)) => culling.draw(rec, view, list),
            // SAFETY: the index buffer holds `index_count` indices, each below the
            // vertex count (built by `single_draw_geometry`).
            None => unsafe { self.device.raw().cmd_draw_indexed(cmd, self.index_count, 1, 0, 0, 0) },
        }
    }

    /// Records the feedback pass into `feedback_target` for a visible view
    /// of `visible_height` pixels. Follow it with the compactor's pass.
    pub fn record_feedback(
        &self,
        rec: Recording<'_>,
        feedback_target: &RenderTarget,
        camera: &Camera,
        view: &FeedbackView,
        visible_height: u32,
    ) -> Result<()> {
        self.record_feedback_with(rec, feedback_target, camera, view, visible_height, true)
    }

    /// Records a second feedback pass in the frame, for where the camera will be: as
    /// [`record_feedback`](Self::record_feedback), drawing every mesh (the culling's
    /// history belongs to the view's pass, whose early set this one must not replace).
    /// Follow it with the streamer's prefetch resolve.
    pub fn record_prefetch_feedback(
        &self,
        rec: Recording<'_>,
        feedback_target: &RenderTarget,
        camera: &Camera,
        view: &FeedbackView,
        visible_height: u32,
    ) -> Result<()> {
        self.record_feedback_with(rec, feedback_target, camera, view, visible_height, false)
    }

    fn record_feedback_with(
        &self,
        rec: Recording<'_>,
        feedback_target: &RenderTarget,
        camera: &Camera,
        view: &FeedbackView,
        visible_height: u32,
        cull: bool,
    ) -> Result<()> {
        let cmd = rec.raw();
        let pixels = u64::from(feedback_target.width()) * u64::from(feedback_target.height());
        if pixels > FEEDBACK_MAX_PIXELS {
            return Err(EngineError::InvalidRequest(format!(
                "feedback target of {pixels} pixels exceeds {FEEDBACK_MAX_PIXELS}, beyond which weight sums could overflow"
            )));
        }
        let aspect = feedback_target.width() as f32 / feedback_target.height() as f32;
        let widen = 1.0 + view.margin.max(0.0);
        let pixel_ratio = view.pixel_ratio(visible_height, feedback_target.height());
        let view_proj = camera.view_projection(aspect, view.margin);
        let base = CityDrawPush {
            feedback: [pixel_ratio.log2(), view.foreground_distance.max(1e-6), widen, widen],
            viewport_light: [
                feedback_target.width() as f32,
                feedback_target.height() as f32,
                0.0,
                0.0,
            ],
            ..city_push(camera, aspect, view.margin)
        };
        let clear = [1.0, 0.0, 1.0, 1.0];
        match self.active_culling().filter(|_| cull) {
            Some(culling) => {
                // Two phases over the pre-pass; the feedback pass draws what the late test kept.
                let feedback = CullView::Feedback;
                culling.prepare(feedback, feedback_target)?;
                culling.record_early(rec, &view_proj, feedback);
                feedback_target.begin(&self.device, rec, clear);
                let early = Some((culling, feedback, CullList::Early));
                self.draw(rec, &self.depth_prepass, self.prepass_set, base, early);
                culling.record_late(rec, &view_proj, feedback, feedback_target);
                let late = Some((culling, feedback, CullList::Late));
                self.draw(rec, &self.depth_prepass, self.prepass_set, base, late);
                let unoccluded = Some((culling, feedback, CullList::Unoccluded));
                self.draw(rec, &self.feedback, self.feedback_set, base, unoccluded);
            }
            None => {
                feedback_target.begin(&self.device, rec, clear);
                self.draw_all(rec, &self.depth_prepass, self.prepass_set, base);
                self.draw_all(rec, &self.feedback, self.feedback_set, base);
            }
        }
        // SAFETY: rendering was begun above in the same command buffer.
        unsafe { self.device.raw().cmd_end_rendering(cmd) };
        Ok(())
    }

    /// Records the visible pass into `target` (its read-back copy included).
    /// `colormap_blend` applies Eq. 8; without it the sampled colour is shown
    /// directly (the pop-in comparison of the paper's Fig. 7).
    pub fn record_visible(
        &self,
        rec: Recording<'_>,
        target: &RenderTarget,
        camera: &Camera,
        lighting: f32,
        colormap_blend: bool,
    ) -> Result<()> {
        self.record_visible_with(
            rec,
            target,
            camera,
            lighting,
            colormap_blend,
            &self.visible,
            self.visible_set,
            None,
        )
    }

    /// [`record_visible`](Self::record_visible) with the ground layer's frame slot
    /// `slot` drawn first in the same rendering (the city's walls and roofs hide it; the
    /// imagery covers the city's own ground surfaces). Record the layer's uploads before.
    pub fn record_visible_on_ground(
        &self,
        rec: Recording<'_>,
        target: &RenderTarget,
        camera: &Camera,
        colormap_blend: bool,
        ground: (&GroundLayer, u32),
    ) -> Result<()> {
        self.record_visible_with(
            rec,
            target,
            camera,
            1.0,
            colormap_blend,
            &self.visible,
            self.visible_set,
            Some(ground),
        )
    }

    /// The ground alone as the view shows it: the city's depth, then the ground layer's
    /// frame slot `slot` tested against it (hidden ground keeps the clear colour), into
    /// `target` with its read-back copy. Measures the ground's error apart from the city's.
    pub fn record_ground_only(
        &self,
        rec: Recording<'_>,
        target: &RenderTarget,
        camera: &Camera,
        ground: (&GroundLayer, u32),
    ) -> Result<()> {
        let aspect = target.width() as f32 / target.height() as f32;
        let view_proj = camera.view_projection(aspect, 0.0);
        let base = CityDrawPush {
            viewport_light: [target.width() as f32, target.height() as f32, 0.0, 1.0],
            ..city_push(camera, aspect, 0.0)
        };
        target.begin(&self.device, rec, [0.0, 0.0, 0.0, 1.0]);
        self.draw_all(rec, &self.depth_prepass, self.prepass_set, base);
        let drawn = ground.0.record_draw(rec, ground.1, view_proj);
        target.end_and_copy(&self.device, rec);
        drawn
    }

    /// The texture each pixel of the last visible pass shows, into `target` with its
    /// read-back copy: texture id + 1 in the red, green and blue bytes, 0 where no mesh
    /// covers the pixel (`shaders/texture_id.frag`). With culling on it draws the lists
    /// that pass drew, so call it after [`record_visible`](Self::record_visible) for the
    /// same camera and target size; without culling it draws every mesh. Attributes a
    /// frame's image error to the textures behind it (the flythrough's error causes).
    pub fn record_texture_ids(&self, rec: Recording<'_>, target: &RenderTarget, camera: &Camera) -> Result<()> {
        if self.max_texture >= TEXTURE_ID_LIMIT {
            return Err(EngineError::InvalidRequest(format!(
                "texture ids are drawn in 24 bits; texture {} is beyond them",
                self.max_texture
            )));
        }
        let aspect = target.width() as f32 / target.height() as f32;
        let base = CityDrawPush {
            viewport_light: [target.width() as f32, target.height() as f32, 0.0, 0.0],
            ..city_push(camera, aspect, 0.0)
        };
        let culling = self.active_culling();
        if culling.is_some() {
            // The lists were written by the culling of an earlier submission.
            memory_barrier(
                &self.device,
                rec,
                (vk::PipelineStageFlags2::COMPUTE_SHADER, vk::AccessFlags2::SHADER_WRITE),
                (
                    vk::PipelineStageFlags2::DRAW_INDIRECT | vk::PipelineStageFlags2::INDEX_INPUT,
                    vk::AccessFlags2::INDIRECT_COMMAND_READ | vk::AccessFlags2::INDEX_READ,
                ),
            );
        }
        target.begin(&self.device, rec, [0.0, 0.0, 0.0, 0.0]);
        match culling {
            Some(culling) => {
                for list in [CullList::Early, CullList::Late] {
                    let drawn = Some((culling, CullView::Visible, list));
                    self.draw(rec, &self.texture_ids, self.texture_id_set, base, drawn);
                }
            }
            None => self.draw_all(rec, &self.texture_ids, self.texture_id_set, base),
        }
        target.end_and_copy(&self.device, rec);
        Ok(())
    }

    /// [`record_visible`](Self::record_visible) with another visible pipeline over the
    /// same geometry (a texture-atlas tree's).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn record_visible_with(
        &self,
        rec: Recording<'_>,
        target: &RenderTarget,
        camera: &Camera,
        lighting: f32,
        colormap_blend: bool,
        pipeline: &Pipeline,
        set: vk::DescriptorSet,
        ground: Option<(&GroundLayer, u32)>,
    ) -> Result<()> {
        let aspect = target.width() as f32 / target.height() as f32;
        let direct = if colormap_blend { 0.0 } else { 1.0 };
        let view_proj = camera.view_projection(aspect, 0.0);
        let base = CityDrawPush {
            viewport_light: [target.width() as f32, target.height() as f32, lighting, direct],
            ..city_push(camera, aspect, 0.0)
        };
        let clear = [0.55, 0.7, 0.9, 1.0];
        let culling = self.active_culling();
        if let Some(culling) = culling {
            culling.prepare(CullView::Visible, target)?;
            culling.record_early(rec, &view_proj, CullView::Visible);
        }
        target.begin(&self.device, rec, clear);
        // Ground first: the city's fragments over it then win the depth test early.
        let drawn = ground.map_or(Ok(()), |(layer, slot)| layer.record_draw(rec, slot, view_proj));
        match culling {
            Some(culling) => {
                // What was visible last frame, then what the depth so drawn does not hide.
                let visible = CullView::Visible;
                self.draw(rec, pipeline, set, base, Some((culling, visible, CullList::Early)));
                culling.record_late(rec, &view_proj, visible, target);
                self.draw(rec, pipeline, set, base, Some((culling, visible, CullList::Late)));
            }
            None => self.draw_all(rec, pipeline, set, base),
        }
        target.end_and_copy(&self.device, rec);
        drawn
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_near_plane_follows_the_eye_and_the_scene() {
        let (low, high) = (Vec3::new(0.0, 0.0, 0.0), Vec3::new(1000.0, 100.0, 1000.0));
        // From outside the bounds: half the distance to them.
        assert_eq!(near_plane(DVec3::new(500.0, 300.0, 500.0), low, high), 100.0);
        assert_eq!(near_plane(DVec3::new(-30.0, 50.0, -40.0), low, high), 25.0);
        // From inside: a quarter of the height above the lowest point, at most 2 m.
        assert_eq!(near_plane(DVec3::new(500.0, 1.7, 500.0), low, high), 0.425);
        assert_eq!(
            near_plane(DVec3::new(500.0, 90.0, 500.0), low, high),
            NEAR_PLANE_MAX_INSIDE
        );
        // Never under the least, even on the ground or with bounds that are not finite.
        assert_eq!(near_plane(DVec3::new(500.0, 0.0, 500.0), low, high), NEAR_PLANE_MIN);
        assert_eq!(
            near_plane(DVec3::new(500.0, 0.0, 500.0), Vec3::NAN, high),
            NEAR_PLANE_MIN
        );
    }

    #[test]
    fn the_projection_is_reversed_with_no_far_plane() {
        let camera = Camera {
            eye: DVec3::ZERO,
            target: DVec3::new(0.0, 0.0, -1.0),
            fov_y: 60f32.to_radians(),
            near: 0.5,
        };
        let depth = |distance: f32| {
            let clip = camera.view_projection(1.0, 0.0) * glam::Vec4::new(0.0, 0.0, -distance, 1.0);
            clip.z / clip.w
        };
        assert!((depth(0.5) - 1.0).abs() < 1e-6, "1 at the near plane");
        assert!((depth(1000.0) - 0.0005).abs() < 1e-9, "near / distance beyond it");
        assert!(depth(1.0e9) > 0.0, "still in front at a million kilometres");
        // Half a metre apart at 10 km: more than 8 float steps apart in depth.
        let (a, b) = (depth(10_000.0), depth(10_000.5));
        assert!(a > b && (a - b) / (a * f32::EPSILON) > 8.0, "{a} against {b}");
    }

    #[test]
    fn texture_ids_survive_either_unorm_rounding_and_decode() {
        // texture_id.frag writes byte k as (k + 0.25) / 255 in f32.
        for k in 0..=255u32 {
            let written = (k as f32 + 0.25) / 255.0;
            let scaled = written * 255.0;
            assert_eq!(scaled.round() as u32, k, "round to nearest, byte {k}");
            assert_eq!(scaled.trunc() as u32, k, "round toward zero, byte {k}");
        }
        assert_eq!(texture_of_id_pixel([0, 0, 0, 0]), None);
        assert_eq!(texture_of_id_pixel([1, 0, 0, 255]), Some(0));
        assert_eq!(texture_of_id_pixel([0x35, 0x12, 0x02, 255]), Some(0x02_1235 - 1));
        assert_eq!(texture_of_id_pixel([0xFF, 0xFF, 0xFF, 255]), Some(TEXTURE_ID_LIMIT - 1));
    }

    #[test]
    fn feedback_pixel_ratio_accounts_for_margin_and_resolution() {
        let view = FeedbackView {
            margin: 0.25,
            foreground_distance: 100.0,
        };
        // 360 visible rows over 90 feedback rows, 25 % wider: 1.25 * 4 = 5.
        assert!((view.pixel_ratio(360, 90) - 5.0).abs() < 1e-6);
        assert!((view.fragment_area(360, 90) - 25.0).abs() < 1e-5);
        let exact = FeedbackView { margin: 0.0, ..view };
        assert!((exact.pixel_ratio(128, 128) - 1.0).abs() < 1e-6);
    }

    #[test]
    fn single_draw_geometry_tags_vertices_and_copies_shared_ones() {
        let vertex = |x: f32| Vertex {
            position: [x, 0.0, 0.0],
            ..Vertex::default()
        };
        let vertices: Vec<Vertex> = (0..6).map(|i| vertex(i as f32)).collect();
        let mesh = |first_index, index_count, vertex_offset| CityMesh {
            first_index,
            index_count,
            vertex_offset,
            texture: 0,
            texture_width: 4,
            texture_height: 4,
            origin: DVec3::ZERO,
        };
        // Mesh 1 shares vertices 2..=4 with mesh 0; mesh 2 is empty.
        let indices = [0, 1, 2, 2, 3, 4, 0, 1, 2];
        let meshes = [mesh(0, 6, 0), mesh(6, 3, 2), mesh(9, 0, 0)];
        let (city, drawn) = single_draw_geometry(&vertices, &indices, &meshes).expect("geometry");
        assert_eq!(city.len(), 5 + 3, "mesh 1 gets its own copies");
        assert_eq!(drawn, vec![0, 1, 2, 2, 3, 4, 5, 6, 7]);
        let ids: Vec<u32> = city.iter().map(|v| v.mesh_id).collect();
        assert_eq!(ids, vec![0, 0, 0, 0, 0, 1, 1, 1]);
        // Every drawn triangle has the positions of the original one.
        let original: Vec<f32> = [0, 1, 2, 2, 3, 4, 2, 3, 4].iter().map(|&i| i as f32).collect();
        let rebuilt: Vec<f32> = drawn.iter().map(|&i| city[i as usize].position[0]).collect();
        assert_eq!(rebuilt, original);
    }

    #[test]
    fn max_mip_is_the_coarsest_full_resolution_level() {
        let mesh = |w, h| CityMesh {
            first_index: 0,
            index_count: 3,
            vertex_offset: 0,
            texture: 0,
            texture_width: w,
            texture_height: h,
            origin: DVec3::ZERO,
        };
        assert_eq!(mesh(512, 512).max_mip(), 9);
        assert_eq!(mesh(4, 32).max_mip(), 5);
        assert_eq!(mesh(1, 1).max_mip(), 0);
    }

    /// Pixel coordinates of `clip` in a `size`-pixel-high square view.
    fn pixel(clip: glam::DVec4, size: f64) -> [f64; 2] {
        [
            (clip.x / clip.w * 0.5 + 0.5) * size,
            (clip.y / clip.w * 0.5 + 0.5) * size,
        ]
    }

    #[test]
    fn relative_positions_keep_a_tenth_of_a_pixel_a_thousand_kilometres_out() {
        // A camera 1,000 km from the origin sliding sideways by a millimetre a frame, a
        // vertex 50 m ahead, a 1,000-pixel view. The city passes' arithmetic (f32: the eye
        // split, subtracted before the translation-free matrix) puts the vertex within a
        // hundredth of a pixel of the f64 projection; the whole matrix in f32 (the eye's
        // translation carried through it) misses by pixels and jumps between frames.
        let size = 1000.0;
        let origin = DVec3::new(1.0e6, 30.0, -1.0e6);
        let vertex = (origin + DVec3::new(3.0, -2.0, -50.0)).as_vec3();
        let (mut relative_worst, mut full_worst) = (0.0f64, 0.0f64);
        for frame in 0..100 {
            let eye = origin + DVec3::new(1e-3 * f64::from(frame), 0.0, 0.0);
            let camera = Camera {
                eye,
                target: eye + DVec3::new(0.0, 0.0, -1.0),
                fov_y: 60f32.to_radians(),
                near: 0.5,
            };
            let exact = camera.view_projection_f64(1.0, 0.0);
            let want = pixel(exact * vertex.as_dvec3().extend(1.0), size);
            let (high, low) = camera.eye_split();
            let relative = (vertex - Vec3::from(high)) - Vec3::from(low);
            let got = pixel(
                (camera.relative_view_projection(1.0, 0.0) * relative.extend(1.0)).as_dvec4(),
                size,
            );
            let full = pixel((camera.view_projection(1.0, 0.0) * vertex.extend(1.0)).as_dvec4(), size);
            for axis in 0..2 {
                relative_worst = relative_worst.max((got[axis] - want[axis]).abs());
                full_worst = full_worst.max((full[axis] - want[axis]).abs());
            }
        }
        assert!(relative_worst < 0.01, "{relative_worst} px");
        assert!(
            full_worst > 0.5,
            "the f32 matrix should lose pixels here: {full_worst} px"
        );
    }

    #[test]
    fn the_eye_splits_into_two_floats_that_sum_to_it() {
        let eye = DVec3::new(1_234_567.891_234, -0.000_123_456_7, 6_378_137.123_456_789);
        let camera = Camera {
            eye,
            target: eye + DVec3::X,
            fov_y: 1.0,
            near: 1.0,
        };
        let (high, low) = camera.eye_split();
        let sum = Vec3::from(high).as_dvec3() + Vec3::from(low).as_dvec3();
        assert!((sum - eye).abs().max_element() < 1e-7, "{sum} against {eye}");
        assert_eq!(Vec3::from(high), eye.as_vec3());
    }
}
