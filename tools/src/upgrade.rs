//! `citystream upgrade`: rewrites a dataset of an older format version as the current one.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use citystream_streaming::dataset::{upgrade, FORMAT_VERSION};

/// Options of `citystream upgrade`.
#[derive(Debug, clap::Args)]
pub struct UpgradeArgs {
    /// Dataset directory. It is rewritten atomically: until the new version is complete,
    /// flushed and verified, the old one stays in place untouched.
    pub dir: PathBuf,
}

/// Runs `citystream upgrade`.
pub fn run(args: &UpgradeArgs) -> Result<()> {
    let start = Instant::now();
    let summary = upgrade(&args.dir).with_context(|| format!("upgrading {}", args.dir.display()))?;
    let line = match summary.written {
        None => format!(
            "{} already has format version {FORMAT_VERSION}; nothing to do\n",
            args.dir.display()
        ),
        Some(written) => format!(
            "upgraded {} from format version {} to {FORMAT_VERSION}: {} textures, {} mips, {} meshes, {:.1} MB of mip data checked and copied in {:.2} s\n",
            args.dir.display(),
            summary.from_version,
            written.textures,
            written.mips,
            written.meshes,
            written.pack_bytes as f64 / 1e6,
            start.elapsed().as_secs_f64()
        ),
    };
    crate::gen::print_stdout(&line)
}
