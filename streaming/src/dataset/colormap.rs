//! `colormap.bin`: the City Colormap (paper §3.7), one mean RGBA8 colour per texture.

use std::path::Path;

use super::error::DatasetError;
use super::io_util::{decode_table, encode_table, read_all, write_all};

const MAGIC: &[u8; 8] = b"CSCOLMAP";

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
        let bytes = read_all(path)?;
        let (_, body) = decode_table(path, &bytes, MAGIC, 4)?;
        Ok(Self {
            colours: body.chunks_exact(4).map(|c| [c[0], c[1], c[2], c[3]]).collect(),
        })
    }

    /// Writes `colormap.bin`.
    pub fn write(&self, path: &Path) -> Result<(), DatasetError> {
        let body: Vec<u8> = self.colours.iter().flatten().copied().collect();
        write_all(path, &encode_table(MAGIC, self.colours.len() as u64, &body))
    }
}

const CRC_MAGIC: &[u8; 8] = b"CSTXCRC\0";

/// Reads `textures.crc`: the CRC-32 of each texture's whole mip chain, used only by `verify`.
pub(crate) fn read_checksums(path: &Path) -> Result<Vec<u32>, DatasetError> {
    let bytes = read_all(path)?;
    let (_, body) = decode_table(path, &bytes, CRC_MAGIC, 4)?;
    Ok(body
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect())
}

/// Writes `textures.crc`.
pub(crate) fn write_checksums(path: &Path, checksums: &[u32]) -> Result<(), DatasetError> {
    let body: Vec<u8> = checksums.iter().flat_map(|c| c.to_le_bytes()).collect();
    write_all(path, &encode_table(CRC_MAGIC, checksums.len() as u64, &body))
}
