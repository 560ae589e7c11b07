//! Format version 1 (read only here) and `citystream upgrade`, which rewrites a version-1,
//! 2 or 3 dataset as the current version.
//!
//! Version 1 kept its five files at the top of the dataset directory, with no manifest and no
//! write id; its table headers were 32 bytes (count at 16, CRC-32 of the body at 24), the
//! pack header had the count at 16 and the length at 24, the scene header was 96 bytes with
//! a CRC of the body only, and `textures.crc` held one CRC per mip chain.

use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::Path;

use super::colormap::{self, u32_records, Colormap};
use super::crs::Crs;
use super::dataset::Dataset;
use super::error::DatasetError;
use super::files::{DatasetFiles, CHECKSUM_FILE, COLORMAP_FILE, META_FILE, PACK_FILE, SCENE_FILE};
use super::format::{TextureInfo, FORMAT_VERSION, TEXTURE_RECORD_BYTES};
use super::io_util::{
    check_versioned_prefix, read_all, table_body, u32_at, u64_at, upgradable_manifest, LEGACY_VERSION,
};
use super::pack::{open_pack, META_MAGIC, PACK_HEADER_BYTES, PACK_MAGIC};
use super::scene::{Scene, SceneLayout};
use super::writer::{DatasetWriter, WriteSummary};

const LEGACY_TABLE_HEADER_BYTES: usize = 32;

/// What [`upgrade`] did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct UpgradeSummary {
    /// The version the dataset had.
    pub from_version: u32,
    /// The new write, or `None` when the dataset already had the current version (and the
    /// CRS asked for, if any).
    pub written: Option<WriteSummary>,
    /// Version-1 files an interrupted upgrade left beside the current write, removed.
    pub leftovers_removed: usize,
}

impl UpgradeSummary {
    fn nothing_to_do(leftovers_removed: usize) -> Self {
        Self {
            from_version: FORMAT_VERSION,
            written: None,
            leftovers_removed,
        }
    }
}

/// Under the writer's lock, removes what an upgrade that died after its commit left: the
/// version-1 files beside the current manifest (and, as every writer does, stale writes).
fn finish_interrupted_upgrade(dir: &Path) -> Result<usize, DatasetError> {
    if !crate::files::has_legacy_files(dir) {
        return Ok(0);
    }
    let writer = DatasetWriter::create_waiting(dir)?;
    let removed = crate::files::remove_legacy_files(dir)?;
    drop(writer);
    Ok(removed)
}

/// Rewrites the dataset in `dir` as the current version, atomically (through
/// [`DatasetWriter`]), giving it `crs` (`None`: the CRS it has, if any). A version-1 dataset has every mip
/// chain checked against its version-1 CRC before it is copied, a version-2 one every mip
/// against its CRC; older files are removed only once the new dataset is in place.
///
/// A dataset of the current version is left as it is, unless `crs` is given and the dataset
/// has none: then it is rewritten with it. One already in another CRS is refused
/// ([`DatasetError::InvalidInput`]): a new CRS means new coordinates, which this does not
/// compute.
pub fn upgrade(dir: &Path, crs: Option<&Crs>) -> Result<UpgradeSummary, DatasetError> {
    if current_needs_nothing(dir, crs)? {
        return Ok(UpgradeSummary::nothing_to_do(finish_interrupted_upgrade(dir)?));
    }
    // Waits for a concurrent upgrade (two runs finding the same old city), then finds the
    // dataset already in the current version and leaves it.
    let mut writer = DatasetWriter::create_waiting(dir)?;
    if current_needs_nothing(dir, crs)? {
        drop(writer);
        return Ok(UpgradeSummary::nothing_to_do(finish_interrupted_upgrade(dir)?));
    }
    let files = match DatasetFiles::resolve(dir) {
        Ok(files) => Some(files),
        Err(DatasetError::NeedsUpgrade { found, .. }) if upgradable_manifest(found) => {
            Some(DatasetFiles::resolve_version(dir, found)?)
        }
        Err(DatasetError::NeedsUpgrade { .. }) => None,
        Err(e) => return Err(e),
    };
    let Some(files) = files else {
        return upgrade_legacy(dir, writer, crs);
    };
    let dataset = Dataset::open_files(&files)?;
    let mut chain = Vec::new();
    let mut level = Vec::new();
    for (id, info) in dataset.textures.textures().iter().enumerate() {
        chain.clear();
        for l in 0..info.mip_count() {
            dataset.textures.read_mip(id as u32, l, &mut level)?;
            chain.extend_from_slice(&level);
        }
        copy_texture(&mut writer, info, &chain, dataset.colormap.colours()[id])?;
    }
    let mut scene = dataset.scene;
    match (&scene.crs, crs) {
        (Some(have), Some(wanted)) if !have.same_as(wanted) => return Err(other_crs(dir, have, wanted)),
        (_, Some(wanted)) => scene.crs = Some(wanted.clone()),
        // A version-3 dataset keeps its CRS; a version-2 one had none.
        (_, None) => {}
    }
    let written = writer.finish(&scene)?;
    Ok(UpgradeSummary {
        from_version: files.version(),
        written: Some(written),
        leftovers_removed: 0,
    })
}

