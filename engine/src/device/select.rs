//! Which physical device the engine takes and what it needs of it: the
//! requirements per texture backing, the examination of each device's
//! features, queue families and sparse formats, and the choice among them.

use std::ffi::CStr;

use ash::vk;

use super::{DeviceCandidate, DeviceOptions, SparseMode, TextureBacking, MASK_FEATURES_ENV};
use crate::error::{EngineError, Result, VkResultExt};
use crate::instance::Instance;

/// What a host must enable on its device for the engine, per texture backing.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DeviceRequirements {
    /// Minimum Vulkan API version of instance and device.
    pub api_version: u32,
    /// Features every backing needs, by their Vulkan names (core 1.0, 1.2
    /// and 1.3 structs).
    pub features: Vec<&'static str>,
    /// Features the sparse backing needs as well (core 1.0).
    pub sparse_features: Vec<&'static str>,
    /// Device extensions beyond Vulkan 1.3 core (none today).
    pub extensions: Vec<&'static CStr>,
    /// Flags the engine's queue family must have with every backing.
    pub queue_flags: vk::QueueFlags,
    /// Flags it must have as well for the sparse backing: on the same
    /// family (a device that binds sparse only on a family of its own gets
    /// texture arrays).
    pub sparse_queue_flags: vk::QueueFlags,
    /// Formats the sparse backing needs sparse 2D images of
    /// (`vkGetPhysicalDeviceSparseImageFormatProperties` reports them,
    /// optimal tiling, sampled and copied into) with a standard block shape;
    /// mip tails, per layer or single, are bound by the engine.
    pub sparse_image_formats: Vec<vk::Format>,
}

impl DeviceRequirements {
    /// Every feature `backing` needs.
    pub fn features_for(&self, backing: TextureBacking) -> Vec<&'static str> {
        let mut features = self.features.clone();
        if backing == TextureBacking::Sparse {
            features.extend(&self.sparse_features);
        }
        features
    }

    /// The queue flags `backing` needs.
    pub fn queue_flags_for(&self, backing: TextureBacking) -> vk::QueueFlags {
        match backing {
            TextureBacking::Sparse => self.queue_flags | self.sparse_queue_flags,
            TextureBacking::Arrays => self.queue_flags,
        }
    }
}

/// The features, extensions and queue capabilities a host's device needs,
/// for each texture backing.
pub fn device_requirements() -> DeviceRequirements {
    DeviceRequirements {
        api_version: vk::API_VERSION_1_3,
        features: vec![
            "fragmentStoresAndAtomics",
            "textureCompressionBC",
            "samplerAnisotropy",
            "timelineSemaphore",
            "dynamicRendering",
            "synchronization2",
        ],
        sparse_features: vec!["sparseBinding", "sparseResidencyImage2D", "shaderResourceResidency"],
        extensions: Vec::new(),
        queue_flags: vk::QueueFlags::GRAPHICS | vk::QueueFlags::COMPUTE,
        sparse_queue_flags: vk::QueueFlags::SPARSE_BINDING,
        sparse_image_formats: crate::texture_cache::CACHE_FORMATS
            .iter()
            .map(|&(_, format, _)| format)
            .collect(),
    }
}

/// The feature structs of [`device_requirements`], ready to merge into a
/// host's own and chain into `VkDeviceCreateInfo`.
#[derive(Clone, Copy, Debug, Default)]
pub struct RequiredFeatures {
    /// Core 1.0 features.
    pub core: vk::PhysicalDeviceFeatures,
    /// Vulkan 1.2 features (its `p_next` is null).
    pub vulkan12: vk::PhysicalDeviceVulkan12Features<'static>,
    /// Vulkan 1.3 features (its `p_next` is null).
    pub vulkan13: vk::PhysicalDeviceVulkan13Features<'static>,
}

