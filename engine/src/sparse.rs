//! Sparse partially resident 2D-array images and `vkQueueBindSparse`.
//!
//! The image owns only its handle and view; its memory is bound block by
//! block from [`SparseMemoryChunk`]s the caller owns. Block size and
//! granularity come from the device (`vkGetImageSparseMemoryRequirements`),
//! never from constants: lavapipe reports 64 KiB blocks and, for BC formats,
//! a granularity in compressed blocks, which [`SparseImage::granularity`]
//! converts to texels.
//!
//! Levels smaller than a block live in the **mip tail** (every desktop GPU
//! reports one; an NVIDIA H200 from level 3 of BC1 2048² layers): bound only
//! opaquely ([`SparseImage::tail_bind`]), at `imageMipTailOffset + layer ×
//! imageMipTailStride` (once for a `SINGLE_MIPTAIL` image), never block by
//! block ([`SparseImage::bind_entries`] refuses tail levels). Lavapipe has no
//! tail: every level down to 1×1 is bound as ordinary blocks. So that tests
//! on it meet one, [`FORCE_MIP_TAIL_ENV`] makes an image without a tail
//! report a synthetic one, whose blocks bind as the levels' own blocks.

use std::sync::Arc;

use ash::vk;
use gpu_allocator::vulkan::Allocation;
use gpu_allocator::MemoryLocation;

use crate::commands::{CommandContext, Recording};
use crate::device::Device;
use crate::error::{EngineError, Result, VkResultExt};
use crate::image::{create_view, image_2d_info, ImageDesc};
use crate::memory;

/// Environment variable `LEVEL[,single]`: where the device reports no mip
/// tail, sparse images report one from level `LEVEL` (one per layer, or with
/// `single` one for the image), so the cache's tail binding, accounting and
/// checks run where no device has a tail (lavapipe). The tail's blocks are
/// bound as the blocks of its levels (lavapipe has no tail offset).
pub const FORCE_MIP_TAIL_ENV: &str = "CITYSTREAM_FORCE_MIP_TAIL";

/// A synthetic mip tail asked for by [`FORCE_MIP_TAIL_ENV`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ForcedMipTail {
    /// First level in the tail.
    pub first_lod: u32,
    /// One tail for the image.
    pub single: bool,
}

/// The synthetic tail [`FORCE_MIP_TAIL_ENV`] asks for, if set; a value that
/// is not `LEVEL` or `LEVEL,single` is an error naming the variable.
pub fn forced_mip_tail() -> Result<Option<ForcedMipTail>> {
    let Some(value) = std::env::var_os(FORCE_MIP_TAIL_ENV).filter(|v| !v.is_empty()) else {
        return Ok(None);
    };
    let text = value.to_string_lossy();
    let bad = || {
        EngineError::InvalidRequest(format!(
            "{FORCE_MIP_TAIL_ENV}={text:?}: expected LEVEL or LEVEL,single (a level number, e.g. 3 or 3,single)"
        ))
    };
    let mut parts = text.split(',').map(str::trim);
    let first_lod = parts
        .next()
        .and_then(|level| level.parse::<u32>().ok())
        .ok_or_else(bad)?;
    let single = match parts.next() {
        None => false,
        Some("single") => true,
        Some(_) => return Err(bad()),
    };
    if parts.next().is_some() || first_lod > 31 {
        return Err(bad());
    }
    Ok(Some(ForcedMipTail { first_lod, single }))
}

/// How to create a [`SparseImage`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct SparseImageDesc {
    /// Width of level 0 in texels.
    pub width: u32,
    /// Height of level 0 in texels.
    pub height: u32,
    /// Array layers.
    pub layers: u32,
    /// Mip levels (a full chain is `log2(max(w, h)) + 1`).
    pub mips: u32,
    /// Texel format.
    pub format: vk::Format,
}

/// Moves freshly created `images` from `UNDEFINED` to
/// `SHADER_READ_ONLY_OPTIMAL`, the layout a cache keeps them in between
/// copies, in one submission on `commands`, and waits for it.
pub fn make_sampleable(commands: &mut CommandContext, images: &[Arc<SparseImage>]) -> Result<()> {
    let cmd = commands.begin()?;
    for image in images {
        image.record_layout(
            cmd,
            vk::ImageLayout::UNDEFINED,
            vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
        );
    }
    commands.submit_and_wait(&[])
}

/// Texel-block dimensions of a format: 4×4 for BC, 1×1 otherwise.
pub fn texel_block(format: vk::Format) -> (u32, u32) {
    match format {
        vk::Format::BC1_RGB_UNORM_BLOCK
        | vk::Format::BC1_RGB_SRGB_BLOCK
        | vk::Format::BC1_RGBA_UNORM_BLOCK
        | vk::Format::BC1_RGBA_SRGB_BLOCK
        | vk::Format::BC3_UNORM_BLOCK
        | vk::Format::BC3_SRGB_BLOCK
        | vk::Format::BC7_UNORM_BLOCK
        | vk::Format::BC7_SRGB_BLOCK => (4, 4),
        _ => (1, 1),
    }
}

