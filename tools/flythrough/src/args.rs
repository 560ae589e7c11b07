//! The flythrough's command line: options, their parsers, and the fixed clock's constants.

use std::path::PathBuf;

use clap::{Parser, ValueEnum};

use citystream_engine::present::PresentMode;
use citystream_engine::texture_cache::Eviction;
use citystream_streaming::bind_latency::BindLatencyPreset;
use citystream_streaming::controller::PolicyKind;
use citystream_streaming::disk_model::DiskModelChoice;
use citystream_streaming::loader::PlanOrder;
use citystream_streaming::source::FaultPlan;

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub(crate) enum Clock {
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
    pub(crate) fn is_modelled(self) -> bool {
        self != Clock::Real
    }

    /// How far the camera moves along its path with a frame of `frame_ms`: the real clock's
    /// follows the time the frame took, the fixed clock's a 60 Hz step, the modelled
    /// clock's the frame's modelled latency, at least `display_period_ms`.
    pub(crate) fn path_advance_ms(self, frame_ms: f64, display_period_ms: f64) -> f64 {
        match self {
            Clock::Real => frame_ms,
            Clock::Fixed => FIXED_STEP_MS,
            Clock::Modelled => frame_ms.max(display_period_ms),
        }
    }

    /// The name written to summary.json.
    pub(crate) fn name(self) -> &'static str {
        match self {
            Clock::Real => "real",
            Clock::Fixed => "fixed",
            Clock::Modelled => "modelled",
        }
    }
}

/// `--controller-latency`: what the controller is fed under `--clock modelled`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub(crate) enum ControllerLatency {
    /// The frame's modelled work.
    Work,
    /// The interval between frames: the work or the display period, whichever is longer.
    Period,
}

impl ControllerLatency {
    /// The name written to summary.json.
    pub(crate) fn name(self) -> &'static str {
        match self {
            ControllerLatency::Work => "work",
            ControllerLatency::Period => "period",
        }
    }
}

/// `--display-period-ms`: finite, in [0, 1000].
fn parse_display_period_ms(text: &str) -> Result<f64, String> {
    let ms: f64 = text
        .parse()
        .map_err(|_| format!("`{text}` is not a number of milliseconds"))?;
    if !(ms.is_finite() && (0.0..=1000.0).contains(&ms)) {
        return Err(format!("{text} ms is not a display period in [0, 1000] ms"));
    }
    Ok(ms)
}

/// `--render-ms`: finite, in (0, 1000].
fn parse_render_ms(text: &str) -> Result<f64, String> {
    let ms: f64 = text
        .parse()
        .map_err(|_| format!("`{text}` is not a number of milliseconds"))?;
    if !(ms.is_finite() && ms > 0.0 && ms <= 1000.0) {
        return Err(format!("{text} ms is not a render cost in (0, 1000] ms"));
    }
    Ok(ms)
}

/// `--priority`: the order a cycle takes its mips in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub(crate) enum Priority {
    /// The paper's: by feedback weight (the default: error per byte read less after
    /// start-up on the frontier, docs/CONTROLLER.md).
    Weight,
    /// By the screen error a mip removes per byte it costs.
    ErrorPerByte,
}

impl Priority {
    /// The loader's order.
    pub(crate) fn order(self) -> PlanOrder {
        match self {
            Priority::Weight => PlanOrder::Weight,
            Priority::ErrorPerByte => PlanOrder::ErrorPerByte,
        }
    }
}

/// `--prefetch`: where the second feedback pass looks from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub(crate) enum Prefetch {
    /// No prefetch pass.
    None,
    /// The path's pose a lead time ahead (replays and benchmarks know it).
    Path,
    /// The camera's motion over the last frames, carried a lead time ahead.
    Motion,
}

impl Prefetch {
    /// The name `--prefetch` takes.
    pub(crate) fn name(self) -> &'static str {
        match self {
            Prefetch::None => "none",
            Prefetch::Path => "path",
            Prefetch::Motion => "motion",
        }
    }
}

/// `--prefetch-lead-s`: in (0, 10] seconds.
fn parse_lead_s(text: &str) -> Result<f64, String> {
    let s: f64 = text
        .parse()
        .map_err(|_| format!("`{text}` is not a number of seconds"))?;
    if !(s.is_finite() && s > 0.0 && s <= 10.0) {
        return Err(format!("{text} s is not a lead time in (0, 10] s"));
    }
    Ok(s)
}

