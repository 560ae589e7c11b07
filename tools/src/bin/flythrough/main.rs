//! `flythrough`: renders a city headless along a camera path. With a
//! dataset it runs the paper's pipeline (Algorithm 1): feedback, compaction,
//! controller, loading task, sparse binds and copies, then the frame with
//! City Colormap blending. It writes PNG frames and `summary.json`.

use std::io::Write;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::{Parser, ValueEnum};
use glam::Vec3;

use citystream_engine::atlas_tree::AtlasTreeRenderer;
use citystream_engine::city::{city_geometry, Camera, CityMesh, CityRenderer, FeedbackView};
use citystream_engine::commands::CommandContext;
use citystream_engine::device::describe;
use citystream_engine::gpu_types::{FeedbackEntry, Vertex, FEEDBACK_MIP_ONE, TEXTURE_SAMPLEABLE};
use citystream_engine::instance::{default_synchronization_validation, default_validation, InstanceOptions};
use citystream_engine::pipeline::Filtering;
use citystream_engine::placeholder;
use citystream_engine::present::PresentMode;
use citystream_engine::scene::MeshRenderer;
use citystream_engine::stream::{DatasetSource, StreamConfig, TextureStreamer};
use citystream_engine::target::{write_png, RenderTarget};
use citystream_engine::texture_cache::{Eviction, GpuTextureCache};
use citystream_engine::timing::{CpuFrameClock, GpuTimer};
use citystream_engine::{Device, DeviceOptions};
use citystream_streaming::atlas_tree::{frustum_planes, intersects_frustum, AtlasTree, Block, DrawWith, TreeView};
use citystream_streaming::bench::path::{standard_path, CameraPath, CameraPose, DEFAULT_STANDARD_DURATION_S};
use citystream_streaming::bench::stats::{Stats, SummaryBuilder};
use citystream_streaming::bind_latency::{BindLatencyModel, BindLatencyPreset};
use citystream_streaming::controller::{PolicyKind, PolicyOptions};
use citystream_streaming::dataset::Dataset;
use citystream_streaming::loader::LoaderOptions;
use citystream_streaming::records::DEFAULT_WEIGHT_CUTOFF;
use citystream_streaming::rng::SplitMix64;
use citystream_streaming::source::{FaultPlan, FaultySource, MipSource};
use citystream_tools::default_city::{ensure_default_city, DEFAULT_CITY_DIR};
use citystream_tools::image_error::{mse, ErrorSeries, FrameError, PrefixedErrorFigures};

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum Clock {
    /// The camera follows wall-clock time; frame latency is measured.
    Real,
    /// A fixed time step per frame; frame latency is modelled (a fixed
    /// render cost plus the bind-latency model's cost of each batch and the
    /// copy at 12 GB/s), so runs are reproducible.
    Fixed,
    /// Frame latency modelled as with `fixed`, and the camera advances by
    /// each frame's modelled latency (at least the 60 Hz step), as it would
    /// in real time on the modelled GPU: a stalled frame makes the camera
    /// jump ahead and the next frames ask for more, as in the paper's
    /// benchmark. Reproducible too.
    Modelled,
}

impl Clock {
    /// Whether frame latency comes from the model instead of being measured.
    fn is_modelled(self) -> bool {
        self != Clock::Real
    }

    /// The name written to summary.json.
    fn name(self) -> &'static str {
        match self {
            Clock::Real => "real",
            Clock::Fixed => "fixed",
            Clock::Modelled => "modelled",
        }
    }
}

/// `--strategy`: how the run decides what to load and draws it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum Strategy {
    /// The paper's: a GPU feedback pass says which mip each visible mesh needs.
    Feedback,
    /// The texture-atlas tree's (docs/ATLAS_TREE.md): nodes chosen by distance draw their
    /// atlases, blocks paged by §6's priorities; `--dataset` names a tree.
    AtlasTree,
}

impl Strategy {
    /// The name written to summary.json.
    fn name(self) -> &'static str {
        match self {
            Strategy::Feedback => "feedback",
            Strategy::AtlasTree => "atlas-tree",
        }
    }
}

#[derive(Debug, Parser)]
#[command(
    name = "flythrough",
    version,
    about = "Stream and render a textured city headless along a camera path",
    long_about = "Renders a city off-screen (no window) along a camera path and writes every N-th \
                  frame as PNG plus summary.json.\n\n\
                  It runs the adaptive streaming pipeline on a city dataset: a feedback pass tells \
                  which mip each visible mesh needs, a loading task reads exactly those mips, \
                  the sparse texture cache binds memory and copies them, and the frame blends \
                  sampled colour with the City Colormap by mip level. Without --dataset it \
                  streams the default city (data/city, created on first run); with \
                  --placeholder it renders a small procedural city, fully resident."
)]
struct Args {
    /// City dataset directory (written by `citystream gen`, `import` or `atlas`).
    /// Default: the default city in data/city, created on first run (the
    /// `small` generated city in 2048x2048 atlases, see docs/DATASET.md).
    #[arg(long)]
    dataset: Option<PathBuf>,
    /// Render a procedural placeholder city, fully resident, instead of
    /// streaming a dataset (no feedback, no streaming).
    #[arg(long, conflicts_with_all = ["dataset", "pop_in"])]
    placeholder: bool,
    /// Output directory for frames/ and summary.json.
    #[arg(long, default_value = "out/flythrough")]
    out: PathBuf,
    /// Camera path: `standard` (the benchmark path derived from the dataset,
    /// see docs/PATHS.md) or a path file (`citystream path`, or recorded in
    /// the window). Default: `standard`; with --window, free flight from the
    /// overview.
    #[arg(long)]
    path: Option<String>,
    /// Number of frames to render (default: as many as the path lasts; 240
    /// with --placeholder).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1_000_000))]
    frames: Option<u32>,
    /// Stop after this many seconds of camera time (default: the path's
    /// length; at most a day).
    #[arg(long, value_parser = parse_duration_s)]
    duration_s: Option<f64>,
    /// Write every N-th frame as PNG (0 writes none). Default: 20; with
    /// --window, 0 (the PNGs are then what the window presented).
    #[arg(long)]
    frame_interval: Option<u32>,
    /// Image width in pixels.
    #[arg(long, default_value_t = 640, value_parser = clap::value_parser!(u32).range(16..=8192))]
    width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 360, value_parser = clap::value_parser!(u32).range(16..=8192))]
    height: u32,
    /// Streaming strategy: `feedback` (the paper's GPU feedback) or `atlas-tree` (a
    /// texture-atlas tree built by `citystream atlas-tree`, named by --dataset; see
    /// docs/ATLAS_TREE.md). Both share the loader, the cache and the policy.
    #[arg(long, value_enum, default_value_t = Strategy::Feedback)]
    strategy: Strategy,
    /// Streaming policy: adaptive (paper Eq. 4-7), baseline (s = s_max, b = 0) or fixed.
    #[arg(long, default_value = "adaptive")]
    policy: PolicyKind,
    /// Target maximum frame latency α in ms (adaptive).
    #[arg(long, default_value_t = 16.0)]
    alpha: f64,
    /// Maximum mip bias β (adaptive).
    #[arg(long, default_value_t = 8.0)]
    beta: f64,
    /// Load size in MB (fixed policy).
    #[arg(long, default_value_t = 4.0)]
    load_size_mb: f64,
    /// Mip bias (fixed policy).
    #[arg(long, default_value_t = 0.0)]
    mip_bias: f64,
    /// Modelled cost of binding sparse memory: none, lavapipe or desktop.
    #[arg(long, default_value = "none")]
    bind_latency: BindLatencyPreset,
    /// Clock: real (measured), fixed (reproducible, modelled latency, 60
    /// frames per camera second) or modelled (reproducible, the camera
    /// advancing by each frame's modelled latency).
    #[arg(long, value_enum, default_value_t = Clock::Real)]
    clock: Clock,
    /// Memory budget of bound texture blocks in MB, or `unlimited`.
    #[arg(long, default_value = "512", value_parser = parse_budget_mb)]
    memory_budget_mb: BudgetMb,
    /// How the cache frees memory at the budget: `view` (drop the levels the
    /// view needs least, see ARCHITECTURE.md, "Eviction") or `ring` (the paper's
    /// oldest-layer ring).
    #[arg(long, default_value = "view", value_parser = parse_eviction)]
    eviction: Eviction,
    /// Layers per cache image (default: derived from the dataset, the
    /// budget and the device).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=65535))]
    cache_layers: Option<u32>,
    /// Pick the Vulkan device whose name contains this text (also CITYSTREAM_DEVICE).
    #[arg(long)]
    device: Option<String>,
    /// Seed of the placeholder city and of the bind-latency model's spikes.
    #[arg(long, default_value_t = 7)]
    seed: u64,
    /// Blocks per side of the placeholder city (with --placeholder).
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u32).range(1..=200))]
    blocks: u32,
    /// Enable the Vulkan validation layer (default: on in debug builds).
    #[arg(long)]
    validation: Option<bool>,
    /// Instead of a flythrough, measure pop-in (the paper's Fig. 7): a static
    /// view that starts with nothing resident and whose textures then refine
    /// one level per frame from the coarsest; the largest inter-frame MSE with
    /// direct sampling (no City Colormap: unloaded reads as zero) and with
    /// colormap blending (Eq. 8). Writes OUT/popin.json.
    #[arg(long)]
    pop_in: bool,
    /// Frames the CPU may record ahead of the GPU (1 waits for every frame).
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u32).range(1..=8))]
    frames_in_flight: u32,
    /// Exit 0 even when textures failed to load (a read error, a truncated
    /// pack); the failures are still counted in summary.json and warned about.
    #[arg(long)]
    allow_load_failures: bool,
    /// Testing aid: make reads of the texture pack fail, `EVERY:TIMES`: one
    /// mip in EVERY (chosen by its texture and level) fails its first TIMES
    /// reads. The loader reads a mip up to 3 times, so TIMES of 2 or less
    /// recover and 3 or more fail the texture.
    #[arg(long, value_parser = FaultPlan::parse)]
    inject_read_failures: Option<FaultPlan>,
    /// Measure image error every N frames: render a reference of the same view
    /// with every needed mip resident and report PSNR against it (0: never).
    #[arg(long, default_value_t = 30)]
    psnr_interval: u32,
    /// Aerial imagery under the city (docs/GROUND.md): a patch set written by
    /// `citystream patches`, draped on the ground through a flexible clipmap; each patch
    /// is inserted when its arrival time comes, and ground tiles share the controller's
    /// load size with the facades.
    #[arg(long, conflicts_with_all = ["placeholder", "pop_in", "window"])]
    ground: Option<PathBuf>,
    /// Open a window and fly through the city interactively (docs/WINDOW.md):
    /// mouse and keys fly, --path replays a path at wall-clock speed, R
    /// records. Needs a display (X11, or XWayland).
    #[arg(long, conflicts_with_all = ["placeholder", "pop_in"])]
    window: bool,
    /// With --window: vsync (default), mailbox or immediate; vsync where the
    /// display lacks the one asked for.
    #[arg(long, default_value = "vsync", requires = "window")]
    present_mode: PresentMode,
    /// With --window: record the flown camera path from the first frame to
    /// this path file (R stops and restarts it); written when recording stops
    /// or the window closes, replacing the file atomically.
    #[arg(long, requires = "window")]
    record: Option<PathBuf>,
    /// With --window: scripted input (docs/WINDOW.md), for demos and tests:
    /// key presses, mouse looks, resizes, minimising and screenshots by frame.
    #[arg(long, requires = "window")]
    input_script: Option<PathBuf>,
    #[command(flatten)]
    remote: citystream_tools::RemoteArgs,
    #[command(flatten)]
    mip_cache: citystream_tools::MipCacheArgs,
}

