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
use citystream_cache::{
    BudgetUse, CacheConfig, CacheError, DeviceLimits, Granularity, ImageConfig, Placement, TexelFormat, TextureCache,
    Utilisation,
};
use citystream_dataset::TextureFormat;
use citystream_streaming::residency::planner::ResidentCache;
use gpu_allocator::MemoryLocation;

use crate::binder::{cache_mip_tail, VulkanBinder};
use crate::buffer::{Buffer, BufferDesc};
use crate::commands::CommandContext;
use crate::device::{Device, TextureBacking};
use crate::error::{EngineError, Result};
use crate::gpu_types::{
    TextureData, BINDING_CACHE_IMAGES, BINDING_COLORMAP, BINDING_TEXTURE_DATA, CACHE_IMAGE_SLOTS,
    TEXTURE_NOT_SAMPLEABLE,
};
use crate::pipeline::{DescriptorResource, Filtering, Sampler};
use crate::scene::upload_buffer;
use crate::sparse::{SparseImage, SparseImageDesc, TexelUpload};
use crate::staging::StagingRing;
use backing::{accounting_granularity, CacheImages, ARRAY_ACCOUNTING_BLOCK_BYTES, CACHE_USAGE};
use layout::LayerProbe;

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
    /// [`GpuTextureCache::images_sharing_format`]).
    NoLayer {
        /// The first cache image of the texture's format.
        image: u32,
        /// The texture's extent.
        extent: u32,
    },
}

#[derive(Clone, Debug)]
struct PendingUpload {
    texture: u32,
    placement: Placement,
    upload: TexelUpload,
    image: u32,
    bytes: std::ops::Range<usize>,
}

/// Per-texture host state behind the GPU table.
#[derive(Clone, Copy, Debug, Default)]
struct TextureSlot {
    placement: Option<Placement>,
    /// Bit m set: mip m is resident (copied and not evicted).
    resident: u32,
    /// Bit m set: mip m is staged in this cycle, not yet recorded.
    pending: u32,
}

/// Sparse cache images, block memory, texture table and colormap.
pub struct GpuTextureCache {
    device: Arc<Device>,
    cache: TextureCache,
    images: CacheImages,
    /// Per image, its format's index in [`CACHE_FORMATS`].
    image_formats: Vec<usize>,
    /// Per format in [`CACHE_FORMATS`], its images.
    format_images: Vec<Vec<u32>>,
    /// Whether the layers place every texture of the source at once.
    holds_every_texture: bool,
    slots: Vec<TextureSlot>,
    table: Vec<TextureData>,
    table_buffer: Buffer,
    colormap_buffer: Buffer,
    sampler: Sampler,
    uploads: Vec<PendingUpload>,
    upload_bytes: Vec<u8>,
    staging: StagingRing,
    /// Textures whose table entry changed since the last table copy.
    dirty: Vec<u32>,
    dirty_flags: Vec<bool>,
    /// The cycle prepared by `prepare_cycle`, waiting for `record_cycle`.
    prepared: Option<PreparedCycle>,
    /// One-off staging buffers, each with the ticket after which it is free.
    retiring: std::collections::VecDeque<(u64, Buffer)>,
    /// The highest ticket handed to `prepare_cycle`.
    last_ticket: u64,
    eviction: Eviction,
    /// Mip bytes per texture level that `drop_finest` released.
    dropped_bytes: u64,
    /// Per texture, bit m: level m was uploaded at least once.
    uploaded_levels: Vec<u32>,
    /// Bytes of the distinct (texture, level) pairs uploaded.
    unique_bytes_uploaded: u64,
}

/// Where a prepared cycle's upload bytes wait and what it did so far.
#[derive(Debug)]
struct PreparedCycle {
    ticket: u64,
    /// Buffer and offset of the first upload byte, when there are uploads.
    source: Option<(vk::Buffer, u64)>,
    report: CycleReport,
}

