//! Physical-device choice, the logical device, its queue and allocator.
//!
//! citystream needs a queue family that does graphics and compute, fragment
//! stores and atomics for the feedback pass, BC texture compression and
//! Vulkan 1.3 (dynamic rendering, synchronization2). Sparse binding and
//! residency for 2D images (and sparse binding on that queue, so the bind and
//! the copy that waits on it share one queue) give the sparse texture cache;
//! a device without them, or one created with [`SparseMode::Off`], gets the
//! texture-array cache ([`TextureBacking`]).

use std::ffi::CStr;
use std::sync::{Arc, Mutex, MutexGuard};

use ash::vk;
use gpu_allocator::vulkan::{Allocator, AllocatorCreateDesc};

use crate::error::{EngineError, Result, VkResultExt};
use crate::instance::{Instance, InstanceOptions, ValidationLog};
pub use select::{
    check_physical_device, choose_device, device_requirements, list_devices, list_devices_masked, required_features,
    DeviceRequirements, RequiredFeatures,
};
use select::{examine_raw, masked_features};

mod select;

/// Environment variable that picks a device by (part of) its name.
pub const DEVICE_ENV: &str = "CITYSTREAM_DEVICE";

/// Environment variable naming device features (Vulkan names, comma
/// separated) to treat as absent, as if the device did not report them: how
/// tests see what the engine does on a device without, say,
/// `sparseResidencyImage2D`.
pub const MASK_FEATURES_ENV: &str = "CITYSTREAM_MASK_FEATURES";

/// Whether a device is set up for the sparse texture cache.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum SparseMode {
    /// Sparse residency where the device has it, texture arrays otherwise.
    #[default]
    Auto,
    /// Sparse residency; a device without it is refused.
    On,
    /// Texture arrays, with the sparse features left disabled even where the
    /// device has them.
    Off,
}

/// How the texture cache holds textures on a device.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TextureBacking {
    /// Sparse partially resident array images, bound block by block (the
    /// paper's cache).
    Sparse,
    /// Ordinary, fully bound 2D array images, a full mip chain's memory per
    /// layer (Trapp and Döllner's texture arrays), for devices without
    /// sparse residency.
    Arrays,
}

impl TextureBacking {
    /// `sparse` or `texture-arrays`, as reports and the command line say it.
    pub fn name(self) -> &'static str {
        match self {
            TextureBacking::Sparse => "sparse",
            TextureBacking::Arrays => "texture-arrays",
        }
    }
}

/// Options for [`Device::new`].
#[derive(Clone, Debug, Default)]
pub struct DeviceOptions {
    /// Instance options (validation on or off).
    pub instance: InstanceOptions,
    /// Case-insensitive substring of the wanted device's name. When `None`,
    /// `CITYSTREAM_DEVICE` is consulted, then the best device is chosen.
    pub device_name: Option<String>,
    /// Enable `VK_KHR_swapchain` to present to a window (the `present`
    /// module); fails with [`EngineError::MissingFeature`] where the device
    /// lacks it.
    pub presentation: bool,
    /// Sparse texture cache or texture arrays ([`Device::texture_backing`]).
    pub sparse: SparseMode,
    /// Features (Vulkan names) treated as absent; empty: those of
    /// [`MASK_FEATURES_ENV`], if set.
    pub masked_features: Vec<String>,
}

/// What the chosen device reports about sparse residency.
#[derive(Clone, Copy, Debug)]
pub struct SparseSupport {
    /// `residencyNonResidentStrict`: non-resident reads return zero.
    pub non_resident_strict: bool,
    /// `shaderResourceMinLod` (`sparseTextureClampARB`).
    pub shader_min_lod: bool,
    /// `sparseAddressSpaceSize`: the engine enforces it, drivers may not.
    pub address_space_size: u64,
}

/// A physical device that was looked at, with what it lacks.
#[derive(Clone, Debug)]
pub struct DeviceCandidate {
    /// Device name.
    pub name: String,
    /// Device type.
    pub device_type: vk::PhysicalDeviceType,
    /// Missing requirements of every path; empty when usable.
    pub missing: Vec<String>,
    /// Missing requirements of the sparse texture cache; empty when the
    /// device can have it.
    pub missing_sparse: Vec<String>,
    physical: vk::PhysicalDevice,
    /// The first queue family with GRAPHICS and COMPUTE.
    queue_family: Option<u32>,
    /// The first with SPARSE_BINDING as well.
    sparse_queue_family: Option<u32>,
}

