//! GPU culling of the city passes: a frame costs what the view shows, not what the city holds.
//!
//! Each view (the feedback view and the visible view) keeps per-mesh flags and a depth
//! pyramid, and draws in two phases (`shaders/city_cull.comp`):
//!
//! 1. **Early**: the meshes in the frustum that passed the occlusion test last frame are
//!    drawn; the depth they leave is copied and reduced to a pyramid of farthest depths.
//! 2. **Late**: every mesh in the frustum is tested against the pyramid; those in front of
//!    it and not drawn early are drawn now. The test's result is next frame's early set.
//!
//! The depth after the late phase is the depth of the unculled draw: a mesh is skipped
//! only when its bounds lie outside the frustum or behind depth already drawn, so it could
//! not have contributed a fragment. The feedback pass, which tests for equal depth after
//! the pre-pass, draws every mesh that passed the late test, and so reports what the
//! unculled pass reports.
//!
//! A list is drawn with one indexed draw of its own index buffer: the indices of its
//! meshes, copied in mesh order, so the culled pass rasterises in the unculled order.
//! (Drawing runs of consecutive meshes straight from the city's index buffer, one
//! indirect draw each, was measured first: on `large` the visible pass then took as long
//! for its 16,700 meshes in 2,005 draws as for all 105,570 in one, lavapipe paying each
//! draw's setup; drawing the culled meshes in short gaps with the listed ones to save
//! draws made the passes 23 % and the culling 3x slower.) A list holds a quarter of the
//! city's indices (at least 2^18, at most 2^24); one that does not fit draws every mesh
//! from the city's index buffer instead (a second draw, empty otherwise), so nothing is
//! ever missing. No multi-draw or draw-count feature is needed. Per-mesh work runs one
//! invocation per chunk of 64 meshes, the chunk's box tested first and chunks outside the
//! frustum skipped by every later phase, without workgroup barriers (which a CPU
//! rasteriser runs as coroutine switches).

use std::sync::{Arc, Mutex};

use ash::vk;
use glam::Mat4;
use gpu_allocator::MemoryLocation;

use crate::buffer::{Buffer, BufferDesc};
use crate::commands::{CommandContext, Recording};
use crate::device::Device;
use crate::error::{EngineError, Result};
use crate::gpu_types::{
    CullCounter, CullPush, MeshBounds, BINDING_CULL_BOUNDS, BINDING_CULL_CHUNK_BOUNDS, BINDING_CULL_CHUNK_FLAGS,
    BINDING_CULL_CITY_INDICES, BINDING_CULL_COUNTER, BINDING_CULL_DRAWS, BINDING_CULL_FLAGS, BINDING_CULL_GROUPS,
    BINDING_CULL_INDICES, BINDING_CULL_PYRAMID, BINDING_CULL_RANGES, CULL_PHASE_COUNT, CULL_PHASE_EMIT,
    CULL_PHASE_FRUSTUM, CULL_PHASE_OCCLUSION, CULL_PHASE_PYRAMID, CULL_PHASE_SCAN, CULL_WINDOWS,
};
use crate::image::memory_barrier;
use crate::pipeline::{DescriptorPool, DescriptorResource, Pipeline};
use crate::scene::upload_buffer;
use crate::shaders;
use crate::target::RenderTarget;
use crate::timing::GpuTimer;
pub use inputs::WINDOW_BYTES_ENV;
pub(crate) use inputs::{chunk_bounds, mesh_bounds, CullList, StorageWindows};

mod inputs;

const WORKGROUP: u32 = 256;
/// Meshes per invocation of the count and emit phases (`CULL_CHUNK`).
pub(crate) const CULL_CHUNK: u32 = 64;
/// Bytes of one `VkDrawIndexedIndirectCommand`.
const DRAW_STRIDE: u64 = 20;
/// Smallest index capacity of a list (or the whole city, if smaller).
const MIN_LIST_INDICES: u64 = 1 << 18;
/// Largest index capacity of a list: 64 MB of indices.
const MAX_LIST_INDICES: u64 = 1 << 24;

