//! A flight: the device, the dataset, the camera path, the streamer and the city passes set up
//! once ([`Flight::new`]), and the frame the headless run and the window share
//! ([`Flight::record`], [`Flight::submit`], [`Flight::latency`]).

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use glam::Vec3;

use citystream_dataset::Dataset;
use citystream_engine::city::{city_geometry, Camera, CityMesh, CityRenderer};
use citystream_engine::commands::{CommandContext, Recording, SemaphoreSignal, SemaphoreWait};
use citystream_engine::cull::CullStats;
use citystream_engine::device::{describe, TextureBacking};
use citystream_engine::gpu_types::{CACHE_IMAGE_SLOTS, TEXTURE_SAMPLEABLE};
use citystream_engine::instance::{default_synchronization_validation, default_validation, InstanceOptions};
use citystream_engine::stream::Frame;
use citystream_engine::target::RenderTarget;
use citystream_engine::texture_cache::{CycleReport, Eviction};
use citystream_engine::timing::{CpuFrameClock, GpuTimer};
use citystream_engine::{Device, DeviceOptions, EngineError};
use citystream_gen::default_city::{ensure_default_city, DEFAULT_CITY_DIR};
use citystream_streaming::atlas_tree::AtlasTree;
use citystream_streaming::bench::path::{standard_path, CameraPath, CameraPose, DEFAULT_STANDARD_DURATION_S};
use citystream_streaming::bench::stats::Stats;
use citystream_streaming::bind_latency::BindLatencyModel;
use citystream_streaming::controller::PolicyOptions;
use citystream_streaming::rng::SplitMix64;

use super::args::{
    Args, Clock, Sparse, Strategy, FIXED_COPY_BYTES_PER_S, FIXED_RENDER_MS, FIXED_STEP_MS, UNLIMITED_BUDGET_BYTES,
};
use super::city_gpu::{cache_layer_size, city_gpu, city_targets, stream_config, CityGeometry, CityGpu, CityTargets};
use super::ground;
use super::measure::MeshesInView;
use super::tree::TreeRun;

/// The passes of a flythrough frame, in recording order, timed separately.
pub(crate) const TIMED_PASSES: usize = 4;

/// GPU milliseconds per frame of each timed pass.
#[derive(Debug, serde::Serialize)]
pub(crate) struct GpuPassMs {
    /// Copies of the cycle's mips and the texture table into the cache.
    pub(crate) uploads: Stats,
    /// Depth pre-pass and feedback pass (paper §3.2), without their culling.
    pub(crate) feedback: Stats,
    /// Compaction of the mesh feedback and its read-back copy (paper §3.3).
    pub(crate) compaction: Stats,
    /// The visible pass and its image copy, without its culling.
    pub(crate) visible: Stats,
    /// GPU culling for the feedback and visible passes (tests, draw compaction, depth
    /// copies and pyramids); null with `--culling off`.
    pub(crate) cull: Option<Stats>,
}

/// Per-pass GPU timestamps and culling statistics of each frame slot, read once the
/// slot's frame completed.
pub(crate) struct PassTimes {
    pub(crate) timer: GpuTimer,
    /// Whether the slot's last frame wrote timestamps not yet read.
    pub(crate) written: Vec<bool>,
    pub(crate) samples: [Vec<f64>; TIMED_PASSES],
    cull_ms: Vec<f64>,
    /// What each completed frame's culling drew (empty with `--culling off`).
    pub(crate) culled: Vec<CullStats>,
}

impl PassTimes {
    pub(crate) fn new(device: &Arc<Device>, frames_in_flight: u32) -> Result<Self> {
        Ok(Self {
            timer: GpuTimer::new(device, frames_in_flight * TIMED_PASSES as u32)?,
            written: vec![false; frames_in_flight as usize],
            samples: Default::default(),
            cull_ms: Vec::new(),
            culled: Vec::new(),
        })
    }

    pub(crate) fn query(slot: u32, pass: usize) -> u32 {
        slot * TIMED_PASSES as u32 + pass as u32
    }

    pub(crate) fn begin(&self, cmd: Recording<'_>, slot: u32, pass: usize) {
        self.timer.begin(cmd, Self::query(slot, pass));
    }