/// One block to bind (`memory: Some`) or unbind (`memory: None`), in block
/// coordinates of a level of a layer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SparseBlockBind {
    /// Array layer.
    pub layer: u32,
    /// Mip level.
    pub mip: u32,
    /// Block column.
    pub x: u32,
    /// Block row.
    pub y: u32,
    /// Backing memory and byte offset, or `None` to make it non-resident.
    pub memory: Option<(vk::DeviceMemory, u64)>,
}

/// A sparse, partially resident 2D-array image with a view of all layers and levels.
pub struct SparseImage {
    device: Arc<Device>,
    raw: vk::Image,
    view: vk::ImageView,
    desc: SparseImageDesc,
    block_size: u64,
    granularity: (u32, u32),
    mip_tail: MipTail,
    /// The colour aspect's sparse format flags (single tail, aligned mip
    /// size, non-standard block shape).
    format_flags: vk::SparseImageFormatFlags,
    memory_type_bits: u32,
    /// `VkMemoryRequirements::size`: the opaque range of the image (a tail
    /// offset may lie beyond it).
    opaque_bytes: u64,
    /// The device asks for a metadata aspect to be bound as well.
    metadata: bool,
}

/// Where a device keeps the levels of a sparse image's mip tail, as
/// `vkGetImageSparseMemoryRequirements` reports it (bytes of the opaque
/// range each layer's tail takes; all zero without a tail).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MipTail {
    /// First level in the tail (the image's level count when there is none).
    pub first_lod: u32,
    /// Bytes of one tail (`imageMipTailSize`).
    pub size: u64,
    /// Opaque offset of layer 0's tail (`imageMipTailOffset`).
    pub offset: u64,
    /// Opaque bytes between the tails of adjacent layers (`imageMipTailStride`).
    pub stride: u64,
    /// One tail for all layers (`VK_SPARSE_IMAGE_FORMAT_SINGLE_MIPTAIL_BIT`).
    pub single: bool,
    /// Asked for by [`FORCE_MIP_TAIL_ENV`] on a device without a tail: its
    /// blocks are bound as the blocks of its levels.
    pub synthetic: bool,
}

/// Block `index` of the mip tail of `layer` (layer 0 for a single tail) to
/// bind to `memory` (`None`: unbind), for [`SparseImage::bind_with_tail`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TailBlockBind {
    /// Array layer (0 for a single tail).
    pub layer: u32,
    /// Block of the tail.
    pub index: u32,
    /// Backing memory and byte offset, or `None` to make it non-resident.
    pub memory: Option<(vk::DeviceMemory, u64)>,
}

/// One tail block's bind: opaque on a device with a tail, the block of a
/// level it stands for with a synthetic tail.
#[derive(Clone, Copy, Debug)]
pub enum TailBind {
    /// `VkSparseMemoryBind` of the image's opaque range.
    Opaque(vk::SparseMemoryBind),
    /// A block of a level (synthetic tails).
    Block(SparseBlockBind),
}

debug_fields!(SparseImage {
    desc,
    block_size,
    granularity
});

const USAGE: vk::ImageUsageFlags =
    vk::ImageUsageFlags::from_raw(vk::ImageUsageFlags::SAMPLED.as_raw() | vk::ImageUsageFlags::TRANSFER_DST.as_raw());

