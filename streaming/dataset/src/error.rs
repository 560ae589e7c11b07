//! The one error type of the dataset format. Every variant names the file (or the texture)
//! and where in it the problem is, so a user can find the broken byte.

use std::fmt;
use std::path::PathBuf;

/// Eight magic bytes, shown escaped because a corrupt file may hold anything.
#[derive(Clone, Copy, PartialEq, Eq)]
pub struct Magic(pub [u8; 8]);

impl fmt::Debug for Magic {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "\"{}\"", self.0.escape_ascii())
    }
}

impl fmt::Display for Magic {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Debug::fmt(self, f)
    }
}

/// Why a dataset could not be read, written or verified.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DatasetError {
    /// A required file does not exist.
    #[error("{}: missing file", path.display())]
    Missing {
        /// The file that was expected.
        path: PathBuf,
    },
    /// The operating system refused a read or write.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file being accessed.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// The file does not start with the expected magic bytes (wrong file or not a dataset).
    #[error("{}: wrong magic {found} at offset 0, expected {expected}", path.display())]
    BadMagic {
        /// The file.
        path: PathBuf,
        /// The bytes found.
        found: Magic,
        /// The bytes expected.
        expected: Magic,
    },
    /// The file was written by a format version this build does not read.
    #[error("{}: format version {found} at offset 8 is not supported (this build reads version {supported})", path.display())]
    UnsupportedVersion {
        /// The file.
        path: PathBuf,
        /// The version stored in the file.
        found: u32,
        /// The version this build reads and writes.
        supported: u32,
    },
    /// The file is from format version 1, which `citystream upgrade` converts.
    #[error(
        "{}: format version {found} dataset; this build reads version {} only: upgrade it with `citystream upgrade {}` (rewrites it atomically)",
        path.display(), super::format::FORMAT_VERSION, dataset_dir(path).display()
    )]
    NeedsUpgrade {
        /// The file (or the dataset directory) found in the old version.
        path: PathBuf,
        /// The version found.
        found: u32,
    },
    /// A file's write id differs from the manifest's: the files come from different writes.
    #[error("{}: written by write {found:016x}, but the dataset manifest names write {expected:016x}: files of different writes are mixed", path.display())]
    MixedWrites {
        /// The file from another write.
        path: PathBuf,
        /// Its write id.
        found: u64,
        /// The manifest's write id.
        expected: u64,
    },
    /// Another process holds the dataset directory's write lock.
    #[error("{}: another process is writing a dataset here (its lock is held); try again when it has finished", dir.display())]
    Locked {
        /// The dataset directory.
        dir: PathBuf,
    },
    /// Another process holds the lease of an object in S3 (a merge's or a shard's) and has
    /// renewed it recently.
    #[error(
        "{url}: held by another writer ({holder}, last renewed {age_s:.0} s ago); two writers here would \
         remove each other's files. Wait for it to finish; if it died, its lease lapses {stale_s:.0} s \
         after its last renewal, and a rerun then takes over"
    )]
    Leased {
        /// The lease object.
        url: PathBuf,
        /// Who holds it (host, process and a random tag).
        holder: String,
        /// Seconds since it was last renewed.
        age_s: f64,
        /// Seconds without renewal after which it may be taken over.
        stale_s: f64,
    },
    /// The file is shorter (or longer) than its header or an offset says.
    #[error("{}: truncated or mis-sized: {what} needs bytes {offset}..{end}, but the file is {file_len} bytes", path.display())]
    Truncated {
        /// The file.
        path: PathBuf,
        /// What needed the bytes.
        what: String,
        /// First byte needed.
        offset: u64,
        /// One past the last byte needed.
        end: u64,
        /// The file's actual length.
        file_len: u64,
    },
    /// Stored and computed CRC-32 differ: the bytes were altered after writing.
    #[error("{}: checksum mismatch for {what} (bytes {offset}..{end}): stored {stored:#010x}, computed {computed:#010x}", path.display())]
    Checksum {
        /// The file.
        path: PathBuf,
        /// What the checksum covers.
        what: String,
        /// First byte covered.
        offset: u64,
        /// One past the last byte covered.
        end: u64,
        /// Checksum stored in the dataset.
        stored: u32,
        /// Checksum of the bytes as read.
        computed: u32,
    },
    /// A value in the file is impossible (an index out of range, a NaN, a bad texture size ...).
    #[error("{}: at offset {offset}: {what}", path.display())]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// Byte offset of the bad value in the file.
        offset: u64,
        /// What is wrong.
        what: String,
    },
    /// A caller asked for a texture id the dataset does not have.
    #[error("texture {texture} does not exist (the dataset has {count} textures)")]
    NoSuchTexture {
        /// The requested texture.
        texture: u32,
        /// Number of textures in the dataset.
        count: u32,
    },
    /// A caller asked for a mip level the texture does not have.
    #[error("texture {texture}: mip level {level} does not exist (the texture has {mip_count} levels)")]
    NoSuchMip {
        /// The texture.
        texture: u32,
        /// The requested level (0 = finest).
        level: u32,
        /// Levels the texture has.
        mip_count: u32,
    },
    /// Data handed to the writer is inconsistent (wrong mip chain length, out-of-range ids ...).
    #[error("invalid dataset content: {0}")]
    InvalidInput(String),
}

/// The dataset directory a file path belongs to, for the upgrade command in messages: the
/// directory itself, or the file's parent.
fn dataset_dir(path: &std::path::Path) -> &std::path::Path {
    if path.is_dir() {
        path
    } else {
        path.parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(std::path::Path::new("."))
    }
}

impl DatasetError {
    /// Wraps an I/O error, turning "not found" into [`DatasetError::Missing`].
    pub(crate) fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        let path = path.into();
        if source.kind() == std::io::ErrorKind::NotFound {
            DatasetError::Missing { path }
        } else {
            DatasetError::Io { path, source }
        }
    }

    /// [`DatasetError::Truncated`]: `what` needs bytes `offset..end` of the file at `path`,
    /// which is `file_len` bytes long.
    pub(crate) fn truncated(
        path: impl Into<PathBuf>,
        what: impl Into<String>,
        offset: u64,
        end: u64,
        file_len: u64,
    ) -> Self {
        DatasetError::Truncated {
            path: path.into(),
            what: what.into(),
            offset,
            end,
            file_len,
        }
    }
}
