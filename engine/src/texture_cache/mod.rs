//! The GPU half of the sparse texture cache (paper §3.6): sparse 2D-array
//! images per format (more than one where one image's layers are too few
//! for the format's share of the budget), pooled block memory, the per-texture
//! [`TextureData`] table and the City Colormap that shaders read.
//!
//! Packing, block accounting and eviction are the Vulkan-free
//! [`citystream_cache::TextureCache`]; this type carries its decisions out.
//!
//! One streaming cycle: [`GpuTextureCache::stage`] any number of mips (each
//! is packed, its blocks accounted, its bytes queued), then either
//! - [`GpuTextureCache::prepare_cycle`] and [`GpuTextureCache::record_cycle`]
//!   (frames in flight): evicted textures are marked not sampleable, new
//!   memory chunks are allocated, all binds and unbinds go out in one
//!   `vkQueueBindSparse` that waits on the GPU for the frames that could
//!   still sample evicted blocks, and the copies plus the table update are
//!   recorded into the caller's command buffer, whose submission waits on
//!   [`GpuTextureCache::bind_wait`]; or
//! - [`GpuTextureCache::finish_cycle`], which does the same in a one-shot
//!   submission and waits for it (tools, tests, reference renders).
//!
//! GPU safety: the table lives in device-local memory and changes only by
//! copies recorded in queue order after barriers, so frames in flight keep
//! reading the entries they were submitted with. Unbinds wait (on the GPU)
//! for the last frame submitted before the cycle, the one that could still
//! sample an evicted texture; each bind batch also waits for the previous
//! one, so memory freed by an unbind is rebound only after it. Staging space
//! and one-off buffers are released when [`GpuTextureCache::retire`] reports
//! the ticket of the submission that read them complete.

use std::sync::Arc;

use ash::vk;
use citystream_cache::{BudgetUse, CacheError, TexelFormat, TextureCache, Utilisation};
use citystream_dataset::TextureFormat;
use citystream_streaming::bind_latency::BatchShape;
pub use citystream_streaming::residency::planner::ResidentCache;

use crate::buffer::Buffer;
use crate::commands::CommandContext;
use crate::device::{Device, TextureBacking};
use crate::error::{EngineError, Result};
use crate::gpu_types::{TextureData, BINDING_CACHE_IMAGES, BINDING_COLORMAP, BINDING_TEXTURE_DATA, CACHE_IMAGE_SLOTS};
use crate::pipeline::{DescriptorResource, Filtering, Sampler};
use crate::scene::upload_buffer;
use crate::sparse::TexelUpload;
use crate::staging::StagingRing;
use backing::{build_images, BuiltImages, CacheImages};
use cycle::{StagingCycle, UploadStats};
use layout::FormatImages;
use table::TextureTable;

mod backing;
mod cycle;
mod layout;
mod table;

/// The formats the cache can hold. Each format of
/// [`GpuCacheConfig::formats`] has one sparse image or more; the images fill
/// the `BINDING_CACHE_IMAGES` array in this order.
pub const CACHE_FORMATS: [(TextureFormat, vk::Format, TexelFormat); 4] = [
    (TextureFormat::Bc1, vk::Format::BC1_RGB_UNORM_BLOCK, TexelFormat::BC1),
    (TextureFormat::Rgba8, vk::Format::R8G8B8A8_UNORM, TexelFormat::RGBA8),
    (TextureFormat::Bc3, vk::Format::BC3_UNORM_BLOCK, TexelFormat::BC3),
    (TextureFormat::Bc7, vk::Format::BC7_UNORM_BLOCK, TexelFormat::BC7),
];

pub use citystream_streaming::residency::Eviction;

/// How many array layers each cache image has.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum CacheLayers {
    /// One image per format of [`GpuCacheConfig::formats`], each with this
    /// many layers.
    Fixed(u32),
    /// Derived ([`citystream_cache::derive_image_layers`]) from the textures
    /// each format must place, the memory budget, the device's
    /// `maxImageArrayLayers` (or `max_layers` if lower; a format needing
    /// more gets more images, up to `CACHE_IMAGE_SLOTS` in all) and the
    /// virtual budget.
    Derived {
        /// Per format in [`CACHE_FORMATS`] order: `(extent, textures)`.
        extents: Vec<Vec<(u32, u64)>>,
        /// A lower layer limit than the device's, if any.
        max_layers: Option<u32>,
    },
}

