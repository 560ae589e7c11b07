//! Sparse-image texture cache (paper §3.6). Vulkan-free.
//!
//! Textures are cached at run time in one sparse 2D-array image per texel
//! format. Each layer is designated for one texture extent
//! `max(width, height)` and holds square regions of that extent, filled
//! left to right, top to bottom, one texture per region; all sizes are
//! powers of two, so every mip of every texture stays aligned and a single
//! [`UvTransform`] per texture is valid at every cached mip.
//!
//! Contracts:
//! - [`TextureCache::insert`] is safe from many threads at once (atomic
//!   region claims; a lock only when a layer is assigned). When every layer
//!   is assigned, the oldest layer in ring order is reused and its textures
//!   are invalidated.
//! - [`TextureCache::stage_mip`] binds, once per block, every sparse block a
//!   staged mip touches, within a memory budget of bound bytes; reaching the
//!   budget evicts the oldest layer first. Levels in a device's mip tail
//!   ([`MipTail`]) are bound as a whole: a per-layer tail is a few blocks
//!   keyed at [`BlockKey::TAIL_LEVEL`], accounted, parked and reclaimed like
//!   any block; a single tail is bound once, from the budget, for good. Blocks no live texture uses any
//!   more stay bound ("parked") until staging needs their memory.
//! - [`TextureCache::take_batch`] hands the engine one [`CycleBatch`] per
//!   streaming cycle: at most one [`BindOp`] per block, unbinds before
//!   binds, the invalidated textures, and the pool chunks to allocate;
//!   it unbinds parked blocks only as far as staging lacked memory.
//! - The paper's concurrent map extent → (layer, index) is a dense array
//!   indexed by `log2(extent)` of atomics packing (assignment, next region);
//!   `nextLayer` is the per-image assignment counter, and layer =
//!   assignment mod layer count gives the ring order.
//! - Safe unloading is the engine's half: per cycle it marks the batch's
//!   invalidated textures not sampleable, allocates new chunks, waits until
//!   no frame in flight can sample the invalidated textures, submits the ops
//!   to its [`SparseBinder`], then copies the staged mips to
//!   [`MipUpload::rect`].
//! - Granularity and block size come from the device ([`DeviceLimits`],
//!   [`Granularity::from_device_report`]); nothing about them is assumed.
#![forbid(unsafe_code)]

pub mod bind_check;
pub mod binder;
pub mod cache;
pub mod config;
pub mod error;
pub mod estimate;
pub mod format;
pub mod geometry;
pub mod pool;

pub use bind_check::{BindChecker, BindViolation, ImageShape};
pub use binder::{BindError, BindOp, BindReport, BlockKey, MemorySlot, SparseBinder};
pub use cache::{
    BudgetUse, CacheStats, CycleBatch, EvictedLayer, EvictionReason, ImageId, MipUpload, Placement, TextureCache,
    Utilisation,
};
pub use config::{
    derive_image_layers, layers_to_place, CacheConfig, ImageConfig, ImageDemand, ImageDesc, MipTail, MAX_LAYER_SIZE,
};
pub use error::{CacheError, ConfigError};
pub use estimate::{estimate_utilisation, UtilisationEstimate};
pub use format::{DeviceLimits, Granularity, GranularityUnit, TexelFormat};
pub use geometry::{TexelRect, UvTransform};
pub use pool::{BlockPool, ChunkInfo};