/// `--memory-budget-mb`: whole MB, or `None` for `unlimited`.
#[derive(Clone, Copy, Debug)]
struct BudgetMb(Option<u64>);

impl BudgetMb {
    fn bytes(self) -> Option<u64> {
        self.0.map(|mb| mb << 20)
    }
}

fn parse_budget_mb(text: &str) -> std::result::Result<BudgetMb, String> {
    if text.eq_ignore_ascii_case("unlimited") {
        return Ok(BudgetMb(None));
    }
    match text.parse::<u64>() {
        Ok(0) => Err("the budget must be at least 1 MB (or `unlimited`)".into()),
        Ok(mb) if mb > 1 << 30 => Err(format!("{mb} MB is beyond any device; use `unlimited`")),
        Ok(mb) => Ok(BudgetMb(Some(mb))),
        Err(_) => Err(format!("`{text}` is neither a whole number of MB nor `unlimited`")),
    }
}

/// `--duration-s`: finite seconds from 0 to a day.
fn parse_duration_s(text: &str) -> std::result::Result<f64, String> {
    use citystream_streaming::bench::path::MAX_PATH_DURATION_S;
    match text.parse::<f64>() {
        Ok(s) if s.is_finite() && (0.0..=MAX_PATH_DURATION_S).contains(&s) => Ok(s),
        Ok(s) => Err(format!("{s} s is not a duration from 0 to {MAX_PATH_DURATION_S} s")),
        Err(_) => Err(format!("`{text}` is not a number of seconds")),
    }
}

/// `--eviction`: `view` or `ring`.
fn parse_eviction(text: &str) -> std::result::Result<Eviction, String> {
    match text {
        "view" => Ok(Eviction::View),
        "ring" => Ok(Eviction::Ring),
        other => Err(format!("`{other}` is not an eviction (view or ring)")),
    }
}

/// The budget the cache gets for "unlimited": more than any dataset.
const UNLIMITED_BUDGET_BYTES: u64 = u64::MAX / 4;

/// Fixed clock: the time step and the modelled render cost of a frame.
const FIXED_STEP_MS: f64 = 1000.0 / 60.0;
const FIXED_RENDER_MS: f64 = 8.0;
/// Fixed clock: host-to-device copy bandwidth of the modelled GPU, the same
/// as the simulator's (`streaming::sim`), so copies cost time too.
const FIXED_COPY_BYTES_PER_S: f64 = 12e9;

#[derive(Debug, serde::Serialize)]
struct Run<'a> {
    device: String,
    scene: String,
    /// `feedback` or `atlas-tree`.
    strategy: &'a str,
    /// Per frame: draws of a renderer binding one texture per draw (meshes in view, a
    /// mesh having one texture; for the tree, atlases drawn plus the meshes in view of the
    /// leaves drawn with their originals). citystream itself draws every mesh in one draw
    /// whatever the strategy.
    draw_calls: Stats,
    /// Per frame: nodes drawn (the atlas tree only).
    nodes_drawn: Option<Stats>,
    /// The atlas tree and its paging (the atlas-tree strategy only).
    atlas_tree: Option<TreeSummary>,
    policy: &'a str,
    alpha_ms: f64,
    mip_deficit: Option<Stats>,
    /// The facades' error against the fully resident reference: `psnr_db`,
    /// `psnr_ceiling_db`, `error_frames`, `mse`, `psnr_of_mean_mse_db` (every measured
    /// frame counts, identical ones at the ceiling; `citystream_tools::image_error`).
    #[serde(flatten)]
    error: PrefixedErrorFigures,
    /// With --ground: tiles of ground imagery composed and uploaded, their MB, and the
    /// ground's error against a reference with every arrived patch resident (both drawn
    /// alone behind the city), under the same keys prefixed `ground_`.
    ground_tiles_uploaded: Option<u64>,
    ground_mb_streamed: Option<f64>,
    #[serde(flatten)]
    ground_error: PrefixedErrorFigures,
    ground: Option<ground::GroundSummary>,
    clock: &'a str,
    bind_latency: &'a str,
    width: u32,
    height: u32,
    duration_s: f64,
    wall_s: f64,
    /// Wall time per frame (ms): compare runs with 1 and 2 frames in flight.
    wall_ms_per_frame: f64,
    frames_in_flight: u32,
    /// Frames whose render thread blocked on the GPU to reuse a frame slot.
    cpu_wait_frames: u32,
    cpu_wait_ms: f64,
    /// Frames whose image was read back (PNG, PSNR): waits outside the steady state.
    readback_wait_frames: u32,
    mips_streamed: u64,
    /// Bytes of the distinct (texture, level) pairs the run uploaded, each once.
    unique_bytes_streamed: u64,
    blocks_bound: u64,
    peak_resident_bytes: u64,
    /// Most device memory the allocator held (geometry, cache blocks, table,
    /// targets, staging), sampled every 30 frames and at the end.
    peak_device_memory_bytes: u64,
    /// The budget in bytes; null when unlimited.
    memory_budget_bytes: Option<u64>,
    eviction: &'a str,
    /// Layers of each cache image, by format (BC1, RGBA8, BC3, BC7) of those the dataset has.
    cache_layers: Vec<u32>,
    /// Frames in which the view needed more than the budget holds.
    frames_over_budget: u64,
    /// Per pause of the path: mips uploaded in its second half (a settled
    /// streamer uploads none while the camera holds still).
    pause_uploads_second_half: Vec<u64>,
    /// Failed reads and header errors, and the textures the loader gave up on.
    load_failures: u64,
    /// Failed reads that a retry then completed.
    read_retries: u64,
    textures_failed: usize,
    /// Levels dropped, layers evicted, loads refused and declined for room.
    dropped_levels: u64,
    evicted_layers: u64,
    refused_for_room: u64,
    declined_loads: u64,
    /// Side of the cache's array layers in texels.
    cache_layer_size: u32,
    /// GPU time of each pass per frame, from timestamps (null where the
    /// queue has none).
    gpu_pass_ms: Option<GpuPassMs>,
    validation_errors: usize,
    frames_written: Vec<String>,
    /// The on-disk mip cache of a remote dataset read through one (`--mip-cache`).
    mip_cache: Option<MipCacheSummary>,
}

