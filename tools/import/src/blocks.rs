//! KTX2 and DDS sources stored as BC1, BC3 or BC7 blocks, read so an import can keep their
//! blocks and levels as they are.

use anyhow::{anyhow, bail, Context, Result};
use citystream_dataset::TextureFormat;

/// A KTX2 or DDS source stored as BC1, BC3 or BC7 blocks.
#[derive(Debug)]
pub struct BlockSource {
    pub(crate) format: TextureFormat,
    pub(crate) width: u32,
    pub(crate) height: u32,
    /// The stored levels, finest first, each exactly its `mip_bytes` long.
    pub(crate) levels: Vec<Vec<u8>>,
}

/// The blocks of a KTX2 or DDS file, or `None` when it holds something else (RGBA8, BC2,
/// a non-power-of-two extent ...). Errors for files that claim BC data but are damaged.
pub fn block_source(bytes: &[u8]) -> Result<Option<BlockSource>> {
    let (format, width, height, levels) = if bytes.starts_with(&[0xAB, 0x4B, 0x54, 0x58, 0x20, 0x32, 0x30, 0xBB]) {
        use ktx2::Format;
        let reader = ktx2::Reader::new(bytes).map_err(|e| anyhow!("invalid KTX2: {e:?}"))?;
        let header = reader.header();
        let format = match header.format {
            Some(
                Format::BC1_RGB_UNORM_BLOCK
                | Format::BC1_RGB_SRGB_BLOCK
                | Format::BC1_RGBA_UNORM_BLOCK
                | Format::BC1_RGBA_SRGB_BLOCK,
            ) => TextureFormat::Bc1,
            Some(Format::BC3_UNORM_BLOCK | Format::BC3_SRGB_BLOCK) => TextureFormat::Bc3,
            Some(Format::BC7_UNORM_BLOCK | Format::BC7_SRGB_BLOCK) => TextureFormat::Bc7,
            _ => return Ok(None),
        };
        let (width, height) = (header.pixel_width, header.pixel_height);
        if header.supercompression_scheme.is_some()
            || header.layer_count > 1
            || header.face_count > 1
            || !keepable_side(width)
            || !keepable_side(height)
        {
            return Ok(None);
        }
        // A level index may list any number of (overlapping) levels: copy a full chain at most.
        let full_chain = width.max(height).trailing_zeros() as usize + 1;
        let levels: Vec<Vec<u8>> = reader
            .levels()
            .take(full_chain)
            .map(|level| level.data.to_vec())
            .collect();
        (format, width, height, levels)
    } else if bytes.starts_with(b"DDS ") {
        match dds_blocks(bytes)? {
            Some(found) => found,
            None => return Ok(None),
        }
    } else {
        return Ok(None);
    };
    // Both readers have checked the sides (`keepable_side`).
    if levels.is_empty() {
        return Ok(None);
    }
    let full_chain = width.max(height).trailing_zeros() as usize + 1;
    let mut kept = Vec::new();
    for (l, data) in levels.iter().take(full_chain).enumerate() {
        let (w, h) = ((width >> l).max(1), (height >> l).max(1));
        let len = format.mip_bytes(w, h) as usize;
        let level = data
            .get(..len)
            .with_context(|| format!("level {l} ({w}x{h}) holds {} of its {len} bytes", data.len()))?;
        kept.push(level.to_vec());
    }
    Ok(Some(BlockSource {
        format,
        width,
        height,
        levels: kept,
    }))
}

/// Whether blocks of a texture with this side can be kept: a power of two, at least one
/// 4-texel block, at most the largest texture side.
fn keepable_side(side: u32) -> bool {
    side.is_power_of_two() && (4..=citystream_gen::library::MAX_IMAGE_SIDE).contains(&side)
}

type DdsLevels = (TextureFormat, u32, u32, Vec<Vec<u8>>);

