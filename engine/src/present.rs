//! Presentation to a window (feature `window`): a surface, a swapchain the
//! host's off-screen [`RenderTarget`] is blitted into every frame, and
//! screenshots of exactly what was presented.
//!
//! The frame keeps rendering into the off-screen target (the same passes as
//! headless runs, so a windowed frame and a headless one are the same
//! pixels); [`Presenter::record_blit`] copies it into the acquired swapchain
//! image. Per frame slot there is one acquire semaphore, reused only after
//! the caller saw that slot's previous frame complete (the streamer's
//! throttle); per swapchain image one render-finished semaphore, which the
//! presentation engine has released by the time that image is acquired again.
//!
//! A host's set-up and frame with the engine's command buffers and swapchain
//! (docs/EMBEDDING.md quotes it, and its test checks that it still does):
//!
//! ```no_run
//! # use std::sync::Arc;
//! # use citystream_engine::commands::CommandContext;
//! # use citystream_engine::instance::InstanceOptions;
//! # use citystream_engine::present::{self, PresentMode, PresentWindow, Presenter, Surface};
//! # use citystream_engine::stream::TextureStreamer;
//! # use citystream_engine::target::RenderTarget;
//! # use citystream_engine::{Device, DeviceOptions, Result};
//! # use citystream_streaming::source::MipSource;
//! # fn host<S: MipSource + 'static>(
//! #     event_loop: &impl raw_window_handle::HasDisplayHandle,
//! #     window: Arc<dyn PresentWindow>,
//! #     size: (u32, u32),
//! #     new_streamer: impl FnOnce(&Arc<Device>) -> Result<TextureStreamer<S>>,
//! #     last_frame_ms: f64,
//! # ) -> Result<()> {
//! // The window system's instance extensions, before the device.
//! let extensions = present::instance_extensions(event_loop)?;
//! let instance = InstanceOptions { extensions, ..InstanceOptions::default() };
//! let options = DeviceOptions { instance, presentation: true, ..DeviceOptions::default() };
//! let device = Arc::new(Device::new(&options)?);
//! let mut streamer = new_streamer(&device)?;
//! let frames_in_flight = streamer.frames_in_flight();
//! // The surface keeps the window alive.
//! let surface = Surface::new(&device, Arc::clone(&window))?;
//! let mut presenter = Presenter::new(&device, surface, size, PresentMode::Vsync, frames_in_flight, false)?;
//! let target = RenderTarget::new(&device, size.0, size.1)?;
//! // The engine's command buffers, one per frame slot.
//! let mut commands = (0..frames_in_flight)
//!     .map(|slot| CommandContext::new(&device, &format!("frame slot {slot}")))
//!     .collect::<Result<Vec<_>>>()?;
//!
//! // Per frame:
//! let mut begun = streamer.begin_frame()?;
//! let slot = begun.slot() as usize;
//! // `begin_frame` waited until this slot's last frame completed: no fence to wait for.
//! let rec = commands[slot].begin_completed()?;
//! streamer.record_uploads(&mut begun, rec)?;
//! // ... the feedback pass, then `record_feedback_resolve` ...
//! target.begin(&device, rec, [0.0, 0.0, 0.0, 1.0]);
//! // ... the visible pass ...
//! target.end_and_copy(&device, rec);
//! // `None`: out of date (resize first) or a hidden window; the frame goes unpresented.
//! let image = presenter.acquire(begun.slot())?;
//! if let Some(image) = &image {
//!     presenter.record_blit(rec, image, &target, false)?;
//! }
//! let submit = streamer.end_frame(begun, last_frame_ms)?;
//! let mut waits = submit.waits.clone();
//! let mut signals = vec![submit.signal];
//! if let Some(image) = &image {
//!     waits.push(image.wait);
//!     signals.push(image.signal);
//! }
//! commands[slot].submit_frame(&waits, &signals)?;
//! if let Some(image) = image {
//!     // `false`: out of date or suboptimal; recreate at the window's size before the next frame.
//!     if !presenter.present(image)? {
//!         presenter.resize(size.0, size.1)?;
//!     }
//! }
//! # Ok(()) }
//! ```

