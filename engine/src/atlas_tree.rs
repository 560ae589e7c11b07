//! Drawing a texture-atlas tree (`docs/ATLAS_TREE.md`): the city's one draw, in which every
//! mesh samples either its original texture or the atlas of the node chosen for it this
//! frame ([`citystream_streaming::atlas_tree::AtlasTree::select`]).
//!
//! A per-draw renderer would bind each chosen node's atlas and draw its triangles; here, as
//! in the feedback strategy's passes, one draw covers every mesh and the choice travels as
//! a per-mesh table (texture and texture matrix) written each frame into that frame slot's
//! buffers. Atlas coordinates come per vertex from a buffer laid out like the vertex
//! buffer, so the vertex format is the city passes' own.
//!
//! [`AtlasTreeStreamer`] is the whole strategy beside a [`TextureStreamer`]: per frame the
//! traversal, the tables, the paging's records for the loader and the visible pass.

use std::sync::Arc;

use ash::vk;
use citystream_dataset::Dataset;
use citystream_streaming::atlas_tree::{
    frustum_planes, intersects_frustum, AtlasTree, Block, DrawWith, Selection, TreeView,
};
use citystream_streaming::source::MipSource;
use gpu_allocator::MemoryLocation;

use crate::buffer::{Buffer, BufferDesc};
use crate::city::{single_draw_layout, visible_pipeline, Camera, CityRenderer};
use crate::commands::{CommandContext, Recording};
use crate::device::Device;
use crate::error::{EngineError, Result};
use crate::gpu_types::{
    CityMeshInfo, BINDING_CITY_MESHES, BINDING_CITY_ORIGINS, BINDING_TREE_ATLAS_UVS, BINDING_TREE_UV_TRANSFORMS,
    TEXTURE_SAMPLEABLE,
};
use crate::ground::GroundLayer;
use crate::pipeline::{BindingSpec, DescriptorPool, DescriptorResource, Pipeline};
use crate::scene::upload_buffer;
use crate::shaders;
use crate::stream::{Frame, TextureStreamer};
use crate::target::RenderTarget;
use crate::texture_cache::GpuTextureCache;

/// One frame slot's per-mesh tables and the descriptor set that reads them.
struct TreeSlot {
    set: vk::DescriptorSet,
    mesh_info: Buffer,
    uv_transforms: Buffer,
}

/// The visible pass of a texture-atlas tree over a [`CityRenderer`]'s geometry.
pub struct AtlasTreeRenderer {
    pipeline: Pipeline,
    _pool: DescriptorPool,
    slots: Vec<TreeSlot>,
    /// Read by the vertex stage through every slot's set.
    _atlas_uvs: Buffer,
    /// Each mesh's own texture, as the feedback strategy draws it.
    originals: Vec<CityMeshInfo>,
    /// Per node: its atlas and texture matrix.
    atlases: Vec<(CityMeshInfo, [f32; 4])>,
    /// Per node: the meshes of the leaves under it, as a range of `subtree_meshes`.
    subtree_ranges: Vec<std::ops::Range<u32>>,
    subtree_meshes: Vec<u32>,
    /// This frame's tables, written into a slot's buffers.
    infos: Vec<CityMeshInfo>,
    transforms: Vec<[f32; 4]>,
}

debug_fields!(AtlasTreeRenderer {
    meshes = |s| s.originals.len(),
    nodes = |s| s.atlases.len(),
    slots = |s| s.slots.len(),
});

/// What a selection draws, counted as a renderer that binds one texture per draw would
/// draw it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TreeDraws {
    /// Nodes drawn with an atlas (their own or a resident ancestor's).
    pub atlas_draws: u32,
    /// Leaves drawn with their original textures.
    pub original_leaves: u32,
}

