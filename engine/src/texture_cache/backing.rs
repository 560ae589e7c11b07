//! The memory behind the cache's array images. Sparse: partially resident
//! images bound block by block from a pool, as the Vulkan-free cache
//! decides (the paper's cache). Texture arrays: ordinary, fully bound 2D
//! array images (Trapp and Döllner's batching), for devices without sparse
//! residency; each layer holds a full mip chain's memory from the start, so
//! the cache's binds are bookkeeping only and a layer is the unit of
//! eviction, while the table's lowest level keeps sampling to the levels
//! loaded.
//!
//! The images are built here too ([`build_images`]): their layer counts
//! planned ([`super::layout`]) from what the device reports of a layer's
//! cost (a probe image's sparse blocks, or an array layer's memory
//! requirements), each checked against the device's limits.

use std::sync::Arc;

use ash::vk;
use citystream_cache::{BindOp, CacheConfig, ChunkInfo, DeviceLimits, Granularity, ImageConfig, TexelFormat};

use super::layout::{image_layouts, plan_layer_counts, FormatImages, LayerProbe};
use super::{GpuCacheConfig, CACHE_FORMATS};
use crate::binder::{cache_mip_tail, VulkanBinder};
use crate::commands::{CommandContext, Recording, SemaphoreWait};
use crate::device::{Device, TextureBacking};
use crate::error::{EngineError, Result};
use crate::image::{image_2d_info, Image, ImageDesc};
use crate::sparse::{
    record_array_copies, record_array_layout, SparseImage, SparseImageDesc, SparseMemoryChunk, TexelUpload,
};

/// The unit the texture-array cache's block accounting counts in: the
/// cache's packing and eviction run on blocks, which fully bound layers do
/// not have. A 64 KiB standard block shape, as sparse devices use.
pub(super) const ARRAY_ACCOUNTING_BLOCK_BYTES: u64 = 64 * 1024;

/// Usage of every cache image: copied into, sampled.
pub(super) const CACHE_USAGE: vk::ImageUsageFlags =
    vk::ImageUsageFlags::from_raw(vk::ImageUsageFlags::SAMPLED.as_raw() | vk::ImageUsageFlags::TRANSFER_DST.as_raw());

/// The texel extent of a standard sparse block of `block_bytes` in
/// `format`: square where the block holds a square number of texel blocks,
/// twice as wide as high otherwise (the Vulkan standard block shapes).
pub(super) fn accounting_granularity(format: TexelFormat, block_bytes: u64) -> Granularity {
    let texel_blocks = (block_bytes / u64::from(format.bytes_per_block.max(1))).max(1);
    let log2 = 63 - texel_blocks.leading_zeros();
    let wide = 1u32 << log2.div_ceil(2);
    let high = 1u32 << (log2 / 2);
    Granularity::texels(wide * format.block_width, high * format.block_height)
}

/// A fully bound array image of the texture-array cache.
pub(super) struct ArrayImage {
    image: Image,
    desc: SparseImageDesc,
    bytes: u64,
}

/// The cache images and what binds their memory.
pub(super) enum CacheImages {
    /// Sparse images and the binder that binds the pool's blocks to them.
    Sparse {
        images: Vec<Arc<SparseImage>>,
        /// Boxed: it is much larger than the arrays' variant.
        binder: Box<VulkanBinder>,
        block_size: u64,
        memory_type_bits: u32,
    },
    /// Fully bound array images.
    Arrays { images: Vec<ArrayImage> },
}

/// What one [`CacheImages::apply_batch`] submitted (nothing for texture
/// arrays, whose blocks are bookkeeping: no bind cost is theirs).
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct Applied {
    pub(super) entries: u32,
    pub(super) seconds: f64,
    /// Blocks bound and unbound.
    pub(super) bound: u32,
    pub(super) unbound: u32,
}

