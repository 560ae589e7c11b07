//! The Vulkan device a flythrough runs on: the one the options ask for, named on standard
//! error with what it means for the texture backing.

use std::sync::Arc;

use anyhow::Result;

use citystream_engine::device::{describe, TextureBacking};
use citystream_engine::instance::{default_synchronization_validation, default_validation, InstanceOptions};
use citystream_engine::{Device, DeviceOptions, EngineError};

use super::args::{Args, Sparse, Strategy};

/// The device the options ask for (`--device`, `--validation`, `CITYSTREAM_VALIDATION`),
/// named on standard error; with `window` (its surface extensions), able to present.
pub(crate) fn flythrough_device(
    args: &Args,
    app_name: &str,
    window: Option<Vec<std::ffi::CString>>,
) -> Result<Arc<Device>> {
    let presentation = window.is_some();
    let created = Device::new(&DeviceOptions {
        instance: InstanceOptions {
            validation: args.validation.unwrap_or_else(default_validation),
            synchronization: default_synchronization_validation(),
            app_name: app_name.into(),
            extensions: window.unwrap_or_default(),
        },
        device_name: args.device.clone(),
        presentation,
        sparse: args.sparse.mode(args.strategy),
        masked_features: Vec::new(),
    });
    let device = Arc::new(created.map_err(|error| {
        // What the setup script installs: the loader, lavapipe and the validation layers.
        // A device refused only for the sparse cache (--sparse on) is not a missing package.
        let installable = matches!(error, EngineError::Loader(_) | EngineError::LayerMissing(_))
            || (matches!(error, EngineError::NoUsableDevice(_)) && args.sparse != Sparse::On);
        let context = if installable {
            "creating the Vulkan device (`make setup` installs the Vulkan loader, lavapipe and the validation layers)"
        } else {
            "creating the Vulkan device"
        };
        anyhow::Error::new(error).context(context)
    })?);
    eprintln!("device: {}", describe(&device));
    let fell_back = args.sparse == Sparse::Auto
        && args.strategy != Strategy::TextureArrays
        && device.texture_backing() == TextureBacking::Arrays;
    if fell_back {
        eprintln!(
            "notice: {} lacks {}; textures stream into texture arrays (docs/STRATEGIES.md)",
            device.name(),
            device.sparse_fallback_reason().unwrap_or("sparse residency")
        );
    }
    if let Some(tail) = std::env::var_os(citystream_engine::sparse::FORCE_MIP_TAIL_ENV).filter(|tail| !tail.is_empty())
    {
        // Unless the forced tail is why sparse images were not taken, which the notice
        // above says.
        let tail_was_why = fell_back
            && device
                .sparse_fallback_reason()
                .is_some_and(|why| why.contains(citystream_engine::sparse::FORCE_MIP_TAIL_ENV));
        if device.texture_backing() == TextureBacking::Arrays && !tail_was_why {
            eprintln!(
                "notice: {}={}: texture arrays have no mip tail, so the forced one is unused (it applies to sparse images)",
                citystream_engine::sparse::FORCE_MIP_TAIL_ENV,
                tail.to_string_lossy()
            );
        }
    }
    if let Some(log) = std::env::var_os("CITYSTREAM_BIND_LOG").filter(|log| !log.is_empty()) {
        if device.texture_backing() == TextureBacking::Arrays {
            eprintln!(
                "notice: CITYSTREAM_BIND_LOG={}: texture arrays bind no sparse memory, so nothing is logged",
                log.to_string_lossy()
            );
        }
    }
    Ok(device)
}