impl DeviceCandidate {
    /// The backing `mode` gives on this device, or what it lacks for it.
    pub fn backing(&self, mode: SparseMode) -> std::result::Result<TextureBacking, String> {
        if let Some(first) = self.missing.first() {
            return Err(first.clone());
        }
        match mode {
            SparseMode::Off => Ok(TextureBacking::Arrays),
            SparseMode::Auto if !self.missing_sparse.is_empty() => Ok(TextureBacking::Arrays),
            SparseMode::Auto => Ok(TextureBacking::Sparse),
            SparseMode::On => match self.missing_sparse.first() {
                Some(first) => Err(format!("{first} (asked for the sparse texture cache)")),
                None => Ok(TextureBacking::Sparse),
            },
        }
    }
}

/// The logical device with its one queue and allocator.
///
/// Threading: `Device` is `Send + Sync`; the queue is behind a mutex
/// ([`Device::queue`]) because Vulkan requires external synchronisation of
/// queue submissions; the allocator is behind another.
pub struct Device {
    pub(crate) raw: ash::Device,
    pub(crate) physical: vk::PhysicalDevice,
    queue: Mutex<vk::Queue>,
    queue_family: u32,
    allocator: AllocatorSlot,
    debug_utils: Option<ash::ext::debug_utils::Device>,
    properties: vk::PhysicalDeviceProperties,
    name: String,
    sparse: SparseSupport,
    backing: TextureBacking,
    /// Why `SparseMode::Auto` chose texture arrays on a device that has the
    /// sparse features, or lacks them (`None` with the sparse backing).
    sparse_fallback: Option<String>,
    /// The core features the device was created with (for a host's device,
    /// those the engine requires of it).
    enabled_features: vk::PhysicalDeviceFeatures,
    instance_fns: ash::Instance,
    log: Arc<ValidationLog>,
    /// Whether `Drop` destroys the logical device (false for a host's device).
    owns_device: bool,
    // Dropped last: destroyed after the logical device in `Drop`; `None`
    // for a host's instance.
    instance: Option<Instance>,
}

/// What [`Device::assemble`] builds a device from.
struct DeviceParts {
    instance_fns: ash::Instance,
    raw: ash::Device,
    physical: vk::PhysicalDevice,
    queue: vk::Queue,
    queue_family: u32,
    allocator: AllocatorSlot,
    debug_utils: bool,
    backing: TextureBacking,
    sparse_fallback: Option<String>,
    log: Arc<ValidationLog>,
    owns_device: bool,
    instance: Option<Instance>,
}

/// The allocator the engine's resources come from.
enum AllocatorSlot {
    /// The engine's own, taken out before the device is destroyed.
    Own(Box<Mutex<Option<Allocator>>>),
    /// A host's allocator, shared with the host.
    Shared(Arc<Mutex<Allocator>>),
}

/// Which allocator a device built from a host's handles uses.
pub enum HostAllocator {
    /// The engine creates its own gpu-allocator on the host's device.
    Create,
    /// The engine allocates from the host's gpu-allocator.
    Shared(Arc<Mutex<Allocator>>),
}

impl std::fmt::Debug for HostAllocator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            HostAllocator::Create => "HostAllocator::Create",
            HostAllocator::Shared(_) => "HostAllocator::Shared",
        })
    }
}

/// A host renderer's own Vulkan objects, for [`Device::from_host`].
pub struct HostDevice {
    /// The loader entry the host uses.
    pub entry: ash::Entry,
    /// The host's instance (Vulkan 1.3).
    pub instance: vk::Instance,
    /// The physical device the host chose.
    pub physical_device: vk::PhysicalDevice,
    /// The host's logical device, created with at least
    /// [`required_features`] of `backing`.
    pub device: vk::Device,
    /// A queue of `queue_family` the engine submits to (binds, uploads).
    pub queue: vk::Queue,
    /// Its family: GRAPHICS and COMPUTE, and SPARSE_BINDING for the sparse
    /// backing (see [`DeviceRequirements`]).
    pub queue_family: u32,
    /// The texture cache the host enabled the features of.
    pub backing: TextureBacking,
    /// Where the engine's memory comes from.
    pub allocator: HostAllocator,
    /// Whether the instance has `VK_EXT_debug_utils` enabled (the engine
    /// then names its objects).
    pub debug_utils: bool,
}