impl CacheImages {
    /// Fully bound array images, one per `(desc, name)`.
    pub(super) fn arrays(device: &Arc<Device>, descs: &[(SparseImageDesc, String)]) -> Result<Self> {
        let images = descs
            .iter()
            .map(|(desc, name)| {
                let image = Image::new(
                    device,
                    ImageDesc {
                        width: desc.width,
                        height: desc.height,
                        layers: desc.layers,
                        mips: desc.mips,
                        format: desc.format,
                        usage: CACHE_USAGE,
                        view_type: vk::ImageViewType::TYPE_2D_ARRAY,
                    },
                    name,
                )?;
                let bytes = image.memory_bytes();
                Ok(ArrayImage {
                    image,
                    desc: *desc,
                    bytes,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(CacheImages::Arrays { images })
    }

    pub(super) fn len(&self) -> usize {
        match self {
            CacheImages::Sparse { images, .. } => images.len(),
            CacheImages::Arrays { images } => images.len(),
        }
    }

    /// Whether sparse image `image` has a tail forced by
    /// `CITYSTREAM_FORCE_MIP_TAIL` (false for texture arrays).
    pub(super) fn sparse_tail_synthetic(&self, image: usize) -> bool {
        match self {
            CacheImages::Sparse { images, .. } => images.get(image).is_some_and(|i| i.mip_tail().synthetic),
            CacheImages::Arrays { .. } => false,
        }
    }

    pub(super) fn view(&self, image: usize) -> Option<vk::ImageView> {
        match self {
            CacheImages::Sparse { images, .. } => images.get(image).map(|i| i.view()),
            CacheImages::Arrays { images } => images.get(image).map(|i| i.image.view()),
        }
    }

    fn raw_and_desc(&self, image: usize) -> Option<(vk::Image, SparseImageDesc)> {
        match self {
            CacheImages::Sparse { images, .. } => images.get(image).map(|i| (i.raw(), *i.desc())),
            CacheImages::Arrays { images } => images.get(image).map(|i| (i.image.raw(), i.desc)),
        }
    }

    /// Records a whole-image layout transition of `image`.
    pub(super) fn record_layout(
        &self,
        device: &Device,
        image: usize,
        rec: Recording<'_>,
        from: vk::ImageLayout,
        to: vk::ImageLayout,
    ) {
        if let Some((raw, desc)) = self.raw_and_desc(image) {
            record_array_layout(device, raw, &desc, rec, from, to);
        }
    }

    /// Records the copies of `uploads` into `image` (in TRANSFER_DST_OPTIMAL);
    /// for sparse images, each checked against the binds first when bind
    /// checking is on.
    pub(super) fn record_copies(
        &mut self,
        device: &Device,
        image: usize,
        rec: Recording<'_>,
        source: vk::Buffer,
        uploads: &[TexelUpload],
    ) -> Result<()> {
        if let CacheImages::Sparse { binder, .. } = self {
            for upload in uploads {
                binder.check_copy(image as u32, upload)?;
            }
        }
        let (raw, desc) = self
            .raw_and_desc(image)
            .ok_or_else(|| EngineError::InvalidRequest(format!("the cache has no image {image}")))?;
        record_array_copies(device, raw, &desc, rec, source, uploads)
    }

    /// Moves every image from `UNDEFINED` to `SHADER_READ_ONLY_OPTIMAL` in one
    /// submission and waits for it.
    pub(super) fn make_sampleable(&self, device: &Device, commands: &mut CommandContext) -> Result<()> {
        let cmd = commands.begin()?;
        for image in 0..self.len() {
            self.record_layout(
                device,
                image,
                cmd,
                vk::ImageLayout::UNDEFINED,
                vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
            );
        }
        commands.submit_and_wait(&[])
    }

    /// Carries out a batch of the cache's decisions: for sparse images, new
    /// pool chunks are allocated and every bind and unbind goes out in one
    /// submission (unbinds waiting for `frames_before`); fully bound arrays
    /// have nothing to do.
    pub(super) fn apply_batch(
        &mut self,
        device: &Arc<Device>,
        new_chunks: &[ChunkInfo],
        ops: &[BindOp],
        frames_before: Option<SemaphoreWait>,
    ) -> Result<Applied> {
        let CacheImages::Sparse {
            binder,
            block_size,
            memory_type_bits,
            ..
        } = self
        else {
            return Ok(Applied::default());
        };
        for chunk in new_chunks {
            let blocks = chunk.bytes / (*block_size).max(1);
            let memory = SparseMemoryChunk::with_requirements(
                device,
                *block_size,
                *memory_type_bits,
                blocks,
                &format!("cache block chunk {}", chunk.chunk),
            )?;
            let index = binder.add_chunk(memory)?;
            if index != chunk.chunk {
                return Err(EngineError::InvalidRequest(format!(
                    "block pool chunk {} was created as engine chunk {index}",
                    chunk.chunk
                )));
            }
        }
        let unbound = ops.iter().filter(|op| matches!(op, BindOp::Unbind { .. })).count() as u32;
        let frame_wait = if unbound > 0 { frames_before } else { None };
        let bind = binder.submit_after(ops, frame_wait)?;
        Ok(Applied {
            entries: bind.entries,
            seconds: bind.seconds,
            bound: ops.len() as u32 - unbound,
            unbound,
        })
    }

    /// What a submission copying into the images must wait on: the last
    /// sparse bind batch, at the copy stage (nothing for fully bound arrays).
    pub(super) fn bind_wait(&self) -> Option<SemaphoreWait> {
        match self {
            CacheImages::Sparse { binder, .. } => {
                (binder.last_signalled() > 0).then(|| binder.wait_for_last_batch(vk::PipelineStageFlags2::COPY))
            }
            CacheImages::Arrays { .. } => None,
        }
    }

    /// Device memory the texture-array images hold (`None` for sparse
    /// images, whose memory is the pool's bound blocks).
    pub(super) fn array_bytes(&self) -> Option<u64> {
        match self {
            CacheImages::Sparse { .. } => None,
            CacheImages::Arrays { images } => Some(images.iter().map(|i| i.bytes).sum()),
        }
    }
}

/// What [`GpuTextureCache::new`] builds for a backing.
pub(super) struct BuiltImages {
    /// The Vulkan-free cache's configuration.
    pub(super) cache_config: CacheConfig,
    pub(super) images: CacheImages,
    /// Which images hold which format.
    pub(super) formats: FormatImages,
    /// Per format, the layers of each of its images.
    pub(super) layer_counts: Vec<Vec<u32>>,
}

/// The cache images of `config` for the device's backing, `held` the
/// formats it holds (indices into [`CACHE_FORMATS`]), each image with `mips`
/// levels.
pub(super) fn build_images(
    device: &Arc<Device>,
    config: &GpuCacheConfig,
    held: &[usize],
    mips: u32,
) -> Result<BuiltImages> {
    // Checked on every backing (texture arrays ignore a tail), so that a value is refused
    // or accepted the same way whatever device runs it.
    if let Some(forced) = crate::sparse::forced_mip_tail()? {
        if forced.first_lod >= mips {
            return Err(EngineError::InvalidRequest(format!(
                "{}: level {} is beyond the cache's mip chain ({} levels of {}x{} layers: 0 to {}); \
                 a tail can start at level 0 to {}",
                crate::sparse::FORCE_MIP_TAIL_ENV,
                forced.first_lod,
                mips,
                config.layer_size,
                config.layer_size,
                mips.saturating_sub(1),
                mips.saturating_sub(1)
            )));
        }
    }
    match device.texture_backing() {
        TextureBacking::Sparse => sparse_images(device, config, held, mips),
        TextureBacking::Arrays => array_images(device, config, held, mips),
    }
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

/// Sparse cache images: layers derived within the device's sparse address
/// space, the block size and granularity the device reports.
fn sparse_images(device: &Arc<Device>, config: &GpuCacheConfig, held: &[usize], mips: u32) -> Result<BuiltImages> {
    let limits = device.properties().limits;
    let virtual_budget_bytes = config
        .virtual_budget_bytes
        .unwrap_or(device.sparse_support().address_space_size);
    let layer_counts = plan_layer_counts(
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
    let formats = FormatImages::new(&layouts);
    let images = CacheImages::Sparse {
        images,
        binder: Box::new(binder),
        block_size,
        memory_type_bits,
    };
    Ok(BuiltImages {
        cache_config,
        images,
        formats,
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
    let layer_counts = plan_layer_counts(config, held, max_layers, config.memory_budget_bytes, |index| {
        Ok(LayerProbe {
            block_bytes: ARRAY_ACCOUNTING_BLOCK_BYTES,
            virtual_bytes: layer_bytes[index],
            // Texture arrays bind no tails.
            single_tail_blocks: 0,
            single_tail_per_layer: false,
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
    let formats = FormatImages::new(&layouts);
    Ok(BuiltImages {
        cache_config,
        images,
        formats,
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
        let info = image_2d_info(format, layer_size, layer_size, mips, layers, CACHE_USAGE);
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
    let tail = probe.mip_tail();
    let single = tail.single && tail.first_lod < probe.desc().mips;
    Ok(LayerProbe {
        block_bytes: probe.block_size(),
        virtual_bytes: desc.virtual_bytes(),
        single_tail_blocks: if single { u64::from(probe.tail_blocks()) } else { 0 },
        single_tail_per_layer: single && tail.synthetic,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn accounting_blocks_take_the_standard_sparse_shapes() {
        // Vulkan's standard 64 KiB shapes: 64-bit texel blocks 128x64, 128-bit
        // 64x64 (in BC blocks of 4x4 texels), 32-bit texels 128x128.
        let block = ARRAY_ACCOUNTING_BLOCK_BYTES;
        assert_eq!(
            accounting_granularity(TexelFormat::BC1, block),
            Granularity::texels(512, 256)
        );
        assert_eq!(
            accounting_granularity(TexelFormat::BC7, block),
            Granularity::texels(256, 256)
        );
        assert_eq!(
            accounting_granularity(TexelFormat::RGBA8, block),
            Granularity::texels(128, 128)
        );
        // A block smaller than one texel block still covers one.
        assert_eq!(accounting_granularity(TexelFormat::BC7, 1), Granularity::texels(4, 4));
    }
}