    pub(crate) fn end(&mut self, cmd: Recording<'_>, slot: u32, pass: usize) {
        self.timer.end(cmd, Self::query(slot, pass));
        if pass + 1 == TIMED_PASSES {
            self.written[slot as usize] = true;
        }
    }

    /// Reads `slot`'s timestamps and `renderer`'s culling statistics; its frame must have
    /// completed. The culling the feedback and visible passes record is moved out of
    /// their times into `cull`.
    pub(crate) fn collect(&mut self, slot: u32, renderer: &CityRenderer) -> Result<()> {
        if !std::mem::take(&mut self.written[slot as usize]) {
            return Ok(());
        }
        let mut times = [None; TIMED_PASSES];
        for (pass, time) in times.iter_mut().enumerate() {
            *time = self.timer.read_ms(Self::query(slot, pass))?;
        }
        if let Some(stats) = renderer.cull_stats(slot)? {
            self.culled.push(stats);
            if let Some([feedback, visible]) = stats.cull_ms {
                times[1] = times[1].map(|t| (t - feedback).max(0.0));
                times[3] = times[3].map(|t| (t - visible).max(0.0));
                self.cull_ms.push(feedback + visible);
            }
        }
        for (samples, time) in self.samples.iter_mut().zip(times) {
            samples.extend(time);
        }
        Ok(())
    }

    pub(crate) fn finish(&mut self, renderer: &CityRenderer) -> Result<Option<GpuPassMs>> {
        for slot in 0..self.written.len() as u32 {
            self.collect(slot, renderer)?;
        }
        if !self.timer.supported() {
            return Ok(None);
        }
        let [uploads, feedback, compaction, visible] =
            std::mem::take(&mut self.samples).map(|s| Stats::from_samples(&s));
        Ok(Some(GpuPassMs {
            uploads,
            feedback,
            compaction,
            visible,
            cull: renderer.culling().then(|| Stats::from_samples(&self.cull_ms)),
        }))
    }
}

/// The device the options ask for (`--device`, `--validation`, `CITYSTREAM_VALIDATION`),
/// named on standard error; with `window` (its surface extensions), able to present.
pub(crate) fn flythrough_device(
    args: &Args,
    app_name: &str,
    window: Option<Vec<std::ffi::CString>>,
) -> Result<Arc<Device>> {
    let presentation = window.is_some();
    let created = Device::new(&DeviceOptions {
        instance: InstanceOptions {
            validation: args.validation.unwrap_or_else(default_validation),
            synchronization: default_synchronization_validation(),
            app_name: app_name.into(),
            extensions: window.unwrap_or_default(),
        },
        device_name: args.device.clone(),
        presentation,
        sparse: args.sparse.mode(args.strategy),
        masked_features: Vec::new(),
    });
    let device = Arc::new(created.map_err(|error| {
        // What the setup script installs: the loader, lavapipe and the validation layers.
        // A device refused only for the sparse cache (--sparse on) is not a missing package.
        let installable = matches!(error, EngineError::Loader(_) | EngineError::LayerMissing(_))
            || (matches!(error, EngineError::NoUsableDevice(_)) && args.sparse != Sparse::On);
        let context = if installable {
            "creating the Vulkan device (`make setup` installs the Vulkan loader, lavapipe and the validation layers)"
        } else {
            "creating the Vulkan device"
        };
        anyhow::Error::new(error).context(context)
    })?);
    eprintln!("device: {}", describe(&device));
    if args.sparse == Sparse::Auto
        && args.strategy != Strategy::TextureArrays
        && device.texture_backing() == TextureBacking::Arrays
    {
        eprintln!(
            "notice: {} lacks {}; textures stream into texture arrays (docs/STRATEGIES.md)",
            device.name(),
            device.sparse_fallback_reason().unwrap_or("sparse residency")
        );
    }
    if let Some(log) = std::env::var_os("CITYSTREAM_BIND_LOG").filter(|log| !log.is_empty()) {
        if device.texture_backing() == TextureBacking::Arrays {
            eprintln!(
                "notice: CITYSTREAM_BIND_LOG={}: texture arrays bind no sparse memory, so nothing is logged",
                log.to_string_lossy()
            );
        }
    }
    Ok(device)
}

