//! The concurrent sparse-image texture cache (paper §3.6).
//!
//! [`TextureCache`] is defined here with its construction and look-ups; its
//! other methods are split by concern into submodules, each an
//! `impl TextureCache` block over the state in `state`:
//! - `types`: what the cache hands out and reports ([`Placement`],
//!   [`CycleBatch`], [`Utilisation`], ...), re-exported here;
//! - `state`: the per-image, per-layer and shared state behind the locks;
//! - `insert`: packing textures into layers by extent, assigning layers in
//!   ring order;
//! - `evict`: layer eviction (ring reuse, budget, caller's choice);
//! - `stage`: binding the blocks a staged mip touches within the budget, and
//!   dropping staged mips;
//! - `batch`: the per-cycle [`CycleBatch`] and the accounting queries.

mod batch;
mod evict;
mod insert;
mod stage;
mod state;
mod types;

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicU32, AtomicU64};
use std::sync::Mutex;

use crate::binder::BlockKey;
use crate::config::{CacheConfig, ImageDesc};
use crate::error::{CacheError, ConfigError};
use crate::format::TexelFormat;
use crate::pool::BlockPool;

pub(crate) use stage::rect_blocks;
use state::{lock, pack, ImageState, LayerState, Padded, Shared, NO_ASSIGNMENT};
pub use types::{
    BudgetUse, CacheStats, CycleBatch, EvictedLayer, EvictionReason, ImageId, MipUpload, Placement, Utilisation,
};

/// The sparse-image texture cache: packing, block accounting, memory
/// budget and ring eviction for every configured image.
///
/// # Threading contract
/// `TextureCache` is `Sync`; share it by reference or `Arc`.
/// - [`insert`](Self::insert) may run on any number of threads at once. Its
///   fast path is one atomic `fetch_add` on the extent's slot and one
///   uncontended per-layer lock; only assigning a new layer (including ring
///   eviction) takes the shared lock.
/// - [`stage_mip`](Self::stage_mip), [`take_batch`](Self::take_batch),
///   [`utilisation`](Self::utilisation) and the queries may also be called
///   from any thread; they serialise on the shared lock.
/// - Locks are always taken shared-then-layer and at most one layer lock at
///   a time, so there is no lock-order cycle.
#[derive(Debug)]
pub struct TextureCache {
    images: Vec<ImageState>,
    shared: Mutex<Shared>,
}

impl TextureCache {
    /// Creates the cache after validating `config` (see
    /// [`CacheConfig::validate`]).
    pub fn new(config: &CacheConfig) -> Result<Self, ConfigError> {
        let descs = config.validate()?;
        let images: Vec<ImageState> = descs
            .into_iter()
            .map(|desc| {
                let layer_count = desc.layer_count;
                ImageState {
                    slots: (0..desc.mip_levels)
                        .map(|_| Padded(AtomicU64::new(pack(NO_ASSIGNMENT, 0))))
                        .collect(),
                    layers: (0..layer_count)
                        .map(|_| Padded(Mutex::new(LayerState::default())))
                        .collect(),
                    next_assignment: AtomicU32::new(0),
                    assignment_modulus: layer_count * ((u32::MAX - 1) / layer_count),
                    desc,
                }
            })
            .collect();
        let budget_blocks = config.budget_blocks();
        let mut shared = Shared {
            live: images.iter().map(|_| VecDeque::new()).collect(),
            next_age: 0,
            pool: BlockPool::new(config.limits.sparse_block_bytes, config.blocks_per_chunk, budget_blocks),
            budget_blocks,
            live_blocks: 0,
            pending_binds: HashMap::new(),
            parked: HashMap::new(),
            next_park: 0,
            memory_shortfall: 0,
            wanted_back: std::collections::HashSet::new(),
            invalidated: Vec::new(),
            evicted: Vec::new(),
            new_chunks: Vec::new(),
            stats: CacheStats::default(),
            single_tails: Vec::new(),
        };
        // Single tails hold every layer's small levels at once: bound with
        // the first batch, before any copy, and never released.
        for image in &images {
            for index in 0..image.desc.single_tail_blocks() as u32 {
                let shared = &mut shared;
                let memory = shared
                    .pool
                    .allocate(&mut shared.new_chunks)
                    .ok_or(ConfigError::TailsOverBudget {
                        tail_bytes: image.desc.tail_bytes(),
                        budget_bytes: config.memory_budget_bytes,
                    })?;
                let key = BlockKey::tail(image.desc.image, 0, index);
                shared.pending_binds.insert(key, memory);
                shared.live_blocks += 1;
                shared.single_tails.push((key, memory));
            }
        }
        shared.stats.chunks = shared.pool.chunk_count();
        Ok(TextureCache {
            images,
            shared: Mutex::new(shared),
        })
    }

    /// The validated images, indexed by [`ImageId`]; the engine creates one
    /// sparse 2D-array image from each (`layer_size`², `layer_count`
    /// layers, `mip_levels` levels).
    pub fn images(&self) -> Vec<ImageDesc> {
        self.images.iter().map(|image| image.desc).collect()
    }

    /// The first image that caches textures of `format`, if one is configured.
    pub fn image_for_format(&self, format: &TexelFormat) -> Option<ImageId> {
        self.images
            .iter()
            .find(|image| image.desc.format == *format)
            .map(|image| image.desc.image)
    }

    /// Every image that caches textures of `format`, in index order (more
    /// than one where one image's layers could not hold the format's share).
    pub fn images_for_format(&self, format: &TexelFormat) -> Vec<ImageId> {
        self.images
            .iter()
            .filter(|image| image.desc.format == *format)
            .map(|image| image.desc.image)
            .collect()
    }

    fn image(&self, image: ImageId) -> Result<&ImageState, CacheError> {
        self.images.get(image as usize).ok_or(CacheError::UnknownImage {
            image,
            images: self.images.len(),
        })
    }

    /// Whether `placement` is still live (its layer not evicted since).
    pub fn is_live(&self, placement: &Placement) -> bool {
        let Ok(state) = self.image(placement.image) else {
            return false;
        };
        let Some(layer) = state.layers.get(placement.layer as usize) else {
            return false;
        };
        let layer = lock(layer);
        layer.assignment == Some(placement.assignment)
            && layer
                .textures
                .get(placement.region as usize)
                .is_some_and(Option::is_some)
    }
}
