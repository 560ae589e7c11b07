//! Cache configuration and its validation against the device and budgets.

use crate::error::ConfigError;
use crate::format::{DeviceLimits, Granularity, TexelFormat};
use crate::geometry::{blocks_in_level, level_size};

/// Largest layer size the cache accepts. Region indices within a layer are
/// packed into 32 bits next to the layer's assignment number, and a layer of
/// 2^15 texels holds at most 2^30 regions (of extent 1), which leaves room
/// for concurrent over-claims.
pub const MAX_LAYER_SIZE: u32 = 1 << 15;

/// One sparse 2D-array image of the cache (one per texture format).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageConfig {
    /// Texel format of every texture cached in this image.
    pub format: TexelFormat,
    /// Sparse granularity in texels (see [`Granularity::from_device_report`]).
    pub granularity: Granularity,
    /// Width and height of each layer in texels (a power of two).
    pub layer_size: u32,
    /// Number of array layers.
    pub layer_count: u32,
    /// The image's mip tail, where the device keeps its small levels in one
    /// opaquely bound range; `None` when every level is bound block by block.
    pub mip_tail: Option<MipTail>,
}

/// A sparse image's mip tail as the cache accounts for it: the levels from
/// `first_level` down are bound as a whole (`imageMipTailFirstLod`), never
/// block by block, in `blocks` sparse blocks (`imageMipTailSize` / block
/// size), per layer or, with `single` (`SINGLE_MIPTAIL`), once for the image.
///
/// A per-layer tail is bound when a texture of the layer first needs one of
/// its levels and released with the last one, like any block; a single tail
/// is taken from the budget when the cache is made and never released.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct MipTail {
    /// First level in the tail (at least 1: a tail from level 0 leaves
    /// nothing to bind per block, and the cache refuses it).
    pub first_level: u32,
    /// Sparse blocks one tail takes.
    pub blocks: u32,
    /// One tail for every layer of the image.
    pub single: bool,
}

/// Everything the cache is configured with. Block size and limits come
/// from the device ([`DeviceLimits`]); budgets are the engine's choice.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CacheConfig {
    /// One entry per format; the entry's index is the image index used in
    /// [`crate::BlockKey::image`] and [`crate::Placement::image`].
    pub images: Vec<ImageConfig>,
    /// Device limits and the sparse block size.
    pub limits: DeviceLimits,
    /// Most bytes of sparse blocks bound at once, over all images. Rounded
    /// down to whole blocks. Reaching it evicts the oldest layer.
    pub memory_budget_bytes: u64,
    /// Most bytes of sparse virtual address space all images together may
    /// span (layers × block-padded full mip chain). Checked at creation;
    /// drivers do not always enforce their own `sparseAddressSpaceSize`.
    pub virtual_budget_bytes: u64,
    /// Sparse blocks per device-memory chunk of the block pool.
    pub blocks_per_chunk: u32,
}

/// A validated image of the cache with its derived sizes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageDesc {
    /// Image index.
    pub image: u32,
    /// Texel format.
    pub format: TexelFormat,
    /// Sparse granularity in texels.
    pub granularity: Granularity,
    /// Layer width and height in texels.
    pub layer_size: u32,
    /// Number of array layers.
    pub layer_count: u32,
    /// Mip levels of the sparse image: the full chain down to 1×1.
    pub mip_levels: u32,
    /// Sparse block size in bytes.
    pub block_bytes: u64,
    /// Sparse blocks covering one layer's full mip chain: the levels above
    /// the tail block by block, and the layer's own tail (none for a single
    /// tail, which [`ImageDesc::single_tail_blocks`] counts once).
    pub blocks_per_layer: u64,
    /// The mip tail, if the image has one (`first_level` below `mip_levels`).
    pub mip_tail: Option<MipTail>,
}