/// `--controller`: which adaptive controller `--policy adaptive` runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub(crate) enum Controller {
    /// The paper's Eq. 4-7, exactly.
    Paper,
    /// Spends the room left under α: docs/CONTROLLER.md.
    Headroom,
    /// Loads what the predicted bind cost fits under α: docs/CONTROLLER.md.
    Predictive,
}

impl Controller {
    /// The policy `--policy policy --controller self` runs; `None` where a controller
    /// other than the paper's is asked of a policy that has none.
    pub(crate) fn policy(self, policy: PolicyKind) -> Option<PolicyKind> {
        match (policy, self) {
            (PolicyKind::Adaptive, Controller::Headroom) => Some(PolicyKind::Headroom),
            (PolicyKind::Adaptive, Controller::Predictive) => Some(PolicyKind::Predictive),
            (_, Controller::Paper) => Some(policy),
            (PolicyKind::Headroom, Controller::Headroom) => Some(policy),
            (PolicyKind::Predictive, Controller::Predictive) => Some(policy),
            (_, Controller::Headroom | Controller::Predictive) => None,
        }
    }

    /// The name `--controller` takes.
    pub(crate) fn name(self) -> &'static str {
        match self {
            Controller::Paper => "paper",
            Controller::Headroom => "headroom",
            Controller::Predictive => "predictive",
        }
    }
}

/// `--strategy`: how the run decides what to load and draws it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub(crate) enum Strategy {
    /// The paper's: a GPU feedback pass says which mip each visible mesh needs.
    Feedback,
    /// The texture-atlas tree's (docs/ATLAS_TREE.md): nodes chosen by distance draw their
    /// atlases, blocks paged by §6's priorities; `--dataset` names a tree.
    AtlasTree,
    /// Texture arrays without sparse residency (Trapp and Döllner, docs/STRATEGIES.md):
    /// every texture loaded before the first frame where the city fits the memory
    /// budget, else streamed by the feedback pass at whole-mip granularity into fully
    /// bound array layers. Implies `--sparse off`.
    TextureArrays,
}

impl Strategy {
    /// The name written to summary.json.
    pub(crate) fn name(self) -> &'static str {
        match self {
            Strategy::Feedback => "feedback",
            Strategy::AtlasTree => "atlas-tree",
            Strategy::TextureArrays => "texture-arrays",
        }
    }
}

/// `--sparse`: whether textures live in sparse images or texture arrays.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub(crate) enum Sparse {
    /// Sparse residency where the device has it, texture arrays otherwise.
    Auto,
    /// Sparse residency; a device without it is refused.
    On,
    /// Texture arrays, even on a device with sparse residency.
    Off,
}

impl Sparse {
    /// The engine's device mode.
    pub(crate) fn mode(self, strategy: Strategy) -> citystream_engine::device::SparseMode {
        use citystream_engine::device::SparseMode;
        if strategy == Strategy::TextureArrays {
            return SparseMode::Off;
        }
        match self {
            Sparse::Auto => SparseMode::Auto,
            Sparse::On => SparseMode::On,
            Sparse::Off => SparseMode::Off,
        }
    }
}

/// The memory budget when `--memory-budget-mb` is left out (MB).
pub(crate) const DEFAULT_BUDGET_MB: u64 = 512;

impl Args {
    /// The memory budget: `--memory-budget-mb`, else [`DEFAULT_BUDGET_MB`], else for
    /// the texture-array strategy none (the device's memory bounds it).
    pub(crate) fn memory_budget_mb(&self) -> BudgetMb {
        match (self.memory_budget_mb_given, self.strategy) {
            (Some(budget), _) => budget,
            (None, Strategy::TextureArrays) => BudgetMb(None),
            (None, _) => BudgetMb(Some(DEFAULT_BUDGET_MB)),
        }
    }
}

/// `--culling`: whether the city passes draw only what the view may show.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub(crate) enum Culling {
    /// GPU culling against the frustum and a depth pyramid (engine `cull` module).
    On,
    /// Every pass draws every mesh in one draw.
    Off,
}

