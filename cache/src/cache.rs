//! The concurrent sparse-image texture cache (paper §3.6).

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard};

use crate::binder::{BindOp, BlockKey, MemorySlot};
use crate::config::{CacheConfig, ImageDesc};
use crate::error::{CacheError, ConfigError};
use crate::format::TexelFormat;
use crate::geometry::{cacheable_mip_count, region_origin, TexelRect, UvTransform};
use crate::pool::{BlockPool, ChunkInfo};

/// Index of a sparse image of the cache (one per format).
pub type ImageId = u32;

/// Where a texture lives in the cache. Returned by
/// [`TextureCache::insert`]; valid until its layer is evicted (then it is
/// listed in [`CycleBatch::invalidated`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Placement {
    /// The caller's key for the texture, reported back on invalidation.
    pub key: u64,
    /// Sparse image (format) index.
    pub image: ImageId,
    /// The image's texel format.
    pub format: TexelFormat,
    /// Array layer.
    pub layer: u32,
    /// Square region index within the layer (left to right, top to bottom).
    pub region: u32,
    /// Which use of the layer this is; a layer gets a new assignment number
    /// each time it is (re)assigned, so stale placements are detectable.
    pub assignment: u32,
    /// Texture width in texels at mip 0.
    pub width: u32,
    /// Texture height in texels at mip 0.
    pub height: u32,
    /// The layer's designated extent, `max(width, height)`.
    pub extent: u32,
    /// Region origin (left) in texels of level 0.
    pub origin_x: u32,
    /// Region origin (top) in texels of level 0.
    pub origin_y: u32,
    /// Layer size in texels of level 0.
    pub layer_size: u32,
    /// Mips the cache can hold for this texture (see
    /// [`crate::geometry::cacheable_mip_count`]); texture mip `m` goes to level
    /// `m` of the layer.
    pub mip_count: u32,
    /// Texture UV to layer UV, valid at every cacheable mip.
    pub uv: UvTransform,
}

impl Placement {
    /// The texel rectangle of texture mip `mip` inside level `mip` of the
    /// layer: the `imageOffset`/`imageExtent` of its buffer-to-image copy.
    pub fn mip_rect(&self, mip: u32) -> Result<TexelRect, CacheError> {
        if mip >= self.mip_count {
            return Err(CacheError::BadMip {
                format: self.format.name,
                width: self.width,
                height: self.height,
                mip,
                mip_count: self.mip_count,
            });
        }
        Ok(TexelRect::of_mip(
            self.origin_x,
            self.origin_y,
            self.width,
            self.height,
            mip,
        ))
    }
}

/// Why a layer was evicted.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum EvictionReason {
    /// Every layer was assigned; the oldest in ring order was reused.
    RingReuse,
    /// Binding more blocks would have exceeded the memory budget.
    MemoryBudget,
    /// The caller chose the layer ([`TextureCache::evict_layer`]).
    Chosen,
}

/// A layer eviction, as reported in [`CycleBatch::evicted_layers`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct EvictedLayer {
    /// Sparse image index.
    pub image: ImageId,
    /// Array layer.
    pub layer: u32,
    /// The assignment that ended.
    pub assignment: u32,
    /// Extent the layer was designated for.
    pub extent: u32,
    /// Why.
    pub reason: EvictionReason,
    /// Textures invalidated.
    pub textures: u32,
    /// Blocks the layer had bound.
    pub blocks: u32,
}

/// What the engine must carry out after a streaming cycle.
///
/// Order of work for the engine: mark every texture in `invalidated` as not
/// sampleable in the texture data the shaders read; allocate device memory
/// for every chunk in `new_chunks`; once the GPU has finished every frame
/// that could still sample the invalidated textures, submit `ops` through a
/// [`crate::SparseBinder`]; then record the copies of the staged mips.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CycleBatch {
    /// Unbinds first (parked blocks whose memory staging needs: see
    /// [`TextureCache::take_batch`]), then binds (blocks newly needed by
    /// staged mips), each sorted by block key. Every block appears
    /// at most once; a memory slot freed by an unbind in this batch is never
    /// rebound in the same batch.
    pub ops: Vec<BindOp>,
    /// Textures whose layer was evicted since the last batch, in eviction
    /// order; each must be inserted again before it is loaded again.
    pub invalidated: Vec<Placement>,
    /// The evictions themselves.
    pub evicted_layers: Vec<EvictedLayer>,
    /// Pool chunks created since the last batch.
    pub new_chunks: Vec<ChunkInfo>,
}

impl CycleBatch {
    /// Nothing to do: no op, no invalidation, no eviction, no new chunk.
    pub fn is_empty(&self) -> bool {
        self.ops.is_empty()
            && self.invalidated.is_empty()
            && self.evicted_layers.is_empty()
            && self.new_chunks.is_empty()
    }
}

/// What [`TextureCache::stage_mip`] tells the loader.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MipUpload {
    /// Sparse image index.
    pub image: ImageId,
    /// Array layer (`imageSubresource.baseArrayLayer`).
    pub layer: u32,
    /// Destination texels; `rect.mip` is `imageSubresource.mipLevel`.
    pub rect: TexelRect,
    /// Bytes of the mip's texel data in the image's format.
    pub bytes: u64,
    /// Blocks this request added to its layer's bound set: new binds plus
    /// parked blocks taken back (those keep their memory and binding and
    /// need no bind). Zero when every block
    /// was already bound.
    pub new_blocks: u32,
    /// The mip had been staged before in this placement.
    pub already_staged: bool,
}