/// `summary.json`'s `mip_cache`: where it lies, how big it may grow, what it did.
#[derive(Debug, serde::Serialize)]
struct MipCacheSummary {
    dir: String,
    capacity_bytes: u64,
    #[serde(flatten)]
    stats: citystream_streaming::dataset::MipCacheStats,
}

/// The passes of a flythrough frame, in recording order, timed separately.
const TIMED_PASSES: usize = 4;

/// GPU milliseconds per frame of each timed pass.
#[derive(Debug, serde::Serialize)]
struct GpuPassMs {
    /// Copies of the cycle's mips and the texture table into the cache.
    uploads: Stats,
    /// Depth pre-pass and feedback pass (paper §3.2).
    feedback: Stats,
    /// Compaction of the mesh feedback and its read-back copy (paper §3.3).
    compaction: Stats,
    /// The visible pass and its image copy.
    visible: Stats,
}

/// Per-pass GPU timestamps of each frame slot, read once the slot's frame
/// completed.
struct PassTimes {
    timer: GpuTimer,
    /// Whether the slot's last frame wrote timestamps not yet read.
    written: Vec<bool>,
    samples: [Vec<f64>; TIMED_PASSES],
}

impl PassTimes {
    fn new(device: &Arc<Device>, frames_in_flight: u32) -> Result<Self> {
        Ok(Self {
            timer: GpuTimer::new(device, frames_in_flight * TIMED_PASSES as u32)?,
            written: vec![false; frames_in_flight as usize],
            samples: Default::default(),
        })
    }

    fn query(slot: u32, pass: usize) -> u32 {
        slot * TIMED_PASSES as u32 + pass as u32
    }

    fn begin(&self, cmd: citystream_engine::vk::CommandBuffer, slot: u32, pass: usize) {
        self.timer.begin(cmd, Self::query(slot, pass));
    }

    fn end(&mut self, cmd: citystream_engine::vk::CommandBuffer, slot: u32, pass: usize) {
        self.timer.end(cmd, Self::query(slot, pass));
        if pass + 1 == TIMED_PASSES {
            self.written[slot as usize] = true;
        }
    }

    /// Reads `slot`'s timestamps; its frame must have completed.
    fn collect(&mut self, slot: u32) -> Result<()> {
        if !std::mem::take(&mut self.written[slot as usize]) {
            return Ok(());
        }
        for (pass, samples) in self.samples.iter_mut().enumerate() {
            samples.extend(self.timer.read_ms(Self::query(slot, pass))?);
        }
        Ok(())
    }

    fn finish(mut self) -> Result<Option<GpuPassMs>> {
        for slot in 0..self.written.len() as u32 {
            self.collect(slot)?;
        }
        if !self.timer.supported() {
            return Ok(None);
        }
        let [uploads, feedback, compaction, visible] = self.samples.map(|s| Stats::from_samples(&s));
        Ok(Some(GpuPassMs {
            uploads,
            feedback,
            compaction,
            visible,
        }))
    }
}

mod ground;
mod window;

fn main() -> Result<()> {
    let args = Args::parse();
    if args.strategy == Strategy::AtlasTree && (args.window || args.placeholder || args.pop_in) {
        bail!(
            "--strategy atlas-tree streams a headless flythrough only; leave out --window, --placeholder and --pop-in"
        );
    }
    if args.window {
        return window::run(&args);
    }
    let device = flythrough_device(&args, "citystream flythrough", None)?;
    let frames_dir = args.out.join("frames");
    std::fs::create_dir_all(&frames_dir).with_context(|| format!("creating {}", frames_dir.display()))?;
    if args.placeholder {
        return placeholder_city(&args, &device);
    }
    let dir = dataset_dir(&args)?;
    if args.pop_in {
        pop_in(&args, &device, &dir)
    } else {
        stream_city(&args, &device, &dir)
    }
}

/// The device the options ask for (`--device`, `--validation`, `CITYSTREAM_VALIDATION`),
/// named on standard error; with `window` (its surface extensions), able to present.
fn flythrough_device(args: &Args, app_name: &str, window: Option<Vec<std::ffi::CString>>) -> Result<Arc<Device>> {
    let presentation = window.is_some();
    let device = Arc::new(
        Device::new(&DeviceOptions {
            instance: InstanceOptions {
                validation: args.validation.unwrap_or_else(default_validation),
                synchronization: default_synchronization_validation(),
                app_name: app_name.into(),
                extensions: window.unwrap_or_default(),
            },
            device_name: args.device.clone(),
            presentation,
        })
        .context("creating the Vulkan device")?,
    );
    eprintln!("device: {}", describe(&device));
    Ok(device)
}

/// The camera path the run follows: the standard path of the dataset or a file.
fn camera_path(name: &str, scene: &citystream_streaming::dataset::Scene) -> Result<CameraPath> {
    if name == "standard" {
        standard_path(scene, DEFAULT_STANDARD_DURATION_S).context("deriving the standard path of the dataset")
    } else {
        CameraPath::load(name).with_context(|| format!("reading the camera path {name}"))
    }
}

