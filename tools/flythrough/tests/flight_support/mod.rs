//! Helpers the flythrough's tests share (each test file is its own crate and includes this
//! module with `mod flight_support;`).
//!
//! The datasets the flights need come from the `citystream` commands, run here through
//! their library functions on the arguments the binary would be given, parsed as it parses
//! them: the `citystream` binary belongs to another package, which these tests cannot run.

#![allow(dead_code, unused_imports)] // reason: each test binary uses a different subset

use std::path::{Path, PathBuf};

use anyhow::Result;
use citystream_testing::tool_tests;
pub use citystream_testing::tool_tests::{setup_ran, stderr};
use clap::{Args, FromArgMatches};

/// Runs `citystream ARGS…` (one of the commands that make or check a dataset) in this
/// process; its error as `citystream` would report it.
pub fn citystream(args: &[&str]) -> Result<()> {
    match args.first().copied() {
        Some("gen") => command(args, citystream_gen::command::run),
        Some("atlas") => command(args, citystream_gen::atlas::run),
        Some("atlas-tree") => command(args, citystream_gen::atlas_tree::run),
        Some("patches") => command(args, citystream_gen::patches::run),
        Some("import") => command(args, citystream_import::command::run),
        Some("path") => command(args, citystream_cli::path::run),
        Some("verify") => command(args, citystream_cli::verify::run),
        Some("info") => command(args, citystream_cli::info::run),
        other => panic!("no citystream command {other:?} in the flythrough's tests"),
    }
}

/// [`citystream`], which must succeed.
pub fn citystream_ok(args: &[&str]) {
    if let Err(e) = citystream(args) {
        panic!("citystream {}: {e:?}", args.join(" "));
    }
}

/// `args` (the command's name first) parsed into `A` as the `citystream` binary parses
/// them, then `run` on them.
fn command<A: Args + FromArgMatches>(args: &[&str], run: fn(&A) -> Result<()>) -> Result<()> {
    let matches = A::augment_args(clap::Command::new("citystream")).try_get_matches_from(args)?;
    run(&A::from_arg_matches(&matches)?)
}

/// `citystream gen --preset tiny --out DIR/city`; the city's directory.
pub fn tiny_city(dir: &Path) -> PathBuf {
    let city = dir.join("city");
    citystream_ok(&["gen", "--preset", "tiny", "--out", city.to_str().expect("utf-8")]);
    city
}

/// `CARGO_TARGET_TMPDIR/group/name`, removed if it exists; its parent exists,
/// it does not (for commands that must create their output themselves).
pub fn fresh_path(group: &str, name: &str) -> PathBuf {
    tool_tests::fresh_path(Path::new(env!("CARGO_TARGET_TMPDIR")), group, name)
}

/// [`fresh_path`], created empty.
pub fn fresh_dir(group: &str, name: &str) -> PathBuf {
    tool_tests::fresh_dir(Path::new(env!("CARGO_TARGET_TMPDIR")), group, name)
}

/// The default city, created once for the tests that fly it (concurrent creators are safe:
/// each builds privately and renames into place).
pub fn default_city() -> PathBuf {
    let city = Path::new(env!("CARGO_TARGET_TMPDIR")).join("default_city").join("city");
    citystream_gen::default_city::ensure_default_city(&city, true).expect("default city created");
    city
}

/// `flythrough ARGS… --dataset DATASET --out OUT` under synchronization validation (its
/// frames overlap, and the prefetch pass records beside the feedback): its output,
/// `summary.json` (null if not written) and `frames.csv` (empty if not written).
pub fn fly_flythrough(args: &[&str], dataset: &Path, out: &Path) -> (std::process::Output, serde_json::Value, String) {
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_flythrough"))
        .env("CITYSTREAM_VALIDATION", "sync")
        .args(args)
        .arg("--dataset")
        .arg(dataset)
        .arg("--out")
        .arg(out)
        .output()
        .expect("flythrough runs");
    let summary = serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap_or_default())
        .unwrap_or(serde_json::Value::Null);
    let csv = std::fs::read_to_string(out.join("frames.csv")).unwrap_or_default();
    (output, summary, csv)
}

/// Column `name` of a `frames.csv`, each cell parsed; `None` where a cell is empty (a frame
/// that did not measure it).
pub fn optional_column(csv: &str, name: &str) -> Vec<Option<f64>> {
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().expect("header").split(',').collect();
    let at = header.iter().position(|h| *h == name).expect("column");
    lines
        .map(|l| {
            let cell = l.split(',').nth(at).expect("cell");
            (!cell.is_empty()).then(|| cell.parse().expect("number"))
        })
        .collect()
}

/// Column `name` of a `frames.csv`, every cell a number.
pub fn column(csv: &str, name: &str) -> Vec<f64> {
    optional_column(csv, name)
        .into_iter()
        .map(|cell| cell.expect("a number in every frame"))
        .collect()
}
