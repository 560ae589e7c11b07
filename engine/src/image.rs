//! Ordinary (fully resident) images with one view, owning their memory.

use std::sync::Arc;

use ash::vk;
use gpu_allocator::vulkan::Allocation;
use gpu_allocator::MemoryLocation;

use crate::commands::Recording;
use crate::device::Device;
use crate::error::{EngineError, Result, VkResultExt};
use crate::memory;

/// How to create an [`Image`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ImageDesc {
    /// Width in texels.
    pub width: u32,
    /// Height in texels.
    pub height: u32,
    /// Array layers (>= 1).
    pub layers: u32,
    /// Mip levels (>= 1).
    pub mips: u32,
    /// Texel format.
    pub format: vk::Format,
    /// Usage flags.
    pub usage: vk::ImageUsageFlags,
    /// View type: `TYPE_2D` or `TYPE_2D_ARRAY`.
    pub view_type: vk::ImageViewType,
}

/// The create info of every 2D image of the engine: optimal tiling, one sample, one queue
/// family, contents undefined until the first transition.
pub(crate) fn image_2d_info(
    format: vk::Format,
    width: u32,
    height: u32,
    mips: u32,
    layers: u32,
    usage: vk::ImageUsageFlags,
) -> vk::ImageCreateInfo<'static> {
    vk::ImageCreateInfo::default()
        .image_type(vk::ImageType::TYPE_2D)
        .format(format)
        .extent(vk::Extent3D {
            width,
            height,
            depth: 1,
        })
        .mip_levels(mips)
        .array_layers(layers)
        .samples(vk::SampleCountFlags::TYPE_1)
        .tiling(vk::ImageTiling::OPTIMAL)
        .usage(usage)
        .sharing_mode(vk::SharingMode::EXCLUSIVE)
        .initial_layout(vk::ImageLayout::UNDEFINED)
}

impl ImageDesc {
    /// The aspect of this image's format.
    pub fn aspect(&self) -> vk::ImageAspectFlags {
        aspect_of(self.format)
    }

    /// The whole subresource range.
    pub fn full_range(&self) -> vk::ImageSubresourceRange {
        vk::ImageSubresourceRange {
            aspect_mask: self.aspect(),
            base_mip_level: 0,
            level_count: self.mips,
            base_array_layer: 0,
            layer_count: self.layers,
        }
    }
}

/// The aspect flags of a format.
pub fn aspect_of(format: vk::Format) -> vk::ImageAspectFlags {
    match format {
        vk::Format::D16_UNORM | vk::Format::D32_SFLOAT | vk::Format::X8_D24_UNORM_PACK32 => vk::ImageAspectFlags::DEPTH,
        vk::Format::D24_UNORM_S8_UINT | vk::Format::D32_SFLOAT_S8_UINT | vk::Format::D16_UNORM_S8_UINT => {
            vk::ImageAspectFlags::DEPTH | vk::ImageAspectFlags::STENCIL
        }
        _ => vk::ImageAspectFlags::COLOR,
    }
}

/// A `VkImage` with its memory and a view of the whole image.
pub struct Image {
    device: Arc<Device>,
    raw: vk::Image,
    view: vk::ImageView,
    allocation: Option<Allocation>,
    desc: ImageDesc,
    name: String,
}

debug_fields!(Image { name, desc });

impl Image {
    /// Creates the image, binds device memory and creates its view.
    pub fn new(device: &Arc<Device>, desc: ImageDesc, name: &str) -> Result<Self> {
        if desc.width == 0 || desc.height == 0 || desc.layers == 0 || desc.mips == 0 {
            return Err(EngineError::InvalidRequest(format!(
                "image {name:?} has a zero dimension: {desc:?}"
            )));
        }
        let info = image_2d_info(desc.format, desc.width, desc.height, desc.mips, desc.layers, desc.usage);
        // SAFETY: valid create info on a live device.
        let raw = unsafe { device.raw.create_image(&info, None) }.vk("vkCreateImage")?;
        let mut image = Self {
            device: Arc::clone(device),
            raw,
            view: vk::ImageView::null(),
            allocation: None,
            desc,
            name: name.to_owned(),
        };
        // SAFETY: raw is a live image of this device.
        let requirements = unsafe { device.raw.get_image_memory_requirements(raw) };
        let allocation = memory::allocate(device, name, requirements, MemoryLocation::GpuOnly, false)?;
        // SAFETY: the allocation satisfies the image's requirements.
        let bound = unsafe {
            device
                .raw
                .bind_image_memory(raw, allocation.memory(), allocation.offset())
        };
        image.allocation = Some(allocation);
        bound.vk("vkBindImageMemory")?;
        image.view = create_view(device, raw, &desc)?;
        device.set_name(raw, name);
        device.set_name(image.view, &format!("{name} view"));
        Ok(image)
    }