/// Texture bytes against bound bytes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Utilisation {
    /// Bytes of staged texture mips of live textures.
    pub texture_bytes: u64,
    /// Bytes of sparse blocks bound for live layers.
    pub bound_bytes: u64,
    /// Bound blocks of live layers.
    pub bound_blocks: u64,
    /// Textures in live layers.
    pub live_textures: u64,
    /// Layers holding an assignment.
    pub live_layers: u64,
    /// Blocks still bound, with their memory, that no live texture uses
    /// (see [`TextureCache::take_batch`]).
    pub parked_blocks: u64,
    /// Bytes of those blocks.
    pub parked_bytes: u64,
    /// Blocks of mip tails held: of live layers, parked, and single tails
    /// (these count in `bound_blocks` too: they are bound for good).
    pub tail_blocks: u64,
    /// Bytes of those blocks.
    pub tail_bytes: u64,
}

impl Utilisation {
    /// Device memory bound to the cache's images: live and parked blocks.
    pub fn held_bytes(&self) -> u64 {
        self.bound_bytes + self.parked_bytes
    }

    /// `texture_bytes / bound_bytes`, 0 when nothing is bound.
    pub fn ratio(&self) -> f64 {
        if self.bound_bytes == 0 {
            0.0
        } else {
            self.texture_bytes as f64 / self.bound_bytes as f64
        }
    }
}

/// Running counts since creation.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CacheStats {
    /// Layer assignments (the paper's `nextLayer` advances, all images).
    pub layer_assignments: u64,
    /// Evictions for ring reuse.
    pub ring_evictions: u64,
    /// Evictions for the memory budget.
    pub budget_evictions: u64,
    /// Layers evicted by [`TextureCache::evict_layer`].
    pub chosen_evictions: u64,
    /// Textures invalidated by evictions.
    pub invalidated_textures: u64,
    /// Chunks the block pool created.
    pub chunks: u32,
    /// Texture mips dropped by [`TextureCache::drop_mip`].
    pub dropped_mips: u64,
    /// Blocks those drops released.
    pub dropped_blocks: u64,
}

/// Bound blocks against the budget.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct BudgetUse {
    /// Blocks bound for live layers, binds not yet handed out included.
    pub live_blocks: u64,
    /// The budget in blocks.
    pub budget_blocks: u64,
}

impl BudgetUse {
    /// Blocks that can still be bound within the budget.
    pub fn free_blocks(&self) -> u64 {
        self.budget_blocks.saturating_sub(self.live_blocks)
    }
}

/// Slot value of an extent that has no layer yet.
const NO_ASSIGNMENT: u32 = u32::MAX;

fn pack(assignment: u32, region: u32) -> u64 {
    (u64::from(assignment) << 32) | u64::from(region)
}

fn unpack(value: u64) -> (u32, u32) {
    ((value >> 32) as u32, value as u32)
}

/// Locks ignoring poisoning: every critical section leaves its state
/// consistent before anything that could panic, so a poisoned lock only
/// means some other thread panicked elsewhere.
fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

#[derive(Debug)]
struct TextureRecord {
    key: u64,
    width: u32,
    height: u32,
    /// Bit `m` set once mip `m` was staged.
    staged_mips: u32,
}

/// A bound block and how many staged texture mips lie on it, so that
/// dropping one texture's level frees only the blocks no other mip uses.
#[derive(Clone, Copy, Debug)]
struct BoundBlock {
    memory: MemorySlot,
    users: u32,
}

#[derive(Debug, Default)]
struct LayerState {
    /// Current assignment; `None` while free.
    assignment: Option<u32>,
    extent: u32,
    /// Indexed by region; regions are claimed in order, so this is dense.
    textures: Vec<Option<TextureRecord>>,
    texture_count: u64,
    /// Bound blocks keyed by (mip, column, row).
    blocks: HashMap<(u32, u32, u32), BoundBlock>,
    texture_bytes: u64,
}

