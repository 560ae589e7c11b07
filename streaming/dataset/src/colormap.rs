//! `colormap.bin`: the City Colormap (paper §3.7), one mean RGBA8 colour per texture.

use std::path::Path;

use super::error::DatasetError;
use super::format::FORMAT_VERSION;
use super::io_util::{decode_table, encode_table, read_all, write_new_durably};

pub(crate) const MAGIC: &[u8; 8] = b"CSCOLMAP";

/// Mean colour of every texture, indexed by texture id. The renderer keeps it resident and
/// blends it with sampled texels by displayed mip level (paper Eq. 8).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Colormap {
    colours: Vec<[u8; 4]>,
}

impl Colormap {
    /// Wraps per-texture colours.
    pub fn new(colours: Vec<[u8; 4]>) -> Self {
        Self { colours }
    }

    /// All colours (sRGB-encoded RGBA8), indexed by texture id; ready to upload as one buffer.
    pub fn colours(&self) -> &[[u8; 4]] {
        &self.colours
    }

    /// Colour of one texture.
    pub fn get(&self, texture: u32) -> Option<[u8; 4]> {
        self.colours.get(texture as usize).copied()
    }

    /// Number of entries.
    pub fn len(&self) -> usize {
        self.colours.len()
    }

    /// Whether there are no entries.
    pub fn is_empty(&self) -> bool {
        self.colours.is_empty()
    }

    /// Reads `colormap.bin`.
    pub fn read(path: &Path) -> Result<Self, DatasetError> {
        Ok(Self::read_with_write_id(path)?.0)
    }

    /// Reads `colormap.bin` and returns the write id in its header.
    pub(crate) fn read_with_write_id(path: &Path) -> Result<(Self, u64), DatasetError> {
        Self::decode_with_write_id(path, &read_all(path)?, FORMAT_VERSION)
    }

    /// Decodes `colormap.bin` bytes of format `version`; `path` names them in errors.
    pub(crate) fn decode_with_write_id(path: &Path, bytes: &[u8], version: u32) -> Result<(Self, u64), DatasetError> {
        let table = decode_table(path, bytes, MAGIC, 4, version)?;
        Ok((Self::from_records(table.body), table.write_id))
    }

    /// Colours from the table's records, 4 bytes each.
    pub(crate) fn from_records(body: &[u8]) -> Self {
        Self {
            colours: body.chunks_exact(4).map(|c| [c[0], c[1], c[2], c[3]]).collect(),
        }
    }

    /// Writes `colormap.bin` of write `write_id` (a new file, flushed to disk).
    pub(crate) fn write_new(&self, path: &Path, write_id: u64) -> Result<u64, DatasetError> {
        let body: Vec<u8> = self.colours.iter().flatten().copied().collect();
        let bytes = encode_table(MAGIC, write_id, self.colours.len() as u64, &body);
        write_new_durably(path, &bytes)?;
        Ok(bytes.len() as u64)
    }
}

pub(crate) const CRC_MAGIC: &[u8; 8] = b"CSTXCRC\0";

/// Decodes `textures.crc` (`path` names it in errors): the CRC-32 of every mip, textures in
/// id order, levels finest first. Returns them and the write id.
pub(crate) fn decode_checksums(path: &Path, bytes: &[u8], version: u32) -> Result<(Vec<u32>, u64), DatasetError> {
    let table = decode_table(path, bytes, CRC_MAGIC, 4, version)?;
    Ok((u32_records(table.body), table.write_id))
}

/// Little-endian u32 records.
pub(crate) fn u32_records(body: &[u8]) -> Vec<u32> {
    body.chunks_exact(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// Writes `textures.crc` of write `write_id` (a new file, flushed to disk).
pub(crate) fn write_checksums(path: &Path, write_id: u64, checksums: &[u32]) -> Result<u64, DatasetError> {
    let body: Vec<u8> = checksums.iter().flat_map(|c| c.to_le_bytes()).collect();
    let bytes = encode_table(CRC_MAGIC, write_id, checksums.len() as u64, &body);
    write_new_durably(path, &bytes)?;
    Ok(bytes.len() as u64)
}
