//! An on-disk cache of mips read from a store ([`DatasetStore`](super::DatasetStore)), so
//! a second flight over the same area reads its mips locally.
//!
//! Layout: `DIR/v1/<dataset>/<texture>-<level>-<crc>`, one file per mip, where `<dataset>`
//! is a hash of the pack's length and header (its write id: a rewritten dataset gets a new
//! one, a mirror of the same write shares it; `SOURCE` names where it was first read) and
//! `<crc>` is the mip's stored CRC-32. Every hit is checked against that CRC and its
//! length, so a damaged or foreign file is a miss (and is removed), never a wrong texel.
//!
//! Safe against partial writes and concurrent processes: an entry is written to a
//! temporary file in its directory and renamed into place, so readers see whole files or
//! none (a file cut short by a crash before the data reached the disk fails its CRC).
//! Processes sharing a directory each add entries; eviction takes an exclusive lock on
//! `DIR/v1/lock`, so one process trims at a time. A file removed while another process
//! reads it stays readable to that reader (POSIX unlink semantics).
//!
//! Bounded, least recently used first: a hit sets the entry's modification time to now;
//! trimming removes the oldest entries until the cache holds at most 7/8 of its capacity.
//! Each process trims when what it believes the cache holds (its last scan plus what it
//! wrote since) passes the capacity, and rescans after writing 1/16 of the capacity, so a
//! single process never leaves the cache above its capacity, and with `P` processes
//! writing at once it exceeds it by at most about `(P - 1)/16` of it. Temporary files older than an hour (a crashed writer's) go when trimming.
//!
//! A shared directory is writable by others, so the cache touches only what it made: it
//! opens an entry only as a regular file, not through a symlink and without blocking (a
//! FIFO or device at an entry's name is a miss, left where it is), counts and removes only
//! files named as its entries or temporary files, and neither reads nor writes through a
//! dataset directory that is a symlink.

use std::fs::{File, OpenOptions};
use std::io::{ErrorKind, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, SystemTime};

use super::error::DatasetError;

/// The layout version: a directory per version, so a future layout never misreads this one.
const LAYOUT_DIR: &str = "v1";
const LOCK_FILE: &str = "lock";
const TEMP_PREFIX: &str = ".tmp-";
/// A temporary file this old belongs to a writer that died.
const STALE_TEMP_AGE: Duration = Duration::from_secs(3600);
/// Numbers temporary files: one counter per process, as caches in one process may share a
/// directory (process id + counter is then unique among all writers).
static TEMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// What a [`MipCache`] did since it was opened (this process only).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct MipCacheStats {
    /// Mips read from the cache.
    pub hits: u64,
    /// Mips asked for and not in the cache (or damaged there).
    pub misses: u64,
    /// Mips written into the cache.
    pub written: u64,
    /// Bytes written into the cache.
    pub written_bytes: u64,
    /// Entries that failed their length or CRC check and were removed.
    pub damaged: u64,
    /// Writes that failed (a full disk, permissions): the mip was loaded all the same.
    pub write_errors: u64,
    /// Entries removed to stay within the capacity.
    pub evicted: u64,
    /// Bytes removed to stay within the capacity.
    pub evicted_bytes: u64,
}

/// One dataset's entries in a [`MipCache`] (see the module docs).
#[derive(Clone, Debug)]
pub struct CacheNamespace {
    dir: PathBuf,
}

/// A size-bounded on-disk mip cache shared by any number of threads and processes.
#[derive(Debug)]
pub struct MipCache {
    root: PathBuf,
    capacity_bytes: u64,
    accounting: Mutex<Accounting>,
    /// One trim at a time in this process (the lock file orders processes).
    trim_lock: Mutex<()>,
    hits: AtomicU64,
    misses: AtomicU64,
    written: AtomicU64,
    written_bytes: AtomicU64,
    damaged: AtomicU64,
    write_errors: AtomicU64,
    evicted: AtomicU64,
    evicted_bytes: AtomicU64,
}

