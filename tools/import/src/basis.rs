//! `KHR_texture_basisu` textures: KTX2 files of Basis Universal data (ETC1S with BasisLZ, or
//! UASTC with or without zstd), transcoded by `basisu` (a pure-Rust port of the reference
//! transcoder, bit-exact with it) straight into the dataset's block format: each Basis block
//! maps onto a BC1, BC3 or BC7 block without decoding the image and encoding it again. The
//! levels are kept as shipped (those finer than `--max-extent` dropped).
//!
//! The container is checked before the transcoder sees it ([`check_container`]: the
//! transcoder trusts the offsets, lengths and counts a file declares, and the fuzzer found
//! them overflowing its arithmetic and sizing its allocations): sides up to the largest
//! texture side, one 2D image (no arrays, cube maps or video), every range inside the file,
//! each UASTC level exactly its blocks' size (zstd levels declaring exactly that), and no
//! level may transcode to more than [`MAX_EXPANSION`] times the file's bytes plus 16 MiB,
//! which ETC1S's best compression on real images stays below.

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
    #[error("a damaged Basis Universal KTX2 file: {0}")]
    Container(String),
    #[error(
        "transcoding would hold {bytes} bytes, more than the {capacity} all transcodes of the import may hold at once"
    )]
    OverBudget { bytes: u64, capacity: u64 },
}

/// Bytes the Basis textures being transcoded at once may hold between them: one process
/// bound, whatever the number of cores (the import transcodes a document's textures in
/// parallel). Each transcode reserves its working bytes ([`BasisTexture::working_bytes`])
/// before it allocates and waits while others hold the room; the capacity is the working
/// bytes of the largest texture the import takes (a zstd UASTC texture of the largest side),
/// so any one fits and large ones run one at a time.
#[derive(Debug)]
pub struct TranscodeBudget {
    capacity: u64,
    used: std::sync::Mutex<u64>,
    freed: std::sync::Condvar,
    peak: std::sync::atomic::AtomicU64,
}

/// The budget every transcode of this process shares.
pub static PROCESS_TRANSCODE_BUDGET: TranscodeBudget = TranscodeBudget::new(working_bytes(
    citystream_gen::library::MAX_IMAGE_SIDE,
    citystream_gen::library::MAX_IMAGE_SIDE,
    true,
));

/// Room held in a [`TranscodeBudget`] until dropped.
#[derive(Debug)]
#[must_use = "the room is given back when the reservation is dropped"]
pub struct Reservation<'a> {
    budget: &'a TranscodeBudget,
    bytes: u64,
}

impl TranscodeBudget {
    /// A budget of `capacity` bytes.
    pub const fn new(capacity: u64) -> Self {
        Self {
            capacity,
            used: std::sync::Mutex::new(0),
            freed: std::sync::Condvar::new(),
            peak: std::sync::atomic::AtomicU64::new(0),
        }
    }

    /// Holds `bytes` of the budget, waiting until others leave room; more than the whole
    /// budget is refused.
    pub fn reserve(&self, bytes: u64) -> Result<Reservation<'_>, BasisError> {
        if bytes > self.capacity {
            return Err(BasisError::OverBudget {
                bytes,
                capacity: self.capacity,
            });
        }
        // A poisoned lock only means another transcode panicked; the count is still right.
        let mut used = self.used.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        while *used + bytes > self.capacity {
            used = self.freed.wait(used).unwrap_or_else(std::sync::PoisonError::into_inner);
        }
        *used += bytes;
        self.peak.fetch_max(*used, std::sync::atomic::Ordering::Relaxed);
        Ok(Reservation { budget: self, bytes })
    }

    /// The most bytes held at once so far.
    pub fn peak(&self) -> u64 {
        self.peak.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// The budget's bytes.
    pub fn capacity(&self) -> u64 {
        self.capacity
    }
}

