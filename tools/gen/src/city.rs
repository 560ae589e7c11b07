//! `citystream gen`: deterministic synthetic cities.
//!
//! The layout (single-threaded, cheap) decides every mesh and the description of its
//! texture; textures are then synthesised, mip-mapped and block-compressed in parallel with
//! rayon, a chunk at a time, and appended to the pack in texture-id order so the output is
//! byte-identical for a given seed whatever the thread count.

use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use citystream_dataset::{DatasetWriter, ShardRecord, TextureFormat, WriteSummary, SHARD_RECORD_FILE};
use rayon::prelude::*;

use crate::files::print_stdout;
use crate::layout::{self, LayoutParams};
use crate::library;
use crate::rng;
use crate::shard::{scene_fingerprint, Shard, ShardArgs, ShardWrite};
use crate::texture;

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
    /// Write one shard of the city (`--shard I/N`, or `--shard-index-env NAME --shards N`).
    #[command(flatten)]
    pub shard: ShardArgs,
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
            shard: ShardArgs::default(),
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

pub(crate) fn generate(args: &GenArgs, params: LayoutParams, format: TextureFormat) -> Result<WriteSummary> {
    let mut city = layout::layout(params, args.seed)?;
    // The procedural textures' chains; user images (`--textures-from`) come on top.
    let chain_bytes = |t: &layout::TextureSpec| -> u64 {
        let (w, h) = (1u32 << t.width_log2, 1u32 << t.height_log2);
        let mips = u32::from(t.width_log2.max(t.height_log2)) + 1;
        (0..mips)
            .map(|l| format.mip_bytes((w >> l).max(1), (h >> l).max(1)))
            .sum::<u64>()
    };
    let pack_bytes: u64 = city.textures.iter().map(chain_bytes).sum();
    let scene_bytes = city.scene.encoded_len();
    let shard = args.shard.resolve()?;
    if let Some(shard) = shard {
        shard.check_divides(city.textures.len(), "textures")?;
    }
    // A shard writes its own range (and at most the whole scene); one bound for S3 is
    // staged under the temporary directory first.
    let written_pack = match shard {
        Some(shard) => city.textures[shard.range(city.textures.len())]
            .iter()
            .map(chain_bytes)
            .sum::<u64>(),
        None => pack_bytes,
    };
    let needed = written_pack + scene_bytes;
    let written_at = if citystream_dataset::remote::is_remote(&args.out.to_string_lossy()) {
        std::env::temp_dir()
    } else {
        args.out.clone()
    };
    let free = free_bytes(&written_at)?;
    if args.dry_run {
        let part = match shard {
            Some(shard) => {
                let range = shard.range(city.textures.len());
                format!(
                    "; shard {} of {}: textures {} to {} ({} textures)",
                    shard.index,
                    shard.count,
                    range.start,
                    range.end.saturating_sub(1),
                    range.len()
                )
            }
            None => String::new(),
        };
        print_stdout(&format!(
            "{} meshes, {} triangles, {} textures{part}; needs {} of disk in {} ({}pack {}, scene {}); {} free\n",
            city.scene.meshes.len(),
            city.scene.triangle_count(),
            city.textures.len(),
            gb(needed),
            args.out.display(),
            if shard.is_some() {
                "this shard's part of the "
            } else {
                ""
            },
            gb(written_pack),
            gb(scene_bytes),
            gb(free)
        ))?;
        return Ok(WriteSummary {
            textures: city.textures.len() as u32,
            mips: 0,
            meshes: city.scene.meshes.len() as u32,
            triangles: city.scene.triangle_count(),
            pack_bytes,
            scene_bytes,
            metadata_bytes: 0,
        });
    }
    if needed > free {
        bail!(
            "{} needs {} of free disk in {} ({}pack {}, scene {}), but only {} is free there",
            args.out.display(),
            gb(needed),
            written_at.display(),
            if shard.is_some() {
                "this shard's part of the "
            } else {
                ""
            },
            gb(written_pack),
            gb(scene_bytes),
            gb(free)
        );
    }
    if let Some(shard) = shard {
        return generate_shard(args, format, city, shard);
    }
    let mut writer = DatasetWriter::create(&args.out)?;

    // User images become textures 0..n; facades pick one of them by a hash of their seed.
    let library = match &args.textures_from {
        Some(dir) => library::load(dir, params.max_extent_log2)?,
        None => Vec::new(),
    };
    if !args.quiet && !library.is_empty() {
        eprintln!("gen: dressing facades with {} images:", library.len());
        for image in &library {
            eprintln!("  {} -> {}x{}", image.path.display(), image.width, image.height);
        }
    }
    let encoded: Vec<_> = library
        .into_par_iter()
        .map(|image| texture::encode_chain(image.rgba, image.width, image.height, format))
        .collect();
    let shared = encoded.len() as u64;
    for texture in encoded {
        let t = texture?;
        writer.add_texture(format, t.width, t.height, t.mip_count, &t.chain, t.mean)?;
    }
    let mut procedural = Vec::with_capacity(city.textures.len());
    for (mesh, spec) in city.scene.meshes.iter_mut().zip(&city.textures) {
        if shared > 0 && matches!(spec.content, layout::Content::Facade(_)) {
            mesh.texture = (rng::mix(&[args.seed, spec.seed]) % shared) as u32;
        } else {
            mesh.texture = (shared + procedural.len() as u64) as u32;
            procedural.push(*spec);
        }
    }

    let mut progress = Progress::new(procedural.len(), args.quiet);
    // Large enough to keep both cores busy, small enough to bound memory (~100 MB at 512²).
    const CHUNK: usize = 1024;
    for chunk in procedural.chunks(CHUNK) {
        let encoded: Vec<_> = chunk.par_iter().map(|spec| texture::generate(spec, format)).collect();
        for texture in encoded {
            let t = texture?;
            writer.add_texture(format, t.width, t.height, t.mip_count, &t.chain, t.mean)?;
        }
        progress.advance(chunk.len());
    }
    progress.finish();
    writer
        .finish(&city.scene)
        .with_context(|| format!("writing {}", args.out.display()))
}