use std::ffi::{CStr, CString};
use std::sync::Arc;

use ash::vk;
use gpu_allocator::MemoryLocation;
use raw_window_handle::{HasDisplayHandle, HasWindowHandle, RawDisplayHandle};

use crate::buffer::{Buffer, BufferDesc};
use crate::commands::{Recording, Semaphore, SemaphoreSignal, SemaphoreWait};
use crate::device::Device;
use crate::error::{EngineError, Result, VkResultExt};
use crate::image::{memory_barrier, transition};
use crate::target::RenderTarget;

/// The instance extensions a surface on `display` needs; put them in
/// `InstanceOptions::extensions`.
pub fn instance_extensions(display: &impl HasDisplayHandle) -> Result<Vec<CString>> {
    let raw = display
        .display_handle()
        .map_err(|e| EngineError::InvalidRequest(format!("the window system gave no display handle: {e}")))?
        .as_raw();
    instance_extensions_for(raw)
}

fn instance_extensions_for(display: RawDisplayHandle) -> Result<Vec<CString>> {
    let names = ash_window::enumerate_required_extensions(display).map_err(|result| {
        EngineError::InvalidRequest(format!("this window system cannot present with Vulkan ({result})"))
    })?;
    Ok(names
        .iter()
        // SAFETY: ash-window returns pointers to ash's static, NUL-terminated extension names.
        .map(|&name| unsafe { CStr::from_ptr(name) }.to_owned())
        .collect())
}

/// A window the surface presents to: kept alive by the surface, so the
/// window outlives it.
pub trait PresentWindow: HasDisplayHandle + HasWindowHandle + Send + Sync + std::fmt::Debug {}
impl<T: HasDisplayHandle + HasWindowHandle + Send + Sync + std::fmt::Debug> PresentWindow for T {}

/// A `VkSurfaceKHR` for one window, which it keeps alive.
pub struct Surface {
    // Keeps the instance (owned by the device) alive until the surface is destroyed.
    _device: Arc<Device>,
    loader: ash::khr::surface::Instance,
    raw: vk::SurfaceKHR,
    _window: Arc<dyn PresentWindow>,
}

debug_fields!(Surface { raw });

impl Surface {
    /// Creates the surface of `window` on the engine's own device (created
    /// with [`instance_extensions`] and `DeviceOptions::presentation`), and
    /// checks that the device's queue can present to it.
    pub fn new(device: &Arc<Device>, window: Arc<dyn PresentWindow>) -> Result<Self> {
        let instance = device.instance().ok_or_else(|| {
            EngineError::InvalidRequest(
                "a host's device: create the surface and swapchain with the host's instance".into(),
            )
        })?;
        let display = window
            .display_handle()
            .map_err(|e| EngineError::InvalidRequest(format!("the window has no display handle: {e}")))?
            .as_raw();
        let handle = window
            .window_handle()
            .map_err(|e| EngineError::InvalidRequest(format!("the window has no window handle: {e}")))?
            .as_raw();
        // SAFETY: the handles come from a live window that `self` keeps alive
        // (`_window`); the instance was created with the surface extensions.
        let raw = unsafe { ash_window::create_surface(&instance.entry, &instance.raw, display, handle, None) }
            .vk("vkCreate*SurfaceKHR")?;
        let loader = ash::khr::surface::Instance::new(&instance.entry, &instance.raw);
        let surface = Self {
            _device: Arc::clone(device),
            loader,
            raw,
            _window: window,
        };
        // SAFETY: physical device, queue family and surface all belong to this instance.
        let supported = unsafe {
            surface
                .loader
                .get_physical_device_surface_support(device.physical(), device.queue_family(), raw)
        }
        .vk("vkGetPhysicalDeviceSurfaceSupportKHR")?;
        if !supported {
            return Err(EngineError::MissingFeature {
                device: device.name().to_owned(),
                feature: format!(
                    "presentation from queue family {} to this window",
                    device.queue_family()
                ),
            });
        }
        Ok(surface)
    }
}

impl Drop for Surface {
    fn drop(&mut self) {
        // SAFETY: the presenter owning the swapchain on it was dropped first (field order).
        unsafe { self.loader.destroy_surface(self.raw, None) };
    }
}

