//! Device choice and the validation plumbing.

use std::sync::Arc;

use anyhow::{ensure, Result};
use ash::vk;
use citystream_dataset::TextureFormat;
use citystream_engine::commands::CommandContext;
use citystream_engine::device::{SparseMode, TextureBacking};
use citystream_engine::instance::InstanceOptions;
use citystream_engine::sparse::{SparseImage, SparseImageDesc};
use citystream_engine::texture_cache::GpuTextureCache;
use citystream_engine::{Device, DeviceOptions, EngineError};
use citystream_tests::{assert_no_validation_errors, test_cache_config, validated_device};

/// Options for a validated device picked by (part of) its name.
fn named_device_options(name: &str) -> DeviceOptions {
    DeviceOptions {
        instance: InstanceOptions {
            validation: true,
            synchronization: false,
            app_name: "device name test".into(),
            extensions: Vec::new(),
        },
        device_name: Some(name.into()),
        presentation: false,
        ..Default::default()
    }
}

#[test]
fn unknown_device_name_lists_the_devices_present() -> Result<()> {
    let options = named_device_options("no such gpu 9000");
    let error = Device::new(&options).expect_err("a device name nobody has must fail");
    let EngineError::NoSuchDevice { wanted, available } = &error else {
        anyhow::bail!("expected NoSuchDevice, got {error}");
    };
    ensure!(wanted == "no such gpu 9000");
    let message = error.to_string();
    ensure!(
        message.contains("no such gpu 9000"),
        "message does not name the request: {message}"
    );
    // The message names the devices that do exist (lavapipe here).
    let real = validated_device()?;
    ensure!(
        available.contains(real.name()),
        "message {message:?} does not list the present device {:?}",
        real.name()
    );
    Ok(())
}

#[test]
fn device_is_picked_by_part_of_its_name() -> Result<()> {
    let any = validated_device()?;
    let fragment: String = any.name().chars().take(4).collect::<String>().to_uppercase();
    let options = named_device_options(&fragment);
    let picked = Device::new(&options)?;
    ensure!(
        picked.name().to_uppercase().contains(&fragment),
        "asked for {fragment:?}, got {:?}",
        picked.name()
    );
    let sparse = picked.sparse_support();
    ensure!(sparse.address_space_size > 0, "device reports no sparse address space");
    assert_no_validation_errors(&picked)
}

#[test]
fn validation_errors_are_collected_and_fail_the_check() -> Result<()> {
    let device = validated_device()?;
    assert_no_validation_errors(&device)?;
    device.provoke_validation_error();
    ensure!(
        device.validation_log().error_count() > 0,
        "an invalid sampler produced no validation error: is the layer active?"
    );
    ensure!(
        assert_no_validation_errors(&device).is_err(),
        "the check must fail once an error was logged"
    );
    Ok(())
}

/// A device whose reported features lack sparse residency (masked, as on MoltenVK or
/// most mobile GPUs) is set up for the texture-array cache by itself, and so is one asked
/// for `SparseMode::Off` (`--sparse off`): no sparse feature is enabled on it (the
/// validation layer refuses a sparse image there), and the texture cache made on it holds
/// fully bound arrays. Asking for sparse on the masked device is refused, naming the
/// missing feature.
#[test]
fn a_device_lacking_sparse_residency_is_set_up_for_texture_arrays() -> Result<()> {
    let masked = DeviceOptions {
        masked_features: vec!["sparseResidencyImage2D".into()],
        ..named_device_options("")
    };
    let off = DeviceOptions {
        sparse: SparseMode::Off,
        ..named_device_options("")
    };
    for options in [&masked, &off] {
        arrays_device_enables_no_sparse_feature(options)?;
    }
    let on = DeviceOptions {
        sparse: SparseMode::On,
        ..masked
    };
    let error = Device::new(&on).expect_err("sparse on a device without it must fail");
    ensure!(
        matches!(&error, EngineError::MissingFeature { feature, .. } | EngineError::NoUsableDevice(feature)
            if feature.contains("sparseResidencyImage2D")),
        "{error}"
    );
    Ok(())
}

/// The device `options` give is set up for texture arrays with no sparse feature enabled.
fn arrays_device_enables_no_sparse_feature(options: &DeviceOptions) -> Result<()> {
    let device = Arc::new(Device::new(options)?);
    ensure!(device.texture_backing() == TextureBacking::Arrays);
    let enabled = device.enabled_features();
    ensure!(
        enabled.sparse_binding == vk::FALSE
            && enabled.sparse_residency_image2_d == vk::FALSE
            && enabled.shader_resource_residency == vk::FALSE,
        "sparse features enabled: {enabled:?}"
    );
    let mut commands = CommandContext::new(&device, "texture-array device test")?;
    let config = test_cache_config(&[TextureFormat::Bc1], 16);
    let colormap = vec![[0, 0, 0, 255]; config.texture_count as usize];
    let cache = GpuTextureCache::new(&device, &mut commands, &config, &colormap)?;
    ensure!(cache.backing() == TextureBacking::Arrays);
    ensure!(cache.texel_memory_bytes() > 0 && cache.texel_memory_bytes() <= config.memory_budget_bytes);
    drop(cache);
    assert_no_validation_errors(&device)?;

    // The sparse features are really off: a sparse image is what validation refuses.
    let sparse = SparseImage::new(
        &device,
        SparseImageDesc {
            width: 256,
            height: 256,
            layers: 1,
            mips: 1,
            format: vk::Format::R8G8B8A8_UNORM,
        },
        "sparse image on a texture-array device",
    );
    drop(sparse);
    let errors = device.validation_log().errors();
    ensure!(
        errors
            .iter()
            .any(|e| e.text.contains("sparseBinding") || e.text.contains("sparseResidency")),
        "no validation error for a sparse image without the sparse features: {errors:?}"
    );
    Ok(())
}