/// The camera path the run follows: the standard path of the dataset or a file.
pub(crate) fn camera_path(name: &str, scene: &citystream_dataset::Scene) -> Result<CameraPath> {
    if name == "standard" {
        standard_path(scene, DEFAULT_STANDARD_DURATION_S).context("deriving the standard path of the dataset")
    } else {
        CameraPath::load(name).with_context(|| format!("reading the camera path {name}"))
    }
}

/// The dataset directory: `--dataset`, or the default city (created on first run).
pub(crate) fn dataset_dir(args: &Args) -> Result<PathBuf> {
    match &args.dataset {
        Some(dir) => Ok(dir.clone()),
        None => {
            let dir = PathBuf::from(DEFAULT_CITY_DIR);
            ensure_default_city(&dir, false)?;
            Ok(dir)
        }
    }
}

/// The streaming policy the options ask for.
pub(crate) fn build_policy(args: &Args) -> Result<Box<dyn citystream_streaming::controller::LoadPolicy>> {
    let Some(policy) = args.controller.policy(args.policy) else {
        bail!(
            "--controller {} applies to --policy adaptive; --policy {} has no controller",
            args.controller.name(),
            args.policy
        );
    };
    policy
        .build(&PolicyOptions {
            alpha_ms: args.alpha,
            beta: args.beta,
            s_max_mb: 64.0,
            s_min_bytes: 64 * 1024,
            fixed_load_size_mb: args.load_size_mb,
            fixed_mip_bias: args.mip_bias,
        })
        .context("building the streaming policy")
}

/// The latency (ms) of a frame the controller is given: measured with the
/// real clock (after sleeping through the modelled bind cost, as a driver
/// would stall), modelled with the others.
pub(crate) fn frame_latency(
    clock: Clock,
    applied: &citystream_engine::texture_cache::CycleReport,
    other_upload_bytes: u64,
    latency: &BindLatencyModel,
    rng: &mut SplitMix64,
    measured_ms: impl FnOnce() -> f64,
) -> f64 {
    let mut bind_cost_ms = 0.0;
    if applied.blocks_bound + applied.blocks_unbound > 0 {
        let runs = u64::from(applied.bind_entries);
        let blocks = u64::from(applied.blocks_bound + applied.blocks_unbound);
        bind_cost_ms = latency.cost_s(blocks, runs, rng) * 1000.0;
        if clock == Clock::Real && bind_cost_ms > 0.0 {
            std::thread::sleep(Duration::from_secs_f64(bind_cost_ms / 1000.0));
        }
    }
    match clock {
        Clock::Real => measured_ms(),
        Clock::Fixed | Clock::Modelled => {
            let copied = applied.bytes_uploaded + other_upload_bytes;
            FIXED_RENDER_MS + bind_cost_ms + copied as f64 / FIXED_COPY_BYTES_PER_S * 1000.0
        }
    }
}

/// `camera`'s focal length in pixels for a view `height_px` tall.
pub(crate) fn focal_px(height_px: u32, camera: &Camera) -> f64 {
    f64::from(height_px) / (2.0 * f64::from(camera.fov_y * 0.5).tan())
}

/// The lowest the eye of `path` comes above the ground plane at `ground_y` within
/// `duration_s` (sampled at the fixed clock's step), never below the near plane of
/// [`pose_camera`] for a scene `extent` wide: nothing nearer is drawn.
pub(crate) fn lowest_eye_height(path: &CameraPath, duration_s: f64, ground_y: f32, extent: f32) -> f64 {
    let steps = (duration_s * 1000.0 / FIXED_STEP_MS).ceil().max(0.0) as u64;
    let lowest = (0..=steps)
        .map(|i| path.sample_between(None, i as f64 * FIXED_STEP_MS / 1000.0).position[1] - ground_y)
        .fold(f32::INFINITY, f32::min);
    let near = pose_camera(&path.sample_between(None, 0.0), extent).near;
    f64::from(lowest.max(near))
}