/// How presented frames meet the display's refresh.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PresentMode {
    /// Wait for vertical blank (FIFO): no tearing, at most the refresh rate.
    Vsync,
    /// The newest frame replaces a queued one (MAILBOX): no tearing, no wait.
    Mailbox,
    /// Present at once (IMMEDIATE): may tear, never waits.
    Immediate,
}

impl PresentMode {
    fn raw(self) -> vk::PresentModeKHR {
        match self {
            PresentMode::Vsync => vk::PresentModeKHR::FIFO,
            PresentMode::Mailbox => vk::PresentModeKHR::MAILBOX,
            PresentMode::Immediate => vk::PresentModeKHR::IMMEDIATE,
        }
    }

    /// The option's name: `vsync`, `mailbox` or `immediate`.
    pub fn name(self) -> &'static str {
        match self {
            PresentMode::Vsync => "vsync",
            PresentMode::Mailbox => "mailbox",
            PresentMode::Immediate => "immediate",
        }
    }
}

impl std::str::FromStr for PresentMode {
    type Err = String;

    fn from_str(text: &str) -> std::result::Result<Self, String> {
        match text {
            "vsync" | "fifo" => Ok(PresentMode::Vsync),
            "mailbox" => Ok(PresentMode::Mailbox),
            "immediate" => Ok(PresentMode::Immediate),
            other => Err(format!("unknown present mode {other:?}: vsync, mailbox or immediate")),
        }
    }
}

/// A swapchain image acquired for this frame: submit the frame waiting on
/// [`wait`](Self::wait) and signalling [`signal`](Self::signal), then
/// [`Presenter::present`] it.
#[derive(Debug)]
#[must_use = "an acquired image must be presented"]
pub struct AcquiredImage {
    index: u32,
    /// The frame's submission waits on this (the image is free to write).
    pub wait: SemaphoreWait,
    /// The frame's submission signals this (the image holds the frame).
    pub signal: SemaphoreSignal,
    suboptimal: bool,
}

/// The swapchain of one surface and what presenting through it needs.
pub struct Presenter {
    // Dropped first: the swapchain before the surface it was made on.
    swapchain: vk::SwapchainKHR,
    loader: ash::khr::swapchain::Device,
    images: Vec<vk::Image>,
    format: vk::Format,
    extent: vk::Extent2D,
    mode: PresentMode,
    requested: PresentMode,
    screenshots: bool,
    acquired: Vec<Semaphore>,
    rendered: Vec<Semaphore>,
    /// Render-finished semaphores of replaced swapchains: a present's wait
    /// on them is not covered by waiting for the queue (presents take no
    /// fence), so they live until the presenter goes.
    retired: Vec<Semaphore>,
    screenshot: Option<Buffer>,
    surface: Surface,
    device: Arc<Device>,
}

debug_fields!(Presenter { swapchain, images = |s| s.images.len(), format, extent, mode });

/// How long `acquire` waits for an image before the frame goes unpresented.
const ACQUIRE_TIMEOUT_NS: u64 = 1_000_000_000;

/// Swapchain formats that take the target's 8-bit UNORM values unchanged
/// (an sRGB format would encode them a second time).
const UNORM_FORMATS: [vk::Format; 2] = [vk::Format::B8G8R8A8_UNORM, vk::Format::R8G8B8A8_UNORM];

impl Presenter {
    /// A swapchain of `width` × `height` (the surface's own extent where it
    /// has one) in `mode`, falling back to vsync (always supported) where the
    /// surface lacks the mode; `frames_in_flight` acquire semaphores. With
    /// `screenshots`, [`record_blit`](Self::record_blit) can also copy the
    /// presented image to the host.
    pub fn new(
        device: &Arc<Device>,
        surface: Surface,
        (width, height): (u32, u32),
        mode: PresentMode,
        frames_in_flight: u32,
        screenshots: bool,
    ) -> Result<Self> {
        let instance = device
            .instance()
            .ok_or_else(|| EngineError::InvalidRequest("presenting needs the engine's own instance".into()))?;
        let loader = ash::khr::swapchain::Device::new(&instance.raw, device.raw());
        let acquired = (0..frames_in_flight.max(1))
            .map(|slot| Semaphore::new(device, &format!("swapchain image acquired (slot {slot})")))
            .collect::<Result<Vec<_>>>()?;
        let mut presenter = Self {
            swapchain: vk::SwapchainKHR::null(),
            loader,
            images: Vec::new(),
            format: vk::Format::UNDEFINED,
            extent: vk::Extent2D::default(),
            mode,
            requested: mode,
            screenshots,
            acquired,
            rendered: Vec::new(),
            retired: Vec::new(),
            screenshot: None,
            surface,
            device: Arc::clone(device),
        };
        if !presenter.create(width, height, mode)? {
            return Err(EngineError::InvalidRequest(
                "the window has no area (minimised?): create the presenter once it shows".into(),
            ));
        }
        Ok(presenter)
    }