/// What the culling writes, the source of its barriers: shader stores, fills (copies to
/// the validation layer, clears to the spec) and copies.
const CULL_WRITES: (vk::PipelineStageFlags2, vk::AccessFlags2) = (
    vk::PipelineStageFlags2::from_raw(
        vk::PipelineStageFlags2::COMPUTE_SHADER.as_raw()
            | vk::PipelineStageFlags2::CLEAR.as_raw()
            | vk::PipelineStageFlags2::COPY.as_raw(),
    ),
    vk::AccessFlags2::from_raw(vk::AccessFlags2::SHADER_WRITE.as_raw() | vk::AccessFlags2::TRANSFER_WRITE.as_raw()),
);

/// The two views a frame culls for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CullView {
    /// The feedback pass's wider view (depth pre-pass and feedback).
    Feedback = 0,
    /// The visible pass's view.
    Visible = 1,
}

/// What one frame's culling drew, read back once its submission completed.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CullStats {
    /// Meshes the visible pass drew (early and late phases; every mesh where a list
    /// overflowed its buffer).
    pub meshes_drawn: u32,
    /// Meshes of the city the visible pass did not draw.
    pub meshes_culled: u32,
    /// Meshes that passed the visible view's tests (in the frustum, not behind the early
    /// phase's depth).
    pub meshes_passed: u32,
    /// Meshes the feedback pass drew (after the pre-pass).
    pub feedback_meshes_drawn: u32,
    /// Whether a list of the visible pass held more indices than its buffer, so that the
    /// pass drew every mesh instead.
    pub overflowed: bool,
    /// GPU milliseconds of the culling work (tests, compaction, depth copies and
    /// pyramids) for the feedback view and for the visible view, when the queue has
    /// timestamps; part of the passes that record them.
    pub cull_ms: Option<[f64; 2]>,
}

struct ListBuffers {
    groups: Buffer,
    /// The list's meshes' indices, in mesh order.
    indices: Buffer,
    draws: Buffer,
    counter: Buffer,
    set: vk::DescriptorSet,
}

/// A view's depth pyramid, resized with its depth target.
struct Pyramid {
    buffer: Buffer,
    /// Depth target width and height and pyramid levels it was made for.
    shape: (u32, u32, u32),
}

struct ViewBuffers {
    flags: Buffer,
    /// Per chunk: whether its box meets the frustum this frame.
    chunk_flags: Buffer,
    pyramid: Mutex<Pyramid>,
    lists: Vec<ListBuffers>,
}

/// Which slot's statistics and timestamps the next recordings write, and what each
/// slot's last frame wrote (a pass not recorded, such as the feedback view of a strategy
/// without feedback, has no timestamps or statistics to read).
#[derive(Debug, Default)]
struct SlotRecords {
    slot: u32,
    /// Per slot: bit `view * 2 + segment` for timestamps, bit `4 + view` for statistics.
    written: Vec<u8>,
}

/// GPU culling state of a [`crate::city::CityRenderer`]: mesh bounds and index ranges,
/// and per view its flags, depth pyramid and three compacted lists.
pub(crate) struct CityCulling {
    device: Arc<Device>,
    pipeline: Pipeline,
    pool: DescriptorPool,
    bounds: Buffer,
    /// One box per chunk of [`CULL_CHUNK`] meshes: the union of theirs.
    chunk_bounds: Buffer,
    ranges: Buffer,
    views: Vec<ViewBuffers>,
    mesh_count: u32,
    /// Chunks of [`CULL_CHUNK`] meshes.
    group_count: u32,
    /// Indices each list's buffer holds.
    capacity: u32,
    /// The city's index buffer (read by the emit phase, drawn on overflow) and its length.
    city_indices: (vk::Buffer, u32),
    /// How the shader views the bounds and the city's indices: windows of a size a
    /// storage binding may address.
    bounds_windows: StorageWindows,
    index_windows: StorageWindows,
    /// Per slot: the six lists' counters, copied for the host.
    readback: Vec<Buffer>,
    /// Per slot, two timed segments per view.
    timer: GpuTimer,
    recording: Mutex<SlotRecords>,
}

debug_fields!(CityCulling { mesh_count, capacity });