/// What this process believes the cache holds.
#[derive(Debug, Default)]
struct Accounting {
    /// The last scan's total (after trimming) plus what this process wrote since it began:
    /// never less than what the cache holds, as far as this process's writes go.
    held_bytes: u64,
    /// Written since the last scan began.
    written_since_scan: u64,
}

impl Accounting {
    fn needs_trim(&self, capacity_bytes: u64) -> bool {
        self.held_bytes > capacity_bytes || self.written_since_scan > capacity_bytes / 16
    }
}

/// One entry found by a scan.
struct ScannedEntry {
    path: PathBuf,
    len: u64,
    used: SystemTime,
}

impl MipCache {
    /// Opens (creating it if needed) the cache in `dir`, holding at most `capacity_bytes`,
    /// and trims it if it holds more.
    pub fn open(dir: &Path, capacity_bytes: u64) -> Result<Self, DatasetError> {
        if capacity_bytes == 0 {
            return Err(DatasetError::InvalidInput(format!(
                "mip cache {}: a capacity of 0 bytes holds nothing",
                dir.display()
            )));
        }
        let root = dir.join(LAYOUT_DIR);
        std::fs::create_dir_all(&root).map_err(|e| DatasetError::io(&root, e))?;
        // Fail now, not on the first write, when the directory is not writable.
        OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(root.join(LOCK_FILE))
            .map_err(|e| DatasetError::io(root.join(LOCK_FILE), e))?;
        let cache = Self {
            root,
            capacity_bytes,
            accounting: Mutex::default(),
            trim_lock: Mutex::default(),
            hits: AtomicU64::new(0),
            misses: AtomicU64::new(0),
            written: AtomicU64::new(0),
            written_bytes: AtomicU64::new(0),
            damaged: AtomicU64::new(0),
            write_errors: AtomicU64::new(0),
            evicted: AtomicU64::new(0),
            evicted_bytes: AtomicU64::new(0),
        };
        let held: u64 = cache
            .scan()
            .map_err(|e| DatasetError::io(&cache.root, e))?
            .iter()
            .map(|e| e.len)
            .sum();
        cache.accounting().held_bytes = held;
        cache.trim();
        Ok(cache)
    }

    /// Bytes the entries in the cache directory `dir` hold (0 where there is none yet): what
    /// a default capacity counts as the cache's own besides the free space.
    pub fn bytes_in(dir: &Path) -> u64 {
        let root = dir.join(LAYOUT_DIR);
        let mut total = 0;
        for namespace in std::fs::read_dir(&root).into_iter().flatten().flatten() {
            for file in std::fs::read_dir(namespace.path()).into_iter().flatten().flatten() {
                if !is_entry_name(&file.file_name().to_string_lossy()) {
                    continue;
                }
                if file.file_name() != "SOURCE" && !file.file_name().to_string_lossy().starts_with(TEMP_PREFIX) {
                    total += file.metadata().map_or(0, |m| if m.is_file() { m.len() } else { 0 });
                }
            }
        }
        total
    }

    /// The cache's directory (as given to [`MipCache::open`]).
    pub fn dir(&self) -> &Path {
        self.root.parent().unwrap_or(&self.root)
    }

    /// Bytes the cache holds at most.
    pub fn capacity_bytes(&self) -> u64 {
        self.capacity_bytes
    }

    /// Bytes the cache holds, as this process last saw it (its last scan plus its writes).
    pub fn held_bytes(&self) -> u64 {
        self.accounting().held_bytes
    }

    fn accounting(&self) -> MutexGuard<'_, Accounting> {
        // Plain counters: a panic elsewhere leaves them usable.
        self.accounting.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// What this cache did since it was opened.
    pub fn stats(&self) -> MipCacheStats {
        let load = |counter: &AtomicU64| counter.load(Ordering::Relaxed);
        MipCacheStats {
            hits: load(&self.hits),
            misses: load(&self.misses),
            written: load(&self.written),
            written_bytes: load(&self.written_bytes),
            damaged: load(&self.damaged),
            write_errors: load(&self.write_errors),
            evicted: load(&self.evicted),
            evicted_bytes: load(&self.evicted_bytes),
        }
    }

