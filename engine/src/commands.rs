//! Command recording and submission: one-shot command contexts, fences and
//! semaphores that own their handles.

use std::marker::PhantomData;
use std::sync::Arc;

use ash::vk;

use crate::device::Device;
use crate::error::{Result, VkResultExt};

/// A binary semaphore owned by Rust.
pub struct Semaphore {
    device: Arc<Device>,
    raw: vk::Semaphore,
}

debug_fields!(Semaphore { raw });

impl Semaphore {
    /// Creates a binary semaphore.
    pub fn new(device: &Arc<Device>, name: &str) -> Result<Self> {
        // SAFETY: valid create info on a live device.
        unsafe { Self::create(device, &vk::SemaphoreCreateInfo::default(), "vkCreateSemaphore", name) }
    }

    /// Creates a semaphore of `info` (binary, or a timeline one), named; `call` names the
    /// creation in an error.
    ///
    /// # Safety
    /// `info` is valid on `device`, whose features allow the kind of semaphore it asks for.
    unsafe fn create(
        device: &Arc<Device>,
        info: &vk::SemaphoreCreateInfo<'_>,
        call: &'static str,
        name: &str,
    ) -> Result<Self> {
        // SAFETY: as the caller guarantees.
        let raw = unsafe { device.raw.create_semaphore(info, None) }.vk(call)?;
        device.set_name(raw, name);
        Ok(Self {
            device: Arc::clone(device),
            raw,
        })
    }

    /// The raw handle.
    pub fn raw(&self) -> vk::Semaphore {
        self.raw
    }
}

impl Drop for Semaphore {
    fn drop(&mut self) {
        // SAFETY: the owner drops only after every wait on it completed.
        unsafe { self.device.raw.destroy_semaphore(self.raw, None) };
    }
}

/// A fence owned by Rust.
pub struct Fence {
    device: Arc<Device>,
    raw: vk::Fence,
}

debug_fields!(Fence { raw });

impl Fence {
    /// Creates a fence, signalled or not.
    pub fn new(device: &Arc<Device>, signalled: bool, name: &str) -> Result<Self> {
        let flags = if signalled {
            vk::FenceCreateFlags::SIGNALED
        } else {
            vk::FenceCreateFlags::empty()
        };
        let info = vk::FenceCreateInfo::default().flags(flags);
        // SAFETY: valid create info on a live device.
        let raw = unsafe { device.raw.create_fence(&info, None) }.vk("vkCreateFence")?;
        device.set_name(raw, name);
        Ok(Self {
            device: Arc::clone(device),
            raw,
        })
    }

    /// The raw handle.
    pub fn raw(&self) -> vk::Fence {
        self.raw
    }

    /// Waits for the fence without a time limit.
    pub fn wait(&self) -> Result<()> {
        // SAFETY: the fence belongs to this device.
        unsafe { self.device.raw.wait_for_fences(&[self.raw], true, u64::MAX) }.vk("vkWaitForFences")
    }

    /// Whether the fence is signalled.
    pub fn is_signalled(&self) -> Result<bool> {
        // SAFETY: the fence belongs to this device.
        unsafe { self.device.raw.get_fence_status(self.raw) }.vk("vkGetFenceStatus")
    }

    /// Resets the fence to unsignalled.
    pub fn reset(&self) -> Result<()> {
        // SAFETY: the fence belongs to this device and is not in a pending submission.
        unsafe { self.device.raw.reset_fences(&[self.raw]) }.vk("vkResetFences")
    }
}

impl Drop for Fence {
    fn drop(&mut self) {
        // SAFETY: the owner drops only after the fence's submission completed.
        unsafe { self.device.raw.destroy_fence(self.raw, None) };
    }
}

/// A semaphore the submission waits on, with the stages that wait.
#[derive(Clone, Copy, Debug)]
pub struct SemaphoreWait {
    /// The semaphore.
    pub semaphore: vk::Semaphore,
    /// Stages that wait for it.
    pub stages: vk::PipelineStageFlags2,
    /// The value to wait for on a timeline semaphore; ignored for binary ones.
    pub value: u64,
}

impl SemaphoreWait {
    /// A wait on a binary semaphore.
    pub fn binary(semaphore: vk::Semaphore, stages: vk::PipelineStageFlags2) -> Self {
        Self {
            semaphore,
            stages,
            value: 0,
        }
    }