impl CityCulling {
    /// Culling for `bounds.len()` meshes whose indices lie at `ranges` (first, count) in
    /// `city_indices` (the city's index buffer, with storage-buffer usage, and its index
    /// count), with `slots` read-back slots (frames in flight).
    pub(crate) fn new(
        device: &Arc<Device>,
        commands: &mut CommandContext,
        bounds: &[MeshBounds],
        ranges: &[[u32; 2]],
        city_indices: (vk::Buffer, u32),
        slots: u32,
    ) -> Result<Self> {
        let mesh_count = u32::try_from(bounds.len())
            .ok()
            .filter(|&n| n > 0 && ranges.len() == bounds.len())
            .ok_or_else(|| {
                EngineError::InvalidRequest(format!(
                    "culling {} meshes with {} index ranges",
                    bounds.len(),
                    ranges.len()
                ))
            })?;
        if slots == 0 {
            return Err(EngineError::InvalidRequest("culling with 0 read-back slots".into()));
        }
        let group_count = mesh_count.div_ceil(CULL_CHUNK);
        // A view shows a part of the city: a quarter of its indices per list, within bounds
        // and what one storage buffer may address. A list that does not fit draws every mesh.
        let city = u64::from(city_indices.1);
        let addressable = u64::from(device.properties().limits.max_storage_buffer_range) / 4;
        let capacity = (city / 4)
            .max(city.min(MIN_LIST_INDICES))
            .min(MAX_LIST_INDICES)
            .min(addressable)
            .max(1) as u32;
        let limits = device.properties().limits;
        let max_range = std::env::var(WINDOW_BYTES_ENV)
            .ok()
            .and_then(|v| v.parse::<u64>().ok())
            .map_or(u64::from(limits.max_storage_buffer_range), |v| {
                v.min(u64::from(limits.max_storage_buffer_range))
            });
        let alignment = limits.min_storage_buffer_offset_alignment;
        let bounds_windows = StorageWindows::new(
            std::mem::size_of_val(bounds) as u64,
            std::mem::size_of::<MeshBounds>() as u64,
            max_range,
            alignment,
            "the mesh bounds",
        )?;
        let index_windows = StorageWindows::new(city * 4, 4, max_range, alignment, "the city's index buffer")?;
        let stages = vk::ShaderStageFlags::COMPUTE;
        let storage = vk::DescriptorType::STORAGE_BUFFER;
        let pipeline = Pipeline::compute(
            device,
            &shaders::CITY_CULL_COMP,
            &[
                (BINDING_CULL_BOUNDS, storage, CULL_WINDOWS, stages),
                (BINDING_CULL_RANGES, storage, 1, stages),
                (BINDING_CULL_FLAGS, storage, 1, stages),
                (BINDING_CULL_GROUPS, storage, 1, stages),
                (BINDING_CULL_DRAWS, storage, 1, stages),
                (BINDING_CULL_COUNTER, storage, 1, stages),
                (BINDING_CULL_PYRAMID, storage, 1, stages),
                (BINDING_CULL_CHUNK_BOUNDS, storage, 1, stages),
                (BINDING_CULL_CHUNK_FLAGS, storage, 1, stages),
                (BINDING_CULL_CITY_INDICES, storage, CULL_WINDOWS, stages),
                (BINDING_CULL_INDICES, storage, 1, stages),
            ],
            std::mem::size_of::<CullPush>() as u32,
            "city culling",
        )?;
        let views_count = 2;
        let pool = DescriptorPool::new(
            device,
            &pipeline,
            views_count * CullList::ALL.len() as u32,
            "city culling descriptors",
        )?;
        let bounds_buffer = upload_buffer(
            device,
            commands,
            bytemuck::cast_slice(bounds),
            vk::BufferUsageFlags::STORAGE_BUFFER,
            "city mesh bounds",
        )?;
        let chunk_bounds = upload_buffer(
            device,
            commands,
            bytemuck::cast_slice(&chunk_bounds(bounds)),
            vk::BufferUsageFlags::STORAGE_BUFFER,
            "city chunk bounds",
        )?;
        let ranges_buffer = upload_buffer(
            device,
            commands,
            bytemuck::cast_slice(ranges),
            vk::BufferUsageFlags::STORAGE_BUFFER,
            "city mesh index ranges",
        )?;
        let gpu = |size: u64, usage: vk::BufferUsageFlags, name: &str| {
            Buffer::new(
                device,
                BufferDesc {
                    size: size.max(4),
                    usage,
                    location: MemoryLocation::GpuOnly,
                },
                name,
            )
        };
        let transfer = vk::BufferUsageFlags::TRANSFER_SRC | vk::BufferUsageFlags::TRANSFER_DST;
        let mut views = Vec::new();
        for view in ["feedback", "visible"] {
            let flags = gpu(
                u64::from(mesh_count) * 4,
                vk::BufferUsageFlags::STORAGE_BUFFER | transfer,
                &format!("culling flags ({view})"),
            )?;
            let chunk_flags = gpu(
                u64::from(group_count) * 4,
                vk::BufferUsageFlags::STORAGE_BUFFER,
                &format!("culling chunk flags ({view})"),
            )?;
            // Sized at first use, for the view's depth target.
            let pyramid = gpu(
                4,
                vk::BufferUsageFlags::STORAGE_BUFFER | transfer,
                &format!("depth pyramid ({view})"),
            )?;
            let mut lists = Vec::new();
            for list in CullList::ALL {
                let name = format!("{view} {list:?}");
                let groups = gpu(
                    u64::from(group_count) * 4,
                    vk::BufferUsageFlags::STORAGE_BUFFER,
                    &format!("culling groups ({name})"),
                )?;
                let indices = gpu(
                    u64::from(capacity) * 4,
                    vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::INDEX_BUFFER,
                    &format!("culled indices ({name})"),
                )?;
                let draws = gpu(
                    2 * DRAW_STRIDE,
                    vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::INDIRECT_BUFFER | transfer,
                    &format!("culled draws ({name})"),
                )?;
                let counter = gpu(
                    std::mem::size_of::<CullCounter>() as u64,
                    vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::INDIRECT_BUFFER | transfer,
                    &format!("culled draw count ({name})"),
                )?;
                let set = pool.allocate(&pipeline, &[])?;
                lists.push(ListBuffers {
                    groups,
                    indices,
                    draws,
                    counter,
                    set,
                });
            }
            views.push(ViewBuffers {
                flags,
                chunk_flags,
                pyramid: Mutex::new(Pyramid {
                    buffer: pyramid,
                    shape: (0, 0, 0),
                }),
                lists,
            });
        }
        let readback = (0..slots)
            .map(|slot| {
                Buffer::new(
                    device,
                    BufferDesc {
                        size: (views.len() * CullList::ALL.len() * std::mem::size_of::<CullCounter>()) as u64,
                        usage: vk::BufferUsageFlags::TRANSFER_DST,
                        location: MemoryLocation::GpuToCpu,
                    },
                    &format!("culling statistics (slot {slot})"),
                )
            })
            .collect::<Result<Vec<_>>>()?;
        let timer = GpuTimer::new(device, slots * 2 * views.len() as u32)?;
        let culling = Self {
            device: Arc::clone(device),
            pipeline,
            pool,
            bounds: bounds_buffer,
            chunk_bounds,
            ranges: ranges_buffer,
            views,
            mesh_count,
            group_count,
            capacity,
            city_indices,
            bounds_windows,
            index_windows,
            readback,
            timer,
            recording: Mutex::new(SlotRecords {
                slot: 0,
                written: vec![0; slots as usize],
            }),
        };
        for view in [CullView::Feedback, CullView::Visible] {
            culling.write_sets(view);
        }
        // Flags start clear: nothing was visible before the first frame.
        let cmd = commands.begin()?;
        for view in &culling.views {
            // SAFETY: cmd is recording outside rendering; the buffer allows transfers.
            unsafe {
                device
                    .raw()
                    .cmd_fill_buffer(cmd.raw(), view.flags.raw(), 0, vk::WHOLE_SIZE, 0)
            };
        }
        commands.submit_and_wait(&[])?;
        Ok(culling)
    }