/// A camera at `pose`, with a depth range scaled to the scene.
pub(crate) fn pose_camera(pose: &CameraPose, extent: f32) -> Camera {
    Camera {
        eye: Vec3::from(pose.position),
        target: Vec3::from(pose.look_at),
        fov_y: 60f32.to_radians(),
        near: (extent * 1e-4).max(0.01),
        far: extent * 4.0,
    }
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
    city_gpu(
        device,
        commands,
        dataset,
        city,
        build_policy(args)?,
        &stream_config(
            budget,
            args.frames_in_flight,
            fragment_area,
            args.clock,
            args.eviction,
            args.cache_layers,
            layer_size,
        ),
        args.inject_read_failures,
        tree,
        args.culling,
    )
}

/// The dataset (with the remote settings of `args` where it is a URL) with its vertices and
/// meshes in the engine's layout.
pub(crate) fn open_city(args: &Args, dir: &std::path::Path) -> Result<(Arc<Dataset>, CityGeometry)> {
    let options = args.remote.options_with_cache(&args.mip_cache)?;
    let dataset = Arc::new(citystream_gen::location::open_dataset_with(dir, &options)?);
    let city = city_geometry(&dataset)?;
    Ok((dataset, city))
}

/// The scene's largest side (at least 1): the scale of the camera's depth range.
pub(crate) fn scene_extent(scene: &citystream_dataset::Scene) -> f32 {
    let size = Vec3::from(scene.bounds.max) - Vec3::from(scene.bounds.min);
    size.x.max(size.y).max(size.z).max(1.0)
}

/// The texture-array strategy's fully resident start.
#[derive(Clone, Copy, Debug, serde::Serialize)]
pub(crate) struct Preload {
    /// Mips and their bytes loaded before the first frame (every level of every texture).
    pub(crate) mips: u32,
    pub(crate) bytes: u64,
    /// Wall time it took.
    pub(crate) seconds: f64,
}

/// The texture-array strategy's start without a budget given: where the cache's arrays
/// hold the whole city within the device's memory, every texture is loaded now, before
/// the first frame, as Trapp and Döllner's batching has it; otherwise nothing is, and the
/// feedback streams into the arrays (said on standard error).
fn preload_city(gpu: &mut CityGpu, commands: &mut CommandContext) -> Result<Option<Preload>> {
    let cache = gpu.streamer.cache();
    if !cache.holds_every_texture() {
        eprintln!(
            "texture arrays: the city does not fit the device's memory ({:.1} MB of layers); its textures stream into them",
            cache.texel_memory_bytes() as f64 / f64::from(1 << 20)
        );
        return Ok(None);
    }
    let started = std::time::Instant::now();
    let report = gpu.streamer.load_everything_now(commands)?;
    if !report.invalidated_textures.is_empty() {
        bail!(
            "loading the whole city into texture arrays sized for it evicted {} textures",
            report.invalidated_textures.len()
        );
    }
    let preload = Preload {
        mips: report.mips_uploaded,
        bytes: report.bytes_uploaded,
        seconds: started.elapsed().as_secs_f64(),
    };
    eprintln!(
        "texture arrays: every texture resident before the first frame: {} mips, {:.1} MB in {:.1} s ({:.1} MB of layers)",
        preload.mips,
        preload.bytes as f64 / f64::from(1 << 20),
        preload.seconds,
        gpu.streamer.bound_bytes() as f64 / f64::from(1 << 20)
    );
    Ok(Some(preload))
}

/// How long a run waits, after its last frame, for the loads in flight to end.
const MAX_FINISH_LOADING: Duration = Duration::from_secs(600);

/// The dataset, the city's streamer and passes, and the strategy and ground the options ask
/// for: everything a flight renders with, set up once. Its frame is written once too
/// ([`Flight::record`], [`Flight::submit`]): the headless run adds measurement and the CSV
/// around it, the window presenting and input.
pub(crate) struct Flight {
    pub(crate) dataset: Arc<Dataset>,
    meshes_in_view: MeshesInView,
    pub(crate) city: CityGeometry,
    /// The scene's largest side, which scales the camera's depth range.
    pub(crate) extent: f32,
    pub(crate) layer_size: u32,
    pub(crate) targets: CityTargets,
    // The ground and the tree draw with the city's streamer and passes: dropped first.
    pub(crate) ground: Option<ground::GroundRun>,
    pub(crate) tree: Option<TreeRun>,
    pub(crate) gpu: CityGpu,
    strategy: Strategy,
    /// What the texture-array strategy loaded before the first frame, where the city
    /// fits its budget.
    pub(crate) preload: Option<Preload>,
    /// One command buffer per frame in flight: a frame's is reused only after the
    /// streamer's throttle saw that frame complete.
    frame_commands: Vec<CommandContext>,
    pub(crate) pass_times: PassTimes,
    clock: Clock,
    latency: BindLatencyModel,
    latency_rng: SplitMix64,
    cpu_clock: CpuFrameClock,
    /// τ in the feedback's fixed point: per feedback fragment, not per visible one.
    pub(crate) tau: u32,
    last_feedback: Option<u64>,
    budget_mb: Option<u64>,
    /// What the over-budget warning says the cache does about it.
    eviction: Eviction,
    warned_over_budget: bool,
    warned_failure: bool,
}