impl Drop for Reservation<'_> {
    fn drop(&mut self) {
        let mut used = self
            .budget
            .used
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        *used -= self.bytes;
        self.budget.freed.notify_all();
    }
}

/// What transcoding a `width`×`height` texture may hold at once: its level 0 as RGBA8 four
/// times over (the transcoded levels, the decode for its mean colour or, for a tinted or
/// resized texture, the RGBA image, its resized copy and the chain encoded from it) and, for
/// zstd, its largest level inflated.
const fn working_bytes(width: u32, height: u32, zstd: bool) -> u64 {
    let texels = width as u64 * height as u64;
    let inflated = if zstd {
        (width as u64).div_ceil(4) * (height as u64).div_ceil(4) * 16
    } else {
        0
    };
    texels * 16 + inflated
}

fn u32_at(bytes: &[u8], at: usize) -> u64 {
    bytes
        .get(at..at + 4)
        .map_or(0, |b| u64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])))
}

fn u64_at(bytes: &[u8], at: usize) -> u64 {
    bytes.get(at..at + 8).map_or(0, |b| {
        u64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]])
    })
}

/// Checks what the transcoder would trust in a KTX2 file of Basis data: the header's
/// shape (a 2D texture of sides 1 to the largest texture side, one layer and face, at most
/// a full chain of levels, no supercompression but BasisLZ and zstd), every range the
/// index names inside the file, UASTC levels exactly their blocks' size (a zstd level
/// declaring exactly that uncompressed), and ETC1S's global data (codebooks, tables and one
/// image descriptor per level) inside its range, each image's slices inside its level.
pub fn check_container(bytes: &[u8]) -> Result<(), BasisError> {
    let bad = |what: String| Err(BasisError::Container(what));
    if bytes.len() < 80 || !is_basis(bytes) {
        return bad(format!("{} bytes, not a KTX2 header of Basis data", bytes.len()));
    }
    let file = bytes.len() as u64;
    let (width, height, depth) = (u32_at(bytes, 20), u32_at(bytes, 24), u32_at(bytes, 28));
    let (layers, faces, levels, scheme) = (
        u32_at(bytes, 32),
        u32_at(bytes, 36),
        u32_at(bytes, 40),
        u32_at(bytes, 44),
    );
    let max = u64::from(citystream_gen::library::MAX_IMAGE_SIDE);
    if !(1..=max).contains(&width) || !(1..=max).contains(&height) || depth > 1 {
        return bad(format!("a {width}x{height}x{depth} texture (2D, sides 1 to {max})"));
    }
    if layers > 1 || faces != 1 {
        return bad(format!("{layers} layers and {faces} faces (one 2D image is read)"));
    }
    let full_chain = u64::from(64 - width.max(height).leading_zeros());
    if !(1..=full_chain).contains(&levels) {
        return bad(format!("{levels} levels for a {width}x{height} texture"));
    }
    if scheme > 2 {
        return bad(format!("supercompression scheme {scheme} (BasisLZ and zstd are read)"));
    }
    let in_file = |offset: u64, length: u64, what: &str| -> Result<(), BasisError> {
        match offset.checked_add(length) {
            Some(end) if end <= file => Ok(()),
            _ => Err(BasisError::Container(format!(
                "{what} at bytes {offset}..+{length} runs past the file's {file}"
            ))),
        }
    };
    in_file(u32_at(bytes, 48), u32_at(bytes, 52), "the data format descriptor")?;
    in_file(u32_at(bytes, 56), u32_at(bytes, 60), "the key/value data")?;
    let (sgd, sgd_len) = (u64_at(bytes, 64), u64_at(bytes, 72));
    in_file(sgd, sgd_len, "the supercompression global data")?;
    in_file(80, 24 * levels, "the level index")?;
    let mut level_ranges = Vec::new();
    for l in 0..levels {
        let at = 80 + 24 * l as usize;
        let (offset, length, uncompressed) = (u64_at(bytes, at), u64_at(bytes, at + 8), u64_at(bytes, at + 16));
        in_file(offset, length, &format!("level {l}"))?;
        if length == 0 {
            return bad(format!("level {l} holds no bytes: a truncated KTX2 file"));
        }
        let blocks = (width >> l).max(1).div_ceil(4) * (height >> l).max(1).div_ceil(4);
        let uastc = blocks * 16;
        match scheme {
            0 if length != uastc => {
                return bad(format!(
                    "level {l} holds {length} bytes, not its {uastc} of UASTC blocks"
                ))
            }
            2 if uncompressed != uastc => {
                return bad(format!(
                    "level {l} declares {uncompressed} bytes uncompressed, not its {uastc} of UASTC blocks"
                ))
            }
            2 => {
                // The transcoder reports a level that is not zstd, or inflates to another
                // size, only as an unsupported target: checked here, by name.
                let data = &bytes[offset as usize..(offset + length) as usize];
                match zstd_inflated_len(data, uastc + 1) {
                    Err(why) => return bad(format!("level {l}: not zstd data ({why})")),
                    Ok(inflated) if inflated > uastc => {
                        return bad(format!(
                            "level {l}: zstd data inflates to more than the declared {uncompressed} bytes"
                        ))
                    }
                    Ok(inflated) if inflated < uastc => {
                        return bad(format!(
                            "level {l}: zstd data inflates to {inflated} bytes, not the declared {uncompressed}"
                        ))
                    }
                    Ok(_) => {}
                }
            }
            _ => {}
        }
        level_ranges.push(length);
    }
    if scheme == 1 {
        // BasisLZ: a 20-byte header (codebook sizes, then their byte lengths), one 20-byte
        // image descriptor per level, then the codebooks and tables.
        let images = 20 + 20 * levels;
        let payload = images
            + u32_at(bytes, sgd as usize + 4)
            + u32_at(bytes, sgd as usize + 8)
            + u32_at(bytes, sgd as usize + 12);
        if sgd_len < images || payload > sgd_len {
            return bad(format!(
                "BasisLZ global data of {sgd_len} bytes, short of its {payload} bytes of descriptors and codebooks"
            ));
        }
        for (l, length) in level_ranges.iter().enumerate() {
            let at = sgd as usize + 20 + 20 * l;
            for (slice, o) in [("RGB", 4), ("alpha", 12)] {
                let (start, len) = (u32_at(bytes, at + o), u32_at(bytes, at + o + 4));
                if start + len > *length {
                    return bad(format!(
                        "level {l}'s {slice} slice at {start}..+{len} runs past the level's {length} bytes"
                    ));
                }
            }
        }
    }
    Ok(())
}