    /// The swapchain's extent.
    pub fn extent(&self) -> (u32, u32) {
        (self.extent.width, self.extent.height)
    }

    /// The present mode in use (the requested one, or vsync where the surface lacked it).
    pub fn mode(&self) -> PresentMode {
        self.mode
    }

    /// The swapchain's format.
    pub fn format(&self) -> vk::Format {
        self.format
    }

    /// `false`: the window has no area now (minimised); the old swapchain stays.
    fn create(&mut self, width: u32, height: u32, wanted: PresentMode) -> Result<bool> {
        let physical = self.device.physical();
        let surface = self.surface.raw;
        let loader = &self.surface.loader;
        // SAFETY: physical device and surface belong to this instance.
        let caps = unsafe { loader.get_physical_device_surface_capabilities(physical, surface) }
            .vk("vkGetPhysicalDeviceSurfaceCapabilitiesKHR")?;
        // SAFETY: as above.
        let formats = unsafe { loader.get_physical_device_surface_formats(physical, surface) }
            .vk("vkGetPhysicalDeviceSurfaceFormatsKHR")?;
        // SAFETY: as above.
        let modes = unsafe { loader.get_physical_device_surface_present_modes(physical, surface) }
            .vk("vkGetPhysicalDeviceSurfacePresentModesKHR")?;
        let format = UNORM_FORMATS
            .iter()
            .find_map(|wanted| formats.iter().find(|f| f.format == *wanted))
            .copied()
            .ok_or_else(|| EngineError::MissingFeature {
                device: self.device.name().to_owned(),
                feature: format!("an 8-bit UNORM swapchain format for this window (it offers {formats:?})"),
            })?;
        let blit_dst = self.device.format_properties(format.format).optimal_tiling_features;
        let blit_src = self
            .device
            .format_properties(crate::target::COLOR_FORMAT)
            .optimal_tiling_features;
        if !blit_dst.contains(vk::FormatFeatureFlags::BLIT_DST | vk::FormatFeatureFlags::SAMPLED_IMAGE_FILTER_LINEAR)
            || !blit_src
                .contains(vk::FormatFeatureFlags::BLIT_SRC | vk::FormatFeatureFlags::SAMPLED_IMAGE_FILTER_LINEAR)
        {
            return Err(EngineError::MissingFeature {
                device: self.device.name().to_owned(),
                feature: format!(
                    "linear blits from {:?} to the swapchain's {:?}",
                    crate::target::COLOR_FORMAT,
                    format.format
                ),
            });
        }
        let mut usage = vk::ImageUsageFlags::TRANSFER_DST;
        if self.screenshots {
            usage |= vk::ImageUsageFlags::TRANSFER_SRC;
        }
        if !caps.supported_usage_flags.contains(usage) {
            return Err(EngineError::MissingFeature {
                device: self.device.name().to_owned(),
                feature: format!(
                    "swapchain images usable as {usage:?} (the surface allows {:?})",
                    caps.supported_usage_flags
                ),
            });
        }
        let extent = if caps.current_extent.width == u32::MAX {
            vk::Extent2D {
                width: width.clamp(caps.min_image_extent.width, caps.max_image_extent.width),
                height: height.clamp(caps.min_image_extent.height, caps.max_image_extent.height),
            }
        } else {
            caps.current_extent
        };
        if extent.width == 0 || extent.height == 0 {
            return Ok(false);
        }
        self.mode = if modes.contains(&wanted.raw()) {
            wanted
        } else {
            PresentMode::Vsync
        };
        let mut image_count = caps.min_image_count + 1;
        if caps.max_image_count > 0 {
            image_count = image_count.min(caps.max_image_count);
        }
        let alpha = [
            vk::CompositeAlphaFlagsKHR::OPAQUE,
            vk::CompositeAlphaFlagsKHR::INHERIT,
            vk::CompositeAlphaFlagsKHR::PRE_MULTIPLIED,
            vk::CompositeAlphaFlagsKHR::POST_MULTIPLIED,
        ]
        .into_iter()
        .find(|a| caps.supported_composite_alpha.contains(*a))
        .unwrap_or(vk::CompositeAlphaFlagsKHR::OPAQUE);
        let old = self.swapchain;
        let info = vk::SwapchainCreateInfoKHR::default()
            .surface(surface)
            .min_image_count(image_count)
            .image_format(format.format)
            .image_color_space(format.color_space)
            .image_extent(extent)
            .image_array_layers(1)
            .image_usage(usage)
            .image_sharing_mode(vk::SharingMode::EXCLUSIVE)
            .pre_transform(caps.current_transform)
            .composite_alpha(alpha)
            .present_mode(self.mode.raw())
            .clipped(true)
            .old_swapchain(old);
        // SAFETY: the surface is live; `old` (if any) is retired by this call
        // and destroyed below once the queue is idle (see `resize`).
        let swapchain = unsafe { self.loader.create_swapchain(&info, None) }.vk("vkCreateSwapchainKHR")?;
        if old != vk::SwapchainKHR::null() {
            // SAFETY: `resize` waited for the queue; nothing uses the old swapchain.
            unsafe { self.loader.destroy_swapchain(old, None) };
        }
        self.swapchain = swapchain;
        // SAFETY: the swapchain was just created by this loader.
        self.images = unsafe { self.loader.get_swapchain_images(swapchain) }.vk("vkGetSwapchainImagesKHR")?;
        self.format = format.format;
        self.extent = extent;
        let rendered = (0..self.images.len())
            .map(|i| Semaphore::new(&self.device, &format!("swapchain image {i} rendered")))
            .collect::<Result<Vec<_>>>()?;
        self.retired
            .append(&mut std::mem::replace(&mut self.rendered, rendered));
        self.screenshot = if self.screenshots {
            Some(Buffer::new(
                &self.device,
                BufferDesc {
                    size: u64::from(extent.width) * u64::from(extent.height) * 4,
                    usage: vk::BufferUsageFlags::TRANSFER_DST,
                    location: MemoryLocation::GpuToCpu,
                },
                "swapchain screenshot",
            )?)
        } else {
            None
        };
        Ok(true)
    }

