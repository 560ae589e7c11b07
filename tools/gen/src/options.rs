//! The options of `citystream gen` (presets, texture encodings), and the extent check and
//! disk arithmetic the generators and the atlas packer share.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use citystream_dataset::TextureFormat;

use crate::layout::LayoutParams;

/// City sizes. Texture counts are for seed 1 (see `docs/DATASET.md`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Preset {
    /// A few blocks, small textures: generates in about a second (tests).
    Tiny,
    /// A few thousand textures: the default city.
    Small,
    /// Tens of thousands of textures.
    Medium,
    /// About 100 000 textures (the benchmark city).
    Large,
    /// More than 1 000 000 textures (Berlin-scale texture count).
    City,
    /// The paper's Berlin (atlas): about 15.4 M triangles in about 233 K BC1 atlases of
    /// 512² (about 41 GB), written straight into atlases; resumable (docs/BERLIN.md).
    Berlin,
}

impl Preset {
    pub(crate) fn params(self) -> LayoutParams {
        let (blocks, max_extent_log2) = match self {
            Preset::Tiny => (2, 6),
            Preset::Small => (8, 9),
            Preset::Medium => (24, 9),
            Preset::Large => (48, 9),
            Preset::City => (156, 9),
            Preset::Berlin => {
                return LayoutParams {
                    blocks: BERLIN_BLOCKS,
                    max_extent_log2: 9,
                    density_scale: BERLIN_DENSITY_SCALE,
                }
            }
        };
        LayoutParams {
            blocks,
            max_extent_log2,
            density_scale: 1.5,
        }
    }
}

/// Blocks per side of the `berlin` preset: its triangle count is the paper's (Table 1,
/// Berlin (atlas): 15,363,486) within a few per cent.
const BERLIN_BLOCKS: u32 = 410;
/// Texel density of the `berlin` preset (the other presets use 1.5): its atlas count and
/// pack size are the paper's (233,110 atlases, 40.8 GB) within a few per cent.
const BERLIN_DENSITY_SCALE: f32 = 1.4;

/// Texture encodings the generator writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum FormatArg {
    /// BC1 (default, as the paper's datasets).
    Bc1,
    /// Uncompressed 8-bit RGBA.
    Rgba8,
    /// BC3 (DXT5): BC1 colours plus an alpha block, 16 bytes per 4×4.
    Bc3,
    /// BC7: 16 bytes per 4×4, the best quality of the four.
    Bc7,
}

impl FormatArg {
    /// The dataset format it writes.
    pub fn texture_format(self) -> TextureFormat {
        match self {
            FormatArg::Bc1 => TextureFormat::Bc1,
            FormatArg::Rgba8 => TextureFormat::Rgba8,
            FormatArg::Bc3 => TextureFormat::Bc3,
            FormatArg::Bc7 => TextureFormat::Bc7,
        }
    }
}

/// Options of `citystream gen`.
#[derive(Debug, clap::Args)]
pub struct GenArgs {
    /// City size.
    #[arg(long, value_enum, default_value = "small")]
    pub preset: Preset,
    /// Seed; the same seed always gives the same dataset: every mesh, mip and colour byte for
    /// byte (only the write id in each file's header differs between runs).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Output directory (created; existing dataset files in it are replaced).
    #[arg(long)]
    pub out: PathBuf,
    /// Texture encoding.
    #[arg(long, value_enum, default_value = "bc1")]
    pub format: FormatArg,
    /// Largest texture side in texels (a power of two, 4 to 16384); caps the preset's maximum.
    #[arg(long, default_value_t = 512)]
    pub max_extent: u32,
    /// Dress facades with the images found in this directory (PNG, JPEG, DDS, KTX2; searched
    /// recursively), resized to powers of two. Each facade picks one image; meshes share them.
    #[arg(long)]
    pub textures_from: Option<PathBuf>,
    /// Lay out the city and print what it holds and the disk the write needs, without
    /// writing anything.
    #[arg(long)]
    pub dry_run: bool,
    /// Do not print progress or the summary.
    #[arg(long)]
    pub quiet: bool,
}

impl GenArgs {
    /// `citystream gen --preset PRESET --seed SEED --out OUT` with every other option at
    /// its default (BC1, 512 texels at most, progress printed).
    pub fn new(preset: Preset, seed: u64, out: PathBuf) -> Self {
        GenArgs {
            preset,
            seed,
            out,
            format: FormatArg::Bc1,
            max_extent: 512,
            textures_from: None,
            dry_run: false,
            quiet: false,
        }
    }
}

/// Bytes free to an unprivileged writer on the file system holding `dir` (or the nearest
/// ancestor that exists).
pub(crate) fn free_bytes(dir: &Path) -> Result<u64> {
    let absolute = std::path::absolute(dir).with_context(|| format!("resolving {}", dir.display()))?;
    let existing = absolute
        .ancestors()
        .find(|p| p.exists())
        .context("no existing ancestor directory")?;
    #[cfg(target_os = "linux")]
    {
        let stat = rustix::fs::statvfs(existing)
            .with_context(|| format!("reading the free space of {}", existing.display()))?;
        Ok(stat.f_bavail.saturating_mul(stat.f_frsize))
    }
    #[cfg(not(target_os = "linux"))]
    {
        let _ = existing;
        Ok(u64::MAX)
    }
}

pub(crate) fn gb(bytes: u64) -> String {
    format!("{:.1} GB", bytes as f64 / 1e9)
}

/// Refuses a texture or atlas extent (the value of `option`) that is not a
/// power of two from 4 (one compressed block) to 16384 (a 2D image's common limit).
pub fn check_texture_extent(option: &str, extent: u32) -> Result<()> {
    if !extent.is_power_of_two() || !(4..=16384).contains(&extent) {
        bail!("{option} {extent} must be a power of two from 4 to 16384");
    }
    Ok(())
}