/// How many bytes the zstd frame `data` inflates to, counting at most `limit` (nothing is
/// kept: the output is counted, not stored).
fn zstd_inflated_len(data: &[u8], limit: u64) -> Result<u64, String> {
    use std::io::Read;
    let decoder = ruzstd::StreamingDecoder::new(data).map_err(|e| e.to_string())?;
    std::io::copy(&mut decoder.take(limit), &mut std::io::sink()).map_err(|e| e.to_string())
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
        check_container(bytes)?;
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

    /// What transcoding this texture may hold at once (see [`TranscodeBudget`]).
    pub fn working_bytes(&self) -> u64 {
        working_bytes(self.width, self.height, self.codec == BasisCodec::UastcZstd)
    }

    /// Holds this texture's working bytes in the process's budget (waiting while other
    /// transcodes hold it); keep the reservation until its images are encoded.
    pub fn reserve(&self) -> Result<Reservation<'static>, BasisError> {
        PROCESS_TRANSCODE_BUDGET.reserve(self.working_bytes())
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

    fn fixture(name: &str) -> Vec<u8> {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../test-data/encoded-tilesets/fuzz")
            .join(name);
        std::fs::read(&path).expect("fixture")
    }

    #[test]
    fn shipped_levels_are_transcoded_from_the_first_within_the_extent() {
        for (file, codec) in [
            ("roof-etc1s.ktx2", BasisCodec::Etc1s),
            ("roof-uastc.ktx2", BasisCodec::Uastc),
            ("roof-uastc-zstd.ktx2", BasisCodec::UastcZstd),
        ] {
            let bytes = fixture(file);
            let texture = BasisTexture::open(&bytes).expect(file);
            assert_eq!((texture.codec, texture.width, texture.height), (codec, 64, 64));
            let full = texture
                .blocks(TextureFormat::Bc7, 14)
                .expect(file)
                .expect("kept as shipped");
            assert_eq!((full.width, full.mip_count), (64, 7));
            assert_eq!(
                full.chain.len() as u64,
                (0..7)
                    .map(|l| TextureFormat::Bc7.mip_bytes(64 >> l, 64 >> l))
                    .sum::<u64>()
            );
            let half = texture
                .blocks(TextureFormat::Bc1, 5)
                .expect(file)
                .expect("kept as shipped");
            assert_eq!((half.width, half.height, half.mip_count), (32, 32, 6));
            assert_eq!(texture.rgba().expect(file).dimensions(), (64, 64));
        }
    }

    #[test]
    fn damaged_containers_are_refused_before_the_transcoder_sees_them() {
        let good = fixture("roof-uastc-zstd.ktx2");
        let refused = |edit: &dyn Fn(&mut Vec<u8>)| {
            let mut bytes = good.clone();
            edit(&mut bytes);
            BasisTexture::open(&bytes).expect_err("refused").to_string()
        };
        // Level 0's uncompressed length one block more than its blocks (the 2^57-byte
        // allocation the fuzzer found declared such a length).
        let error = refused(&|b| {
            let at = 80 + 16;
            let length = u64_at(b, at) + 16;
            b[at..at + 8].copy_from_slice(&length.to_le_bytes());
        });
        assert!(error.contains("uncompressed"), "{error}");
        assert!(refused(&|b| b.truncate(b.len() - 100)).contains("runs past"));
        assert!(refused(&|b| b[40..44].copy_from_slice(&20u32.to_le_bytes())).contains("20 levels"));
        assert!(refused(&|b| b[20..24].copy_from_slice(&40_000u32.to_le_bytes())).contains("40000x64"));
        assert!(refused(&|b| b[32..36].copy_from_slice(&6u32.to_le_bytes())).contains("6 layers"));
        let etc1s = fixture("roof-etc1s.ktx2");
        let mut short = etc1s.clone();
        // The global data's endpoint codebook claims more bytes than the global data holds.
        let sgd = u64_at(&short, 64) as usize;
        short[sgd + 4..sgd + 8].copy_from_slice(&u32::MAX.to_le_bytes());
        let error = BasisTexture::open(&short).expect_err("refused").to_string();
        assert!(error.contains("BasisLZ global data"), "{error}");
    }

    /// A KTX2 file of one 4x4 UASTC level (16 bytes of blocks) stored as `level`, zstd.
    fn one_zstd_level(level: &[u8]) -> Vec<u8> {
        let mut file = KTX2_MAGIC.to_vec();
        file.extend_from_slice(&[0; 68]);
        let mut put = |at: usize, v: u32| file[at..at + 4].copy_from_slice(&v.to_le_bytes());
        put(20, 4); // width
        put(24, 4); // height
        put(36, 1); // faces
        put(40, 1); // levels
        put(44, 2); // zstd
        file.extend_from_slice(&104u64.to_le_bytes());
        file.extend_from_slice(&(level.len() as u64).to_le_bytes());
        file.extend_from_slice(&16u64.to_le_bytes());
        file.extend_from_slice(level);
        file
    }

    /// A zstd frame holding `bytes` in one raw block.
    fn zstd_frame(bytes: &[u8]) -> Vec<u8> {
        let mut frame = 0xFD2F_B528u32.to_le_bytes().to_vec();
        // Single segment, a one-byte content size.
        frame.extend_from_slice(&[0x20, bytes.len() as u8]);
        let header = 1 | ((bytes.len() as u32) << 3); // last block, raw
        frame.extend_from_slice(&header.to_le_bytes()[..3]);
        frame.extend_from_slice(bytes);
        frame
    }

    #[test]
    fn a_zstd_level_of_another_size_or_not_zstd_is_named() {
        check_container(&one_zstd_level(&zstd_frame(&[7; 16]))).expect("16 bytes, as declared");
        let error = |level: &[u8]| {
            check_container(&one_zstd_level(level))
                .expect_err("refused")
                .to_string()
        };
        let half = error(&zstd_frame(&[7; 8]));
        assert!(
            half.contains("level 0: zstd data inflates to 8 bytes, not the declared 16"),
            "{half}"
        );
        let twice = error(&zstd_frame(&[7; 32]));
        assert!(
            twice.contains("level 0: zstd data inflates to more than the declared 16 bytes"),
            "{twice}"
        );
        let garbage = error(&[0x55; 24]);
        assert!(garbage.contains("level 0: not zstd data"), "{garbage}");
    }

    #[test]
    fn a_level_of_no_bytes_is_a_truncated_file() {
        let mut bytes = fixture("roof-etc1s.ktx2");
        let (levels, sgd) = (u32_at(&bytes, 40) as usize, u64_at(&bytes, 64) as usize);
        for l in 0..levels {
            // Each level empty, and its image descriptor's slices empty with it.
            bytes[80 + 24 * l + 8..80 + 24 * l + 16].copy_from_slice(&0u64.to_le_bytes());
            bytes[sgd + 20 + 20 * l + 4..sgd + 20 + 20 * l + 20].copy_from_slice(&[0; 16]);
        }
        let error = BasisTexture::open(&bytes).expect_err("refused").to_string();
        assert!(
            error.contains("level 0 holds no bytes: a truncated KTX2 file"),
            "{error}"
        );
    }

    #[test]
    fn transcodes_share_one_budget_and_wait_for_room() {
        let budget = TranscodeBudget::new(100);
        let in_use = std::sync::atomic::AtomicU64::new(0);
        let most = std::sync::atomic::AtomicU64::new(0);
        std::thread::scope(|scope| {
            for _ in 0..4 {
                scope.spawn(|| {
                    for _ in 0..50 {
                        let held = budget.reserve(60).expect("60 of 100");
                        let now = in_use.fetch_add(60, std::sync::atomic::Ordering::SeqCst) + 60;
                        most.fetch_max(now, std::sync::atomic::Ordering::SeqCst);
                        std::thread::yield_now();
                        in_use.fetch_sub(60, std::sync::atomic::Ordering::SeqCst);
                        drop(held);
                    }
                });
            }
        });
        // Two of 60 never fit in 100: the four threads took turns.
        assert_eq!(most.into_inner(), 60);
        assert_eq!(budget.peak(), 60);
        let small = budget.reserve(30).expect("30");
        let other = budget.reserve(70).expect("70 beside 30");
        drop((small, other));
        let error = budget
            .reserve(101)
            .map(drop)
            .expect_err("more than the budget")
            .to_string();
        assert!(error.contains("101 bytes, more than the 100"), "{error}");
        // The process's budget takes the largest texture the import reads.
        let largest = citystream_gen::library::MAX_IMAGE_SIDE;
        assert_eq!(
            PROCESS_TRANSCODE_BUDGET.capacity(),
            working_bytes(largest, largest, true)
        );
        let bytes = fixture("roof-uastc-zstd.ktx2");
        let texture = BasisTexture::open(&bytes).expect("fixture");
        assert_eq!(texture.working_bytes(), 64 * 64 * 16 + 16 * 16 * 16);
    }

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
