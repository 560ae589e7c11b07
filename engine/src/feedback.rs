//! Feedback buffers and their compaction (paper §3.3).
//!
//! The fragment stage combines, per mesh, the finest needed mip level and a
//! summed weight into a sparse array with one [`MeshFeedback`] per mesh. The
//! compaction pass appends every mesh whose weight reaches τ to a dense array
//! through an atomic counter and resets the sparse array for the next frame.
//! Read-back is two small copies: first the counter, then only as many dense
//! entries as it says, so host traffic scales with the visible meshes, not
//! with the scene.

use std::sync::Arc;

use ash::vk;
use gpu_allocator::MemoryLocation;

use crate::buffer::{Buffer, BufferDesc};
use crate::commands::CommandContext;
use crate::device::Device;
use crate::error::{EngineError, Result};
use crate::gpu_types::{
    CompactPush, FeedbackCounter, FeedbackEntry, MeshFeedback, BINDING_COMPACT_COUNTER, BINDING_COMPACT_DENSE,
    BINDING_COMPACT_SPARSE,
};
use crate::image::memory_barrier;
use crate::pipeline::{DescriptorPool, DescriptorResource, Pipeline};
use crate::shaders;

const WORKGROUP: u32 = 256;
const MAX_GROUPS_X: u32 = 65_535;

/// The per-mesh feedback array, the dense output, and the compaction pipeline.
#[derive(Debug)]
pub struct FeedbackCompactor {
    device: Arc<Device>,
    pipeline: Pipeline,
    _pool: DescriptorPool,
    set: vk::DescriptorSet,
    sparse: Buffer,
    dense: Buffer,
    counter: Buffer,
    counter_readback: Buffer,
    entries_readback: Buffer,
    mesh_count: u32,
    capacity: u32,
}

/// What one compaction produced.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct CompactedFeedback {
    /// The entries, in the (unspecified) order the GPU appended them.
    pub entries: Vec<FeedbackEntry>,
    /// Entries that passed τ but did not fit the dense array.
    pub dropped: u32,
}

impl FeedbackCompactor {
    /// Buffers for `mesh_count` meshes and at most `capacity` compacted
    /// entries per frame; the sparse array starts reset.
    pub fn new(device: &Arc<Device>, commands: &mut CommandContext, mesh_count: u32, capacity: u32) -> Result<Self> {
        if mesh_count == 0 || capacity == 0 {
            return Err(EngineError::InvalidRequest(format!(
                "feedback for {mesh_count} meshes with room for {capacity} entries: both must be positive"
            )));
        }
        let storage = |size: u64, extra: vk::BufferUsageFlags, name: &str| {
            Buffer::new(
                device,
                BufferDesc {
                    size,
                    usage: vk::BufferUsageFlags::STORAGE_BUFFER | extra,
                    location: MemoryLocation::GpuOnly,
                },
                name,
            )
        };
        let transfer = vk::BufferUsageFlags::TRANSFER_SRC | vk::BufferUsageFlags::TRANSFER_DST;
        let entry_size = std::mem::size_of::<FeedbackEntry>() as u64;
        let sparse = storage(
            u64::from(mesh_count) * std::mem::size_of::<MeshFeedback>() as u64,
            transfer,
            "mesh feedback",
        )?;
        let dense = storage(u64::from(capacity) * entry_size, transfer, "compacted feedback")?;
        let counter = storage(
            std::mem::size_of::<FeedbackCounter>() as u64,
            transfer,
            "feedback counter",
        )?;
        let readback = |size: u64, name: &str| {
            Buffer::new(
                device,
                BufferDesc {
                    size,
                    usage: vk::BufferUsageFlags::TRANSFER_DST,
                    location: MemoryLocation::GpuToCpu,
                },
                name,
            )
        };
        let counter_readback = readback(
            std::mem::size_of::<FeedbackCounter>() as u64,
            "feedback counter read-back",
        )?;
        let entries_readback = readback(u64::from(capacity) * entry_size, "compacted feedback read-back")?;
        let stages = vk::ShaderStageFlags::COMPUTE;
        let pipeline = Pipeline::compute(
            device,
            &shaders::FEEDBACK_COMPACT_COMP,
            &[
                (BINDING_COMPACT_SPARSE, vk::DescriptorType::STORAGE_BUFFER, 1, stages),
                (BINDING_COMPACT_DENSE, vk::DescriptorType::STORAGE_BUFFER, 1, stages),
                (BINDING_COMPACT_COUNTER, vk::DescriptorType::STORAGE_BUFFER, 1, stages),
            ],
            std::mem::size_of::<CompactPush>() as u32,
            "feedback compaction",
        )?;
        let pool = DescriptorPool::new(device, &pipeline, 1, "feedback compaction descriptors")?;
        let set = pool.allocate(
            &pipeline,
            &[
                (BINDING_COMPACT_SPARSE, DescriptorResource::StorageBuffer(sparse.raw())),
                (BINDING_COMPACT_DENSE, DescriptorResource::StorageBuffer(dense.raw())),
                (
                    BINDING_COMPACT_COUNTER,
                    DescriptorResource::StorageBuffer(counter.raw()),
                ),
            ],
        )?;
        let compactor = Self {
            device: Arc::clone(device),
            pipeline,
            _pool: pool,
            set,
            sparse,
            dense,
            counter,
            counter_readback,
            entries_readback,
            mesh_count,
            capacity,
        };
        // Zero the array, then run the compaction with a τ nothing reaches:
        // it appends nothing and leaves every mesh reset to (unseen, 0).
        let cmd = commands.begin()?;
        // SAFETY: cmd is recording; the buffer is live and allows transfers.
        unsafe {
            device
                .raw()
                .cmd_fill_buffer(cmd, compactor.sparse.raw(), 0, vk::WHOLE_SIZE, 0)
        };
        compactor.record_compact(cmd, u32::MAX, false);
        commands.submit_and_wait(&[])?;
        Ok(compactor)
    }

