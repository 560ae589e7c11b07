//! The engine's error type and the one place `vk::Result`s become errors.

use ash::vk;

/// Errors the engine reports to its callers.
#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    /// The Vulkan loader library (libvulkan.so.1) could not be loaded.
    #[error("cannot load the Vulkan loader (is libvulkan1 installed?): {0}")]
    Loader(String),
    /// A Vulkan call returned an error code.
    #[error("{call} failed: {result}")]
    Vulkan { call: &'static str, result: vk::Result },
    /// A layer the caller asked for is not installed.
    #[error("Vulkan layer {0} is not installed (Debian package vulkan-validationlayers)")]
    LayerMissing(String),
    /// An instance extension the caller asked for is not available.
    #[error(
        "the Vulkan loader offers no instance extension {0} (needed to show a window; is a display server running?)"
    )]
    ExtensionMissing(String),
    /// The user asked for a device by name and none matched.
    #[error("no Vulkan device matches {wanted:?}; devices present: {available}")]
    NoSuchDevice { wanted: String, available: String },
    /// The chosen device lacks something citystream needs.
    #[error("Vulkan device {device:?} lacks {feature}, which citystream needs")]
    MissingFeature { device: String, feature: String },
    /// No device at all is usable.
    #[error("no usable Vulkan device: {0}")]
    NoUsableDevice(String),
    /// gpu-allocator could not satisfy an allocation.
    #[error("GPU memory allocation for {name:?} failed: {source}")]
    Allocation {
        name: String,
        source: gpu_allocator::AllocationError,
    },
    /// The device was lost (driver reset, GPU fault): nothing on it can be used again.
    #[error("the Vulkan device was lost during {call}")]
    DeviceLost { call: &'static str },
    /// Device (or host) memory ran out.
    #[error("out of {} memory for {what}", if *host { "host" } else { "device" })]
    OutOfMemory { what: String, host: bool },
    /// A texture format the device or the cache cannot store.
    #[error("texture {texture}: format {format} is not supported: {reason}")]
    UnsupportedFormat {
        texture: u32,
        format: String,
        reason: String,
    },
    /// A request the engine cannot carry out as asked (bad size, range, format).
    #[error("{0}")]
    InvalidRequest(String),
    /// The load policy could not be built from its options.
    #[error("load policy: {0}")]
    Policy(#[from] citystream_streaming::controller::PolicyError),
    /// The bind log (`CITYSTREAM_BIND_LOG`) could not be written.
    #[error("cannot write the bind log {path}: {source}")]
    BindLog { path: String, source: std::io::Error },
    /// A shader module could not be read.
    #[error("shader {name}: {source}")]
    Shader { name: &'static str, source: std::io::Error },
}

/// The engine's result type.
pub type Result<T> = std::result::Result<T, EngineError>;

/// Turns a `VkResult` into an [`EngineError`] that names the call.
pub(crate) trait VkResultExt<T> {
    fn vk(self, call: &'static str) -> Result<T>;
}

impl<T> VkResultExt<T> for std::result::Result<T, vk::Result> {
    fn vk(self, call: &'static str) -> Result<T> {
        self.map_err(|result| match result {
            vk::Result::ERROR_DEVICE_LOST => EngineError::DeviceLost { call },
            vk::Result::ERROR_OUT_OF_DEVICE_MEMORY => EngineError::OutOfMemory {
                what: call.to_owned(),
                host: false,
            },
            vk::Result::ERROR_OUT_OF_HOST_MEMORY => EngineError::OutOfMemory {
                what: call.to_owned(),
                host: true,
            },
            result => EngineError::Vulkan { call, result },
        })
    }
}
