//! Device choice and the validation plumbing.

use anyhow::{ensure, Result};
use citystream_engine::instance::InstanceOptions;
use citystream_engine::{Device, DeviceOptions, EngineError};
use citystream_tests::{assert_no_validation_errors, validated_device};

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