debug_fields!(GpuTextureCache {
    backing = |s| s.backing().name(),
    images = |s| s.images.len(),
    textures = |s| s.slots.len(),
    pending_uploads = |s| s.uploads.len(),
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
        let built = match device.texture_backing() {
            TextureBacking::Sparse => sparse_images(device, config, &held, mips)?,
            TextureBacking::Arrays => array_images(device, config, &held, mips)?,
        };
        // Array layers are memory, so placing every texture means holding it;
        // sparse layers are address space, which says nothing of the budget.
        let holds_every_texture = matches!(built.images, CacheImages::Arrays { .. })
            && layout::holds_every_texture(config, &built.layer_counts);
        let BuiltImages {
            cache_config,
            images,
            image_formats,
            format_images,
            ..
        } = built;
        let cache = TextureCache::new(&cache_config).map_err(|e| EngineError::InvalidRequest(e.to_string()))?;

        let table = vec![TextureData::default(); config.texture_count as usize];
        // Device-local and changed only by recorded copies, so frames in
        // flight never see an entry rewritten under them.
        let table_buffer = upload_buffer(
            device,
            commands,
            bytemuck::cast_slice(&table),
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
            image_formats,
            format_images,
            holds_every_texture,
            slots: vec![TextureSlot::default(); config.texture_count as usize],
            table,
            table_buffer,
            colormap_buffer,
            sampler,
            uploads: Vec::new(),
            upload_bytes: Vec::new(),
            staging,
            dirty: Vec::new(),
            dirty_flags: vec![false; config.texture_count as usize],
            prepared: None,
            retiring: std::collections::VecDeque::new(),
            last_ticket: 0,
            eviction: config.eviction,
            dropped_bytes: 0,
            uploaded_levels: vec![0; config.texture_count as usize],
            unique_bytes_uploaded: 0,
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

    /// Bit m set: mip m of `texture` is resident in its current place
    /// (copied, or recorded to be copied, and not evicted).
    pub fn resident_levels(&self, texture: u32) -> u32 {
        self.slots.get(texture as usize).map_or(0, |s| s.resident)
    }

    /// Levels of `texture` resident or staged in the current cycle.
    pub fn held_levels(&self, texture: u32) -> u32 {
        self.slots.get(texture as usize).map_or(0, |s| s.resident | s.pending)
    }

    /// Whether `texture` has mips staged in the current cycle.
    pub fn has_pending(&self, texture: u32) -> bool {
        self.slots.get(texture as usize).is_some_and(|s| s.pending != 0)
    }

    /// Textures with resident levels, in id order.
    pub fn resident_textures(&self) -> impl Iterator<Item = u32> + '_ {
        self.slots
            .iter()
            .enumerate()
            .filter(|(_, s)| s.resident != 0)
            .map(|(texture, _)| texture as u32)
    }

    /// Bytes of level `mip` of `texture` in its place (0 if it has none).
    pub fn level_bytes(&self, texture: u32, mip: u32) -> u64 {
        let Some(placement) = self.slots.get(texture as usize).and_then(|s| s.placement) else {
            return 0;
        };
        placement
            .mip_rect(mip)
            .map_or(0, |rect| placement.format.image_bytes(rect.width, rect.height))
    }

    /// Blocks that dropping resident level `mip` of `texture` would free.
    pub fn exclusive_blocks(&self, texture: u32, mip: u32) -> u32 {
        self.slots
            .get(texture as usize)
            .and_then(|s| s.placement)
            .map_or(0, |placement| self.cache.exclusive_blocks(&placement, mip))
    }

    /// Bound blocks against the budget.
    pub fn budget_use(&self) -> BudgetUse {
        self.cache.budget_use()
    }

    /// Whether every texture the cache was sized for ([`CacheLayers::Derived`])
    /// fits at once, within the budget and the device's limits: texture
    /// arrays with a layer for each (always `false` for sparse images).
    pub fn holds_every_texture(&self) -> bool {
        self.holds_every_texture
    }

    /// Bytes of the mips staged in this cycle, not yet recorded.
    pub fn staged_bytes(&self) -> u64 {
        self.upload_bytes.len() as u64
    }

    /// Bytes of the staging ring the uploads go through; a cycle staging more
    /// uses a one-off buffer of its size.
    pub fn staging_capacity(&self) -> u64 {
        self.staging.capacity()
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
        self.unique_bytes_uploaded
    }

    /// Texture bytes released by [`drop_finest`](Self::drop_finest) so far.
    pub fn dropped_bytes(&self) -> u64 {
        self.dropped_bytes
    }

    /// The index of `format` in [`CACHE_FORMATS`], if the cache holds it.
    pub fn format_index(format: TextureFormat) -> Option<usize> {
        CACHE_FORMATS.iter().position(|(f, _, _)| *f == format)
    }

    /// The images holding textures of the same format as `image` (itself
    /// included), in index order.
    pub fn images_sharing_format(&self, image: u32) -> &[u32] {
        self.image_formats
            .get(image as usize)
            .map_or(&[], |&format| self.format_images[format].as_slice())
    }

    /// Textures placed in each live layer of `image`: `(layer, textures)`,
    /// layers oldest first.
    pub fn layer_textures(&self, image: u32) -> Vec<(u32, Vec<u32>)> {
        self.cache
            .live_layer_keys(image)
            .into_iter()
            .map(|(layer, keys)| (layer, keys.into_iter().filter_map(|k| u32::try_from(k).ok()).collect()))
            .collect()
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
        let Some(slot) = self.slots.get(texture as usize).copied() else {
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
        self.dropped_bytes += self.level_bytes(texture, mip);
        self.slots[texture as usize].resident &= !(1 << mip);
        self.publish(texture);
        Ok(Some((mip, freed)))
    }

    /// The table entry the shaders see for `texture`.
    pub fn texture_data(&self, texture: u32) -> Option<&TextureData> {
        self.table.get(texture as usize)
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
        for (format_index, images) in self.format_images.iter().enumerate() {
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
        let slot = *self
            .slots
            .get(texture as usize)
            .ok_or_else(|| EngineError::InvalidRequest(format!("texture {texture} is outside the cache's table")))?;
        let format_index = Self::format_index(format)
            .filter(|&index| !self.format_images[index].is_empty())
            .ok_or_else(|| EngineError::UnsupportedFormat {
                texture,
                format: format!("{format:?}"),
                reason: "the cache has no sparse image of that format".into(),
            })?;
        let texel_format = CACHE_FORMATS[format_index].2;
        let images = &self.format_images[format_index];
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
                let slot = &mut self.slots[texture as usize];
                slot.placement = Some(fresh);
                slot.resident = 0;
                slot.pending = 0;
                self.table[texture as usize].state = TEXTURE_NOT_SAMPLEABLE;
                self.mark_dirty(texture);
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
        self.slots[texture as usize].pending |= 1 << mip;
        let start = self.upload_bytes.len();
        self.upload_bytes.extend_from_slice(bytes);
        // Copies of block formats cover whole blocks even for levels below 4x4.
        let (bw, bh) = (texel_format.block_width, texel_format.block_height);
        self.uploads.push(PendingUpload {
            texture,
            placement,
            image: placement.image,
            upload: TexelUpload {
                layer: upload.layer,
                mip,
                x: rect.x,
                y: rect.y,
                width: rect.width.div_ceil(bw) * bw,
                height: rect.height.div_ceil(bh) * bh,
                buffer_offset: 0,
            },
            bytes: start..start + bytes.len(),
        });
        Ok(StageOutcome::Staged {
            new_blocks: upload.new_blocks,
        })
    }
}

/// What [`GpuTextureCache::new`] builds for a backing.
struct BuiltImages {
    /// The Vulkan-free cache's configuration.
    cache_config: CacheConfig,
    images: CacheImages,
    /// Each image's format (an index into [`CACHE_FORMATS`]).
    image_formats: Vec<usize>,
    /// Each format's images.
    format_images: Vec<Vec<u32>>,
    /// Per format, the layers of each of its images.
    layer_counts: Vec<Vec<u32>>,
}

/// The images of `layer_counts` (per format in [`CACHE_FORMATS`] order) in
/// image order: `(format index, nth image of the format, layers)`.
fn image_layouts(layer_counts: &[Vec<u32>]) -> Vec<(usize, usize, u32)> {
    layer_counts
        .iter()
        .enumerate()
        .flat_map(|(format, counts)| {
            counts
                .iter()
                .enumerate()
                .map(move |(nth, &layers)| (format, nth, layers))
        })
        .collect()
}

/// A cache image of `layers` square layers of `config`'s size with `mips` levels.
fn image_desc(config: &GpuCacheConfig, layers: u32, mips: u32, format: vk::Format) -> SparseImageDesc {
    SparseImageDesc {
        width: config.layer_size,
        height: config.layer_size,
        layers,
        mips,
        format,
    }
}

/// Each image's format and each format's images, for `layouts`.
fn format_indices(layouts: &[(usize, usize, u32)]) -> (Vec<usize>, Vec<Vec<u32>>) {
    let mut format_images = vec![Vec::new(); CACHE_FORMATS.len()];
    for (image, &(format, _, _)) in layouts.iter().enumerate() {
        format_images[format].push(image as u32);
    }
    (layouts.iter().map(|&(format, _, _)| format).collect(), format_images)
}

/// Sparse cache images: layers derived within the device's sparse address
/// space, the block size and granularity the device reports.
fn sparse_images(device: &Arc<Device>, config: &GpuCacheConfig, held: &[usize], mips: u32) -> Result<BuiltImages> {
    let limits = device.properties().limits;
    let virtual_budget_bytes = config
        .virtual_budget_bytes
        .unwrap_or(device.sparse_support().address_space_size);
    let layer_counts = layout::plan_layer_counts(
        config,
        held,
        limits.max_image_array_layers,
        virtual_budget_bytes,
        |index| {
            let (_, vk_format, texel_format) = CACHE_FORMATS[index];
            probe_layer(device, config.layer_size, vk_format, texel_format)
        },
    )?;
    let layouts = image_layouts(&layer_counts);
    let mut images = Vec::with_capacity(layouts.len());
    let mut image_configs = Vec::with_capacity(layouts.len());
    for &(format_index, nth, layers) in &layouts {
        let (_, vk_format, texel_format) = CACHE_FORMATS[format_index];
        let image = SparseImage::new(
            device,
            image_desc(config, layers, mips, vk_format),
            &format!("cache {} #{nth}", texel_format.name),
        )?;
        ensure_served(device, &image)?;
        let (gw, gh) = image.granularity();
        image_configs.push(ImageConfig {
            format: texel_format,
            granularity: Granularity::texels(gw, gh),
            layer_size: config.layer_size,
            layer_count: layers,
            mip_tail: cache_mip_tail(&image),
        });
        images.push(Arc::new(image));
    }
    let block_size = images.iter().map(|i| i.block_size()).max().unwrap_or(0);
    let memory_type_bits = images.iter().fold(u32::MAX, |bits, i| bits & i.memory_type_bits());
    if images.iter().any(|i| i.block_size() != block_size) {
        return Err(EngineError::InvalidRequest(
            "cache images report different sparse block sizes; one block pool cannot serve them".into(),
        ));
    }
    let cache_config = CacheConfig {
        images: image_configs,
        limits: DeviceLimits {
            max_image_array_layers: limits.max_image_array_layers,
            max_image_dimension_2d: limits.max_image_dimension2_d,
            sparse_block_bytes: block_size,
        },
        memory_budget_bytes: config.memory_budget_bytes,
        virtual_budget_bytes,
        blocks_per_chunk: config.blocks_per_chunk,
    };
    let binder = VulkanBinder::new(device, images.clone())?;
    let (image_formats, format_images) = format_indices(&layouts);
    let images = CacheImages::Sparse {
        images,
        binder: Box::new(binder),
        block_size,
        memory_type_bits,
    };
    Ok(BuiltImages {
        cache_config,
        images,
        image_formats,
        format_images,
        layer_counts,
    })
}

/// Texture arrays: fully bound images whose layers, each a full mip chain's
/// memory, share out the memory budget (at most the layers the textures
/// need, the device's layer and resource-size limits per image, and half the
/// largest device-local heap: the layers are allocated whole, whatever is
/// loaded, and geometry, targets and an error reference need room too).
fn array_images(device: &Arc<Device>, config: &GpuCacheConfig, held: &[usize], mips: u32) -> Result<BuiltImages> {
    let limits = device.properties().limits;
    let heap_share = device.device_local_heap_bytes() / 2;
    let budget = config.memory_budget_bytes.min(heap_share.max(1));
    let config = &GpuCacheConfig {
        memory_budget_bytes: budget,
        ..config.clone()
    };
    let mut layer_bytes = [0u64; CACHE_FORMATS.len()];
    let mut max_layers = limits.max_image_array_layers;
    for &index in held {
        let (_, vk_format, _) = CACHE_FORMATS[index];
        let (bytes, format_max_layers) = array_layer_cost(device, config.layer_size, mips, vk_format)?;
        layer_bytes[index] = bytes;
        max_layers = max_layers.min(format_max_layers);
    }
    let layer_counts = layout::plan_layer_counts(config, held, max_layers, config.memory_budget_bytes, |index| {
        Ok(LayerProbe {
            block_bytes: ARRAY_ACCOUNTING_BLOCK_BYTES,
            virtual_bytes: layer_bytes[index],
        })
    })?;
    let layouts = image_layouts(&layer_counts);
    // Fixed layer counts are the caller's; the device's limits still hold.
    if let Some(&(format, _, layers)) = layouts.iter().find(|&&(_, _, layers)| layers > max_layers) {
        return Err(EngineError::InvalidRequest(format!(
            "{layers} layers of {}x{} {} texels in one array image; the device allows {max_layers}",
            config.layer_size, config.layer_size, CACHE_FORMATS[format].2.name
        )));
    }
    let needed: u64 = layouts
        .iter()
        .map(|&(format, _, layers)| u64::from(layers).saturating_mul(layer_bytes[format]))
        .fold(0, u64::saturating_add);
    if needed > config.memory_budget_bytes {
        let smallest = held.iter().map(|&index| layer_bytes[index]).min().unwrap_or(0);
        return Err(EngineError::InvalidRequest(format!(
            "the texture-array cache needs {needed} bytes for {:?} layers of {}x{} texels (a layer is its \
             full mip chain, {smallest} bytes or more), above the memory budget of {} bytes; raise the \
             budget or lower the layer size",
            layer_counts.iter().map(|c| c.iter().sum::<u32>()).collect::<Vec<_>>(),
            config.layer_size,
            config.layer_size,
            config.memory_budget_bytes
        )));
    }
    let cache_limits = DeviceLimits {
        max_image_array_layers: limits.max_image_array_layers,
        max_image_dimension_2d: limits.max_image_dimension2_d,
        sparse_block_bytes: ARRAY_ACCOUNTING_BLOCK_BYTES,
    };
    let mut image_configs = Vec::with_capacity(layouts.len());
    let mut descs = Vec::with_capacity(layouts.len());
    for &(format_index, nth, layers) in &layouts {
        let (_, vk_format, texel_format) = CACHE_FORMATS[format_index];
        image_configs.push(ImageConfig {
            format: texel_format,
            granularity: accounting_granularity(texel_format, ARRAY_ACCOUNTING_BLOCK_BYTES),
            layer_size: config.layer_size,
            layer_count: layers,
            mip_tail: None,
        });
        descs.push((
            image_desc(config, layers, mips, vk_format),
            format!("cache {} array #{nth}", texel_format.name),
        ));
    }
    // Every layer's blocks fit the accounting budget, so only layers run
    // out: the budget was spent on them when the images were made.
    let mut accounted = 0u64;
    for (index, image_config) in image_configs.iter().enumerate() {
        let desc = citystream_cache::ImageDesc::new(index, image_config, &cache_limits)
            .map_err(|e| EngineError::InvalidRequest(e.to_string()))?;
        accounted = accounted.saturating_add(desc.virtual_bytes());
    }
    let cache_config = CacheConfig {
        images: image_configs,
        limits: cache_limits,
        memory_budget_bytes: accounted,
        virtual_budget_bytes: accounted,
        blocks_per_chunk: config.blocks_per_chunk,
    };
    let images = CacheImages::arrays(device, &descs)?;
    // The layers were counted from one layer's cost; what the images took is
    // what holds the budget.
    let held_bytes = images.array_bytes().unwrap_or(0);
    if held_bytes > config.memory_budget_bytes {
        return Err(EngineError::InvalidRequest(format!(
            "the texture-array images took {held_bytes} bytes of device memory, above the budget of {} bytes \
             (the device's layers cost more than one layer's requirements said)",
            config.memory_budget_bytes
        )));
    }
    let (image_formats, format_images) = format_indices(&layouts);
    Ok(BuiltImages {
        cache_config,
        images,
        image_formats,
        format_images,
        layer_counts,
    })
}

/// Bytes one layer of a fully bound `layer_size`² array image of `format`
/// with `mips` levels takes, from the device's memory requirements (what a
/// second layer adds to a one-layer image, so its alignment counts), and the
/// most layers one image may have: the device's `maxArrayLayers` for the
/// format, its `maxResourceSize` and `maxMemoryAllocationSize`.
fn array_layer_cost(device: &Arc<Device>, layer_size: u32, mips: u32, format: vk::Format) -> Result<(u64, u32)> {
    let bytes_for = |layers: u32| {
        let info = vk::ImageCreateInfo::default()
            .image_type(vk::ImageType::TYPE_2D)
            .format(format)
            .extent(vk::Extent3D {
                width: layer_size,
                height: layer_size,
                depth: 1,
            })
            .mip_levels(mips)
            .array_layers(layers)
            .samples(vk::SampleCountFlags::TYPE_1)
            .tiling(vk::ImageTiling::OPTIMAL)
            .usage(CACHE_USAGE)
            .sharing_mode(vk::SharingMode::EXCLUSIVE)
            .initial_layout(vk::ImageLayout::UNDEFINED);
        let query = vk::DeviceImageMemoryRequirements::default().create_info(&info);
        let mut requirements = vk::MemoryRequirements2::default();
        // SAFETY: a Vulkan 1.3 query on a live device with a valid create info.
        unsafe {
            device
                .raw()
                .get_device_image_memory_requirements(&query, &mut requirements)
        };
        requirements.memory_requirements.size
    };
    let one = bytes_for(1);
    let layer_bytes = one.max(bytes_for(2).saturating_sub(one));
    // SAFETY: physical belongs to the device's instance.
    let properties = unsafe {
        device.instance_fns().get_physical_device_image_format_properties(
            device.physical(),
            format,
            vk::ImageType::TYPE_2D,
            vk::ImageTiling::OPTIMAL,
            CACHE_USAGE,
            vk::ImageCreateFlags::empty(),
        )
    }
    .map_err(|_| EngineError::MissingFeature {
        device: device.name().to_owned(),
        feature: format!("sampled {layer_size}x{layer_size} array images of {format:?}"),
    })?;
    let largest = properties.max_resource_size.min(device.max_memory_allocation_bytes());
    if layer_bytes == 0
        || properties.max_mip_levels < mips
        || properties.max_extent.width < layer_size
        || layer_bytes > largest
    {
        return Err(EngineError::MissingFeature {
            device: device.name().to_owned(),
            feature: format!(
                "{layer_size}x{layer_size} array images of {format:?} with {mips} levels ({layer_bytes} bytes a layer)"
            ),
        });
    }
    let by_size = u32::try_from(largest / layer_bytes).unwrap_or(u32::MAX);
    Ok((layer_bytes, properties.max_array_layers.min(by_size).max(1)))
}

impl Drop for GpuTextureCache {
    fn drop(&mut self) {
        // The images, the table and the staging may still be read by submitted
        // frames; a device lost leaves nothing better to do than free them anyway.
        let _ = self.device.wait_idle();
    }
}

/// Refuses `image` where the sparse cache cannot serve it, naming its format and why.
fn ensure_served(device: &Device, image: &SparseImage) -> Result<()> {
    match image.unserved_reason() {
        None => Ok(()),
        Some(reason) => Err(EngineError::MissingFeature {
            device: device.name().to_owned(),
            feature: format!(
                "sparse {:?} images the cache can serve ({reason}); the texture-array cache \
                 (--sparse off, or auto) serves this device",
                image.desc().format
            ),
        }),
    }
}

/// Creates a one-layer sparse image of `format` and reads its block size
/// and granularity.
fn probe_layer(device: &Arc<Device>, layer_size: u32, format: vk::Format, texel: TexelFormat) -> Result<LayerProbe> {
    let probe = SparseImage::new(
        device,
        SparseImageDesc {
            width: layer_size,
            height: layer_size,
            layers: 1,
            mips: 32 - layer_size.max(1).leading_zeros(),
            format,
        },
        "cache layer probe",
    )?;
    ensure_served(device, &probe)?;
    let (gw, gh) = probe.granularity();
    let desc = citystream_cache::ImageDesc::new(
        0,
        &ImageConfig {
            format: texel,
            granularity: Granularity::texels(gw, gh),
            layer_size,
            layer_count: 1,
            mip_tail: cache_mip_tail(&probe),
        },
        &DeviceLimits {
            max_image_array_layers: 1,
            max_image_dimension_2d: layer_size,
            sparse_block_bytes: probe.block_size(),
        },
    )
    .map_err(|e| EngineError::InvalidRequest(e.to_string()))?;
    Ok(LayerProbe {
        block_bytes: probe.block_size(),
        virtual_bytes: desc.virtual_bytes(),
    })
}

/// Puts `bytes` into the staging ring for the submission `ticket` or, where
/// the ring has no room, into a one-off buffer released with that ticket
/// ([`GpuTextureCache::retire`]). Returns the buffer and the bytes' offset.
fn stage_bytes(
    device: &Arc<Device>,
    staging: &mut StagingRing,
    retiring: &mut std::collections::VecDeque<(u64, Buffer)>,
    bytes: &[u8],
    ticket: u64,
    label: &str,
) -> Result<(vk::Buffer, u64)> {
    if let Some(range) = staging.push(bytes, 16, ticket)? {
        return Ok((staging.buffer(), range.offset));
    }
    let mut oversize = Buffer::new(
        device,
        BufferDesc {
            size: bytes.len() as u64,
            usage: vk::BufferUsageFlags::TRANSFER_SRC,
            location: MemoryLocation::CpuToGpu,
        },
        label,
    )?;
    oversize.write(0, bytes)?;
    let raw = oversize.raw();
    retiring.push_back((ticket, oversize));
    Ok((raw, 0))
}

fn same_place(a: &Placement, b: &Placement) -> bool {
    a.image == b.image && a.layer == b.layer && a.region == b.region && a.assignment == b.assignment
}

/// The residency planner's view of the cache (`citystream_streaming::residency::planner`).
impl ResidentCache for GpuTextureCache {
    fn resident_textures(&self) -> impl Iterator<Item = u32> + '_ {
        GpuTextureCache::resident_textures(self)
    }

    fn resident_levels(&self, texture: u32) -> u32 {
        GpuTextureCache::resident_levels(self, texture)
    }

    fn held_levels(&self, texture: u32) -> u32 {
        GpuTextureCache::held_levels(self, texture)
    }

    fn has_pending(&self, texture: u32) -> bool {
        GpuTextureCache::has_pending(self, texture)
    }

    fn level_bytes(&self, texture: u32, level: u32) -> u64 {
        GpuTextureCache::level_bytes(self, texture, level)
    }

    fn exclusive_blocks(&self, texture: u32, level: u32) -> u32 {
        GpuTextureCache::exclusive_blocks(self, texture, level)
    }

    fn budget_use(&self) -> BudgetUse {
        GpuTextureCache::budget_use(self)
    }

    fn images_sharing_format(&self, image: u32) -> &[u32] {
        GpuTextureCache::images_sharing_format(self, image)
    }

    fn layer_textures(&self, image: u32) -> Vec<(u32, Vec<u32>)> {
        GpuTextureCache::layer_textures(self, image)
    }
}