impl SparseImage {
    /// Creates the image (no memory bound) and its view.
    pub fn new(device: &Arc<Device>, desc: SparseImageDesc, name: &str) -> Result<Self> {
        let limits = device.properties().limits;
        if desc.width == 0 || desc.height == 0 || desc.layers == 0 || desc.mips == 0 {
            return Err(EngineError::InvalidRequest(format!(
                "sparse image {name:?} has a zero dimension: {desc:?}"
            )));
        }
        if desc.width.max(desc.height) > limits.max_image_dimension2_d || desc.layers > limits.max_image_array_layers {
            return Err(EngineError::InvalidRequest(format!(
                "sparse image {name:?} ({}x{}, {} layers) exceeds the device limits ({} per side, {} layers)",
                desc.width, desc.height, desc.layers, limits.max_image_dimension2_d, limits.max_image_array_layers
            )));
        }
        let full_chain = 32 - desc.width.max(desc.height).leading_zeros();
        if desc.mips > full_chain {
            return Err(EngineError::InvalidRequest(format!(
                "sparse image {name:?} asks for {} mips; a {}x{} image has at most {full_chain}",
                desc.mips, desc.width, desc.height
            )));
        }
        // SAFETY: physical belongs to the instance.
        let format_props = unsafe {
            device
                .instance_fns()
                .get_physical_device_sparse_image_format_properties(
                    device.physical(),
                    desc.format,
                    vk::ImageType::TYPE_2D,
                    vk::SampleCountFlags::TYPE_1,
                    USAGE,
                    vk::ImageTiling::OPTIMAL,
                )
        };
        if format_props.is_empty() {
            return Err(EngineError::MissingFeature {
                device: device.name().to_owned(),
                feature: format!("sparse residency for format {:?}", desc.format),
            });
        }
        let info = image_2d_info(desc.format, desc.width, desc.height, desc.mips, desc.layers, USAGE)
            .flags(vk::ImageCreateFlags::SPARSE_BINDING | vk::ImageCreateFlags::SPARSE_RESIDENCY);
        // SAFETY: valid create info; the device enabled sparse binding and residency.
        let raw = unsafe { device.raw.create_image(&info, None) }.vk("vkCreateImage (sparse)")?;
        let mut image = Self {
            device: Arc::clone(device),
            raw,
            view: vk::ImageView::null(),
            desc,
            block_size: 0,
            granularity: (0, 0),
            mip_tail: MipTail {
                first_lod: desc.mips,
                ..MipTail::default()
            },
            format_flags: vk::SparseImageFormatFlags::empty(),
            memory_type_bits: 0,
            opaque_bytes: 0,
            metadata: false,
        };
        // SAFETY: raw is a live sparse image.
        let requirements = unsafe { device.raw.get_image_memory_requirements(raw) };
        // SAFETY: raw is a live sparse image.
        let sparse = unsafe { device.raw.get_image_sparse_memory_requirements(raw) };
        let color = sparse
            .iter()
            .find(|r| r.format_properties.aspect_mask.contains(vk::ImageAspectFlags::COLOR))
            .ok_or_else(|| EngineError::MissingFeature {
                device: device.name().to_owned(),
                feature: format!("sparse memory requirements for the colour aspect of {:?}", desc.format),
            })?;
        image.metadata = sparse
            .iter()
            .any(|r| r.format_properties.aspect_mask.contains(vk::ImageAspectFlags::METADATA));
        let (block_w, block_h) = texel_block(desc.format);
        let reported = color.format_properties.image_granularity;
        // A standard sparse block shape covers exactly one memory block. Some
        // drivers (lavapipe) report BC granularity in compressed blocks rather
        // than texels: whichever reading spans one memory block is the right one.
        let bytes_per_block = bytes_per_texel_block(desc.format);
        let area = u64::from(reported.width) * u64::from(reported.height);
        let as_texels = area * bytes_per_block / u64::from(block_w * block_h);
        let as_blocks = area * bytes_per_block;
        let in_blocks = block_w > 1 && as_texels != requirements.alignment && as_blocks == requirements.alignment;
        image.granularity = if in_blocks {
            (reported.width * block_w, reported.height * block_h)
        } else {
            (reported.width, reported.height)
        };
        image.block_size = requirements.alignment;
        image.mip_tail = MipTail {
            first_lod: color.image_mip_tail_first_lod.min(desc.mips),
            size: color.image_mip_tail_size,
            offset: color.image_mip_tail_offset,
            stride: color.image_mip_tail_stride,
            single: color
                .format_properties
                .flags
                .contains(vk::SparseImageFormatFlags::SINGLE_MIPTAIL),
            synthetic: false,
        };
        image.format_flags = color.format_properties.flags;
        image.memory_type_bits = requirements.memory_type_bits;
        image.opaque_bytes = requirements.size;
        // A synthetic tail only where the device reports none.
        if image.mip_tail.first_lod >= desc.mips {
            if let Some(forced) = forced_mip_tail()?.filter(|forced| forced.first_lod < desc.mips) {
                image.mip_tail = image.synthetic_tail(forced);
            }
        }
        image.view = create_view(
            device,
            raw,
            &ImageDesc {
                width: desc.width,
                height: desc.height,
                layers: desc.layers,
                mips: desc.mips,
                format: desc.format,
                usage: USAGE,
                view_type: vk::ImageViewType::TYPE_2D_ARRAY,
            },
        )?;
        device.set_name(raw, name);
        device.set_name(image.view, &format!("{name} view"));
        Ok(image)
    }

    /// The raw image.
    pub fn raw(&self) -> vk::Image {
        self.raw
    }

    /// A 2D-array view of every layer and level.
    pub fn view(&self) -> vk::ImageView {
        self.view
    }

    /// The description it was created from.
    pub fn desc(&self) -> &SparseImageDesc {
        &self.desc
    }

    /// Bytes of one sparse block (the memory alignment).
    pub fn block_size(&self) -> u64 {
        self.block_size
    }

    /// Sparse granularity in texels (converted from compressed blocks where
    /// the driver reports those).
    pub fn granularity(&self) -> (u32, u32) {
        self.granularity
    }

    /// First level of the mip tail; equals the mip count when there is none.
    pub fn mip_tail_first_lod(&self) -> u32 {
        self.mip_tail.first_lod
    }

