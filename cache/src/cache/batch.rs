//! The streaming cycle's hand-out and the accounting queries: the
//! [`CycleBatch`] of unbinds and binds, and what is bound, parked and
//! within the budget.

use super::state::lock;
use super::types::{BudgetUse, CacheStats, CycleBatch, Utilisation};
use super::TextureCache;
use crate::binder::{BindOp, BlockKey, MemorySlot};

impl TextureCache {
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
    ///
    /// [`ImageId`]: super::ImageId
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