/// Sizes and budgets of the cache.
#[derive(Clone, Debug, PartialEq)]
pub struct GpuCacheConfig {
    /// Side of every array layer in texels (a power of two).
    pub layer_size: u32,
    /// Images and layers per format.
    pub layers: CacheLayers,
    /// The formats of the textures the cache holds (each gets its own
    /// images); a texture of another format is refused.
    pub formats: Vec<TextureFormat>,
    /// Bytes of bound blocks allowed; reaching it evicts the oldest layer.
    pub memory_budget_bytes: u64,
    /// Virtual address space all cache images may span; `None` uses the
    /// device's `sparseAddressSpaceSize`, which drivers such as lavapipe do
    /// not enforce themselves.
    pub virtual_budget_bytes: Option<u64>,
    /// Blocks per device-memory chunk of the block pool.
    pub blocks_per_chunk: u32,
    /// Dataset textures the table covers (texture ids `0..texture_count`).
    pub texture_count: u32,
    /// Filtering of the cache sampler.
    pub filtering: Filtering,
    /// Bytes of the host-visible staging ring the uploads go through; a
    /// cycle whose uploads do not fit uses a one-off buffer instead.
    pub staging_bytes: u64,
    /// How memory is freed at the budget.
    pub eviction: Eviction,
}

/// A cache format's mip tail ([`GpuTextureCache::format_tails`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FormatTail {
    /// The format's name (`BC1`, `RGBA8`, ...).
    pub format: &'static str,
    /// First level in the tail; `None` without a tail.
    pub first_level: Option<u32>,
    /// Bytes of one tail (of a layer, or of the image when single).
    pub bytes_per_tail: u64,
    /// One tail per image (`SINGLE_MIPTAIL`) rather than per layer.
    pub single: bool,
    /// Forced by `CITYSTREAM_FORCE_MIP_TAIL` on a device without a tail.
    pub synthetic: bool,
    /// Tail bytes the format's images hold now (live, parked, single).
    pub held_bytes: u64,
}

/// What one [`GpuTextureCache::finish_cycle`] did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CycleReport {
    /// Blocks bound.
    pub blocks_bound: u32,
    /// Blocks unbound.
    pub blocks_unbound: u32,
    /// Bind entries submitted after merging.
    pub bind_entries: u32,
    /// The blocks bound and unbound and their runs in the images' layout, as the
    /// bind-latency models charge them (not the merged entries, which depend on where
    /// the allocator placed memory).
    pub bind_shape: BatchShape,
    /// Seconds the bind submission took on the CPU.
    pub bind_seconds: f64,
    /// Mips copied into the cache.
    pub mips_uploaded: u32,
    /// Bytes copied into the cache.
    pub bytes_uploaded: u64,
    /// Textures made unsampleable by eviction.
    pub textures_invalidated: u32,
    /// Their ids, for the streaming states (they must be loaded again).
    pub invalidated_textures: Vec<u32>,
}

impl CycleReport {
    /// Adds `other`'s counts to these (several cycles reported as one).
    pub fn absorb(&mut self, other: CycleReport) {
        self.blocks_bound += other.blocks_bound;
        self.blocks_unbound += other.blocks_unbound;
        self.bind_entries += other.bind_entries;
        self.bind_shape += other.bind_shape;
        self.bind_seconds += other.bind_seconds;
        self.mips_uploaded += other.mips_uploaded;
        self.bytes_uploaded += other.bytes_uploaded;
        self.textures_invalidated += other.textures_invalidated;
        self.invalidated_textures.extend(other.invalidated_textures);
    }
}