impl Drop for Flight {
    fn drop(&mut self) {
        // The targets, the ground's and the tree's resources and the command buffers go
        // before the streamer (field order), and frames may still be in flight on an error
        // path, which skips `finish_loading`: the GPU finishes with them first.
        let _ = self.gpu.streamer.device().wait_idle();
    }
}

/// How the ground layer is sized: the view's focal length and the lowest the eye comes
/// above the ground (`None`: anywhere, so every level of the imagery may be needed).
pub(crate) struct GroundSizing {
    pub(crate) focal_px: f64,
    pub(crate) lowest_eye_m: Option<f64>,
}

/// What one frame of a flight does besides the standard sequence.
#[derive(Clone, Copy, Debug)]
pub(crate) struct FrameSettings<'a> {
    /// Camera time, seconds: when ground patches arrive.
    pub(crate) time_s: f64,
    /// Record the feedback pass and its compaction (the window can pause streaming).
    pub(crate) feedback: bool,
    /// Compact every seen mesh (τ = 0): the error reference loads what this frame saw.
    pub(crate) every_seen_mesh: bool,
    /// City Colormap blending (Eq. 8).
    pub(crate) colormap_blend: bool,
    /// A renderer that draws this frame's view next (the error reference): it is given
    /// the visible pass's culling state, so that it draws the same meshes in the same
    /// phases and its image differs from the frame's by texels alone.
    pub(crate) share_visible_culling: Option<&'a CityRenderer>,
}

/// A frame recorded into its command buffer and not yet submitted.
pub(crate) struct RecordedFrame {
    /// The frame's number, from 0 ([`Frame::index`]).
    pub(crate) index: u64,
    /// Its slot among the frames in flight.
    pub(crate) slot: u32,
    /// Time `begin_frame` blocked for the slot's previous frame.
    pub(crate) cpu_wait: std::time::Duration,
    /// The streamer's token, until [`Flight::submit`] ends the frame with it.
    token: Option<Frame>,
    /// This frame's uploads into the cache.
    pub(crate) applied: CycleReport,
    /// Bytes of ground imagery uploaded in this frame.
    pub(crate) ground_bytes: u64,
    /// Draws of a renderer binding one texture per draw ([`super::output::Run`]'s `draw_calls`).
    pub(crate) draw_calls: u32,
    /// Nodes the atlas tree drew.
    pub(crate) nodes_drawn: Option<u32>,
    /// Where the frame consumed feedback not seen before: its mip deficit and the
    /// textures still a level or more coarser than needed, against the cache as
    /// `begin_frame` left it (this frame's evictions applied, its uploads not yet).
    pub(crate) feedback: Option<FeedbackStatus>,
}

/// What streaming still owes the view, from one read-back.
#[derive(Clone, Copy, Debug)]
pub(crate) struct FeedbackStatus {
    pub(crate) deficit: Option<f64>,
    pub(crate) pending: usize,
    /// Meshes the read-back lists (those whose weight reached τ).
    pub(crate) meshes_seen: usize,
}