impl Culling {
    /// The name written to summary.json.
    pub(crate) fn name(self) -> &'static str {
        match self {
            Culling::On => "on",
            Culling::Off => "off",
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
                  the sparse texture cache binds memory and copies them (texture arrays on a \
                  device without sparse residency, --sparse), and the frame blends \
                  sampled colour with the City Colormap by mip level. Without --dataset it \
                  streams the default city (data/city, created on first run); with \
                  --placeholder it renders a small procedural city, fully resident."
)]
pub(crate) struct Args {
    /// City dataset directory (written by `citystream gen`, `import` or `atlas`).
    /// Default: the default city in data/city, created on first run (the
    /// `small` generated city in 2048x2048 atlases, see docs/DATASET.md).
    #[arg(long)]
    pub(crate) dataset: Option<PathBuf>,
    /// Render a procedural placeholder city, fully resident, instead of
    /// streaming a dataset (no feedback, no streaming).
    #[arg(long, conflicts_with_all = ["dataset", "pop_in"])]
    pub(crate) placeholder: bool,
    /// Output directory for frames/ and summary.json.
    #[arg(long, default_value = "out/flythrough", value_parser = citystream_gen::files::local_out)]
    pub(crate) out: PathBuf,
    /// Camera path: `standard` (the benchmark path derived from the dataset,
    /// see docs/PATHS.md) or a path file (`citystream path`, or recorded in
    /// the window). Default: `standard`; with --window, free flight from the
    /// overview.
    #[arg(long)]
    pub(crate) path: Option<String>,
    /// Number of frames to render (default: as many as the path lasts; 240
    /// with --placeholder).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1_000_000))]
    pub(crate) frames: Option<u32>,
    /// Stop after this many seconds of camera time (default: the path's
    /// length; at most a day).
    #[arg(long, value_parser = parse_duration_s)]
    pub(crate) duration_s: Option<f64>,
    /// Write every N-th frame as PNG (0 writes none). Default: 20; with
    /// --window, 0 (the PNGs are then what the window presented).
    #[arg(long)]
    pub(crate) frame_interval: Option<u32>,
    /// Image width in pixels.
    #[arg(long, default_value_t = 640, value_parser = clap::value_parser!(u32).range(16..=8192))]
    pub(crate) width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 360, value_parser = clap::value_parser!(u32).range(16..=8192))]
    pub(crate) height: u32,
    /// Streaming strategy: `feedback` (the paper's GPU feedback), `atlas-tree` (a
    /// texture-atlas tree built by `citystream atlas-tree`, named by --dataset; see
    /// docs/ATLAS_TREE.md) or `texture-arrays` (fully resident texture arrays where the
    /// city fits the budget, else the feedback strategy on texture arrays; see
    /// docs/STRATEGIES.md). All share the loader, the cache and the policy.
    #[arg(long, value_enum, default_value_t = Strategy::Feedback)]
    pub(crate) strategy: Strategy,
    /// GPU culling of the city passes: `on` draws only the meshes in the view's frustum
    /// and not behind depth already drawn (two phases per pass, docs/ARCHITECTURE.md);
    /// `off` draws every mesh in every pass. The feedback is the same, and so are the images
    /// except where two surfaces tie in depth (the culled pass keeps the one it drew first);
    /// the error reference draws the view's own visibility, so the error figures agree.
    #[arg(long, value_enum, default_value_t = Culling::On)]
    pub(crate) culling: Culling,
    /// Streaming policy: adaptive (the controller `--controller` names), baseline (s = s_max,
    /// b = 0) or fixed; `headroom` is `adaptive --controller headroom`, `predictive`
    /// `adaptive --controller predictive`.
    #[arg(long, default_value = "adaptive")]
    pub(crate) policy: PolicyKind,
    /// The adaptive policy's controller: `paper` (Eq. 4-7 exactly), `headroom` (load
    /// size and bias engage only as the frame nears α) or `predictive` (each cycle binds
    /// what the predicted bind cost fits under α; docs/CONTROLLER.md).
    #[arg(long, value_enum, default_value_t = Controller::Paper)]
    pub(crate) controller: Controller,
    /// Target maximum frame latency α in ms (adaptive).
    #[arg(long, default_value_t = 16.0)]
    pub(crate) alpha: f64,
    /// Maximum mip bias β (adaptive).
    #[arg(long, default_value_t = 8.0)]
    pub(crate) beta: f64,
    /// Load size in MB (fixed policy).
    #[arg(long, default_value_t = 4.0)]
    pub(crate) load_size_mb: f64,
    /// The order a cycle takes its mips in: `weight` (the paper's, by feedback weight)
    /// or `error-per-byte` (the screen error a mip removes per byte it costs).
    #[arg(long, value_enum, default_value_t = Priority::Weight)]
    pub(crate) priority: Priority,
    /// Prefetch: `none`; `path` (a second feedback pass from where the path puts the
    /// camera `--prefetch-lead-s` ahead); `motion` (from the camera's motion of the last
    /// frames carried that far ahead). Its requests follow the view's in every cycle.
    #[arg(long, value_enum, default_value_t = Prefetch::None)]
    pub(crate) prefetch: Prefetch,
    /// How far ahead the prefetch pass looks, seconds of path time.
    #[arg(long, default_value_t = DEFAULT_PREFETCH_LEAD_S, value_parser = parse_lead_s)]
    pub(crate) prefetch_lead_s: f64,
    /// With --clock fixed or modelled: what the prefetch pass costs in the modelled frame
    /// (ms). Default: the feedback pass's share of a frame ([`FEEDBACK_PASS_SHARE`]) of
    /// `--render-ms`.
    #[arg(long, value_parser = parse_render_ms)]
    pub(crate) prefetch_cost_ms: Option<f64>,
    /// Mip bias (fixed policy).
    #[arg(long, default_value_t = 0.0)]
    pub(crate) mip_bias: f64,
    /// Modelled cost of binding sparse memory: none, lavapipe, desktop (the paper's Windows
    /// driver, calibrated on its Table 3) or h200-linux (an NVIDIA H200 under Linux, as
    /// measured).
    #[arg(long, default_value = "none")]
    pub(crate) bind_latency: BindLatencyPreset,
    /// With --clock fixed or modelled: the disk the loader's reads take modelled time on,
    /// so that a loading cycle lasts as long as its reads while frames go on: none (reads
    /// take no time: a cycle lasts one frame), 970evo (the paper's SSD), measured (this
    /// machine's, probed on the dataset's pack first and written to OUT/disk-model.json)
    /// or measured:FILE (figures a probe wrote). With a model the 16 ms load-time limit
    /// applies to the reads' modelled start.
    #[arg(long, default_value = "none")]
    pub(crate) disk_model: DiskModelChoice,
    /// Clock: real (measured), fixed (reproducible, modelled latency, 60
    /// frames per camera second) or modelled (reproducible, the camera
    /// advancing by each frame's modelled latency).
    #[arg(long, value_enum, default_value_t = Clock::Real)]
    pub(crate) clock: Clock,
    /// With --clock modelled: the display period (ms) a frame lasts at the least, as under a
    /// FIFO (vsync) swapchain; the camera advances by the longer of it and the frame's
    /// modelled work. 16.67 (60 Hz) by default; 0: uncapped.
    #[arg(long, default_value_t = FIXED_STEP_MS, value_parser = parse_display_period_ms)]
    pub(crate) display_period_ms: f64,
    /// With --clock fixed or modelled: what rendering a frame costs (ms) in the modelled
    /// latency, before its binds and copies. 8 by default.
    #[arg(long, default_value_t = FIXED_RENDER_MS, value_parser = parse_render_ms)]
    pub(crate) render_ms: f64,
    /// The latency the controller is fed, `work` (the default: the frame's modelled work
    /// with --clock modelled; in the window with --clock real, the interval between frames
    /// less the waits for the display, acquiring an image and presenting) or `period` (the
    /// interval between frames, as a host timing start to start under vsync would).
    #[arg(long, value_enum, default_value_t = ControllerLatency::Work)]
    pub(crate) controller_latency: ControllerLatency,
    /// Memory budget of the texture cache in MB (bound sparse blocks, or texture-array
    /// layers), or `unlimited`. Default: 512; with --strategy texture-arrays, unlimited:
    /// the whole city is loaded before the first frame where the device holds it (a budget
    /// in MB makes that strategy stream within it).
    #[arg(long = "memory-budget-mb", value_parser = parse_budget_mb)]
    pub(crate) memory_budget_mb_given: Option<BudgetMb>,
    /// How the cache frees memory at the budget: `view` (drop the levels the
    /// view needs least, see ARCHITECTURE.md, "Eviction") or `ring` (the paper's
    /// oldest-layer ring).
    #[arg(long, default_value = "view", value_parser = parse_eviction)]
    pub(crate) eviction: Eviction,
    /// Layers per cache image (default: derived from the dataset, the
    /// budget and the device).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=65535))]
    pub(crate) cache_layers: Option<u32>,
    /// Pick the Vulkan device whose name contains this text (also CITYSTREAM_DEVICE).
    #[arg(long)]
    pub(crate) device: Option<String>,
    /// Texture cache backing: `auto` (sparse residency where the device has it, texture
    /// arrays otherwise, with a notice), `on` (sparse; refuse a device without it) or `off`
    /// (texture arrays: fully bound layers of a full mip chain each, streamed at whole-mip
    /// granularity; docs/STRATEGIES.md).
    #[arg(long, value_enum, default_value_t = Sparse::Auto)]
    pub(crate) sparse: Sparse,
    /// Seed of the placeholder city and of the bind-latency model's spikes.
    #[arg(long, default_value_t = 7)]
    pub(crate) seed: u64,
    /// Blocks per side of the placeholder city (with --placeholder).
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u32).range(1..=200))]
    pub(crate) blocks: u32,
    /// Enable the Vulkan validation layer (default: on in debug builds).
    #[arg(long)]
    pub(crate) validation: Option<bool>,
    /// Instead of a flythrough, measure pop-in (the paper's Fig. 7): a static
    /// view that starts with nothing resident and whose textures then refine
    /// one level per frame from the coarsest; the largest inter-frame MSE with
    /// direct sampling (no City Colormap: unloaded reads as zero) and with
    /// colormap blending (Eq. 8). Writes OUT/popin.json.
    #[arg(long)]
    pub(crate) pop_in: bool,
    /// Frames the CPU may record ahead of the GPU (1 waits for every frame).
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u32).range(1..=8))]
    pub(crate) frames_in_flight: u32,
    /// Exit 0 even when textures failed to load (a read error, a truncated
    /// pack); the failures are still counted in summary.json and warned about.
    #[arg(long)]
    pub(crate) allow_load_failures: bool,
    /// Testing aid: make reads of the texture pack fail, `EVERY:TIMES`: one
    /// mip in EVERY (chosen by its texture and level) fails its first TIMES
    /// reads. The loader reads a mip up to 3 times, so TIMES of 2 or less
    /// recover and 3 or more fail the texture.
    #[arg(long, value_parser = FaultPlan::parse)]
    pub(crate) inject_read_failures: Option<FaultPlan>,
    /// Measure image error every N frames: render a reference of the same view
    /// with every needed mip resident and report PSNR against it (0: never).
    #[arg(long, default_value_t = 30)]
    pub(crate) psnr_interval: u32,
    /// A depth-precision probe in the city (headless runs): two parallel slabs 0.5 m apart
    /// facing the first pose's eye from this many metres, in its heading 20° above the
    /// horizon, the nearer with the dataset's first texture and the farther with its second.
    /// On every measured frame (`--psnr-interval`) the view from that frame's eye towards
    /// them must show the nearer inside its outline; one pixel of the farther fails the run.
    /// `depth_slabs` in summary.json counts them. The slabs are part of the city flown:
    /// they draw, stream their textures and count in the image error like any mesh.
    #[arg(long, value_parser = super::depth_slabs::parse_depth_slabs_m, conflicts_with_all = ["placeholder", "pop_in", "window"])]
    pub(crate) depth_slabs: Option<f64>,
    /// Aerial imagery under the city (docs/GROUND.md): a patch set written by
    /// `citystream patches`, draped on the ground through a flexible clipmap; each patch
    /// is inserted when its arrival time comes, and ground tiles share the controller's
    /// load size with the facades.
    #[arg(long, conflicts_with_all = ["placeholder", "pop_in"])]
    pub(crate) ground: Option<PathBuf>,
    /// Open a window and fly through the city interactively (docs/WINDOW.md):
    /// mouse and keys fly, --path replays a path at wall-clock speed, R
    /// records. Needs a display (X11, or XWayland).
    #[arg(long, conflicts_with_all = ["placeholder", "pop_in"])]
    pub(crate) window: bool,
    /// With --window: vsync (default), mailbox or immediate; vsync where the
    /// display lacks the one asked for.
    #[arg(long, default_value = "vsync", requires = "window")]
    pub(crate) present_mode: PresentMode,
    /// With --window: record the flown camera path from the first frame to
    /// this path file (R stops and restarts it); written when recording stops
    /// or the window closes, replacing the file atomically.
    #[arg(long, requires = "window")]
    pub(crate) record: Option<PathBuf>,
    /// With --window: scripted input (docs/WINDOW.md), for demos and tests:
    /// key presses, mouse looks, resizes, minimising and screenshots by frame.
    #[arg(long, requires = "window")]
    pub(crate) input_script: Option<PathBuf>,
    #[command(flatten)]
    pub(crate) remote: citystream_gen::location::RemoteArgs,
    #[command(flatten)]
    pub(crate) mip_cache: citystream_gen::location::MipCacheArgs,
}

