//! Where a dataset's files are read from: a local directory, or a store that serves the
//! same files by name and byte range (an HTTP server or an object store; see the tools'
//! remote stores).
//!
//! A dataset opened from a store reads its small files (manifest, scene, tables) whole,
//! once, and the pack by range: every mip is one ranged read, checked against its CRC-32
//! like a local read. Paths are the dataset's file paths as [`super::DatasetFiles`] builds
//! them under the store's root: for a remote store a URL held in a `Path`
//! (`https://host/city/write-…/scene.bin`), so every error names the URL at fault.

use std::path::Path;
use std::sync::Arc;

use super::error::DatasetError;
use super::mip_cache::MipCache;

/// A small file whole: from `store`, or from the local directory when there is none.
pub(crate) fn read_file(store: Option<&Arc<dyn DatasetStore>>, path: &Path) -> Result<Vec<u8>, DatasetError> {
    match store {
        Some(store) => store.read_all(path),
        None => super::io_util::read_all(path),
    }
}

/// Reads the files of a dataset (see the module docs).
///
/// Threading: `Send + Sync`; [`DatasetStore::read_at`] is called from many loader threads
/// at once.
pub trait DatasetStore: Send + Sync + std::fmt::Debug {
    /// The whole file at `path` (the small files: manifest, scene, tables). A missing file
    /// is [`DatasetError::Missing`].
    fn read_all(&self, path: &Path) -> Result<Vec<u8>, DatasetError>;
    /// The length of the file at `path`, in bytes.
    fn len(&self, path: &Path) -> Result<u64, DatasetError>;
    /// Exactly `dst.len()` bytes of the file at `path` from `offset`; fewer is
    /// [`DatasetError::Truncated`].
    fn read_at(&self, path: &Path, offset: u64, dst: &mut [u8]) -> Result<(), DatasetError>;
    /// `(offset, len)` ranges of the file at `path` about to be read with
    /// [`DatasetStore::read_at`], highest priority first: a store with latency starts
    /// fetching them. The default does nothing.
    fn prefetch(&self, _path: &Path, _ranges: &[(u64, u64)]) {}
    /// The on-disk cache mips read from this store go through: a pack opened from the
    /// store reads cached mips locally (each checked against its CRC-32) and caches what
    /// it reads. The default has none.
    fn mip_cache(&self) -> Option<&Arc<MipCache>> {
        None
    }
}