    /// This wait as a `vkQueueSubmit2` wait info.
    pub fn submit_info(&self) -> vk::SemaphoreSubmitInfo<'static> {
        vk::SemaphoreSubmitInfo::default()
            .semaphore(self.semaphore)
            .stage_mask(self.stages)
            .value(self.value)
    }
}

/// A semaphore a submission signals: a binary one, or a timeline one with
/// the value it is set to.
#[derive(Clone, Copy, Debug)]
pub struct SemaphoreSignal {
    /// The semaphore.
    pub semaphore: vk::Semaphore,
    /// The value for a timeline semaphore; ignored for binary ones.
    pub value: u64,
}

impl SemaphoreSignal {
    /// This signal as a `vkQueueSubmit2` signal info, at `ALL_COMMANDS`: set
    /// once every command of the submission has completed (the streamer
    /// reads a frame's feedback and reuses its staging space after it).
    pub fn submit_info(&self) -> vk::SemaphoreSubmitInfo<'static> {
        vk::SemaphoreSubmitInfo::default()
            .semaphore(self.semaphore)
            .value(self.value)
            .stage_mask(vk::PipelineStageFlags2::ALL_COMMANDS)
    }
}

/// A timeline semaphore owned by Rust: bind batches signal increasing
/// values, and copy submissions wait for the value of the batch they need.
pub struct TimelineSemaphore {
    /// The semaphore, destroyed when it drops (after the idle wait in this type's drop).
    semaphore: Semaphore,
}

debug_fields!(TimelineSemaphore { raw = |s| s.semaphore.raw });

impl TimelineSemaphore {
    /// Creates a timeline semaphore starting at `initial`.
    pub fn new(device: &Arc<Device>, initial: u64, name: &str) -> Result<Self> {
        let mut type_info = vk::SemaphoreTypeCreateInfo::default()
            .semaphore_type(vk::SemaphoreType::TIMELINE)
            .initial_value(initial);
        let info = vk::SemaphoreCreateInfo::default().push_next(&mut type_info);
        // SAFETY: valid create info; timeline semaphores are enabled on the device.
        let semaphore = unsafe { Semaphore::create(device, &info, "vkCreateSemaphore (timeline)", name) }?;
        Ok(Self { semaphore })
    }

    /// The raw handle.
    pub fn raw(&self) -> vk::Semaphore {
        self.semaphore.raw
    }

    /// The current counter value.
    pub fn value(&self) -> Result<u64> {
        let Semaphore { device, raw } = &self.semaphore;
        // SAFETY: the semaphore belongs to this device.
        unsafe { device.raw.get_semaphore_counter_value(*raw) }.vk("vkGetSemaphoreCounterValue")
    }

    /// Waits until the counter reaches `value`.
    pub fn wait(&self, value: u64) -> Result<()> {
        let semaphores = [self.semaphore.raw];
        let values = [value];
        let info = vk::SemaphoreWaitInfo::default().semaphores(&semaphores).values(&values);
        // SAFETY: the semaphore belongs to this device.
        unsafe { self.semaphore.device.raw.wait_semaphores(&info, u64::MAX) }.vk("vkWaitSemaphores")
    }
}

impl Drop for TimelineSemaphore {
    fn drop(&mut self) {
        // The GPU may still be about to signal it; wait for the device first. The
        // semaphore itself is destroyed when the field drops, after this: nothing pending
        // references it after the idle wait.
        let _ = self.semaphore.device.wait_idle();
    }
}

/// A command buffer in the recording state, lent for `'a` to the engine's recorders:
/// every function of the engine that records commands takes one, so none of them can
/// be handed a buffer that is not recording.
///
/// The engine's own buffers lend one from [`CommandContext::begin`] (or
/// [`CommandContext::recording`]), borrowing the context so that it cannot submit,
/// reset or free the buffer while the `Recording` lives. A host recording the engine's
/// passes into a buffer of its own makes one with [`Recording::from_raw`], whose
/// contract is the one every recorder relies on. Not `Send`: one thread records.
///
/// ```no_run
/// # fn f(device: &std::sync::Arc<citystream_engine::Device>, target: &citystream_engine::target::RenderTarget) -> citystream_engine::Result<()> {
/// let mut commands = citystream_engine::commands::CommandContext::new(device, "frame")?;
/// let rec = commands.begin()?;
/// target.end_and_copy(device, rec);
/// commands.submit_and_wait(&[])?;
/// # Ok(()) }
/// ```
///
/// Recording into a buffer after it was submitted does not compile:
///
/// ```compile_fail,E0499
/// # fn f(device: &std::sync::Arc<citystream_engine::Device>, target: &citystream_engine::target::RenderTarget) -> citystream_engine::Result<()> {
/// let mut commands = citystream_engine::commands::CommandContext::new(device, "frame")?;
/// let rec = commands.begin()?;
/// commands.submit_and_wait(&[])?;
/// target.end_and_copy(device, rec); // `rec` still borrows `commands`, which submitted
/// # Ok(()) }
/// ```
#[derive(Clone, Copy, Debug)]
pub struct Recording<'a> {
    cmd: vk::CommandBuffer,
    /// Borrows what keeps the buffer recording, and stays on its thread.
    _recording: PhantomData<(&'a mut (), *const ())>,
}

