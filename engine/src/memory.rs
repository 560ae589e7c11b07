//! Device memory through gpu-allocator: one place that allocates and frees,
//! so every resource reports failures the same way.

use ash::vk;
use gpu_allocator::vulkan::{Allocation, AllocationCreateDesc, AllocationScheme};
use gpu_allocator::MemoryLocation;

use crate::device::Device;
use crate::error::{EngineError, Result};

/// Allocates memory for `requirements` at `location`; `linear` for buffers
/// and linear images, `false` for optimal-tiling images and sparse blocks.
pub(crate) fn allocate(
    device: &Device,
    name: &str,
    requirements: vk::MemoryRequirements,
    location: MemoryLocation,
    linear: bool,
) -> Result<Allocation> {
    device
        .with_allocator(|allocator| {
            allocator.allocate(&AllocationCreateDesc {
                name,
                requirements,
                location,
                linear,
                allocation_scheme: AllocationScheme::GpuAllocatorManaged,
            })
        })
        .ok_or_else(|| EngineError::InvalidRequest("device is shutting down".into()))?
        .map_err(|source| match source {
            gpu_allocator::AllocationError::OutOfMemory => EngineError::OutOfMemory {
                what: name.to_owned(),
                host: false,
            },
            source => EngineError::Allocation {
                name: name.to_owned(),
                source,
            },
        })
}

/// Returns an allocation; the caller guarantees the GPU no longer uses it.
pub(crate) fn free(device: &Device, allocation: Allocation) {
    // Freeing fails only for a foreign allocation, which cannot happen here.
    let _ = device.with_allocator(|allocator| allocator.free(allocation));
}
