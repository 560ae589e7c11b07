//! Helpers the flythrough's tests share (each test file is its own crate and includes this
//! module with `mod flight_support;`).
//!
//! The datasets the flights need come from the `citystream` commands, run here through
//! their library functions on the arguments the binary would be given, parsed as it parses
//! them: the `citystream` binary belongs to another package, which these tests cannot run.

#![allow(dead_code)] // reason: each test binary uses a different subset

use std::path::{Path, PathBuf};
use std::process::Output;

use anyhow::Result;
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
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(group).join(name);
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(dir.parent().expect("parent")).expect("create parent");
    dir
}

/// [`fresh_path`], created empty.
pub fn fresh_dir(group: &str, name: &str) -> PathBuf {
    let dir = fresh_path(group, name);
    std::fs::create_dir_all(&dir).expect("create dir");
    dir
}

/// The command's standard error, as text.
pub fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// Whether `tools/scripts/setup.sh` ran to the end on this machine (its stamp exists): tests of
/// what it installs (Xvfb, nginx) fail rather than skip once it has.
pub fn setup_ran() -> bool {
    let dir = std::env::var_os("CITYSTREAM_SETUP_STAMP_DIR").unwrap_or_else(|| "/var/lib/citystream".into());
    Path::new(&dir).join("setup-v5").exists()
}
