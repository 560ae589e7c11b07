//! `KHR_texture_basisu` textures: KTX2 files of Basis Universal data (ETC1S with BasisLZ, or
//! UASTC with or without zstd), transcoded by `basisu` (a pure-Rust port of the reference
//! transcoder, bit-exact with it) straight into the dataset's block format: each Basis block
//! maps onto a BC1, BC3 or BC7 block without decoding the image and encoding it again. The
//! levels are kept as shipped (those finer than `--max-extent` dropped).
//!
//! Sizes are checked before anything is transcoded: sides up to the largest texture side,
//! one 2D image (no arrays, cube maps or video), and no level may transcode to more than
//! [`MAX_EXPANSION`] times the file's bytes plus 16 MiB, which ETC1S's best compression on
//! real images stays below, so a damaged header cannot make the import allocate gigabytes.

use basisu::{DecodeFlags, SourceFormat, Supercompression, TargetFormat, Transcoder};
use citystream_dataset::TextureFormat;
use citystream_gen::texture::{decode_level, mean_colour, EncodedTexture};
use image::RgbaImage;

/// Most bytes a level may transcode to, per byte of the file (ETC1S at its smallest, 0.3
/// bits per texel, is about 107 times smaller than RGBA8).
pub const MAX_EXPANSION: u64 = 256;
const EXPANSION_SLACK: u64 = 16 << 20;

const KTX2_MAGIC: [u8; 12] = [0xAB, 0x4B, 0x54, 0x58, 0x20, 0x32, 0x30, 0xBB, 0x0D, 0x0A, 0x1A, 0x0A];

/// Why a Basis texture could not be transcoded.
#[derive(Debug, thiserror::Error)]
pub enum BasisError {
    #[error("a Basis Universal KTX2 file the transcoder refuses: {0:?}")]
    Transcoder(basisu::Error),
    #[error(
        "a Basis Universal KTX2 file of {0}, which the import does not read (ETC1S and UASTC LDR 2D textures are)"
    )]
    Unsupported(String),
    #[error("a {width}x{height} Basis Universal texture (sides 1 to {max})")]
    Extent { width: u32, height: u32, max: u32 },
    #[error("level {level} would transcode to {bytes} bytes from a {file}-byte file (at most {MAX_EXPANSION} times its size plus 16 MiB)")]
    TooLarge { level: u32, bytes: u64, file: u64 },
}

impl From<basisu::Error> for BasisError {
    fn from(e: basisu::Error) -> Self {
        Self::Transcoder(e)
    }
}

/// Whether `bytes` is a KTX2 file of Basis Universal data (`vkFormat` undefined, as
/// `KHR_texture_basisu` requires).
pub fn is_basis(bytes: &[u8]) -> bool {
    bytes.starts_with(&KTX2_MAGIC) && bytes.get(12..16) == Some(&[0, 0, 0, 0])
}

/// The Basis codec of a texture, as `info` counts textures by encoding.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BasisCodec {
    Etc1s,
    Uastc,
    UastcZstd,
}

impl BasisCodec {
    /// Name in `info`'s counts.
    pub fn name(self) -> &'static str {
        match self {
            BasisCodec::Etc1s => "ktx2-etc1s",
            BasisCodec::Uastc => "ktx2-uastc",
            BasisCodec::UastcZstd => "ktx2-uastc-zstd",
        }
    }
}

/// A Basis KTX2 file opened and checked.
pub struct BasisTexture<'a> {
    transcoder: Transcoder<'a>,
    pub codec: BasisCodec,
    pub width: u32,
    pub height: u32,
    file_len: u64,
}

impl std::fmt::Debug for BasisTexture<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "BasisTexture({:?}, {}x{})", self.codec, self.width, self.height)
    }
}

impl<'a> BasisTexture<'a> {
    /// Opens `bytes` (a file [`is_basis`] accepts).
    pub fn open(bytes: &'a [u8]) -> Result<Self, BasisError> {
        let transcoder = Transcoder::new(bytes)?;
        let codec = match (transcoder.source_format(), transcoder.supercompression()) {
            (SourceFormat::Etc1s, _) => BasisCodec::Etc1s,
            (SourceFormat::UastcLdr, Supercompression::Zstandard) => BasisCodec::UastcZstd,
            (SourceFormat::UastcLdr, Supercompression::None) => BasisCodec::Uastc,
            (source, scheme) => {
                return Err(BasisError::Unsupported(format!(
                    "{source:?} with {scheme:?} supercompression"
                )))
            }
        };
        if transcoder.is_video() || transcoder.layer_count() > 1 || transcoder.face_count() != 1 {
            return Err(BasisError::Unsupported(format!(
                "{} layers, {} faces{}",
                transcoder.layer_count(),
                transcoder.face_count(),
                if transcoder.is_video() { ", video" } else { "" }
            )));
        }
        let (width, height) = transcoder.base_dimensions();
        let max = citystream_gen::library::MAX_IMAGE_SIDE;
        if !(1..=max).contains(&width) || !(1..=max).contains(&height) {
            return Err(BasisError::Extent { width, height, max });
        }
        Ok(Self {
            transcoder,
            codec,
            width,
            height,
            file_len: bytes.len() as u64,
        })
    }

