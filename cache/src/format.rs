//! Texel formats and the device's sparse-image facts the cache plans with.

use crate::error::ConfigError;

/// A texture format as the cache sees it: the size of one texel block and
/// its byte size. Uncompressed formats have 1×1 texel blocks; block
/// compressed formats (BC1, BC7, …) have 4×4.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct TexelFormat {
    /// Short name used in error messages and reports (e.g. `"BC1"`).
    pub name: &'static str,
    /// Texel-block width in texels (power of two).
    pub block_width: u32,
    /// Texel-block height in texels (power of two).
    pub block_height: u32,
    /// Bytes per texel block.
    pub bytes_per_block: u32,
}

impl TexelFormat {
    /// BC1 (DXT1): 4×4 texel blocks of 8 bytes.
    pub const BC1: TexelFormat = TexelFormat {
        name: "BC1",
        block_width: 4,
        block_height: 4,
        bytes_per_block: 8,
    };

    /// BC3 (DXT5): 4×4 texel blocks of 16 bytes.
    pub const BC3: TexelFormat = TexelFormat {
        name: "BC3",
        block_width: 4,
        block_height: 4,
        bytes_per_block: 16,
    };

    /// BC7: 4×4 texel blocks of 16 bytes.
    pub const BC7: TexelFormat = TexelFormat {
        name: "BC7",
        block_width: 4,
        block_height: 4,
        bytes_per_block: 16,
    };

    /// RGBA8 (any 8-bit four-channel format): one texel of 4 bytes.
    pub const RGBA8: TexelFormat = TexelFormat {
        name: "RGBA8",
        block_width: 1,
        block_height: 1,
        bytes_per_block: 4,
    };

    /// Whether texels are stored in multi-texel compressed blocks.
    pub fn is_block_compressed(&self) -> bool {
        self.block_width > 1 || self.block_height > 1
    }

    /// Bytes of a `width`×`height` texel image in this format (partial
    /// texel blocks at the edges count whole, as the copy commands need).
    pub fn image_bytes(&self, width: u32, height: u32) -> u64 {
        let blocks_x = u64::from(width.div_ceil(self.block_width));
        let blocks_y = u64::from(height.div_ceil(self.block_height));
        blocks_x * blocks_y * u64::from(self.bytes_per_block)
    }

    pub(crate) fn validate(&self) -> Result<(), ConfigError> {
        let ok = self.block_width.is_power_of_two() && self.block_height.is_power_of_two() && self.bytes_per_block > 0;
        if ok {
            Ok(())
        } else {
            Err(ConfigError::BadFormat {
                format: self.name,
                reason: format!(
                    "texel block {}x{} of {} bytes: dimensions must be powers of two and the size non-zero",
                    self.block_width, self.block_height, self.bytes_per_block
                ),
            })
        }
    }
}

/// Sparse-image granularity (the texel extent one sparse block covers in a
/// 2D mip level), always in **texels**.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Granularity {
    /// Block width in texels.
    pub width: u32,
    /// Block height in texels.
    pub height: u32,
}

impl Granularity {
    /// Granularity given directly in texels.
    pub fn texels(width: u32, height: u32) -> Self {
        Granularity { width, height }
    }

