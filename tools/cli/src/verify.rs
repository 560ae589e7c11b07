//! `citystream verify`: full consistency check of a dataset.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use citystream_dataset::verify_dataset;

/// Options of `citystream verify`.
#[derive(Debug, clap::Args)]
pub struct VerifyArgs {
    /// Dataset directory, or its URL (`http(s)://host/path/`, `s3://bucket/prefix/`).
    /// A remote dataset's mips are read from the server, never from a mip cache.
    pub dir: PathBuf,
    #[command(flatten)]
    pub remote: citystream_gen::location::RemoteArgs,
}

/// Runs `citystream verify`; fails (non-zero exit) with the file and offset of the first problem.
pub fn run(args: &VerifyArgs) -> Result<()> {
    let start = Instant::now();
    let mut options = args.remote.options()?;
    // Verifying checks what the server holds.
    options.mip_cache = None;
    let dataset = citystream_gen::location::open_dataset_with(&args.dir, &options)
        .with_context(|| format!("verify failed for {}", args.dir.display()))?;
    let report = verify_dataset(&dataset).with_context(|| format!("verify failed for {}", args.dir.display()))?;
    let tree = citystream_gen::atlas_tree::open_if_tree(&dataset)
        .with_context(|| format!("verify failed for {}", args.dir.display()))?;
    citystream_gen::files::print_stdout(&format!(
        "ok: {}: {} meshes, {} textures, {} mips, {:.1} MB of mip data{} checked in {:.2} s\n",
        args.dir.display(),
        report.meshes,
        report.textures,
        report.mips,
        report.bytes_read as f64 / 1e6,
        tree.map(|t| format!(", an atlas tree of {} nodes", t.nodes.len()))
            .unwrap_or_default(),
        start.elapsed().as_secs_f64()
    ))
}