/// `--memory-budget-mb`: whole MB, or `None` for `unlimited`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct BudgetMb(pub(crate) Option<u64>);

impl BudgetMb {
    pub(crate) fn bytes(self) -> Option<u64> {
        self.0.map(|mb| mb << 20)
    }
}

pub(crate) fn parse_budget_mb(text: &str) -> std::result::Result<BudgetMb, String> {
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
pub(crate) fn parse_duration_s(text: &str) -> std::result::Result<f64, String> {
    use citystream_streaming::bench::path::MAX_PATH_DURATION_S;
    match text.parse::<f64>() {
        Ok(s) if s.is_finite() && (0.0..=MAX_PATH_DURATION_S).contains(&s) => Ok(s),
        Ok(s) => Err(format!("{s} s is not a duration from 0 to {MAX_PATH_DURATION_S} s")),
        Err(_) => Err(format!("`{text}` is not a number of seconds")),
    }
}

/// `--eviction`: `view` or `ring`.
pub(crate) fn parse_eviction(text: &str) -> std::result::Result<Eviction, String> {
    match text {
        "view" => Ok(Eviction::View),
        "ring" => Ok(Eviction::Ring),
        other => Err(format!("`{other}` is not an eviction (view or ring)")),
    }
}

/// The budget the cache gets for "unlimited": more than any dataset.
pub(crate) const UNLIMITED_BUDGET_BYTES: u64 = u64::MAX / 4;

/// Fixed clock: the time step. Fixed and modelled clocks: the render cost of a frame
/// without `--render-ms`.
pub(crate) const FIXED_STEP_MS: f64 = 1000.0 / 60.0;
pub(crate) const FIXED_RENDER_MS: f64 = 8.0;
/// `--prefetch-lead-s` by default: chosen on the frontier (pressure city, 640×360, path
/// prefetch at 0.5, 1 and 2 s read 53.35, 53.56 and 53.66 dB after start-up with 37, 36 and
/// 54 frames over α; 1 s is within 0.1 dB of the best with the fewest; docs/CONTROLLER.md).
pub(crate) const DEFAULT_PREFETCH_LEAD_S: f64 = 1.0;
/// The view's feedback work's share of a frame: what the prefetch pass, a second one,
/// adds to `--render-ms` by default. Measured on lavapipe (`gpu_pass_ms` of `flythrough
/// --dataset data/large-atlas --clock modelled --bind-latency desktop --memory-budget-mb
/// 256 --duration-s 30 --width 640 --height 360 --psnr-interval 12 --policy predictive
/// --alpha 12`, 2026-12-07): depth pre-pass and feedback 13.34 ms, compaction 1.01, half
/// of the culling's 20.48 (it culls two views) of 81.51 ms of passes: 0.30.
pub(crate) const FEEDBACK_PASS_SHARE: f64 = 0.30;
/// Fixed clock: host-to-device copy bandwidth of the modelled GPU, the same
/// as the simulator's (`streaming::sim`), so copies cost time too.
pub(crate) const FIXED_COPY_BYTES_PER_S: f64 = 12e9;

/// `--frame-interval`: 20 by default headless, 0 in the window.
pub(crate) fn frame_interval(args: &Args) -> u32 {
    args.frame_interval.unwrap_or(if args.window { 0 } else { 20 })
}

/// Whether frame `frame` is written to OUT/frames/ at `--frame-interval`.
pub(crate) fn writes_frame(args: &Args, frame: u32) -> bool {
    frame_interval(args) > 0 && frame.is_multiple_of(frame_interval(args))
}

pub(crate) fn frames_dir_path(args: &Args) -> PathBuf {
    args.out.join("frames")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_clock_advances_the_path_by_its_own_time() {
        // A 9 ms frame under a 16.67 ms display period, and a 40 ms stall.
        assert_eq!(Clock::Real.path_advance_ms(9.0, FIXED_STEP_MS), 9.0);
        assert_eq!(Clock::Fixed.path_advance_ms(9.0, FIXED_STEP_MS), FIXED_STEP_MS);
        assert_eq!(Clock::Fixed.path_advance_ms(40.0, 0.0), FIXED_STEP_MS);
        assert_eq!(Clock::Modelled.path_advance_ms(9.0, FIXED_STEP_MS), FIXED_STEP_MS);
        assert_eq!(Clock::Modelled.path_advance_ms(40.0, FIXED_STEP_MS), 40.0);
        assert_eq!(Clock::Modelled.path_advance_ms(9.0, 0.0), 9.0);
    }
}