    /// Converts the device's raw report (`VkSparseImageFormatProperties::
    /// imageGranularity`) into texels. For block-compressed formats the
    /// device may report the granularity in compressed texel blocks (lavapipe
    /// reports BC1 as 128×64 blocks, i.e. 512×256 texels); `unit` says which
    /// unit the report uses ([`GranularityUnit::infer`] can decide it).
    /// Errors on a zero or non-power-of-two report or one that overflows.
    pub fn from_device_report(
        format: &TexelFormat,
        reported_width: u32,
        reported_height: u32,
        unit: GranularityUnit,
    ) -> Result<Self, ConfigError> {
        format.validate()?;
        let (scale_x, scale_y) = match unit {
            GranularityUnit::TexelBlocks => (format.block_width, format.block_height),
            GranularityUnit::Texels => (1, 1),
        };
        let bad = |reason: String| ConfigError::BadGranularity {
            format: format.name,
            reason,
        };
        if !reported_width.is_power_of_two() || !reported_height.is_power_of_two() {
            return Err(bad(format!(
                "device reported {reported_width}x{reported_height}; expected non-zero powers of two"
            )));
        }
        let width = reported_width
            .checked_mul(scale_x)
            .ok_or_else(|| bad(format!("{reported_width} blocks wide overflows u32 texels")))?;
        let height = reported_height
            .checked_mul(scale_y)
            .ok_or_else(|| bad(format!("{reported_height} blocks high overflows u32 texels")))?;
        let granularity = Granularity { width, height };
        granularity.validate(format)?;
        Ok(granularity)
    }

    pub(crate) fn validate(&self, format: &TexelFormat) -> Result<(), ConfigError> {
        let ok = self.width.is_power_of_two()
            && self.height.is_power_of_two()
            && self.width.is_multiple_of(format.block_width)
            && self.height.is_multiple_of(format.block_height);
        if ok {
            Ok(())
        } else {
            Err(ConfigError::BadGranularity {
                format: format.name,
                reason: format!(
                    "{}x{} texels: must be powers of two and whole {}x{} texel blocks",
                    self.width, self.height, format.block_width, format.block_height
                ),
            })
        }
    }
}

/// The unit of a device-reported sparse granularity.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum GranularityUnit {
    /// Texels.
    Texels,
    /// Texel blocks of the format (compressed blocks for BC formats).
    TexelBlocks,
}

impl GranularityUnit {
    /// Decides the unit of a raw report from the fact that a standard-shape
    /// sparse block holds exactly `sparse_block_bytes` bytes of texel data:
    /// the unit under which `width × height` texel blocks (or texels) of
    /// `format` fill one block. Uncompressed formats are always
    /// [`GranularityUnit::Texels`]. Returns `None` when neither unit fits
    /// (a non-standard block shape); the caller must then know the unit.
    pub fn infer(
        format: &TexelFormat,
        reported_width: u32,
        reported_height: u32,
        sparse_block_bytes: u64,
    ) -> Option<GranularityUnit> {
        if !format.is_block_compressed() {
            return Some(GranularityUnit::Texels);
        }
        let blocks = u64::from(reported_width) * u64::from(reported_height);
        let as_blocks = blocks * u64::from(format.bytes_per_block);
        let as_texels = format.image_bytes(reported_width, reported_height);
        if as_blocks == sparse_block_bytes {
            Some(GranularityUnit::TexelBlocks)
        } else if as_texels == sparse_block_bytes {
            Some(GranularityUnit::Texels)
        } else {
            None
        }
    }
}

/// Device facts the cache is bounded by. The engine fills them from the
/// physical device; tests use [`DeviceLimits::lavapipe_reference`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DeviceLimits {
    /// `VkPhysicalDeviceLimits::maxImageArrayLayers`.
    pub max_image_array_layers: u32,
    /// `VkPhysicalDeviceLimits::maxImageDimension2D`.
    pub max_image_dimension_2d: u32,
    /// Sparse block size in bytes (`VkMemoryRequirements::alignment` of the
    /// sparse image): the memory one bound block takes.
    pub sparse_block_bytes: u64,
}

impl DeviceLimits {
    /// The values measured on lavapipe (Mesa 25.0): 2048 layers, 16384
    /// texels, 64 KiB blocks. For tests and tools that plan without a device;
    /// the engine must read the real values.
    pub fn lavapipe_reference() -> Self {
        DeviceLimits {
            max_image_array_layers: 2048,
            max_image_dimension_2d: 16384,
            sparse_block_bytes: 64 * 1024,
        }
    }
}
