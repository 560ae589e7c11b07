//! `citystream path`: writes the standard benchmark camera path (paper §4.1) of a dataset.

use std::fmt::Write as _;
use std::path::PathBuf;

use anyhow::{Context, Result};
use citystream_dataset::Dataset;
use citystream_streaming::bench::path::{standard_path, DEFAULT_STANDARD_DURATION_S};

use citystream_gen::files::print_stdout;

/// Options of `citystream path`.
#[derive(Debug, clap::Args)]
pub struct PathArgs {
    /// Dataset directory (its scene is read; no texture data).
    #[arg(long)]
    pub dataset: PathBuf,
    /// Camera path file to write (JSON, format in docs/PATHS.md).
    #[arg(long, value_parser = citystream_gen::files::local_out)]
    pub out: PathBuf,
    /// Length of the path in seconds (at least 18: four 2 s pauses plus ten flight segments).
    #[arg(long, default_value_t = DEFAULT_STANDARD_DURATION_S)]
    pub duration: f64,
}

/// Runs `citystream path`.
pub fn run(args: &PathArgs) -> Result<()> {
    let scene = Dataset::open(&args.dataset)
        .with_context(|| format!("opening dataset {}", args.dataset.display()))?
        .scene;
    let path = standard_path(&scene, args.duration)
        .with_context(|| format!("building the standard path for {}", args.dataset.display()))?;
    path.save(&args.out)?;

    let list = |times: &mut dyn Iterator<Item = f64>| times.map(|t| format!("{t:.2}")).collect::<Vec<_>>().join(", ");
    let pauses = path.pauses();
    let jumps = path.jumps();
    let mut report = String::new();
    writeln!(
        report,
        "wrote {}: standard path of {}",
        args.out.display(),
        args.dataset.display()
    )?;
    writeln!(
        report,
        "duration {:.2} s, {} keyframes",
        path.duration_s(),
        path.keyframes().len()
    )?;
    writeln!(
        report,
        "{} pauses of {} s at {} s",
        pauses.len(),
        list(&mut pauses.iter().map(|p| p.duration_s)),
        list(&mut pauses.iter().map(|p| p.start_s))
    )?;
    writeln!(
        report,
        "{} jumps at {} s",
        jumps.len(),
        list(&mut jumps.iter().copied())
    )?;
    print_stdout(&report)
}
