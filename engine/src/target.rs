//! Headless off-screen colour + depth target and read-back to PNG.

use std::sync::Arc;

use ash::vk;
use gpu_allocator::MemoryLocation;

use crate::buffer::{Buffer, BufferDesc};
use crate::commands::{CommandContext, Recording};
use crate::device::Device;
use crate::error::{EngineError, Result};
use crate::image::{Image, ImageDesc};

/// Colour format of the off-screen target (8-bit UNORM, written to PNG as is).
pub const COLOR_FORMAT: vk::Format = vk::Format::R8G8B8A8_UNORM;
/// Depth format of the off-screen target.
pub const DEPTH_FORMAT: vk::Format = vk::Format::D32_SFLOAT;

/// Both depth tests, early and late: where drawing reads and writes the depth attachment.
const DEPTH_TESTS: vk::PipelineStageFlags2 = vk::PipelineStageFlags2::from_raw(
    vk::PipelineStageFlags2::EARLY_FRAGMENT_TESTS.as_raw() | vk::PipelineStageFlags2::LATE_FRAGMENT_TESTS.as_raw(),
);
/// Drawing's writes to the depth attachment.
const DEPTH_WRITE: (vk::PipelineStageFlags2, vk::AccessFlags2) =
    (DEPTH_TESTS, vk::AccessFlags2::DEPTH_STENCIL_ATTACHMENT_WRITE);
/// Drawing's depth tests and writes.
const DEPTH_READ_WRITE: (vk::PipelineStageFlags2, vk::AccessFlags2) = (
    DEPTH_TESTS,
    vk::AccessFlags2::from_raw(
        vk::AccessFlags2::DEPTH_STENCIL_ATTACHMENT_WRITE.as_raw()
            | vk::AccessFlags2::DEPTH_STENCIL_ATTACHMENT_READ.as_raw(),
    ),
);
/// Drawing's writes to the colour attachment.
const COLOR_WRITE: (vk::PipelineStageFlags2, vk::AccessFlags2) = (
    vk::PipelineStageFlags2::COLOR_ATTACHMENT_OUTPUT,
    vk::AccessFlags2::COLOR_ATTACHMENT_WRITE,
);
/// Culling's compute shaders, which read and write the depth copy's buffer.
const CULLING_READ_WRITE: (vk::PipelineStageFlags2, vk::AccessFlags2) = (
    vk::PipelineStageFlags2::COMPUTE_SHADER,
    vk::AccessFlags2::from_raw(vk::AccessFlags2::SHADER_READ.as_raw() | vk::AccessFlags2::SHADER_WRITE.as_raw()),
);

/// An off-screen colour and depth target with a host-visible read-back buffer.
#[derive(Debug)]
pub struct RenderTarget {
    color: Image,
    depth: Image,
    readback: Buffer,
    width: u32,
    height: u32,
}

