//! Where a dataset's files live, and how a write replaces them in one atomic step.
//!
//! A dataset directory holds a 32-byte manifest, `dataset.manifest`, and one subdirectory per
//! write, `write-<id>/`, with the five data files. The manifest names the current write. A
//! writer builds its files in a fresh subdirectory, flushes them to disk, then renames a new
//! manifest over the old one; only after that rename does the new dataset exist. Readers
//! therefore see the old or the new dataset, never a mix, and a writer that dies leaves the
//! old one untouched (its subdirectory is removed by the next writer). Writers exclude each
//! other with `flock` on the directory itself, which the kernel releases when a writer dies.
//!
//! Nothing else in the directory is touched: a writer only creates its own subdirectory and
//! the manifest, removes only `write-<id>` subdirectories and its temporary manifests, and
//! deletes version-1 files at the top level only when their header proves them ours.

use std::fs::{File, TryLockError};
use std::path::{Path, PathBuf};

use super::error::DatasetError;
use super::format::FORMAT_VERSION;
use super::io_util::{
    check_prefix, expect_end, header_prefix, read_all, u32_at, upgradable_manifest, write_new_durably, LEGACY_VERSION,
};
use super::store::DatasetStore;

/// The manifest file at the top of a dataset directory.
pub const MANIFEST_FILE: &str = "dataset.manifest";
/// Scene file of format versions 1 to 3 (read by the upgrade only).
pub const SCENE_FILE: &str = "scene.bin";
/// The tile tree (format 4 on).
pub const TILES_FILE: &str = "tiles.bin";
/// Each tile's geometry (format 4 on).
pub const GEOMETRY_PACK_FILE: &str = "geometry.pack";
/// The CRC-32 of each tile's geometry (format 4 on).
pub const GEOMETRY_CRC_FILE: &str = "geometry.crc";
/// Texture metadata file name.
pub const META_FILE: &str = "textures.meta";
/// Texture pack file name.
pub const PACK_FILE: &str = "textures.pack";
/// City Colormap file name.
pub const COLORMAP_FILE: &str = "colormap.bin";
/// Per-mip checksum file name.
pub const CHECKSUM_FILE: &str = "textures.crc";
/// Every file of the format: the seven data files of a write, then the manifest.
pub const DATASET_FILES: [&str; 8] = [
    TILES_FILE,
    GEOMETRY_PACK_FILE,
    GEOMETRY_CRC_FILE,
    META_FILE,
    PACK_FILE,
    COLORMAP_FILE,
    CHECKSUM_FILE,
    MANIFEST_FILE,
];
const MANIFEST_MAGIC: &[u8; 8] = b"CSMANIFS";
const MANIFEST_BYTES: usize = 32;
const WRITE_DIR_PREFIX: &str = "write-";
const TEMP_MANIFEST_PREFIX: &str = ".dataset.manifest.";

/// Magic bytes of the version-1 files, which sat at the top of the dataset directory.
const LEGACY_FILES: [(&str, &[u8; 8]); 5] = [
    (SCENE_FILE, b"CSSCENE\0"),
    (META_FILE, b"CSTXMETA"),
    (PACK_FILE, b"CSTXPACK"),
    (COLORMAP_FILE, b"CSCOLMAP"),
    (CHECKSUM_FILE, b"CSTXCRC\0"),
];

/// The files of the dataset a directory's manifest names.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DatasetFiles {
    dir: PathBuf,
    data_dir: PathBuf,
    write_id: u64,
    /// The format version every file must have: this build's, or the previous one's for
    /// the upgrade.
    version: u32,
}

impl DatasetFiles {
    /// Reads the manifest of the dataset in `dir`. A version-1 dataset (files at the top,
    /// no manifest) is reported as [`DatasetError::NeedsUpgrade`].
    pub fn resolve(dir: &Path) -> Result<Self, DatasetError> {
        Self::resolve_version(dir, FORMAT_VERSION)
    }

