//! citystream's on-disk city: the dataset format (scene file, texture pack with per-mip byte
//! ranges, colormap), its atomic writes and checked reads, upgrades from older formats, the
//! on-disk mip cache, and (feature `remote`, module `remote`) the same datasets over HTTP or
//! S3. No Vulkan and no streaming policy: `citystream-streaming`'s loader reads through it.
//!
//! Modules, private behind the re-exports below: `scene`, `pack`, `colormap` and `format`
//! (the files and their records), `crs` (the coordinate reference system a scene names),
//! `files` and `writer` (the manifest, write directories and atomic replacement), `store`
//! (where a dataset's bytes live: a directory or a remote store), `verify` (every mip
//! checked), `legacy` (upgrades from formats 1 and 2), `mip_cache` (remote mips kept on
//! disk), `io_util` and `error`.
//!
//! A dataset is a directory holding a manifest, `dataset.manifest`, that names the current
//! write, and that write's subdirectory `write-<id>/` with five files (format version
//! [`FORMAT_VERSION`], all little-endian, specified in `docs/DATASET.md`). Every file
//! carries the write id in its header, so files of different writes are never mixed; writes
//! replace a dataset atomically ([`DatasetFiles`], [`DatasetWriter`]):
//!
//! - `scene.bin` ([`Scene`]): meshes (one texture each), flat vertex and index arrays,
//!   per-mesh and scene bounds, positions relative to an f64 origin, and the coordinate
//!   reference system ([`Crs`]) the origin is given in.
//! - `textures.meta` ([`TextureInfo`], 10 bytes per texture): extent as log2, mip count,
//!   format and the offset of the texture's first mip in the pack. Per-mip offsets are
//!   derived: mips lie back to back, level 0 (finest) first.
//! - `textures.pack`: every mip of every texture, so a loader reads exactly one mip with one
//!   positioned read ([`TexturePack::read_mip`]) and never a whole texture (paper §3.5).
//! - `colormap.bin` ([`Colormap`]): mean colour per texture, the City Colormap (paper §3.7).
//! - `textures.crc`: CRC-32 of every mip, checked on every read ([`TexturePack::read_mip`]).
//!
//! Contracts:
//! - Opening ([`Dataset::open`], [`TexturePack::open`]) reads the scene and the tables but
//!   no mip data, and validates everything a renderer relies on (sizes, checksums of the
//!   tables and of the whole scene, one write id everywhere, texture extents and offsets
//!   inside the pack, mesh ranges, indices, finite attributes, bounds that match the
//!   vertices). After a successful open, every `(texture, level)` pair below
//!   [`TextureInfo::mip_count`] maps to a byte range inside the pack.
//! - Every failure is a [`DatasetError`] naming the file and the offset or index at fault;
//!   no input makes this module panic or read out of bounds.
//! - Textures are powers of two per side; block-compressed ones are at least 4×4 at level 0.
//!   Mips of block formats smaller than 4 texels on a side still occupy whole 4×4 blocks.

#![forbid(unsafe_code)]

mod colormap;
mod crs;
mod error;
mod files;
mod format;
mod io_util;
mod legacy;
mod mip_cache;
mod pack;
mod scene;
mod store;
mod verify;
mod writer;

#[cfg(feature = "remote")]
pub mod remote;

use std::path::Path;
use std::sync::Arc;

pub use colormap::Colormap;
pub use crs::{Crs, CrsError, MAX_CRS_BYTES};
pub use error::{DatasetError, Magic};
pub use files::{write_dir_name, DatasetFiles, MANIFEST_FILE};
pub use format::{full_mip_count, TextureFormat, TextureInfo, MAX_EXTENT_LOG2, MAX_PACK_OFFSET};
pub use io_util::ensure_regular_file;
pub use legacy::{upgrade, UpgradeSummary};
pub use mip_cache::{CacheNamespace, MipCache, MipCacheStats};
pub use pack::{MipLocation, TexturePack, PACK_HEADER_BYTES};
pub use scene::{Aabb, Mesh, Scene};
pub use store::DatasetStore;
pub use verify::{verify, verify_dataset, VerifyReport};
pub use writer::{DatasetWriter, WriteSummary};

/// The format version this build reads and writes.
pub const FORMAT_VERSION: u32 = 3;
/// Scene file name inside a dataset directory.
pub const SCENE_FILE: &str = "scene.bin";
/// Texture metadata file name.
pub const META_FILE: &str = "textures.meta";
/// Texture pack file name.
pub const PACK_FILE: &str = "textures.pack";
/// City Colormap file name.
pub const COLORMAP_FILE: &str = "colormap.bin";
/// Per-mip checksum file name.
pub const CHECKSUM_FILE: &str = "textures.crc";

/// An opened dataset: the scene, the texture table with an open pack, and the colormap.
///
/// Threading: `Send + Sync`; see [`TexturePack`] for concurrent mip reads.
#[derive(Debug)]
pub struct Dataset {
    files: DatasetFiles,
    /// Where it was opened from (`None`: the local directory).
    store: Option<Arc<dyn DatasetStore>>,
    /// All meshes and geometry.
    pub scene: Scene,
    /// Texture metadata and mip reads.
    pub textures: TexturePack,
    /// Mean colour per texture.
    pub colormap: Colormap,
    scene_file_len: u64,
}

