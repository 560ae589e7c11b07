//! The GPU half of the sparse texture cache (paper §3.6): one sparse
//! 2D-array image per format, pooled block memory, the per-texture
//! [`TextureData`] table and the City Colormap that shaders read.
//!
//! Packing, block accounting and eviction are the Vulkan-free
//! [`citystream_cache::TextureCache`]; this type carries its decisions out.
//!
//! One streaming cycle: [`GpuTextureCache::stage`] any number of mips (each
//! is packed, its blocks accounted, its bytes queued), then
//! [`GpuTextureCache::finish_cycle`]: textures the cache invalidated are
//! marked not sampleable first, new memory chunks are allocated, all binds
//! and unbinds go out in one `vkQueueBindSparse`, and the copies wait on its
//! timeline value. Only then does the table say the new mips are sampleable.
//!
//! Threading and GPU safety: owned by one thread. The caller calls
//! `finish_cycle` only when no submitted frame can still read the table or
//! the images (the frame loop waits for the fences of frames in flight), so
//! unbinding an evicted texture's blocks can never race a frame sampling it.

use std::sync::Arc;

use ash::vk;
use citystream_cache::{
    CacheConfig, CacheError, DeviceLimits, Granularity, ImageConfig, Placement, SparseBinder, TexelFormat,
    TextureCache, Utilisation,
};
use citystream_streaming::dataset::TextureFormat;
use gpu_allocator::MemoryLocation;

use crate::binder::VulkanBinder;
use crate::buffer::{Buffer, BufferDesc};
use crate::commands::CommandContext;
use crate::device::Device;
use crate::error::{EngineError, Result};
use crate::gpu_types::{
    TextureData, BINDING_CACHE_IMAGE0, BINDING_CACHE_IMAGE1, BINDING_COLORMAP, BINDING_TEXTURE_DATA,
    TEXTURE_NOT_SAMPLEABLE, TEXTURE_SAMPLEABLE,
};
use crate::pipeline::{DescriptorResource, Filtering, Sampler};
use crate::sparse::{SparseImage, SparseImageDesc, SparseMemoryChunk, TexelUpload};
use crate::staging::StagingRing;

/// The cache images, in binding order: image 0 is BC1 (`BINDING_CACHE_IMAGE0`),
/// image 1 is RGBA8 (`BINDING_CACHE_IMAGE1`).
pub const CACHE_FORMATS: [(TextureFormat, vk::Format, TexelFormat); 2] = [
    (TextureFormat::Bc1, vk::Format::BC1_RGB_UNORM_BLOCK, TexelFormat::BC1),
    (TextureFormat::Rgba8, vk::Format::R8G8B8A8_UNORM, TexelFormat::RGBA8),
];

/// Sizes and budgets of the cache.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GpuCacheConfig {
    /// Side of every array layer in texels (a power of two).
    pub layer_size: u32,
    /// Layers per cache image.
    pub layer_count: u32,
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
}

/// Sparse cache images, block memory, texture table and colormap.
pub struct GpuTextureCache {
    device: Arc<Device>,
    cache: TextureCache,
    images: Vec<Arc<SparseImage>>,
    binder: VulkanBinder,
    block_size: u64,
    memory_type_bits: u32,
    slots: Vec<TextureSlot>,
    table: Vec<TextureData>,
    table_buffer: Buffer,
    colormap_buffer: Buffer,
    sampler: Sampler,
    uploads: Vec<PendingUpload>,
    upload_bytes: Vec<u8>,
    staging: StagingRing,
    cycles: u64,
}

