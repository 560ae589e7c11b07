//! Placing textures: the paper's packing by extent (one atomic add claims a
//! region of the extent's current layer) and layer assignment in ring
//! order, with or without evicting the oldest layer.

use std::sync::atomic::Ordering;

use super::state::{
    lock, pack, placement_of, unpack, ImageState, LayerState, LiveLayer, Shared, TextureRecord, NO_ASSIGNMENT,
};
use super::types::{EvictionReason, ImageId, Placement};
use super::TextureCache;
use crate::config::ImageDesc;
use crate::error::CacheError;
use crate::geometry::cacheable_mip_count;

impl TextureCache {
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
    ///
    /// [`CycleBatch::invalidated`]: super::CycleBatch::invalidated
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
