//! Offline utilisation estimate for a list of texture extents, for tools
//! that report how well a generated city would pack.

use std::collections::{HashMap, HashSet};

use crate::config::ImageDesc;
use crate::error::CacheError;
use crate::geometry::{cacheable_mip_count, region_origin, TexelRect};

/// Result of [`estimate_utilisation`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct UtilisationEstimate {
    /// Textures packed.
    pub textures: u64,
    /// Bytes of every cacheable mip of every texture.
    pub texture_bytes: u64,
    /// Distinct sparse blocks those mips touch.
    pub bound_blocks: u64,
    /// `bound_blocks` × block size.
    pub bound_bytes: u64,
    /// Layers the packing needs (may exceed the image's layer count: the
    /// estimate ignores eviction).
    pub layers_used: u64,
    /// Of `bound_blocks`, those of mip tails (each used layer's, or the
    /// image's single tail).
    pub tail_blocks: u64,
}

impl UtilisationEstimate {
    /// `texture_bytes / bound_bytes`, 0 when nothing is bound.
    pub fn ratio(&self) -> f64 {
        if self.bound_bytes == 0 {
            0.0
        } else {
            self.texture_bytes as f64 / self.bound_bytes as f64
        }
    }
}

/// Packs `extents` (width, height) in order into unlimited layers of
/// `image` the way [`crate::TextureCache::insert`] does sequentially, loads
/// every cacheable mip of each, and counts texture bytes against the bytes
/// of the blocks they touch. Errors name the first extent the image cannot
/// hold (by its index in the list).
pub fn estimate_utilisation(image: &ImageDesc, extents: &[(u32, u32)]) -> Result<UtilisationEstimate, CacheError> {
    // Per extent: (virtual layer number, next region).
    let mut open: HashMap<u32, (u64, u64)> = HashMap::new();
    let mut blocks: HashSet<(u64, u32, u32, u32)> = HashSet::new();
    let mut estimate = UtilisationEstimate::default();
    for (index, &(width, height)) in extents.iter().enumerate() {
        let bad = |reason: String| CacheError::BadExtent {
            image: image.image,
            format: image.format.name,
            width,
            height,
            reason: format!("extent #{index}: {reason}"),
        };
        if !width.is_power_of_two() || !height.is_power_of_two() {
            return Err(bad("sides must be non-zero powers of two".into()));
        }
        let extent = width.max(height);
        if extent > image.layer_size {
            return Err(bad(format!("larger than the layer size {}", image.layer_size)));
        }
        let mip_count = cacheable_mip_count(&image.format, width, height);
        if mip_count == 0 {
            return Err(bad("smaller than one texel block".into()));
        }
        let capacity = image.regions_per_layer(extent);
        let layers_used = &mut estimate.layers_used;
        let entry = open.entry(extent).or_insert_with(|| {
            *layers_used += 1;
            (*layers_used - 1, 0)
        });
        if entry.1 == capacity {
            *entry = (*layers_used, 0);
            *layers_used += 1;
        }
        let (layer, region) = *entry;
        entry.1 += 1;
        // A region index is below (layer_size / extent)², at most 2^30.
        let (origin_x, origin_y) = region_origin(image.layer_size, extent, region as u32);
        for mip in 0..mip_count {
            let rect = TexelRect::of_mip(origin_x, origin_y, width, height, mip);
            estimate.texture_bytes += image.format.image_bytes(rect.width, rect.height);
            for (mip, x, y) in crate::cache::rect_blocks(image, &rect) {
                blocks.insert((layer, mip, x, y));
            }
        }
        estimate.textures += 1;
    }
    // A single tail is bound whatever the textures.
    estimate.tail_blocks = blocks
        .iter()
        .filter(|&&(_, mip, _, _)| mip == crate::BlockKey::TAIL_LEVEL)
        .count() as u64
        + image.single_tail_blocks();
    estimate.bound_blocks = blocks.len() as u64 + image.single_tail_blocks();
    estimate.bound_bytes = estimate.bound_blocks * image.block_bytes;
    Ok(estimate)
}
