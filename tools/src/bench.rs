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

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use anyhow::{bail, Context, Result};

use crate::default_city::{ensure_default_city, DEFAULT_CITY_DIR};
use crate::report::{self, RunInput};

/// Options of `citystream bench`.
#[derive(Debug, clap::Args)]
pub struct BenchArgs {
    /// Dataset directory every run opens (default: the default city in
    /// data/city, created on first use).
    #[arg(long)]
    dataset: Option<PathBuf>,
    /// Output directory: one subdirectory per run, plus table.md and the
    /// charts of the comparison.
    #[arg(long)]
    out: PathBuf,
    /// Frame limit passed to every run (default: the flythrough's own).
    #[arg(long)]
    frames: Option<u64>,
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
    let dataset = match &args.dataset {
        Some(dir) if !dir.exists() => bail!("dataset directory {} does not exist", dir.display()),
        Some(dir) => dir.clone(),
        None => {
            let dir = PathBuf::from(DEFAULT_CITY_DIR);
            ensure_default_city(&dir, false)?;
            dir
        }
    };
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;

    let total = POLICY_RUNS.len();
    let mut inputs = Vec::with_capacity(total);
    for (i, policy) in POLICY_RUNS.iter().enumerate() {
        let run_dir = args.out.join(policy.dir);
        let run_args = flythrough_args(args, &dataset, policy, &run_dir);
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
        let status = Command::new(&flythrough)
            .args(&run_args)
            .status()
            .with_context(|| format!("starting {}", flythrough.display()))?;
        if !status.success() {
            bail!(
                "flythrough run `{}` failed ({status}); command: {} {}",
                policy.name,
                flythrough.display(),
                run_args.join(" ")
            );
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
    let outputs = report::write_report(&inputs, &args.out)?;
    report::print_outputs(&outputs);
    Ok(())
}

/// The flythrough command line of one policy run.
fn flythrough_args(args: &BenchArgs, dataset: &Path, policy: &PolicyRun, run_dir: &Path) -> Vec<String> {
    let mut out: Vec<String> = vec!["--dataset".into(), dataset.display().to_string()];
    out.extend(policy.args.iter().map(|a| a.to_string()));
    out.extend(
        ["--clock", "fixed", "--bind-latency", "desktop"]
            .iter()
            .map(|a| a.to_string()),
    );
    if let Some(frames) = args.frames {
        out.push("--frames".into());
        out.push(frames.to_string());
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