/// Outcome of [`GpuTextureCache::stage`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum StageOutcome {
    /// Queued for the next `finish_cycle`.
    Staged {
        /// Blocks this mip made the cache bind.
        new_blocks: u32,
    },
    /// The budget's freed memory is reusable only after the next
    /// `finish_cycle`; stop staging for this cycle.
    MemoryPending,
    /// [`Eviction::Ring`]: the room the mip needed was made by evicting the ring's oldest
    /// layer, and that layer held this texture; nothing was staged. The texture is no
    /// longer resident: load it again later (its next stage inserts it afresh).
    EvictedItself,
    /// [`Eviction::View`]: the budget has too few free blocks; nothing was
    /// staged.
    NoRoom {
        /// Blocks the mip needs newly bound.
        needed_blocks: u64,
    },
    /// [`Eviction::View`]: the texture needs a new layer and every layer of
    /// every image of its format is live; the caller may free one
    /// ([`GpuTextureCache::evict_layer`] on any of
    /// [`ResidentCache::images_sharing_format`]).
    NoLayer {
        /// The first cache image of the texture's format.
        image: u32,
        /// The texture's extent.
        extent: u32,
    },
}

/// Sparse cache images, block memory, texture table and colormap, in
/// parts of one job each: the images and what binds their memory
/// (`backing.rs`), which image holds which format (`layout.rs`), the texture
/// table (`table.rs`) and the staging cycle (`cycle.rs`). Residency queries
/// are its [`ResidentCache`] impl.
pub struct GpuTextureCache {
    device: Arc<Device>,
    /// The Vulkan-free packing, block accounting and eviction.
    cache: TextureCache,
    /// The images and what binds their memory.
    images: CacheImages,
    formats: FormatImages,
    /// Whether the layers place every texture of the source at once.
    holds_every_texture: bool,
    table: TextureTable,
    /// The device-local copy of `table`'s entries the shaders read.
    table_buffer: Buffer,
    colormap_buffer: Buffer,
    sampler: Sampler,
    cycle: StagingCycle,
    eviction: Eviction,
    stats: UploadStats,
}

debug_fields!(GpuTextureCache {
    backing = |s| s.backing().name(),
    images = |s| s.images.len(),
    textures = |s| s.table.slots().len(),
    pending_uploads = |s| s.cycle.pending.uploads().len(),
});

fn cache_error(texture: u32, mip: u32, error: CacheError) -> EngineError {
    EngineError::InvalidRequest(format!("texture {texture} mip {mip}: {error}"))
}

impl GpuTextureCache {
    /// Creates the cache images (transitioned for sampling), the table with
    /// every texture unsampleable, and the colormap (one RGBA8 per texture).
    pub fn new(
        device: &Arc<Device>,
        commands: &mut CommandContext,
        config: &GpuCacheConfig,
        colormap: &[[u8; 4]],
    ) -> Result<Self> {
        if colormap.len() != config.texture_count as usize || config.texture_count == 0 {
            return Err(EngineError::InvalidRequest(format!(
                "the cache covers {} textures but the colormap has {} colours",
                config.texture_count,
                colormap.len()
            )));
        }
        let mips = 32 - config.layer_size.max(1).leading_zeros();
        let held = layout::held_formats(config)?;
        let built = build_images(device, config, &held, mips)?;
        // Array layers are memory, so placing every texture means holding it;
        // sparse layers are address space, which says nothing of the budget.
        let holds_every_texture = matches!(built.images, CacheImages::Arrays { .. })
            && layout::holds_every_texture(config, &built.layer_counts);
        let BuiltImages {
            cache_config,
            images,
            formats,
            ..
        } = built;
        let cache = TextureCache::new(&cache_config).map_err(|e| EngineError::InvalidRequest(e.to_string()))?;

        let table = TextureTable::new(config.texture_count as usize);
        // Device-local and changed only by recorded copies, so frames in
        // flight never see an entry rewritten under them.
        let table_buffer = upload_buffer(
            device,
            commands,
            bytemuck::cast_slice(table.entries()),
            vk::BufferUsageFlags::STORAGE_BUFFER,
            "texture data table",
        )?;
        let packed: Vec<u32> = colormap.iter().map(|c| u32::from_le_bytes(*c)).collect();
        let colormap_buffer = upload_buffer(
            device,
            commands,
            bytemuck::cast_slice(&packed),
            vk::BufferUsageFlags::STORAGE_BUFFER,
            "city colormap",
        )?;
        let sampler = Sampler::new(device, config.filtering, "cache sampler")?;
        let staging = StagingRing::new(device, config.staging_bytes.max(64 * 1024))?;

        images.make_sampleable(device, commands)?;

        let mut cache = Self {
            device: Arc::clone(device),
            cache,
            images,
            formats,
            holds_every_texture,
            table,
            table_buffer,
            colormap_buffer,
            sampler,
            cycle: StagingCycle::new(staging),
            eviction: config.eviction,
            stats: UploadStats::new(config.texture_count as usize),
        };
        // Single mip tails are bound with the images, not in a frame's cycle.
        if cache.cache.images().iter().any(|image| image.single_tail_blocks() > 0) {
            cache.finish_cycle(commands)?;
        }
        Ok(cache)
    }