    /// The entries of the dataset `identity` names (any bytes that differ when the data
    /// does: the pack's length and header); `description` (where it was read) is written
    /// beside them for people looking into the directory.
    pub fn namespace(&self, identity: &[u8], description: &str) -> CacheNamespace {
        // Two CRC-32s with different seeds: 64 bits, ample for a handful of datasets, and
        // an entry of the wrong dataset would still have to match its mip's CRC.
        let low = crc32fast::hash(identity);
        let mut hasher = crc32fast::Hasher::new_with_initial(0x9e37_79b9);
        hasher.update(identity);
        hasher.update(&(identity.len() as u64).to_le_bytes());
        let dir = self.root.join(format!("{:08x}{low:08x}", hasher.finalize()));
        let description_path = dir.join("SOURCE");
        if !description_path.exists() && std::fs::create_dir_all(&dir).is_ok() && is_real_dir(&dir) {
            // Informational only: a failure here costs nothing.
            let _ = Self::write_atomically(&dir, &description_path, format!("{description}\n").as_bytes());
        }
        CacheNamespace { dir }
    }

    fn entry_path(namespace: &CacheNamespace, texture: u32, level: u32, crc: u32) -> PathBuf {
        namespace.dir.join(format!("{texture}-{level}-{crc:08x}"))
    }

    /// Whether the cache holds an entry for the mip (unchecked: a read checks it).
    pub fn contains(&self, namespace: &CacheNamespace, texture: u32, level: u32, crc: u32) -> bool {
        is_real_dir(&namespace.dir)
            && std::fs::symlink_metadata(Self::entry_path(namespace, texture, level, crc)).is_ok_and(|m| m.is_file())
    }

    /// Reads the mip into `dst` (exactly its length) if the cache holds it whole and its
    /// CRC-32 is `crc`; marks it used. A damaged entry is removed and reads as a miss.
    pub fn read(&self, namespace: &CacheNamespace, texture: u32, level: u32, crc: u32, dst: &mut [u8]) -> bool {
        let path = Self::entry_path(namespace, texture, level, crc);
        let opened = if is_real_dir(&namespace.dir) {
            open_entry(&path).ok()
        } else {
            None
        };
        let hit = match opened {
            // Not a regular file (a FIFO, a device, a directory): not the cache's; a miss.
            Some((_, meta)) if !meta.is_file() => false,
            Some((mut file, meta)) => {
                let whole =
                    meta.len() == dst.len() as u64 && file.read_exact(dst).is_ok() && crc32fast::hash(dst) == crc;
                if whole {
                    // Least recently used goes first; a failed touch only ages the entry.
                    let _ = file.set_modified(SystemTime::now());
                } else {
                    self.damaged.fetch_add(1, Ordering::Relaxed);
                    let _ = std::fs::remove_file(&path);
                }
                whole
            }
            None => false,
        };
        let counter = if hit { &self.hits } else { &self.misses };
        counter.fetch_add(1, Ordering::Relaxed);
        hit
    }

    /// Stores a mip (already checked against `crc` by the caller). Best effort: a failure
    /// is counted in [`MipCacheStats::write_errors`] and otherwise ignored, as the mip was
    /// loaded; a mip larger than a quarter of the capacity is not cached (it would push
    /// out most of the rest).
    pub fn write(&self, namespace: &CacheNamespace, texture: u32, level: u32, crc: u32, bytes: &[u8]) {
        let len = bytes.len() as u64;
        if len > self.capacity_bytes / 4 {
            return;
        }
        let path = Self::entry_path(namespace, texture, level, crc);
        let result = std::fs::create_dir_all(&namespace.dir).and_then(|()| {
            if !is_real_dir(&namespace.dir) {
                return Err(std::io::Error::new(
                    ErrorKind::InvalidInput,
                    "the dataset's cache directory is a symlink",
                ));
            }
            Self::write_atomically(&namespace.dir, &path, bytes)
        });
        if result.is_err() {
            self.write_errors.fetch_add(1, Ordering::Relaxed);
            return;
        }
        self.written.fetch_add(1, Ordering::Relaxed);
        self.written_bytes.fetch_add(len, Ordering::Relaxed);
        let needs_trim = {
            let mut accounting = self.accounting();
            accounting.held_bytes += len;
            accounting.written_since_scan += len;
            accounting.needs_trim(self.capacity_bytes)
        };
        if needs_trim {
            self.trim();
        }
    }