    /// The per-mesh array the fragment stage writes.
    pub fn mesh_feedback_buffer(&self) -> vk::Buffer {
        self.sparse.raw()
    }

    /// Meshes the array covers.
    pub fn mesh_count(&self) -> u32 {
        self.mesh_count
    }

    /// Records: reset the counter, compact with `tau` (which also resets
    /// the per-mesh array for the next frame), and, when `read_back` is set,
    /// copy the counter to the host for [`read_back`](Self::read_back). The
    /// engine sets it only when no streaming task runs (Algorithm 1), so
    /// nothing crosses to the host otherwise. Must follow the fragment stage
    /// that wrote the array.
    pub fn record_compact(&self, cmd: vk::CommandBuffer, tau: u32, read_back: bool) {
        let raw = self.device.raw();
        // SAFETY: cmd is recording outside rendering; buffers are live.
        unsafe { raw.cmd_fill_buffer(cmd, self.counter.raw(), 0, vk::WHOLE_SIZE, 0) };
        memory_barrier(
            &self.device,
            cmd,
            (
                vk::PipelineStageFlags2::FRAGMENT_SHADER
                    | vk::PipelineStageFlags2::CLEAR
                    | vk::PipelineStageFlags2::COPY,
                vk::AccessFlags2::SHADER_WRITE | vk::AccessFlags2::TRANSFER_WRITE,
            ),
            (
                vk::PipelineStageFlags2::COMPUTE_SHADER,
                vk::AccessFlags2::SHADER_READ | vk::AccessFlags2::SHADER_WRITE,
            ),
        );
        self.pipeline.bind(cmd, self.set);
        self.pipeline.push(
            cmd,
            &CompactPush {
                mesh_count: self.mesh_count,
                tau,
                capacity: self.capacity,
                pad0: 0,
            },
        );
        let groups = self.mesh_count.div_ceil(WORKGROUP);
        let (x, y) = if groups <= MAX_GROUPS_X {
            (groups, 1)
        } else {
            (MAX_GROUPS_X, groups.div_ceil(MAX_GROUPS_X))
        };
        // SAFETY: pipeline and set are bound; the shader bounds-checks the index.
        unsafe { raw.cmd_dispatch(cmd, x, y, 1) };
        memory_barrier(
            &self.device,
            cmd,
            (vk::PipelineStageFlags2::COMPUTE_SHADER, vk::AccessFlags2::SHADER_WRITE),
            (
                vk::PipelineStageFlags2::COPY | vk::PipelineStageFlags2::FRAGMENT_SHADER,
                vk::AccessFlags2::TRANSFER_READ | vk::AccessFlags2::SHADER_READ | vk::AccessFlags2::SHADER_WRITE,
            ),
        );
        if !read_back {
            return;
        }
        let region = vk::BufferCopy {
            src_offset: 0,
            dst_offset: 0,
            size: std::mem::size_of::<FeedbackCounter>() as u64,
        };
        // SAFETY: both buffers hold a FeedbackCounter.
        unsafe { raw.cmd_copy_buffer(cmd, self.counter.raw(), self.counter_readback.raw(), &[region]) };
        memory_barrier(
            &self.device,
            cmd,
            (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE),
            (vk::PipelineStageFlags2::HOST, vk::AccessFlags2::HOST_READ),
        );
    }

