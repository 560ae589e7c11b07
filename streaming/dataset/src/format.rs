//! Texture formats, per-texture metadata and mip-chain arithmetic.
//!
//! Offsets of individual mips are never stored: a texture's mips lie back to back in the
//! pack, finest (level 0) first, so a mip's offset is the base offset plus the sizes of the
//! finer levels. That keeps the per-texture record at ten bytes on disk.

/// The format version this build reads and writes.
pub const FORMAT_VERSION: u32 = 4;

/// Largest supported texture side, as a power of two (2^14 = 16384, the Vulkan guaranteed
/// minimum for `maxImageDimension2D` on desktop GPUs). Anything larger is treated as corrupt.
pub const MAX_EXTENT_LOG2: u8 = 14;

/// Pixel encoding of every mip of one texture.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum TextureFormat {
    /// 8-bit RGBA, 4 bytes per texel, rows tightly packed.
    Rgba8,
    /// BC1 (DXT1): 8 bytes per 4×4 block, blocks in row-major order.
    Bc1,
    /// BC3 (DXT5): 16 bytes per 4×4 block. Read and verified; the generator does not write it.
    Bc3,
    /// BC7: 16 bytes per 4×4 block. Read and verified; the generator does not write it.
    Bc7,
}

impl TextureFormat {
    /// All formats, in code order.
    pub const ALL: [TextureFormat; 4] = [Self::Rgba8, Self::Bc1, Self::Bc3, Self::Bc7];

    /// The byte stored in `textures.meta`.
    pub fn code(self) -> u8 {
        match self {
            Self::Rgba8 => 1,
            Self::Bc1 => 2,
            Self::Bc3 => 3,
            Self::Bc7 => 4,
        }
    }

    /// Inverse of [`TextureFormat::code`]; `None` for unknown codes.
    pub fn from_code(code: u8) -> Option<Self> {
        Self::ALL.into_iter().find(|f| f.code() == code)
    }

    /// Lower-case name used on the command line and in `info` output.
    pub fn name(self) -> &'static str {
        match self {
            Self::Rgba8 => "rgba8",
            Self::Bc1 => "bc1",
            Self::Bc3 => "bc3",
            Self::Bc7 => "bc7",
        }
    }

    /// Inverse of [`TextureFormat::name`].
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|f| f.name() == name)
    }

    /// Whether texels are stored in 4×4 blocks.
    pub fn is_block_compressed(self) -> bool {
        !matches!(self, Self::Rgba8)
    }

    /// Bytes of one mip of `width` × `height` texels. Block formats round each side up to
    /// whole 4×4 blocks, so BC1 levels of 2×2 and 1×1 still take one 8-byte block. Saturates
    /// at `u64::MAX` (only for extents near 2^32 a side, far past any valid texture).
    pub fn mip_bytes(self, width: u32, height: u32) -> u64 {
        let (w, h) = (u64::from(width), u64::from(height));
        let (units, unit_bytes) = match self {
            Self::Rgba8 => (w * h, 4),
            Self::Bc1 => (w.div_ceil(4) * h.div_ceil(4), 8),
            Self::Bc3 | Self::Bc7 => (w.div_ceil(4) * h.div_ceil(4), 16),
        };
        units.saturating_mul(unit_bytes)
    }
}

/// Metadata of one texture: extent, mip count, format and where its mip chain starts.
///
/// In memory this is 12 bytes (measured by a test), on disk 10 bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TextureInfo {
    offset_low: u32,
    offset_high: u16,
    width_log2: u8,
    height_log2: u8,
    mip_count: u8,
    format: TextureFormat,
}

/// Size of one texture record in `textures.meta`.
pub(crate) const TEXTURE_RECORD_BYTES: usize = 10;

/// Largest pack offset the 48-bit record field can hold.
pub const MAX_PACK_OFFSET: u64 = (1 << 48) - 1;

impl TextureInfo {
    /// Builds a record. Fails when the offset does not fit in 48 bits, a side exceeds
    /// 2^[`MAX_EXTENT_LOG2`], a block format has a side below 4, or `mip_count` is 0 or
    /// longer than the full chain to 1×1.
    pub fn new(
        format: TextureFormat,
        width_log2: u8,
        height_log2: u8,
        mip_count: u8,
        offset: u64,
    ) -> Result<Self, String> {
        if width_log2 > MAX_EXTENT_LOG2 || height_log2 > MAX_EXTENT_LOG2 {
            return Err(format!(
                "texture extent 2^{width_log2} x 2^{height_log2} exceeds the maximum 2^{MAX_EXTENT_LOG2}"
            ));
        }
        if format.is_block_compressed() && (width_log2 < 2 || height_log2 < 2) {
            return Err(format!(
                "{} texture of {}x{} is smaller than one 4x4 block",
                format.name(),
                1u32 << width_log2,
                1u32 << height_log2
            ));
        }
        let full_chain = width_log2.max(height_log2) + 1;
        if mip_count == 0 || mip_count > full_chain {
            return Err(format!(
                "mip count {mip_count} is not in 1..={full_chain} for a {}x{} texture",
                1u32 << width_log2,
                1u32 << height_log2
            ));
        }
        if offset > MAX_PACK_OFFSET {
            return Err(format!("pack offset {offset} exceeds 48 bits"));
        }
        Ok(Self {
            offset_low: offset as u32,
            offset_high: (offset >> 32) as u16,
            width_log2,
            height_log2,
            mip_count,
            format,
        })
    }