impl Recording<'_> {
    /// Lends the host's command buffer `cmd` to the engine's recorders.
    ///
    /// # Safety
    /// Whenever the returned `Recording` or a copy of it is used, `cmd` must be a
    /// primary command buffer of the device the recorders were created on, in the
    /// recording state (begun, not yet ended), not reset, freed or recorded into by
    /// another thread, and not inside a render pass or dynamic rendering instance
    /// unless the recorder's documentation says it expects one.
    pub unsafe fn from_raw(cmd: vk::CommandBuffer) -> Self {
        Self {
            cmd,
            _recording: PhantomData,
        }
    }

    /// The command buffer, for the host's own commands between the engine's.
    pub fn raw(&self) -> vk::CommandBuffer {
        self.cmd
    }
}

/// Records `vkCmdFillBuffer` of the whole `buffer` with `value` (outside
/// rendering; the buffer needs `TRANSFER_DST`).
pub fn record_fill(device: &Device, rec: Recording<'_>, buffer: &crate::buffer::Buffer, value: u32) {
    // SAFETY: rec is recording (its invariant); the buffer is live (owned by the caller).
    unsafe {
        device
            .raw
            .cmd_fill_buffer(rec.raw(), buffer.raw(), 0, vk::WHOLE_SIZE, value)
    };
}

/// A command pool with one primary command buffer and a fence: record,
/// submit, wait, reuse.
///
/// Threading: owned by one thread at a time.
pub struct CommandContext {
    device: Arc<Device>,
    pool: vk::CommandPool,
    cmd: vk::CommandBuffer,
    fence: Fence,
    pending: bool,
    /// Begun and not yet submitted: [`Recording`]s may be lent.
    recording: bool,
    /// A submission without the fence may still run (its completion is
    /// tracked by the caller's timeline semaphore).
    untracked: bool,
}

debug_fields!(CommandContext { pending });