/// Writes a texture of an older dataset, its whole mip chain in `chain`, unchanged.
fn copy_texture(
    writer: &mut DatasetWriter,
    info: &TextureInfo,
    chain: &[u8],
    colour: [u8; 4],
) -> Result<u32, DatasetError> {
    writer.add_texture(
        info.format(),
        info.width(),
        info.height(),
        info.mip_count(),
        chain,
        colour,
    )
}

/// Whether `dir` holds a dataset of this version that already has `crs` (or any CRS or none,
/// when `crs` is `None`). Fails when it has another CRS.
fn current_needs_nothing(dir: &Path, crs: Option<&Crs>) -> Result<bool, DatasetError> {
    match DatasetFiles::resolve(dir) {
        Ok(files) => {
            let Some(wanted) = crs else { return Ok(true) };
            match Dataset::open_files(&files)?.scene.crs {
                None => Ok(false),
                Some(have) if have.same_as(wanted) => Ok(true),
                Some(have) => Err(other_crs(dir, &have, wanted)),
            }
        }
        Err(DatasetError::NeedsUpgrade { .. }) => Ok(false),
        Err(e) => Err(e),
    }
}

/// The refusal to give the dataset in `dir`, in CRS `have`, another CRS `wanted`.
fn other_crs(dir: &Path, have: &Crs, wanted: &Crs) -> DatasetError {
    DatasetError::InvalidInput(format!(
        "{}: the dataset is already in CRS {have}; giving it {wanted} would need its coordinates transformed, which citystream does not do",
        dir.display()
    ))
}

/// The version-1 half of [`upgrade`].
fn upgrade_legacy(dir: &Path, mut writer: DatasetWriter, crs: Option<&Crs>) -> Result<UpgradeSummary, DatasetError> {
    let mut legacy = LegacyDataset::open(dir)?;
    let mut chain = Vec::new();
    for (id, info) in legacy.textures.iter().enumerate() {
        let len = usize::try_from(info.chain_len())
            .map_err(|_| DatasetError::InvalidInput(format!("texture {id}: mip chain larger than memory")))?;
        chain.resize(len, 0);
        legacy.read_chain(id as u32, info, &mut chain)?;
        copy_texture(&mut writer, info, &chain, legacy.colours.colours()[id])?;
    }
    legacy.scene.crs = crs.cloned();
    let written = writer.finish(&legacy.scene)?;
    Ok(UpgradeSummary {
        from_version: LEGACY_VERSION,
        written: Some(written),
        leftovers_removed: 0,
    })
}

/// A version-1 dataset, opened with the checks version 1 allowed.
struct LegacyDataset {
    scene: Scene,
    textures: Vec<TextureInfo>,
    colours: Colormap,
    chain_checksums: Vec<u32>,
    pack: File,
    pack_len: u64,
    pack_path: std::path::PathBuf,
}