    /// The same texture with its mip chain at `offset` instead (a pack joined from others).
    pub fn moved_to(&self, offset: u64) -> Result<Self, String> {
        Self::new(self.format, self.width_log2, self.height_log2, self.mip_count, offset)
    }

    /// Pixel format of every mip.
    pub fn format(&self) -> TextureFormat {
        self.format
    }

    /// Width of level 0 in texels (a power of two).
    pub fn width(&self) -> u32 {
        1 << self.width_log2
    }

    /// Height of level 0 in texels (a power of two).
    pub fn height(&self) -> u32 {
        1 << self.height_log2
    }

    /// log2 of the width of level 0.
    pub fn width_log2(&self) -> u8 {
        self.width_log2
    }

    /// log2 of the height of level 0.
    pub fn height_log2(&self) -> u8 {
        self.height_log2
    }

    /// `max(width, height)`, the key the sparse-image cache sorts textures by (paper §3.6).
    pub fn max_extent(&self) -> u32 {
        self.width().max(self.height())
    }

    /// Number of mip levels stored (level 0 is the finest).
    pub fn mip_count(&self) -> u32 {
        u32::from(self.mip_count)
    }

    /// Absolute byte offset of level 0 in `textures.pack`.
    pub fn offset(&self) -> u64 {
        u64::from(self.offset_low) | (u64::from(self.offset_high) << 32)
    }

    /// Extent of `level` (each side halves per level and stops at 1).
    pub fn mip_extent(&self, level: u32) -> (u32, u32) {
        let shift_w = u32::from(self.width_log2).min(level);
        let shift_h = u32::from(self.height_log2).min(level);
        (self.width() >> shift_w, self.height() >> shift_h)
    }

    /// Bytes of `level`.
    pub fn mip_len(&self, level: u32) -> u64 {
        let (w, h) = self.mip_extent(level);
        self.format.mip_bytes(w, h)
    }

    /// Absolute byte offset of `level` in `textures.pack`, derived from the base offset.
    pub fn mip_offset(&self, level: u32) -> u64 {
        self.offset() + (0..level).map(|l| self.mip_len(l)).sum::<u64>()
    }

    /// Bytes of the whole stored chain.
    pub fn chain_len(&self) -> u64 {
        (0..self.mip_count()).map(|l| self.mip_len(l)).sum()
    }

    pub(crate) fn encode(&self) -> [u8; TEXTURE_RECORD_BYTES] {
        let o = self.offset().to_le_bytes();
        [
            o[0],
            o[1],
            o[2],
            o[3],
            o[4],
            o[5],
            self.width_log2 | (self.height_log2 << 4),
            self.mip_count,
            self.format.code(),
            0,
        ]
    }

    pub(crate) fn decode(record: &[u8; TEXTURE_RECORD_BYTES]) -> Result<Self, String> {
        let offset = u64::from_le_bytes([record[0], record[1], record[2], record[3], record[4], record[5], 0, 0]);
        let format =
            TextureFormat::from_code(record[8]).ok_or_else(|| format!("unknown texture format code {}", record[8]))?;
        if record[9] != 0 {
            return Err(format!("reserved flags byte is {} (expected 0)", record[9]));
        }
        Self::new(format, record[6] & 0xf, record[6] >> 4, record[7], offset)
    }
}

/// Number of levels of a full mip chain for an extent of `2^width_log2 × 2^height_log2`.
pub fn full_mip_count(width_log2: u8, height_log2: u8) -> u8 {
    width_log2.max(height_log2) + 1
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mip_bytes_saturates_instead_of_overflowing() {
        // A damaged DDS header once reached this with u32::MAX sides (found by fuzzing).
        for format in TextureFormat::ALL {
            assert!(format.mip_bytes(u32::MAX, u32::MAX) >= 1 << 63, "{format:?}");
        }
        assert_eq!(TextureFormat::Bc1.mip_bytes(2, 2), 8);
        assert_eq!(TextureFormat::Bc7.mip_bytes(8, 4), 32);
        assert_eq!(TextureFormat::Rgba8.mip_bytes(16384, 16384), 1 << 30);
    }
}
