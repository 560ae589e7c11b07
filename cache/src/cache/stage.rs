//! Staging and dropping mips: binding every block a staged mip touches
//! within the memory budget (evicting for it, or not), and releasing the
//! blocks of a dropped mip that no other staged mip uses.

use super::state::{lock, release_block, BoundBlock};
use super::types::{EvictionReason, MipUpload, Placement};
use super::TextureCache;
use crate::binder::BlockKey;
use crate::config::ImageDesc;
use crate::error::CacheError;
use crate::geometry::TexelRect;

impl TextureCache {
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
