//! The cache's internal state: per-image slots and layers, the shared state
//! behind the one shared lock, and the helpers every operation uses on them
//! (slot packing, poison-free locking, releasing a block). Private to the
//! cache module; its submodules operate on it.

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicU32, AtomicU64};
use std::sync::{Mutex, MutexGuard};

use super::types::{CacheStats, EvictedLayer, Placement};
use crate::binder::{BlockKey, MemorySlot};
use crate::config::ImageDesc;
use crate::geometry::{cacheable_mip_count, region_origin, UvTransform};
use crate::pool::{BlockPool, ChunkInfo};

/// Slot value of an extent that has no layer yet.
pub(super) const NO_ASSIGNMENT: u32 = u32::MAX;

pub(super) fn pack(assignment: u32, region: u32) -> u64 {
    (u64::from(assignment) << 32) | u64::from(region)
}

pub(super) fn unpack(value: u64) -> (u32, u32) {
    ((value >> 32) as u32, value as u32)
}

/// Locks ignoring poisoning: every critical section leaves its state
/// consistent before anything that could panic, so a poisoned lock only
/// means some other thread panicked elsewhere.
pub(super) fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

#[derive(Debug)]
pub(super) struct TextureRecord {
    pub(super) key: u64,
    pub(super) width: u32,
    pub(super) height: u32,
    /// Bit `m` set once mip `m` was staged.
    pub(super) staged_mips: u32,
}

/// A bound block and how many staged texture mips lie on it, so that
/// dropping one texture's level frees only the blocks no other mip uses.
#[derive(Clone, Copy, Debug)]
pub(super) struct BoundBlock {
    pub(super) memory: MemorySlot,
    pub(super) users: u32,
}

#[derive(Debug, Default)]
pub(super) struct LayerState {
    /// Current assignment; `None` while free.
    pub(super) assignment: Option<u32>,
    pub(super) extent: u32,
    /// Indexed by region; regions are claimed in order, so this is dense.
    pub(super) textures: Vec<Option<TextureRecord>>,
    pub(super) texture_count: u64,
    /// Bound blocks keyed by (mip, column, row).
    pub(super) blocks: HashMap<(u32, u32, u32), BoundBlock>,
    pub(super) texture_bytes: u64,
}

impl LayerState {
    /// Blocks of the layer's mip tail bound now.
    pub(super) fn tail_blocks(&self) -> u64 {
        self.blocks
            .keys()
            .filter(|(mip, _, _)| *mip == BlockKey::TAIL_LEVEL)
            .count() as u64
    }
}

/// Keeps each hot atomic or lock on its own cache line so threads working
/// on different extents or layers do not slow each other down.
#[derive(Debug, Default)]
#[repr(align(64))]
pub(super) struct Padded<T>(pub(super) T);

impl<T> std::ops::Deref for Padded<T> {
    type Target = T;
    fn deref(&self) -> &T {
        &self.0
    }
}

#[derive(Debug)]
pub(super) struct ImageState {
    pub(super) desc: ImageDesc,
    /// Per `log2(extent)`: the paper's map extent → (layer, index), packed
    /// as (assignment number, next region index) so one `fetch_add` claims a
    /// region of the current layer.
    pub(super) slots: Vec<Padded<AtomicU64>>,
    pub(super) layers: Vec<Padded<Mutex<LayerState>>>,
    /// The paper's `nextLayer`: the next assignment number. Layer =
    /// assignment % layer_count, so assignments walk the layers in ring
    /// order. Written only under the shared lock.
    pub(super) next_assignment: AtomicU32,
    /// Assignment numbers wrap at a multiple of the layer count below
    /// `NO_ASSIGNMENT`.
    pub(super) assignment_modulus: u32,
}

#[derive(Clone, Copy, Debug)]
pub(super) struct LiveLayer {
    pub(super) layer: u32,
    pub(super) assignment: u32,
    /// Global age over all images, for budget eviction.
    pub(super) age: u64,
}

#[derive(Debug)]
pub(super) struct Shared {
    /// Per image, live layers oldest first (ring order).
    pub(super) live: Vec<VecDeque<LiveLayer>>,
    pub(super) next_age: u64,
    pub(super) pool: BlockPool,
    pub(super) budget_blocks: u64,
    /// Blocks bound in live layers (including binds not yet submitted).
    pub(super) live_blocks: u64,
    /// Binds not yet handed out in a batch.
    pub(super) pending_binds: HashMap<BlockKey, MemorySlot>,
    /// Blocks no live texture uses any more (of evicted layers, or dropped
    /// levels) whose bind was submitted: they stay bound, holding their
    /// memory, until a batch needs the memory ([`TextureCache::take_batch`]
    /// unbinds the oldest first) or a mip staged on the same block takes
    /// them back without a bind.
    ///
    /// [`TextureCache::take_batch`]: super::TextureCache::take_batch
    pub(super) parked: HashMap<BlockKey, ParkedBlock>,
    /// Order in which blocks were parked, for oldest-first unbinding.
    pub(super) next_park: u64,
    /// Blocks that staging found no memory for since the last batch
    /// ([`CacheError::MemoryPending`]): the next batch unbinds that many
    /// parked blocks.
    ///
    /// [`CacheError::MemoryPending`]: crate::error::CacheError::MemoryPending
    pub(super) memory_shortfall: u64,
    /// Parked blocks a mip that met [`CacheError::MemoryPending`] takes back
    /// when it is staged again: the next batch does not unbind them to make
    /// room (that would leave the retry short again).
    ///
    /// [`CacheError::MemoryPending`]: crate::error::CacheError::MemoryPending
    pub(super) wanted_back: std::collections::HashSet<BlockKey>,
    pub(super) invalidated: Vec<Placement>,
    pub(super) evicted: Vec<EvictedLayer>,
    pub(super) new_chunks: Vec<ChunkInfo>,
    pub(super) stats: CacheStats,
    /// Blocks of the images' single mip tails and their memory, bound for
    /// good (counted in `live_blocks`).
    pub(super) single_tails: Vec<(BlockKey, MemorySlot)>,
}

/// A block bound for no live texture, still holding its memory.
#[derive(Clone, Copy, Debug)]
pub(super) struct ParkedBlock {
    pub(super) memory: MemorySlot,
    /// When it was parked ([`Shared::next_park`]).
    pub(super) since: u64,
}

/// Returns a block's memory: to the pool at once if its bind was never
/// handed out, else it parks, bound, until a batch needs its memory.
pub(super) fn release_block(shared: &mut Shared, key: BlockKey, memory: MemorySlot) {
    if shared.pending_binds.remove(&key).is_some() {
        // Never submitted: nothing to unbind.
        shared.pool.free(memory);
    } else {
        let since = shared.next_park;
        shared.next_park += 1;
        shared.parked.insert(key, ParkedBlock { memory, since });
    }
}

pub(super) fn placement_of(
    desc: &ImageDesc,
    layer_index: u32,
    assignment: u32,
    region: u32,
    extent: u32,
    record: &TextureRecord,
) -> Placement {
    let (origin_x, origin_y) = region_origin(desc.layer_size, extent, region);
    Placement {
        key: record.key,
        image: desc.image,
        format: desc.format,
        layer: layer_index,
        region,
        assignment,
        width: record.width,
        height: record.height,
        extent,
        origin_x,
        origin_y,
        layer_size: desc.layer_size,
        mip_count: cacheable_mip_count(&desc.format, record.width, record.height),
        uv: UvTransform::new(desc.layer_size, origin_x, origin_y, record.width, record.height),
    }
}