debug_fields!(HostDevice {
    instance,
    physical_device,
    device,
    queue_family,
    backing,
    allocator
});

debug_fields!(Device {
    name,
    queue_family,
    backing
});

impl Device {
    /// Creates the instance and the device.
    pub fn new(options: &DeviceOptions) -> Result<Self> {
        let instance = Instance::new(&options.instance)?;
        let candidates = list_devices_masked(&instance, &masked_features(options)?)?;
        let env_name = std::env::var(DEVICE_ENV).ok().filter(|s| !s.is_empty());
        let wanted = options.device_name.clone().or(env_name);
        let (chosen, backing) = choose_device(&candidates, wanted.as_deref(), options.sparse)?;
        let family = match backing {
            TextureBacking::Sparse => chosen.sparse_queue_family,
            TextureBacking::Arrays => chosen.queue_family,
        };
        let queue_family = family.ok_or_else(|| EngineError::MissingFeature {
            device: chosen.name.clone(),
            feature: format!(
                "a queue family with {:?}",
                device_requirements().queue_flags_for(backing)
            ),
        })?;
        let physical = chosen.physical;

        let priorities = [1.0f32];
        let queue_infos = [vk::DeviceQueueCreateInfo::default()
            .queue_family_index(queue_family)
            .queue_priorities(&priorities)];
        let mut extensions = Vec::new();
        if options.presentation {
            // SAFETY: plain enumeration on a physical device of this instance.
            let available = unsafe { instance.raw.enumerate_device_extension_properties(physical) }
                .vk("vkEnumerateDeviceExtensionProperties")?;
            if !available.iter().any(|e| {
                e.extension_name_as_c_str()
                    .is_ok_and(|n| n == ash::khr::swapchain::NAME)
            }) {
                return Err(EngineError::MissingFeature {
                    device: chosen.name.clone(),
                    feature: "VK_KHR_swapchain (presentation to a window)".to_owned(),
                });
            }
            extensions.push(ash::khr::swapchain::NAME.as_ptr());
        }
        let required = required_features(backing);
        let mut vk12 = required.vulkan12;
        let mut vk13 = required.vulkan13;
        let create_info = vk::DeviceCreateInfo::default()
            .queue_create_infos(&queue_infos)
            .enabled_extension_names(&extensions)
            .enabled_features(&required.core)
            .push_next(&mut vk12)
            .push_next(&mut vk13);
        // SAFETY: physical came from this instance; create_info points at live data.
        let raw = unsafe { instance.raw.create_device(physical, &create_info, None) }.vk("vkCreateDevice")?;
        // SAFETY: the queue family and index were requested in create_info.
        let queue = unsafe { raw.get_device_queue(queue_family, 0) };
        let allocator = match create_allocator(&instance.raw, &raw, physical) {
            Ok(a) => a,
            Err(e) => {
                // SAFETY: nothing was created from the device yet.
                unsafe { raw.destroy_device(None) };
                return Err(e);
            }
        };
        Ok(Self::assemble(DeviceParts {
            instance_fns: instance.raw.clone(),
            raw,
            physical,
            queue,
            queue_family,
            allocator: AllocatorSlot::Own(Box::new(Mutex::new(Some(allocator)))),
            debug_utils: instance.has_debug_utils(),
            backing,
            sparse_fallback: (backing == TextureBacking::Arrays && options.sparse == SparseMode::Auto)
                .then(|| chosen.missing_sparse.first().cloned())
                .flatten(),
            log: Arc::clone(instance.validation_log()),
            owns_device: true,
            instance: Some(instance),
        }))
    }