    fn write_sets(&self, view: CullView) {
        let v = &self.views[view as usize];
        let pyramid = lock(&v.pyramid).buffer.raw();
        for list in &v.lists {
            self.pool.write(
                list.set,
                &[
                    (BINDING_CULL_BOUNDS, self.bounds_windows.resource(self.bounds.raw())),
                    (
                        BINDING_CULL_RANGES,
                        DescriptorResource::StorageBuffer(self.ranges.raw()),
                    ),
                    (BINDING_CULL_FLAGS, DescriptorResource::StorageBuffer(v.flags.raw())),
                    (
                        BINDING_CULL_GROUPS,
                        DescriptorResource::StorageBuffer(list.groups.raw()),
                    ),
                    (BINDING_CULL_DRAWS, DescriptorResource::StorageBuffer(list.draws.raw())),
                    (
                        BINDING_CULL_COUNTER,
                        DescriptorResource::StorageBuffer(list.counter.raw()),
                    ),
                    (BINDING_CULL_PYRAMID, DescriptorResource::StorageBuffer(pyramid)),
                    (
                        BINDING_CULL_CITY_INDICES,
                        self.index_windows.resource(self.city_indices.0),
                    ),
                    (
                        BINDING_CULL_INDICES,
                        DescriptorResource::StorageBuffer(list.indices.raw()),
                    ),
                    (
                        BINDING_CULL_CHUNK_BOUNDS,
                        DescriptorResource::StorageBuffer(self.chunk_bounds.raw()),
                    ),
                    (
                        BINDING_CULL_CHUNK_FLAGS,
                        DescriptorResource::StorageBuffer(v.chunk_flags.raw()),
                    ),
                ],
            );
        }
    }

