//! The GPU side of a city: the streamer over the dataset with the city passes that draw
//! with it, and the targets they draw into; what the flight (its streamer as the options
//! ask for it), the error reference, the atlas-tree run and the pop-in measurement each
//! set up.

use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context, Result};

use citystream_dataset::Dataset;
use citystream_engine::city::{CityMesh, CityRenderer, FeedbackView};
use citystream_engine::commands::CommandContext;
use citystream_engine::gpu_types::Vertex;
use citystream_engine::pipeline::Filtering;
use citystream_engine::stream::{StreamConfig, TextureStreamer};
use citystream_engine::target::RenderTarget;
use citystream_engine::texture_cache::Eviction;
use citystream_engine::Device;
use citystream_streaming::atlas_tree::AtlasTree;
use citystream_streaming::disk_model::DiskModel;
use citystream_streaming::loader::LoaderOptions;
use citystream_streaming::records::DEFAULT_WEIGHT_CUTOFF;
use citystream_streaming::source::{DatasetSource, FaultPlan, FaultySource};

use super::args::{Args, Clock, Culling, Prefetch, UNLIMITED_BUDGET_BYTES};
use super::controller::build_policy;

/// A streamer over the dataset and the city passes that draw with it.
pub(crate) struct CityGpu {
    pub(crate) streamer: TextureStreamer<FaultySource<DatasetSource>>,
    pub(crate) renderer: CityRenderer,
}

/// The streamer of references and measurements that load levels
/// explicitly: no budget, one frame in flight, the fixed clock.
pub(crate) fn reference_config(fragment_area: f32, layer_size: u32) -> StreamConfig {
    stream_config(
        UNLIMITED_BUDGET_BYTES,
        1,
        fragment_area,
        Clock::Fixed,
        Eviction::View,
        None,
        layer_size,
    )
}

/// The cache layer size for `dataset`: 2048 texels, or the largest
/// texture's extent where that is larger, up to what the device (and the
/// cache) allow; a texture larger than that fails to load, reported.
pub(crate) fn cache_layer_size(dataset: &Dataset, device: &Device) -> u32 {
    const DEFAULT_LAYER_SIZE: u32 = 2048;
    let largest = (0..dataset.textures.len())
        .filter_map(|texture| dataset.textures.info(texture).ok())
        .map(|info| info.width().max(info.height()))
        .max()
        .unwrap_or(1);
    let device_limit = device
        .properties()
        .limits
        .max_image_dimension2_d
        .min(citystream_cache::MAX_LAYER_SIZE);
    // Powers of two: the largest one the device allows.
    let device_limit = 1u32 << device_limit.max(1).ilog2();
    let size = largest
        .next_power_of_two()
        .clamp(DEFAULT_LAYER_SIZE.min(device_limit), device_limit);
    if largest > device_limit {
        eprintln!(
            "warning: the dataset has textures of up to {largest} texels, beyond the device's {device_limit}; \
             they fail to load (counted in summary.json)"
        );
    } else if size > DEFAULT_LAYER_SIZE {
        eprintln!("cache layers of {size}² texels for textures of up to {largest} texels");
    }
    size
}

/// The streamer's cache and feedback settings shared by the streamed run,
/// the error reference and the pop-in measurement.
pub(crate) fn stream_config(
    memory_budget_bytes: u64,
    frames_in_flight: u32,
    fragment_area: f32,
    clock: Clock,
    eviction: Eviction,
    layer_count: Option<u32>,
    layer_size: u32,
) -> StreamConfig {
    StreamConfig {
        frames_in_flight,
        layer_size,
        layer_count,
        max_layers: None,
        eviction,
        memory_budget_bytes,
        blocks_per_chunk: 256,
        staging_bytes: 16 << 20,
        filtering: Filtering::BilinearNearestLevel,
        feedback_capacity: None,
        weight_cutoff: DEFAULT_WEIGHT_CUTOFF,
        fragment_area,
        // The fixed clock must not depend on how fast this machine reads:
        // no wall-clock load-time limit there (the load size still bounds a cycle).
        loader: match clock {
            Clock::Real => LoaderOptions::default(),
            Clock::Fixed | Clock::Modelled => LoaderOptions {
                load_time: Duration::from_secs(3600),
                ..LoaderOptions::default()
            },
        },
        deterministic: clock.is_modelled(),
        prefetch: false,
    }
}