    /// Writes `bytes` to a temporary file in `dir` and renames it to `path`.
    fn write_atomically(dir: &Path, path: &Path, bytes: &[u8]) -> std::io::Result<()> {
        // A name no other writer uses: process id, a per-process counter and the time
        // (processes in different PID namespaces may share the id), created only if new.
        let nanos = SystemTime::now()
            .duration_since(SystemTime::UNIX_EPOCH)
            .map_or(0, |d| d.subsec_nanos());
        let temp = dir.join(format!(
            "{TEMP_PREFIX}{}-{}-{nanos}",
            std::process::id(),
            TEMP_COUNTER.fetch_add(1, Ordering::Relaxed)
        ));
        let mut file = OpenOptions::new().write(true).create_new(true).open(&temp)?;
        let written = file.write_all(bytes).and_then(|()| std::fs::rename(&temp, path));
        if written.is_err() {
            let _ = std::fs::remove_file(&temp);
        }
        written
    }

    /// Every entry in the cache; removes stale temporary files on the way.
    fn scan(&self) -> std::io::Result<Vec<ScannedEntry>> {
        let mut entries = Vec::new();
        let now = SystemTime::now();
        for namespace in std::fs::read_dir(&self.root)? {
            let namespace = namespace?;
            if !namespace.file_type()?.is_dir() {
                continue;
            }
            let files = match std::fs::read_dir(namespace.path()) {
                Ok(files) => files,
                // Removed by another process meanwhile.
                Err(e) if e.kind() == ErrorKind::NotFound => continue,
                Err(e) => return Err(e),
            };
            for file in files {
                let Ok(file) = file else { continue };
                let Ok(meta) = file.metadata() else { continue };
                let name = file.file_name();
                let name = name.to_string_lossy();
                // The entry's own metadata (a symlink is not followed): only regular files
                // named as the cache names its files are the cache's.
                if !meta.is_file() {
                    continue;
                }
                let used = meta.modified().unwrap_or(SystemTime::UNIX_EPOCH);
                if is_temp_name(&name) {
                    if now.duration_since(used).is_ok_and(|age| age > STALE_TEMP_AGE) {
                        let _ = std::fs::remove_file(file.path());
                    }
                    continue;
                }
                if !is_entry_name(&name) {
                    continue;
                }
                entries.push(ScannedEntry {
                    path: file.path(),
                    len: meta.len(),
                    used,
                });
            }
        }
        Ok(entries)
    }

    /// Removes the least recently used entries until the cache holds at most 7/8 of its
    /// capacity, if this process believes it holds more than its capacity or wrote a
    /// sixteenth of it since the last scan. One thread per process at a time (the others
    /// wait, then look again: the entries they wrote may have come after the scan), and one
    /// process per directory (a process that finds another trimming skips).
    pub fn trim(&self) {
        let _one_at_a_time = self.trim_lock.lock().unwrap_or_else(|e| e.into_inner());
        {
            let mut accounting = self.accounting();
            if !accounting.needs_trim(self.capacity_bytes) {
                return;
            }
            accounting.written_since_scan = 0;
        }
        // Writable (an exclusive lock over NFS needs it) and recreated if someone emptied
        // the directory. Only another process trimming skips this trim; where locking
        // itself fails, trimming unlocked is still safe (removals of files another process
        // also removes just fail).
        let lock = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(self.root.join(LOCK_FILE));
        if let Ok(lock) = &lock {
            if let Err(std::fs::TryLockError::WouldBlock) = lock.try_lock() {
                return;
            }
        }
        if let Ok(mut entries) = self.scan() {
            let mut held: u64 = entries.iter().map(|e| e.len).sum();
            if held > self.capacity_bytes {
                let goal = self.capacity_bytes / 8 * 7;
                entries.sort_by_key(|e| e.used);
                for entry in entries {
                    if held <= goal {
                        break;
                    }
                    if std::fs::remove_file(&entry.path).is_ok() {
                        held -= entry.len;
                        self.evicted.fetch_add(1, Ordering::Relaxed);
                        self.evicted_bytes.fetch_add(entry.len, Ordering::Relaxed);
                    }
                }
            }
            // What was written during the scan may or may not be in `held`: count it
            // again, so the belief never falls below the truth.
            let mut accounting = self.accounting();
            accounting.held_bytes = held + accounting.written_since_scan;
        }
        if let Ok(lock) = &lock {
            let _ = lock.unlock();
        }
    }
}