/// The features the engine needs with `backing`, as Vulkan structs.
pub fn required_features(backing: TextureBacking) -> RequiredFeatures {
    let sparse = backing == TextureBacking::Sparse;
    RequiredFeatures {
        core: vk::PhysicalDeviceFeatures::default()
            .sparse_binding(sparse)
            .sparse_residency_image2_d(sparse)
            .shader_resource_residency(sparse)
            .fragment_stores_and_atomics(true)
            .texture_compression_bc(true)
            .sampler_anisotropy(true),
        vulkan12: vk::PhysicalDeviceVulkan12Features::default().timeline_semaphore(true),
        vulkan13: vk::PhysicalDeviceVulkan13Features::default()
            .dynamic_rendering(true)
            .synchronization2(true),
    }
}

/// What `physical` lacks for the engine with `backing` (empty when usable),
/// and the first queue family with the flags it needs.
pub fn check_physical_device(
    instance: &ash::Instance,
    physical: vk::PhysicalDevice,
    backing: TextureBacking,
) -> (Vec<String>, Option<u32>) {
    let candidate = examine_raw(instance, physical, &[]);
    let (mut missing, family) = match backing {
        TextureBacking::Sparse => {
            let mut missing = candidate.missing;
            missing.extend(candidate.missing_sparse);
            (missing, candidate.sparse_queue_family)
        }
        TextureBacking::Arrays => (candidate.missing, candidate.queue_family),
    };
    // A malformed forced tail would otherwise pass here and be refused only when the
    // streamer builds its cache.
    if let Err(error) = crate::sparse::forced_mip_tail() {
        missing.push(error.to_string());
    }
    (missing, family)
}

fn rank(device_type: vk::PhysicalDeviceType) -> u32 {
    match device_type {
        vk::PhysicalDeviceType::DISCRETE_GPU => 0,
        vk::PhysicalDeviceType::INTEGRATED_GPU => 1,
        vk::PhysicalDeviceType::VIRTUAL_GPU => 2,
        vk::PhysicalDeviceType::CPU => 3,
        _ => 4,
    }
}

/// Lists every physical device with what it lacks for citystream.
pub fn list_devices(instance: &Instance) -> Result<Vec<DeviceCandidate>> {
    list_devices_masked(instance, &[])
}

/// As [`list_devices`], treating the features named in `masked` (Vulkan
/// names) as absent.
pub fn list_devices_masked(instance: &Instance, masked: &[String]) -> Result<Vec<DeviceCandidate>> {
    // SAFETY: plain enumeration on a live instance.
    let physicals = unsafe { instance.raw.enumerate_physical_devices() }.vk("vkEnumeratePhysicalDevices")?;
    Ok(physicals
        .into_iter()
        .map(|p| examine_raw(&instance.raw, p, masked))
        .collect())
}

/// The masked feature names of `options`, else of [`MASK_FEATURES_ENV`].
/// Refused where a name is not one of the features the engine checks (a typo
/// or a wrong case would otherwise mask nothing, silently).
pub(super) fn masked_features(options: &DeviceOptions) -> Result<Vec<String>> {
    let (masked, source) = if !options.masked_features.is_empty() {
        (options.masked_features.clone(), "DeviceOptions::masked_features")
    } else {
        let list = std::env::var(MASK_FEATURES_ENV).unwrap_or_default();
        let names = list
            .split(',')
            .map(str::trim)
            .filter(|name| !name.is_empty())
            .map(str::to_owned)
            .collect();
        (names, MASK_FEATURES_ENV)
    };
    let requirements = device_requirements();
    let known = requirements.features_for(TextureBacking::Sparse);
    if let Some(unknown) = masked.iter().find(|name| !known.contains(&name.as_str())) {
        return Err(EngineError::InvalidRequest(format!(
            "{source}: {unknown:?} is not a feature the engine checks; the names are Vulkan's, \
             case-sensitive: {}",
            known.join(", ")
        )));
    }
    Ok(masked)
}