    /// The descriptors a pass needs to sample city textures (bindings
    /// `BINDING_CACHE_IMAGES`, an array whose unused elements repeat image
    /// 0, `BINDING_TEXTURE_DATA` and `BINDING_COLORMAP`).
    pub fn descriptors(&self) -> [(u32, DescriptorResource); 3] {
        let first = self.images.view(0).unwrap_or_default();
        let mut views = [first; CACHE_IMAGE_SLOTS as usize];
        for (index, slot) in views.iter_mut().enumerate() {
            *slot = self.images.view(index).unwrap_or(first);
        }
        [
            (
                BINDING_CACHE_IMAGES,
                DescriptorResource::SampledImageArray(views, self.sampler.raw()),
            ),
            (
                BINDING_TEXTURE_DATA,
                DescriptorResource::StorageBuffer(self.table_buffer.raw()),
            ),
            (
                BINDING_COLORMAP,
                DescriptorResource::StorageBuffer(self.colormap_buffer.raw()),
            ),
        ]
    }

    /// Whether every texture the cache was sized for ([`CacheLayers::Derived`])
    /// fits at once, within the budget and the device's limits: texture
    /// arrays with a layer for each (always `false` for sparse images).
    pub fn holds_every_texture(&self) -> bool {
        self.holds_every_texture
    }

    /// Bytes of the mips staged in this cycle, not yet recorded.
    pub fn staged_bytes(&self) -> u64 {
        self.cycle.pending.bytes().len() as u64
    }

    /// Bytes of the staging ring the uploads go through; a cycle staging more
    /// uses a one-off buffer of its size.
    pub fn staging_capacity(&self) -> u64 {
        self.cycle.staging.capacity()
    }

    /// How the cache holds textures: sparse images or texture arrays.
    pub fn backing(&self) -> TextureBacking {
        match self.images {
            CacheImages::Sparse { .. } => TextureBacking::Sparse,
            CacheImages::Arrays { .. } => TextureBacking::Arrays,
        }
    }

    /// Device memory holding texels: the bound blocks of sparse images, or
    /// every layer's full mip chain of the texture arrays (bound from the
    /// start, whatever is loaded).
    pub fn texel_memory_bytes(&self) -> u64 {
        self.images
            .array_bytes()
            .unwrap_or_else(|| self.cache.utilisation().held_bytes())
    }

    /// Bytes of the distinct `(texture, level)` pairs uploaded so far, each
    /// counted once however often it was uploaded.
    pub fn unique_bytes_uploaded(&self) -> u64 {
        self.stats.unique_bytes()
    }

    /// Texture bytes released by [`drop_finest`](Self::drop_finest) so far.
    pub fn dropped_bytes(&self) -> u64 {
        self.stats.dropped_bytes()
    }

    /// The index of `format` in [`CACHE_FORMATS`], if the cache holds it.
    pub fn format_index(format: TextureFormat) -> Option<usize> {
        CACHE_FORMATS.iter().position(|(f, _, _)| *f == format)
    }

