//! `--textures-from DIR`: a user's own images as facade textures.
//!
//! PNG, JPEG, DDS (BC1–BC3) and KTX2 (RGBA8 and BC1/BC3 level 0, no supercompression) files
//! under DIR are decoded, resized to the nearest power of two per side (clamped to 4 ..
//! the maximum extent) and mip-mapped like generated textures. Files that cannot be read
//! are reported on stderr and skipped; finding no usable image is an error.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use image::imageops::FilterType;
use image::RgbaImage;
use rayon::prelude::*;

/// One decoded, power-of-two-sized user image.
#[derive(Debug, Clone)]
pub struct UserImage {
    pub path: PathBuf,
    pub width: u32,
    pub height: u32,
    /// RGBA8 rows, top first.
    pub rgba: Vec<u8>,
}

const EXTENSIONS: [&str; 5] = ["png", "jpg", "jpeg", "dds", "ktx2"];

fn collect_files(dir: &Path, out: &mut Vec<PathBuf>) -> Result<()> {
    let entries = std::fs::read_dir(dir).with_context(|| format!("reading directory {}", dir.display()))?;
    for entry in entries {
        let entry = entry.with_context(|| format!("reading directory {}", dir.display()))?;
        let path = entry.path();
        if path.is_dir() {
            collect_files(&path, out)?;
        } else if path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
        {
            out.push(path);
        }
    }
    Ok(())
}

/// Nearest power of two (in log2 terms) of `n`, as log2, clamped to `2..=max_log2`.
pub fn pow2_log2(n: u32, max_log2: u8) -> u8 {
    let log = f64::from(n.max(1)).log2().round() as i64;
    log.clamp(2, i64::from(max_log2)) as u8
}

/// Loads every usable image under `dir`, sorted by path so the result is deterministic.
pub fn load(dir: &Path, max_extent_log2: u8) -> Result<Vec<UserImage>> {
    let mut files = Vec::new();
    collect_files(dir, &mut files)?;
    files.sort();
    let decoded: Vec<_> = files.par_iter().map(|path| (path, decode(path))).collect();
    let mut images = Vec::new();
    for (path, result) in decoded {
        match result {
            Ok(image) => images.push(fit(path, image, max_extent_log2)),
            Err(e) => eprintln!("warning: skipping {}: {e:#}", path.display()),
        }
    }
    if images.is_empty() {
        bail!("no usable PNG, JPEG, DDS or KTX2 image found under {}", dir.display());
    }
    Ok(images)
}

fn fit(path: &Path, image: RgbaImage, max_extent_log2: u8) -> UserImage {
    let w = 1u32 << pow2_log2(image.width(), max_extent_log2);
    let h = 1u32 << pow2_log2(image.height(), max_extent_log2);
    let resized = if (w, h) == image.dimensions() {
        image
    } else {
        image::imageops::resize(&image, w, h, FilterType::Triangle)
    };
    UserImage {
        path: path.to_path_buf(),
        width: w,
        height: h,
        rgba: resized.into_raw(),
    }
}

fn decode(path: &Path) -> Result<RgbaImage> {
    citystream_dataset::ensure_regular_file(path)?;
    decode_image_bytes(&std::fs::read(path)?)
}

/// Largest image side the tools decode: the dataset format's largest texture side.
pub const MAX_IMAGE_SIDE: u32 = 1 << citystream_dataset::MAX_EXTENT_LOG2;

/// Decoded sizes below this are decoded whatever the file size.
const MIN_SUSPICIOUS_DECODE: u64 = 64 << 20;
/// More than deflate's limit (about 1032:1) and than JPEG reaches on flat images.
const MAX_COMPRESSION_RATIO: u64 = 2048;

const KTX2_MAGIC: [u8; 8] = [0xAB, 0x4B, 0x54, 0x58, 0x20, 0x32, 0x30, 0xBB];