impl AtlasTreeRenderer {
    /// Builds the pass for `tree` over `city` (built from the tree's dataset: its meshes are
    /// the scene's, `indices` the scene's indices, `vertex_count` its vertices), with one
    /// set of per-mesh tables per frame in flight. Every node's atlas must be a texture of
    /// `cache`.
    pub fn new(
        device: &Arc<Device>,
        commands: &mut CommandContext,
        city: &CityRenderer,
        indices: &[u32],
        tree: &AtlasTree,
        cache: &GpuTextureCache,
        frames_in_flight: u32,
    ) -> Result<Self> {
        let meshes = city.meshes();
        let invalid = |what: String| EngineError::InvalidRequest(format!("atlas tree: {what}"));
        if tree.nodes.is_empty() {
            return Err(invalid("no nodes".into()));
        }
        let extent = tree.params.atlas_extent;
        let atlas_info = |atlas: u32| CityMeshInfo {
            texture_id: atlas,
            texture_width: extent,
            texture_height: extent,
            max_mip: extent.max(1).ilog2(),
            // Each mesh keeps its own origin (`write_selection`).
            ..CityMeshInfo::default()
        };
        let mut atlases = Vec::with_capacity(tree.nodes.len());
        for (n, node) in tree.nodes.iter().enumerate() {
            // What `AtlasTree::decode` checks of a file, for trees built in code too: the
            // walk below relies on children after their parent and in range.
            let children_end = u64::from(node.first_child) + u64::from(node.child_count);
            if node.child_count > 0 && (node.first_child as usize <= n || children_end > tree.nodes.len() as u64) {
                return Err(invalid(format!(
                    "node {n}'s children {}..{children_end} are not after it within the {} nodes",
                    node.first_child,
                    tree.nodes.len()
                )));
            }
            // Scale 0 means "own texture coordinates" to the vertex stage.
            if !(node.uv_scale.is_finite() && node.uv_scale > 0.0) {
                return Err(invalid(format!(
                    "node {n}'s texture matrix has scale {}",
                    node.uv_scale
                )));
            }
            if cache.texture_data(node.atlas).is_none() {
                return Err(invalid(format!(
                    "node {n}'s atlas {} is not a texture of the cache",
                    node.atlas
                )));
            }
            if node.is_leaf() && node.first_mesh as u64 + node.mesh_count as u64 > meshes.len() as u64 {
                return Err(invalid(format!(
                    "leaf {n} has meshes beyond the city's {}",
                    meshes.len()
                )));
            }
            atlases.push((
                atlas_info(node.atlas),
                [node.uv_scale, node.uv_offset[0], node.uv_offset[1], 0.0],
            ));
        }
        // Each node's leaf meshes, as one contiguous run per node: children's runs are
        // nested in their parent's when leaves are listed depth first.
        let mut subtree_meshes = Vec::new();
        let mut subtree_ranges = vec![0..0; tree.nodes.len()];
        let mut stack = vec![(0u32, false)];
        let mut starts = vec![0u32; tree.nodes.len()];
        while let Some((n, done)) = stack.pop() {
            let node = &tree.nodes[n as usize];
            if done {
                subtree_ranges[n as usize] = starts[n as usize]..subtree_meshes.len() as u32;
                continue;
            }
            starts[n as usize] = subtree_meshes.len() as u32;
            stack.push((n, true));
            if node.is_leaf() {
                subtree_meshes.extend(node.first_mesh..node.first_mesh + node.mesh_count);
            } else {
                stack.extend(node.children().rev().map(|c| (c, false)));
            }
        }
        let (sources, _) = single_draw_layout(tree.atlas_uvs.len(), indices, meshes)?;
        let drawn_uvs: Vec<[f32; 2]> = sources
            .iter()
            .map(|&(_, source)| tree.atlas_uvs[source as usize])
            .collect();
        let atlas_uvs = upload_buffer(
            device,
            commands,
            bytemuck::cast_slice(if drawn_uvs.is_empty() {
                &[[0.0f32; 2]][..]
            } else {
                &drawn_uvs
            }),
            vk::BufferUsageFlags::STORAGE_BUFFER,
            "atlas tree vertex coordinates",
        )?;
        let fragment = vk::ShaderStageFlags::FRAGMENT;
        let vertex = vk::ShaderStageFlags::VERTEX;
        let mut bindings: Vec<BindingSpec> = cache
            .descriptors()
            .iter()
            .map(|(binding, resource)| (*binding, resource.descriptor_type(), resource.count(), fragment))
            .collect();
        // The vertex stage reads each mesh's local origin; the fragment stage its texture.
        bindings.push((
            BINDING_CITY_MESHES,
            vk::DescriptorType::STORAGE_BUFFER,
            1,
            vertex | fragment,
        ));
        bindings.push((BINDING_CITY_ORIGINS, vk::DescriptorType::STORAGE_BUFFER, 1, vertex));
        bindings.push((BINDING_TREE_ATLAS_UVS, vk::DescriptorType::STORAGE_BUFFER, 1, vertex));
        bindings.push((
            BINDING_TREE_UV_TRANSFORMS,
            vk::DescriptorType::STORAGE_BUFFER,
            1,
            vertex,
        ));
        let pipeline = visible_pipeline(device, shaders::CITY_TREE_VERT, bindings, "atlas tree visible pipeline")?;
        let slot_count = frames_in_flight.max(1);
        let pool = DescriptorPool::new(device, &pipeline, slot_count, "atlas tree descriptors")?;
        let table_bytes = |stride: usize| (stride * meshes.len().max(1)) as u64;
        let mut slots = Vec::with_capacity(slot_count as usize);
        for slot in 0..slot_count {
            let host_buffer = |bytes: u64, name: String| {
                Buffer::new(
                    device,
                    BufferDesc {
                        size: bytes,
                        usage: vk::BufferUsageFlags::STORAGE_BUFFER,
                        location: MemoryLocation::CpuToGpu,
                    },
                    &name,
                )
            };
            let mesh_info = host_buffer(
                table_bytes(std::mem::size_of::<CityMeshInfo>()),
                format!("atlas tree mesh textures (slot {slot})"),
            )?;
            let uv_transforms = host_buffer(
                table_bytes(std::mem::size_of::<[f32; 4]>()),
                format!("atlas tree texture matrices (slot {slot})"),
            )?;
            let mut resources = cache.descriptors().to_vec();
            resources.extend([
                (BINDING_CITY_MESHES, DescriptorResource::StorageBuffer(mesh_info.raw())),
                // The city's own: it draws the tree's meshes, so it outlives these sets' use.
                (
                    BINDING_CITY_ORIGINS,
                    DescriptorResource::StorageBuffer(city.origins_buffer()),
                ),
                (
                    BINDING_TREE_ATLAS_UVS,
                    DescriptorResource::StorageBuffer(atlas_uvs.raw()),
                ),
                (
                    BINDING_TREE_UV_TRANSFORMS,
                    DescriptorResource::StorageBuffer(uv_transforms.raw()),
                ),
            ]);
            let set = pool.allocate(&pipeline, &resources)?;
            slots.push(TreeSlot {
                set,
                mesh_info,
                uv_transforms,
            });
        }
        let originals = city.mesh_infos();
        Ok(Self {
            pipeline,
            _pool: pool,
            slots,
            _atlas_uvs: atlas_uvs,
            originals,
            atlases,
            subtree_ranges,
            subtree_meshes,
            infos: Vec::new(),
            transforms: Vec::new(),
        })
    }