/// Changes whenever the standard generator would write other bytes for the same
/// arguments, so that shards of another build are not joined with this one's.
const GENERATOR_VERSION: u32 = 1;

/// Writes shard `shard` of the city (see [`crate::shard`]): its contiguous range of the
/// texture ids and the meshes that use them, numbered from 0, resumable at every chunk.
fn generate_shard(args: &GenArgs, format: TextureFormat, city: layout::City, shard: Shard) -> Result<WriteSummary> {
    if args.textures_from.is_some() {
        bail!("--shard: --textures-from is not supported (its shared textures are used all over the city, not by one shard's range)");
    }
    let range = shard.range(city.textures.len());
    // The standard layout gives mesh m texture m: a shard's meshes are those of its range.
    if let Some((m, _)) = city
        .scene
        .meshes
        .iter()
        .enumerate()
        .find(|(m, mesh)| mesh.texture as usize != *m)
    {
        bail!("--shard: mesh {m} does not use texture {m}; this layout cannot be divided by texture ranges");
    }
    let job = format!(
        "citystream gen --preset {:?} --seed {} --format {} --max-extent {}, generator {GENERATOR_VERSION}, layout {:08x}",
        args.preset,
        args.seed,
        format.name(),
        args.max_extent,
        scene_fingerprint(&city.scene, city.textures.len())
    )
    .to_lowercase();
    let out = ShardWrite::begin(&args.out, shard, &job, args.quiet)?;
    let part = city
        .scene
        .part(|mesh| range.contains(&(mesh.texture as usize)), range.start as u32)?;
    let resume_job = format!("{job}, shard {} of {}", shard.index, shard.count);
    let mut writer = DatasetWriter::create_resumable(out.dir(), &resume_job).with_context(|| {
        format!(
            "starting shard {} of {} in {}",
            shard.index,
            shard.count,
            out.dir().display()
        )
    })?;
    let done = (writer.texture_count() as usize).min(range.len());
    if writer.resumed() && !args.quiet {
        eprintln!(
            "gen: resuming shard {}/{}: {done} of {} textures are written",
            shard.index,
            shard.count,
            range.len()
        );
    }
    let specs = &city.textures[range.start + done..range.end];
    let mut progress = Progress::resumed(range.len(), done, "textures", 10, args.quiet || range.len() < 10_000);
    const CHUNK: usize = 1024;
    for chunk in specs.chunks(CHUNK) {
        let encoded: Vec<_> = chunk.par_iter().map(|spec| texture::generate(spec, format)).collect();
        for texture in encoded {
            let t = texture?;
            writer.add_texture(format, t.width, t.height, t.mip_count, &t.chain, t.mean)?;
        }
        writer.checkpoint()?;
        progress.advance(chunk.len());
    }
    progress.finish();
    let record = ShardRecord {
        job,
        index: shard.index,
        count: shard.count,
        textures: writer.texture_count(),
        meshes: part.meshes.len() as u32,
        pack_bytes: writer.pack_len(),
    };
    writer.add_file(SHARD_RECORD_FILE, &record.encode()?)?;
    let summary = writer
        .finish(&part)
        .with_context(|| format!("writing {}", out.dir().display()))?;
    out.publish()?;
    Ok(summary)
}

