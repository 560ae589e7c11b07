//! On-disk city dataset format: scene file, texture pack with per-mip byte ranges, colormap.
//!
//! A dataset is a directory of five files (format version [`FORMAT_VERSION`], all
//! little-endian, specified in `docs/DATASET.md`):
//!
//! - `scene.bin` ([`Scene`]): meshes (one texture each), flat vertex and index arrays,
//!   per-mesh and scene bounds, positions relative to an f64 origin.
//! - `textures.meta` ([`TextureInfo`], 10 bytes per texture): extent as log2, mip count,
//!   format and the offset of the texture's first mip in the pack. Per-mip offsets are
//!   derived: mips lie back to back, level 0 (finest) first.
//! - `textures.pack`: every mip of every texture, so a loader reads exactly one mip with one
//!   positioned read ([`TexturePack::read_mip`]) and never a whole texture (paper §3.5).
//! - `colormap.bin` ([`Colormap`]): mean colour per texture, the City Colormap (paper §3.7).
//! - `textures.crc`: CRC-32 per mip chain, read only by [`verify`].
//!
//! Contracts:
//! - Opening ([`Dataset::open`], [`TexturePack::open`]) reads the scene and the tables but
//!   no mip data, and validates everything a renderer relies on (sizes, checksums of the
//!   tables and scene, texture extents and offsets inside the pack, mesh ranges, indices,
//!   finite attributes). After a successful open, every `(texture, level)` pair below
//!   [`TextureInfo::mip_count`] maps to a byte range inside the pack.
//! - Every failure is a [`DatasetError`] naming the file and the offset or index at fault;
//!   no input makes this module panic or read out of bounds.
//! - Textures are powers of two per side; block-compressed ones are at least 4×4 at level 0.
//!   Mips of block formats smaller than 4 texels on a side still occupy whole 4×4 blocks.

mod colormap;
mod error;
mod format;
mod io_util;
mod pack;
mod scene;
mod verify;
mod writer;

use std::path::{Path, PathBuf};

pub use colormap::Colormap;
pub use error::{DatasetError, Magic};
pub use format::{full_mip_count, TextureFormat, TextureInfo, MAX_EXTENT_LOG2, MAX_PACK_OFFSET};
pub use io_util::ensure_regular_file;
pub use pack::{MipLocation, TexturePack, PACK_HEADER_BYTES};
pub use scene::{Aabb, Mesh, Scene};
pub use verify::{verify, VerifyReport};
pub use writer::{DatasetWriter, WriteSummary};

/// The format version this build reads and writes.
pub const FORMAT_VERSION: u32 = 1;
/// Scene file name inside a dataset directory.
pub const SCENE_FILE: &str = "scene.bin";
/// Texture metadata file name.
pub const META_FILE: &str = "textures.meta";
/// Texture pack file name.
pub const PACK_FILE: &str = "textures.pack";
/// City Colormap file name.
pub const COLORMAP_FILE: &str = "colormap.bin";
/// Per-texture checksum file name.
pub const CHECKSUM_FILE: &str = "textures.crc";

/// An opened dataset: the scene, the texture table with an open pack, and the colormap.
///
/// Threading: `Send + Sync`; see [`TexturePack`] for concurrent mip reads.
#[derive(Debug)]
pub struct Dataset {
    dir: PathBuf,
    /// All meshes and geometry.
    pub scene: Scene,
    /// Texture metadata and mip reads.
    pub textures: TexturePack,
    /// Mean colour per texture.
    pub colormap: Colormap,
}

impl Dataset {
    /// Opens the dataset in `dir`: reads and validates `scene.bin`, `textures.meta`,
    /// `colormap.bin` and the header of `textures.pack`, and checks they agree (every mesh's
    /// texture exists, one colour per texture). Reads no mip data.
    pub fn open(dir: impl AsRef<Path>) -> Result<Self, DatasetError> {
        let dir = dir.as_ref();
        let textures = TexturePack::open(dir)?;
        let colormap_path = dir.join(COLORMAP_FILE);
        let colormap = Colormap::read(&colormap_path)?;
        if colormap.len() != textures.textures().len() {
            return Err(DatasetError::Corrupt {
                path: colormap_path,
                offset: 16,
                what: format!("{} colours for {} textures", colormap.len(), textures.len()),
            });
        }
        let scene_path = dir.join(SCENE_FILE);
        let scene = Scene::read(&scene_path)?;
        let count = textures.len();
        if let Some((m, mesh)) = scene.meshes.iter().enumerate().find(|(_, m)| m.texture >= count) {
            return Err(DatasetError::Corrupt {
                path: scene_path,
                offset: 96 + m as u64 * 44 + 16,
                what: format!(
                    "mesh {m} uses texture {}, but the dataset has {count} textures",
                    mesh.texture
                ),
            });
        }
        Ok(Self {
            dir: dir.to_path_buf(),
            scene,
            textures,
            colormap,
        })
    }

    /// The dataset directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Host bytes per texture of the opened metadata (texture table + colormap entry),
    /// excluding the scene geometry.
    pub fn metadata_bytes_per_texture() -> usize {
        std::mem::size_of::<TextureInfo>() + std::mem::size_of::<[u8; 4]>()
    }
}