    /// Recreates the swapchain for a window now `width` × `height` (after a
    /// resize, or when [`acquire`](Self::acquire) or
    /// [`present`](Self::present) said it is out of date). Waits for the
    /// queue to go idle first: the old images, semaphores and screenshot
    /// buffer may still be in use. `false`: the window has no area now
    /// (minimised); render nothing and try again once it has one.
    pub fn resize(&mut self, width: u32, height: u32) -> Result<bool> {
        self.device.wait_idle()?;
        self.create(width, height, self.requested)
    }

    /// Acquires the next image for the frame in `slot` (the slot whose
    /// previous frame the caller saw complete); `None` when the swapchain is
    /// out of date and must be [`resize`](Self::resize)d first, or when no
    /// image came within a second (a hidden window): render without presenting.
    pub fn acquire(&mut self, slot: u32) -> Result<Option<AcquiredImage>> {
        let semaphore = self
            .acquired
            .get(slot as usize)
            .ok_or_else(|| EngineError::InvalidRequest(format!("frame slot {slot} beyond the presenter's slots")))?
            .raw();
        // SAFETY: the swapchain is live; the semaphore's last wait (this
        // slot's previous frame) completed, so it is unsignalled and unused.
        let acquired = unsafe {
            self.loader
                .acquire_next_image(self.swapchain, ACQUIRE_TIMEOUT_NS, semaphore, vk::Fence::null())
        };
        let (index, suboptimal) = match acquired {
            Ok(pair) => pair,
            // A hidden window may never release an image (no refresh comes):
            // the frame goes unpresented rather than the program hanging.
            Err(vk::Result::ERROR_OUT_OF_DATE_KHR | vk::Result::TIMEOUT | vk::Result::NOT_READY) => return Ok(None),
            Err(e) => return Err(e).vk("vkAcquireNextImageKHR"),
        };
        Ok(Some(AcquiredImage {
            index,
            wait: SemaphoreWait::binary(semaphore, vk::PipelineStageFlags2::BLIT),
            signal: SemaphoreSignal {
                semaphore: self.rendered[index as usize].raw(),
                value: 0,
            },
            suboptimal,
        }))
    }

