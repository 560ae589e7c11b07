//! The default city: what `flythrough` and `make run` stream when no
//! dataset is named.
//!
//! It is the `small` generated city (seed 1) packed into 2048×2048 BC1
//! atlases, the analogue of the paper's Table 3 dataset, Berlin (atlas).
//! The atlases are larger than the paper's 512×512 because the default view
//! is 640×360, 1/36 of the paper's 3840×2160 framebuffer: at that size a
//! view needs, relative to each atlas's base level, about the mip levels a
//! 4K view needs of 512×512 atlases, so a baseline cycle binds hundreds of
//! sparse blocks, as it does in the paper.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use citystream_streaming::dataset::{CHECKSUM_FILE, SCENE_FILE};

use crate::atlas::AtlasArgs;
use crate::gen::{FormatArg, GenArgs, Preset};

/// Where the default city is created, relative to the working directory.
pub const DEFAULT_CITY_DIR: &str = "data/city";

/// Atlas side of the default city, in texels.
pub const DEFAULT_CITY_ATLAS_EXTENT: u32 = 2048;

/// True when `dir` holds a finished dataset (the checksum table is written last).
pub fn is_dataset(dir: &Path) -> bool {
    dir.join(SCENE_FILE).is_file() && dir.join(CHECKSUM_FILE).is_file()
}

/// The per-mesh-texture city the atlases of `dir` are made from.
pub fn source_dir(dir: &Path) -> PathBuf {
    let name = dir
        .file_name()
        .map_or_else(|| "city".into(), |n| n.to_string_lossy().into_owned());
    dir.with_file_name(format!("{name}-per-mesh"))
}

/// Creates the default city in `dir` unless a dataset is already there.
/// Returns whether it generated one. Progress goes to stderr unless `quiet`.
pub fn ensure_default_city(dir: &Path, quiet: bool) -> Result<bool> {
    if is_dataset(dir) {
        return Ok(false);
    }
    let source = source_dir(dir);
    if !quiet {
        eprintln!(
            "creating the default city in {} (first run): `citystream gen --preset small --seed 1 --out {}`, \
             then `citystream atlas --atlas-extent {DEFAULT_CITY_ATLAS_EXTENT}`",
            dir.display(),
            source.display()
        );
    }
    if !is_dataset(&source) {
        crate::gen::run(&GenArgs {
            preset: Preset::Small,
            seed: 1,
            out: source.clone(),
            format: FormatArg::Bc1,
            max_extent: 512,
            textures_from: None,
            quiet,
        })
        .with_context(|| format!("generating the default city's textures into {}", source.display()))?;
    }
    crate::atlas::run(&AtlasArgs {
        input: source,
        out: dir.to_path_buf(),
        region: 512.0,
        atlas_extent: DEFAULT_CITY_ATLAS_EXTENT,
    })
    .with_context(|| format!("packing the default city's atlases into {}", dir.display()))?;
    Ok(true)
}
