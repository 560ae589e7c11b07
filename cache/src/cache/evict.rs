//! Layer eviction: the ring's oldest layer, the oldest over all images for
//! the budget, or a layer the caller chooses; and the live-layer listings
//! callers choose from.

use super::state::{lock, placement_of, release_block, LayerState, Shared};
use super::types::{EvictedLayer, EvictionReason, ImageId, Placement};
use super::TextureCache;
use crate::binder::BlockKey;
use crate::error::CacheError;

impl TextureCache {
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
    pub(super) fn evict_oldest_of(&self, shared: &mut Shared, image: usize, reason: EvictionReason) {
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
    pub(super) fn evict_oldest(&self, shared: &mut Shared, reason: EvictionReason) -> bool {
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
}
