//! Full consistency check of a dataset directory (`citystream verify`).

use std::path::Path;

use super::colormap::read_checksums;
use super::error::DatasetError;
use super::{Dataset, CHECKSUM_FILE, META_FILE};

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

/// Opens the dataset in `dir` (which validates headers, sizes, table checksums, every
/// texture record and offset, and every mesh, index and vertex), then checks that no two
/// mip chains overlap, reads every mip of every texture with one positioned read and
/// compares each chain's CRC-32 with `textures.crc`. Returns the first problem found.
pub fn verify(dir: &Path) -> Result<VerifyReport, DatasetError> {
    let dataset = Dataset::open(dir)?;
    let pack = &dataset.textures;
    let checksum_path = dir.join(CHECKSUM_FILE);
    let checksums = read_checksums(&checksum_path)?;
    if checksums.len() != pack.textures().len() {
        return Err(DatasetError::Corrupt {
            path: checksum_path,
            offset: 16,
            what: format!("{} checksums for {} textures", checksums.len(), pack.len()),
        });
    }

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
                path: dir.join(META_FILE),
                offset: 32 + u64::from(b) * 10,
                what: format!(
                    "texture {b} starts at pack offset {start_b}, inside texture {a} (which ends at {end_a})"
                ),
            });
        }
    }

    let mut buf = Vec::new();
    let mut mips = 0u64;
    let mut bytes_read = 0u64;
    for (id, info) in pack.textures().iter().enumerate() {
        let id = id as u32;
        let mut hasher = crc32fast::Hasher::new();
        for level in 0..info.mip_count() {
            pack.read_mip(id, level, &mut buf)?;
            hasher.update(&buf);
            mips += 1;
            bytes_read += buf.len() as u64;
        }
        let computed = hasher.finalize();
        let stored = checksums[id as usize];
        if computed != stored {
            return Err(DatasetError::Checksum {
                path: pack.pack_path().to_path_buf(),
                what: format!(
                    "texture {id} ({}x{} {}, {} mips)",
                    info.width(),
                    info.height(),
                    info.format().name(),
                    info.mip_count()
                ),
                offset: info.offset(),
                end: info.offset() + info.chain_len(),
                stored,
                computed,
            });
        }
    }
    Ok(VerifyReport {
        textures: pack.len(),
        mips,
        bytes_read,
        meshes: dataset.scene.meshes.len() as u32,
    })
}