impl ImageDesc {
    /// Validates one image configuration against the device limits.
    /// `image` is its index, used in errors.
    pub fn new(image: usize, config: &ImageConfig, limits: &DeviceLimits) -> Result<Self, ConfigError> {
        config.format.validate()?;
        config.granularity.validate(&config.format)?;
        if limits.sparse_block_bytes == 0 {
            return Err(ConfigError::ZeroBlockSize);
        }
        let layer_size = config.layer_size;
        let bad_size = |reason: String| ConfigError::BadLayerSize {
            image,
            format: config.format.name,
            layer_size,
            reason,
        };
        if !layer_size.is_power_of_two() {
            return Err(bad_size("must be a power of two".into()));
        }
        if layer_size < config.format.block_width || layer_size < config.format.block_height {
            return Err(bad_size(format!(
                "smaller than one {}x{} texel block",
                config.format.block_width, config.format.block_height
            )));
        }
        if layer_size > limits.max_image_dimension_2d {
            return Err(bad_size(format!(
                "above the device's maxImageDimension2D {}",
                limits.max_image_dimension_2d
            )));
        }
        if layer_size > MAX_LAYER_SIZE {
            return Err(bad_size(format!("above the cache's maximum {MAX_LAYER_SIZE}")));
        }
        if config.layer_count == 0 || config.layer_count > limits.max_image_array_layers {
            return Err(ConfigError::BadLayerCount {
                image,
                format: config.format.name,
                layer_count: config.layer_count,
                max_layers: limits.max_image_array_layers,
            });
        }
        let mip_levels = layer_size.trailing_zeros() + 1;
        // A tail that starts below the last level is no tail.
        let mip_tail = config.mip_tail.filter(|tail| tail.first_level < mip_levels);
        if let Some(tail) = mip_tail {
            if tail.first_level == 0 || tail.blocks == 0 {
                return Err(ConfigError::UnservedMipTail {
                    image,
                    format: config.format.name,
                    reason: if tail.first_level == 0 {
                        "its mip tail starts at level 0, so no level can be bound block by block".into()
                    } else {
                        "its mip tail takes no memory".into()
                    },
                });
            }
        }
        let block_levels = mip_tail.map_or(mip_levels, |tail| tail.first_level);
        let layer_tail_blocks = mip_tail
            .filter(|tail| !tail.single)
            .map_or(0, |tail| u64::from(tail.blocks));
        let blocks_per_layer = (0..block_levels)
            .map(|mip| {
                let size = level_size(layer_size, mip);
                blocks_in_level(size, &config.granularity)
            })
            .sum::<u64>()
            + layer_tail_blocks;
        let image_index = u32::try_from(image).map_err(|_| bad_size("image index beyond u32".into()))?;
        Ok(ImageDesc {
            image: image_index,
            format: config.format,
            granularity: config.granularity,
            layer_size,
            layer_count: config.layer_count,
            mip_levels,
            block_bytes: limits.sparse_block_bytes,
            blocks_per_layer,
            mip_tail,
        })
    }

    /// Virtual address space the image spans: layers × blocks per layer ×
    /// block size, and a single tail once (saturating).
    pub fn virtual_bytes(&self) -> u64 {
        u64::from(self.layer_count)
            .saturating_mul(self.blocks_per_layer)
            .saturating_add(self.single_tail_blocks())
            .saturating_mul(self.block_bytes)
    }

    /// Whether level `mip` lies in the mip tail (bound as a whole).
    pub fn in_tail(&self, mip: u32) -> bool {
        self.mip_tail.is_some_and(|tail| mip >= tail.first_level)
    }

    /// Blocks of the image's single tail (zero without one): bound for the
    /// cache's whole life.
    pub fn single_tail_blocks(&self) -> u64 {
        self.mip_tail
            .filter(|tail| tail.single)
            .map_or(0, |tail| u64::from(tail.blocks))
    }

    /// Bytes one tail takes (zero without a tail).
    pub fn tail_bytes(&self) -> u64 {
        self.mip_tail
            .map_or(0, |tail| u64::from(tail.blocks).saturating_mul(self.block_bytes))
    }

    /// Square regions of `extent` texels one layer holds.
    pub fn regions_per_layer(&self, extent: u32) -> u64 {
        let per_row = u64::from(self.layer_size / extent.max(1));
        per_row * per_row
    }
}