    /// Level `level` transcoded to `target`, once its size is checked.
    fn transcode(&self, level: u32, target: TargetFormat) -> Result<Vec<u8>, BasisError> {
        let bytes = self.transcoder.output_size(level, target)? as u64;
        if bytes
            > self
                .file_len
                .saturating_mul(MAX_EXPANSION)
                .saturating_add(EXPANSION_SLACK)
        {
            return Err(BasisError::TooLarge {
                level,
                bytes,
                file: self.file_len,
            });
        }
        Ok(self.transcoder.transcode(level, target, DecodeFlags::NONE)?)
    }

    /// The texture in `format` with the file's levels as shipped, from the first at most
    /// `2^max_log2` a side: each block transcoded directly. `None` where that cannot be kept
    /// as it is (sides that are not powers of two, or no shipped level within the extent):
    /// the caller decodes [`rgba`](Self::rgba) and encodes it instead.
    pub fn blocks(&self, format: TextureFormat, max_log2: u32) -> Result<Option<EncodedTexture>, BasisError> {
        let (width, height) = (self.width, self.height);
        if !width.is_power_of_two() || !height.is_power_of_two() || width < 4 || height < 4 {
            return Ok(None);
        }
        let first = width.max(height).trailing_zeros().saturating_sub(max_log2);
        let full_chain = width.max(height).trailing_zeros() + 1;
        let shipped = self.transcoder.level_count().min(full_chain);
        let (w0, h0) = (width >> first, height >> first);
        if first >= shipped || w0 < 4 || h0 < 4 {
            return Ok(None);
        }
        let target = match format {
            TextureFormat::Bc1 => TargetFormat::Bc1Rgb,
            TextureFormat::Bc3 => TargetFormat::Bc3Rgba,
            TextureFormat::Bc7 => TargetFormat::Bc7Rgba,
            TextureFormat::Rgba8 => TargetFormat::Rgba32,
        };
        let mut chain = Vec::new();
        let mut level0 = Vec::new();
        for level in first..shipped {
            let info = self.transcoder.image_level_info(level)?;
            let (w, h) = ((width >> level).max(1), (height >> level).max(1));
            if (info.width, info.height) != (w, h) {
                return Err(BasisError::Unsupported(format!(
                    "level {level} of {}x{} in a {width}x{height} texture",
                    info.width, info.height
                )));
            }
            let data = self.transcode(level, target)?;
            if data.len() as u64 != format.mip_bytes(w, h) {
                return Err(BasisError::Unsupported(format!(
                    "level {level} transcoded to {} bytes, not the {} of a {w}x{h} {}",
                    data.len(),
                    format.mip_bytes(w, h),
                    format.name()
                )));
            }
            if level == first {
                level0 = data.clone();
            }
            chain.extend_from_slice(&data);
        }
        let mean = mean_colour(&decode_level(format, &level0, w0, h0));
        Ok(Some(EncodedTexture {
            format,
            width: w0,
            height: h0,
            mip_count: shipped - first,
            chain,
            mean,
        }))
    }

    /// Level 0 as RGBA8 (for textures that are tinted or need resizing).
    pub fn rgba(&self) -> Result<RgbaImage, BasisError> {
        let data = self.transcode(0, TargetFormat::Rgba32)?;
        let (width, height) = (self.width, self.height);
        RgbaImage::from_raw(width, height, data).ok_or_else(|| {
            BasisError::Unsupported(format!("level 0 transcoded to the wrong size for {width}x{height}"))
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_ktx2_files_of_undefined_format_are_basis() {
        let mut header = KTX2_MAGIC.to_vec();
        header.extend_from_slice(&[0; 40]);
        assert!(is_basis(&header));
        header[12] = 131; // BC1
        assert!(!is_basis(&header));
        assert!(!is_basis(b"\x89PNG\r\n\x1a\n"));
        assert!(BasisTexture::open(&header[..20]).is_err());
    }
}