    /// Sizes `view`'s depth pyramid for `target`. A new size waits for the queue to idle
    /// (the old pyramid may be in use by frames in flight): a window's resize, not a
    /// per-frame cost.
    pub(crate) fn prepare(&self, view: CullView, target: &RenderTarget) -> Result<()> {
        let (width, height) = (target.width(), target.height());
        let levels = 32 - width.max(height).leading_zeros();
        let v = &self.views[view as usize];
        if lock(&v.pyramid).shape == (width, height, levels) {
            return Ok(());
        }
        let mut texels = 0u64;
        let (mut w, mut h) = (width, height);
        for _ in 0..levels {
            texels += u64::from(w) * u64::from(h);
            w = w.div_ceil(2);
            h = h.div_ceil(2);
        }
        self.device.wait_idle()?;
        let buffer = Buffer::new(
            &self.device,
            BufferDesc {
                size: (texels * 4).max(target.depth_bytes()),
                usage: vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::TRANSFER_DST,
                location: MemoryLocation::GpuOnly,
            },
            &format!("depth pyramid ({view:?})"),
        )?;
        *lock(&v.pyramid) = Pyramid {
            buffer,
            shape: (width, height, levels),
        };
        self.write_sets(view);
        Ok(())
    }

    /// Makes the next recordings write statistics and timestamps into `slot` (the frame
    /// slot of the command buffer being recorded).
    pub(crate) fn set_slot(&self, slot: u32) -> Result<()> {
        if slot as usize >= self.readback.len() {
            return Err(EngineError::InvalidRequest(format!(
                "culling slot {slot} of {} slots",
                self.readback.len()
            )));
        }
        let mut recording = lock(&self.recording);
        recording.slot = slot;
        recording.written[slot as usize] = 0;
        Ok(())
    }

    fn mark_written(&self, bit: u32) {
        let mut recording = lock(&self.recording);
        let slot = recording.slot as usize;
        recording.written[slot] |= 1 << bit;
    }

    fn slot(&self) -> u32 {
        lock(&self.recording).slot
    }

    fn query(&self, view: CullView, segment: u32) -> u32 {
        (self.slot() * 2 + view as u32) * 2 + segment
    }

    fn push(&self, view_proj: &Mat4, view: CullView, phase: u32, list: CullList) -> CullPush {
        let (width, height, levels) = lock(&self.views[view as usize].pyramid).shape;
        let (mask, want) = list.predicate();
        CullPush {
            view_proj: view_proj.to_cols_array_2d(),
            pyramid: [width, height, levels, 0],
            mesh_count: self.mesh_count,
            phase,
            mask,
            want,
            capacity: self.capacity,
            group_count: self.group_count,
            city_indices: self.city_indices.1,
            window_shifts: self.bounds_windows.shift | (self.index_windows.shift << 8),
        }
    }

    fn dispatch(&self, rec: Recording<'_>, set: vk::DescriptorSet, push: &CullPush, invocations: u32) {
        self.pipeline.bind(rec, set);
        self.pipeline.push(rec, push);
        self.pipeline.dispatch_flat(rec, invocations, WORKGROUP);
    }

    fn compute_barrier(&self, rec: Recording<'_>) {
        memory_barrier(
            &self.device,
            rec,
            CULL_WRITES,
            (
                vk::PipelineStageFlags2::COMPUTE_SHADER,
                vk::AccessFlags2::SHADER_READ | vk::AccessFlags2::SHADER_WRITE,
            ),
        );
    }