    /// The mip tail as the device reports it (or as [`FORCE_MIP_TAIL_ENV`]
    /// makes it).
    pub fn mip_tail(&self) -> MipTail {
        self.mip_tail
    }

    /// The colour aspect's sparse format flags as the device reports them.
    pub fn format_flags(&self) -> vk::SparseImageFormatFlags {
        self.format_flags
    }

    /// Why the texture cache cannot serve this image sparse, if it cannot:
    /// a tail from level 0 (nothing to bind per block), or a block shape
    /// that is not one memory block of texels.
    pub fn unserved_reason(&self) -> Option<String> {
        if self.desc.mips > 0 && self.mip_tail.first_lod == 0 {
            return Some(format!(
                "its mip tail starts at level 0 of a {}x{} image: nothing can be bound block by block",
                self.desc.width, self.desc.height
            ));
        }
        if self.metadata {
            return Some("its sparse images need a metadata aspect bound, which the cache does not bind".into());
        }
        let (gw, gh) = self.granularity;
        let (bw, bh) = texel_block(self.desc.format);
        let texel_blocks = u64::from(gw / bw.max(1)) * u64::from(gh / bh.max(1));
        let spans_one_block =
            gw % bw == 0 && gh % bh == 0 && texel_blocks * bytes_per_texel_block(self.desc.format) == self.block_size;
        if !spans_one_block {
            let standard = !self
                .format_flags
                .contains(vk::SparseImageFormatFlags::NONSTANDARD_BLOCK_SIZE);
            return Some(format!(
                "a {}sparse block shape of {gw}x{gh} texels that is not one {}-byte memory block",
                if standard { "" } else { "non-standard " },
                self.block_size
            ));
        }
        None
    }

    /// Sparse blocks one tail takes (`imageMipTailSize` over the block
    /// size); zero without a tail.
    pub fn tail_blocks(&self) -> u32 {
        if self.mip_tail.first_lod >= self.desc.mips || self.block_size == 0 {
            return 0;
        }
        u32::try_from(self.mip_tail.size.div_ceil(self.block_size)).unwrap_or(u32::MAX)
    }

    /// A tail from `forced.first_lod` made of the blocks its levels would
    /// take, per layer or, single, for every layer.
    fn synthetic_tail(&self, forced: ForcedMipTail) -> MipTail {
        let per_layer: u64 = (forced.first_lod..self.desc.mips)
            .map(|mip| {
                let (w, h) = self.level_blocks(mip);
                u64::from(w) * u64::from(h)
            })
            .sum();
        let layer_bytes = per_layer * self.block_size;
        MipTail {
            first_lod: forced.first_lod,
            size: if forced.single {
                layer_bytes * u64::from(self.desc.layers)
            } else {
                layer_bytes
            },
            offset: 0,
            stride: if forced.single { 0 } else { layer_bytes },
            single: forced.single,
            synthetic: true,
        }
    }

    /// The bind of block `index` of the tail of `layer` (layer 0 for a
    /// single tail) to `memory` (`None`: unbind): opaque at the tail's
    /// offset, or the level block it stands for in a synthetic tail.
    pub fn tail_bind(&self, layer: u32, index: u32, memory: Option<(vk::DeviceMemory, u64)>) -> Result<TailBind> {
        let tail = self.mip_tail;
        let blocks = self.tail_blocks();
        let outside = || {
            EngineError::InvalidRequest(format!(
                "tail block {index} of layer {layer}: the image has {} layers and a {}tail of {blocks} blocks",
                self.desc.layers,
                if tail.single { "single " } else { "" }
            ))
        };
        if index >= blocks || layer >= self.desc.layers || (tail.single && layer != 0) {
            return Err(outside());
        }
        if tail.synthetic {
            // Block `index` of the tail's levels, layer by layer for a single tail.
            let mut rest = u64::from(index);
            let layers = if tail.single {
                0..self.desc.layers
            } else {
                layer..layer + 1
            };
            for at_layer in layers {
                for mip in tail.first_lod..self.desc.mips {
                    let (w, h) = self.level_blocks(mip);
                    let count = u64::from(w) * u64::from(h);
                    if rest < count {
                        return Ok(TailBind::Block(SparseBlockBind {
                            layer: at_layer,
                            mip,
                            x: (rest % u64::from(w)) as u32,
                            y: (rest / u64::from(w)) as u32,
                            memory,
                        }));
                    }
                    rest -= count;
                }
            }
            return Err(outside());
        }
        let layer_offset = if tail.single { 0 } else { u64::from(layer) * tail.stride };
        let (memory, memory_offset) = memory.unwrap_or((vk::DeviceMemory::null(), 0));
        Ok(TailBind::Opaque(vk::SparseMemoryBind {
            // An opaque offset: it may lie past the image's memory size (NVK).
            resource_offset: tail.offset + layer_offset + u64::from(index) * self.block_size,
            size: self.block_size.min(tail.size - u64::from(index) * self.block_size),
            memory,
            memory_offset,
            flags: vk::SparseMemoryBindFlags::empty(),
        }))
    }