    /// Writes `selection` (of the tree this pass was built for) into frame slot `slot`'s
    /// tables: each drawn node's leaf meshes get the atlas it is drawn with, or their own
    /// textures; meshes under no draw (culled) the root's atlas. The slot's last frame must
    /// have completed (as after [`crate::stream::TextureStreamer::begin_frame`] returned it).
    pub fn write_selection(&mut self, slot: u32, selection: &Selection) -> Result<TreeDraws> {
        let mut draws = TreeDraws::default();
        let (root_info, root_transform) = self.atlases[0];
        // A mesh drawn with an atlas keeps its own origin: its vertices are relative to it.
        let with_origin = |info: CityMeshInfo, original: &CityMeshInfo| CityMeshInfo {
            origin: original.origin,
            ..info
        };
        self.infos.clear();
        self.infos
            .extend(self.originals.iter().map(|original| with_origin(root_info, original)));
        self.transforms.clear();
        self.transforms.resize(self.originals.len(), root_transform);
        for &(n, with) in &selection.draws {
            let range =
                self.subtree_ranges.get(n as usize).cloned().ok_or_else(|| {
                    EngineError::InvalidRequest(format!("atlas tree: drawn node {n} is not in the tree"))
                })?;
            let meshes = &self.subtree_meshes[range.start as usize..range.end as usize];
            match with {
                DrawWith::Atlas(a) => {
                    let (info, transform) = *self.atlases.get(a as usize).ok_or_else(|| {
                        EngineError::InvalidRequest(format!("atlas tree: node {n} drawn with the atlas of node {a}"))
                    })?;
                    for &m in meshes {
                        self.infos[m as usize] = with_origin(info, &self.originals[m as usize]);
                        self.transforms[m as usize] = transform;
                    }
                    draws.atlas_draws += 1;
                }
                DrawWith::Originals => {
                    for &m in meshes {
                        self.infos[m as usize] = self.originals[m as usize];
                        self.transforms[m as usize] = [0.0; 4];
                    }
                    draws.original_leaves += 1;
                }
            }
        }
        let tables = self
            .slots
            .get_mut(slot as usize)
            .ok_or_else(|| EngineError::InvalidRequest(format!("atlas tree: frame slot {slot} out of range")))?;
        if !self.infos.is_empty() {
            tables.mesh_info.write(0, &self.infos)?;
            tables.uv_transforms.write(0, &self.transforms)?;
        }
        Ok(draws)
    }