    /// Evicts live layer `layer` of `image` ([`Eviction::View`]): its
    /// textures become unsampleable in this cycle's table update and are
    /// reported in the cycle's `invalidated_textures`; its blocks are
    /// unbound after the frames submitted before.
    pub fn evict_layer(&mut self, image: u32, layer: u32) -> Result<()> {
        self.cache
            .evict_layer(image, layer)
            .map_err(|e| EngineError::InvalidRequest(format!("evicting layer {layer} of image {image}: {e}")))
    }

    /// Drops the finest resident level of `texture` ([`Eviction::View`]):
    /// the texture's table entry stops naming it in this cycle's update,
    /// recorded before the frame's passes, and its blocks no other level
    /// uses are unbound by the next bind batch, which waits for the frames
    /// submitted before. Returns the level and the blocks freed; `None` if
    /// nothing is resident, a mip of it is staged in this cycle, or its layer
    /// was evicted in this cycle (its levels are gone already).
    pub fn drop_finest(&mut self, texture: u32) -> Result<Option<(u32, u32)>> {
        let Some(slot) = self.table.slot(texture) else {
            return Err(EngineError::InvalidRequest(format!(
                "texture {texture} is outside the cache's table"
            )));
        };
        let Some(placement) = slot.placement else {
            return Ok(None);
        };
        // A layer evicted earlier in this cycle still shows its textures'
        // levels as resident until the cycle reports it.
        if slot.resident == 0 || slot.pending != 0 || !self.cache.is_live(&placement) {
            return Ok(None);
        }
        let mip = slot.resident.trailing_zeros();
        let freed = self
            .cache
            .drop_mip(&placement, mip)
            .map_err(|e| cache_error(texture, mip, e))?;
        self.stats.dropped(self.level_bytes(texture, mip));
        self.table.slot_mut(texture).resident &= !(1 << mip);
        self.table.publish(texture);
        Ok(Some((mip, freed)))
    }

    /// The table entry the shaders see for `texture`.
    pub fn texture_data(&self, texture: u32) -> Option<&TextureData> {
        self.table.entry(texture)
    }

    /// The finest level `texture` was ever sampleable at, `None` if it never was: a
    /// texture whose entry is coarser now lost levels to the budget (dropped or evicted).
    pub fn finest_ever_sampleable(&self, texture: u32) -> Option<u32> {
        self.table.finest_published(texture)
    }

    /// Texture bytes versus bound bytes.
    pub fn utilisation(&self) -> Utilisation {
        self.cache.utilisation()
    }

    /// Per cache format held (in [`CACHE_FORMATS`] order), its mip tail:
    /// where it starts, its bytes, single or per layer, and the tail bytes
    /// its images hold now. Texture arrays have no tail.
    pub fn format_tails(&self) -> Vec<FormatTail> {
        let held = self.cache.tail_bytes_held();
        let descs = self.cache.images();
        let mut tails: Vec<FormatTail> = Vec::new();
        for (format_index, images) in self.formats.iter() {
            let Some(&first) = images.first() else { continue };
            let Some(desc) = descs.get(first as usize) else {
                continue;
            };
            let synthetic = self.images.sparse_tail_synthetic(first as usize);
            tails.push(FormatTail {
                format: CACHE_FORMATS[format_index].2.name,
                first_level: desc.mip_tail.map(|tail| tail.first_level),
                bytes_per_tail: desc.tail_bytes(),
                single: desc.mip_tail.is_some_and(|tail| tail.single),
                synthetic,
                held_bytes: images.iter().filter_map(|&image| held.get(image as usize)).sum(),
            });
        }
        tails
    }

    /// The Vulkan-free cache (for statistics and block queries).
    pub fn packing(&self) -> &TextureCache {
        &self.cache
    }

