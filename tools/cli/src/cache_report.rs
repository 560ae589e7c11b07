//! `citystream cache-report`: how well a dataset's textures pack into the
//! sparse cache (paper §3.6): texture bytes against bound block bytes, per
//! cache image, with every cacheable mip of every texture loaded.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use citystream_cache::{estimate_utilisation, DeviceLimits, Granularity, ImageConfig, ImageDesc, MipTail, TexelFormat};
use citystream_dataset::{Dataset, TextureFormat};
use serde::Serialize;

/// Options of `citystream cache-report`.
#[derive(Debug, clap::Args)]
pub struct CacheReportArgs {
    /// Dataset directory.
    pub dir: PathBuf,
    /// Side of a cache array layer in texels (a power of two).
    #[arg(long, default_value_t = 2048)]
    pub layer_size: u32,
    /// Sparse block size in bytes (the device's; lavapipe: 65536).
    #[arg(long, default_value_t = 65536)]
    pub block_bytes: u64,
    /// Sparse granularity of BC1 in texels, WIDTHxHEIGHT (lavapipe: 512x256).
    #[arg(long, default_value = "512x256")]
    pub bc1_granularity: String,
    /// Sparse granularity of RGBA8 in texels, WIDTHxHEIGHT (lavapipe: 128x128).
    #[arg(long, default_value = "128x128")]
    pub rgba8_granularity: String,
    /// The device's mip tails: `none` (lavapipe: every level in blocks), `per-layer`
    /// (one tail per layer, as RADV and ANV) or `single` (one per image, as NVK). A tail
    /// holds the levels smaller than one block in --tail-blocks blocks.
    #[arg(long, value_enum, default_value_t = TailKind::None)]
    pub mip_tails: TailKind,
    /// Blocks one mip tail takes (imageMipTailSize over the block size; 1 for 64 KiB tails).
    #[arg(long, default_value_t = 1)]
    pub tail_blocks: u32,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

/// `--mip-tails`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum TailKind {
    None,
    PerLayer,
    Single,
}

/// The tail a device with standard block shapes reports for `layer_size`²
/// layers of `granularity`: from the first level smaller than one block.
fn standard_tail(layer_size: u32, granularity: &Granularity, kind: TailKind, blocks: u32) -> Option<MipTail> {
    let single = match kind {
        TailKind::None => return None,
        TailKind::PerLayer => false,
        TailKind::Single => true,
    };
    let levels = layer_size.max(1).ilog2() + 1;
    let first_level = (0..levels).find(|&mip| {
        let size = (layer_size >> mip).max(1);
        size < granularity.width || size < granularity.height
    })?;
    Some(MipTail {
        first_level,
        blocks,
        single,
    })
}

#[derive(Debug, Serialize)]
struct ImageReport {
    format: &'static str,
    textures: u64,
    texture_bytes: u64,
    bound_blocks: u64,
    bound_bytes: u64,
    layers_used: u64,
    utilisation: f64,
    /// The mip tail's first level (null without tails).
    tail_first_level: Option<u32>,
    /// Bytes of one tail (a layer's, or the image's when single).
    tail_bytes_per_tail: u64,
    tail_single: bool,
    /// Bytes of tails held with every cacheable mip loaded (within `bound_bytes`).
    tail_bytes_held: u64,
}

fn parse_granularity(text: &str, option: &str) -> Result<Granularity> {
    let (w, h) = text
        .split_once('x')
        .with_context(|| format!("{option} {text:?}: expected WIDTHxHEIGHT, e.g. 512x256"))?;
    let w: u32 = w
        .trim()
        .parse()
        .with_context(|| format!("{option} {text:?}: bad width"))?;
    let h: u32 = h
        .trim()
        .parse()
        .with_context(|| format!("{option} {text:?}: bad height"))?;
    if w == 0 || h == 0 {
        bail!("{option} {text:?}: sides must be positive");
    }
    Ok(Granularity::texels(w, h))
}

/// Runs `citystream cache-report`.
pub fn run(args: &CacheReportArgs) -> Result<()> {
    let dataset = Dataset::open(&args.dir).with_context(|| format!("opening {}", args.dir.display()))?;
    let limits = DeviceLimits {
        max_image_array_layers: 2048,
        max_image_dimension_2d: 16384,
        sparse_block_bytes: args.block_bytes,
    };
    let images = [
        (
            TextureFormat::Bc1,
            TexelFormat::BC1,
            parse_granularity(&args.bc1_granularity, "--bc1-granularity")?,
        ),
        (
            TextureFormat::Rgba8,
            TexelFormat::RGBA8,
            parse_granularity(&args.rgba8_granularity, "--rgba8-granularity")?,
        ),
    ];
    let mut reports = Vec::new();
    for (index, (format, texel_format, granularity)) in images.into_iter().enumerate() {
        let extents: Vec<(u32, u32)> = dataset
            .textures
            .textures()
            .iter()
            .filter(|t| t.format() == format)
            .map(|t| (t.width(), t.height()))
            .collect();
        if extents.is_empty() {
            continue;
        }
        let desc = ImageDesc::new(
            index,
            &ImageConfig {
                format: texel_format,
                granularity,
                layer_size: args.layer_size,
                layer_count: 1,
                mip_tail: standard_tail(args.layer_size, &granularity, args.mip_tails, args.tail_blocks),
            },
            &limits,
        )
        .with_context(|| format!("cache image for {}", texel_format.name))?;
        let estimate = estimate_utilisation(&desc, &extents)
            .with_context(|| format!("packing the {} textures of {}", texel_format.name, args.dir.display()))?;
        reports.push(ImageReport {
            format: texel_format.name,
            textures: estimate.textures,
            texture_bytes: estimate.texture_bytes,
            bound_blocks: estimate.bound_blocks,
            bound_bytes: estimate.bound_bytes,
            layers_used: estimate.layers_used,
            utilisation: estimate.ratio(),
            tail_first_level: desc.mip_tail.map(|tail| tail.first_level),
            tail_bytes_per_tail: desc.tail_bytes(),
            tail_single: desc.mip_tail.is_some_and(|tail| tail.single),
            tail_bytes_held: estimate.tail_blocks * desc.block_bytes,
        });
    }
    if reports.is_empty() {
        bail!("{} has no BC1 or RGBA8 textures to pack", args.dir.display());
    }
    if args.json {
        println!("{}", serde_json::to_string_pretty(&reports)?);
        return Ok(());
    }
    println!(
        "cache packing of {} (layer {}x{}, blocks of {} B, every cacheable mip loaded)",
        args.dir.display(),
        args.layer_size,
        args.layer_size,
        args.block_bytes
    );
    println!(
        "| format | textures | texture MB | bound blocks | bound MB | layers | utilisation | tail from | tail KB | single | tails MB |"
    );
    println!("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: |");
    for r in &reports {
        println!(
            "| {} | {} | {:.1} | {} | {:.1} | {} | {:.1} % | {} | {:.0} | {} | {:.1} |",
            r.format,
            r.textures,
            r.texture_bytes as f64 / 1e6,
            r.bound_blocks,
            r.bound_bytes as f64 / 1e6,
            r.layers_used,
            r.utilisation * 100.0,
            r.tail_first_level
                .map_or("-".to_owned(), |level| format!("level {level}")),
            r.tail_bytes_per_tail as f64 / 1024.0,
            if r.tail_single { "yes" } else { "no" },
            r.tail_bytes_held as f64 / 1e6
        );
    }
    Ok(())
}