    /// [`DatasetFiles::resolve`] of a dataset of format `version` (the upgrade reads the
    /// previous version with this).
    pub(crate) fn resolve_version(dir: &Path, version: u32) -> Result<Self, DatasetError> {
        let manifest_path = dir.join(MANIFEST_FILE);
        let write_id = match read_all(&manifest_path) {
            Ok(bytes) => decode_manifest(&manifest_path, &bytes, version)?,
            Err(DatasetError::Missing { .. }) if legacy_file(&dir.join(SCENE_FILE), b"CSSCENE\0") => {
                return Err(DatasetError::NeedsUpgrade {
                    path: dir.to_path_buf(),
                    found: LEGACY_VERSION,
                });
            }
            Err(e) => return Err(e),
        };
        Ok(Self {
            dir: dir.to_path_buf(),
            data_dir: dir.join(write_dir_name(write_id)),
            write_id,
            version,
        })
    }

    /// Reads the manifest of the dataset at `root` of `store` (a remote dataset).
    pub fn resolve_in(store: &dyn DatasetStore, root: &Path) -> Result<Self, DatasetError> {
        let manifest_path = root.join(MANIFEST_FILE);
        // Exactly the manifest's bytes are asked for, so a store that answers with more
        // (a server sending gigabytes for a 32-byte file) is refused, not buffered.
        let len = store.len(&manifest_path)?;
        if len != MANIFEST_BYTES as u64 {
            return Err(DatasetError::InvalidInput(format!(
                "{}: {len} bytes, a manifest is {MANIFEST_BYTES}",
                manifest_path.display()
            )));
        }
        let mut bytes = [0; MANIFEST_BYTES];
        store.read_at(&manifest_path, 0, &mut bytes)?;
        let write_id = decode_manifest(&manifest_path, &bytes, FORMAT_VERSION)?;
        Ok(Self {
            dir: root.to_path_buf(),
            data_dir: root.join(write_dir_name(write_id)),
            write_id,
            version: FORMAT_VERSION,
        })
    }

    /// The format version of the files.
    pub fn version(&self) -> u32 {
        self.version
    }

    /// The dataset directory (where the manifest is).
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The current write's subdirectory, which holds the data files.
    pub fn data_dir(&self) -> &Path {
        &self.data_dir
    }

    /// The id every file of the current write carries in its header.
    pub fn write_id(&self) -> u64 {
        self.write_id
    }

    /// Path of one data file (`scene.bin`, `textures.pack`, ...) of the current write.
    pub fn path(&self, name: &str) -> PathBuf {
        self.data_dir.join(name)
    }

    /// Fails with [`DatasetError::MixedWrites`] unless `found` is this write's id.
    pub(crate) fn check_write_id(&self, path: &Path, found: u64) -> Result<(), DatasetError> {
        if found == self.write_id {
            Ok(())
        } else {
            Err(DatasetError::MixedWrites {
                path: path.to_path_buf(),
                found,
                expected: self.write_id,
            })
        }
    }
}

/// Name of the subdirectory holding the files of write `write_id`.
pub fn write_dir_name(write_id: u64) -> String {
    format!("{WRITE_DIR_PREFIX}{write_id:016x}")
}

fn parse_write_dir_name(name: &str) -> Option<u64> {
    let hex = name.strip_prefix(WRITE_DIR_PREFIX)?;
    // Exactly what `write_dir_name` makes: a user's `write-+00…` or upper-case name is not ours.
    let ours = hex.len() == 16 && hex.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b));
    ours.then(|| u64::from_str_radix(hex, 16).ok()).flatten()
}

/// The 32-byte manifest naming write `write_id`: what a store written object by object puts
/// last, once the write's files are in place.
pub fn manifest_bytes(write_id: u64) -> Vec<u8> {
    encode_manifest(write_id)
}

/// A fresh write id for a write that does not go through [`super::DatasetWriter`] (one
/// composed in object storage).
pub fn fresh_write_id() -> u64 {
    new_write_id()
}

fn encode_manifest(write_id: u64) -> Vec<u8> {
    let mut out = header_prefix(MANIFEST_MAGIC, write_id);
    out.extend_from_slice(&crc32fast::hash(&out).to_le_bytes());
    out.extend_from_slice(&0u32.to_le_bytes());
    debug_assert_eq!(out.len(), MANIFEST_BYTES);
    out
}

