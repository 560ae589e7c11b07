//! The memory behind the cache's array images. Sparse: partially resident
//! images bound block by block from a pool, as the Vulkan-free cache
//! decides (the paper's cache). Texture arrays: ordinary, fully bound 2D
//! array images (Trapp and Döllner's batching), for devices without sparse
//! residency; each layer holds a full mip chain's memory from the start, so
//! the cache's binds are bookkeeping only and a layer is the unit of
//! eviction, while the table's lowest level keeps sampling to the levels
//! loaded.

use std::sync::Arc;

use ash::vk;
use citystream_cache::{BindOp, ChunkInfo, Granularity, TexelFormat};

use crate::binder::VulkanBinder;
use crate::commands::{CommandContext, Recording, SemaphoreWait};
use crate::device::Device;
use crate::error::{EngineError, Result};
use crate::image::{Image, ImageDesc};
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
