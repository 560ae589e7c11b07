//! `citystream gen`: the Berlin generator for `--preset berlin`, the standard one for the
//! other presets, and the summary of what was written.

use std::time::Instant;

use anyhow::{bail, Result};

use crate::berlin;
use crate::city::{check_texture_extent, generate, GenArgs, Preset};
use crate::files::print_stdout;

/// Runs `citystream gen`.
pub fn run(args: &GenArgs) -> Result<()> {
    let start = Instant::now();
    check_texture_extent("--max-extent", args.max_extent)?;
    let format = args.format.texture_format();
    let mut params = args.preset.params();
    params.max_extent_log2 = params.max_extent_log2.min(args.max_extent.trailing_zeros() as u8);
    crate::shard::check_out(&args.out, args.shard.resolve()?)?;
    if args.preset == Preset::Berlin && args.shard.resolve()?.is_some() {
        bail!("--shard: --preset berlin is written straight into atlases and cannot be sharded yet; shard a per-mesh preset");
    }
    let summary = if args.preset == Preset::Berlin {
        berlin::generate(args, params, berlin::RunControl::default())?
    } else {
        generate(args, params, format)?
    };
    if args.quiet || args.dry_run {
        return Ok(());
    }
    let seconds = start.elapsed().as_secs_f64();
    let texture_bytes = summary.pack_bytes as f64;
    let report = format!(
        "generated {} (preset {:?}, seed {}): {} textures, {} mips, {} meshes, {} triangles\n\
         bytes: pack {:.1} MB ({}), scene {:.1} MB, metadata {:.2} MB\n\
         time {:.2} s: {:.0} textures/s, {:.1} MB/s of texture data ({} threads)\n",
        args.out.display(),
        args.preset,
        args.seed,
        summary.textures,
        summary.mips,
        summary.meshes,
        summary.triangles,
        texture_bytes / 1e6,
        format.name(),
        summary.scene_bytes as f64 / 1e6,
        summary.metadata_bytes as f64 / 1e6,
        seconds,
        f64::from(summary.textures) / seconds,
        texture_bytes / 1e6 / seconds,
        rayon::current_num_threads()
    );
    print_stdout(&report)
}