    /// Bytes of the image's opaque memory range (`VkMemoryRequirements::size`).
    pub fn opaque_bytes(&self) -> u64 {
        self.opaque_bytes
    }

    /// Binds and unbinds `blocks` of levels above the tail and blocks of
    /// mip tails ([`TailBlockBind`]) in
    /// one `vkQueueBindSparse`, signalling `signal` and `fence` (may be
    /// null). Returns the bind entries submitted.
    pub fn bind_with_tail(
        &self,
        blocks: &[SparseBlockBind],
        tail: &[TailBlockBind],
        signal: &[vk::Semaphore],
        fence: vk::Fence,
    ) -> Result<usize> {
        let mut level_blocks = Vec::new();
        let mut opaque = Vec::new();
        for bind in tail {
            match self.tail_bind(bind.layer, bind.index, bind.memory)? {
                TailBind::Opaque(bind) => opaque.push(bind),
                TailBind::Block(block) => level_blocks.push(block),
            }
        }
        let mut entries = self.bind_entries(blocks)?;
        entries.extend(self.entries_of(&level_blocks)?);
        submit_bind_sparse_after(
            &self.device,
            &[(self.raw, entries.as_slice())],
            &[(self.raw, opaque.as_slice())],
            &[],
            signal,
            None,
            fence,
        )?;
        Ok(entries.len() + opaque.len())
    }

    /// Memory types the blocks may come from.
    pub fn memory_type_bits(&self) -> u32 {
        self.memory_type_bits
    }

    /// Extent of `mip` in texels.
    pub fn level_extent(&self, mip: u32) -> (u32, u32) {
        ((self.desc.width >> mip).max(1), (self.desc.height >> mip).max(1))
    }

    /// Number of blocks across and down `mip`.
    pub fn level_blocks(&self, mip: u32) -> (u32, u32) {
        let (w, h) = self.level_extent(mip);
        (w.div_ceil(self.granularity.0), h.div_ceil(self.granularity.1))
    }

    /// Texel offset and extent of a block, clipped to its level.
    pub fn block_region(&self, mip: u32, x: u32, y: u32) -> Result<(vk::Offset3D, vk::Extent3D)> {
        let (bw, bh) = self.level_blocks(mip);
        if mip >= self.desc.mips || x >= bw || y >= bh {
            return Err(EngineError::InvalidRequest(format!(
                "block ({x}, {y}) of level {mip} lies outside the image ({bw}x{bh} blocks, {} levels)",
                self.desc.mips
            )));
        }
        let (w, h) = self.level_extent(mip);
        let (gw, gh) = self.granularity;
        let offset = vk::Offset3D {
            x: (x * gw) as i32,
            y: (y * gh) as i32,
            z: 0,
        };
        let extent = vk::Extent3D {
            width: gw.min(w - x * gw),
            height: gh.min(h - y * gh),
            depth: 1,
        };
        Ok((offset, extent))
    }

    /// Binds and unbinds `blocks` in one `vkQueueBindSparse`, signalling
    /// `signal` (the copy submission waits on it) and `fence` (may be null).
    /// Returns the number of bind entries submitted after merging.
    pub fn bind(&self, blocks: &[SparseBlockBind], signal: &[vk::Semaphore], fence: vk::Fence) -> Result<usize> {
        let entries = self.bind_entries(blocks)?;
        submit_bind_sparse(&self.device, &[(self.raw, entries.as_slice())], signal, None, fence)?;
        Ok(entries.len())
    }

    /// Turns blocks into bind entries: runs of blocks adjacent in a row whose
    /// memory is contiguous (or which are all unbound) become one entry.
    /// Levels in the mip tail are refused: they are bound as a whole
    /// ([`tail_bind`](Self::tail_bind)).
    pub fn bind_entries(&self, blocks: &[SparseBlockBind]) -> Result<Vec<vk::SparseImageMemoryBind>> {
        let first_tail_lod = self.mip_tail.first_lod;
        if let Some(block) = blocks
            .iter()
            .find(|b| b.mip >= first_tail_lod && first_tail_lod < self.desc.mips)
        {
            return Err(EngineError::InvalidRequest(format!(
                "layer {} level {} block ({}, {}): levels from {first_tail_lod} on are in the mip tail and are \
                 bound as a whole, not per block",
                block.layer, block.mip, block.x, block.y
            )));
        }
        self.entries_of(blocks)
    }

    /// [`bind_entries`](Self::bind_entries) for blocks of the cache's own
    /// levels and of a synthetic tail's levels, which on a device without a
    /// tail are ordinary blocks.
    pub(crate) fn bind_entries_with_synthetic_tail(
        &self,
        blocks: &[SparseBlockBind],
    ) -> Result<Vec<vk::SparseImageMemoryBind>> {
        if self.mip_tail.synthetic {
            self.entries_of(blocks)
        } else {
            self.bind_entries(blocks)
        }
    }

