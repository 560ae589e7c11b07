//! `citystream import`: a glTF 2.0 scene ([`crate::gltf`]) or an OGC 3D Tiles tileset
//! ([`crate::tiles`]) as a dataset.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use citystream_dataset::{Crs, DatasetWriter};
use citystream_gen::city::{check_texture_extent, FormatArg};
use citystream_gen::files::print_stdout;
use citystream_gen::shard::ShardArgs;

use crate::gltf::load;

/// Options of `citystream import`.
#[derive(Debug, clap::Args)]
pub struct ImportArgs {
    /// glTF 2.0 file (`.gltf` with external files or data URIs, or `.glb`), or an OGC 3D
    /// Tiles tileset (`tileset.json`, 1.0 and 1.1: b3dm and glTF content; a path or an
    /// `http(s)://` or `s3://` URL).
    pub input: PathBuf,
    /// Output dataset directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Texture encoding.
    #[arg(long, value_enum, default_value = "bc1")]
    pub format: FormatArg,
    /// Largest texture side in texels (a power of two, 4 to 16384); larger images are downscaled.
    #[arg(long, default_value_t = 512)]
    pub max_extent: u32,
    /// glTF: the coordinate reference system the model's coordinates are in (`EPSG:<code>`
    /// or WKT), axes as the scene frame maps them: x easting, y height, −z northing (glTF
    /// carries no CRS; without this option the dataset has a local frame). Tilesets: the
    /// UTM projection to place the city in (EPSG:326xx, 327xx, 258xx); without it, a local
    /// east-north-up frame at the tileset's centre.
    #[arg(long, value_parser = parse_crs)]
    pub crs: Option<Crs>,
    /// Tilesets: which tiles' content to import (`finest`: tiles not refined further under
    /// REPLACE refinement, every tile under ADD; `all`: every level).
    #[arg(long, value_enum)]
    pub lod: Option<crate::tiles::Lod>,
    /// Tilesets: content citystream does not import (point clouds, instanced and composite
    /// tiles, implicit tiling, glTF content requiring an extension it does not decode) is an
    /// error instead of a warning.
    #[arg(long)]
    pub strict: bool,
    /// Tilesets: import one shard of the contents (`--shard I/N`, or `--shard-index-env NAME
    /// --shards N`) into OUT/shards/I/, for `citystream merge OUT`.
    #[command(flatten)]
    pub shard: ShardArgs,
}

/// Parses a `--crs` value.
pub fn parse_crs(text: &str) -> Result<Crs, String> {
    Crs::parse(text).map_err(|e| e.to_string())
}

/// Runs `citystream import`.
pub fn run(args: &ImportArgs) -> Result<()> {
    let start = Instant::now();
    check_texture_extent("--max-extent", args.max_extent)?;
    let format = args.format.texture_format();
    let input = &args.input;
    citystream_gen::shard::check_out(&args.out, args.shard.resolve()?)?;
    if crate::tiles::is_tileset(input) {
        let lod = args.lod.unwrap_or(crate::tiles::Lod::Finest);
        let options = crate::tiles::LoadOptions {
            format,
            max_extent: args.max_extent,
            lod,
            strict: args.strict,
            report: true,
            crs: args.crs.clone(),
            part: args.shard.resolve()?,
        };
        return crate::tiles::import(input, &args.out, &options);
    }
    if args.shard.resolve()?.is_some() {
        bail!(
            "--shard divides a 3D Tiles tileset's contents; {} is one glTF file",
            input.display()
        );
    }
    if args.lod.is_some() || args.strict {
        bail!(
            "--lod and --strict apply to 3D Tiles tilesets (a .json input), not to {}",
            input.display()
        );
    }
    let mut imported = load(input, format, args.max_extent)?;
    imported.scene.crs = args.crs.clone();
    let kept = imported.kept_blocks;
    let mut writer = DatasetWriter::create(&args.out)?;
    for t in imported.textures {
        writer.add_texture(t.format, t.width, t.height, t.mip_count, &t.chain, t.mean)?;
    }
    let summary = writer
        .finish(&imported.scene)
        .with_context(|| format!("writing {}", args.out.display()))?;
    imported.encodings.write(&args.out)?;
    print_stdout(&format!(
        "imported {} into {}: {} meshes, {} triangles, {} textures ({}), {:.1} MB pack, {:.2} s\nencodings: {}\n",
        input.display(),
        args.out.display(),
        summary.meshes,
        summary.triangles,
        summary.textures,
        imported.encodings.texture_note(kept, format.name()),
        summary.pack_bytes as f64 / 1e6,
        start.elapsed().as_secs_f64(),
        imported.encodings.summary()
    ))
}