    /// Compacts `lists` of `view` from its flags into indirect draws (count, scan, emit).
    fn emit(&self, rec: Recording<'_>, view_proj: &Mat4, view: CullView, lists: &[CullList]) {
        let cmd = rec.raw();
        let v = &self.views[view as usize];
        let raw = self.device.raw();
        // The last frame's draws and copies read these buffers, and earlier dispatches
        // bound them, before they are cleared.
        memory_barrier(
            &self.device,
            rec,
            (
                vk::PipelineStageFlags2::DRAW_INDIRECT
                    | vk::PipelineStageFlags2::INDEX_INPUT
                    | vk::PipelineStageFlags2::COPY
                    | vk::PipelineStageFlags2::COMPUTE_SHADER,
                vk::AccessFlags2::INDIRECT_COMMAND_READ
                    | vk::AccessFlags2::INDEX_READ
                    | vk::AccessFlags2::TRANSFER_READ
                    | vk::AccessFlags2::SHADER_WRITE,
            ),
            (
                vk::PipelineStageFlags2::CLEAR
                    | vk::PipelineStageFlags2::COPY
                    | vk::PipelineStageFlags2::COMPUTE_SHADER,
                vk::AccessFlags2::TRANSFER_WRITE | vk::AccessFlags2::SHADER_WRITE,
            ),
        );
        for &list in lists {
            let l = &v.lists[list as usize];
            // SAFETY: cmd is recording outside rendering; the buffer allows transfers.
            unsafe { raw.cmd_fill_buffer(cmd, l.counter.raw(), 0, vk::WHOLE_SIZE, 0) };
        }
        for phase in [CULL_PHASE_COUNT, CULL_PHASE_SCAN, CULL_PHASE_EMIT] {
            self.compute_barrier(rec);
            let invocations = if phase == CULL_PHASE_SCAN { 1 } else { self.group_count };
            for &list in lists {
                let push = self.push(view_proj, view, phase, list);
                self.dispatch(rec, v.lists[list as usize].set, &push, invocations);
            }
        }
        memory_barrier(
            &self.device,
            rec,
            (vk::PipelineStageFlags2::COMPUTE_SHADER, vk::AccessFlags2::SHADER_WRITE),
            (
                vk::PipelineStageFlags2::DRAW_INDIRECT
                    | vk::PipelineStageFlags2::INDEX_INPUT
                    | vk::PipelineStageFlags2::COPY,
                vk::AccessFlags2::INDIRECT_COMMAND_READ
                    | vk::AccessFlags2::INDEX_READ
                    | vk::AccessFlags2::TRANSFER_READ,
            ),
        );
    }

    /// Orders earlier draws' reads of the lists (indices, draw records) before the
    /// dispatches that bind them.
    fn draws_before_dispatch(&self, rec: Recording<'_>) {
        memory_barrier(
            &self.device,
            rec,
            (
                vk::PipelineStageFlags2::DRAW_INDIRECT | vk::PipelineStageFlags2::INDEX_INPUT,
                vk::AccessFlags2::INDIRECT_COMMAND_READ | vk::AccessFlags2::INDEX_READ,
            ),
            (
                vk::PipelineStageFlags2::COMPUTE_SHADER,
                vk::AccessFlags2::SHADER_READ | vk::AccessFlags2::SHADER_WRITE,
            ),
        );
    }

    /// The early phase of `view` (outside rendering): frustum flags, and the early list.
    pub(crate) fn record_early(&self, rec: Recording<'_>, view_proj: &Mat4, view: CullView) {
        let query = self.query(view, 0);
        self.timer.begin(rec, query);
        // The last frame's passes over this view's flags, and its draws of the lists the
        // dispatches bind, finish before they change.
        self.draws_before_dispatch(rec);
        memory_barrier(
            &self.device,
            rec,
            (
                vk::PipelineStageFlags2::COMPUTE_SHADER,
                vk::AccessFlags2::SHADER_READ | vk::AccessFlags2::SHADER_WRITE,
            ),
            (
                vk::PipelineStageFlags2::COMPUTE_SHADER,
                vk::AccessFlags2::SHADER_READ | vk::AccessFlags2::SHADER_WRITE,
            ),
        );
        let v = &self.views[view as usize];
        let push = self.push(view_proj, view, CULL_PHASE_FRUSTUM, CullList::Early);
        self.dispatch(rec, v.lists[0].set, &push, self.group_count);
        self.emit(rec, view_proj, view, &[CullList::Early]);
        self.timer.end(rec, query);
        self.mark_written(view as u32 * 2);
    }