    fn entries_of(&self, blocks: &[SparseBlockBind]) -> Result<Vec<vk::SparseImageMemoryBind>> {
        let mut sorted = blocks.to_vec();
        sorted.sort_by_key(|b| (b.layer, b.mip, b.y, b.x));
        let mut entries: Vec<vk::SparseImageMemoryBind> = Vec::with_capacity(sorted.len());
        let mut last: Option<SparseBlockBind> = None;
        for block in sorted {
            if block.layer >= self.desc.layers {
                return Err(EngineError::InvalidRequest(format!(
                    "layer {} lies outside the image's {} layers",
                    block.layer, self.desc.layers
                )));
            }
            let (offset, extent) = self.block_region(block.mip, block.x, block.y)?;
            let extends_previous = match (last, entries.last()) {
                (Some(prev), Some(entry)) => {
                    let same_row = prev.layer == block.layer && prev.mip == block.mip && prev.y == block.y;
                    let next_column = prev.x + 1 == block.x;
                    // Only full-width blocks can be extended by the next one.
                    let full_width = entry.extent.width % self.granularity.0 == 0;
                    let memory_follows = match (prev.memory, block.memory) {
                        (Some((m0, o0)), Some((m1, o1))) => m0 == m1 && o0 + self.block_size == o1,
                        (None, None) => true,
                        _ => false,
                    };
                    same_row && next_column && full_width && memory_follows
                }
                _ => false,
            };
            if extends_previous {
                if let Some(entry) = entries.last_mut() {
                    entry.extent.width += extent.width;
                }
            } else {
                let (memory, memory_offset) = block.memory.unwrap_or((vk::DeviceMemory::null(), 0));
                entries.push(vk::SparseImageMemoryBind {
                    subresource: vk::ImageSubresource {
                        aspect_mask: vk::ImageAspectFlags::COLOR,
                        mip_level: block.mip,
                        array_layer: block.layer,
                    },
                    offset,
                    extent,
                    memory,
                    memory_offset,
                    flags: vk::SparseMemoryBindFlags::empty(),
                });
            }
            last = Some(block);
        }
        Ok(entries)
    }
}

/// One `vkQueueBindSparse` for the entries of several images, signalling the
/// binary semaphores `signal`, optionally a timeline semaphore value, and
/// `fence` (may be null).
pub fn submit_bind_sparse(
    device: &Device,
    images: &[(vk::Image, &[vk::SparseImageMemoryBind])],
    signal: &[vk::Semaphore],
    timeline: Option<(vk::Semaphore, u64)>,
    fence: vk::Fence,
) -> Result<()> {
    submit_bind_sparse_after(device, images, &[], &[], signal, timeline, fence)
}

/// Binds `binds` of the opaque memory range of each image (mip tails, or a
/// whole image's memory) in one `vkQueueBindSparse`, and waits for it.
pub fn bind_opaque_and_wait(device: &Arc<Device>, images: &[(vk::Image, &[vk::SparseMemoryBind])]) -> Result<()> {
    let fence = crate::commands::Fence::new(device, false, "opaque sparse bind")?;
    submit_bind_sparse_after(device, &[], images, &[], &[], None, fence.raw())?;
    fence.wait()
}

/// As [`submit_bind_sparse`], but the binds start only once every timeline
/// semaphore in `waits` reached its value (GPU-side waits: the host does
/// not block).
pub fn submit_bind_sparse_after(
    device: &Device,
    images: &[(vk::Image, &[vk::SparseImageMemoryBind])],
    opaque: &[(vk::Image, &[vk::SparseMemoryBind])],
    waits: &[(vk::Semaphore, u64)],
    signal: &[vk::Semaphore],
    timeline: Option<(vk::Semaphore, u64)>,
    fence: vk::Fence,
) -> Result<()> {
    let image_binds: Vec<_> = images
        .iter()
        .filter(|(_, entries)| !entries.is_empty())
        .map(|&(image, entries)| vk::SparseImageMemoryBindInfo::default().image(image).binds(entries))
        .collect();
    let opaque_binds: Vec<_> = opaque
        .iter()
        .filter(|(_, entries)| !entries.is_empty())
        .map(|&(image, entries)| {
            vk::SparseImageOpaqueMemoryBindInfo::default()
                .image(image)
                .binds(entries)
        })
        .collect();
    let mut semaphores = signal.to_vec();
    let mut values = vec![0u64; signal.len()];
    if let Some((semaphore, value)) = timeline {
        semaphores.push(semaphore);
        values.push(value);
    }
    let wait_semaphores: Vec<vk::Semaphore> = waits.iter().map(|w| w.0).collect();
    let wait_values: Vec<u64> = waits.iter().map(|w| w.1).collect();
    let mut timeline_info = vk::TimelineSemaphoreSubmitInfo::default()
        .wait_semaphore_values(&wait_values)
        .signal_semaphore_values(&values);
    let mut info = vk::BindSparseInfo::default()
        .wait_semaphores(&wait_semaphores)
        .signal_semaphores(&semaphores)
        .image_binds(&image_binds)
        .image_opaque_binds(&opaque_binds);
    if timeline.is_some() || !waits.is_empty() {
        info = info.push_next(&mut timeline_info);
    }
    let queue = device.queue();
    // SAFETY: the queue supports sparse binding and is locked; entries were
    // built from checked block coordinates; memory offsets are block aligned
    // and come from allowed memory types (SparseMemoryChunk's contract).
    unsafe { device.raw.queue_bind_sparse(*queue, &[info], fence) }.vk("vkQueueBindSparse")
}