/// A one-line progress report on stderr, redrawn in place on a terminal and printed every
/// `step` per cent otherwise, with the rate and the time left.
pub(crate) struct Progress {
    total: usize,
    done: usize,
    /// Items done before this run (a resumed write): not part of the rate.
    start_done: usize,
    unit: &'static str,
    step: usize,
    start: Instant,
    last_step: usize,
    enabled: bool,
    terminal: bool,
}

impl Progress {
    /// Progress of `total` textures, every 10 %; silent for fewer than 10,000.
    pub(crate) fn new(total: usize, quiet: bool) -> Self {
        Self::resumed(total, 0, "textures", 10, quiet || total < 10_000)
    }

    /// Progress of `total` items of `unit`, `done` of them before this run, every `step` %.
    pub(crate) fn resumed(total: usize, done: usize, unit: &'static str, step: usize, quiet: bool) -> Self {
        let step = step.max(1);
        Self {
            total,
            done,
            start_done: done,
            unit,
            step,
            start: Instant::now(),
            last_step: done * 100 / total.max(1) / step,
            enabled: !quiet,
            terminal: std::io::stderr().is_terminal(),
        }
    }

    pub(crate) fn advance(&mut self, n: usize) {
        self.done += n;
        let percent = self.done * 100 / self.total.max(1);
        if !self.enabled || (!self.terminal && percent / self.step == self.last_step) {
            return;
        }
        self.last_step = percent / self.step;
        let elapsed = self.start.elapsed().as_secs_f64();
        let rate = (self.done - self.start_done) as f64 / elapsed.max(1e-9);
        let left = (self.total - self.done) as f64 / rate.max(1e-9);
        let line = format!(
            "gen: {}/{} {} ({percent}%), {rate:.1}/s, {} elapsed, about {} left",
            self.done,
            self.total,
            self.unit,
            duration(elapsed),
            duration(left)
        );
        let mut err = std::io::stderr().lock();
        // Progress output is best effort: a closed stderr must not stop generation.
        let _ = if self.terminal {
            write!(err, "\r{line}\x1b[K")
        } else {
            writeln!(err, "{line}")
        };
    }

    pub(crate) fn finish(&self) {
        if self.enabled && self.terminal {
            let _ = writeln!(std::io::stderr());
        }
    }
}

/// Seconds as `1 h 02 min`, `3 min 07 s` or `42 s`.
fn duration(seconds: f64) -> String {
    let s = seconds.max(0.0).round() as u64;
    if s >= 3600 {
        format!("{} h {:02} min", s / 3600, s % 3600 / 60)
    } else if s >= 60 {
        format!("{} min {:02} s", s / 60, s % 60)
    } else {
        format!("{s} s")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The presets promise sizes (tests use `tiny`, the benchmark uses `large`, `city` must
    /// reach the paper's scale); check them on the layout, which is cheap.
    /// Written, reopened, every mip byte-identical to what the generator produced.
    #[test]
    fn tiny_city_round_trips_every_mip() -> Result<()> {
        let out = std::env::temp_dir().join(format!("citystream-gen-roundtrip-{}", std::process::id()));
        let args = GenArgs {
            quiet: true,
            ..GenArgs::new(Preset::Tiny, 3, out.clone())
        };
        let summary = generate(&args, Preset::Tiny.params(), TextureFormat::Bc1)?;
        let dataset = citystream_dataset::Dataset::open(&out)?;
        let city = layout::layout(Preset::Tiny.params(), 3)?;
        assert_eq!(dataset.scene, city.scene);
        assert_eq!(summary.textures as usize, city.textures.len());
        let mut buf = Vec::new();
        for (id, spec) in city.textures.iter().enumerate() {
            let expected = texture::generate(spec, TextureFormat::Bc1)?;
            let mut offset = 0;
            for level in 0..expected.mip_count {
                dataset.textures.read_mip(id as u32, level, &mut buf)?;
                assert_eq!(
                    buf,
                    expected.chain[offset..offset + buf.len()],
                    "texture {id} level {level}"
                );
                offset += buf.len();
            }
            assert_eq!(offset, expected.chain.len());
            assert_eq!(dataset.colormap.get(id as u32), Some(expected.mean));
        }
        std::fs::remove_dir_all(&out)?;
        Ok(())
    }

    #[test]
    fn presets_have_their_documented_texture_counts() {
        let count = |p: Preset| layout::layout(p.params(), 1).expect("layout").textures.len();
        let tiny = count(Preset::Tiny);
        assert!((50..=1_000).contains(&tiny), "tiny has {tiny}");
        let small = count(Preset::Small);
        assert!((2_000..=10_000).contains(&small), "small has {small}");
        let large = count(Preset::Large);
        assert!((90_000..=130_000).contains(&large), "large has {large}");
        let city = count(Preset::City);
        assert!(city >= 1_000_000, "city has {city}");
        eprintln!("textures: tiny {tiny}, small {small}, large {large}, city {city}");
    }
}