impl RenderTarget {
    /// Creates a `width` × `height` target.
    pub fn new(device: &Arc<Device>, width: u32, height: u32) -> Result<Self> {
        let max = device.properties().limits.max_image_dimension2_d;
        if width == 0 || height == 0 || width > max || height > max {
            return Err(EngineError::InvalidRequest(format!(
                "render target {width}x{height} is outside 1..={max} per side"
            )));
        }
        let attachment = |format, usage, name| {
            Image::new(
                device,
                ImageDesc {
                    width,
                    height,
                    layers: 1,
                    mips: 1,
                    format,
                    usage,
                    view_type: vk::ImageViewType::TYPE_2D,
                },
                name,
            )
        };
        let color = attachment(
            COLOR_FORMAT,
            vk::ImageUsageFlags::COLOR_ATTACHMENT | vk::ImageUsageFlags::TRANSFER_SRC,
            "render target colour",
        )?;
        // Depth is copied out for GPU culling's depth pyramid.
        let depth = attachment(
            DEPTH_FORMAT,
            vk::ImageUsageFlags::DEPTH_STENCIL_ATTACHMENT | vk::ImageUsageFlags::TRANSFER_SRC,
            "render target depth",
        )?;
        let readback = Buffer::new(
            device,
            BufferDesc {
                size: u64::from(width) * u64::from(height) * 4,
                usage: vk::BufferUsageFlags::TRANSFER_DST,
                location: MemoryLocation::GpuToCpu,
            },
            "render target read-back",
        )?;
        Ok(Self {
            color,
            depth,
            readback,
            width,
            height,
        })
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// The colour image, in TRANSFER_SRC_OPTIMAL after
    /// [`end_and_copy`](Self::end_and_copy) (a presenter blits from it).
    pub fn color_image(&self) -> vk::Image {
        self.color.raw()
    }

    /// Records the transitions and `vkCmdBeginRendering` that clear colour to
    /// `clear` and depth to 0 (infinitely far: depth is reversed, [`crate::city::Camera`]).
    pub fn begin(&self, device: &Device, rec: Recording<'_>, clear: [f32; 4]) {
        self.color.transition(
            device,
            rec,
            vk::ImageLayout::UNDEFINED,
            vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL,
            // An earlier frame still in flight may be drawing into, copying
            // or blitting out of this image: wait for those before discarding it.
            (
                vk::PipelineStageFlags2::COLOR_ATTACHMENT_OUTPUT
                    | vk::PipelineStageFlags2::COPY
                    | vk::PipelineStageFlags2::BLIT,
                vk::AccessFlags2::COLOR_ATTACHMENT_WRITE,
            ),
            COLOR_WRITE,
        );
        self.depth.transition(
            device,
            rec,
            vk::ImageLayout::UNDEFINED,
            vk::ImageLayout::DEPTH_ATTACHMENT_OPTIMAL,
            DEPTH_WRITE,
            DEPTH_READ_WRITE,
        );
        self.begin_rendering(device, rec, vk::AttachmentLoadOp::CLEAR, clear);
    }

    fn begin_rendering(&self, device: &Device, rec: Recording<'_>, load: vk::AttachmentLoadOp, clear: [f32; 4]) {
        let cmd = rec.raw();
        let color_attachments = [vk::RenderingAttachmentInfo::default()
            .image_view(self.color.view())
            .image_layout(vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL)
            .load_op(load)
            .store_op(vk::AttachmentStoreOp::STORE)
            .clear_value(vk::ClearValue {
                color: vk::ClearColorValue { float32: clear },
            })];
        // Stored: a paused rendering resumes on it, and culling copies it out.
        let depth_attachment = vk::RenderingAttachmentInfo::default()
            .image_view(self.depth.view())
            .image_layout(vk::ImageLayout::DEPTH_ATTACHMENT_OPTIMAL)
            .load_op(load)
            .store_op(vk::AttachmentStoreOp::STORE)
            .clear_value(vk::ClearValue {
                depth_stencil: vk::ClearDepthStencilValue { depth: 0.0, stencil: 0 },
            });
        let area = vk::Rect2D {
            offset: vk::Offset2D { x: 0, y: 0 },
            extent: vk::Extent2D {
                width: self.width,
                height: self.height,
            },
        };
        let info = vk::RenderingInfo::default()
            .render_area(area)
            .layer_count(1)
            .color_attachments(&color_attachments)
            .depth_attachment(&depth_attachment);
        let viewport = vk::Viewport {
            x: 0.0,
            y: 0.0,
            width: self.width as f32,
            height: self.height as f32,
            min_depth: 0.0,
            max_depth: 1.0,
        };
        // SAFETY: cmd is recording; attachments are in the layouts just set.
        unsafe {
            device.raw.cmd_begin_rendering(cmd, &info);
            device.raw.cmd_set_viewport(cmd, 0, &[viewport]);
            device.raw.cmd_set_scissor(cmd, 0, &[area]);
        }
    }

    /// A copy of the whole of one aspect of an attachment, tightly packed in a buffer.
    fn whole_image_region(&self, aspect_mask: vk::ImageAspectFlags) -> vk::BufferImageCopy {
        vk::BufferImageCopy {
            buffer_offset: 0,
            buffer_row_length: 0,
            buffer_image_height: 0,
            image_subresource: vk::ImageSubresourceLayers {
                aspect_mask,
                mip_level: 0,
                base_array_layer: 0,
                layer_count: 1,
            },
            image_offset: vk::Offset3D::default(),
            image_extent: vk::Extent3D {
                width: self.width,
                height: self.height,
                depth: 1,
            },
        }
    }

    /// Bytes of the depth image copied by [`copy_depth`](Self::copy_depth): one 32-bit
    /// float per pixel, row by row.
    pub(crate) fn depth_bytes(&self) -> u64 {
        u64::from(self.width) * u64::from(self.height) * 4
    }

    /// Ends the rendering begun by [`begin`](Self::begin) or [`resume`](Self::resume);
    /// follow with [`copy_depth`](Self::copy_depth), then [`resume`](Self::resume).
    pub(crate) fn pause(&self, device: &Device, rec: Recording<'_>) {
        let cmd = rec.raw();
        // SAFETY: cmd is recording inside the rendering begun by `begin` or `resume`.
        unsafe { device.raw.cmd_end_rendering(cmd) };
    }

    /// After [`pause`](Self::pause): records the copy of the depth drawn so far into
    /// `into` (at least [`depth_bytes`](Self::depth_bytes)), visible to compute shaders
    /// after.
    pub(crate) fn copy_depth(&self, device: &Device, rec: Recording<'_>, into: vk::Buffer) {
        let cmd = rec.raw();
        self.depth.transition(
            device,
            rec,
            vk::ImageLayout::DEPTH_ATTACHMENT_OPTIMAL,
            vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
            DEPTH_WRITE,
            (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_READ),
        );
        // The last frame's culling read the buffer before this copy overwrites it.
        crate::image::memory_barrier(
            device,
            rec,
            CULLING_READ_WRITE,
            (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE),
        );
        let region = self.whole_image_region(vk::ImageAspectFlags::DEPTH);
        // SAFETY: the image is in TRANSFER_SRC_OPTIMAL; the caller's buffer holds the region.
        unsafe {
            device.raw.cmd_copy_image_to_buffer(
                cmd,
                self.depth.raw(),
                vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                into,
                &[region],
            )
        };
        crate::image::memory_barrier(
            device,
            rec,
            (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE),
            CULLING_READ_WRITE,
        );
    }

    /// Resumes rendering after [`copy_depth`](Self::copy_depth), keeping the colour and depth drawn so far.
    pub(crate) fn resume(&self, device: &Device, rec: Recording<'_>) {
        self.depth.transition(
            device,
            rec,
            vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
            vk::ImageLayout::DEPTH_ATTACHMENT_OPTIMAL,
            (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_READ),
            DEPTH_READ_WRITE,
        );
        // The colour drawn before the pause is loaded by the resumed rendering.
        crate::image::memory_barrier(
            device,
            rec,
            COLOR_WRITE,
            (
                vk::PipelineStageFlags2::COLOR_ATTACHMENT_OUTPUT,
                vk::AccessFlags2::COLOR_ATTACHMENT_READ | vk::AccessFlags2::COLOR_ATTACHMENT_WRITE,
            ),
        );
        self.begin_rendering(device, rec, vk::AttachmentLoadOp::LOAD, [0.0; 4]);
    }

    /// Ends rendering and records the copy of the colour image into the
    /// read-back buffer. Read it with [`RenderTarget::read_pixels`] after the
    /// submission's fence.
    pub fn end_and_copy(&self, device: &Device, rec: Recording<'_>) {
        let cmd = rec.raw();
        // SAFETY: cmd is recording inside the rendering begun by `begin`.
        unsafe { device.raw.cmd_end_rendering(cmd) };
        self.color.transition(
            device,
            rec,
            vk::ImageLayout::COLOR_ATTACHMENT_OPTIMAL,
            vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
            COLOR_WRITE,
            // The copy below, and a presenter's blit into a window after it.
            (
                vk::PipelineStageFlags2::COPY | vk::PipelineStageFlags2::BLIT,
                vk::AccessFlags2::TRANSFER_READ,
            ),
        );
        let region = self.whole_image_region(vk::ImageAspectFlags::COLOR);
        // An earlier frame's copy into the read-back buffer finishes first.
        crate::image::memory_barrier(
            device,
            rec,
            (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE),
            (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE),
        );
        // SAFETY: image in TRANSFER_SRC_OPTIMAL, buffer large enough for the region.
        unsafe {
            device.raw.cmd_copy_image_to_buffer(
                cmd,
                self.color.raw(),
                vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                self.readback.raw(),
                &[region],
            )
        };
        crate::image::memory_barrier(
            device,
            rec,
            (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE),
            (vk::PipelineStageFlags2::HOST, vk::AccessFlags2::HOST_READ),
        );
    }

    /// The depth drawn by the last rendering, once its submission has completed: one
    /// float per pixel, row by row, copied out through a submission of its own on
    /// `commands` (a test's check, not a per-frame path).
    pub fn read_depth(&self, device: &Arc<Device>, commands: &mut CommandContext) -> Result<Vec<f32>> {
        let buffer = Buffer::new(
            device,
            BufferDesc {
                size: self.depth_bytes(),
                usage: vk::BufferUsageFlags::TRANSFER_DST,
                location: MemoryLocation::GpuToCpu,
            },
            "render target depth read-back",
        )?;
        let rec = commands.begin()?;
        // The next `begin` takes the depth from UNDEFINED, so it may stay in TRANSFER_SRC.
        self.copy_depth(device, rec, buffer.raw());
        crate::image::memory_barrier(
            device,
            rec,
            (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE),
            (vk::PipelineStageFlags2::HOST, vk::AccessFlags2::HOST_READ),
        );
        commands.submit_and_wait(&[])?;
        buffer.read::<f32>(0, (self.width * self.height) as usize)
    }

    /// The pixels copied by the last [`RenderTarget::end_and_copy`], once its
    /// submission has completed.
    pub fn read_pixels(&self) -> Result<image::RgbaImage> {
        let bytes = self.readback.read::<u8>(0, (self.width * self.height * 4) as usize)?;
        image::RgbaImage::from_raw(self.width, self.height, bytes)
            .ok_or_else(|| EngineError::InvalidRequest("read-back buffer smaller than the target".into()))
    }
}
