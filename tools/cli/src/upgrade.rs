//! `citystream upgrade`: rewrites a dataset of an older format version as the current one.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use citystream_dataset::{upgrade, Crs, FORMAT_VERSION};

/// Options of `citystream upgrade`.
#[derive(Debug, clap::Args)]
pub struct UpgradeArgs {
    /// Dataset directory. It is rewritten atomically: until the new version is complete,
    /// flushed and verified, the old one stays in place untouched.
    pub dir: PathBuf,
    /// The coordinate reference system the dataset's origin is in (`EPSG:<code>` or WKT),
    /// for a dataset that has none (older versions had none). A dataset already in another
    /// CRS is refused: its coordinates would have to be transformed.
    #[arg(long, value_parser = citystream_import::command::parse_crs)]
    pub crs: Option<Crs>,
}

/// Runs `citystream upgrade`.
pub fn run(args: &UpgradeArgs) -> Result<()> {
    let start = Instant::now();
    let summary = upgrade(&args.dir, args.crs.as_ref()).with_context(|| format!("upgrading {}", args.dir.display()))?;
    let crs = args.crs.as_ref().map_or(String::new(), |crs| format!(" in CRS {crs}"));
    let line = match summary.written {
        None if summary.leftovers_removed > 0 => format!(
            "{} already has format version {FORMAT_VERSION}{crs}; nothing to do but finish an interrupted \
             upgrade's clean-up: removed {} version-1 files\n",
            args.dir.display(),
            summary.leftovers_removed
        ),
        None => format!(
            "{} already has format version {FORMAT_VERSION}{crs}; nothing to do\n",
            args.dir.display()
        ),
        Some(written) => format!(
            "upgraded {} from format version {} to {FORMAT_VERSION}{crs}: {} textures, {} mips, {} meshes, {:.1} MB of mip data checked and copied in {:.2} s\n",
            args.dir.display(),
            summary.from_version,
            written.textures,
            written.mips,
            written.meshes,
            written.pack_bytes as f64 / 1e6,
            start.elapsed().as_secs_f64()
        ),
    };
    citystream_gen::files::print_stdout(&line)
}