fn decode_manifest(path: &Path, bytes: &[u8], version: u32) -> Result<u64, DatasetError> {
    let write_id = check_prefix(path, bytes, MANIFEST_MAGIC, MANIFEST_BYTES, version)?;
    expect_end(path, bytes, 0, MANIFEST_BYTES as u64, || "the manifest".into())?;
    if u32_at(bytes, 28) != 0 {
        return Err(DatasetError::Corrupt {
            path: path.to_path_buf(),
            offset: 28,
            what: "reserved word is not 0".into(),
        });
    }
    let stored = u32_at(bytes, 24);
    let computed = crc32fast::hash(&bytes[..24]);
    if stored != computed {
        return Err(DatasetError::Checksum {
            path: path.to_path_buf(),
            what: "the manifest".into(),
            offset: 0,
            end: 24,
            stored,
            computed,
        });
    }
    Ok(write_id)
}

/// Whether `path` is a version-1 dataset file with `magic` (so ours to replace).
fn legacy_file(path: &Path, magic: &[u8; 8]) -> bool {
    use std::io::Read;
    let mut header = [0u8; 12];
    super::io_util::ensure_regular_file(path).is_ok()
        && File::open(path).and_then(|mut f| f.read_exact(&mut header)).is_ok()
        && &header[..8] == magic
        && u32_at(&header, 8) == LEGACY_VERSION
}

/// A fresh write id: unique per process, time and call, never 0.
fn new_write_id() -> u64 {
    use std::sync::atomic::{AtomicU64, Ordering};
    static CALLS: AtomicU64 = AtomicU64::new(0);
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64);
    let mut x = nanos ^ (u64::from(std::process::id()) << 32) ^ CALLS.fetch_add(1, Ordering::Relaxed).rotate_left(48);
    // splitmix64 finaliser: spreads the inputs over all bits.
    x = (x ^ (x >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    (x ^ (x >> 31)).max(1)
}

fn sync_dir(dir: &Path) -> Result<(), DatasetError> {
    File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(|e| DatasetError::io(dir, e))
}

/// One write in progress: holds the directory's lock and the new write's subdirectory,
/// which is removed again unless [`PendingWrite::commit`] switches the manifest to it.
#[derive(Debug)]
pub(crate) struct PendingWrite {
    dir: PathBuf,
    data_dir: PathBuf,
    write_id: u64,
    previous: Option<u64>,
    committed: bool,
    /// A resumable write outlives an error or a crash: its subdirectory is kept for the next
    /// writer of the same job to continue (or for any other writer to remove).
    keep_on_drop: bool,
    /// Whether this write continues one an earlier process left.
    resumed: bool,
    // Held for the write's lifetime; the kernel drops the lock with the descriptor.
    _lock: File,
}

/// Whether `text` is a URL (`scheme://…`) rather than a path.
pub fn looks_like_url(text: &str) -> bool {
    text.split_once("://").is_some_and(|(scheme, _)| {
        !scheme.is_empty()
            && scheme
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '+' | '-' | '.'))
    })
}

/// Refuses a write directory given as a URL: a path of `s3://bucket/x` would be the local
/// folder `./s3:/bucket/x`, and nothing would reach the bucket.
fn refuse_url(dir: &Path) -> Result<(), DatasetError> {
    let text = dir.to_string_lossy();
    if looks_like_url(&text) {
        return Err(DatasetError::InvalidInput(format!(
            "{text} is a URL: a dataset is written to a local directory; to build one into S3, \
             write it with --shard I/N (--shard 0/1 for one process) and join the shards there with \
             `citystream merge {text}` (docs/SHARDS.md)"
        )));
    }
    Ok(())
}

impl PendingWrite {
    /// Creates `dir` if needed, takes its write lock (waiting for another writer to finish
    /// when `wait`, else failing with [`DatasetError::Locked`]), removes what earlier writers
    /// that died left behind, and creates the new write's subdirectory.
    pub(crate) fn begin(dir: &Path, wait: bool) -> Result<Self, DatasetError> {
        Self::begin_adopting(dir, wait, &mut |_| false)
    }

