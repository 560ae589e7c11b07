//! citystream's on-disk city: the dataset format (scene file, texture pack with per-mip byte
//! ranges, colormap), its atomic writes and checked reads, upgrades from older formats, the
//! on-disk mip cache, and (feature `remote`, module `remote`) the same datasets over HTTP or
//! S3. No Vulkan and no streaming policy: `citystream-streaming`'s loader reads through it.
//!
//! Modules, private behind the re-exports below: `dataset` (an opened [`Dataset`]), `scene`,
//! `pack`, `colormap` and `format` (the files and their records; `format` also holds the
//! format version), `crs` (the coordinate reference system a scene names), `files` and
//! `writer` (the file names, the manifest, write directories and atomic replacement),
//! `store` (where a dataset's bytes live: a directory or a remote store), `shard` (the record
//! naming a shard of a sharded build, and one dataset's files joined from shards), `verify` (every
//! mip checked), `legacy` (upgrades from formats 1 and 2), `mip_cache` (remote mips kept on
//! disk), `io_util` and `error`. Each constant lives in the module that uses it and is
//! re-exported here, so no module imports from this root.
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
mod dataset;
mod error;
mod files;
mod format;
mod io_util;
mod legacy;
mod mip_cache;
mod pack;
mod scene;
mod shard;
mod store;
pub mod tile_geometry;
pub mod tiled;
pub mod tiles;
pub mod tiling;
mod verify;
mod writer;

#[cfg(feature = "remote")]
pub mod remote;

pub use colormap::Colormap;
pub use crs::{Crs, CrsError, MAX_CRS_BYTES};
pub use dataset::Dataset;
pub use error::{DatasetError, Magic};
pub use files::{
    fresh_write_id, looks_like_url, manifest_bytes, write_dir_name, DatasetFiles, CHECKSUM_FILE, COLORMAP_FILE,
    DATASET_FILES, GEOMETRY_CRC_FILE, GEOMETRY_PACK_FILE, MANIFEST_FILE, META_FILE, PACK_FILE, SCENE_FILE, TILES_FILE,
};
pub use format::{full_mip_count, TextureFormat, TextureInfo, FORMAT_VERSION, MAX_EXTENT_LOG2, MAX_PACK_OFFSET};
pub use io_util::ensure_regular_file;
pub use legacy::{upgrade, UpgradeSummary};
pub use mip_cache::{CacheNamespace, MipCache, MipCacheStats};
pub use pack::{MipLocation, TexturePack, PACK_HEADER_BYTES};
pub use scene::{Aabb, Mesh, Scene};
pub use shard::{part_pack_body, JoinedTables, ShardRecord, MAX_SHARDS, SHARDS_DIR, SHARD_RECORD_FILE};
pub use store::DatasetStore;
pub use verify::{verify, verify_dataset, VerifyReport};
pub use writer::{DatasetWriter, WriteSummary};