    /// Records the blit of `target`'s colour (as its `end_and_copy` left
    /// it) into the acquired image, scaled if the sizes differ, and the
    /// transition for presentation; with `screenshot`, also the copy of the
    /// presented image for [`read_screenshot`](Self::read_screenshot).
    pub fn record_blit(
        &self,
        rec: Recording<'_>,
        acquired: &AcquiredImage,
        target: &RenderTarget,
        screenshot: bool,
    ) -> Result<()> {
        let cmd = rec.raw();
        let image = self.images[acquired.index as usize];
        let range = vk::ImageSubresourceRange {
            aspect_mask: vk::ImageAspectFlags::COLOR,
            base_mip_level: 0,
            level_count: 1,
            base_array_layer: 0,
            layer_count: 1,
        };
        let device = &*self.device;
        // The acquired image from one layout to another.
        let image_transition = |from, to, src, dst| transition(device, rec, image, range, from, to, src, dst);
        // Chained to the acquire semaphore's wait at the blit stage.
        image_transition(
            vk::ImageLayout::UNDEFINED,
            vk::ImageLayout::TRANSFER_DST_OPTIMAL,
            (vk::PipelineStageFlags2::BLIT, vk::AccessFlags2::NONE),
            (vk::PipelineStageFlags2::BLIT, vk::AccessFlags2::TRANSFER_WRITE),
        );
        let layers = vk::ImageSubresourceLayers {
            aspect_mask: vk::ImageAspectFlags::COLOR,
            mip_level: 0,
            base_array_layer: 0,
            layer_count: 1,
        };
        let corner = |w: u32, h: u32| vk::Offset3D {
            x: w as i32,
            y: h as i32,
            z: 1,
        };
        let region = vk::ImageBlit {
            src_subresource: layers,
            src_offsets: [vk::Offset3D::default(), corner(target.width(), target.height())],
            dst_subresource: layers,
            dst_offsets: [vk::Offset3D::default(), corner(self.extent.width, self.extent.height)],
        };
        let same_size = (target.width(), target.height()) == (self.extent.width, self.extent.height);
        let filter = if same_size {
            vk::Filter::NEAREST
        } else {
            vk::Filter::LINEAR
        };
        // SAFETY: the target's colour is in TRANSFER_SRC_OPTIMAL (end_and_copy,
        // whose barrier includes the blit stage); the image was just transitioned.
        unsafe {
            device.raw.cmd_blit_image(
                cmd,
                target.color_image(),
                vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                image,
                vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                &[region],
                filter,
            )
        };
        let mut layout = vk::ImageLayout::TRANSFER_DST_OPTIMAL;
        let mut last = (vk::PipelineStageFlags2::BLIT, vk::AccessFlags2::TRANSFER_WRITE);
        if screenshot {
            let buffer = self
                .screenshot
                .as_ref()
                .ok_or_else(|| EngineError::InvalidRequest("the presenter was created without screenshots".into()))?;
            image_transition(
                layout,
                vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                last,
                (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_READ),
            );
            // An earlier frame's screenshot copy finishes before this one overwrites the buffer.
            memory_barrier(
                device,
                rec,
                (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE),
                (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE),
            );
            let copy = vk::BufferImageCopy {
                buffer_offset: 0,
                buffer_row_length: 0,
                buffer_image_height: 0,
                image_subresource: layers,
                image_offset: vk::Offset3D::default(),
                image_extent: vk::Extent3D {
                    width: self.extent.width,
                    height: self.extent.height,
                    depth: 1,
                },
            };
            // SAFETY: image in TRANSFER_SRC_OPTIMAL; the buffer holds extent × 4 bytes.
            unsafe {
                device.raw.cmd_copy_image_to_buffer(
                    cmd,
                    image,
                    vk::ImageLayout::TRANSFER_SRC_OPTIMAL,
                    buffer.raw(),
                    &[copy],
                )
            };
            memory_barrier(
                device,
                rec,
                (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE),
                (vk::PipelineStageFlags2::HOST, vk::AccessFlags2::HOST_READ),
            );
            layout = vk::ImageLayout::TRANSFER_SRC_OPTIMAL;
            last = (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_READ);
        }
        // Presentation waits on the render-finished semaphore, whose signal
        // (at all commands) makes the writes available; no access after it.
        image_transition(
            layout,
            vk::ImageLayout::PRESENT_SRC_KHR,
            last,
            (vk::PipelineStageFlags2::NONE, vk::AccessFlags2::NONE),
        );
        Ok(())
    }