/// One rectangle of texels to copy from a buffer into a level of a layer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TexelUpload {
    /// Array layer.
    pub layer: u32,
    /// Mip level.
    pub mip: u32,
    /// Left edge in texels (a multiple of the format's texel block).
    pub x: u32,
    /// Top edge in texels.
    pub y: u32,
    /// Width in texels.
    pub width: u32,
    /// Height in texels.
    pub height: u32,
    /// Byte offset of the tightly packed source texels in the buffer.
    pub buffer_offset: u64,
}

impl SparseImage {
    /// Records copies from `source` into the image, which must be in
    /// TRANSFER_DST_OPTIMAL, and whose destination blocks must be bound.
    pub fn record_copies(&self, rec: Recording<'_>, source: vk::Buffer, uploads: &[TexelUpload]) -> Result<()> {
        record_array_copies(&self.device, self.raw, &self.desc, rec, source, uploads)
    }

    /// Records a whole-image transition between UNDEFINED, TRANSFER_DST_OPTIMAL
    /// and SHADER_READ_ONLY_OPTIMAL with matching stages.
    pub fn record_layout(&self, rec: Recording<'_>, from: vk::ImageLayout, to: vk::ImageLayout) {
        record_array_layout(&self.device, self.raw, &self.desc, rec, from, to);
    }
}

/// Records copies from `source` into `image` (a 2D array image of `desc`,
/// sparse or not), which must be in TRANSFER_DST_OPTIMAL with the
/// destination memory bound.
pub(crate) fn record_array_copies(
    device: &Device,
    image: vk::Image,
    desc: &SparseImageDesc,
    rec: Recording<'_>,
    source: vk::Buffer,
    uploads: &[TexelUpload],
) -> Result<()> {
    let cmd = rec.raw();
    let (bw, bh) = texel_block(desc.format);
    let mut regions = Vec::with_capacity(uploads.len());
    for u in uploads {
        let (lw, lh) = (
            (desc.width >> u.mip.min(31)).max(1),
            (desc.height >> u.mip.min(31)).max(1),
        );
        let fits = u.layer < desc.layers
            && u.mip < desc.mips
            && u.x.checked_add(u.width).is_some_and(|r| r <= lw.max(bw))
            && u.y.checked_add(u.height).is_some_and(|b| b <= lh.max(bh));
        if !fits || u.x % bw != 0 || u.y % bh != 0 || u.width == 0 || u.height == 0 {
            return Err(EngineError::InvalidRequest(format!(
                "upload {u:?} does not fit level {} ({lw}x{lh}) of layer {} in a {}-layer image, or is not block aligned",
                u.mip, u.layer, desc.layers
            )));
        }
        regions.push(vk::BufferImageCopy {
            buffer_offset: u.buffer_offset,
            buffer_row_length: 0,
            buffer_image_height: 0,
            image_subresource: vk::ImageSubresourceLayers {
                aspect_mask: vk::ImageAspectFlags::COLOR,
                mip_level: u.mip,
                base_array_layer: u.layer,
                layer_count: 1,
            },
            image_offset: vk::Offset3D {
                x: u.x as i32,
                y: u.y as i32,
                z: 0,
            },
            image_extent: vk::Extent3D {
                width: u.width,
                height: u.height,
                depth: 1,
            },
        });
    }
    if regions.is_empty() {
        return Ok(());
    }
    // SAFETY: cmd is recording; regions were checked against the image;
    // the caller keeps `source` alive until the submission completes.
    unsafe {
        device
            .raw
            .cmd_copy_buffer_to_image(cmd, source, image, vk::ImageLayout::TRANSFER_DST_OPTIMAL, &regions)
    };
    Ok(())
}

