//! Feedback buffers and their compaction (paper §3.3).
//!
//! The fragment stage combines, per mesh, the finest needed mip level and a
//! summed weight into a sparse array with one [`MeshFeedback`] per mesh. The
//! compaction pass appends every mesh whose weight reaches τ to a dense array
//! through an atomic counter and resets the sparse array for the next frame.
//!
//! The dense array and its counter live in host-readable memory, one pair
//! per *read-back slot*: with frames in flight each frame compacts into its
//! own slot, and the host reads a slot once the frame that wrote it has
//! completed, with no copy and no wait. Host traffic scales with the visible
//! meshes, not with the scene.

use std::sync::Arc;

use ash::vk;
use gpu_allocator::MemoryLocation;

use crate::buffer::{Buffer, BufferDesc};
use crate::commands::{CommandContext, Recording};
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

/// One frame's compaction output: the dense entries and their counter, in
/// host-readable memory.
#[derive(Debug)]
struct ReadbackSlot {
    dense: Buffer,
    counter: Buffer,
    set: vk::DescriptorSet,
}

/// The per-mesh feedback array, the read-back slots, and the compaction pipeline.
#[derive(Debug)]
pub struct FeedbackCompactor {
    device: Arc<Device>,
    pipeline: Pipeline,
    _pool: DescriptorPool,
    sparse: Buffer,
    slots: Vec<ReadbackSlot>,
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
    /// entries per frame, with one read-back slot; the sparse array starts reset.
    pub fn new(device: &Arc<Device>, commands: &mut CommandContext, mesh_count: u32, capacity: u32) -> Result<Self> {
        Self::with_slots(device, commands, mesh_count, capacity, 1)
    }

    /// As [`new`](Self::new) with `slots` read-back slots (one per frame in flight).
    pub fn with_slots(
        device: &Arc<Device>,
        commands: &mut CommandContext,
        mesh_count: u32,
        capacity: u32,
        slots: u32,
    ) -> Result<Self> {
        if mesh_count == 0 || capacity == 0 || slots == 0 {
            return Err(EngineError::InvalidRequest(format!(
                "feedback for {mesh_count} meshes with room for {capacity} entries in {slots} slots: all must be positive"
            )));
        }
        let transfer = vk::BufferUsageFlags::TRANSFER_SRC | vk::BufferUsageFlags::TRANSFER_DST;
        let sparse = Buffer::new(
            device,
            BufferDesc {
                size: u64::from(mesh_count) * std::mem::size_of::<MeshFeedback>() as u64,
                usage: vk::BufferUsageFlags::STORAGE_BUFFER | transfer,
                location: MemoryLocation::GpuOnly,
            },
            "mesh feedback",
        )?;
        let host_readable = |size: u64, name: &str| {
            Buffer::new(
                device,
                BufferDesc {
                    size,
                    usage: vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::TRANSFER_DST,
                    location: MemoryLocation::GpuToCpu,
                },
                name,
            )
        };
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
        let pool = DescriptorPool::new(device, &pipeline, slots, "feedback compaction descriptors")?;
        let entry_size = std::mem::size_of::<FeedbackEntry>() as u64;
        let mut readback_slots = Vec::with_capacity(slots as usize);
        for slot in 0..slots {
            let dense = host_readable(
                u64::from(capacity) * entry_size,
                &format!("compacted feedback (slot {slot})"),
            )?;
            let counter = host_readable(
                std::mem::size_of::<FeedbackCounter>() as u64,
                &format!("feedback counter (slot {slot})"),
            )?;
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
            readback_slots.push(ReadbackSlot { dense, counter, set });
        }
        let compactor = Self {
            device: Arc::clone(device),
            pipeline,
            _pool: pool,
            sparse,
            slots: readback_slots,
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
                .cmd_fill_buffer(cmd.raw(), compactor.sparse.raw(), 0, vk::WHOLE_SIZE, 0)
        };
        compactor.record_compact(cmd, u32::MAX, 0)?;
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

    /// Read-back slots.
    pub fn slot_count(&self) -> u32 {
        self.slots.len() as u32
    }

    fn slot(&self, slot: u32) -> Result<&ReadbackSlot> {
        self.slots.get(slot as usize).ok_or_else(|| {
            EngineError::InvalidRequest(format!("feedback read-back slot {slot} of {} slots", self.slots.len()))
        })
    }

    /// Records: reset `slot`'s counter, compact with `tau` into `slot`
    /// (which also resets the per-mesh array for the next frame), and make
    /// the slot visible to the host. Must follow the fragment stage that
    /// wrote the array; the slot must not be read until this submission
    /// completed, nor recorded again while an earlier use is unread.
    pub fn record_compact(&self, rec: Recording<'_>, tau: u32, slot: u32) -> Result<()> {
        let cmd = rec.raw();
        let target = self.slot(slot)?;
        let raw = self.device.raw();
        // SAFETY: cmd is recording outside rendering; buffers are live.
        unsafe { raw.cmd_fill_buffer(cmd, target.counter.raw(), 0, vk::WHOLE_SIZE, 0) };
        memory_barrier(
            &self.device,
            rec,
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
        self.pipeline.bind(rec, target.set);
        self.pipeline.push(
            rec,
            &CompactPush {
                mesh_count: self.mesh_count,
                tau,
                capacity: self.capacity,
                pad0: 0,
            },
        );
        self.pipeline.dispatch_flat(rec, self.mesh_count, WORKGROUP);
        memory_barrier(
            &self.device,
            rec,
            (vk::PipelineStageFlags2::COMPUTE_SHADER, vk::AccessFlags2::SHADER_WRITE),
            (
                vk::PipelineStageFlags2::COPY
                    | vk::PipelineStageFlags2::FRAGMENT_SHADER
                    | vk::PipelineStageFlags2::HOST,
                vk::AccessFlags2::TRANSFER_READ
                    | vk::AccessFlags2::SHADER_READ
                    | vk::AccessFlags2::SHADER_WRITE
                    | vk::AccessFlags2::HOST_READ,
            ),
        );
        Ok(())
    }

    /// After the submission that compacted into `slot` completed: the entries.
    pub fn read_back(&self, slot: u32) -> Result<CompactedFeedback> {
        let target = self.slot(slot)?;
        let counter = target
            .counter
            .read::<FeedbackCounter>(0, 1)?
            .first()
            .copied()
            .unwrap_or_default();
        let kept = counter.count.min(self.capacity);
        Ok(CompactedFeedback {
            entries: target.dense.read::<FeedbackEntry>(0, kept as usize)?,
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
        unsafe { self.device.raw().cmd_copy_buffer(cmd.raw(), src, dst, &[region]) };
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