impl LayerState {
    /// Blocks of the layer's mip tail bound now.
    fn tail_blocks(&self) -> u64 {
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
struct Padded<T>(T);

impl<T> std::ops::Deref for Padded<T> {
    type Target = T;
    fn deref(&self) -> &T {
        &self.0
    }
}

#[derive(Debug)]
struct ImageState {
    desc: ImageDesc,
    /// Per `log2(extent)`: the paper's map extent → (layer, index), packed
    /// as (assignment number, next region index) so one `fetch_add` claims a
    /// region of the current layer.
    slots: Vec<Padded<AtomicU64>>,
    layers: Vec<Padded<Mutex<LayerState>>>,
    /// The paper's `nextLayer`: the next assignment number. Layer =
    /// assignment % layer_count, so assignments walk the layers in ring
    /// order. Written only under the shared lock.
    next_assignment: AtomicU32,
    /// Assignment numbers wrap at a multiple of the layer count below
    /// `NO_ASSIGNMENT`.
    assignment_modulus: u32,
}

#[derive(Clone, Copy, Debug)]
struct LiveLayer {
    layer: u32,
    assignment: u32,
    /// Global age over all images, for budget eviction.
    age: u64,
}

#[derive(Debug)]
struct Shared {
    /// Per image, live layers oldest first (ring order).
    live: Vec<VecDeque<LiveLayer>>,
    next_age: u64,
    pool: BlockPool,
    budget_blocks: u64,
    /// Blocks bound in live layers (including binds not yet submitted).
    live_blocks: u64,
    /// Binds not yet handed out in a batch.
    pending_binds: HashMap<BlockKey, MemorySlot>,
    /// Blocks no live texture uses any more (of evicted layers, or dropped
    /// levels) whose bind was submitted: they stay bound, holding their
    /// memory, until a batch needs the memory ([`TextureCache::take_batch`]
    /// unbinds the oldest first) or a mip staged on the same block takes
    /// them back without a bind.
    parked: HashMap<BlockKey, ParkedBlock>,
    /// Order in which blocks were parked, for oldest-first unbinding.
    next_park: u64,
    /// Blocks that staging found no memory for since the last batch
    /// ([`CacheError::MemoryPending`]): the next batch unbinds that many
    /// parked blocks.
    memory_shortfall: u64,
    /// Parked blocks a mip that met [`CacheError::MemoryPending`] takes back
    /// when it is staged again: the next batch does not unbind them to make
    /// room (that would leave the retry short again).
    wanted_back: std::collections::HashSet<BlockKey>,
    invalidated: Vec<Placement>,
    evicted: Vec<EvictedLayer>,
    new_chunks: Vec<ChunkInfo>,
    stats: CacheStats,
    /// Blocks of the images' single mip tails and their memory, bound for
    /// good (counted in `live_blocks`).
    single_tails: Vec<(BlockKey, MemorySlot)>,
}

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

    /// Places a `width`×`height` texture (powers of two, at most the layer
    /// size, at least one texel block) in image `image`, in a region of a
    /// layer designated for its extent `max(width, height)`. `key` is the
    /// caller's identity for the texture, reported back on invalidation;
    /// the cache does not check keys for uniqueness.
    ///
    /// May assign a new layer; when every layer is assigned, the oldest
    /// layer of the image in ring order is reused and its textures are
    /// reported in the next [`CycleBatch::invalidated`]. Safe to call from
    /// many threads at once.
    pub fn insert(&self, image: ImageId, key: u64, width: u32, height: u32) -> Result<Placement, CacheError> {
        self.insert_with(image, key, width, height, true)
    }

    /// As [`insert`](Self::insert), but never evicts: when the texture
    /// needs a new layer and every layer of the image is live, returns
    /// [`CacheError::NoLayer`]; the caller may free one with
    /// [`evict_layer`](Self::evict_layer). A free layer is taken in ring
    /// order from the paper's `nextLayer` on.
    pub fn try_insert(&self, image: ImageId, key: u64, width: u32, height: u32) -> Result<Placement, CacheError> {
        self.insert_with(image, key, width, height, false)
    }

    /// As [`try_insert`](Self::try_insert) over several images of one
    /// format, in order: the first with room (a region of a layer already
    /// assigned to the extent, or a free layer) places the texture.
    /// [`CacheError::NoLayer`] names the first image when none has room.
    pub fn try_insert_in(
        &self,
        images: &[ImageId],
        key: u64,
        width: u32,
        height: u32,
    ) -> Result<Placement, CacheError> {
        let mut no_layer = None;
        for &image in images {
            match self.try_insert(image, key, width, height) {
                Err(error @ CacheError::NoLayer { .. }) => {
                    no_layer.get_or_insert(error);
                }
                placed => return placed,
            }
        }
        Err(no_layer.unwrap_or(CacheError::UnknownImage {
            image: ImageId::MAX,
            images: self.images.len(),
        }))
    }

    /// As [`insert`](Self::insert) over several images of one format: the
    /// first with room places the texture; when none has, the image whose
    /// oldest live layer is oldest of all reuses it, so the ring runs over
    /// the format's layers in every image.
    pub fn insert_in(&self, images: &[ImageId], key: u64, width: u32, height: u32) -> Result<Placement, CacheError> {
        match self.try_insert_in(images, key, width, height) {
            Err(CacheError::NoLayer { image: first, .. }) => {
                let oldest = {
                    let shared = lock(&self.shared);
                    images
                        .iter()
                        .copied()
                        .min_by_key(|&image| {
                            shared
                                .live
                                .get(image as usize)
                                .and_then(|live| live.front())
                                .map_or(u64::MAX, |live| live.age)
                        })
                        .unwrap_or(first)
                };
                self.insert(oldest, key, width, height)
            }
            placed => placed,
        }
    }

    fn insert_with(
        &self,
        image: ImageId,
        key: u64,
        width: u32,
        height: u32,
        evict: bool,
    ) -> Result<Placement, CacheError> {
        let state = self.image(image)?;
        let desc = &state.desc;
        let bad = |reason: String| CacheError::BadExtent {
            image,
            format: desc.format.name,
            width,
            height,
            reason,
        };
        if !width.is_power_of_two() || !height.is_power_of_two() {
            return Err(bad("sides must be non-zero powers of two".into()));
        }
        let extent = width.max(height);
        if extent > desc.layer_size {
            return Err(bad(format!("larger than the layer size {}", desc.layer_size)));
        }
        let mip_count = cacheable_mip_count(&desc.format, width, height);
        if mip_count == 0 {
            return Err(bad(format!(
                "smaller than one {}x{} texel block",
                desc.format.block_width, desc.format.block_height
            )));
        }
        let slot = &state.slots[extent.ilog2() as usize];
        let capacity = desc.regions_per_layer(extent);
        let texture = NewTexture {
            key,
            width,
            height,
            extent,
        };
        loop {
            let (assignment, region) = unpack(slot.fetch_add(1, Ordering::AcqRel));
            if assignment != NO_ASSIGNMENT && u64::from(region) < capacity {
                let layer_index = assignment % desc.layer_count;
                let mut layer = lock(&state.layers[layer_index as usize]);
                // The extent check rules out a wrapped assignment number
                // that a layer of another extent now carries.
                if layer.assignment == Some(assignment) && layer.extent == extent {
                    return Ok(record(desc, &mut layer, &texture, layer_index, assignment, region));
                }
            }
            // Slow path: the layer is full or was evicted. Whoever holds the
            // shared lock first assigns a new layer; the others retry.
            let mut shared = lock(&self.shared);
            if unpack(slot.load(Ordering::Acquire)).0 != assignment {
                continue;
            }
            let (layer_index, new_assignment) = if evict {
                self.assign_layer(&mut shared, state, extent)
            } else {
                self.assign_free_layer(&mut shared, state, extent)
                    .ok_or(CacheError::NoLayer { image, extent })?
            };
            // Region 0 is ours; concurrent claims on the old value fail the
            // liveness check above and retry.
            slot.store(pack(new_assignment, 1), Ordering::Release);
            let mut layer = lock(&state.layers[layer_index as usize]);
            return Ok(record(desc, &mut layer, &texture, layer_index, new_assignment, 0));
        }
    }

    /// Assigns the next layer in ring order to `extent`, evicting it first
    /// if it is still live. Returns (layer index, assignment number).
    fn assign_layer(&self, shared: &mut Shared, state: &ImageState, extent: u32) -> (u32, u32) {
        let desc = &state.desc;
        let assignment = state.next_assignment.load(Ordering::Acquire);
        let next = (assignment + 1) % state.assignment_modulus;
        state.next_assignment.store(next, Ordering::Release);
        let layer_index = assignment % desc.layer_count;
        let image = desc.image as usize;
        // Live layers of an image form a contiguous run of the ring ending
        // just before this one, so if this layer is live it is the oldest.
        let oldest_is_this = shared.live[image].front().is_some_and(|live| live.layer == layer_index);
        if oldest_is_this {
            self.evict_oldest_of(shared, image, EvictionReason::RingReuse);
        }
        make_live(shared, state, layer_index, assignment, extent);
        (layer_index, assignment)
    }

    /// Assigns the first free layer from the ring's next position on to
    /// `extent`, evicting nothing; `None` if every layer is live.
    fn assign_free_layer(&self, shared: &mut Shared, state: &ImageState, extent: u32) -> Option<(u32, u32)> {
        let desc = &state.desc;
        let count = desc.layer_count;
        let next = state.next_assignment.load(Ordering::Acquire);
        let start = next % count;
        let layer_index = (0..count)
            .map(|step| (start + step) % count)
            .find(|&layer| lock(&state.layers[layer as usize]).assignment.is_none())?;
        // The assignment number keeps `assignment % layer_count == layer`
        // and stays ahead of every earlier one, so stale slots never match.
        let mut wide = u64::from(next - start) + u64::from(layer_index);
        if wide < u64::from(next) {
            wide += u64::from(count);
        }
        let assignment = if wide >= u64::from(state.assignment_modulus) {
            layer_index
        } else {
            wide as u32
        };
        state
            .next_assignment
            .store((assignment + 1) % state.assignment_modulus, Ordering::Release);
        make_live(shared, state, layer_index, assignment, extent);
        Some((layer_index, assignment))
    }

    /// Evicts live layer `layer` of `image`, chosen by the caller: its
    /// textures are invalidated (listed in the next batch) and its blocks
    /// released. Errors if the image is unknown or the layer is not live.
    pub fn evict_layer(&self, image: ImageId, layer: u32) -> Result<(), CacheError> {
        self.image(image)?;
        let mut shared = lock(&self.shared);
        let live = &mut shared.live[image as usize];
        let Some(position) = live.iter().position(|l| l.layer == layer) else {
            return Err(CacheError::LayerNotLive { image, layer });
        };
        // Move it to the front so the common eviction path takes it.
        if let Some(entry) = live.remove(position) {
            live.push_front(entry);
        }
        self.evict_oldest_of(&mut shared, image as usize, EvictionReason::Chosen);
        Ok(())
    }

    /// Live layers of `image` (their index, extent and textures), oldest
    /// first.
    pub fn live_layers(&self, image: ImageId) -> Vec<(u32, u32, u64)> {
        self.map_live_layers(image, |index, layer| (index, layer.extent, layer.texture_count))
    }

    /// The keys of the textures placed in each live layer of `image`:
    /// `(layer, keys)`, oldest layer first.
    pub fn live_layer_keys(&self, image: ImageId) -> Vec<(u32, Vec<u64>)> {
        self.map_live_layers(image, |index, layer| {
            (
                index,
                layer.textures.iter().flatten().map(|record| record.key).collect(),
            )
        })
    }

    /// `f(layer index, layer)` for each live layer of `image`, oldest first
    /// (nothing for an unknown image).
    fn map_live_layers<T>(&self, image: ImageId, f: impl Fn(u32, &LayerState) -> T) -> Vec<T> {
        let Ok(state) = self.image(image) else {
            return Vec::new();
        };
        let shared = lock(&self.shared);
        shared.live[image as usize]
            .iter()
            .map(|live| f(live.layer, &lock(&state.layers[live.layer as usize])))
            .collect()
    }

    /// Evicts the oldest live layer of `image`: invalidates its textures
    /// and releases its blocks.
    fn evict_oldest_of(&self, shared: &mut Shared, image: usize, reason: EvictionReason) {
        let Some(live) = shared.live[image].pop_front() else {
            return;
        };
        let Some(state) = self.images.get(image) else {
            return;
        };
        let mut layer = lock(&state.layers[live.layer as usize]);
        layer.assignment = None;
        let extent = layer.extent;
        let textures: Vec<Placement> = std::mem::take(&mut layer.textures)
            .into_iter()
            .enumerate()
            .filter_map(|(region, record)| {
                record.map(|record| {
                    placement_of(&state.desc, live.layer, live.assignment, region as u32, extent, &record)
                })
            })
            .collect();
        let mut blocks: Vec<_> = layer.blocks.drain().collect();
        // Parked in key order, so which of them a later batch unbinds
        // first does not depend on hashing.
        blocks.sort_unstable_by_key(|(key, _)| *key);
        layer.texture_bytes = 0;
        layer.texture_count = 0;
        drop(layer);
        for ((mip, x, y), bound) in &blocks {
            let key = BlockKey {
                image: image as u32,
                layer: live.layer,
                mip: *mip,
                x: *x,
                y: *y,
            };
            release_block(shared, key, bound.memory);
        }
        shared.live_blocks -= blocks.len() as u64;
        match reason {
            EvictionReason::RingReuse => shared.stats.ring_evictions += 1,
            EvictionReason::MemoryBudget => shared.stats.budget_evictions += 1,
            EvictionReason::Chosen => shared.stats.chosen_evictions += 1,
        }
        shared.stats.invalidated_textures += textures.len() as u64;
        shared.evicted.push(EvictedLayer {
            image: image as u32,
            layer: live.layer,
            assignment: live.assignment,
            extent,
            reason,
            textures: textures.len() as u32,
            blocks: blocks.len() as u32,
        });
        shared.invalidated.extend(textures);
    }

    /// Evicts the oldest live layer over all images. False if none is live.
    fn evict_oldest(&self, shared: &mut Shared, reason: EvictionReason) -> bool {
        let oldest = shared
            .live
            .iter()
            .enumerate()
            .filter_map(|(image, live)| live.front().map(|front| (front.age, image)))
            .min();
        match oldest {
            Some((_, image)) => {
                self.evict_oldest_of(shared, image, reason);
                true
            }
            None => false,
        }
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

    /// The sparse blocks mip `mip` of a placed texture touches, in key
    /// order. Pure geometry; does not bind anything.
    pub fn blocks_for_mip(&self, placement: &Placement, mip: u32) -> Result<Vec<BlockKey>, CacheError> {
        let state = self.image(placement.image)?;
        let rect = placement.mip_rect(mip)?;
        Ok(rect_blocks(&state.desc, &rect)
            .into_iter()
            .map(|(mip, x, y)| BlockKey {
                image: placement.image,
                layer: placement.layer,
                mip,
                x,
                y,
            })
            .collect())
    }

    /// Prepares texture mip `mip` of `placement` for its copy: makes sure
    /// every block it touches is bound (queuing a bind, with a pool slot,
    /// for each block no texture of the layer needed before), records the
    /// mip as staged, and returns where to copy it.
    ///
    /// If binding would exceed the memory budget, the oldest layers (over
    /// all images, possibly this texture's own) are evicted first. Errors:
    /// [`CacheError::Invalidated`] if the placement's layer is gone (also
    /// when the budget just evicted it); [`CacheError::OverBudget`] if the
    /// mip needs more blocks than the whole budget;
    /// [`CacheError::MemoryPending`] if the budget allows it but the freed
    /// memory still waits for the next batch's unbinds (retry next cycle).
    pub fn stage_mip(&self, placement: &Placement, mip: u32) -> Result<MipUpload, CacheError> {
        self.stage_mip_with(placement, mip, true)
    }

    /// As [`stage_mip`](Self::stage_mip), but never evicts: if the budget's
    /// free blocks cannot hold the blocks the mip needs, returns
    /// [`CacheError::NoRoom`] and changes nothing. For callers that choose
    /// what to give up themselves ([`drop_mip`](Self::drop_mip)).
    pub fn try_stage_mip(&self, placement: &Placement, mip: u32) -> Result<MipUpload, CacheError> {
        self.stage_mip_with(placement, mip, false)
    }

    fn stage_mip_with(&self, placement: &Placement, mip: u32, evict: bool) -> Result<MipUpload, CacheError> {
        let state = self.image(placement.image)?;
        let desc = &state.desc;
        let rect = placement.mip_rect(mip)?;
        let layer_mutex = state
            .layers
            .get(placement.layer as usize)
            .ok_or_else(|| invalidated(placement))?;
        let touched = rect_blocks(desc, &rect);
        let mut shared = lock(&self.shared);
        loop {
            let mut layer = lock(layer_mutex);
            if layer.assignment != Some(placement.assignment)
                || !layer
                    .textures
                    .get(placement.region as usize)
                    .is_some_and(Option::is_some)
            {
                return Err(invalidated(placement));
            }
            let needed: Vec<BlockKey> = touched
                .iter()
                .filter(|&at| !layer.blocks.contains_key(at))
                .map(|&(mip, x, y)| BlockKey {
                    image: placement.image,
                    layer: placement.layer,
                    mip,
                    x,
                    y,
                })
                .collect();
            let needed_count = needed.len() as u64;
            if shared.live_blocks + needed_count <= shared.budget_blocks {
                let reclaimed = needed.iter().filter(|key| shared.parked.contains_key(key)).count() as u64;
                let fresh = needed_count - reclaimed;
                if fresh > shared.pool.available() {
                    shared.memory_shortfall += fresh - shared.pool.available();
                    let shared = &mut *shared;
                    let parked = &shared.parked;
                    shared
                        .wanted_back
                        .extend(needed.iter().filter(|key| parked.contains_key(key)));
                    return Err(CacheError::MemoryPending {
                        needed_blocks: fresh,
                        free_blocks: shared.pool.available(),
                    });
                }
                let shared = &mut *shared;
                for key in &needed {
                    // A parked block needed again keeps its memory and
                    // its binding: no unbind, no bind.
                    let memory = match shared.parked.remove(key) {
                        Some(parked) => parked.memory,
                        None => match shared.pool.allocate(&mut shared.new_chunks) {
                            Some(memory) => {
                                shared.pending_binds.insert(*key, memory);
                                memory
                            }
                            // Unreachable: availability was checked above.
                            None => {
                                return Err(CacheError::MemoryPending {
                                    needed_blocks: fresh,
                                    free_blocks: 0,
                                })
                            }
                        },
                    };
                    layer
                        .blocks
                        .insert((key.mip, key.x, key.y), BoundBlock { memory, users: 0 });
                    shared.live_blocks += 1;
                }
                shared.stats.chunks = shared.pool.chunk_count();
                let bytes = desc.format.image_bytes(rect.width, rect.height);
                let mut already_staged = false;
                if let Some(Some(record)) = layer.textures.get_mut(placement.region as usize) {
                    already_staged = record.staged_mips & (1 << mip) != 0;
                    record.staged_mips |= 1 << mip;
                }
                if !already_staged {
                    layer.texture_bytes += bytes;
                    for at in &touched {
                        if let Some(bound) = layer.blocks.get_mut(at) {
                            bound.users += 1;
                        }
                    }
                }
                return Ok(MipUpload {
                    image: placement.image,
                    layer: placement.layer,
                    rect,
                    bytes,
                    new_blocks: needed.len() as u32,
                    already_staged,
                });
            }
            drop(layer);
            if !evict {
                return Err(CacheError::NoRoom {
                    needed_blocks: needed_count,
                    free_blocks: shared.budget_blocks.saturating_sub(shared.live_blocks),
                });
            }
            // Single tails hold their part of the budget for good: no eviction frees it.
            let evictable_budget = shared.budget_blocks - shared.single_tails.len() as u64;
            if needed_count > evictable_budget {
                return Err(CacheError::OverBudget {
                    needed_blocks: needed_count,
                    budget_blocks: evictable_budget,
                });
            }
            if !self.evict_oldest(&mut shared, EvictionReason::MemoryBudget) {
                return Err(CacheError::OverBudget {
                    needed_blocks: needed_count,
                    budget_blocks: shared.budget_blocks,
                });
            }
        }
    }

    /// Hands out everything accumulated since the last call: the bind
    /// batch for the binder, invalidated textures, evictions and new pool
    /// chunks (see [`CycleBatch`] for what the engine does with them). After
    /// this call the cache assumes the batch will be submitted; memory of
    /// unbound blocks becomes reusable for later batches.
    ///
    /// Blocks no live texture uses are unbound only as far as staging
    /// lacked memory since the last batch, oldest parked first; the rest
    /// stay bound. Binding is what stalls a frame (paper §3.2), so an
    /// eviction costs nothing until its memory is wanted, and then only as
    /// many unbinds as the binds that want it.
    pub fn take_batch(&self) -> CycleBatch {
        let mut shared = lock(&self.shared);
        let shared = &mut *shared;
        let wanted = std::mem::take(&mut shared.memory_shortfall).min(shared.parked.len() as u64) as usize;
        let wanted_back = std::mem::take(&mut shared.wanted_back);
        // Most batches want none: the parked set is looked at only when some are.
        let mut unbinds: Vec<(BlockKey, MemorySlot)> = Vec::new();
        if wanted > 0 {
            let mut oldest: Vec<(u64, BlockKey)> = shared
                .parked
                .iter()
                .filter(|(key, _)| !wanted_back.contains(key))
                .map(|(key, p)| (p.since, *key))
                .collect();
            if wanted < oldest.len() {
                oldest.select_nth_unstable(wanted);
                oldest.truncate(wanted);
            }
            unbinds = oldest
                .into_iter()
                .filter_map(|(_, key)| shared.parked.remove(&key).map(|p| (key, p.memory)))
                .collect();
        }
        unbinds.sort_by_key(|(key, _)| *key);
        let mut binds: Vec<(BlockKey, MemorySlot)> = shared.pending_binds.drain().collect();
        binds.sort_by_key(|(key, _)| *key);
        let mut ops = Vec::with_capacity(unbinds.len() + binds.len());
        for (block, memory) in unbinds {
            shared.pool.free(memory);
            ops.push(BindOp::Unbind { block });
        }
        ops.extend(binds.into_iter().map(|(block, memory)| BindOp::Bind { block, memory }));
        CycleBatch {
            ops,
            invalidated: std::mem::take(&mut shared.invalidated),
            evicted_layers: std::mem::take(&mut shared.evicted),
            new_chunks: std::mem::take(&mut shared.new_chunks),
        }
    }

    /// The memory slot backing `block` in the cache's current accounting
    /// (including binds not yet handed out), or `None` if the block is not
    /// bound for a live layer.
    pub fn block_memory(&self, block: &BlockKey) -> Option<MemorySlot> {
        let state = self.images.get(block.image as usize)?;
        let layer = lock(state.layers.get(block.layer as usize)?);
        layer
            .blocks
            .get(&(block.mip, block.x, block.y))
            .map(|bound| bound.memory)
    }

    /// Every block bound for a live layer, and every block of a single mip
    /// tail, with its memory, in key order.
    pub fn bound_blocks(&self) -> Vec<(BlockKey, MemorySlot)> {
        let shared = lock(&self.shared);
        let mut all = shared.single_tails.clone();
        for state in &self.images {
            for (layer_index, layer) in state.layers.iter().enumerate() {
                let layer = lock(layer);
                all.extend(layer.blocks.iter().map(|(&(mip, x, y), bound)| {
                    (
                        BlockKey {
                            image: state.desc.image,
                            layer: layer_index as u32,
                            mip,
                            x,
                            y,
                        },
                        bound.memory,
                    )
                }));
            }
        }
        all.sort_by_key(|(key, _)| *key);
        all
    }

    /// Every parked block (bound, holding memory, used by no live texture;
    /// see [`take_batch`](Self::take_batch)) with its memory, in key order.
    pub fn parked_blocks(&self) -> Vec<(BlockKey, MemorySlot)> {
        let shared = lock(&self.shared);
        let mut all: Vec<_> = shared.parked.iter().map(|(key, p)| (*key, p.memory)).collect();
        all.sort_by_key(|(key, _)| *key);
        all
    }

    /// Texture bytes of staged mips versus bytes of bound blocks, over
    /// live layers.
    pub fn utilisation(&self) -> Utilisation {
        let shared = lock(&self.shared);
        let mut report = Utilisation::default();
        for state in &self.images {
            let single = state.desc.single_tail_blocks();
            report.bound_blocks += single;
            report.bound_bytes += single * state.desc.block_bytes;
            report.tail_blocks += single;
            report.tail_bytes += single * state.desc.block_bytes;
            for layer in &state.layers {
                let layer = lock(layer);
                if layer.assignment.is_some() {
                    report.live_layers += 1;
                    report.live_textures += layer.texture_count;
                    report.texture_bytes += layer.texture_bytes;
                    report.bound_blocks += layer.blocks.len() as u64;
                    report.bound_bytes += layer.blocks.len() as u64 * state.desc.block_bytes;
                    let tail = layer.tail_blocks();
                    report.tail_blocks += tail;
                    report.tail_bytes += tail * state.desc.block_bytes;
                }
            }
        }
        for key in shared.parked.keys() {
            let block_bytes = self.images.get(key.image as usize).map_or(0, |s| s.desc.block_bytes);
            report.parked_blocks += 1;
            report.parked_bytes += block_bytes;
            if key.is_tail() {
                report.tail_blocks += 1;
                report.tail_bytes += block_bytes;
            }
        }
        drop(shared);
        report
    }

    /// Bytes of mip tails each image holds now (live, parked and single
    /// tails), indexed by [`ImageId`].
    pub fn tail_bytes_held(&self) -> Vec<u64> {
        let shared = lock(&self.shared);
        let mut held: Vec<u64> = self
            .images
            .iter()
            .map(|state| state.desc.single_tail_blocks() * state.desc.block_bytes)
            .collect();
        for (state, bytes) in self.images.iter().zip(&mut held) {
            for layer in &state.layers {
                let layer = lock(layer);
                if layer.assignment.is_some() {
                    let tail = layer.tail_blocks();
                    *bytes += tail * state.desc.block_bytes;
                }
            }
        }
        for key in shared.parked.keys().filter(|key| key.is_tail()) {
            if let (Some(bytes), Some(state)) = (held.get_mut(key.image as usize), self.images.get(key.image as usize))
            {
                *bytes += state.desc.block_bytes;
            }
        }
        held
    }

    /// Drops texture mip `mip` of `placement`: the mip is no longer staged,
    /// and every block it touched that no other staged mip uses is released
    /// (unbound by the next batch, or never bound if its bind was not handed
    /// out yet). Returns the blocks released. The caller must first make
    /// sure nothing samples the level any more (the engine raises the
    /// texture's finest sampled level in the same cycle, before the unbind
    /// batch runs). Errors: [`CacheError::Invalidated`] if the layer is
    /// gone, [`CacheError::NotStaged`] if the mip is not staged.
    pub fn drop_mip(&self, placement: &Placement, mip: u32) -> Result<u32, CacheError> {
        let state = self.image(placement.image)?;
        let rect = placement.mip_rect(mip)?;
        let touched = rect_blocks(&state.desc, &rect);
        let layer_mutex = state
            .layers
            .get(placement.layer as usize)
            .ok_or_else(|| invalidated(placement))?;
        let mut shared = lock(&self.shared);
        let mut layer = lock(layer_mutex);
        if layer.assignment != Some(placement.assignment) {
            return Err(invalidated(placement));
        }
        let record = layer
            .textures
            .get_mut(placement.region as usize)
            .and_then(Option::as_mut)
            .ok_or_else(|| invalidated(placement))?;
        if record.staged_mips & (1 << mip) == 0 {
            return Err(CacheError::NotStaged {
                key: placement.key,
                mip,
            });
        }
        record.staged_mips &= !(1 << mip);
        layer.texture_bytes -= state.desc.format.image_bytes(rect.width, rect.height);
        let mut released = 0u32;
        for &(mip, x, y) in &touched {
            let Some(bound) = layer.blocks.get_mut(&(mip, x, y)) else {
                continue;
            };
            bound.users = bound.users.saturating_sub(1);
            if bound.users == 0 {
                let memory = bound.memory;
                layer.blocks.remove(&(mip, x, y));
                let key = BlockKey {
                    image: placement.image,
                    layer: placement.layer,
                    mip,
                    x,
                    y,
                };
                release_block(&mut shared, key, memory);
                released += 1;
            }
        }
        shared.live_blocks -= u64::from(released);
        shared.stats.dropped_mips += 1;
        shared.stats.dropped_blocks += u64::from(released);
        Ok(released)
    }

    /// Blocks that dropping staged mip `mip` of `placement` would release
    /// now: those it touches that no other staged mip uses. Zero when the
    /// placement is gone or the mip is not staged.
    pub fn exclusive_blocks(&self, placement: &Placement, mip: u32) -> u32 {
        let Ok(state) = self.image(placement.image) else {
            return 0;
        };
        let Ok(rect) = placement.mip_rect(mip) else {
            return 0;
        };
        let touched = rect_blocks(&state.desc, &rect);
        let Some(layer_mutex) = state.layers.get(placement.layer as usize) else {
            return 0;
        };
        let layer = lock(layer_mutex);
        let staged = layer.assignment == Some(placement.assignment)
            && layer
                .textures
                .get(placement.region as usize)
                .and_then(Option::as_ref)
                .is_some_and(|record| record.staged_mips & (1 << mip) != 0);
        if !staged {
            return 0;
        }
        touched
            .iter()
            .filter(|at| layer.blocks.get(at).is_some_and(|bound| bound.users == 1))
            .count() as u32
    }

    /// Blocks bound for live layers (binds not yet handed out included) and
    /// the budget, in blocks.
    ///
    /// Single mip tails, bound for good, count in neither: what is left of
    /// the budget for the streamed levels is what a planner can use.
    pub fn budget_use(&self) -> BudgetUse {
        let shared = lock(&self.shared);
        let fixed = shared.single_tails.len() as u64;
        BudgetUse {
            live_blocks: shared.live_blocks - fixed,
            budget_blocks: shared.budget_blocks - fixed,
        }
    }

    /// Running counts since creation.
    pub fn stats(&self) -> CacheStats {
        lock(&self.shared).stats
    }
}

/// Records a free layer as assigned to `extent` under `assignment`: newest
/// in the image's live list, counted, and marked in the layer itself.
fn make_live(shared: &mut Shared, state: &ImageState, layer_index: u32, assignment: u32, extent: u32) {
    let age = shared.next_age;
    shared.next_age += 1;
    shared.live[state.desc.image as usize].push_back(LiveLayer {
        layer: layer_index,
        assignment,
        age,
    });
    shared.stats.layer_assignments += 1;
    let mut layer = lock(&state.layers[layer_index as usize]);
    layer.assignment = Some(assignment);
    layer.extent = extent;
}

/// A block bound for no live texture, still holding its memory.
#[derive(Clone, Copy, Debug)]
struct ParkedBlock {
    memory: MemorySlot,
    /// When it was parked ([`Shared::next_park`]).
    since: u64,
}

/// Returns a block's memory: to the pool at once if its bind was never
/// handed out, else it parks, bound, until a batch needs its memory.
fn release_block(shared: &mut Shared, key: BlockKey, memory: MemorySlot) {
    if shared.pending_binds.remove(&key).is_some() {
        // Never submitted: nothing to unbind.
        shared.pool.free(memory);
    } else {
        let since = shared.next_park;
        shared.next_park += 1;
        shared.parked.insert(key, ParkedBlock { memory, since });
    }
}

struct NewTexture {
    key: u64,
    width: u32,
    height: u32,
    extent: u32,
}

fn record(
    desc: &ImageDesc,
    layer: &mut LayerState,
    texture: &NewTexture,
    layer_index: u32,
    assignment: u32,
    region: u32,
) -> Placement {
    let record = TextureRecord {
        key: texture.key,
        width: texture.width,
        height: texture.height,
        staged_mips: 0,
    };
    let placement = placement_of(desc, layer_index, assignment, region, texture.extent, &record);
    let index = region as usize;
    if layer.textures.len() <= index {
        layer.textures.resize_with(index + 1, || None);
    }
    layer.textures[index] = Some(record);
    layer.texture_count += 1;
    placement
}

fn placement_of(
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

/// The blocks of a layer that `rect` (texels of level `rect.mip`) lies on,
/// as `(mip, x, y)`: its blocks of the level; for a level in a per-layer
/// tail, every block of the layer's tail (keyed at [`BlockKey::TAIL_LEVEL`]);
/// none in a single tail, which is bound for good.
pub(crate) fn rect_blocks(desc: &ImageDesc, rect: &TexelRect) -> Vec<(u32, u32, u32)> {
    match desc.mip_tail {
        Some(tail) if rect.mip >= tail.first_level => {
            if tail.single {
                Vec::new()
            } else {
                (0..tail.blocks).map(|index| (BlockKey::TAIL_LEVEL, index, 0)).collect()
            }
        }
        _ => {
            let (x0, y0, x1, y1) = rect.block_range(&desc.granularity);
            (y0..y1).flat_map(|y| (x0..x1).map(move |x| (rect.mip, x, y))).collect()
        }
    }
}

fn invalidated(placement: &Placement) -> CacheError {
    CacheError::Invalidated {
        key: placement.key,
        image: placement.image,
        layer: placement.layer,
    }
}