    /// Records the visible pass of frame slot `slot` (as written by
    /// [`write_selection`](Self::write_selection)) over `city`'s geometry into `target`,
    /// its read-back copy included; lighting and blending as
    /// [`CityRenderer::record_visible`], with the ground layer's same frame slot drawn
    /// first where `ground` is given.
    #[allow(clippy::too_many_arguments)]
    pub fn record_visible(
        &self,
        rec: Recording<'_>,
        slot: u32,
        city: &CityRenderer,
        target: &RenderTarget,
        camera: &Camera,
        colormap_blend: bool,
        ground: Option<&GroundLayer>,
    ) -> Result<()> {
        let tables = self
            .slots
            .get(slot as usize)
            .ok_or_else(|| EngineError::InvalidRequest(format!("atlas tree: frame slot {slot} out of range")))?;
        city.record_visible_with(
            rec,
            target,
            camera,
            1.0,
            colormap_blend,
            &self.pipeline,
            tables.set,
            ground.map(|layer| (layer, slot)),
        )
    }
}

/// The texture-atlas tree as a streaming strategy (`docs/ATLAS_TREE.md`): the tree, its
/// visible pass, and per frame the paper's traversal (§4: nodes chosen by distance among
/// the resident blocks) and §6 paging (the ideal block set within a capacity, handed to a
/// [`TextureStreamer`]'s loader as host records in place of feedback).
///
/// Contract of the records: those chosen for frame N's view are handed to the loader by
/// frame N + 1's [`TextureStreamer::begin_frame`] (as feedback is, `frames_in_flight`
/// frames later), so the strategy's loads trail its view by one frame.
pub struct AtlasTreeStreamer {
    tree: AtlasTree,
    renderer: AtlasTreeRenderer,
    dataset: Arc<Dataset>,
    capacity_bytes: u64,
    /// Levels of the atlases (one extent for the whole tree).
    atlas_mips: u32,
}

debug_fields!(AtlasTreeStreamer {
    renderer,
    capacity_bytes
});

/// What one frame of an [`AtlasTreeStreamer`] chose and drew.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TreeFrame {
    /// Nodes drawn.
    pub nodes_drawn: u32,
    /// Draws of a renderer binding one texture per draw: one per atlas drawn, one per
    /// original texture (mesh) in view of the leaves drawn with theirs.
    pub draw_calls: u32,
    /// Nodes drawn with an ancestor's atlas, their own not resident.
    pub fallbacks: u32,
    /// Blocks in the ideal set handed to the loader.
    pub ideal_blocks: u32,
    /// The ideal set did not all fit the capacity.
    pub over_capacity: bool,
}