    /// Presents the image once the frame that signalled `acquired.signal`
    /// has rendered it. `false`: the swapchain no longer matches the window
    /// (out of date or suboptimal); [`resize`](Self::resize) before the next frame.
    pub fn present(&mut self, acquired: AcquiredImage) -> Result<bool> {
        let waits = [acquired.signal.semaphore];
        let swapchains = [self.swapchain];
        let indices = [acquired.index];
        let info = vk::PresentInfoKHR::default()
            .wait_semaphores(&waits)
            .swapchains(&swapchains)
            .image_indices(&indices);
        let result = {
            let queue = self.device.queue();
            // SAFETY: queue access is serialised by the lock; the image was
            // acquired from this swapchain and its frame submitted signalling `waits`.
            unsafe { self.loader.queue_present(*queue, &info) }
        };
        match result {
            // Some surfaces report every present as suboptimal (a copy
            // path); recreating is worth it only when the size changed.
            Ok(suboptimal) if suboptimal || acquired.suboptimal => Ok(!self.extent_changed()?),
            Ok(_) => Ok(true),
            Err(vk::Result::ERROR_OUT_OF_DATE_KHR) => Ok(false),
            Err(e) => Err(e).vk("vkQueuePresentKHR"),
        }
    }

    /// Whether the surface's extent differs from the swapchain's.
    fn extent_changed(&self) -> Result<bool> {
        // SAFETY: physical device and surface belong to this instance.
        let caps = unsafe {
            self.surface
                .loader
                .get_physical_device_surface_capabilities(self.device.physical(), self.surface.raw)
        }
        .vk("vkGetPhysicalDeviceSurfaceCapabilitiesKHR")?;
        Ok(caps.current_extent.width != u32::MAX && caps.current_extent != self.extent)
    }

    /// The image the last [`record_blit`](Self::record_blit) with
    /// `screenshot` copied, as RGBA, once its frame has completed.
    pub fn read_screenshot(&self) -> Result<image::RgbaImage> {
        let buffer = self
            .screenshot
            .as_ref()
            .ok_or_else(|| EngineError::InvalidRequest("the presenter was created without screenshots".into()))?;
        let (width, height) = (self.extent.width, self.extent.height);
        let mut bytes = buffer.read::<u8>(0, (width * height * 4) as usize)?;
        if self.format == vk::Format::B8G8R8A8_UNORM {
            for pixel in bytes.chunks_exact_mut(4) {
                pixel.swap(0, 2);
            }
        }
        image::RgbaImage::from_raw(width, height, bytes)
            .ok_or_else(|| EngineError::InvalidRequest("screenshot buffer smaller than the swapchain".into()))
    }
}

impl Drop for Presenter {
    fn drop(&mut self) {
        // The last frames may still wait on the semaphores or present the
        // images; nothing of the swapchain may go before they are done.
        let _ = self.device.wait_idle();
        // SAFETY: the queue is idle; the swapchain was created by this loader.
        unsafe { self.loader.destroy_swapchain(self.swapchain, None) };
    }
}