impl std::fmt::Debug for GpuTextureCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuTextureCache")
            .field("images", &self.images.len())
            .field("textures", &self.slots.len())
            .field("pending_uploads", &self.uploads.len())
            .finish()
    }
}

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
        let mut images = Vec::with_capacity(CACHE_FORMATS.len());
        let mut image_configs = Vec::with_capacity(CACHE_FORMATS.len());
        for (_, vk_format, texel_format) in CACHE_FORMATS {
            let image = SparseImage::new(
                device,
                SparseImageDesc {
                    width: config.layer_size,
                    height: config.layer_size,
                    layers: config.layer_count,
                    mips,
                    format: vk_format,
                },
                &format!("cache {}", texel_format.name),
            )?;
            if image.mip_tail_first_lod() < mips {
                return Err(EngineError::MissingFeature {
                    device: device.name().to_owned(),
                    feature: format!(
                        "per-block binding of every level of {:?} (it reports a mip tail from level {}); \
                         mip-tail binding is not implemented",
                        vk_format,
                        image.mip_tail_first_lod()
                    ),
                });
            }
            let (gw, gh) = image.granularity();
            image_configs.push(ImageConfig {
                format: texel_format,
                granularity: Granularity::texels(gw, gh),
                layer_size: config.layer_size,
                layer_count: config.layer_count,
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
        let limits = device.properties().limits;
        let cache_config = CacheConfig {
            images: image_configs,
            limits: DeviceLimits {
                max_image_array_layers: limits.max_image_array_layers,
                max_image_dimension_2d: limits.max_image_dimension2_d,
                sparse_block_bytes: block_size,
            },
            memory_budget_bytes: config.memory_budget_bytes,
            virtual_budget_bytes: config
                .virtual_budget_bytes
                .unwrap_or(device.sparse_support().address_space_size),
            blocks_per_chunk: config.blocks_per_chunk,
        };
        let cache = TextureCache::new(&cache_config).map_err(|e| EngineError::InvalidRequest(e.to_string()))?;
        let binder = VulkanBinder::new(device, images.clone())?;

        let table = vec![TextureData::default(); config.texture_count as usize];
        let host_storage = |size: u64, name: &str| {
            Buffer::new(
                device,
                BufferDesc {
                    size,
                    usage: vk::BufferUsageFlags::STORAGE_BUFFER,
                    location: MemoryLocation::CpuToGpu,
                },
                name,
            )
        };
        let mut table_buffer = host_storage(std::mem::size_of_val(table.as_slice()) as u64, "texture data table")?;
        table_buffer.write(0, &table)?;
        let packed: Vec<u32> = colormap.iter().map(|c| u32::from_le_bytes(*c)).collect();
        let mut colormap_buffer = host_storage(std::mem::size_of_val(packed.as_slice()) as u64, "city colormap")?;
        colormap_buffer.write(0, &packed)?;
        let sampler = Sampler::new(device, config.filtering, "cache sampler")?;
        let staging = StagingRing::new(device, config.staging_bytes.max(64 * 1024))?;

        let cmd = commands.begin()?;
        for image in &images {
            image.record_layout(
                cmd,
                vk::ImageLayout::UNDEFINED,
                vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
            );
        }
        commands.submit_and_wait(&[])?;

        Ok(Self {
            device: Arc::clone(device),
            cache,
            images,
            binder,
            block_size,
            memory_type_bits,
            slots: vec![TextureSlot::default(); config.texture_count as usize],
            table,
            table_buffer,
            colormap_buffer,
            sampler,
            uploads: Vec::new(),
            upload_bytes: Vec::new(),
            staging,
            cycles: 0,
        })
    }

    /// The descriptors a pass needs to sample city textures (bindings
    /// `BINDING_CACHE_IMAGE0/1`, `BINDING_TEXTURE_DATA`, `BINDING_COLORMAP`).
    pub fn descriptors(&self) -> [(u32, DescriptorResource); 4] {
        [
            (
                BINDING_CACHE_IMAGE0,
                DescriptorResource::SampledImage(self.images[0].view(), self.sampler.raw()),
            ),
            (
                BINDING_CACHE_IMAGE1,
                DescriptorResource::SampledImage(self.images[1].view(), self.sampler.raw()),
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

    /// The table entry the shaders see for `texture`.
    pub fn texture_data(&self, texture: u32) -> Option<&TextureData> {
        self.table.get(texture as usize)
    }

    /// Texture bytes versus bound bytes.
    pub fn utilisation(&self) -> Utilisation {
        self.cache.utilisation()
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
        let (image_index, _, texel_format) = CACHE_FORMATS
            .iter()
            .enumerate()
            .find(|(_, (f, _, _))| *f == format)
            .map(|(i, (_, v, t))| (i as u32, *v, *t))
            .ok_or_else(|| {
                EngineError::InvalidRequest(format!("texture {texture}: format {format:?} is not cached"))
            })?;
        let placement = match slot.placement {
            Some(p) if self.cache.is_live(&p) && p.image == image_index && p.width == width && p.height == height => p,
            _ => {
                let fresh = self
                    .cache
                    .insert(image_index, u64::from(texture), width, height)
                    .map_err(|e| cache_error(texture, mip, e))?;
                // A new place starts empty; the old one (if any) is no longer
                // sampled, whether or not its eviction was reported yet.
                let slot = &mut self.slots[texture as usize];
                slot.placement = Some(fresh);
                slot.resident = 0;
                self.table[texture as usize].state = TEXTURE_NOT_SAMPLEABLE;
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
        let upload = match self.cache.stage_mip(&placement, mip) {
            Ok(upload) => upload,
            Err(CacheError::MemoryPending { .. }) => return Ok(StageOutcome::MemoryPending),
            Err(e) => return Err(cache_error(texture, mip, e)),
        };
        let start = self.upload_bytes.len();
        self.upload_bytes.extend_from_slice(bytes);
        // Copies of block formats cover whole blocks even for levels below 4x4.
        let (bw, bh) = (texel_format.block_width, texel_format.block_height);
        self.uploads.push(PendingUpload {
            texture,
            placement,
            image: image_index,
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

    /// Carries out the cycle: invalidations, new memory, one sparse bind,
    /// the copies (waiting on the bind), then the table update. See the
    /// module docs for the caller's GPU-safety contract.
    pub fn finish_cycle(&mut self, commands: &mut CommandContext) -> Result<CycleReport> {
        let batch = self.cache.take_batch();
        let mut report = CycleReport::default();

        // 1. Evicted textures stop being sampleable before their blocks go.
        for gone in &batch.invalidated {
            let Ok(texture) = u32::try_from(gone.key) else { continue };
            let Some(slot) = self.slots.get_mut(texture as usize) else {
                continue;
            };
            if slot.placement.is_some_and(|p| same_place(&p, gone)) {
                slot.placement = None;
                slot.resident = 0;
                self.table[texture as usize].state = TEXTURE_NOT_SAMPLEABLE;
                report.textures_invalidated += 1;
                report.invalidated_textures.push(texture);
            }
        }
        // Mips staged for a place that was evicted in the same cycle must not be copied.
        self.uploads
            .retain(|u| !batch.invalidated.iter().any(|gone| same_place(&u.placement, gone)));
        self.table_buffer.write(0, &self.table)?;

        // 2. Memory for new pool chunks.
        for chunk in &batch.new_chunks {
            let blocks = chunk.bytes / self.block_size.max(1);
            let memory = SparseMemoryChunk::with_requirements(
                &self.device,
                self.block_size,
                self.memory_type_bits,
                blocks,
                &format!("cache block chunk {}", chunk.chunk),
            )?;
            let index = self.binder.add_chunk(memory);
            if index != chunk.chunk {
                return Err(EngineError::InvalidRequest(format!(
                    "block pool chunk {} was created as engine chunk {index}",
                    chunk.chunk
                )));
            }
        }

        // 3. One bind submission.
        let bind = self
            .binder
            .submit(&batch.ops)
            .map_err(|e| EngineError::InvalidRequest(format!("sparse bind failed: {e}")))?;
        report.bind_entries = bind.entries;
        report.bind_seconds = bind.seconds;
        for op in &batch.ops {
            match op {
                citystream_cache::BindOp::Bind { .. } => report.blocks_bound += 1,
                citystream_cache::BindOp::Unbind { .. } => report.blocks_unbound += 1,
            }
        }

        // 4. Copies, after the bind, from the staging ring (or, for a cycle
        // larger than the ring, a one-off buffer).
        self.cycles += 1;
        if !self.uploads.is_empty() {
            let ticket = self.cycles;
            let (source, base, _oversize) = match self.staging.push(&self.upload_bytes, 16, ticket)? {
                Some(range) => (self.staging.buffer(), range.offset, None),
                None => {
                    let mut oversize = Buffer::new(
                        &self.device,
                        BufferDesc {
                            size: self.upload_bytes.len() as u64,
                            usage: vk::BufferUsageFlags::TRANSFER_SRC,
                            location: MemoryLocation::CpuToGpu,
                        },
                        "cache upload staging (oversize cycle)",
                    )?;
                    oversize.write(0, &self.upload_bytes)?;
                    (oversize.raw(), 0, Some(oversize))
                }
            };
            let cmd = commands.begin()?;
            for (index, image) in self.images.iter().enumerate() {
                let uploads: Vec<TexelUpload> = self
                    .uploads
                    .iter()
                    .filter(|u| u.image as usize == index)
                    .map(|u| TexelUpload {
                        buffer_offset: base + u.bytes.start as u64,
                        ..u.upload
                    })
                    .collect();
                if uploads.is_empty() {
                    continue;
                }
                image.record_layout(
                    cmd,
                    vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
                    vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                );
                image.record_copies(cmd, source, &uploads)?;
                image.record_layout(
                    cmd,
                    vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                    vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
                );
            }
            commands.submit_and_wait(&[self.binder.wait_for_last_batch(vk::PipelineStageFlags2::COPY)])?;
            self.staging.retire(ticket);
            // 5. Now the mips are there: publish them.
            for u in &self.uploads {
                let slot = &mut self.slots[u.texture as usize];
                if slot.placement.is_some_and(|p| same_place(&p, &u.placement)) {
                    slot.resident |= 1 << u.upload.mip;
                }
                report.mips_uploaded += 1;
                report.bytes_uploaded += u.bytes.len() as u64;
            }
            let touched: Vec<u32> = self.uploads.iter().map(|u| u.texture).collect();
            for texture in touched {
                self.publish(texture);
            }
            self.table_buffer.write(0, &self.table)?;
        }
        self.uploads.clear();
        self.upload_bytes.clear();
        Ok(report)
    }

    /// Writes a texture's table entry from its host state. The coarsest
    /// resident level bounds sampling (the loader starts at the 4×4 level, so
    /// coarser levels of uncompressed textures are never loaded), and the
    /// finest level such that it and every level up to that one are resident
    /// is the finest sampled.
    fn publish(&mut self, texture: u32) {
        let slot = self.slots[texture as usize];
        let entry = &mut self.table[texture as usize];
        let Some(placement) = slot.placement else {
            entry.state = TEXTURE_NOT_SAMPLEABLE;
            return;
        };
        let resident = slot.resident & ((1u64 << placement.mip_count.min(32)) - 1) as u32;
        if resident == 0 {
            entry.state = TEXTURE_NOT_SAMPLEABLE;
            return;
        }
        let coarsest = 31 - resident.leading_zeros();
        let mut lowest = coarsest;
        while lowest > 0 && resident & (1 << (lowest - 1)) != 0 {
            lowest -= 1;
        }
        *entry = TextureData {
            uv_transform: [
                placement.uv.scale[0],
                placement.uv.scale[1],
                placement.uv.offset[0],
                placement.uv.offset[1],
            ],
            image: placement.image,
            layer: placement.layer,
            lowest_mip: lowest,
            state: TEXTURE_SAMPLEABLE,
            mip_count: coarsest + 1,
            ..TextureData::default()
        };
    }
}

fn same_place(a: &Placement, b: &Placement) -> bool {
    a.image == b.image && a.layer == b.layer && a.region == b.region && a.assignment == b.assignment
}