    /// Queues mip `mip` of `texture` (a `width`×`height` texture of
    /// `format`) with its bytes, packing the texture first if it has no live
    /// place. The bytes must be exactly the mip's size in `format`.
    pub fn stage(
        &mut self,
        texture: u32,
        format: TextureFormat,
        width: u32,
        height: u32,
        mip: u32,
        bytes: &[u8],
    ) -> Result<StageOutcome> {
        let slot = self
            .table
            .slot(texture)
            .ok_or_else(|| EngineError::InvalidRequest(format!("texture {texture} is outside the cache's table")))?;
        let format_index = Self::format_index(format)
            .filter(|&index| !self.formats.of_format(index).is_empty())
            .ok_or_else(|| EngineError::UnsupportedFormat {
                texture,
                format: format!("{format:?}"),
                reason: "the cache has no sparse image of that format".into(),
            })?;
        let texel_format = CACHE_FORMATS[format_index].2;
        let images = self.formats.of_format(format_index);
        let placement = match slot.placement {
            Some(p)
                if self.cache.is_live(&p) && images.contains(&p.image) && p.width == width && p.height == height =>
            {
                p
            }
            _ => {
                let inserted = match self.eviction {
                    Eviction::Ring => self.cache.insert_in(images, u64::from(texture), width, height),
                    Eviction::View => self.cache.try_insert_in(images, u64::from(texture), width, height),
                };
                let fresh = match inserted {
                    Ok(fresh) => fresh,
                    Err(CacheError::NoLayer { image, extent }) => return Ok(StageOutcome::NoLayer { image, extent }),
                    Err(e) => return Err(cache_error(texture, mip, e)),
                };
                // A new place starts empty; the old one (if any) is no longer
                // sampled, whether or not its eviction was reported yet.
                self.table.place(texture, Some(fresh));
                fresh
            }
        };
        let rect = placement.mip_rect(mip).map_err(|e| cache_error(texture, mip, e))?;
        let expected = texel_format.image_bytes(rect.width, rect.height);
        if bytes.len() as u64 != expected {
            return Err(EngineError::InvalidRequest(format!(
                "texture {texture} mip {mip}: {} bytes given, a {}x{} {} level needs {expected}",
                bytes.len(),
                rect.width,
                rect.height,
                texel_format.name
            )));
        }
        let staged = match self.eviction {
            Eviction::Ring => self.cache.stage_mip(&placement, mip),
            Eviction::View => self.cache.try_stage_mip(&placement, mip),
        };
        let upload = match staged {
            Ok(upload) => upload,
            Err(CacheError::MemoryPending { .. }) => return Ok(StageOutcome::MemoryPending),
            Err(CacheError::NoRoom { needed_blocks, .. }) => return Ok(StageOutcome::NoRoom { needed_blocks }),
            // Not a failure of the texture: the ring reached its own layer.
            Err(CacheError::Invalidated { .. }) => return Ok(StageOutcome::EvictedItself),
            Err(e) => return Err(cache_error(texture, mip, e)),
        };
        self.table.slot_mut(texture).pending |= 1 << mip;
        // Copies of block formats cover whole blocks even for levels below 4x4.
        let (bw, bh) = (texel_format.block_width, texel_format.block_height);
        let copy = TexelUpload {
            layer: upload.layer,
            mip,
            x: rect.x,
            y: rect.y,
            width: rect.width.div_ceil(bw) * bw,
            height: rect.height.div_ceil(bh) * bh,
            buffer_offset: 0,
        };
        self.cycle.pending.push(texture, placement, copy, bytes);
        Ok(StageOutcome::Staged {
            new_blocks: upload.new_blocks,
        })
    }
}

impl Drop for GpuTextureCache {
    fn drop(&mut self) {
        // The images, the table and the staging may still be read by submitted
        // frames; a device lost leaves nothing better to do than free them anyway.
        let _ = self.device.wait_idle();
    }
}