    /// Records a layout transition of the whole image ([`transition`]).
    pub(crate) fn transition(
        &self,
        device: &Device,
        rec: Recording<'_>,
        from: vk::ImageLayout,
        to: vk::ImageLayout,
        src: (vk::PipelineStageFlags2, vk::AccessFlags2),
        dst: (vk::PipelineStageFlags2, vk::AccessFlags2),
    ) {
        transition(device, rec, self.raw, self.desc.full_range(), from, to, src, dst);
    }

    /// The raw image.
    pub fn raw(&self) -> vk::Image {
        self.raw
    }

    /// The view of the whole image.
    pub fn view(&self) -> vk::ImageView {
        self.view
    }

    /// The description it was created from.
    pub fn desc(&self) -> &ImageDesc {
        &self.desc
    }

    /// Bytes of device memory bound to the image.
    pub fn memory_bytes(&self) -> u64 {
        self.allocation.as_ref().map_or(0, Allocation::size)
    }
}

/// Creates a view of every layer and level of `image`.
pub(crate) fn create_view(device: &Device, image: vk::Image, desc: &ImageDesc) -> Result<vk::ImageView> {
    let info = vk::ImageViewCreateInfo::default()
        .image(image)
        .view_type(desc.view_type)
        .format(desc.format)
        .subresource_range(desc.full_range());
    // SAFETY: image is live and the range lies within it.
    unsafe { device.raw.create_image_view(&info, None) }.vk("vkCreateImageView")
}

impl Drop for Image {
    fn drop(&mut self) {
        // SAFETY: the owner guarantees the GPU no longer uses the image.
        unsafe { destroy_image_and_view(&self.device, self.raw, self.view) };
        if let Some(allocation) = self.allocation.take() {
            memory::free(&self.device, allocation);
        }
    }
}

/// Destroys an image and its view (where it has one yet).
///
/// # Safety
/// Both belong to `device`, and the GPU no longer uses either.
pub(crate) unsafe fn destroy_image_and_view(device: &Device, image: vk::Image, view: vk::ImageView) {
    // SAFETY: as the caller guarantees.
    unsafe {
        if view != vk::ImageView::null() {
            device.raw.destroy_image_view(view, None);
        }
        device.raw.destroy_image(image, None);
    }
}

/// Records a whole-image layout transition with synchronization2.
#[allow(clippy::too_many_arguments, reason = "a barrier is exactly these eight facts")]
pub(crate) fn transition(
    device: &Device,
    rec: Recording<'_>,
    image: vk::Image,
    range: vk::ImageSubresourceRange,
    from: vk::ImageLayout,
    to: vk::ImageLayout,
    src: (vk::PipelineStageFlags2, vk::AccessFlags2),
    dst: (vk::PipelineStageFlags2, vk::AccessFlags2),
) {
    let cmd = rec.raw();
    let barrier = vk::ImageMemoryBarrier2::default()
        .src_stage_mask(src.0)
        .src_access_mask(src.1)
        .dst_stage_mask(dst.0)
        .dst_access_mask(dst.1)
        .old_layout(from)
        .new_layout(to)
        .src_queue_family_index(vk::QUEUE_FAMILY_IGNORED)
        .dst_queue_family_index(vk::QUEUE_FAMILY_IGNORED)
        .image(image)
        .subresource_range(range);
    let barriers = [barrier];
    let dependency = vk::DependencyInfo::default().image_memory_barriers(&barriers);
    // SAFETY: cmd is in the recording state; the barrier refers to a live image.
    unsafe { device.raw.cmd_pipeline_barrier2(cmd, &dependency) };
}

/// Records a global memory barrier with synchronization2.
pub fn memory_barrier(
    device: &Device,
    rec: Recording<'_>,
    src: (vk::PipelineStageFlags2, vk::AccessFlags2),
    dst: (vk::PipelineStageFlags2, vk::AccessFlags2),
) {
    let cmd = rec.raw();
    let barrier = vk::MemoryBarrier2::default()
        .src_stage_mask(src.0)
        .src_access_mask(src.1)
        .dst_stage_mask(dst.0)
        .dst_access_mask(dst.1);
    let barriers = [barrier];
    let dependency = vk::DependencyInfo::default().memory_barriers(&barriers);
    // SAFETY: cmd is in the recording state.
    unsafe { device.raw.cmd_pipeline_barrier2(cmd, &dependency) };
}
