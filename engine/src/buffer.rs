//! Buffers that own their memory.

use std::sync::Arc;

use ash::vk;
use gpu_allocator::vulkan::Allocation;
use gpu_allocator::MemoryLocation;

use crate::device::Device;
use crate::error::{EngineError, Result, VkResultExt};
use crate::memory;

/// How to create a [`Buffer`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct BufferDesc {
    /// Size in bytes (non-zero).
    pub size: u64,
    /// Usage flags.
    pub usage: vk::BufferUsageFlags,
    /// Where the memory lives: `GpuOnly`, `CpuToGpu` (uploads) or `GpuToCpu` (read-back).
    pub location: MemoryLocation,
}

/// A `VkBuffer` with its memory. Dropping it destroys both; the owner drops
/// it only after the GPU finished every submission that used it.
pub struct Buffer {
    device: Arc<Device>,
    raw: vk::Buffer,
    allocation: Option<Allocation>,
    desc: BufferDesc,
    name: String,
}

debug_fields!(Buffer { name, desc });

impl Buffer {
    /// A host-visible transfer source holding `bytes` (a one-off staging
    /// buffer).
    pub fn staged(device: &Arc<Device>, bytes: &[u8], name: &str) -> Result<Self> {
        let mut buffer = Self::new(
            device,
            BufferDesc {
                size: bytes.len() as u64,
                usage: vk::BufferUsageFlags::TRANSFER_SRC,
                location: MemoryLocation::CpuToGpu,
            },
            name,
        )?;
        buffer.write(0, bytes)?;
        Ok(buffer)
    }

    /// Creates a buffer and binds fresh memory to it.
    pub fn new(device: &Arc<Device>, desc: BufferDesc, name: &str) -> Result<Self> {
        if desc.size == 0 {
            return Err(EngineError::InvalidRequest(format!("buffer {name:?} has size 0")));
        }
        let info = vk::BufferCreateInfo::default()
            .size(desc.size)
            .usage(desc.usage)
            .sharing_mode(vk::SharingMode::EXCLUSIVE);
        // SAFETY: valid create info on a live device.
        let raw = unsafe { device.raw.create_buffer(&info, None) }.vk("vkCreateBuffer")?;
        // From here on `buffer` owns `raw`, so an early return destroys it.
        let mut buffer = Self {
            device: Arc::clone(device),
            raw,
            allocation: None,
            desc,
            name: name.to_owned(),
        };
        // SAFETY: raw is a live buffer of this device.
        let requirements = unsafe { device.raw.get_buffer_memory_requirements(raw) };
        let allocation = memory::allocate(device, name, requirements, desc.location, true)?;
        // SAFETY: the allocation satisfies the buffer's requirements.
        let bound = unsafe {
            device
                .raw
                .bind_buffer_memory(raw, allocation.memory(), allocation.offset())
        };
        buffer.allocation = Some(allocation);
        bound.vk("vkBindBufferMemory")?;
        device.set_name(raw, name);
        Ok(buffer)
    }

    /// The raw handle.
    pub fn raw(&self) -> vk::Buffer {
        self.raw
    }

    /// Size in bytes.
    pub fn size(&self) -> u64 {
        self.desc.size
    }

    /// The buffer's debug name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The host mapping, for host-visible buffers.
    pub fn mapped(&self) -> Option<&[u8]> {
        let slice = self.allocation.as_ref()?.mapped_slice()?;
        Some(&slice[..self.desc.size as usize])
    }

    /// The mutable host mapping, for host-visible buffers.
    pub fn mapped_mut(&mut self) -> Option<&mut [u8]> {
        let size = self.desc.size as usize;
        let slice = self.allocation.as_mut()?.mapped_slice_mut()?;
        Some(&mut slice[..size])
    }

    /// Copies `data` into the host-visible buffer at byte `offset`.
    pub fn write<T: bytemuck::Pod>(&mut self, offset: u64, data: &[T]) -> Result<()> {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        let name = self.name.clone();
        let mapped = self
            .mapped_mut()
            .ok_or_else(|| EngineError::InvalidRequest(format!("buffer {name:?} is not host visible")))?;
        let start = usize::try_from(offset).unwrap_or(usize::MAX);
        let end = start
            .checked_add(bytes.len())
            .filter(|&e| e <= mapped.len())
            .ok_or_else(|| {
                EngineError::InvalidRequest(format!(
                    "write of {} bytes at {offset} overruns buffer {name:?} of {} bytes",
                    bytes.len(),
                    mapped.len()
                ))
            })?;
        mapped[start..end].copy_from_slice(bytes);
        Ok(())
    }

    /// Reads `count` values of `T` from the host-visible buffer at byte `offset`.
    pub fn read<T: bytemuck::Pod>(&self, offset: u64, count: usize) -> Result<Vec<T>> {
        let mapped = self
            .mapped()
            .ok_or_else(|| EngineError::InvalidRequest(format!("buffer {:?} is not host visible", self.name)))?;
        let size = std::mem::size_of::<T>() * count;
        let start = usize::try_from(offset).unwrap_or(usize::MAX);
        let end = start.checked_add(size).filter(|&e| e <= mapped.len()).ok_or_else(|| {
            EngineError::InvalidRequest(format!(
                "read of {size} bytes at {offset} overruns buffer {:?} of {} bytes",
                self.name,
                mapped.len()
            ))
        })?;
        Ok(bytemuck::pod_collect_to_vec(&mapped[start..end]))
    }
}

impl Drop for Buffer {
    fn drop(&mut self) {
        // SAFETY: the owner guarantees the GPU no longer uses the buffer.
        unsafe { self.device.raw.destroy_buffer(self.raw, None) };
        if let Some(allocation) = self.allocation.take() {
            memory::free(&self.device, allocation);
        }
    }
}