impl AtlasTreeStreamer {
    /// The strategy for `tree`, built from `dataset` (whose scene `city` renders and whose
    /// textures, atlases included, `streamer` streams), paging at most `capacity_bytes` of
    /// blocks (the rest of the budget is room for blocks on their way in and out).
    pub fn new<S: MipSource + 'static>(
        commands: &mut CommandContext,
        city: &CityRenderer,
        streamer: &TextureStreamer<S>,
        dataset: Arc<Dataset>,
        tree: AtlasTree,
        capacity_bytes: u64,
    ) -> Result<Self> {
        let renderer = AtlasTreeRenderer::new(
            streamer.device(),
            commands,
            city,
            &dataset.scene.indices,
            &tree,
            streamer.cache(),
            streamer.frames_in_flight(),
        )?;
        let atlas_mips = dataset
            .textures
            .info(tree.nodes[0].atlas)
            .map_err(|e| EngineError::InvalidRequest(format!("atlas tree: the root's atlas: {e}")))?
            .mip_count();
        Ok(Self {
            tree,
            renderer,
            dataset,
            capacity_bytes,
            atlas_mips,
        })
    }

    /// The tree.
    pub fn tree(&self) -> &AtlasTree {
        &self.tree
    }

    /// The bytes of blocks the paging keeps within.
    pub fn capacity_bytes(&self) -> u64 {
        self.capacity_bytes
    }

    /// The view the traversal sees: `camera`'s frustum, the screen height, the
    /// texel-per-pixel ratio the tree was built for.
    pub fn view(&self, camera: &Camera, width: u32, height: u32) -> TreeView {
        let aspect = width as f32 / height as f32;
        TreeView {
            eye: camera.eye.as_vec3().to_array(),
            planes: frustum_planes(camera.view_projection(aspect, 0.0).to_cols_array_2d()),
            screen_height: height as f32,
            fov_y: camera.fov_y,
            texel_per_pixel: self.tree.params.texel_per_pixel,
        }
    }

    /// One frame for `camera` into `target`: chooses nodes by distance among the blocks
    /// `streamer` holds, writes the choice into `frame`'s tables, hands the loader the
    /// ideal block set (loaded from the next frame on: see the type's docs) and records the
    /// visible pass (over the ground layer's same frame slot where `ground` is given).
    #[allow(clippy::too_many_arguments)]
    pub fn record_frame<S: MipSource + 'static>(
        &mut self,
        rec: Recording<'_>,
        frame: &Frame,
        streamer: &mut TextureStreamer<S>,
        city: &CityRenderer,
        target: &RenderTarget,
        camera: &Camera,
        ground: Option<&GroundLayer>,
    ) -> Result<TreeFrame> {
        let view = self.view(camera, target.width(), target.height());
        let tree = &self.tree;
        let scene = &self.dataset.scene;
        let textures = &self.dataset.textures;
        let sampleable_from = |texture: u32, level: u32| {
            streamer
                .texture_data(texture)
                .is_some_and(|d| d.state == TEXTURE_SAMPLEABLE && d.lowest_mip <= level)
        };
        // An atlas counts as resident once any level of it is: the cache holds atlases
        // partially, refining from the coarsest level as the loader brings the finer ones
        // (the paper pages whole atlases), and a node's own atlas at a coarser level than
        // its distance needs still shows more than an ancestor's, which covers four times
        // the ground per level up. A leaf's originals count once every one is whole.
        let resident = |block: Block| match block {
            Block::Atlas(n) => sampleable_from(tree.nodes[n as usize].atlas, u32::MAX),
            Block::Originals(n) => {
                let node = &tree.nodes[n as usize];
                (node.first_mesh..node.first_mesh + node.mesh_count)
                    .all(|m| sampleable_from(scene.meshes[m as usize].texture, 0))
            }
        };
        let selection = tree.select(&view, resident);
        let draws = self.renderer.write_selection(frame.slot(), &selection)?;
        let original_draws = selection
            .draws
            .iter()
            .filter(|(_, with)| *with == DrawWith::Originals)
            .map(|&(n, _)| {
                let node = &tree.nodes[n as usize];
                (node.first_mesh..node.first_mesh + node.mesh_count)
                    .filter(|&m| intersects_frustum(&scene.meshes[m as usize].bounds, &view.planes))
                    .count() as u32
            })
            .sum::<u32>();
        let block_bytes = |block: Block, level: u32| match block {
            Block::Atlas(n) => textures
                .info(tree.nodes[n as usize].atlas)
                .map(|info| (level..info.mip_count()).map(|l| info.mip_len(l)).sum())
                .unwrap_or(0),
            Block::Originals(n) => {
                let node = &tree.nodes[n as usize];
                (node.first_mesh..node.first_mesh + node.mesh_count)
                    .filter_map(|m| textures.info(scene.meshes[m as usize].texture).ok())
                    .map(|info| info.chain_len())
                    .sum()
            }
        };
        let paging = tree.paging_within(
            &view,
            self.capacity_bytes,
            block_bytes,
            scene.meshes.len() as u32,
            self.atlas_mips,
        );
        let ideal_blocks = paging.ideal.len() as u32;
        let over_capacity = paging.over_capacity > 0;
        streamer.set_host_records(paging.records)?;
        self.renderer
            .record_visible(rec, frame.slot(), city, target, camera, true, ground)?;
        Ok(TreeFrame {
            nodes_drawn: selection.draws.len() as u32,
            draw_calls: draws.atlas_draws + original_draws,
            fallbacks: selection.fallbacks,
            ideal_blocks,
            over_capacity,
        })
    }
}