impl CacheConfig {
    /// Validates the whole configuration: every image (a format may have
    /// several), a memory budget of at least one block, non-empty chunks, and
    /// the images' total virtual size within the virtual budget.
    pub fn validate(&self) -> Result<Vec<ImageDesc>, ConfigError> {
        if self.images.is_empty() {
            return Err(ConfigError::NoImages);
        }
        if self.limits.sparse_block_bytes == 0 {
            return Err(ConfigError::ZeroBlockSize);
        }
        if self.memory_budget_bytes < self.limits.sparse_block_bytes {
            return Err(ConfigError::MemoryBudgetTooSmall {
                budget_bytes: self.memory_budget_bytes,
                block_bytes: self.limits.sparse_block_bytes,
            });
        }
        if self.blocks_per_chunk == 0 {
            return Err(ConfigError::ZeroChunk);
        }
        let descs = self
            .images
            .iter()
            .enumerate()
            .map(|(index, image)| ImageDesc::new(index, image, &self.limits))
            .collect::<Result<Vec<_>, _>>()?;
        let single_tail_blocks: u64 = descs.iter().map(ImageDesc::single_tail_blocks).sum();
        if single_tail_blocks >= self.budget_blocks() && single_tail_blocks > 0 {
            return Err(ConfigError::TailsOverBudget {
                tail_bytes: single_tail_blocks.saturating_mul(self.limits.sparse_block_bytes),
                budget_bytes: self.memory_budget_bytes,
            });
        }
        let needed_bytes = descs
            .iter()
            .fold(0u64, |sum, desc| sum.saturating_add(desc.virtual_bytes()));
        if needed_bytes > self.virtual_budget_bytes {
            let (largest_image, largest_bytes) = descs
                .iter()
                .enumerate()
                .map(|(index, desc)| (index, desc.virtual_bytes()))
                .max_by_key(|&(_, bytes)| bytes)
                .unwrap_or((0, 0));
            return Err(ConfigError::VirtualBudgetExceeded {
                needed_bytes,
                budget_bytes: self.virtual_budget_bytes,
                largest_image,
                largest_bytes,
            });
        }
        Ok(descs)
    }

    /// Memory budget in whole sparse blocks.
    pub fn budget_blocks(&self) -> u64 {
        self.memory_budget_bytes / self.limits.sparse_block_bytes.max(1)
    }
}

/// What the images of one format must place, for [`derive_image_layers`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ImageDemand {
    /// `(extent, textures)`: how many textures of each extent the format's
    /// images may have to place.
    pub extents: Vec<(u32, u64)>,
    /// Virtual bytes one layer spans (its block-padded full mip chain).
    pub layer_virtual_bytes: u64,
}

/// Layers of `layer_size`² that place every texture of `extents`
/// (`(extent, textures)`) at once: each extent packs `(layer_size / extent)²`
/// textures per layer (an extent above the layer takes a layer).
pub fn layers_to_place(layer_size: u32, extents: &[(u32, u64)]) -> u64 {
    extents
        .iter()
        .map(|&(extent, textures)| {
            let per_row = u64::from(layer_size / extent.clamp(1, layer_size.max(1)));
            textures.div_ceil((per_row * per_row).max(1))
        })
        .fold(0, u64::saturating_add)
}

