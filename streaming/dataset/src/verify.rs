//! Full consistency check of a dataset directory (`citystream verify`).

use std::path::Path;

use super::dataset::Dataset;
use super::error::DatasetError;
use super::files::META_FILE;
use super::io_util::TABLE_HEADER_BYTES;

/// What [`verify`] checked.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct VerifyReport {
    /// Textures whose every mip was read and checksummed.
    pub textures: u32,
    /// Mips read (one positioned read each, as the loader does).
    pub mips: u64,
    /// Bytes of mip data read.
    pub bytes_read: u64,
    /// Meshes validated.
    pub meshes: u32,
}

/// Opens the dataset in `dir` (which validates the manifest, headers, sizes, checksums of
/// the tables and the scene, write ids, every texture record and offset, and every mesh,
/// index and vertex), then checks that no two mip chains overlap and reads every mip of every
/// texture with one positioned read, checking each against its stored CRC-32. Returns the
/// first problem found.
pub fn verify(dir: &Path) -> Result<VerifyReport, DatasetError> {
    verify_dataset(&Dataset::open(dir)?)
}

/// [`verify`] of an opened dataset (local or remote): the overlap check and every mip read
/// and checksummed.
pub fn verify_dataset(dataset: &Dataset) -> Result<VerifyReport, DatasetError> {
    let pack = &dataset.textures;
    let mut by_offset: Vec<(u64, u64, u32)> = pack
        .textures()
        .iter()
        .enumerate()
        .map(|(id, t)| (t.offset(), t.offset() + t.chain_len(), id as u32))
        .collect();
    by_offset.sort_unstable();
    for pair in by_offset.windows(2) {
        let ((_, end_a, a), (start_b, _, b)) = (pair[0], pair[1]);
        if start_b < end_a {
            return Err(DatasetError::Corrupt {
                path: dataset.files().path(META_FILE),
                offset: TABLE_HEADER_BYTES as u64 + u64::from(b) * 10,
                what: format!(
                    "texture {b} starts at pack offset {start_b}, inside texture {a} (which ends at {end_a})"
                ),
            });
        }
    }

    // Every mip in read order: a remote store fetches ahead (as much as it holds, the rest
    // as reads make room) instead of one request at a time; a local pack ignores it.
    let order: Vec<(u32, u32)> = pack
        .textures()
        .iter()
        .enumerate()
        .flat_map(|(id, info)| (0..info.mip_count()).map(move |level| (id as u32, level)))
        .collect();
    pack.prefetch(&order);
    let mut buf = Vec::new();
    let mut mips = 0u64;
    let mut bytes_read = 0u64;
    for (id, info) in pack.textures().iter().enumerate() {
        for level in 0..info.mip_count() {
            pack.read_mip(id as u32, level, &mut buf)?;
            mips += 1;
            bytes_read += buf.len() as u64;
        }
    }
    Ok(VerifyReport {
        textures: pack.len(),
        mips,
        bytes_read,
        meshes: dataset.scene.meshes.len() as u32,
    })
}