    /// [`PendingWrite::begin`] for a resumable write: the first write subdirectory an
    /// earlier writer left that `adopt` accepts becomes this write (kept on drop); every
    /// other one is removed as usual.
    pub(crate) fn begin_resumable(dir: &Path, adopt: &mut dyn FnMut(&Path) -> bool) -> Result<Self, DatasetError> {
        let mut write = Self::begin_adopting(dir, false, adopt)?;
        write.keep_on_drop = true;
        Ok(write)
    }

    fn begin_adopting(dir: &Path, wait: bool, adopt: &mut dyn FnMut(&Path) -> bool) -> Result<Self, DatasetError> {
        refuse_url(dir)?;
        std::fs::create_dir_all(dir).map_err(|e| DatasetError::io(dir, e))?;
        let lock = File::open(dir).map_err(|e| DatasetError::io(dir, e))?;
        if wait {
            lock.lock().map_err(|e| DatasetError::io(dir, e))?;
        } else {
            match lock.try_lock() {
                Ok(()) => {}
                Err(TryLockError::WouldBlock) => return Err(DatasetError::Locked { dir: dir.to_path_buf() }),
                Err(TryLockError::Error(e)) => return Err(DatasetError::io(dir, e)),
            }
        }
        let manifest_path = dir.join(MANIFEST_FILE);
        let previous = match read_all(&manifest_path) {
            // A dataset of the previous version is replaced like one of this version.
            Ok(bytes) => Some(match decode_manifest(&manifest_path, &bytes, FORMAT_VERSION) {
                Err(DatasetError::NeedsUpgrade { found, .. }) if upgradable_manifest(found) => {
                    decode_manifest(&manifest_path, &bytes, found)?
                }
                current => current?,
            }),
            Err(DatasetError::Missing { .. }) => None,
            // A file of that name that is not our manifest is never replaced.
            Err(e) => return Err(e),
        };
        if let Some(write_id) = remove_stale_writes(dir, previous, adopt)? {
            return Ok(Self {
                dir: dir.to_path_buf(),
                data_dir: dir.join(write_dir_name(write_id)),
                write_id,
                previous,
                committed: false,
                keep_on_drop: false,
                resumed: true,
                _lock: lock,
            });
        }
        loop {
            let write_id = new_write_id();
            let data_dir = dir.join(write_dir_name(write_id));
            match std::fs::create_dir(&data_dir) {
                Ok(()) => {
                    return Ok(Self {
                        dir: dir.to_path_buf(),
                        data_dir,
                        write_id,
                        previous,
                        committed: false,
                        keep_on_drop: false,
                        resumed: false,
                        _lock: lock,
                    })
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
                Err(e) => return Err(DatasetError::io(&data_dir, e)),
            }
        }
    }

    pub(crate) fn write_id(&self) -> u64 {
        self.write_id
    }

    /// The write the manifest named when the lock was taken (`None`: no dataset yet).
    pub(crate) fn previous(&self) -> Option<u64> {
        self.previous
    }

    pub(crate) fn path(&self, name: &str) -> PathBuf {
        self.data_dir.join(name)
    }

    /// Whether this write continues one an earlier process left (see
    /// [`PendingWrite::begin_resumable`]).
    pub(crate) fn resumed(&self) -> bool {
        self.resumed
    }

    /// The files of this write as a reader will see them after the commit.
    pub(crate) fn files(&self) -> DatasetFiles {
        DatasetFiles {
            dir: self.dir.clone(),
            data_dir: self.data_dir.clone(),
            write_id: self.write_id,
            version: FORMAT_VERSION,
        }
    }

    /// Makes this write the dataset: flushes the subdirectory, renames a new manifest over
    /// the old one and flushes the directory. Then removes the previous write and any
    /// version-1 files; failures there only leave garbage the next writer removes.
    pub(crate) fn commit(mut self) -> Result<(), DatasetError> {
        sync_dir(&self.data_dir)?;
        // The new subdirectory's own entry must be durable before a manifest names it.
        sync_dir(&self.dir)?;
        let temp = self
            .dir
            .join(format!("{TEMP_MANIFEST_PREFIX}{:016x}.tmp", self.write_id));
        write_new_durably(&temp, &encode_manifest(self.write_id))?;
        let manifest = self.dir.join(MANIFEST_FILE);
        if let Err(e) = std::fs::rename(&temp, &manifest) {
            let _ = std::fs::remove_file(&temp);
            return Err(DatasetError::io(&manifest, e));
        }
        self.committed = true;
        sync_dir(&self.dir)?;
        if let Some(previous) = self.previous {
            let _ = std::fs::remove_dir_all(self.dir.join(write_dir_name(previous)));
        }
        let _ = remove_legacy_files(&self.dir);
        Ok(())
    }
}

impl Drop for PendingWrite {
    fn drop(&mut self) {
        if !self.committed && !self.keep_on_drop {
            let _ = std::fs::remove_dir_all(&self.data_dir);
        }
    }
}

/// Whether version-1 files lie in `dir`: beside a manifest of this version, what an upgrade
/// that died after its commit left (they are never read again).
pub(crate) fn has_legacy_files(dir: &Path) -> bool {
    LEGACY_FILES
        .iter()
        .any(|(name, magic)| legacy_file(&dir.join(name), magic))
}

/// Removes the version-1 files beside a manifest of this version (see [`has_legacy_files`]).
pub(crate) fn remove_legacy_files(dir: &Path) -> Result<usize, DatasetError> {
    let mut removed = 0;
    for (name, magic) in LEGACY_FILES {
        let path = dir.join(name);
        if legacy_file(&path, magic) {
            std::fs::remove_file(&path).map_err(|e| DatasetError::io(&path, e))?;
            removed += 1;
        }
    }
    Ok(removed)
}

/// Removes write subdirectories other than `current` and temporary manifests: under the
/// lock, any such entry was left by a writer that died.
/// Removes what earlier writers left in `dir` (every write subdirectory but `current`'s,
/// temporary manifests), except the first write subdirectory `adopt` accepts: its id is
/// returned.
fn remove_stale_writes(
    dir: &Path,
    current: Option<u64>,
    adopt: &mut dyn FnMut(&Path) -> bool,
) -> Result<Option<u64>, DatasetError> {
    let entries = std::fs::read_dir(dir).map_err(|e| DatasetError::io(dir, e))?;
    let mut adopted = None;
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(name) = name.to_str() else { continue };
        let is_dir = entry.file_type().is_ok_and(|t| t.is_dir());
        let stale = parse_write_dir_name(name).filter(|&id| is_dir && Some(id) != current);
        if let Some(id) = stale {
            if adopted.is_none() && adopt(&entry.path()) {
                adopted = Some(id);
                continue;
            }
            std::fs::remove_dir_all(entry.path()).map_err(|e| DatasetError::io(entry.path(), e))?;
        } else if !is_dir && name.starts_with(TEMP_MANIFEST_PREFIX) && name.ends_with(".tmp") {
            std::fs::remove_file(entry.path()).map_err(|e| DatasetError::io(entry.path(), e))?;
        }
    }
    Ok(adopted)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn write_dir_names_round_trip_and_reject_others() {
        for id in [1, 0xdead_beef, u64::MAX] {
            assert_eq!(parse_write_dir_name(&write_dir_name(id)), Some(id));
        }
        for other in [
            "write-1",
            "write-xyz0000000000000",
            "writes-0000000000000001",
            "photos",
            "write-+000000000000001",
            "write-00000000DEADBEEF",
        ] {
            assert_eq!(parse_write_dir_name(other), None, "{other}");
        }
    }

    #[test]
    fn manifest_round_trips_and_catches_flips() {
        let path = Path::new("m");
        let bytes = encode_manifest(0x0123_4567_89ab_cdef);
        assert_eq!(
            decode_manifest(path, &bytes, FORMAT_VERSION).expect("decode"),
            0x0123_4567_89ab_cdef
        );
        for byte in 0..MANIFEST_BYTES {
            let mut flipped = bytes.clone();
            flipped[byte] ^= 0x10;
            assert!(
                decode_manifest(path, &flipped, FORMAT_VERSION).is_err(),
                "flip in byte {byte} accepted"
            );
        }
        assert!(decode_manifest(path, &bytes[..20], FORMAT_VERSION).is_err());
    }

    #[test]
    fn write_ids_differ() {
        let ids: std::collections::HashSet<u64> = (0..1000).map(|_| new_write_id()).collect();
        assert_eq!(ids.len(), 1000);
        assert!(!ids.contains(&0));
    }
}