/// The BC1/BC3/BC7 levels of a DDS file (FourCC `DXT1`/`DXT5`, or `DX10` with a BC1, BC3 or
/// BC7 DXGI format), or `None` for other pixel formats.
fn dds_blocks(bytes: &[u8]) -> Result<Option<DdsLevels>> {
    let u32_at = |at: usize| -> Result<u32> {
        bytes
            .get(at..at + 4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .with_context(|| format!("DDS header ends before byte {}", at + 4))
    };
    if u32_at(4)? != 124 {
        bail!("DDS header size is {}, not 124", u32_at(4)?);
    }
    let (height, width) = (u32_at(12)?, u32_at(16)?);
    if !keepable_side(width) || !keepable_side(height) {
        // Not keepable as blocks; the decoder reports what is wrong with it.
        return Ok(None);
    }
    const DDSD_MIPMAPCOUNT: u32 = 0x2_0000;
    let levels = if u32_at(8)? & DDSD_MIPMAPCOUNT != 0 {
        u32_at(28)?.max(1)
    } else {
        1
    };
    let four_cc = bytes.get(84..88).context("DDS header ends before its FourCC")?;
    let (format, mut offset): (TextureFormat, usize) = match four_cc {
        b"DXT1" => (TextureFormat::Bc1, 128),
        b"DXT5" => (TextureFormat::Bc3, 128),
        b"DX10" => {
            let format = match u32_at(128)? {
                71 | 72 => TextureFormat::Bc1,
                77 | 78 => TextureFormat::Bc3,
                98 | 99 => TextureFormat::Bc7,
                _ => return Ok(None),
            };
            // A plain 2D texture: dimension TEXTURE2D (3), one array element.
            if u32_at(132)? != 3 || u32_at(140)? > 1 {
                return Ok(None);
            }
            (format, 148)
        }
        _ => return Ok(None),
    };
    let mut found = Vec::new();
    for l in 0..levels.min(15) {
        let (w, h) = ((width >> l).max(1), (height >> l).max(1));
        let len = usize::try_from(format.mip_bytes(w, h)).unwrap_or(usize::MAX);
        let Some(level) = offset.checked_add(len).and_then(|end| bytes.get(offset..end)) else {
            bail!(
                "DDS level {l} ({w}x{h}) needs {len} bytes from byte {offset}, past the file's {}",
                bytes.len()
            );
        };
        found.push(level.to_vec());
        offset += len;
    }
    Ok(Some((format, width, height, found)))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A KTX2 file of a 4x4 BC1 texture whose level index lists `entries` levels, every one
    /// pointing at the same 8-byte block.
    fn ktx2_with_level_entries(entries: usize) -> Vec<u8> {
        let mut f = vec![0xAB, 0x4B, 0x54, 0x58, 0x20, 0x32, 0x30, 0xBB, 0x0D, 0x0A, 0x1A, 0x0A];
        for v in [131u32, 1, 4, 4, 0, 0, 1, entries as u32, 0] {
            f.extend_from_slice(&v.to_le_bytes());
        }
        let dfd_offset = 80 + 24 * entries;
        for v in [dfd_offset as u32, 4, 0, 0] {
            f.extend_from_slice(&v.to_le_bytes());
        }
        f.extend_from_slice(&[0u8; 16]);
        let data_offset = (dfd_offset + 4) as u64;
        for _ in 0..entries {
            for v in [data_offset, 8, 8] {
                f.extend_from_slice(&v.to_le_bytes());
            }
        }
        f.extend_from_slice(&4u32.to_le_bytes());
        f.extend_from_slice(&[0x55; 8]);
        f
    }

    #[test]
    fn a_level_index_longer_than_the_chain_is_not_copied_whole() {
        // 100,000 entries (2.4 MB of index): at most the full chain (3 levels of 4x4) is kept.
        let source = block_source(&ktx2_with_level_entries(100_000))
            .expect("readable")
            .expect("BC1 blocks");
        assert_eq!((source.format, source.width, source.height), (TextureFormat::Bc1, 4, 4));
        assert_eq!(source.levels.len(), 3);
        assert!(source.levels.iter().all(|l| l == &[0x55; 8]));
    }
}