/// Records a whole-image transition of `image` (of `desc`) between
/// UNDEFINED, TRANSFER_DST_OPTIMAL and SHADER_READ_ONLY_OPTIMAL with
/// matching stages.
pub(crate) fn record_array_layout(
    device: &Device,
    image: vk::Image,
    desc: &SparseImageDesc,
    rec: Recording<'_>,
    from: vk::ImageLayout,
    to: vk::ImageLayout,
) {
    let stage_of = |layout: vk::ImageLayout| match layout {
        vk::ImageLayout::TRANSFER_DST_OPTIMAL => (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE),
        // COPY too: the submission waits for the sparse binds at the copy
        // stage, and the layout change must come after them as well.
        vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL => (
            vk::PipelineStageFlags2::FRAGMENT_SHADER
                | vk::PipelineStageFlags2::COMPUTE_SHADER
                | vk::PipelineStageFlags2::COPY,
            vk::AccessFlags2::SHADER_SAMPLED_READ,
        ),
        _ => (vk::PipelineStageFlags2::TOP_OF_PIPE, vk::AccessFlags2::NONE),
    };
    let range = vk::ImageSubresourceRange {
        aspect_mask: vk::ImageAspectFlags::COLOR,
        base_mip_level: 0,
        level_count: desc.mips,
        base_array_layer: 0,
        layer_count: desc.layers,
    };
    crate::image::transition(device, rec, image, range, from, to, stage_of(from), stage_of(to));
}

/// Bytes per texel block (one texel for uncompressed formats).
pub fn bytes_per_texel_block(format: vk::Format) -> u64 {
    match format {
        vk::Format::BC1_RGB_UNORM_BLOCK
        | vk::Format::BC1_RGB_SRGB_BLOCK
        | vk::Format::BC1_RGBA_UNORM_BLOCK
        | vk::Format::BC1_RGBA_SRGB_BLOCK => 8,
        vk::Format::BC3_UNORM_BLOCK
        | vk::Format::BC3_SRGB_BLOCK
        | vk::Format::BC7_UNORM_BLOCK
        | vk::Format::BC7_SRGB_BLOCK => 16,
        vk::Format::R8G8B8A8_UNORM | vk::Format::R8G8B8A8_SRGB | vk::Format::B8G8R8A8_UNORM => 4,
        _ => 4,
    }
}

impl Drop for SparseImage {
    fn drop(&mut self) {
        // SAFETY: the owner drops only after the GPU finished with the image;
        // memory bound to it is owned by chunks that outlive nothing here.
        unsafe { crate::image::destroy_image_and_view(&self.device, self.raw, self.view) };
    }
}

/// A chunk of device memory from which sparse blocks are bound.
pub struct SparseMemoryChunk {
    device: Arc<Device>,
    allocation: Option<Allocation>,
    size: u64,
}

debug_fields!(SparseMemoryChunk { size });

impl SparseMemoryChunk {
    /// Allocates `blocks` blocks usable by `image`.
    pub fn new(device: &Arc<Device>, image: &SparseImage, blocks: u64, name: &str) -> Result<Self> {
        Self::with_requirements(device, image.block_size(), image.memory_type_bits(), blocks, name)
    }

    /// Allocates `blocks` blocks of `block_size` bytes from a memory type in
    /// `memory_type_bits` (for chunks shared by several images, the
    /// intersection of their bits and the largest of their block sizes).
    pub fn with_requirements(
        device: &Arc<Device>,
        block_size: u64,
        memory_type_bits: u32,
        blocks: u64,
        name: &str,
    ) -> Result<Self> {
        let size = blocks.checked_mul(block_size).filter(|&s| s > 0).ok_or_else(|| {
            EngineError::InvalidRequest(format!("chunk {name:?} of {blocks} blocks has no valid size"))
        })?;
        if memory_type_bits == 0 {
            return Err(EngineError::InvalidRequest(format!(
                "chunk {name:?}: the images sharing it have no memory type in common"
            )));
        }
        let requirements = vk::MemoryRequirements {
            size,
            alignment: block_size,
            memory_type_bits,
        };
        let allocation = memory::allocate(device, name, requirements, MemoryLocation::GpuOnly, false)?;
        Ok(Self {
            device: Arc::clone(device),
            allocation: Some(allocation),
            size,
        })
    }

    /// The device memory and byte offset of block `index` of this chunk.
    pub fn block(&self, index: u64, block_size: u64) -> Option<(vk::DeviceMemory, u64)> {
        let allocation = self.allocation.as_ref()?;
        let offset = index.checked_mul(block_size)?;
        // SAFETY: the memory handle stays valid while this chunk owns the allocation.
        let memory = unsafe { allocation.memory() };
        (offset + block_size <= self.size).then(|| (memory, allocation.offset() + offset))
    }

    /// The device memory and offset of the block at byte `offset` of this
    /// chunk, when `offset` is block aligned and the block fits.
    pub fn at(&self, offset: u64, block_size: u64) -> Option<(vk::DeviceMemory, u64)> {
        if block_size == 0 || !offset.is_multiple_of(block_size) {
            return None;
        }
        self.block(offset / block_size, block_size)
    }

    /// Size in bytes.
    pub fn size(&self) -> u64 {
        self.size
    }
}

impl Drop for SparseMemoryChunk {
    fn drop(&mut self) {
        if let Some(allocation) = self.allocation.take() {
            memory::free(&self.device, allocation);
        }
    }
}