/// The layers of each cache image, per format (one list per demand, one
/// count per image), derived from what each format must hold and what the
/// budget and the device allow, instead of a fixed count:
///
/// - enough layers to place every texture at once (each extent packs
///   `(layer_size / extent)²` textures per layer);
/// - no more than `budget_blocks`: a live layer holds at least one bound
///   block, so more layers could never be in use at once;
/// - at most `max_layers` per image (the device's `maxImageArrayLayers`, or
///   less): a format that needs more gets more images, shared evenly;
/// - at most `max_images` images in all (the shaders' slots), every format
///   at least one;
/// - all layers together within `virtual_budget_bytes`, shared in
///   proportion to demand.
///
/// Every format gets at least one layer. Where a limit leaves fewer layers
/// than textures need, the cache reuses layers as it runs.
pub fn derive_image_layers(
    layer_size: u32,
    demands: &[ImageDemand],
    budget_blocks: u64,
    max_layers: u32,
    max_images: u32,
    virtual_budget_bytes: u64,
) -> Vec<Vec<u32>> {
    let max_layers = u64::from(max_layers.max(1));
    let mut wanted: Vec<u64> = demands
        .iter()
        .map(|demand| layers_to_place(layer_size, &demand.extents).min(budget_blocks).max(1))
        .collect();
    // Images per format, then the slots shared out: the format with the
    // most images gives one up until they fit.
    let mut images: Vec<u64> = wanted.iter().map(|&layers| layers.div_ceil(max_layers)).collect();
    let slots = u64::from(max_images).max(demands.len() as u64);
    while images.iter().sum::<u64>() > slots {
        let Some(most) = images
            .iter_mut()
            .filter(|count| **count > 1)
            .max_by_key(|count| **count)
        else {
            break;
        };
        *most -= 1;
    }
    for (layers, &count) in wanted.iter_mut().zip(&images) {
        *layers = (*layers).min(count.saturating_mul(max_layers));
    }
    let total_virtual: u128 = wanted
        .iter()
        .zip(demands)
        .map(|(&layers, demand)| u128::from(layers) * u128::from(demand.layer_virtual_bytes))
        .sum();
    if total_virtual > u128::from(virtual_budget_bytes) {
        // Every format keeps one layer; the layers beyond it are scaled down
        // by the same factor, rounding down, so the sum stays within the budget.
        let first_layers: u128 = demands.iter().map(|d| u128::from(d.layer_virtual_bytes)).sum();
        let extra_virtual = total_virtual - first_layers;
        let room = u128::from(virtual_budget_bytes).saturating_sub(first_layers);
        for layers in &mut wanted {
            let extra = u128::from(*layers - 1) * room / extra_virtual.max(1);
            *layers = 1 + extra.min(u128::from(*layers - 1)) as u64;
        }
    }
    wanted
        .iter()
        .map(|&layers| {
            let count = layers.div_ceil(max_layers);
            (0..count)
                .map(|image| (layers / count + u64::from(image < layers % count)) as u32)
                .collect()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn demand(extents: &[(u32, u64)]) -> ImageDemand {
        ImageDemand {
            extents: extents.to_vec(),
            layer_virtual_bytes: 1 << 20,
        }
    }

    #[test]
    fn layers_follow_textures_budget_and_device() {
        // 2048-texel layers: 64 textures of 256 per layer, one of 2048.
        let city = [demand(&[(256, 640), (2048, 5)]), demand(&[(256, 1)])];
        let derive = |budget_blocks, max_layers, max_images, virtual_budget| {
            derive_image_layers(2048, &city, budget_blocks, max_layers, max_images, virtual_budget)
        };
        assert_eq!(derive(1 << 20, 2048, 8, u64::MAX), vec![vec![15], vec![1]]);
        // The budget caps it: 8 blocks can keep at most 8 layers live.
        assert_eq!(derive(8, 2048, 8, u64::MAX), vec![vec![8], vec![1]]);
        // A device with few layers per image: more images of the format,
        // shared evenly, as many layers in all.
        assert_eq!(derive(1 << 20, 4, 8, u64::MAX), vec![vec![4, 4, 4, 3], vec![1]]);
        assert_eq!(derive(10, 4, 8, u64::MAX), vec![vec![4, 3, 3], vec![1]]);
        // Few image slots: the format with the most images gives them up.
        assert_eq!(derive(1 << 20, 4, 3, u64::MAX), vec![vec![4, 4], vec![1]]);
        assert_eq!(derive(1 << 20, 4, 1, u64::MAX), vec![vec![4], vec![1]]);
        // The virtual budget is shared: 8 MiB for 16 MiB wanted.
        assert_eq!(derive(1 << 20, 2048, 8, 8 << 20), vec![vec![7], vec![1]]);
        assert_eq!(derive(1 << 20, 4, 8, 8 << 20), vec![vec![4, 3], vec![1]]);
        // A format with nothing to place keeps its one layer within the
        // budget: the others share what is left.
        let lopsided = [
            ImageDemand {
                extents: vec![(2048, 5000)],
                layer_virtual_bytes: 3 << 20,
            },
            ImageDemand {
                extents: vec![],
                layer_virtual_bytes: 22 << 20,
            },
        ];
        let budget = 2u64 << 30;
        let counts = derive_image_layers(2048, &lopsided, 1 << 20, 2048, 8, budget);
        let layers = |format: usize| counts[format].iter().map(|&l| u64::from(l)).sum::<u64>();
        let used = layers(0) * (3 << 20) + layers(1) * (22 << 20);
        assert!(used <= budget, "{counts:?} use {used} of {budget}");
        assert_eq!(counts, vec![vec![675], vec![1]]);
    }

    #[test]
    fn degenerate_inputs_still_give_one_layer() {
        let odd = [demand(&[(0, 3), (1 << 20, 2)]), demand(&[])];
        assert_eq!(derive_image_layers(2048, &odd, 0, 0, 0, 0), vec![vec![1], vec![1]]);
        // More than u32::MAX layers wanted: images of at most max_layers.
        let huge = [demand(&[(1, u64::MAX)])];
        let counts = derive_image_layers(1 << 15, &huge, u64::MAX, u32::MAX, 8, u64::MAX);
        assert_eq!(counts[0].len(), 5);
        assert_eq!(counts[0].iter().map(|&l| u64::from(l)).sum::<u64>(), 1 << 34);
    }
}