/// The streamer and renderer of a city; `faults` makes chosen reads of the
/// dataset fail (`--inject-read-failures`).
#[allow(clippy::too_many_arguments)]
pub(crate) fn city_gpu(
    device: &Arc<Device>,
    commands: &mut CommandContext,
    dataset: &Arc<Dataset>,
    city: &CityGeometry,
    policy: Box<dyn citystream_streaming::controller::LoadPolicy>,
    config: &StreamConfig,
    faults: Option<FaultPlan>,
    tree: Option<&AtlasTree>,
    culling: Culling,
) -> Result<CityGpu> {
    let (vertices, meshes) = city;
    let source = FaultySource::new(
        DatasetSource::new(Arc::clone(dataset)),
        faults,
        dataset.textures.pack_path().to_path_buf(),
    );
    // A tree's loader also knows each node's atlas, as a mesh after the scene's.
    let mesh_textures = match tree {
        Some(tree) => tree.loader_mesh_textures(&dataset.scene),
        None => dataset.scene.meshes.iter().map(|m| m.texture).collect(),
    };
    let streamer = TextureStreamer::new(
        device,
        source,
        mesh_textures,
        dataset.colormap.colours(),
        policy,
        config,
    )?;
    let mut renderer = CityRenderer::new(
        device,
        commands,
        vertices,
        &dataset.scene.indices,
        meshes.to_vec(),
        streamer.cache(),
        streamer.compactor(),
    )?;
    if culling == Culling::On {
        renderer
            .enable_culling(commands, vertices, &dataset.scene.indices, config.frames_in_flight)
            .context("GPU culling (--culling off draws every mesh instead)")?;
    }
    Ok(CityGpu { streamer, renderer })
}

/// The streamer and renderer of the run the options ask for (policy,
/// budget, eviction, clock, frames in flight, injected failures).
#[allow(clippy::too_many_arguments)]
pub(crate) fn streamed_city_gpu(
    args: &Args,
    device: &Arc<Device>,
    commands: &mut CommandContext,
    dataset: &Arc<Dataset>,
    city: &CityGeometry,
    fragment_area: f32,
    layer_size: u32,
    tree: Option<&AtlasTree>,
    reserved_bytes: u64,
    disk: Option<DiskModel>,
) -> Result<CityGpu> {
    let budget = match args.memory_budget_mb().bytes() {
        Some(budget) if budget <= reserved_bytes => bail!(
            "the {} MB memory budget leaves nothing for textures beside the ground layer's {:.1} MB",
            budget >> 20,
            reserved_bytes as f64 / f64::from(1 << 20)
        ),
        Some(budget) => budget - reserved_bytes,
        None => UNLIMITED_BUDGET_BYTES,
    };
    let mut config = stream_config(
        budget,
        args.frames_in_flight,
        fragment_area,
        args.clock,
        args.eviction,
        args.cache_layers,
        layer_size,
    );
    config.loader.order = args.priority.order();
    // The prefetch pass goes with the feedback it extends (not the atlas tree's paging).
    config.prefetch = args.prefetch != Prefetch::None && tree.is_none();
    if let Some(disk) = disk {
        // Reads take modelled time: the paper's load-time limit applies to it again.
        config.loader = LoaderOptions {
            disk: Some(disk),
            load_time: LoaderOptions::default().load_time,
            ..config.loader
        };
    }
    city_gpu(
        device,
        commands,
        dataset,
        city,
        build_policy(args)?,
        &config,
        args.inject_read_failures,
        tree,
        args.culling,
    )
}

/// The visible and feedback targets of the city passes and the feedback view.
pub(crate) struct CityTargets {
    pub(crate) target: RenderTarget,
    /// A quarter of the visible resolution per axis.
    pub(crate) feedback_target: RenderTarget,
    pub(crate) view: FeedbackView,
    /// Visible pixels one feedback fragment stands for.
    pub(crate) fragment_area: f32,
}

pub(crate) fn city_targets(device: &Arc<Device>, width: u32, height: u32) -> Result<CityTargets> {
    let target = RenderTarget::new(device, width, height)?;
    let feedback_target = RenderTarget::new(device, (width / 4).max(16), (height / 4).max(16))?;
    let view = FeedbackView::default();
    let fragment_area = view.fragment_area(height, feedback_target.height());
    Ok(CityTargets {
        target,
        feedback_target,
        view,
        fragment_area,
    })
}

/// A dataset's vertices and meshes in the engine's layout.
pub(crate) type CityGeometry = (Vec<Vertex>, Vec<CityMesh>);
