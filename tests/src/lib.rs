//! Shared helpers for the lavapipe integration tests: a device with the
//! validation layer forced on, a check that no validation error was
//! reported, and image comparison that writes actual/expected/difference
//! PNGs on failure.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use citystream_engine::instance::InstanceOptions;
use citystream_engine::{Device, DeviceOptions};

/// Creates a device with `VK_LAYER_KHRONOS_validation` on, whatever the build.
pub fn validated_device() -> Result<Arc<Device>> {
    let options = DeviceOptions {
        instance: InstanceOptions {
            validation: true,
            app_name: "citystream tests".to_owned(),
        },
        device_name: None,
    };
    Ok(Arc::new(Device::new(&options).context("creating a validated Vulkan device")?))
}

/// Fails when the validation layer reported any error on `device`.
pub fn assert_no_validation_errors(device: &Device) -> Result<()> {
    let errors = device.validation_log().errors();
    if !errors.is_empty() {
        let listing: Vec<String> = errors.iter().map(|e| format!("  {}: {}", e.id, e.text)).collect();
        bail!("{} validation error(s):\n{}", errors.len(), listing.join("\n"));
    }
    Ok(())
}

/// Outcome of comparing two images.
#[derive(Debug)]
pub struct Comparison {
    /// Pixels compared (not masked out).
    pub compared: usize,
    /// Compared pixels whose channels differ by more than the tolerance.
    pub mismatched: usize,
    /// Largest channel difference among compared pixels.
    pub max_difference: u8,
}

/// Compares `actual` with `expected` channel by channel, skipping pixels
/// where `mask` is false. On any mismatch beyond `tolerance`, writes
/// `NAME-actual.png`, `NAME-expected.png` and `NAME-difference.png` into
/// `out_dir` and returns an error naming them.
pub fn compare_images(
    actual: &image::RgbaImage,
    expected: &image::RgbaImage,
    mask: impl Fn(u32, u32) -> bool,
    tolerance: u8,
    out_dir: &Path,
    name: &str,
) -> Result<Comparison> {
    if actual.dimensions() != expected.dimensions() {
        bail!(
            "{name}: actual image is {:?}, expected {:?}",
            actual.dimensions(),
            expected.dimensions()
        );
    }
    let mut difference = image::RgbaImage::new(actual.width(), actual.height());
    let mut result = Comparison {
        compared: 0,
        mismatched: 0,
        max_difference: 0,
    };
    for (x, y, a) in actual.enumerate_pixels() {
        if !mask(x, y) {
            difference.put_pixel(x, y, image::Rgba([0, 0, 64, 255]));
            continue;
        }
        let e = expected.get_pixel(x, y);
        let worst = a.0.iter().zip(e.0.iter()).map(|(p, q)| p.abs_diff(*q)).max().unwrap_or(0);
        result.compared += 1;
        result.max_difference = result.max_difference.max(worst);
        if worst > tolerance {
            result.mismatched += 1;
            difference.put_pixel(x, y, image::Rgba([255, 0, 0, 255]));
        } else {
            difference.put_pixel(x, y, image::Rgba([worst.saturating_mul(16), worst.saturating_mul(16), worst.saturating_mul(16), 255]));
        }
    }
    if result.mismatched > 0 {
        std::fs::create_dir_all(out_dir)?;
        let paths: Vec<PathBuf> = ["actual", "expected", "difference"]
            .iter()
            .map(|kind| out_dir.join(format!("{name}-{kind}.png")))
            .collect();
        actual.save(&paths[0])?;
        expected.save(&paths[1])?;
        difference.save(&paths[2])?;
        bail!(
            "{name}: {} of {} pixels differ by more than {tolerance} (max {}); see {}",
            result.mismatched,
            result.compared,
            result.max_difference,
            paths.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(", ")
        );
    }
    Ok(result)
}