/// The dataset directory: `--dataset`, or the default city (created on first run).
fn dataset_dir(args: &Args) -> Result<PathBuf> {
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
fn build_policy(args: &Args) -> Result<Box<dyn citystream_streaming::controller::LoadPolicy>> {
    args.policy
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
fn frame_latency(
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
fn focal_px(height_px: u32, camera: &Camera) -> f64 {
    f64::from(height_px) / (2.0 * f64::from(camera.fov_y * 0.5).tan())
}

/// The lowest the eye of `path` comes above the ground plane at `ground_y` within
/// `duration_s` (sampled at the fixed clock's step), never below the near plane of
/// [`pose_camera`] for a scene `extent` wide: nothing nearer is drawn.
fn lowest_eye_height(path: &CameraPath, duration_s: f64, ground_y: f32, extent: f32) -> f64 {
    let steps = (duration_s * 1000.0 / FIXED_STEP_MS).ceil().max(0.0) as u64;
    let lowest = (0..=steps)
        .map(|i| path.sample_between(None, i as f64 * FIXED_STEP_MS / 1000.0).position[1] - ground_y)
        .fold(f32::INFINITY, f32::min);
    let near = pose_camera(&path.sample_between(None, 0.0), extent).near;
    f64::from(lowest.max(near))
}

/// A camera at `pose`, with a depth range scaled to the scene.
fn pose_camera(pose: &CameraPose, extent: f32) -> Camera {
    Camera {
        eye: Vec3::from(pose.position),
        target: Vec3::from(pose.look_at),
        fov_y: 60f32.to_radians(),
        near: (extent * 1e-4).max(0.01),
        far: extent * 4.0,
    }
}

/// An orbit around `centre` over a scene `extent` wide and `tall` high:
/// close over a flat city, clear of a single tall model.
fn orbit_camera(centre: Vec3, extent: f32, tall: f32, t: f64) -> Camera {
    let angle = (t as f32) * std::f32::consts::TAU;
    let radius = extent * 0.55 + tall * 1.5;
    let height = extent * (0.18 + 0.12 * (angle * 2.0).sin().abs()) + tall;
    Camera {
        eye: centre + Vec3::new(angle.cos() * radius, height, angle.sin() * radius),
        target: centre,
        fov_y: 60f32.to_radians(),
        // Scaled to the scene, so a one-metre model and a city both fit the depth range.
        near: extent * 1e-3,
        far: (extent + tall) * 4.0,
    }
}

/// The live one-line status: rewritten in place on a terminal, a line every
/// 30 frames otherwise (logs, CI).
fn status(frame: u32, frames: u32, dt: f64, s_mb: f64, b: f64, mb_s: f64, resident_mb: f64) {
    use std::io::IsTerminal;
    let line = format!(
        "frame {:>6}/{frames}  dt {dt:7.2} ms  s {s_mb:7.2} MB  b {b:4.2}  {mb_s:7.2} MB/s  resident {resident_mb:8.1} MB",
        frame + 1
    );
    if std::io::stderr().is_terminal() {
        // The path's length is known, so a bar shows how far the run is.
        const BAR: usize = 20;
        let done = (f64::from(frame + 1) / f64::from(frames.max(1)) * BAR as f64).round() as usize;
        let bar = format!("{}{}", "#".repeat(done.min(BAR)), "-".repeat(BAR - done.min(BAR)));
        eprint!("\r[{bar}] {line}");
        let _ = std::io::stderr().flush();
    } else if frame.is_multiple_of(30) || frame + 1 == frames {
        eprintln!("{line}");
    }
}

/// A streamer over the dataset and the city passes that draw with it.
struct CityGpu {
    streamer: TextureStreamer<FaultySource<DatasetSource>>,
    renderer: CityRenderer,
}

/// The streamer of references and measurements that load levels
/// explicitly: no budget, one frame in flight, the fixed clock.
fn reference_config(fragment_area: f32, layer_size: u32) -> StreamConfig {
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
fn cache_layer_size(dataset: &Dataset, device: &Device) -> u32 {
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
fn stream_config(
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
    }
}

/// The streamer and renderer of a city; `faults` makes chosen reads of the
/// dataset fail (`--inject-read-failures`).
#[allow(clippy::too_many_arguments)]
fn city_gpu(
    device: &Arc<Device>,
    commands: &mut CommandContext,
    dataset: &Arc<Dataset>,
    city: &CityGeometry,
    policy: Box<dyn citystream_streaming::controller::LoadPolicy>,
    config: &StreamConfig,
    faults: Option<FaultPlan>,
    tree: Option<&AtlasTree>,
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
    let renderer = CityRenderer::new(
        device,
        commands,
        vertices,
        &dataset.scene.indices,
        meshes.to_vec(),
        streamer.cache(),
        streamer.compactor(),
    )?;
    Ok(CityGpu { streamer, renderer })
}

/// The streamer and renderer of the run the options ask for (policy,
/// budget, eviction, clock, frames in flight, injected failures).
#[allow(clippy::too_many_arguments)]
fn streamed_city_gpu(
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
    let budget = match args.memory_budget_mb.bytes() {
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
    )
}

/// The mip deficit of one frame: the weighted mean, over the meshes whose
/// feedback weight reaches `tau` (those streaming serves), of displayed minus
/// needed level; 0 when everything needed is shown.
fn mip_deficit(entries: &[FeedbackEntry], tau: u32, meshes: &[CityMesh], cache: &GpuTextureCache) -> Option<f64> {
    let (mut weighted, mut total) = (0.0f64, 0.0f64);
    for (entry, _, needed, displayed) in served_levels(entries, tau, meshes, cache) {
        let weight = f64::from(entry.weight);
        weighted += weight * (displayed - needed).max(0.0);
        total += weight;
    }
    (total > 0.0).then(|| weighted / total)
}

/// Textures that feedback entries reaching `tau` show at least a whole
/// level coarser than they need: what streaming has still to deliver.
fn pending_textures(entries: &[FeedbackEntry], tau: u32, meshes: &[CityMesh], cache: &GpuTextureCache) -> usize {
    let mut pending: Vec<u32> = served_levels(entries, tau, meshes, cache)
        .filter(|(_, _, needed, displayed)| displayed - needed >= 1.0)
        .map(|(_, mesh, _, _)| mesh.texture)
        .collect();
    pending.sort_unstable();
    pending.dedup();
    pending.len()
}

/// For each entry reaching `tau`: its mesh, the level it needs and the level
/// the cache displays (the coarsest when the texture is not sampleable).
fn served_levels<'a>(
    entries: &'a [FeedbackEntry],
    tau: u32,
    meshes: &'a [CityMesh],
    cache: &'a GpuTextureCache,
) -> impl Iterator<Item = (&'a FeedbackEntry, &'a CityMesh, f64, f64)> + 'a {
    entries
        .iter()
        .filter(move |e| e.weight >= tau)
        .filter_map(move |entry| {
            let mesh = meshes.get(entry.mesh_id as usize)?;
            let needed = f64::from(entry.mip) / f64::from(FEEDBACK_MIP_ONE);
            let displayed = match cache.texture_data(mesh.texture) {
                Some(d) if d.state == TEXTURE_SAMPLEABLE => needed
                    .max(f64::from(d.lowest_mip))
                    .min(f64::from(d.mip_count.saturating_sub(1))),
                _ => f64::from(mesh.max_mip()),
            };
            Some((entry, mesh, needed, displayed))
        })
}

/// Loads, into the reference streamer, every level from the one each seen
/// mesh needs up to its coarsest, with no budget or load size; returns how
/// many textures the reference cache had to evict (0 for a faithful reference).
fn load_reference(
    reference: &mut CityGpu,
    commands: &mut CommandContext,
    entries: &[FeedbackEntry],
    meshes: &[CityMesh],
) -> Result<u32> {
    let mut needed: Vec<(u32, u32)> = entries
        .iter()
        .filter_map(|e| {
            meshes
                .get(e.mesh_id as usize)
                .map(|m| (m.texture, e.mip / FEEDBACK_MIP_ONE as u32))
        })
        .collect();
    needed.sort_unstable();
    needed.dedup_by_key(|(t, _)| *t);
    let evicted = reference.streamer.load_now(&needed, commands)?;
    Ok(evicted.len() as u32)
}

const CSV_HEADER: &str = "frame,time_s,dt_ms,tw_ms,tm_ms,tb_ms,tbl_ms,tbu_ms,load_size_mb,mip_bias,mips,bytes,\
                          blocks_bound,resident_bytes,mip_deficit,psnr_db,mse,ground_psnr_db,ground_mse,\
                          eye_x,eye_y,eye_z,look_x,look_y,look_z";

/// One frame's line of frames.csv.
struct CsvRow<'a> {
    frame: u32,
    time_s: f64,
    frame_ms: f64,
    telemetry: &'a citystream_streaming::controller::Telemetry,
    applied: &'a citystream_engine::texture_cache::CycleReport,
    resident: u64,
    deficit: Option<f64>,
    /// The facades' and the ground's error, on measured frames.
    error: Option<FrameError>,
    ground_error: Option<FrameError>,
    camera: &'a Camera,
}

fn write_csv_row(csv: &mut impl Write, row: &CsvRow) -> Result<()> {
    let t = row.telemetry;
    let (eye, look) = (row.camera.eye, row.camera.target);
    // The pose exactly (shortest round-trip form): a replay is compared with it.
    writeln!(
        csv,
        "{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
        row.frame,
        row.time_s,
        row.frame_ms,
        t.tw_ms,
        t.tm_ms,
        t.tb_ms,
        t.tbl_ms,
        t.tbu_ms,
        t.load_size_mb,
        t.mip_bias,
        row.applied.mips_uploaded,
        row.applied.bytes_uploaded,
        row.applied.blocks_bound,
        row.resident,
        optional(row.deficit),
        // The error exactly (shortest round-trip form), so that figures recomputed from the
        // CSV equal the summary's.
        exact(row.error.map(|e| e.psnr_db)),
        exact(row.error.map(|e| e.mse)),
        exact(row.ground_error.map(|e| e.psnr_db)),
        exact(row.ground_error.map(|e| e.mse)),
        eye.x,
        eye.y,
        eye.z,
        look.x,
        look.y,
        look.z,
    )?;
    Ok(())
}

fn optional(value: Option<f64>) -> String {
    value
        .filter(|v| v.is_finite())
        .map(|v| format!("{v:.4}"))
        .unwrap_or_default()
}

/// A measured value in shortest round-trip form; empty when not measured.
fn exact(value: Option<f64>) -> String {
    value.map(|v| v.to_string()).unwrap_or_default()
}

/// The visible and feedback targets of the city passes and the feedback view.
struct CityTargets {
    target: RenderTarget,
    /// A quarter of the visible resolution per axis.
    feedback_target: RenderTarget,
    view: FeedbackView,
    /// Visible pixels one feedback fragment stands for.
    fragment_area: f32,
}

fn city_targets(device: &Arc<Device>, width: u32, height: u32) -> Result<CityTargets> {
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
type CityGeometry = (Vec<Vertex>, Vec<CityMesh>);

/// The dataset (with the remote settings of `args` where it is a URL) with its vertices and
/// meshes in the engine's layout.
fn open_city(args: &Args, dir: &std::path::Path) -> Result<(Arc<Dataset>, CityGeometry)> {
    let options = args.remote.options_with_cache(&args.mip_cache)?;
    let dataset = Arc::new(citystream_tools::open_dataset_with(dir, &options)?);
    let city = city_geometry(&dataset)?;
    Ok((dataset, city))
}

/// The atlas-tree strategy's state: the tree, its visible pass, and what it drew.
struct TreeRun {
    tree: AtlasTree,
    renderer: AtlasTreeRenderer,
    /// Bytes the ideal block set may take: most of the memory budget, the rest left for
    /// blocks on their way in and out.
    capacity_bytes: u64,
    atlas_mips: u32,
    scene_meshes: u32,
    /// Per frame: nodes drawn with an ancestor's atlas, and blocks in the ideal set.
    fallbacks: Vec<f64>,
    ideal_blocks: Vec<f64>,
    /// Frames whose wanted blocks did not all fit the capacity.
    frames_over_capacity: u64,
}

/// What one tree frame drew.
struct TreeFrame {
    nodes_drawn: u32,
    draw_calls: u32,
}

/// `summary.json`'s `atlas_tree`.
#[derive(Debug, serde::Serialize)]
struct TreeSummary {
    nodes: usize,
    leaves: usize,
    depth: u32,
    atlas_extent: u32,
    capacity_bytes: Option<u64>,
    fallbacks: Stats,
    ideal_blocks: Stats,
    frames_over_capacity: u64,
}

impl TreeRun {
    fn new(
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
    fn view(&self, camera: &Camera, width: u32, height: u32) -> TreeView {
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
    fn record_frame(
        &mut self,
        cmd: citystream_engine::vk::CommandBuffer,
        slot: u32,
        gpu: &mut CityGpu,
        dataset: &Dataset,
        target: &RenderTarget,
        camera: &Camera,
        ground: Option<&citystream_engine::ground::GroundLayer>,
    ) -> Result<TreeFrame> {
        let view = self.view(camera, target.width(), target.height());
        let tree = &self.tree;
        let cache = gpu.streamer.cache();
        let sampleable_from = |texture: u32, level: u32| {
            cache
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
            .record_visible(cmd, slot, &gpu.renderer, target, camera, true, ground)?;
        let nodes_drawn = selection.draws.len() as u32;
        self.fallbacks.push(f64::from(selection.fallbacks));
        Ok(TreeFrame {
            nodes_drawn,
            draw_calls: draws.atlas_draws + original_draws,
        })
    }

    fn summary(&self, budget: Option<u64>) -> TreeSummary {
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

/// Draws of the feedback strategy's frame as a renderer binding one texture per draw
/// issues them: one per mesh in view.
fn meshes_in_view(scene: &citystream_streaming::dataset::Scene, camera: &Camera, width: u32, height: u32) -> u32 {
    let planes = frustum_planes(
        camera
            .view_projection(width as f32 / height as f32, 0.0)
            .to_cols_array_2d(),
    );
    scene
        .meshes
        .iter()
        .filter(|mesh| mesh.index_count > 0 && intersects_frustum(&mesh.bounds, &planes))
        .count() as u32
}

/// The feedback entries (reaching `tau`) of the fully resident reference's own feedback
/// pass for `camera`: what the reference must load where the run has no feedback of its
/// own (the atlas-tree strategy). Its loader is handed no records, so only `load_now` fills it.
fn reference_feedback(
    reference: &mut CityGpu,
    commands: &mut CommandContext,
    targets: &CityTargets,
    camera: &Camera,
    visible_height: u32,
) -> Result<Vec<FeedbackEntry>> {
    let tau = reference.streamer.gpu_tau();
    reference.streamer.set_host_records(Vec::new())?;
    let index = feedback_frame_now(
        reference,
        commands,
        (&targets.feedback_target, &targets.view),
        camera,
        visible_height,
        Some(0),
    )?;
    feedback_reaching(&reference.streamer, index, tau)
}

/// Runs one streamer frame of feedback for `camera` (uploads, feedback pass, compaction
/// with `compact_tau` or the streamer's own threshold) and waits for it; returns the
/// frame's index, whose feedback is then readable.
fn feedback_frame_now(
    gpu: &mut CityGpu,
    commands: &mut CommandContext,
    (feedback_target, view): (&RenderTarget, &FeedbackView),
    camera: &Camera,
    visible_height: u32,
    compact_tau: Option<u32>,
) -> Result<u64> {
    let begun = gpu.streamer.begin_frame()?;
    let cmd = commands.begin()?;
    gpu.streamer.record_uploads(cmd)?;
    gpu.renderer
        .record_feedback(cmd, feedback_target, camera, view, visible_height)?;
    match compact_tau {
        Some(tau) => gpu.streamer.record_feedback_resolve_with_tau(cmd, tau)?,
        None => gpu.streamer.record_feedback_resolve(cmd)?,
    }
    let submit = gpu.streamer.end_frame(FIXED_STEP_MS)?;
    commands.submit(&submit.waits, &[submit.signal])?;
    // The frame timeline says when the feedback is readable (a fence may
    // signal before the timeline value is visible).
    gpu.streamer.wait_for_frame(begun.index)?;
    commands.wait()?;
    Ok(begun.index)
}

/// The compacted feedback entries of completed frame `index` whose weight reaches `tau`.
fn feedback_reaching<S: MipSource + 'static>(
    streamer: &TextureStreamer<S>,
    index: u64,
    tau: u32,
) -> Result<Vec<FeedbackEntry>> {
    Ok(streamer
        .feedback_of(index)?
        .map(|f| f.entries)
        .unwrap_or_default()
        .into_iter()
        .filter(|e| e.weight >= tau)
        .collect())
}

fn stream_city(args: &Args, device: &Arc<Device>, dir: &std::path::Path) -> Result<()> {
    let (dataset, city) = open_city(args, dir)?;
    let tree = match args.strategy {
        Strategy::AtlasTree => Some(citystream_tools::atlas_tree::open_tree(&dataset, dir)?),
        Strategy::Feedback => None,
    };
    let meshes = &city.1;
    let scene = &dataset.scene;
    let layer_size = cache_layer_size(&dataset, device);
    let mut commands = CommandContext::new(device, "flythrough setup and measurements")?;
    let targets = city_targets(device, args.width, args.height)?;
    let CityTargets {
        target,
        feedback_target,
        view,
        fragment_area,
    } = &targets;
    let fragment_area = *fragment_area;
    let bounds = scene.bounds;
    let size = Vec3::from(bounds.max) - Vec3::from(bounds.min);
    let extent = size.x.max(size.y).max(size.z).max(1.0);
    let path_name = args.path.as_deref().unwrap_or("standard");
    let path = camera_path(path_name, scene)?;
    path.restart();
    let duration_s = args.duration_s.unwrap_or(path.duration_s()).max(0.0);
    let frames_in_flight = args.frames_in_flight;
    let ground = match &args.ground {
        Some(dir) => {
            let set = ground::GroundSet::open(dir, &dataset)?;
            let (config, reference) = ground::ground_config(
                &set,
                scene,
                frames_in_flight,
                focal_px(args.height, &pose_camera(&path.sample_between(None, 0.0), extent)),
                lowest_eye_height(&path, duration_s, scene.bounds.min[1], extent),
                args.memory_budget_mb.bytes(),
                device,
            )?;
            Some((set, config, reference))
        }
        None => None,
    };
    let mut gpu = streamed_city_gpu(
        args,
        device,
        &mut commands,
        &dataset,
        &city,
        fragment_area,
        layer_size,
        tree.as_ref(),
        // The ground's tile array and staging come out of the same budget.
        ground.as_ref().map_or(0, |(_, config, _)| config.memory_bytes()),
    )?;
    let mut ground_run = match ground {
        Some((set, config, reference)) => Some(ground::GroundRun::new(
            device,
            set,
            config,
            (args.psnr_interval > 0).then_some(reference),
        )?),
        None => None,
    };
    let mut tree_run = match tree {
        Some(tree) => Some(TreeRun::new(args, device, &mut commands, &gpu, &dataset, tree)?),
        None => None,
    };
    // The error reference: every needed level resident, no budget, loaded
    // synchronously between frames (its policy never runs).
    let mut reference = if args.psnr_interval > 0 {
        Some(city_gpu(
            device,
            &mut commands,
            &dataset,
            &city,
            PolicyKind::Baseline.build(&PolicyOptions::default())?,
            &reference_config(fragment_area, layer_size),
            None,
            None,
        )?)
    } else {
        None
    };
    // One command buffer per frame in flight: a frame's is reused only after
    // the streamer's throttle saw that frame complete.
    let mut frame_commands = (0..frames_in_flight)
        .map(|i| CommandContext::new(device, &format!("flythrough frame (slot {i})")))
        .collect::<std::result::Result<Vec<_>, _>>()?;
    let latency = BindLatencyModel::preset(args.bind_latency);
    let mut latency_rng = SplitMix64::new(args.seed);
    let mut pass_times = PassTimes::new(device, frames_in_flight)?;

    // With the fixed clock the frame count follows from the duration; with
    // the modelled one it is at most that.
    let frames = args
        .frames
        .unwrap_or_else(|| ((duration_s * 1000.0 / FIXED_STEP_MS).ceil() as u32).max(1));
    eprintln!(
        "path: {} ({:.1} s, pauses at {:?} s, jumps at {:?} s)",
        path_name,
        path.duration_s(),
        path.pauses()
            .iter()
            .map(|p| (p.start_s * 10.0).round() / 10.0)
            .collect::<Vec<_>>(),
        path.jumps()
            .iter()
            .map(|t| (t * 10.0).round() / 10.0)
            .collect::<Vec<_>>()
    );
    // τ in the feedback's fixed point: per feedback fragment, not per visible one.
    let tau = gpu.streamer.gpu_tau();
    eprintln!(
        "scene: {} ({} meshes, {} textures), {} frame(s) in flight",
        dir.display(),
        scene.meshes.len(),
        dataset.textures.len(),
        frames_in_flight
    );

    let csv_path = args.out.join("frames.csv");
    let mut csv = std::io::BufWriter::new(
        std::fs::File::create(&csv_path).with_context(|| format!("creating {}", csv_path.display()))?,
    );
    writeln!(csv, "{CSV_HEADER}")?;
    let mut summary = SummaryBuilder::new();
    let mut deficits = Vec::new();
    let mut errors = ErrorSeries::new();
    let mut clock = CpuFrameClock::new();
    let started = std::time::Instant::now();
    let mut written = Vec::new();
    let mut sim_time_s = 0.0f64;
    let mut frame_ms = FIXED_STEP_MS;
    let (mut mips_total, mut blocks_total, mut peak_resident) = (0u64, 0u64, 0u64);
    let mut peak_device_memory = 0u64;
    let mut reference_incomplete = 0u32;
    let mut frames_run = 0;
    let mut waits = WaitCounts::default();
    let mut last_feedback_frame = None;
    let mut warned_over_budget = false;
    let mut warned_failure = false;
    let mut uploads_at: Vec<(f64, u64)> = Vec::new();
    let (mut nodes_drawn, mut draw_call_samples) = (Vec::new(), Vec::new());
    for frame in 0..frames {
        let time_s = match args.clock {
            Clock::Fixed | Clock::Modelled => sim_time_s,
            Clock::Real => started.elapsed().as_secs_f64(),
        };
        let path_done = match args.clock {
            Clock::Real => time_s > duration_s,
            Clock::Modelled => time_s >= duration_s,
            Clock::Fixed => false,
        };
        if args.frames.is_none() && path_done {
            break;
        }
        frames_run += 1;
        let camera = pose_camera(&path.sample(time_s), extent);
        let measure_error = reference.is_some() && frame % args.psnr_interval.max(1) == 0;
        let write_frame = frame_interval(args) > 0 && frame % frame_interval(args) == 0;

        // Algorithm 1 through the streamer: retire finished frames, hand
        // completed feedback to the loader, pack and bind what it loaded.
        let begun = gpu.streamer.begin_frame()?;
        if begun.over_budget && !warned_over_budget {
            warned_over_budget = true;
            eprintln!(
                "\nwarning: from frame {frame} the view needs more texture memory than the {} MB budget holds; \
                 showing the most important levels that fit (frames over budget are counted in summary.json)",
                args.memory_budget_mb.0.unwrap_or(0)
            );
        }
        if !warned_failure && gpu.streamer.totals().failed > 0 {
            warned_failure = true;
            if let Some(first) = gpu.streamer.load_failures().first() {
                eprintln!(
                    "\nwarning: from frame {frame} textures fail to load; the first{}: {} \
                     (counted in summary.json; the run will exit non-zero unless --allow-load-failures)",
                    first.level.map(|l| format!(", at level {l}")).unwrap_or_default(),
                    first.reason
                );
            }
        }
        // The deficit of the feedback just consumed (from frames_in_flight
        // frames ago with the fixed clock), against the host's table as
        // begin_frame left it: this frame's evictions applied, its uploads not yet.
        let deficit = match gpu.streamer.latest_feedback() {
            Some((from, entries)) if last_feedback_frame != Some(from) => {
                last_feedback_frame = Some(from);
                mip_deficit(entries, tau, meshes, gpu.streamer.cache())
            }
            _ => None,
        };
        // The streamer's throttle saw this slot's last frame complete.
        let slot = begun.slot;
        // Patches that arrived, and the ground tiles this frame's share of the load size
        // pays for; charged to the facades' next loading cycle.
        let ground_frame = match ground_run.as_mut() {
            Some(run) => {
                let frame = run.update(time_s, slot, &camera, gpu.streamer.decision().load_size_bytes)?;
                gpu.streamer.charge_host_uploads(frame.bytes);
                frame
            }
            None => Default::default(),
        };
        pass_times.collect(slot)?;
        let commands_of_frame = &mut frame_commands[slot as usize];
        let cmd = commands_of_frame.begin_completed()?;
        pass_times.begin(cmd, slot, 0);
        let applied = gpu.streamer.record_uploads(cmd)?;
        if let Some(run) = ground_run.as_mut() {
            run.layer.record_uploads(cmd, slot)?;
        }
        pass_times.end(cmd, slot, 0);
        // The atlas tree has no feedback: its two passes stay empty (0 ms).
        pass_times.begin(cmd, slot, 1);
        if tree_run.is_none() {
            gpu.renderer
                .record_feedback(cmd, feedback_target, &camera, view, args.height)?;
        }
        pass_times.end(cmd, slot, 1);
        pass_times.begin(cmd, slot, 2);
        // The error reference needs every seen mesh: τ = 0 then.
        match (&tree_run, measure_error) {
            (Some(_), _) => {}
            (None, true) => gpu.streamer.record_feedback_resolve_with_tau(cmd, 0)?,
            (None, false) => gpu.streamer.record_feedback_resolve(cmd)?,
        }
        pass_times.end(cmd, slot, 2);
        pass_times.begin(cmd, slot, 3);
        let draw_calls = match tree_run.as_mut() {
            Some(run) => {
                let ground = ground_run.as_ref().map(|g| &g.layer);
                let drawn = run.record_frame(cmd, slot, &mut gpu, &dataset, target, &camera, ground)?;
                nodes_drawn.push(f64::from(drawn.nodes_drawn));
                drawn.draw_calls
            }
            None => {
                match ground_run.as_ref() {
                    Some(run) => {
                        gpu.renderer
                            .record_visible_on_ground(cmd, target, &camera, true, (&run.layer, slot))?
                    }
                    None => gpu.renderer.record_visible(cmd, target, &camera, 1.0, true),
                }
                meshes_in_view(scene, &camera, args.width, args.height)
            }
        };
        draw_call_samples.push(f64::from(draw_calls));
        pass_times.end(cmd, slot, 3);
        // The controller step with the previous frame's latency.
        let submit = gpu.streamer.end_frame(frame_ms)?;
        commands_of_frame.submit_frame(&submit.waits, &[submit.signal])?;
        waits.count(begun.cpu_wait, false);

        let (mut error, mut ground_error) = (None, None);
        if write_frame || measure_error {
            // Reading this frame's image back is a wait outside the steady state.
            waits.count(gpu.streamer.wait_for_frame(begun.index)?, true);
            let pixels = target.read_pixels()?;
            if write_frame {
                let path = frames_dir_path(args).join(format!("frame_{frame:05}.png"));
                write_png(&pixels, &path)?;
                written.push(path.display().to_string());
            }
            if let (true, Some(reference)) = (measure_error, reference.as_mut()) {
                // The reference loads what the loader serves (entries
                // reaching τ); lighter ones are read back for eviction only.
                let entries: Vec<FeedbackEntry> = match tree_run {
                    Some(_) => reference_feedback(reference, &mut commands, &targets, &camera, args.height)?,
                    None => feedback_reaching(&gpu.streamer, begun.index, tau)?,
                };
                reference_incomplete += load_reference(reference, &mut commands, &entries, meshes)?;
                let cmd = commands.begin()?;
                // On the streamed ground, so that this error is the facades' alone
                // (`ground_psnr_db` measures the ground's).
                match ground_run.as_ref() {
                    Some(run) => {
                        reference
                            .renderer
                            .record_visible_on_ground(cmd, target, &camera, true, (&run.layer, slot))?
                    }
                    None => reference.renderer.record_visible(cmd, target, &camera, 1.0, true),
                }
                commands.submit_and_wait(&[])?;
                error = Some(FrameError::of_images(&pixels, &target.read_pixels()?));
            }
            if let (true, Some(run)) = (measure_error, ground_run.as_mut()) {
                ground_error = run.measure(&mut commands, &gpu.renderer, target, &camera, slot)?;
            }
        }

        frame_ms = frame_latency(
            args.clock,
            &applied,
            ground_frame.bytes,
            &latency,
            &mut latency_rng,
            || clock.tick().as_secs_f64() * 1000.0,
        );
        let bytes = applied.bytes_uploaded;
        let mips = u64::from(applied.mips_uploaded);
        mips_total += mips;
        blocks_total += u64::from(applied.blocks_bound);
        let resident = gpu.streamer.cache().utilisation().bound_bytes;
        peak_resident = peak_resident.max(resident);
        if frame % 30 == 0 {
            peak_device_memory = peak_device_memory.max(device.device_memory_bytes().unwrap_or(0));
        }

        sim_time_s += match args.clock {
            Clock::Modelled => frame_ms.max(FIXED_STEP_MS),
            _ => FIXED_STEP_MS,
        } / 1000.0;
        let t = gpu.streamer.policy().telemetry();
        summary.push_frame(frame_ms, t.tw_ms, t.load_size_mb, t.mip_bias, mips, bytes);
        deficits.extend(deficit);
        if let Some(error) = error {
            errors.push(error);
        }
        uploads_at.push((time_s, mips));
        write_csv_row(
            &mut csv,
            &CsvRow {
                frame,
                time_s,
                frame_ms,
                telemetry: &t,
                applied: &applied,
                resident,
                deficit,
                error,
                ground_error,
                camera: &camera,
            },
        )?;
        let mb_per_s = bytes as f64 / 1e6 / (frame_ms / 1000.0).max(1e-6);
        status(
            frame,
            frames,
            frame_ms,
            t.load_size_mb,
            t.mip_bias,
            mb_per_s,
            resident as f64 / 1e6,
        );
    }
    if std::io::IsTerminal::is_terminal(&std::io::stderr()) {
        eprintln!();
    }
    csv.flush()?;
    device.wait_idle()?;
    let gpu_pass_ms = pass_times.finish()?;
    let peak_device_memory = peak_device_memory.max(device.device_memory_bytes().unwrap_or(0));
    if reference_incomplete > 0 {
        eprintln!("warning: the error reference evicted {reference_incomplete} textures; PSNR is optimistic");
    }
    let validation_errors = device.validation_log().error_count();
    let summary = summary.finish();
    let residency = gpu.streamer.residency_totals();
    let pause_uploads_second_half = path
        .pauses()
        .iter()
        .map(|pause| {
            let from = pause.start_s + pause.duration_s / 2.0;
            let to = pause.start_s + pause.duration_s;
            uploads_at
                .iter()
                .filter(|(t, _)| *t >= from && *t < to)
                .map(|(_, mips)| mips)
                .sum()
        })
        .collect();
    let run = Run {
        device: describe(device),
        scene: dir.display().to_string(),
        strategy: args.strategy.name(),
        draw_calls: Stats::from_samples(&draw_call_samples),
        nodes_drawn: (!nodes_drawn.is_empty()).then(|| Stats::from_samples(&nodes_drawn)),
        atlas_tree: tree_run.as_ref().map(|run| run.summary(args.memory_budget_mb.bytes())),
        policy: gpu.streamer.policy().kind().name(),
        alpha_ms: args.alpha,
        mip_deficit: (!deficits.is_empty()).then(|| Stats::from_samples(&deficits)),
        error: PrefixedErrorFigures {
            prefix: "",
            figures: errors.figures(),
        },
        ground_tiles_uploaded: ground_run.as_ref().map(|g| g.layer.totals().tiles_uploaded),
        ground_mb_streamed: ground_run
            .as_ref()
            .map(|g| g.layer.totals().bytes_uploaded as f64 / f64::from(1 << 20)),
        ground_error: PrefixedErrorFigures {
            prefix: "ground_",
            figures: ground_run.as_ref().and_then(|g| g.errors.figures()),
        },
        ground: ground_run
            .as_ref()
            .zip(args.ground.as_deref())
            .map(|(g, dir)| g.summary(dir)),
        clock: args.clock.name(),
        bind_latency: args.bind_latency.name(),
        width: args.width,
        height: args.height,
        duration_s: match args.clock {
            Clock::Real => started.elapsed().as_secs_f64(),
            Clock::Fixed | Clock::Modelled => sim_time_s,
        },
        wall_s: started.elapsed().as_secs_f64(),
        wall_ms_per_frame: started.elapsed().as_secs_f64() * 1000.0 / f64::from(frames_run.max(1)),
        frames_in_flight,
        cpu_wait_frames: waits.throttle_frames,
        cpu_wait_ms: waits.throttle_ms,
        readback_wait_frames: waits.readback_frames,
        mips_streamed: mips_total,
        unique_bytes_streamed: residency.unique_bytes_uploaded,
        blocks_bound: blocks_total,
        peak_resident_bytes: peak_resident,
        peak_device_memory_bytes: peak_device_memory,
        memory_budget_bytes: args.memory_budget_mb.bytes(),
        eviction: args.eviction.name(),
        cache_layers: gpu
            .streamer
            .cache()
            .packing()
            .images()
            .iter()
            .map(|i| i.layer_count)
            .collect(),
        frames_over_budget: residency.frames_over_budget,
        pause_uploads_second_half,
        dropped_levels: residency.dropped_levels,
        evicted_layers: residency.evicted_layers,
        refused_for_room: residency.refused_for_room,
        declined_loads: residency.declined_loads,
        load_failures: gpu.streamer.totals().failed,
        read_retries: gpu.streamer.totals().read_retries,
        textures_failed: gpu.streamer.failed_textures(),
        cache_layer_size: layer_size,
        gpu_pass_ms,
        validation_errors,
        frames_written: written,
        mip_cache: dataset.textures.mip_cache().map(|cache| MipCacheSummary {
            dir: cache.dir().display().to_string(),
            capacity_bytes: cache.capacity_bytes(),
            stats: cache.stats(),
        }),
    };
    let mut json = serde_json::to_value(summary)?;
    if let (Some(object), serde_json::Value::Object(extra)) = (json.as_object_mut(), serde_json::to_value(&run)?) {
        object.extend(extra);
    }
    let path = args.out.join("summary.json");
    std::fs::write(&path, serde_json::to_string_pretty(&json)?)
        .with_context(|| format!("writing {}", path.display()))?;
    eprintln!(
        "{} frames, {} mips streamed, wrote {} frames, {} and {}; the CPU waited for the GPU in {} frame(s) \
         ({:.1} ms) plus {} image read-back(s)",
        frames_run,
        mips_total,
        run.frames_written.len(),
        csv_path.display(),
        path.display(),
        waits.throttle_frames,
        waits.throttle_ms,
        waits.readback_frames,
    );
    if let Some(cache) = &run.mip_cache {
        eprintln!(
            "mip cache {}: {} hits, {} misses, {:.1} MB written, {} evicted, {} damaged (capacity {:.0} MB)",
            cache.dir,
            cache.stats.hits,
            cache.stats.misses,
            cache.stats.written_bytes as f64 / f64::from(1 << 20),
            cache.stats.evicted,
            cache.stats.damaged,
            cache.capacity_bytes as f64 / f64::from(1 << 20)
        );
    }
    let failures = gpu.streamer.load_failures();
    drop(reference);
    drop(ground_run);
    drop(tree_run);
    drop(gpu);
    if validation_errors > 0 {
        bail!("{validation_errors} Vulkan validation error(s) during the run");
    }
    if run.textures_failed > 0 {
        let first = failures
            .first()
            .map(|f| format!("; the first: {}", f.reason))
            .unwrap_or_default();
        let message = format!(
            "{} texture(s) failed to load ({} failure(s)){first}",
            run.textures_failed, run.load_failures
        );
        if !args.allow_load_failures {
            bail!("{message}; the frames show their colormap colour or coarser levels (--allow-load-failures exits 0)");
        }
        eprintln!("warning: {message}");
    }
    Ok(())
}

/// Frames in which the render thread blocked on the GPU.
#[derive(Debug, Default)]
struct WaitCounts {
    /// Frames whose slot was still in use by the GPU (the throttle blocked).
    throttle_frames: u32,
    throttle_ms: f64,
    /// Frames whose image was read back (PNG frames, PSNR), which waits.
    readback_frames: u32,
}

impl WaitCounts {
    fn count(&mut self, waited: Duration, readback: bool) {
        if readback {
            self.readback_frames += 1;
        } else if !waited.is_zero() {
            self.throttle_frames += 1;
            self.throttle_ms += waited.as_secs_f64() * 1000.0;
        }
    }
}

#[derive(Debug, serde::Serialize)]
struct PopIn {
    frames: u32,
    max_mse_direct: f64,
    max_mse_blended: f64,
    mse_direct: Vec<f64>,
    mse_blended: Vec<f64>,
    paper_max_mse_direct: f64,
    paper_max_mse_blended: f64,
}

fn pop_in(args: &Args, device: &Arc<Device>, dir: &std::path::Path) -> Result<()> {
    let (dataset, city) = open_city(args, dir)?;
    let meshes = &city.1;
    let scene = &dataset.scene;
    let layer_size = cache_layer_size(&dataset, device);
    let mut commands = CommandContext::new(device, "pop-in frame")?;
    let CityTargets {
        target,
        feedback_target,
        view,
        fragment_area,
    } = city_targets(device, args.width, args.height)?;
    // Levels are loaded explicitly, one per frame: the policy never runs.
    let mut gpu = city_gpu(
        device,
        &mut commands,
        &dataset,
        &city,
        PolicyKind::Baseline.build(&PolicyOptions::default())?,
        &reference_config(fragment_area, layer_size),
        None,
        None,
    )?;
    // The view of the path's first pause: the static view a user replaying
    // the benchmark sees longest.
    let size = Vec3::from(scene.bounds.max) - Vec3::from(scene.bounds.min);
    let extent = size.x.max(size.y).max(size.z).max(1.0);
    let path = camera_path(args.path.as_deref().unwrap_or("standard"), scene)?;
    let at = path.pauses().first().map_or(0.0, |p| p.start_s);
    let camera = pose_camera(&path.sample_between(None, at), extent);
    // What the static view needs: one streamer frame of feedback.
    let index = feedback_frame_now(
        &mut gpu,
        &mut commands,
        (&feedback_target, &view),
        &camera,
        args.height,
        None,
    )?;
    let entries = gpu
        .streamer
        .feedback_of(index)?
        .context("the pop-in view's feedback frame did not complete")?
        .entries;
    let source = gpu.streamer.source().inner().clone();
    let mut wanted: Vec<(u32, u32, u32)> = Vec::new(); // (texture, needed level, next level to load)
    for entry in &entries {
        let Some(mesh) = meshes.get(entry.mesh_id as usize) else {
            continue;
        };
        let chain = source.mip_chain(mesh.texture)?;
        let needed = (entry.mip / FEEDBACK_MIP_ONE as u32).min(chain.mip_count - 1);
        wanted.push((mesh.texture, needed, chain.mip_count - 1));
    }
    wanted.sort_unstable();
    wanted.dedup_by_key(|w| w.0);
    eprintln!("pop-in: {} textures refine from their coarsest level", wanted.len());

    let render = |gpu: &CityGpu, commands: &mut CommandContext, blend: bool| -> Result<image::RgbaImage> {
        let cmd = commands.begin()?;
        gpu.renderer.record_visible(cmd, &target, &camera, 1.0, blend);
        commands.submit_and_wait(&[])?;
        Ok(target.read_pixels()?)
    };
    let mut previous: Option<(image::RgbaImage, image::RgbaImage)> = None;
    let (mut mse_direct, mut mse_blended) = (Vec::new(), Vec::new());
    let mut frames = 0;
    loop {
        // Frame 0 shows nothing resident; each later frame loads one level,
        // the next finer one, of every texture still coarser than needed.
        let mut levels = Vec::new();
        for (texture, needed, next) in wanted.iter_mut() {
            if frames == 0 || *next == u32::MAX || *next < *needed {
                continue;
            }
            levels.push((*texture, *next));
            *next = next.checked_sub(1).unwrap_or(u32::MAX);
        }
        let loaded = levels.len();
        gpu.streamer.load_levels_now(&levels, &mut commands)?;
        let direct = render(&gpu, &mut commands, false)?;
        let blended = render(&gpu, &mut commands, true)?;
        if frame_interval(args) > 0 && frames % frame_interval(args) == 0 {
            write_png(
                &direct,
                &frames_dir_path(args).join(format!("popin_direct_{frames:03}.png")),
            )?;
            write_png(
                &blended,
                &frames_dir_path(args).join(format!("popin_blended_{frames:03}.png")),
            )?;
        }
        if let Some((d, b)) = &previous {
            mse_direct.push(mse(d, &direct));
            mse_blended.push(mse(b, &blended));
        }
        previous = Some((direct, blended));
        frames += 1;
        if (frames > 1 && loaded == 0) || frames > 64 {
            break;
        }
    }
    device.wait_idle()?;
    let max = |v: &[f64]| v.iter().copied().fold(0.0f64, f64::max);
    let result = PopIn {
        frames,
        max_mse_direct: max(&mse_direct),
        max_mse_blended: max(&mse_blended),
        mse_direct,
        mse_blended,
        paper_max_mse_direct: 438.0,
        paper_max_mse_blended: 62.0,
    };
    let path = args.out.join("popin.json");
    std::fs::write(&path, serde_json::to_string_pretty(&result)?)
        .with_context(|| format!("writing {}", path.display()))?;
    println!(
        "pop-in over {} frames: max inter-frame MSE {:.1} with direct sampling, {:.1} with colormap blending \
         (paper: 438 -> 62); wrote {}",
        result.frames,
        result.max_mse_direct,
        result.max_mse_blended,
        path.display()
    );
    drop(gpu);
    let errors = device.validation_log().error_count();
    if errors > 0 {
        bail!("{errors} Vulkan validation error(s) during the run");
    }
    Ok(())
}

/// `--frame-interval`: 20 by default headless, 0 in the window.
fn frame_interval(args: &Args) -> u32 {
    args.frame_interval.unwrap_or(if args.window { 0 } else { 20 })
}

fn frames_dir_path(args: &Args) -> PathBuf {
    args.out.join("frames")
}

fn placeholder_city(args: &Args, device: &Arc<Device>) -> Result<()> {
    let geometry = placeholder::city(args.seed, args.blocks);
    let textures = placeholder::textures(args.seed)?;
    let mut commands = CommandContext::new(device, "flythrough frame")?;
    let renderer = MeshRenderer::new(
        device,
        &mut commands,
        &geometry,
        &textures,
        Filtering::Trilinear { max_anisotropy: 8 },
    )?;
    let target = RenderTarget::new(device, args.width, args.height)?;
    let extent = args.blocks as f32 * 30.0;
    let aspect = args.width as f32 / args.height as f32;
    let mut clock = CpuFrameClock::new();
    let mut summary = SummaryBuilder::new();
    let mut written = Vec::new();
    let started = std::time::Instant::now();
    let frames = args.frames.unwrap_or(240);
    for frame in 0..frames {
        let camera = orbit_camera(Vec3::new(0.0, 15.0, 0.0), extent, 0.0, frame as f64 / frames as f64);
        let cmd = commands.begin()?;
        target.begin(device, cmd, [0.55, 0.7, 0.9, 1.0]);
        renderer.record(cmd, camera.view_projection(aspect, 0.0), [0.4, 0.8, 0.3, 1.0]);
        target.end_and_copy(device, cmd);
        commands.submit_and_wait(&[])?;
        if frame_interval(args) > 0 && frame % frame_interval(args) == 0 {
            let path = frames_dir_path(args).join(format!("frame_{frame:05}.png"));
            write_png(&target.read_pixels()?, &path)?;
            written.push(path.display().to_string());
        }
        let dt = clock.tick().as_secs_f64() * 1000.0;
        summary.push_frame(dt, dt, 0.0, 0.0, 0, 0);
        status(frame, frames, dt, 0.0, 0.0, 0.0, 0.0);
    }
    if std::io::IsTerminal::is_terminal(&std::io::stderr()) {
        eprintln!();
    }
    device.wait_idle()?;
    let validation_errors = device.validation_log().error_count();
    let mut json = serde_json::to_value(summary.finish())?;
    if let Some(object) = json.as_object_mut() {
        object.insert("device".into(), describe(device).into());
        object.insert(
            "scene".into(),
            format!(
                "placeholder city (seed {}, {}x{} blocks)",
                args.seed, args.blocks, args.blocks
            )
            .into(),
        );
        object.insert("duration_s".into(), started.elapsed().as_secs_f64().into());
        object.insert("validation_errors".into(), validation_errors.into());
        object.insert("frames_written".into(), written.into());
    }
    let path = args.out.join("summary.json");
    std::fs::write(&path, serde_json::to_string_pretty(&json)?)
        .with_context(|| format!("writing {}", path.display()))?;
    eprintln!("wrote {}", path.display());
    if validation_errors > 0 {
        bail!("{validation_errors} Vulkan validation error(s) during the run");
    }
    Ok(())
}
