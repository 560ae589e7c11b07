//! The atlas-tree strategy of a flythrough: the engine's [`AtlasTreeStreamer`] and what the
//! run measures of it.

use std::sync::Arc;

use anyhow::Result;

use citystream_dataset::Dataset;
use citystream_engine::atlas_tree::{AtlasTreeStreamer, TreeFrame};
use citystream_engine::city::Camera;
use citystream_engine::commands::{CommandContext, Recording};
use citystream_engine::ground::GroundLayer;
use citystream_engine::stream::Frame;
use citystream_engine::target::RenderTarget;
use citystream_streaming::atlas_tree::AtlasTree;
use citystream_streaming::bench::stats::Stats;

use super::args::{Args, UNLIMITED_BUDGET_BYTES};
use super::city_gpu::CityGpu;

/// The atlas-tree strategy and, per frame, what it chose.
pub(crate) struct TreeRun {
    pub(crate) strategy: AtlasTreeStreamer,
    /// Per frame: nodes drawn with an ancestor's atlas, and blocks in the ideal set.
    fallbacks: Vec<f64>,
    ideal_blocks: Vec<f64>,
    /// Frames whose wanted blocks did not all fit the capacity.
    frames_over_capacity: u64,
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
    /// The strategy over `gpu`'s city and streamer, paging within most of the memory budget
    /// (an eighth left for blocks on their way in and out).
    pub(crate) fn new(
        args: &Args,
        commands: &mut CommandContext,
        gpu: &CityGpu,
        dataset: &Arc<Dataset>,
        tree: AtlasTree,
    ) -> Result<Self> {
        eprintln!(
            "atlas tree: {} nodes, {} leaves, depth {}, {}² atlases",
            tree.nodes.len(),
            tree.nodes.iter().filter(|n| n.is_leaf()).count(),
            tree.depth(),
            tree.params.atlas_extent
        );
        let budget = args.memory_budget_mb().bytes().unwrap_or(UNLIMITED_BUDGET_BYTES);
        let strategy = AtlasTreeStreamer::new(
            commands,
            &gpu.renderer,
            &gpu.streamer,
            Arc::clone(dataset),
            tree,
            budget / 8 * 7,
        )?;
        Ok(Self {
            strategy,
            fallbacks: Vec::new(),
            ideal_blocks: Vec::new(),
            frames_over_capacity: 0,
        })
    }

    /// One frame of the strategy ([`AtlasTreeStreamer::record_frame`]), counted.
    pub(crate) fn record_frame(
        &mut self,
        rec: Recording<'_>,
        frame: &Frame,
        gpu: &mut CityGpu,
        (target, camera): (&RenderTarget, &Camera),
        ground: Option<&GroundLayer>,
    ) -> Result<TreeFrame> {
        let drawn = self
            .strategy
            .record_frame(rec, frame, &mut gpu.streamer, &gpu.renderer, target, camera, ground)?;
        self.fallbacks.push(f64::from(drawn.fallbacks));
        self.ideal_blocks.push(f64::from(drawn.ideal_blocks));
        self.frames_over_capacity += u64::from(drawn.over_capacity);
        Ok(drawn)
    }

    pub(crate) fn summary(&self, budget: Option<u64>) -> TreeSummary {
        let tree = self.strategy.tree();
        TreeSummary {
            nodes: tree.nodes.len(),
            leaves: tree.nodes.iter().filter(|n| n.is_leaf()).count(),
            depth: tree.depth(),
            atlas_extent: tree.params.atlas_extent,
            capacity_bytes: budget.map(|_| self.strategy.capacity_bytes()),
            fallbacks: Stats::from_samples(&self.fallbacks),
            ideal_blocks: Stats::from_samples(&self.ideal_blocks),
            frames_over_capacity: self.frames_over_capacity,
        }
    }
}