impl Dataset {
    /// Opens the dataset in `dir`: reads its manifest, then reads and validates `scene.bin`,
    /// `textures.meta`, `textures.crc`, `colormap.bin` and the header of `textures.pack` of
    /// the write it names, and checks they agree (one write id, every mesh's texture exists,
    /// one colour per texture). Reads no mip data.
    ///
    /// A writer may replace the dataset meanwhile and remove the files just resolved; the
    /// open then starts again from the new manifest (a few times at most).
    pub fn open(dir: impl AsRef<Path>) -> Result<Self, DatasetError> {
        let dir = dir.as_ref();
        Self::open_resolved(|| DatasetFiles::resolve(dir), Self::open_files)
    }

    /// Resolves the manifest and opens the write it names; when the open fails because a
    /// writer replaced the dataset meanwhile (the manifest now names another write), starts
    /// again, three attempts at most.
    fn open_resolved(
        resolve: impl Fn() -> Result<DatasetFiles, DatasetError>,
        open: impl Fn(&DatasetFiles) -> Result<Self, DatasetError>,
    ) -> Result<Self, DatasetError> {
        let mut attempts = 0;
        loop {
            let files = resolve()?;
            match open(&files) {
                Ok(dataset) => return Ok(dataset),
                Err(e) => {
                    attempts += 1;
                    let replaced = resolve().is_ok_and(|now| now.write_id() != files.write_id());
                    if !replaced || attempts >= 3 {
                        return Err(e);
                    }
                }
            }
        }
    }

    /// [`Dataset::open`] of resolved files.
    pub fn open_files(files: &DatasetFiles) -> Result<Self, DatasetError> {
        Self::open_files_in(None, files)
    }

    /// Opens the dataset at `root` of `store` (a remote dataset: `root` is its URL): the
    /// manifest, then the files of the write it names, validated as [`Dataset::open`] does;
    /// mips are then read from the store by range. If the dataset is replaced meanwhile,
    /// the open starts again from the new manifest (a few times at most).
    pub fn open_store(store: Arc<dyn DatasetStore>, root: &Path) -> Result<Self, DatasetError> {
        Self::open_resolved(
            || DatasetFiles::resolve_in(store.as_ref(), root),
            |files| Self::open_files_in(Some(&store), files),
        )
    }

    fn open_files_in(store: Option<&Arc<dyn DatasetStore>>, files: &DatasetFiles) -> Result<Self, DatasetError> {
        let read_file = |path: &Path| store::read_file(store, path);
        let textures = TexturePack::open_files_in(store, files)?;
        let colormap_path = files.path(COLORMAP_FILE);
        let (colormap, write_id) =
            Colormap::decode_with_write_id(&colormap_path, &read_file(&colormap_path)?, files.version())?;
        files.check_write_id(&colormap_path, write_id)?;
        if colormap.len() != textures.textures().len() {
            return Err(DatasetError::Corrupt {
                path: colormap_path,
                offset: 24,
                what: format!("{} colours for {} textures", colormap.len(), textures.len()),
            });
        }
        let scene_path = files.path(SCENE_FILE);
        let scene_bytes = read_file(&scene_path)?;
        let layout = if files.version() == io_util::PREVIOUS_VERSION {
            scene::SceneLayout::PREVIOUS
        } else {
            scene::SceneLayout::CURRENT
        };
        let (scene, write_id) = Scene::decode_with(&scene_path, &scene_bytes, layout)?;
        files.check_write_id(&scene_path, write_id)?;
        let count = textures.len();
        if let Some((m, mesh)) = scene.meshes.iter().enumerate().find(|(_, m)| m.texture >= count) {
            return Err(DatasetError::Corrupt {
                path: scene_path,
                offset: scene.mesh_record_offset(layout, m) + 16,
                what: format!(
                    "mesh {m} uses texture {}, but the dataset has {count} textures",
                    mesh.texture
                ),
            });
        }
        Ok(Self {
            files: files.clone(),
            store: store.cloned(),
            scene,
            textures,
            colormap,
            scene_file_len: scene_bytes.len() as u64,
        })
    }

    /// Another file of the opened write's directory (beside the five of the format, e.g. an
    /// atlas tree's `atlas-tree.bin`), whole, from wherever the dataset was opened; `None`
    /// where the write has no such file.
    pub fn read_write_file(&self, name: &str) -> Result<Option<Vec<u8>>, DatasetError> {
        let path = self.files.path(name);
        if self.store.is_none() && !path.exists() {
            return Ok(None);
        }
        match store::read_file(self.store.as_ref(), &path) {
            Ok(bytes) => Ok(Some(bytes)),
            Err(DatasetError::Missing { .. }) => Ok(None),
            Err(e) => Err(e),
        }
    }

    /// Bytes of the scene file as it was read.
    pub fn scene_file_len(&self) -> u64 {
        self.scene_file_len
    }

    /// The dataset directory.
    pub fn dir(&self) -> &Path {
        self.files.dir()
    }

    /// Where the opened write's files are.
    pub fn files(&self) -> &DatasetFiles {
        &self.files
    }

    /// Host bytes per texture of the opened metadata (texture record, index of its first mip
    /// checksum, colormap entry), excluding the scene geometry and the per-mip checksums
    /// ([`Dataset::metadata_bytes_per_mip`]).
    pub fn metadata_bytes_per_texture() -> usize {
        std::mem::size_of::<TextureInfo>() + std::mem::size_of::<u32>() + std::mem::size_of::<[u8; 4]>()
    }

    /// Host bytes per mip of the opened metadata: its CRC-32.
    pub fn metadata_bytes_per_mip() -> usize {
        std::mem::size_of::<u32>()
    }
}