    /// The one place a `Device` is put together, for the engine's own
    /// objects and for a host's alike.
    fn assemble(parts: DeviceParts) -> Self {
        let physical = parts.physical;
        // SAFETY: `physical` came from this instance.
        let properties = unsafe { parts.instance_fns.get_physical_device_properties(physical) };
        let name = properties
            .device_name_as_c_str()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|_| "<unnamed device>".to_owned());
        let debug_utils = parts
            .debug_utils
            .then(|| ash::ext::debug_utils::Device::new(&parts.instance_fns, &parts.raw));
        let sparse = SparseSupport {
            non_resident_strict: properties.sparse_properties.residency_non_resident_strict == vk::TRUE,
            shader_min_lod: chosen_feature_min_lod(&parts.instance_fns, physical),
            address_space_size: properties.limits.sparse_address_space_size,
        };
        Self {
            raw: parts.raw,
            physical,
            queue: Mutex::new(parts.queue),
            queue_family: parts.queue_family,
            allocator: parts.allocator,
            debug_utils,
            properties,
            name,
            sparse,
            backing: parts.backing,
            sparse_fallback: parts.sparse_fallback,
            enabled_features: required_features(parts.backing).core,
            instance_fns: parts.instance_fns,
            log: parts.log,
            owns_device: parts.owns_device,
            instance: parts.instance,
        }
    }

    /// A device over a host renderer's own instance, device and queue: the
    /// seam for embedding the engine. The engine checks that the physical
    /// device has what it needs ([`device_requirements`]) and that
    /// `queue_family` has the queue flags, and never destroys the host's
    /// objects; the host destroys its device only after dropping this
    /// `Device` and everything built on it. Validation messages go to the
    /// host's own messenger; [`Device::validation_log`] stays empty.
    ///
    /// # Safety
    /// Every handle must be valid and come from `entry` and `instance`;
    /// `device` must have been created on `physical_device` with every
    /// feature of [`required_features`] enabled and with a queue of
    /// `queue_family`, and `queue` must be that queue. The host must not
    /// submit to `queue` concurrently with the engine except while holding
    /// [`Device::queue`]. The engine waits for idle on that queue only
    /// (`vkQueueWaitIdle`), never for the whole device.
    pub unsafe fn from_host(host: HostDevice) -> Result<Self> {
        // SAFETY: the caller guarantees the handles are valid and belong together.
        let instance_fns = unsafe { ash::Instance::load(host.entry.static_fn(), host.instance) };
        // SAFETY: as above.
        let raw = unsafe { ash::Device::load(instance_fns.fp_v1_0(), host.device) };
        let physical = host.physical_device;
        let candidate = examine_raw(&instance_fns, physical, &[]);
        let name = candidate.name.clone();
        let mode = match host.backing {
            TextureBacking::Sparse => SparseMode::On,
            TextureBacking::Arrays => SparseMode::Off,
        };
        if let Err(feature) = candidate.backing(mode) {
            return Err(EngineError::MissingFeature { device: name, feature });
        }
        // SAFETY: `physical` came from this instance.
        let families = unsafe { instance_fns.get_physical_device_queue_family_properties(physical) };
        let wanted = device_requirements().queue_flags_for(host.backing);
        if !families
            .get(host.queue_family as usize)
            .is_some_and(|f| f.queue_flags.contains(wanted))
        {
            return Err(EngineError::MissingFeature {
                device: name,
                feature: format!("queue family {} with {wanted:?} (the host's queue)", host.queue_family),
            });
        }
        let allocator = match host.allocator {
            HostAllocator::Create => AllocatorSlot::Own(Box::new(Mutex::new(Some(create_allocator(
                &instance_fns,
                &raw,
                physical,
            )?)))),
            HostAllocator::Shared(shared) => AllocatorSlot::Shared(shared),
        };
        Ok(Self::assemble(DeviceParts {
            instance_fns,
            raw,
            physical,
            queue: host.queue,
            queue_family: host.queue_family,
            allocator,
            debug_utils: host.debug_utils,
            backing: host.backing,
            sparse_fallback: None,
            log: Arc::new(ValidationLog::default()),
            owns_device: false,
            instance: None,
        }))
    }

    /// The raw `ash` device.
    pub fn raw(&self) -> &ash::Device {
        &self.raw
    }

    /// The instance the engine created, or `None` for a host's device.
    pub fn instance(&self) -> Option<&Instance> {
        self.instance.as_ref()
    }

    /// The instance's functions (the engine's or the host's instance).
    pub fn instance_fns(&self) -> &ash::Instance {
        &self.instance_fns
    }

    /// Whether the engine created (and destroys) this logical device.
    pub fn owns_device(&self) -> bool {
        self.owns_device
    }

    /// The chosen physical device.
    pub fn physical(&self) -> vk::PhysicalDevice {
        self.physical
    }

    /// The device's name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Device properties and limits.
    pub fn properties(&self) -> &vk::PhysicalDeviceProperties {
        &self.properties
    }

    /// Sparse-residency properties of the device.
    pub fn sparse_support(&self) -> SparseSupport {
        self.sparse
    }

    /// How texture caches on this device hold textures: sparse images where
    /// the device was created with the sparse features, texture arrays
    /// otherwise.
    pub fn texture_backing(&self) -> TextureBacking {
        self.backing
    }

    /// What the device lacks for the sparse cache, where `SparseMode::Auto`
    /// chose texture arrays (a feature, the queue family, or a format the
    /// cache cannot serve sparse); `None` otherwise.
    pub fn sparse_fallback_reason(&self) -> Option<&str> {
        self.sparse_fallback.as_deref()
    }

    /// The core features enabled on the device ([`required_features`] of its
    /// backing).
    pub fn enabled_features(&self) -> vk::PhysicalDeviceFeatures {
        self.enabled_features
    }

    /// The family of the one queue the engine uses.
    pub fn queue_family(&self) -> u32 {
        self.queue_family
    }

    /// Locks the queue for a submission.
    pub fn queue(&self) -> MutexGuard<'_, vk::Queue> {
        self.queue.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Runs `f` with the allocator; `None` once the device is shutting down.
    pub(crate) fn with_allocator<R>(&self, f: impl FnOnce(&mut Allocator) -> R) -> Option<R> {
        match &self.allocator {
            AllocatorSlot::Own(own) => own.lock().unwrap_or_else(|e| e.into_inner()).as_mut().map(f),
            AllocatorSlot::Shared(shared) => Some(f(&mut shared.lock().unwrap_or_else(|e| e.into_inner()))),
        }
    }

    /// Bytes of device memory the allocator holds (every buffer, image and
    /// sparse block chunk the engine allocated, with the allocator's unused
    /// room in its memory blocks); `None` once the device is shutting down.
    /// With a host's shared allocator it includes the host's allocations.
    pub fn device_memory_bytes(&self) -> Option<u64> {
        self.with_allocator(|allocator| allocator.capacity())
    }

    /// The validation messages collected so far (always empty for a host's
    /// device: its messages go to the host's messenger).
    pub fn validation_log(&self) -> &Arc<ValidationLog> {
        &self.log
    }

    /// Waits until the device is idle.
    ///
    /// On a host's device ([`Device::from_host`]) this waits for the
    /// engine's queue only: `vkDeviceWaitIdle` would need every queue of the
    /// host's device synchronised, which the engine cannot do.
    pub fn wait_idle(&self) -> Result<()> {
        let queue = self.queue();
        if self.owns_device {
            // SAFETY: holding the queue lock, so no submission races this call;
            // the engine's device has no other queue.
            unsafe { self.raw.device_wait_idle() }.vk("vkDeviceWaitIdle")
        } else {
            // SAFETY: holding the lock of the queue the host shares with the engine.
            unsafe { self.raw.queue_wait_idle(*queue) }.vk("vkQueueWaitIdle")
        }
    }

    /// Gives a Vulkan object a debug name, so validation messages and
    /// captures say what it is. Does nothing without debug utils.
    pub fn set_name<H: vk::Handle>(&self, handle: H, name: &str) {
        let Some(debug) = &self.debug_utils else { return };
        let Ok(name) = std::ffi::CString::new(name.replace('\0', " ")) else {
            return;
        };
        let info = vk::DebugUtilsObjectNameInfoEXT::default()
            .object_handle(handle)
            .object_name(&name);
        // SAFETY: the handle belongs to this device; naming failures are harmless.
        let _ = unsafe { debug.set_debug_utils_object_name(&info) };
    }

    /// Memory type bits helper: first type index allowed by `bits` with `flags`.
    pub fn memory_type_index(&self, bits: u32, flags: vk::MemoryPropertyFlags) -> Option<u32> {
        // SAFETY: physical belongs to the instance.
        let props = unsafe { self.instance_fns.get_physical_device_memory_properties(self.physical) };
        (0..props.memory_type_count)
            .find(|&i| bits & (1 << i) != 0 && props.memory_types[i as usize].property_flags.contains(flags))
    }

    /// `maxMemoryAllocationSize`: the largest single allocation the device
    /// takes (Vulkan 1.1).
    pub fn max_memory_allocation_bytes(&self) -> u64 {
        let mut vk11 = vk::PhysicalDeviceVulkan11Properties::default();
        let mut properties = vk::PhysicalDeviceProperties2::default().push_next(&mut vk11);
        // SAFETY: physical belongs to the instance; the chain is well formed.
        unsafe {
            self.instance_fns
                .get_physical_device_properties2(self.physical, &mut properties)
        };
        vk11.max_memory_allocation_size
    }

    /// Bytes of the largest device-local memory heap.
    pub fn device_local_heap_bytes(&self) -> u64 {
        // SAFETY: physical belongs to the instance.
        let props = unsafe { self.instance_fns.get_physical_device_memory_properties(self.physical) };
        props.memory_heaps[..props.memory_heap_count as usize]
            .iter()
            .filter(|heap| heap.flags.contains(vk::MemoryHeapFlags::DEVICE_LOCAL))
            .map(|heap| heap.size)
            .max()
            .unwrap_or(0)
    }

    /// Format properties of `format` on this device.
    pub fn format_properties(&self, format: vk::Format) -> vk::FormatProperties {
        // SAFETY: physical belongs to the instance.
        unsafe {
            self.instance_fns
                .get_physical_device_format_properties(self.physical, format)
        }
    }
}