    /// Records a copy of `view`'s per-mesh flags into `into` (the culling of another
    /// renderer of the same city), so that `into`'s next pass over that view draws the
    /// meshes this one draws next, in the same two phases. A depth tie between an early
    /// and a late mesh goes to the one drawn first, so a renderer culling on its own
    /// history can resolve it differently; the error reference draws the view's own
    /// visibility instead. Record it before this view's next early phase.
    pub(crate) fn record_copy_flags(&self, rec: Recording<'_>, view: CullView, into: &CityCulling) -> Result<()> {
        if into.mesh_count != self.mesh_count {
            return Err(EngineError::InvalidRequest(format!(
                "culling flags of {} meshes copied into a culling of {} meshes",
                self.mesh_count, into.mesh_count
            )));
        }
        let (from, to) = (&self.views[view as usize].flags, &into.views[view as usize].flags);
        // Either buffer's earlier passes (this view's last frame, `into`'s last render,
        // the first clear) finish before the copy reads or replaces it.
        memory_barrier(
            &self.device,
            rec,
            CULL_WRITES,
            (
                vk::PipelineStageFlags2::COPY,
                vk::AccessFlags2::TRANSFER_READ | vk::AccessFlags2::TRANSFER_WRITE,
            ),
        );
        let region = vk::BufferCopy {
            src_offset: 0,
            dst_offset: 0,
            size: u64::from(self.mesh_count.max(1)) * 4,
        };
        // SAFETY: both buffers hold `mesh_count` flags (at least one word) and allow
        // transfers; rec is recording outside rendering.
        unsafe {
            self.device
                .raw()
                .cmd_copy_buffer(rec.raw(), from.raw(), to.raw(), &[region])
        };
        // Both cultings' next dispatches over the flags (in this submission or a later one).
        memory_barrier(
            &self.device,
            rec,
            (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE),
            (
                vk::PipelineStageFlags2::COMPUTE_SHADER,
                vk::AccessFlags2::SHADER_READ | vk::AccessFlags2::SHADER_WRITE,
            ),
        );
        Ok(())
    }

    /// The late phase of `view`, after its early draws: pyramid from `target`'s depth
    /// (rendering is paused and resumed around it), occlusion flags, the late list (and
    /// for the feedback view the unoccluded one), and the statistics copy.
    pub(crate) fn record_late(&self, rec: Recording<'_>, view_proj: &Mat4, view: CullView, target: &RenderTarget) {
        let v = &self.views[view as usize];
        let query = self.query(view, 1);
        let (pyramid, (mut width, mut height, levels)) = {
            let p = lock(&v.pyramid);
            (p.buffer.raw(), p.shape)
        };
        target.pause(&self.device, rec);
        self.timer.begin(rec, query);
        // The early draws read the early list the dispatches bind.
        self.draws_before_dispatch(rec);
        target.copy_depth(&self.device, rec, pyramid);
        for level in 1..levels {
            width = width.div_ceil(2);
            height = height.div_ceil(2);
            self.compute_barrier(rec);
            let mut push = self.push(view_proj, view, CULL_PHASE_PYRAMID, CullList::Early);
            push.want = level;
            self.dispatch(rec, v.lists[0].set, &push, width * height);
        }
        self.compute_barrier(rec);
        let push = self.push(view_proj, view, CULL_PHASE_OCCLUSION, CullList::Early);
        self.dispatch(rec, v.lists[0].set, &push, self.group_count);
        // Only the feedback view draws the unoccluded list (its feedback pass).
        match view {
            CullView::Feedback => self.emit(rec, view_proj, view, &[CullList::Late, CullList::Unoccluded]),
            CullView::Visible => self.emit(rec, view_proj, view, &[CullList::Late]),
        }
        self.copy_statistics(rec, view);
        self.timer.end(rec, query);
        self.mark_written(view as u32 * 2 + 1);
        self.mark_written(4 + view as u32);
        target.resume(&self.device, rec);
    }