/// Whether `name` is one the cache gives an entry: `<texture>-<level>-<crc as 8 hex digits>`.
fn is_entry_name(name: &str) -> bool {
    let mut parts = name.split('-');
    let (Some(texture), Some(level), Some(crc), None) = (parts.next(), parts.next(), parts.next(), parts.next()) else {
        return false;
    };
    let decimal = |s: &str| !s.is_empty() && s.len() <= 10 && s.bytes().all(|b| b.is_ascii_digit());
    decimal(texture) && decimal(level) && crc.len() == 8 && crc.bytes().all(|b| b.is_ascii_hexdigit())
}

/// Whether `name` is one the cache gives a temporary file: `.tmp-<pid>-<counter>-<nanos>`
/// (or `.tmp-<pid>-<counter>`, as earlier versions named them).
fn is_temp_name(name: &str) -> bool {
    name.strip_prefix(TEMP_PREFIX).is_some_and(|rest| {
        let parts: Vec<&str> = rest.split('-').collect();
        (2..=3).contains(&parts.len())
            && parts
                .iter()
                .all(|p| !p.is_empty() && p.bytes().all(|b| b.is_ascii_digit()))
    })
}

/// Whether `dir` is a directory itself, not a symlink to one.
fn is_real_dir(dir: &Path) -> bool {
    std::fs::symlink_metadata(dir).is_ok_and(|m| m.is_dir())
}