    /// After the submission with [`record_compact`](Self::record_compact)
    /// completed: reads the counter, copies only that many entries, returns them.
    pub fn read_back(&self, commands: &mut CommandContext) -> Result<CompactedFeedback> {
        let counter = self
            .counter_readback
            .read::<FeedbackCounter>(0, 1)?
            .first()
            .copied()
            .unwrap_or_default();
        let kept = counter.count.min(self.capacity);
        if kept == 0 {
            return Ok(CompactedFeedback {
                entries: Vec::new(),
                dropped: counter.dropped,
            });
        }
        let bytes = u64::from(kept) * std::mem::size_of::<FeedbackEntry>() as u64;
        let cmd = commands.begin()?;
        let region = vk::BufferCopy {
            src_offset: 0,
            dst_offset: 0,
            size: bytes,
        };
        // SAFETY: `kept` entries fit both buffers.
        unsafe {
            self.device
                .raw()
                .cmd_copy_buffer(cmd, self.dense.raw(), self.entries_readback.raw(), &[region])
        };
        memory_barrier(
            &self.device,
            cmd,
            (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE),
            (vk::PipelineStageFlags2::HOST, vk::AccessFlags2::HOST_READ),
        );
        commands.submit_and_wait(&[])?;
        Ok(CompactedFeedback {
            entries: self.entries_readback.read::<FeedbackEntry>(0, kept as usize)?,
            dropped: counter.dropped,
        })
    }

    /// Overwrites the per-mesh array from the host (tests and replays).
    pub fn upload_mesh_feedback(&self, commands: &mut CommandContext, values: &[MeshFeedback]) -> Result<()> {
        self.transfer_mesh_feedback(commands, Some(values)).map(|_| ())
    }

    /// Reads the per-mesh array back (tests and diagnostics).
    pub fn download_mesh_feedback(&self, commands: &mut CommandContext) -> Result<Vec<MeshFeedback>> {
        self.transfer_mesh_feedback(commands, None)
    }

    fn transfer_mesh_feedback(
        &self,
        commands: &mut CommandContext,
        upload: Option<&[MeshFeedback]>,
    ) -> Result<Vec<MeshFeedback>> {
        if upload.is_some_and(|v| v.len() != self.mesh_count as usize) {
            return Err(EngineError::InvalidRequest(format!(
                "feedback upload of {} meshes into an array of {}",
                upload.map_or(0, <[_]>::len),
                self.mesh_count
            )));
        }
        let size = self.sparse.size();
        let mut staging = Buffer::new(
            &self.device,
            BufferDesc {
                size,
                usage: vk::BufferUsageFlags::TRANSFER_SRC | vk::BufferUsageFlags::TRANSFER_DST,
                location: if upload.is_some() {
                    MemoryLocation::CpuToGpu
                } else {
                    MemoryLocation::GpuToCpu
                },
            },
            "mesh feedback staging",
        )?;
        if let Some(values) = upload {
            staging.write(0, values)?;
        }
        let (src, dst) = if upload.is_some() {
            (staging.raw(), self.sparse.raw())
        } else {
            (self.sparse.raw(), staging.raw())
        };
        let cmd = commands.begin()?;
        memory_barrier(
            &self.device,
            cmd,
            (vk::PipelineStageFlags2::ALL_COMMANDS, vk::AccessFlags2::MEMORY_WRITE),
            (
                vk::PipelineStageFlags2::COPY,
                vk::AccessFlags2::TRANSFER_READ | vk::AccessFlags2::TRANSFER_WRITE,
            ),
        );
        let region = vk::BufferCopy {
            src_offset: 0,
            dst_offset: 0,
            size,
        };
        // SAFETY: both buffers are `size` bytes.
        unsafe { self.device.raw().cmd_copy_buffer(cmd, src, dst, &[region]) };
        memory_barrier(
            &self.device,
            cmd,
            (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE),
            (
                vk::PipelineStageFlags2::HOST | vk::PipelineStageFlags2::COMPUTE_SHADER,
                vk::AccessFlags2::HOST_READ | vk::AccessFlags2::SHADER_READ,
            ),
        );
        commands.submit_and_wait(&[])?;
        if upload.is_some() {
            Ok(Vec::new())
        } else {
            staging.read::<MeshFeedback>(0, self.mesh_count as usize)
        }
    }
}