impl Flight {
    /// Sets up the streamed city of `dataset` (opened from `dir` by [`open_city`]) for
    /// `width` × `height` frames: the strategy (`--strategy`), the ground (`--ground`,
    /// sized by `sizing`, given the scene's extent) and the streamer the options ask for.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn new(
        args: &Args,
        device: &Arc<Device>,
        commands: &mut CommandContext,
        dir: &Path,
        (dataset, city): (Arc<Dataset>, CityGeometry),
        (width, height): (u32, u32),
        sizing: impl FnOnce(f32) -> GroundSizing,
    ) -> Result<Self> {
        let tree = match args.strategy {
            Strategy::AtlasTree => Some(citystream_gen::atlas_tree::open_tree(&dataset, dir)?),
            Strategy::Feedback | Strategy::TextureArrays => None,
        };
        let scene = &dataset.scene;
        let layer_size = cache_layer_size(&dataset, device);
        let targets = city_targets(device, width, height)?;
        let extent = scene_extent(scene);
        let frames_in_flight = args.frames_in_flight;
        let ground = match &args.ground {
            Some(ground_dir) => {
                let set = ground::GroundSet::open(ground_dir, &dataset)?;
                let sizing = sizing(extent);
                let (config, reference) = ground::ground_config(
                    &set,
                    scene,
                    frames_in_flight,
                    sizing.focal_px,
                    sizing.lowest_eye_m.unwrap_or(f64::MIN_POSITIVE),
                    args.memory_budget_mb().bytes(),
                    device,
                )?;
                Some((set, config, reference))
            }
            None => None,
        };
        let mut gpu = streamed_city_gpu(
            args,
            device,
            commands,
            &dataset,
            &city,
            targets.fragment_area,
            layer_size,
            tree.as_ref(),
            // The ground's tile array and staging come out of the same budget.
            ground.as_ref().map_or(0, |(_, config, _)| config.memory_bytes()),
        )?;
        let ground = match ground {
            Some((set, config, reference)) => Some(ground::GroundRun::new(
                device,
                set,
                config,
                // The window measures no error.
                (!args.window && args.psnr_interval > 0).then_some(reference),
                args.memory_budget_mb().bytes(),
            )?),
            None => None,
        };
        let tree = match tree {
            Some(tree) => Some(TreeRun::new(args, commands, &gpu, &dataset, tree)?),
            None => None,
        };
        let preload = match args.strategy {
            // No budget (none given, or `unlimited`): the city loads whole where it fits.
            Strategy::TextureArrays if args.memory_budget_mb().0.is_none() => preload_city(&mut gpu, commands)?,
            Strategy::TextureArrays => {
                eprintln!("texture arrays: streaming within the memory budget given");
                None
            }
            Strategy::Feedback | Strategy::AtlasTree => None,
        };
        let frame_commands = (0..frames_in_flight)
            .map(|i| CommandContext::new(device, &format!("flythrough frame (slot {i})")))
            .collect::<std::result::Result<Vec<_>, _>>()?;
        let pass_times = PassTimes::new(device, frames_in_flight)?;
        let tau = gpu.streamer.gpu_tau();
        Ok(Self {
            meshes_in_view: MeshesInView::new(&dataset.scene),
            dataset,
            city,
            extent,
            layer_size,
            targets,
            gpu,
            ground,
            tree,
            strategy: args.strategy,
            preload,
            frame_commands,
            pass_times,
            clock: args.clock,
            latency: BindLatencyModel::preset(args.bind_latency),
            latency_rng: SplitMix64::new(args.seed),
            cpu_clock: CpuFrameClock::new(),
            tau,
            last_feedback: None,
            budget_mb: args.memory_budget_mb().0,
            eviction: args.eviction,
            warned_over_budget: false,
            warned_failure: false,
        })
    }

    /// Whether frames record the feedback pass: not for the atlas tree, nor for a city
    /// loaded whole into texture arrays.
    pub(crate) fn has_feedback(&self) -> bool {
        self.tree.is_none() && self.preload.is_none()
    }

    /// The city's meshes in the engine's layout.
    pub(crate) fn meshes(&self) -> &[CityMesh] {
        &self.city.1
    }

    /// Records frame `frame` for `camera` into its slot's command buffer, in the order
    /// the streamer asks for (module docs of `citystream_engine::stream`): `begin_frame`
    /// (retire, hand feedback to the loader, pack and bind), the ground's arrivals and its
    /// share of the load size, then the uploads, the feedback pass and its compaction, and
    /// the visible pass of the strategy, each timed. The host may record more (a blit to
    /// the swapchain) before [`Self::submit`].
    pub(crate) fn record(
        &mut self,
        frame: u32,
        camera: &Camera,
        settings: &FrameSettings<'_>,
    ) -> Result<RecordedFrame> {
        let mut begun = self.gpu.streamer.begin_frame()?;
        self.warn_once(frame, begun.over_budget());
        let feedback = match self.gpu.streamer.latest_feedback() {
            Some((from, entries)) if self.last_feedback != Some(from) => {
                self.last_feedback = Some(from);
                let served = self.gpu.streamer.served_levels(entries)?;
                Some(FeedbackStatus {
                    deficit: served.mip_deficit,
                    pending: served.pending_textures,
                    meshes_seen: entries.len(),
                })
            }
            _ => None,
        };
        // The streamer's throttle saw this slot's last frame complete.
        let slot = begun.slot();
        // Patches that arrived, and the ground tiles this frame's share of the load size
        // pays for (charged to the facades' next loading cycle).
        let ground_bytes = match self.ground.as_mut() {
            Some(run) => {
                run.update(settings.time_s, &mut self.gpu.streamer, &begun, camera)?
                    .bytes
            }
            None => 0,
        };
        self.pass_times.collect(slot, &self.gpu.renderer)?;
        self.gpu.renderer.set_cull_slot(slot)?;
        let feedback_pass = self.has_feedback() && settings.feedback;
        let rec = self.frame_commands[slot as usize].begin_completed()?;
        let passes = &mut self.pass_times;
        passes.begin(rec, slot, 0);
        let applied = self.gpu.streamer.record_uploads(&mut begun, rec)?;
        if let Some(run) = self.ground.as_mut() {
            run.layer.record_uploads(rec, slot)?;
        }
        passes.end(rec, slot, 0);
        // Without feedback (`has_feedback`) the two passes stay empty (0 ms).
        let CityTargets {
            target,
            feedback_target,
            view,
            ..
        } = &self.targets;
        passes.begin(rec, slot, 1);
        if feedback_pass {
            self.gpu
                .renderer
                .record_feedback(rec, feedback_target, camera, view, target.height())?;
        }
        passes.end(rec, slot, 1);
        passes.begin(rec, slot, 2);
        match (feedback_pass, settings.every_seen_mesh) {
            (false, _) => {}
            (true, true) => self.gpu.streamer.record_feedback_resolve_with_tau(&mut begun, rec, 0)?,
            (true, false) => self.gpu.streamer.record_feedback_resolve(&mut begun, rec)?,
        }
        passes.end(rec, slot, 2);
        if let Some(other) = settings.share_visible_culling {
            self.gpu.renderer.record_share_visible_culling(rec, other)?;
        }
        passes.begin(rec, slot, 3);
        let ground_layer = self.ground.as_ref().map(|g| (&g.layer, slot));
        let (draw_calls, nodes_drawn) = match self.tree.as_mut() {
            Some(run) => {
                let drawn = run.record_frame(
                    rec,
                    &begun,
                    &mut self.gpu,
                    (target, camera),
                    ground_layer.map(|(layer, _)| layer),
                )?;
                (drawn.draw_calls, Some(drawn.nodes_drawn))
            }
            None => {
                let blend = settings.colormap_blend;
                match ground_layer {
                    Some(ground) => self
                        .gpu
                        .renderer
                        .record_visible_on_ground(rec, target, camera, blend, ground)?,
                    None => self.gpu.renderer.record_visible(rec, target, camera, 1.0, blend)?,
                }
                let size = (target.width(), target.height());
                let draws = match self.strategy {
                    Strategy::TextureArrays => {
                        let cache = self.gpu.streamer.cache();
                        let image_of = |texture: u32| {
                            cache
                                .texture_data(texture)
                                .filter(|t| t.state == TEXTURE_SAMPLEABLE)
                                .map(|t| t.image)
                        };
                        // The engine binds CACHE_IMAGE_SLOTS arrays at once: Alg. 1's a_max.
                        self.meshes_in_view.array_batches(
                            &self.dataset.scene,
                            camera,
                            size,
                            CACHE_IMAGE_SLOTS,
                            image_of,
                        )
                    }
                    _ => self.meshes_in_view.count(&self.dataset.scene, camera, size.0, size.1),
                };
                (draws, None)
            }
        };
        passes.end(rec, slot, 3);
        Ok(RecordedFrame {
            index: begun.index(),
            slot,
            cpu_wait: begun.cpu_wait(),
            token: Some(begun),
            applied,
            ground_bytes,
            draw_calls,
            nodes_drawn,
            feedback,
        })
    }

    /// Ends `frame` with the controller step on `frame_ms`, the latency of the frame
    /// before (Eq. 4–7), and submits it with the streamer's waits and signal and the
    /// host's own (`waits`, `signals`: a swapchain image's).
    pub(crate) fn submit(
        &mut self,
        frame: &mut RecordedFrame,
        frame_ms: f64,
        waits: &[SemaphoreWait],
        signals: &[SemaphoreSignal],
    ) -> Result<()> {
        let token = frame
            .token
            .take()
            .with_context(|| format!("frame {} was submitted twice", frame.index))?;
        let submit = self.gpu.streamer.end_frame(token, frame_ms)?;
        let waits: Vec<SemaphoreWait> = submit.waits.iter().chain(waits).copied().collect();
        let signals: Vec<SemaphoreSignal> = std::iter::once(submit.signal).chain(signals.iter().copied()).collect();
        self.frame_commands[frame.slot as usize].submit_frame(&waits, &signals)?;
        Ok(())
    }

    /// `frame`'s command buffer, recorded and not yet submitted, for what the host records
    /// after the flight's passes (the window's blit to the swapchain).
    /// With it, the frame's render target.
    pub(crate) fn recording(&mut self, frame: &RecordedFrame) -> Result<(Recording<'_>, &RenderTarget)> {
        let rec = self.frame_commands[frame.slot as usize].recording()?;
        Ok((rec, &self.targets.target))
    }

    /// The latency of `frame` the controller is given next: measured since the last call
    /// with the real clock, modelled with the others ([`frame_latency`]).
    pub(crate) fn latency(&mut self, frame: &RecordedFrame) -> f64 {
        let cpu_clock = &mut self.cpu_clock;
        frame_latency(
            self.clock,
            &frame.applied,
            frame.ground_bytes,
            &self.latency,
            &mut self.latency_rng,
            || cpu_clock.tick().as_secs_f64() * 1000.0,
        )
    }

    /// Starts the latency clock afresh: time since the last frame (hidden, waiting) is not
    /// the next frame's latency.
    pub(crate) fn restart_latency_clock(&mut self) {
        self.cpu_clock.tick();
    }

    /// Lets the loading task in flight end when the run does, so that its reads count as
    /// read or failed (a remote source that stopped answering fails them within its
    /// timeouts and retries) and a run never ends with reads silently outstanding.
    pub(crate) fn finish_loading(&self) -> Result<()> {
        let streamer = &self.gpu.streamer;
        if streamer.finish_loading(Duration::from_secs(1)) {
            return Ok(());
        }
        eprintln!("waiting for the loads in flight to end (a remote source may take up to its timeouts and retries)");
        if !streamer.finish_loading(MAX_FINISH_LOADING) {
            bail!(
                "the loads in flight did not end within {} s of the last frame",
                MAX_FINISH_LOADING.as_secs()
            );
        }
        Ok(())
    }

    /// The first frame over budget and the first failed load are worth a line each.
    fn warn_once(&mut self, frame: u32, over_budget: bool) {
        if over_budget && !self.warned_over_budget {
            self.warned_over_budget = true;
            let response = match self.eviction {
                Eviction::View => "showing the most important levels that fit",
                Eviction::Ring => "the ring evicts its oldest layers, whatever the view shows",
            };
            eprintln!(
                "\nwarning: from frame {frame} the view needs more texture memory than the {} MB budget holds; \
                 {response} (frames over budget are counted in summary.json)",
                self.budget_mb.unwrap_or(0)
            );
        }
        if !self.warned_failure && self.gpu.streamer.totals().failed > 0 {
            self.warned_failure = true;
            if let Some(first) = self.gpu.streamer.load_failures().first() {
                eprintln!(
                    "\nwarning: from frame {frame} textures fail to load; the first{}: {} \
                     (counted in summary.json; the run will exit non-zero unless --allow-load-failures)",
                    first.level.map(|l| format!(", at level {l}")).unwrap_or_default(),
                    first.reason
                );
            }
        }
    }
}
