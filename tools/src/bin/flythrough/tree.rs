//! The atlas-tree strategy's state: the tree, its visible pass, and what it drew.

use std::sync::Arc;

use anyhow::Result;

use citystream_engine::atlas_tree::AtlasTreeRenderer;
use citystream_engine::city::Camera;
use citystream_engine::commands::{CommandContext, Recording};
use citystream_engine::gpu_types::TEXTURE_SAMPLEABLE;
use citystream_engine::target::RenderTarget;
use citystream_engine::Device;
use citystream_streaming::atlas_tree::{frustum_planes, intersects_frustum, AtlasTree, Block, DrawWith, TreeView};
use citystream_streaming::bench::stats::Stats;
use citystream_streaming::dataset::Dataset;

use super::args::{Args, UNLIMITED_BUDGET_BYTES};
use super::flight::CityGpu;

/// The atlas-tree strategy's state: the tree, its visible pass, and what it drew.
pub(crate) struct TreeRun {
    pub(crate) tree: AtlasTree,
    pub(crate) renderer: AtlasTreeRenderer,
    /// Bytes the ideal block set may take: most of the memory budget, the rest left for
    /// blocks on their way in and out.
    pub(crate) capacity_bytes: u64,
    pub(crate) atlas_mips: u32,
    pub(crate) scene_meshes: u32,
    /// Per frame: nodes drawn with an ancestor's atlas, and blocks in the ideal set.
    pub(crate) fallbacks: Vec<f64>,
    pub(crate) ideal_blocks: Vec<f64>,
    /// Frames whose wanted blocks did not all fit the capacity.
    pub(crate) frames_over_capacity: u64,
}

/// What one tree frame drew.
pub(crate) struct TreeFrame {
    pub(crate) nodes_drawn: u32,
    pub(crate) draw_calls: u32,
}

/// `summary.json`'s `atlas_tree`.
#[derive(Debug, serde::Serialize)]
pub(crate) struct TreeSummary {
    pub(crate) nodes: usize,
    pub(crate) leaves: usize,
    pub(crate) depth: u32,
    pub(crate) atlas_extent: u32,
    pub(crate) capacity_bytes: Option<u64>,
    pub(crate) fallbacks: Stats,
    pub(crate) ideal_blocks: Stats,
    pub(crate) frames_over_capacity: u64,
}

impl TreeRun {
    pub(crate) fn new(
        args: &Args,
        device: &Arc<Device>,
        commands: &mut CommandContext,
        gpu: &CityGpu,
        dataset: &Dataset,
        tree: AtlasTree,
    ) -> Result<Self> {
        let renderer = AtlasTreeRenderer::new(
            device,
            commands,
            &gpu.renderer,
            &dataset.scene.indices,
            &tree,
            gpu.streamer.cache(),
            args.frames_in_flight,
        )?;
        let atlas_mips = dataset.textures.info(tree.nodes[0].atlas)?.mip_count();
        let budget = args.memory_budget_mb.bytes().unwrap_or(UNLIMITED_BUDGET_BYTES);
        eprintln!(
            "atlas tree: {} nodes, {} leaves, depth {}, {}² atlases",
            tree.nodes.len(),
            tree.nodes.iter().filter(|n| n.is_leaf()).count(),
            tree.depth(),
            tree.params.atlas_extent
        );
        Ok(Self {
            renderer,
            capacity_bytes: budget / 8 * 7,
            atlas_mips,
            scene_meshes: dataset.scene.meshes.len() as u32,
            tree,
            fallbacks: Vec::new(),
            ideal_blocks: Vec::new(),
            frames_over_capacity: 0,
        })
    }

    /// The view the traversal sees: the camera's frustum, the run's screen height, the
    /// texel-per-pixel ratio the tree was built for.
    pub(crate) fn view(&self, camera: &Camera, width: u32, height: u32) -> TreeView {
        let aspect = width as f32 / height as f32;
        TreeView {
            eye: camera.eye.to_array(),
            planes: frustum_planes(camera.view_projection(aspect, 0.0).to_cols_array_2d()),
            screen_height: height as f32,
            fov_y: camera.fov_y,
            texel_per_pixel: self.tree.params.texel_per_pixel,
        }
    }

    /// One frame: choose nodes by distance among the resident blocks (§4, §6), write the
    /// choice into frame slot `slot`'s tables, hand the loader the ideal block set for the
    /// next frame, and record the visible pass.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn record_frame(
        &mut self,
        rec: Recording<'_>,
        slot: u32,
        gpu: &mut CityGpu,
        dataset: &Dataset,
        target: &RenderTarget,
        camera: &Camera,
        ground: Option<&citystream_engine::ground::GroundLayer>,
    ) -> Result<TreeFrame> {
        let view = self.view(camera, target.width(), target.height());
        let tree = &self.tree;
        let streamer = &gpu.streamer;
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
                    .all(|m| sampleable_from(dataset.scene.meshes[m as usize].texture, 0))
            }
        };
        let selection = tree.select(&view, resident);
        let draws = self.renderer.write_selection(slot, &selection)?;
        // Draws of a renderer binding one texture per draw: one per atlas drawn, one per
        // original texture (mesh) of the leaves drawn with theirs that is in view.
        let original_draws = selection
            .draws
            .iter()
            .filter(|(_, with)| *with == DrawWith::Originals)
            .map(|&(n, _)| {
                let node = &tree.nodes[n as usize];
                (node.first_mesh..node.first_mesh + node.mesh_count)
                    .filter(|&m| intersects_frustum(&dataset.scene.meshes[m as usize].bounds, &view.planes))
                    .count() as u32
            })
            .sum::<u32>();
        let textures = &dataset.textures;
        let block_bytes = |block: Block, level: u32| match block {
            Block::Atlas(n) => textures
                .info(tree.nodes[n as usize].atlas)
                .map(|info| (level..info.mip_count()).map(|l| info.mip_len(l)).sum())
                .unwrap_or(0),
            Block::Originals(n) => {
                let node = &tree.nodes[n as usize];
                (node.first_mesh..node.first_mesh + node.mesh_count)
                    .filter_map(|m| textures.info(dataset.scene.meshes[m as usize].texture).ok())
                    .map(|info| info.chain_len())
                    .sum()
            }
        };
        let paging = tree.paging_within(
            &view,
            self.capacity_bytes,
            block_bytes,
            self.scene_meshes,
            self.atlas_mips,
        );
        self.frames_over_capacity += u64::from(paging.over_capacity > 0);
        self.ideal_blocks.push(paging.ideal.len() as f64);
        gpu.streamer.set_host_records(paging.records)?;
        self.renderer
            .record_visible(rec, slot, &gpu.renderer, target, camera, true, ground)?;
        let nodes_drawn = selection.draws.len() as u32;
        self.fallbacks.push(f64::from(selection.fallbacks));
        Ok(TreeFrame {
            nodes_drawn,
            draw_calls: draws.atlas_draws + original_draws,
        })
    }

    pub(crate) fn summary(&self, budget: Option<u64>) -> TreeSummary {
        TreeSummary {
            nodes: self.tree.nodes.len(),
            leaves: self.tree.nodes.iter().filter(|n| n.is_leaf()).count(),
            depth: self.tree.depth(),
            atlas_extent: self.tree.params.atlas_extent,
            capacity_bytes: budget.map(|_| self.capacity_bytes),
            fallbacks: Stats::from_samples(&self.fallbacks),
            ideal_blocks: Stats::from_samples(&self.ideal_blocks),
            frames_over_capacity: self.frames_over_capacity,
        }
    }
}