pub(super) fn examine_raw(raw: &ash::Instance, physical: vk::PhysicalDevice, masked: &[String]) -> DeviceCandidate {
    // SAFETY: `physical` came from this instance.
    let properties = unsafe { raw.get_physical_device_properties(physical) };
    let name = properties
        .device_name_as_c_str()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|_| "<unnamed device>".to_owned());
    let mut vk13 = vk::PhysicalDeviceVulkan13Features::default();
    let mut vk12 = vk::PhysicalDeviceVulkan12Features::default();
    let mut features2 = vk::PhysicalDeviceFeatures2::default()
        .push_next(&mut vk12)
        .push_next(&mut vk13);
    // SAFETY: `physical` came from this instance; the chain is well formed.
    unsafe { raw.get_physical_device_features2(physical, &mut features2) };
    let features = features2.features;

    let mut missing = Vec::new();
    if properties.api_version < vk::API_VERSION_1_3 {
        missing.push(format!(
            "Vulkan 1.3 (it reports {}.{})",
            vk::api_version_major(properties.api_version),
            vk::api_version_minor(properties.api_version)
        ));
    }
    let reported = |name: &str, value: u32| value == vk::TRUE && !masked.iter().any(|m| m == name);
    let required: [(&str, u32); 6] = [
        ("fragmentStoresAndAtomics", features.fragment_stores_and_atomics),
        ("textureCompressionBC", features.texture_compression_bc),
        ("samplerAnisotropy", features.sampler_anisotropy),
        ("timelineSemaphore", vk12.timeline_semaphore),
        ("dynamicRendering", vk13.dynamic_rendering),
        ("synchronization2", vk13.synchronization2),
    ];
    missing.extend(
        required
            .iter()
            .filter(|(n, v)| !reported(n, *v))
            .map(|(n, _)| format!("feature {n}")),
    );
    let sparse: [(&str, u32); 3] = [
        ("sparseBinding", features.sparse_binding),
        ("sparseResidencyImage2D", features.sparse_residency_image2_d),
        ("shaderResourceResidency", features.shader_resource_residency),
    ];
    let mut missing_sparse: Vec<String> = sparse
        .iter()
        .filter(|(n, v)| !reported(n, *v))
        .map(|(n, _)| format!("feature {n}"))
        .collect();

    // SAFETY: `physical` came from this instance.
    let families = unsafe { raw.get_physical_device_queue_family_properties(physical) };
    let family_with = |wanted: vk::QueueFlags| {
        families
            .iter()
            .position(|f| f.queue_flags.contains(wanted) && f.queue_count > 0)
            .map(|i| i as u32)
    };
    let requirements = device_requirements();
    let queue_family = family_with(requirements.queue_flags_for(TextureBacking::Arrays));
    let sparse_queue_family = family_with(requirements.queue_flags_for(TextureBacking::Sparse));
    if queue_family.is_none() {
        missing.push("a queue family with GRAPHICS and COMPUTE".to_owned());
    }
    if sparse_queue_family.is_none() && missing_sparse.is_empty() {
        // A separate sparse-binding family (recent RADV) would need the binds
        // and the copies that wait on them on two queues; arrays run instead.
        let separate = families
            .iter()
            .any(|f| f.queue_flags.contains(vk::QueueFlags::SPARSE_BINDING) && f.queue_count > 0);
        missing_sparse.push(if separate {
            "SPARSE_BINDING on the GRAPHICS and COMPUTE queue family (the device binds on a family of its own)"
                .to_owned()
        } else {
            "a queue family with GRAPHICS, COMPUTE and SPARSE_BINDING".to_owned()
        });
    }
    if missing_sparse.is_empty() {
        missing_sparse.extend(unserved_sparse_formats(raw, physical));
    }
    DeviceCandidate {
        name,
        device_type: properties.device_type,
        missing,
        missing_sparse,
        physical,
        queue_family,
        sparse_queue_family,
    }
}