/// Decodes a PNG, JPEG, DDS or KTX2 image to RGBA8. Images up to [`MAX_IMAGE_SIDE`] on a
/// side decode (the decoder's memory limit is raised to what that needs); larger ones are
/// refused with their extent, before anything is allocated.
pub fn decode_image_bytes(bytes: &[u8]) -> Result<RgbaImage> {
    if bytes.starts_with(&KTX2_MAGIC) {
        return decode_ktx2(bytes);
    }
    let reader = || image::ImageReader::new(std::io::Cursor::new(bytes)).with_guessed_format();
    let (w, h) = reader()?.into_dimensions()?;
    if w > MAX_IMAGE_SIDE || h > MAX_IMAGE_SIDE {
        bail!("image is {w}x{h}, larger than the maximum {MAX_IMAGE_SIDE} texels per side; downscale it first");
    }
    // Decoders allocate the whole image before reading its data, so a header claiming a
    // huge extent in a tiny file would cost that memory for nothing.
    let decoded = u64::from(w) * u64::from(h) * 4;
    if bytes.starts_with(b"DDS ") {
        // DXT1 stores 8 bytes per 4x4 block, DXT3/5 16: level 0 must be in the file.
        let block = if bytes.get(84..88) == Some(b"DXT1") { 8 } else { 16 };
        let needed = 128 + u64::from(w.div_ceil(4)) * u64::from(h.div_ceil(4)) * block;
        if (bytes.len() as u64) < needed {
            bail!(
                "DDS image of {w}x{h} needs {needed} bytes for its first level, the file has {}",
                bytes.len()
            );
        }
    } else if decoded > MIN_SUSPICIOUS_DECODE && decoded / MAX_COMPRESSION_RATIO > bytes.len() as u64 {
        bail!(
            "image claims {w}x{h} ({} MiB decoded) in {} bytes, beyond any real compression: damaged or hostile",
            decoded >> 20,
            bytes.len()
        );
    }
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(MAX_IMAGE_SIDE);
    limits.max_image_height = Some(MAX_IMAGE_SIDE);
    // RGBA with 16-bit channels at the largest extent: the biggest decode accepted (2 GiB).
    limits.max_alloc = Some(u64::from(MAX_IMAGE_SIDE) * u64::from(MAX_IMAGE_SIDE) * 8);
    let mut reader = reader()?;
    reader.limits(limits);
    Ok(reader.decode()?.into_rgba8())
}