    fn copy_statistics(&self, rec: Recording<'_>, view: CullView) {
        let cmd = rec.raw();
        let size = std::mem::size_of::<CullCounter>() as u64;
        let readback = &self.readback[self.slot() as usize];
        // The host read the slot's last statistics before its frame was recorded again.
        for (l, list) in self.views[view as usize].lists.iter().enumerate() {
            let region = vk::BufferCopy {
                src_offset: 0,
                dst_offset: (view as u64 * CullList::ALL.len() as u64 + l as u64) * size,
                size,
            };
            // SAFETY: both buffers hold the region; cmd is recording outside rendering.
            unsafe {
                self.device
                    .raw()
                    .cmd_copy_buffer(cmd, list.counter.raw(), readback.raw(), &[region])
            };
        }
        memory_barrier(
            &self.device,
            rec,
            (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE),
            (vk::PipelineStageFlags2::HOST, vk::AccessFlags2::HOST_READ),
        );
    }

    /// Records `list` of `view`'s draws with the bound graphics pipeline and vertex buffer
    /// (inside rendering): its own indices, or on overflow the city's. Binds index buffers.
    pub(crate) fn draw(&self, rec: Recording<'_>, view: CullView, list: CullList) {
        let cmd = rec.raw();
        let l = &self.views[view as usize].lists[list as usize];
        let raw = self.device.raw();
        // SAFETY: the draws were written by this frame's culling behind a barrier to
        // DRAW_INDIRECT and INDEX_INPUT; the first draws the list's indices (each below the
        // city's vertex count, copied from the city's), the second, on overflow only, the
        // city's own index buffer; one draw each needs no multi-draw feature.
        unsafe {
            raw.cmd_bind_index_buffer(cmd, l.indices.raw(), 0, vk::IndexType::UINT32);
            raw.cmd_draw_indexed_indirect(cmd, l.draws.raw(), 0, 1, DRAW_STRIDE as u32);
            raw.cmd_bind_index_buffer(cmd, self.city_indices.0, 0, vk::IndexType::UINT32);
            raw.cmd_draw_indexed_indirect(cmd, l.draws.raw(), DRAW_STRIDE, 1, DRAW_STRIDE as u32);
        }
    }

    /// The statistics of the frame recorded into `slot`, once its submission completed.
    pub(crate) fn stats(&self, slot: u32) -> Result<CullStats> {
        let readback = self.readback.get(slot as usize).ok_or_else(|| {
            EngineError::InvalidRequest(format!("culling slot {slot} of {} slots", self.readback.len()))
        })?;
        let written = lock(&self.recording).written[slot as usize];
        let counters = readback.read::<CullCounter>(0, self.views.len() * CullList::ALL.len())?;
        let at = |view: CullView, list: CullList| {
            let copied = written & (1 << (4 + view as u32)) != 0;
            let counter = counters[view as usize * CullList::ALL.len() + list as usize];
            if copied {
                counter
            } else {
                CullCounter::default()
            }
        };
        let early = at(CullView::Visible, CullList::Early);
        let late = at(CullView::Visible, CullList::Late);
        // A list that overflowed drew every mesh.
        let drawn = |counter: CullCounter| {
            if counter.overflowed != 0 {
                self.mesh_count
            } else {
                counter.meshes
            }
        };
        let meshes_drawn = (drawn(early) + drawn(late)).min(self.mesh_count);
        let mut cull_ms = None;
        for view in [CullView::Feedback, CullView::Visible] {
            for segment in 0..2 {
                if written & (1 << (view as u32 * 2 + segment)) == 0 {
                    continue;
                }
                let query = (slot * 2 + view as u32) * 2 + segment;
                if let Some(ms) = self.timer.read_ms(query)? {
                    cull_ms.get_or_insert([0.0; 2])[view as usize] += ms;
                }
            }
        }
        Ok(CullStats {
            meshes_drawn,
            meshes_culled: self.mesh_count - meshes_drawn,
            meshes_passed: early.meshes + late.meshes,
            feedback_meshes_drawn: drawn(at(CullView::Feedback, CullList::Unoccluded)),
            overflowed: early.overflowed + late.overflowed != 0,
            cull_ms,
        })
    }
}

fn lock<T>(mutex: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}