/// Opens an entry for reading with its metadata: never through a symlink, and without
/// blocking on a FIFO (whose metadata then says it is not a regular file).
fn open_entry(path: &Path) -> std::io::Result<(File, std::fs::Metadata)> {
    let mut options = OpenOptions::new();
    options.read(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK);
    }
    #[cfg(not(unix))]
    if !std::fs::symlink_metadata(path)?.is_file() {
        return Err(std::io::Error::new(ErrorKind::InvalidInput, "not a regular file"));
    }
    let file = options.open(path)?;
    let meta = file.metadata()?;
    Ok((file, meta))
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;

    fn fresh(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("citystream-mip-cache-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    fn mip(seed: u8, len: usize) -> (Vec<u8>, u32) {
        let bytes: Vec<u8> = (0..len)
            .map(|i| (i as u8).wrapping_mul(31).wrapping_add(seed))
            .collect();
        let crc = crc32fast::hash(&bytes);
        (bytes, crc)
    }

    #[test]
    fn a_written_mip_reads_back_and_a_damaged_one_is_a_miss_and_goes() {
        let dir = fresh("roundtrip");
        let cache = MipCache::open(&dir, 1 << 20).expect("open");
        let ns = cache.namespace(b"http://host/city/pack", "http://host/city");
        let (bytes, crc) = mip(1, 4096);
        let mut dst = vec![0; 4096];
        assert!(!cache.read(&ns, 3, 1, crc, &mut dst));
        cache.write(&ns, 3, 1, crc, &bytes);
        assert!(cache.read(&ns, 3, 1, crc, &mut dst));
        assert_eq!(dst, bytes);
        // Another dataset does not see it.
        let other = cache.namespace(b"http://host/other/pack", "other");
        assert!(!cache.read(&other, 3, 1, crc, &mut dst));

        // A flipped byte, a short file and a wrong length are misses, and the entry goes.
        let path = MipCache::entry_path(&ns, 3, 1, crc);
        let mut damaged = bytes.clone();
        damaged[100] ^= 1;
        std::fs::write(&path, &damaged).expect("damage");
        assert!(!cache.read(&ns, 3, 1, crc, &mut dst));
        assert!(!path.exists());
        std::fs::write(&path, &bytes[..1000]).expect("cut");
        assert!(!cache.read(&ns, 3, 1, crc, &mut dst));
        assert!(!path.exists());
        let stats = cache.stats();
        assert_eq!((stats.hits, stats.misses, stats.damaged, stats.written), (1, 4, 2, 1));
        // No temporary file left behind.
        let leftovers = std::fs::read_dir(&ns.dir)
            .expect("dir")
            .filter(|e| {
                e.as_ref()
                    .expect("entry")
                    .file_name()
                    .to_string_lossy()
                    .starts_with(TEMP_PREFIX)
            })
            .count();
        assert_eq!(leftovers, 0);
        std::fs::remove_dir_all(&dir).expect("clean up");
    }

    #[test]
    fn the_least_recently_used_mips_go_first_and_the_capacity_holds() {
        let dir = fresh("lru");
        // Sixteen 4 KiB mips fit in 64 KiB + room for no more.
        let cache = MipCache::open(&dir, 64 << 10).expect("open");
        let ns = cache.namespace(b"lru", "lru");
        let mips: Vec<(Vec<u8>, u32)> = (0..24).map(|i| mip(i, 4096)).collect();
        let mut dst = vec![0; 4096];
        let base = SystemTime::now() - Duration::from_secs(1000);
        for (i, (bytes, crc)) in mips.iter().enumerate().take(16) {
            cache.write(&ns, i as u32, 0, *crc, bytes);
            // Distinct ages, oldest first, without sleeping.
            File::options()
                .write(true)
                .open(MipCache::entry_path(&ns, i as u32, 0, *crc))
                .and_then(|f| f.set_modified(base + Duration::from_secs(i as u64)))
                .expect("age");
        }
        // Using mips 0 and 1 makes them the most recent.
        assert!(cache.read(&ns, 0, 0, mips[0].1, &mut dst));
        assert!(cache.read(&ns, 1, 0, mips[1].1, &mut dst));
        for (i, (bytes, crc)) in mips.iter().enumerate().skip(16) {
            cache.write(&ns, i as u32, 0, *crc, bytes);
        }
        let held: u64 = cache.scan().expect("scan").iter().map(|e| e.len).sum();
        assert!(held <= 64 << 10, "{held} bytes held");
        assert!(cache.stats().evicted > 0);
        // The recently used survive; the oldest untouched went first.
        assert!(cache.contains(&ns, 0, 0, mips[0].1) && cache.contains(&ns, 1, 0, mips[1].1));
        assert!(!cache.contains(&ns, 2, 0, mips[2].1));
        assert!(cache.contains(&ns, 23, 0, mips[23].1));
        // Reopening with a smaller capacity trims at once.
        drop(cache);
        let cache = MipCache::open(&dir, 16 << 10).expect("reopen");
        let held: u64 = cache.scan().expect("scan").iter().map(|e| e.len).sum();
        assert!(held <= 16 << 10, "{held} bytes held after reopening smaller");
        std::fs::remove_dir_all(&dir).expect("clean up");
    }

    #[test]
    fn caches_sharing_a_directory_from_many_threads_stay_whole_and_bounded() {
        let dir = fresh("shared");
        let mips: Vec<(Vec<u8>, u32)> = (0..64).map(|i| mip(i, 2048 + usize::from(i) * 16)).collect();
        // Four independent caches on one directory, as four processes would be.
        std::thread::scope(|scope| {
            for worker in 0..4u32 {
                let (dir, mips) = (&dir, &mips);
                scope.spawn(move || {
                    let cache = MipCache::open(dir, 96 << 10).expect("open");
                    let ns = cache.namespace(b"shared", "shared");
                    let mut dst = Vec::new();
                    for round in 0..3u32 {
                        for step in 0..mips.len() as u32 {
                            // Each worker walks the mips from its own place.
                            let i = (step + worker * 7 + round) % mips.len() as u32;
                            let (bytes, crc) = &mips[i as usize];
                            dst.resize(bytes.len(), 0);
                            if cache.read(&ns, i, 0, *crc, &mut dst) {
                                assert_eq!(&dst, bytes, "mip {i} read back different bytes");
                            } else {
                                cache.write(&ns, i, 0, *crc, bytes);
                            }
                        }
                    }
                    assert_eq!(cache.stats().damaged, 0);
                });
            }
        });
        let cache = MipCache::open(&dir, 96 << 10).expect("open");
        let held: u64 = cache.scan().expect("scan").iter().map(|e| e.len).sum();
        // Four writers may overshoot by about 4/16 of the capacity between their scans.
        assert!(held <= (96 << 10) + (96 << 10) / 4, "{held} bytes held");
        std::fs::remove_dir_all(&dir).expect("clean up");
    }

    #[test]
    fn stale_temporary_files_go_and_a_zero_capacity_is_refused() {
        let dir = fresh("stale");
        assert!(MipCache::open(&dir, 0).is_err());
        let cache = MipCache::open(&dir, 1 << 20).expect("open");
        let ns = cache.namespace(b"stale", "stale");
        let (bytes, crc) = mip(9, 512);
        cache.write(&ns, 0, 0, crc, &bytes);
        let stale = ns.dir.join(format!("{TEMP_PREFIX}1-1"));
        let fresh_temp = ns.dir.join(format!("{TEMP_PREFIX}1-2"));
        std::fs::write(&stale, b"half").expect("stale");
        std::fs::write(&fresh_temp, b"half").expect("fresh");
        File::options()
            .write(true)
            .open(&stale)
            .and_then(|f| f.set_modified(SystemTime::now() - STALE_TEMP_AGE - Duration::from_secs(60)))
            .expect("age");
        let entries = cache.scan().expect("scan");
        assert_eq!(entries.len(), 1, "temporary files are not entries");
        assert!(!stale.exists() && fresh_temp.exists());
        // Someone empties the directory's lock file away: trimming still happens.
        std::fs::remove_file(dir.join(LAYOUT_DIR).join(LOCK_FILE)).expect("remove the lock file");
        for i in 1..40u32 {
            let (bytes, crc) = mip(i as u8, 64 << 10);
            cache.write(&ns, i, 0, crc, &bytes);
        }
        let held: u64 = cache.scan().expect("scan").iter().map(|e| e.len).sum();
        assert!(held <= 1 << 20, "{held} bytes held in a 1 MiB cache");
        assert!(cache.stats().evicted > 0);
        std::fs::remove_dir_all(&dir).expect("clean up");
    }

    #[test]
    fn entry_and_temporary_names_are_only_the_cache_s_own() {
        assert!(is_entry_name("12-3-0badf00d") && is_entry_name("0-0-00000000"));
        for foreign in [
            "notes.txt",
            "12-3",
            "12-3-0badf00",
            "12-3-0badf00d-x",
            "a-3-0badf00d",
            "SOURCE",
            "-3-0badf00d",
        ] {
            assert!(!is_entry_name(foreign), "{foreign}");
        }
        assert!(is_temp_name(".tmp-41-7-123456"));
        assert!(is_temp_name(".tmp-41-7"));
        assert!(!is_temp_name(".tmp-mine") && !is_temp_name(".tmp-1") && !is_temp_name("tmp-1-2-3"));
    }

    #[cfg(unix)]
    #[test]
    fn a_fifo_or_a_symlink_at_an_entry_s_name_is_a_miss_left_alone_without_blocking() {
        let dir = fresh("fifo");
        let cache = MipCache::open(&dir, 1 << 20).expect("open");
        let ns = cache.namespace(b"fifo", "fifo");
        std::fs::create_dir_all(&ns.dir).expect("namespace dir");
        let (bytes, crc) = mip(3, 256);
        let fifo = MipCache::entry_path(&ns, 1, 0, crc);
        let made = std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .expect("mkfifo");
        assert!(made.success());
        // A read that blocked would never send: the test fails instead of hanging.
        let (sender, receiver) = std::sync::mpsc::channel();
        let reader = {
            let (cache, ns) = (Arc::new(cache), ns.clone());
            let thread_cache = Arc::clone(&cache);
            std::thread::spawn(move || {
                let mut dst = vec![0; 256];
                let _ = sender.send(thread_cache.read(&ns, 1, 0, crc, &mut dst));
            });
            cache
        };
        let hit = receiver
            .recv_timeout(Duration::from_secs(10))
            .expect("the read blocked on a FIFO");
        assert!(!hit);
        assert!(
            std::fs::symlink_metadata(&fifo).is_ok(),
            "the FIFO is not the cache's to remove"
        );
        // A symlink to a file elsewhere holding the very bytes: not followed, not removed.
        let outside = dir.join("outside");
        std::fs::write(&outside, &bytes).expect("outside file");
        let link = MipCache::entry_path(&ns, 2, 0, crc);
        std::os::unix::fs::symlink(&outside, &link).expect("symlink");
        let mut dst = vec![0; 256];
        assert!(!reader.read(&ns, 2, 0, crc, &mut dst));
        assert!(!reader.contains(&ns, 2, 0, crc));
        assert!(std::fs::symlink_metadata(&link).is_ok() && outside.exists());
        std::fs::remove_dir_all(&dir).expect("clean up");
    }

    #[test]
    fn trimming_never_touches_files_that_are_not_entries() {
        let dir = fresh("foreign");
        let cache = MipCache::open(&dir, 16 << 10).expect("open");
        let ns = cache.namespace(b"foreign", "foreign");
        std::fs::create_dir_all(&ns.dir).expect("namespace dir");
        // Someone else's file, larger than the whole capacity, beside the entries.
        let notes = ns.dir.join("notes.txt");
        std::fs::write(&notes, vec![7u8; 64 << 10]).expect("notes");
        for i in 0..12u8 {
            let (bytes, crc) = mip(i, 4096);
            cache.write(&ns, u32::from(i), 0, crc, &bytes);
        }
        assert!(cache.stats().evicted > 0, "entries beyond the capacity go");
        let held: u64 = cache.scan().expect("scan").iter().map(|e| e.len).sum();
        assert!(held <= 16 << 10, "{held} bytes of entries held");
        assert_eq!(std::fs::metadata(&notes).expect("notes stays").len(), 64 << 10);
        assert_eq!(MipCache::bytes_in(&dir), held, "only entries count");
        std::fs::remove_dir_all(&dir).expect("clean up");
    }

    #[cfg(unix)]
    #[test]
    fn a_dataset_directory_that_is_a_symlink_is_neither_read_nor_written_through() {
        let dir = fresh("linked");
        let elsewhere = fresh("linked-elsewhere");
        std::fs::create_dir_all(&elsewhere).expect("elsewhere");
        let cache = MipCache::open(&dir, 1 << 20).expect("open");
        let ns = cache.namespace(b"linked", "linked");
        let _ = std::fs::remove_dir_all(&ns.dir);
        std::os::unix::fs::symlink(&elsewhere, &ns.dir).expect("symlink the dataset's directory");
        for i in 0..8u8 {
            let (bytes, crc) = mip(i, 1024);
            cache.write(&ns, u32::from(i), 0, crc, &bytes);
        }
        assert_eq!(cache.stats().written, 0);
        assert_eq!(cache.stats().write_errors, 8);
        assert_eq!(
            std::fs::read_dir(&elsewhere).expect("list").count(),
            0,
            "nothing written through"
        );
        // An entry placed there by someone else is not read through the link either.
        let (bytes, crc) = mip(1, 1024);
        std::fs::write(elsewhere.join(format!("1-0-{crc:08x}")), &bytes).expect("plant");
        let mut dst = vec![0; 1024];
        assert!(!cache.read(&ns, 1, 0, crc, &mut dst));
        std::fs::remove_dir_all(&dir).expect("clean up");
        std::fs::remove_dir_all(&elsewhere).expect("clean up");
    }
}