impl LegacyDataset {
    fn open(dir: &Path) -> Result<Self, DatasetError> {
        let meta_path = dir.join(META_FILE);
        let meta = read_all(&meta_path)?;
        let (count, body) = legacy_table(&meta_path, &meta, META_MAGIC, TEXTURE_RECORD_BYTES)?;
        let mut textures = Vec::with_capacity(body.len() / TEXTURE_RECORD_BYTES);
        for (index, chunk) in body.chunks_exact(TEXTURE_RECORD_BYTES).enumerate() {
            let mut record = [0u8; TEXTURE_RECORD_BYTES];
            record.copy_from_slice(chunk);
            textures.push(TextureInfo::decode(&record).map_err(|what| DatasetError::Corrupt {
                path: meta_path.clone(),
                offset: (LEGACY_TABLE_HEADER_BYTES + index * TEXTURE_RECORD_BYTES) as u64,
                what: format!("texture {index}: {what}"),
            })?);
        }

        let pack_path = dir.join(PACK_FILE);
        let (pack, pack_len, header) = open_pack(&pack_path)?;
        check_versioned_prefix(&pack_path, &header, PACK_MAGIC, header.len(), LEGACY_VERSION)?;
        if u64_at(&header, 16) != count || u64_at(&header, 24) != pack_len {
            return Err(DatasetError::Corrupt {
                path: pack_path,
                offset: 16,
                what: format!(
                    "header lists {} textures and {} bytes; {META_FILE} lists {count} textures, the file has {pack_len} bytes",
                    u64_at(&header, 16),
                    u64_at(&header, 24)
                ),
            });
        }

        let colormap_path = dir.join(COLORMAP_FILE);
        let colours_bytes = read_all(&colormap_path)?;
        let (colour_count, colour_body) = legacy_table(&colormap_path, &colours_bytes, colormap::MAGIC, 4)?;
        let checksum_path = dir.join(CHECKSUM_FILE);
        let checksum_bytes = read_all(&checksum_path)?;
        let (checksum_count, checksum_body) = legacy_table(&checksum_path, &checksum_bytes, colormap::CRC_MAGIC, 4)?;
        for (path, found) in [(&colormap_path, colour_count), (&checksum_path, checksum_count)] {
            if found != count {
                return Err(DatasetError::Corrupt {
                    path: path.clone(),
                    offset: 16,
                    what: format!("{found} records for {count} textures"),
                });
            }
        }

        let scene_path = dir.join(SCENE_FILE);
        let (scene, _) = Scene::read_with_write_id(&scene_path, SceneLayout::LEGACY)?;
        if let Some((m, mesh)) = scene
            .meshes
            .iter()
            .enumerate()
            .find(|(_, m)| u64::from(m.texture) >= count)
        {
            return Err(DatasetError::Corrupt {
                path: scene_path,
                offset: SceneLayout::LEGACY.header_len as u64 + m as u64 * 44 + 16,
                what: format!(
                    "mesh {m} uses texture {}, but the dataset has {count} textures",
                    mesh.texture
                ),
            });
        }
        Ok(Self {
            scene,
            textures,
            colours: Colormap::from_records(colour_body),
            chain_checksums: u32_records(checksum_body),
            pack,
            pack_len,
            pack_path,
        })
    }

    /// Reads texture `id`'s whole chain into `dst` and checks its version-1 CRC.
    fn read_chain(&self, id: u32, info: &TextureInfo, dst: &mut [u8]) -> Result<(), DatasetError> {
        let (offset, end) = (info.offset(), info.offset() + info.chain_len());
        if offset < PACK_HEADER_BYTES || end > self.pack_len {
            return Err(DatasetError::truncated(
                &self.pack_path,
                format!("texture {id}'s mip chain"),
                offset,
                end,
                self.pack_len,
            ));
        }
        self.pack
            .read_exact_at(dst, offset)
            .map_err(|e| DatasetError::io(&self.pack_path, e))?;
        let stored = self.chain_checksums[id as usize];
        let computed = crc32fast::hash(dst);
        if stored != computed {
            return Err(DatasetError::Checksum {
                path: self.pack_path.clone(),
                what: format!("texture {id}'s mip chain"),
                offset,
                end,
                stored,
                computed,
            });
        }
        Ok(())
    }
}

/// A version-1 table: header, exact size, CRC-32 of the body. Returns `(count, body)`.
fn legacy_table<'a>(
    path: &Path,
    bytes: &'a [u8],
    magic: &[u8; 8],
    record_len: usize,
) -> Result<(u64, &'a [u8]), DatasetError> {
    check_versioned_prefix(path, bytes, magic, LEGACY_TABLE_HEADER_BYTES, LEGACY_VERSION)?;
    let count = u64_at(bytes, 16);
    let body = table_body(path, bytes, count, record_len, LEGACY_TABLE_HEADER_BYTES)?;
    let stored = u32_at(bytes, 24);
    let computed = crc32fast::hash(body);
    if stored != computed {
        return Err(DatasetError::Checksum {
            path: path.to_path_buf(),
            what: "the record table".into(),
            offset: LEGACY_TABLE_HEADER_BYTES as u64,
            end: bytes.len() as u64,
            stored,
            computed,
        });
    }
    Ok((count, body))
}
