//! The values the cache hands out and reports: placements, the per-cycle
//! batch, evictions, staged-mip uploads and the accounting summaries. Plain
//! data, kept apart from the locking state so callers can read them alone.

use crate::binder::BindOp;
use crate::error::CacheError;
use crate::format::TexelFormat;
use crate::geometry::{TexelRect, UvTransform};
use crate::pool::ChunkInfo;

/// Index of a sparse image of the cache (one per format).
pub type ImageId = u32;

/// Where a texture lives in the cache. Returned by
/// [`TextureCache::insert`]; valid until its layer is evicted (then it is
/// listed in [`CycleBatch::invalidated`]).
///
/// [`TextureCache::insert`]: super::TextureCache::insert
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
    ///
    /// [`TextureCache::evict_layer`]: super::TextureCache::evict_layer
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
    ///
    /// [`TextureCache::take_batch`]: super::TextureCache::take_batch
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
///
/// [`TextureCache::stage_mip`]: super::TextureCache::stage_mip
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
    ///
    /// [`TextureCache::take_batch`]: super::TextureCache::take_batch
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
    ///
    /// [`TextureCache::evict_layer`]: super::TextureCache::evict_layer
    pub chosen_evictions: u64,
    /// Textures invalidated by evictions.
    pub invalidated_textures: u64,
    /// Chunks the block pool created.
    pub chunks: u32,
    /// Texture mips dropped by [`TextureCache::drop_mip`].
    ///
    /// [`TextureCache::drop_mip`]: super::TextureCache::drop_mip
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