/// Level 0 of a KTX2 file as RGBA8.
pub fn decode_ktx2(bytes: &[u8]) -> Result<RgbaImage> {
    use ktx2::Format;
    let reader = ktx2::Reader::new(bytes).map_err(|e| anyhow::anyhow!("invalid KTX2: {e:?}"))?;
    let header = reader.header();
    if header.supercompression_scheme.is_some() {
        bail!(
            "supercompressed KTX2 ({:?}) is not supported",
            header.supercompression_scheme
        );
    }
    let (w, h) = (header.pixel_width, header.pixel_height.max(1));
    if w == 0 || w > MAX_IMAGE_SIDE || h > MAX_IMAGE_SIDE {
        bail!("KTX2 extent {w}x{h} is out of range");
    }
    let level = reader.levels().next().context("KTX2 file has no levels")?;
    let (wu, hu) = (w as usize, h as usize);
    let rgba = match header.format {
        Some(Format::R8G8B8A8_UNORM | Format::R8G8B8A8_SRGB) => {
            let len = wu * hu * 4;
            level
                .data
                .get(..len)
                .context("KTX2 level 0 is shorter than its extent")?
                .to_vec()
        }
        Some(f) => {
            let codec = match f {
                Format::BC1_RGB_UNORM_BLOCK
                | Format::BC1_RGB_SRGB_BLOCK
                | Format::BC1_RGBA_UNORM_BLOCK
                | Format::BC1_RGBA_SRGB_BLOCK => texpresso::Format::Bc1,
                Format::BC3_UNORM_BLOCK | Format::BC3_SRGB_BLOCK => texpresso::Format::Bc3,
                other => bail!("KTX2 format {other:?} is not supported (RGBA8, BC1 and BC3 are)"),
            };
            let needed = codec.compressed_size(wu, hu);
            let data = level
                .data
                .get(..needed)
                .context("KTX2 level 0 is shorter than its extent")?;
            let mut out = vec![0u8; wu * hu * 4];
            codec.decompress(data, wu, hu, &mut out);
            out
        }
        None => bail!("KTX2 with an undefined format (Basis Universal) is not supported"),
    };
    RgbaImage::from_raw(w, h, rgba).context("KTX2 level 0 has the wrong size")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image_files::{dds_file, ktx2_file};

    /// A PNG of `w`×`h` RGBA8 texels of one colour, compressed fast.
    fn flat_png(w: u32, h: u32) -> Vec<u8> {
        use image::codecs::png::{CompressionType, FilterType as PngFilter, PngEncoder};
        use image::ImageEncoder;
        let texels = vec![7u8; w as usize * h as usize * 4];
        let mut png = Vec::new();
        PngEncoder::new_with_quality(&mut png, CompressionType::Fast, PngFilter::NoFilter)
            .write_image(&texels, w, h, image::ExtendedColorType::Rgba8)
            .expect("encode png");
        png
    }

    #[test]
    fn images_of_the_largest_extent_decode_and_larger_ones_are_refused_by_size() {
        // 16384² RGBA8 is 1 GiB decoded, twice the image crate's default limit.
        let image = decode_image_bytes(&flat_png(MAX_IMAGE_SIDE, MAX_IMAGE_SIDE)).expect("largest extent decodes");
        assert_eq!(image.dimensions(), (MAX_IMAGE_SIDE, MAX_IMAGE_SIDE));
        assert_eq!(image.get_pixel(MAX_IMAGE_SIDE - 1, MAX_IMAGE_SIDE - 1).0, [7; 4]);
        drop(image);
        let err = decode_image_bytes(&flat_png(MAX_IMAGE_SIDE + 1, 2)).expect_err("too wide");
        assert!(
            format!("{err:#}").contains("16385x2, larger than the maximum 16384"),
            "{err:#}"
        );
    }

    #[test]
    fn tiny_files_claiming_huge_images_are_refused_before_allocating() {
        // Found by `fuzz --target texture`: 136 bytes made the decoder allocate 432 MiB.
        let err = decode_image_bytes(&dds_file(b"DXT1", 0, 12292, 12292, &[vec![0u8; 8]])).expect_err("short DDS");
        assert!(format!("{err:#}").contains("needs 75546760 bytes"), "{err:#}");
        assert!(decode_image_bytes(&dds_file(b"DXT1", 0, 8, 8, &[vec![0u8; 32]])).is_ok());
        // A PNG header claiming 16384x16384 with no data behind it.
        let mut png = flat_png(4, 4);
        png[16..24].copy_from_slice(&[0, 0, 0x40, 0, 0, 0, 0x40, 0]);
        let crc = crc32fast::hash(&png[12..29]);
        png[29..33].copy_from_slice(&crc.to_be_bytes());
        let err = decode_image_bytes(&png).expect_err("hostile PNG");
        assert!(format!("{err:#}").contains("beyond any real compression"), "{err:#}");
    }

    #[test]
    fn sizes_round_to_the_nearest_power_of_two_within_limits() {
        assert_eq!(pow2_log2(100, 9), 7);
        assert_eq!(pow2_log2(37, 9), 5);
        assert_eq!(pow2_log2(3000, 9), 9);
        assert_eq!(pow2_log2(1, 9), 2);
        assert_eq!(pow2_log2(64, 9), 6);
    }

    #[test]
    fn dds_dxt1_files_load_through_the_library_scan() {
        // 8x8 DXT1: four blocks of one colour, behind a minimal DDS header.
        let mut block = [0u8; 8];
        let solid = [[30u8, 160, 60, 255]; 16];
        texpresso::Format::Bc1.compress_block_masked(solid, 0xffff, texpresso::Params::default(), &mut block);
        let dds = dds_file(b"DXT1", 0, 8, 8, &[block.repeat(4)]);
        assert_eq!(dds.len(), 128 + 32);
        let dir = std::env::temp_dir().join(format!("citystream-dds-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("create dir");
        std::fs::write(dir.join("wall.DDS"), &dds).expect("write dds");
        let images = load(&dir, 9).expect("load library");
        std::fs::remove_dir_all(&dir).expect("clean up");
        assert_eq!(images.len(), 1);
        assert_eq!((images[0].width, images[0].height), (8, 8));
        assert!(images[0]
            .rgba
            .chunks(4)
            .all(|p| (i32::from(p[1]) - 160).abs() <= 8 && p[0] < 50));
    }

    #[test]
    fn ktx2_rgba8_and_bc1_decode_and_bad_files_are_errors() {
        let rgba: Vec<u8> = (0..4 * 2 * 4).map(|i| i as u8 * 3).collect();
        let image = decode_ktx2(&ktx2_file(37, 4, 2, std::slice::from_ref(&rgba))).expect("rgba8 ktx2");
        assert_eq!(image.dimensions(), (4, 2));
        assert_eq!(image.into_raw(), rgba);

        // One BC1 block of a single colour decodes to 16 texels of (almost) that colour.
        let mut block = [0u8; 8];
        let solid = [[200u8, 40, 40, 255]; 16];
        texpresso::Format::Bc1.compress_block_masked(solid, 0xffff, texpresso::Params::default(), &mut block);
        let image = decode_ktx2(&ktx2_file(131, 4, 4, &[block.to_vec()])).expect("bc1 ktx2");
        assert!(image.pixels().all(|p| (i32::from(p[0]) - 200).abs() <= 8 && p[1] < 60));

        assert!(decode_ktx2(b"not a ktx2 file").is_err());
        let truncated = ktx2_file(37, 64, 64, std::slice::from_ref(&rgba));
        assert!(decode_ktx2(&truncated).is_err(), "level shorter than 64x64");
        assert!(
            decode_ktx2(&ktx2_file(145, 4, 4, &[vec![0u8; 16]])).is_err(),
            "BC7 is refused"
        );
    }
}