/// Why the sparse cache could not serve each cache format on `physical`, from
/// its sparse image format properties (and a forced tail from level 0,
/// [`crate::sparse::FORCE_MIP_TAIL_ENV`]): no sparse residency for the
/// format, or a non-standard block shape. Decided before the device is made,
/// so `SparseMode::Auto` picks texture arrays instead of refusing later.
fn unserved_sparse_formats(raw: &ash::Instance, physical: vk::PhysicalDevice) -> Vec<String> {
    let forced_from_zero = matches!(
        crate::sparse::forced_mip_tail(),
        Ok(Some(forced)) if forced.first_lod == 0
    );
    let mut unserved = Vec::new();
    for (_, format, _) in crate::texture_cache::CACHE_FORMATS {
        // SAFETY: `physical` came from this instance.
        let properties = unsafe {
            raw.get_physical_device_sparse_image_format_properties(
                physical,
                format,
                vk::ImageType::TYPE_2D,
                vk::SampleCountFlags::TYPE_1,
                vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_DST,
                vk::ImageTiling::OPTIMAL,
            )
        };
        let color = properties
            .iter()
            .find(|p| p.aspect_mask.contains(vk::ImageAspectFlags::COLOR));
        let metadata = properties
            .iter()
            .any(|p| p.aspect_mask.contains(vk::ImageAspectFlags::METADATA));
        let reason = match color {
            None => Some("no sparse residency for 2D images of it".to_owned()),
            Some(_) if metadata => Some("a metadata aspect to bind, which the cache does not bind".to_owned()),
            Some(p) if p.flags.contains(vk::SparseImageFormatFlags::NONSTANDARD_BLOCK_SIZE) => Some(format!(
                "a non-standard sparse block shape ({}x{})",
                p.image_granularity.width, p.image_granularity.height
            )),
            Some(_) if forced_from_zero => Some(format!(
                "a mip tail from level 0, forced by {}=0, leaves nothing to bind block by block",
                crate::sparse::FORCE_MIP_TAIL_ENV
            )),
            Some(_) => None,
        };
        if let Some(reason) = reason {
            unserved.push(format!("sparse images of {format:?} the cache can serve: {reason}"));
        }
    }
    unserved
}

/// Chooses a device and its texture backing under `mode`: by name when
/// asked, otherwise the best usable one (discrete before integrated before
/// CPU).
pub fn choose_device(
    candidates: &[DeviceCandidate],
    wanted: Option<&str>,
    mode: SparseMode,
) -> Result<(DeviceCandidate, TextureBacking)> {
    let describe = || {
        if candidates.is_empty() {
            "none".to_owned()
        } else {
            candidates
                .iter()
                .map(|c| format!("{:?}", c.name))
                .collect::<Vec<_>>()
                .join(", ")
        }
    };
    let chosen = match wanted {
        Some(wanted) => {
            let needle = wanted.to_lowercase();
            candidates
                .iter()
                .find(|c| c.name.to_lowercase().contains(&needle))
                .ok_or_else(|| EngineError::NoSuchDevice {
                    wanted: wanted.to_owned(),
                    available: describe(),
                })?
        }
        None => {
            let usable = candidates
                .iter()
                .filter(|c| c.backing(mode).is_ok())
                .min_by_key(|c| rank(c.device_type));
            match usable {
                Some(c) => c,
                None => {
                    let why = if candidates.is_empty() {
                        "the Vulkan loader found no device (is mesa-vulkan-drivers installed?)".to_owned()
                    } else {
                        candidates
                            .iter()
                            .map(|c| {
                                let mut lacks = c.missing.clone();
                                if mode == SparseMode::On {
                                    lacks.extend(c.missing_sparse.iter().cloned());
                                }
                                format!("{:?} lacks {}", c.name, lacks.join(", "))
                            })
                            .collect::<Vec<_>>()
                            .join("; ")
                    };
                    return Err(EngineError::NoUsableDevice(why));
                }
            }
        }
    };
    let backing = chosen.backing(mode).map_err(|feature| EngineError::MissingFeature {
        device: chosen.name.clone(),
        feature,
    })?;
    Ok((chosen.clone(), backing))
}