impl CommandContext {
    /// Creates the pool, the command buffer and the fence.
    pub fn new(device: &Arc<Device>, name: &str) -> Result<Self> {
        let fence = Fence::new(device, false, &format!("{name} fence"))?;
        let info = vk::CommandPoolCreateInfo::default()
            .queue_family_index(device.queue_family())
            .flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER);
        // SAFETY: valid create info on a live device.
        let pool = unsafe { device.raw.create_command_pool(&info, None) }.vk("vkCreateCommandPool")?;
        let alloc = vk::CommandBufferAllocateInfo::default()
            .command_pool(pool)
            .level(vk::CommandBufferLevel::PRIMARY)
            .command_buffer_count(1);
        // SAFETY: the pool was just created on this device.
        let cmd = match unsafe { device.raw.allocate_command_buffers(&alloc) } {
            Ok(buffers) => buffers[0],
            Err(result) => {
                // SAFETY: the pool has no buffers in use.
                unsafe { device.raw.destroy_command_pool(pool, None) };
                return Err(crate::EngineError::Vulkan {
                    call: "vkAllocateCommandBuffers",
                    result,
                });
            }
        };
        device.set_name(pool, &format!("{name} pool"));
        device.set_name(cmd, name);
        Ok(Self {
            device: Arc::clone(device),
            pool,
            cmd,
            fence,
            pending: false,
            recording: false,
            untracked: false,
        })
    }

    /// Waits for any previous submission, then begins recording (what was recorded and
    /// not submitted is discarded).
    pub fn begin(&mut self) -> Result<Recording<'_>> {
        self.wait()?;
        if self.untracked {
            // The last submission had no fence: wait for the whole queue.
            self.device.wait_idle()?;
            self.untracked = false;
        }
        self.reset_and_begin()
    }

    /// Begins recording without waiting on the fence: for a frame's command
    /// buffer whose last submission ([`submit_frame`](Self::submit_frame))
    /// the caller saw complete on its timeline semaphore.
    pub fn begin_completed(&mut self) -> Result<Recording<'_>> {
        self.wait()?;
        self.untracked = false;
        self.reset_and_begin()
    }

    /// Resets and begins the buffer; the callers made sure its last
    /// submission completed (fence, queue or the caller's timeline).
    fn reset_and_begin(&mut self) -> Result<Recording<'_>> {
        let info = vk::CommandBufferBeginInfo::default().flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT);
        // SAFETY: the buffer is not pending (see the callers) and its pool allows reset.
        unsafe {
            self.device
                .raw
                .reset_command_buffer(self.cmd, vk::CommandBufferResetFlags::empty())
                .vk("vkResetCommandBuffer")?;
            self.device
                .raw
                .begin_command_buffer(self.cmd, &info)
                .vk("vkBeginCommandBuffer")?;
        }
        self.recording = true;
        Ok(self.lend())
    }

    /// The buffer begun and not yet submitted, lent again (for a host that records more
    /// into a frame after the engine's passes); an error if it is not recording.
    pub fn recording(&mut self) -> Result<Recording<'_>> {
        if !self.recording {
            return Err(crate::EngineError::InvalidRequest(
                "the command buffer is not recording: begin it first".into(),
            ));
        }
        Ok(self.lend())
    }

    fn lend(&mut self) -> Recording<'_> {
        Recording {
            cmd: self.cmd,
            _recording: PhantomData,
        }
    }

    /// Ends recording and submits without the fence; completion is tracked
    /// by a timeline semaphore in `signal`. Reuse the context with
    /// [`begin_completed`](Self::begin_completed) once that value is reached.
    pub fn submit_frame(&mut self, waits: &[SemaphoreWait], signal: &[SemaphoreSignal]) -> Result<()> {
        self.submit_with(waits, signal, false)?;
        self.untracked = true;
        Ok(())
    }

    /// Ends recording and submits, waiting on `waits` and signalling `signal`.
    pub fn submit(&mut self, waits: &[SemaphoreWait], signal: &[SemaphoreSignal]) -> Result<()> {
        self.submit_with(waits, signal, true)
    }

    fn submit_with(&mut self, waits: &[SemaphoreWait], signal: &[SemaphoreSignal], fenced: bool) -> Result<()> {
        if !self.recording {
            return Err(crate::EngineError::InvalidRequest(
                "submitting a command buffer that was not begun".into(),
            ));
        }
        self.recording = false;
        // SAFETY: the buffer is in the recording state (the flag above).
        unsafe { self.device.raw.end_command_buffer(self.cmd) }.vk("vkEndCommandBuffer")?;
        let wait_infos: Vec<_> = waits.iter().map(SemaphoreWait::submit_info).collect();
        let signal_infos: Vec<_> = signal.iter().map(SemaphoreSignal::submit_info).collect();
        let cmd_infos = [vk::CommandBufferSubmitInfo::default().command_buffer(self.cmd)];
        let submit = vk::SubmitInfo2::default()
            .wait_semaphore_infos(&wait_infos)
            .command_buffer_infos(&cmd_infos)
            .signal_semaphore_infos(&signal_infos);
        let fence = if fenced {
            self.fence.reset()?;
            self.fence.raw()
        } else {
            vk::Fence::null()
        };
        let queue = self.device.queue();
        // SAFETY: queue access is serialised by the lock; every handle is live.
        unsafe { self.device.raw.queue_submit2(*queue, &[submit], fence) }.vk("vkQueueSubmit2")?;
        self.pending = fenced;
        Ok(())
    }

    /// Waits for the last submission to finish.
    pub fn wait(&mut self) -> Result<()> {
        if self.pending {
            self.fence.wait()?;
            self.pending = false;
        }
        Ok(())
    }

    /// Submits and waits.
    pub fn submit_and_wait(&mut self, waits: &[SemaphoreWait]) -> Result<()> {
        self.submit(waits, &[])?;
        self.wait()
    }

    /// The device.
    pub fn device(&self) -> &Arc<Device> {
        &self.device
    }
}

impl Drop for CommandContext {
    fn drop(&mut self) {
        // Errors here mean device loss; destruction must still happen.
        let _ = self.wait();
        if self.untracked {
            let _ = self.device.wait_idle();
        }
        // SAFETY: the buffer is no longer pending; destroying the pool frees it.
        unsafe { self.device.raw.destroy_command_pool(self.pool, None) };
    }
}