/// The residency planner's view of the cache
/// (`citystream_streaming::residency::planner`), and the cache's own API for
/// residency: callers bring the trait into scope ([`ResidentCache`] is
/// re-exported here).
impl ResidentCache for GpuTextureCache {
    /// Textures with resident levels, in id order.
    fn resident_textures(&self) -> impl Iterator<Item = u32> + '_ {
        self.table
            .slots()
            .iter()
            .enumerate()
            .filter(|(_, s)| s.resident != 0)
            .map(|(texture, _)| texture as u32)
    }

    /// Bit m set: mip m of `texture` is resident in its current place
    /// (copied, or recorded to be copied, and not evicted).
    fn resident_levels(&self, texture: u32) -> u32 {
        self.table.slot(texture).map_or(0, |s| s.resident)
    }

    /// Levels of `texture` resident or staged in the current cycle.
    fn held_levels(&self, texture: u32) -> u32 {
        self.table.slot(texture).map_or(0, |s| s.resident | s.pending)
    }

    /// Whether `texture` has mips staged in the current cycle.
    fn has_pending(&self, texture: u32) -> bool {
        self.table.slot(texture).is_some_and(|s| s.pending != 0)
    }

    /// Bytes of level `level` of `texture` in its place (0 if it has none).
    fn level_bytes(&self, texture: u32, level: u32) -> u64 {
        let Some(placement) = self.table.slot(texture).and_then(|s| s.placement) else {
            return 0;
        };
        placement
            .mip_rect(level)
            .map_or(0, |rect| placement.format.image_bytes(rect.width, rect.height))
    }

    /// Blocks that dropping resident level `level` of `texture` would free.
    fn exclusive_blocks(&self, texture: u32, level: u32) -> u32 {
        self.table
            .slot(texture)
            .and_then(|s| s.placement)
            .map_or(0, |placement| self.cache.exclusive_blocks(&placement, level))
    }

    /// Bound blocks against the budget.
    fn budget_use(&self) -> BudgetUse {
        self.cache.budget_use()
    }

    /// The images holding textures of the same format as `image` (itself
    /// included), in index order.
    fn images_sharing_format(&self, image: u32) -> &[u32] {
        self.formats.sharing(image)
    }

    /// Textures placed in each live layer of `image`: `(layer, textures)`,
    /// layers oldest first.
    fn layer_textures(&self, image: u32) -> Vec<(u32, Vec<u32>)> {
        self.cache
            .live_layer_keys(image)
            .into_iter()
            .map(|(layer, keys)| (layer, keys.into_iter().filter_map(|k| u32::try_from(k).ok()).collect()))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cycles_absorbed_add_their_counts_and_keep_every_invalidated_texture() {
        let mut total = CycleReport {
            blocks_bound: 3,
            bind_seconds: 0.5,
            textures_invalidated: 1,
            invalidated_textures: vec![9],
            ..CycleReport::default()
        };
        total.absorb(CycleReport {
            blocks_bound: 2,
            blocks_unbound: 4,
            bind_entries: 1,
            bind_seconds: 0.25,
            mips_uploaded: 5,
            bytes_uploaded: 4096,
            textures_invalidated: 2,
            invalidated_textures: vec![3, 9],
            bind_shape: BatchShape {
                bound: 2,
                unbound: 4,
                bind_runs: 1,
                unbind_runs: 2,
            },
        });
        assert_eq!(
            (total.blocks_bound, total.blocks_unbound, total.bind_entries),
            (5, 4, 1)
        );
        assert_eq!((total.bind_shape.blocks(), total.bind_shape.runs()), (6, 3));
        assert_eq!((total.mips_uploaded, total.bytes_uploaded), (5, 4096));
        assert_eq!(total.bind_seconds, 0.75);
        assert_eq!(total.textures_invalidated, 3);
        assert_eq!(total.invalidated_textures, vec![9, 3, 9]);
    }

    #[test]
    fn each_dataset_format_has_its_cache_format() {
        for format in [
            TextureFormat::Bc1,
            TextureFormat::Rgba8,
            TextureFormat::Bc3,
            TextureFormat::Bc7,
        ] {
            let index = GpuTextureCache::format_index(format).expect("a cache format");
            assert_eq!(CACHE_FORMATS[index].0, format);
        }
        assert_eq!(GpuTextureCache::format_index(TextureFormat::Bc1), Some(0));
    }
}