impl Device {
    /// Makes one deliberately invalid Vulkan call (a sampler whose
    /// anisotropy exceeds the device limit), so tests can prove that the
    /// validation layer is active and its errors reach [`ValidationLog`].
    /// Returns whether the call itself succeeded (drivers may accept it).
    #[doc(hidden)]
    pub fn provoke_validation_error(&self) -> bool {
        let limit = self.properties.limits.max_sampler_anisotropy;
        let info = vk::SamplerCreateInfo::default()
            .anisotropy_enable(true)
            .max_anisotropy(limit * 4.0 + 1.0);
        // SAFETY: the sampler is destroyed right away; an invalid parameter is
        // the point of the call and lavapipe tolerates it.
        unsafe {
            match self.raw.create_sampler(&info, None) {
                Ok(sampler) => {
                    self.raw.destroy_sampler(sampler, None);
                    true
                }
                Err(_) => false,
            }
        }
    }
}

fn chosen_feature_min_lod(instance: &ash::Instance, physical: vk::PhysicalDevice) -> bool {
    // SAFETY: physical belongs to the instance.
    let features = unsafe { instance.get_physical_device_features(physical) };
    features.shader_resource_min_lod == vk::TRUE
}

fn create_allocator(instance: &ash::Instance, device: &ash::Device, physical: vk::PhysicalDevice) -> Result<Allocator> {
    Allocator::new(&AllocatorCreateDesc {
        instance: instance.clone(),
        device: device.clone(),
        physical_device: physical,
        debug_settings: Default::default(),
        buffer_device_address: false,
        allocation_sizes: Default::default(),
    })
    .map_err(|source| EngineError::Allocation {
        name: "allocator".to_owned(),
        source,
    })
}

impl Drop for Device {
    fn drop(&mut self) {
        // Wait before destruction; errors (device lost) leave nothing better
        // to do than destroy anyway.
        let _ = self.wait_idle();
        // The allocator frees its memory blocks, so it must go before the device.
        if let AllocatorSlot::Own(own) = &self.allocator {
            own.lock().unwrap_or_else(|e| e.into_inner()).take();
        }
        if self.owns_device {
            // SAFETY: every resource holds an Arc<Device>, so none is left alive.
            unsafe { self.raw.destroy_device(None) };
        }
    }
}

/// The driver name string for reports (e.g. "llvmpipe").
pub fn describe(device: &Device) -> String {
    let p = device.properties();
    let api = p.api_version;
    let name: &CStr = p.device_name_as_c_str().unwrap_or(c"?");
    format!(
        "{} (Vulkan {}.{}.{})",
        name.to_string_lossy(),
        vk::api_version_major(api),
        vk::api_version_minor(api),
        vk::api_version_patch(api)
    )
}
