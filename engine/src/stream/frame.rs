//! A frame's token and what its submission carries.

use std::time::Duration;

use ash::vk;

#[cfg(doc)]
use super::TextureStreamer;
use crate::commands::{SemaphoreSignal, SemaphoreWait};
#[cfg(doc)]
use crate::error::EngineError;
#[cfg(doc)]
use crate::texture_cache::Eviction;

/// A frame between [`TextureStreamer::begin_frame`] and [`TextureStreamer::end_frame`],
/// and what `begin_frame` did.
///
/// The token is the frame's proof of order: the recording calls take it by reference and
/// `end_frame` consumes it, so a frame cannot be ended twice or recorded into after it
/// ended, and a host cannot make one up. Calls the types cannot order (a second
/// `begin_frame` before `end_frame`, uploads recorded twice or never, a second resolve, a
/// token of another streamer) are refused
/// with [`EngineError::InvalidRequest`].
///
/// ```no_run
/// # use citystream_engine::{commands::CommandContext, stream::TextureStreamer};
/// # use citystream_streaming::source::DatasetSource;
/// # fn f(streamer: &mut TextureStreamer<DatasetSource>, commands: &mut CommandContext) -> citystream_engine::Result<()> {
/// let mut frame = streamer.begin_frame()?;
/// let rec = commands.begin()?;
/// streamer.record_uploads(&mut frame, rec)?;
/// let submit = streamer.end_frame(frame, 8.0)?;
/// commands.submit_frame(&submit.waits, &[submit.signal])?;
/// # Ok(()) }
/// ```
///
/// Ending a frame twice, or recording into it after it ended, does not compile:
///
/// ```compile_fail,E0382
/// # use citystream_engine::{commands::CommandContext, stream::TextureStreamer};
/// # use citystream_streaming::source::DatasetSource;
/// # fn f(streamer: &mut TextureStreamer<DatasetSource>, commands: &mut CommandContext) -> citystream_engine::Result<()> {
/// let mut frame = streamer.begin_frame()?;
/// let rec = commands.begin()?;
/// streamer.record_uploads(&mut frame, rec)?;
/// let submit = streamer.end_frame(frame, 8.0)?;
/// streamer.record_uploads(&mut frame, rec)?; // `frame` was consumed by end_frame
/// # Ok(()) }
/// ```
#[derive(Debug)]
#[must_use = "a frame is ended with TextureStreamer::end_frame"]
pub struct Frame {
    pub(super) index: u64,
    pub(super) slot: u32,
    pub(super) cpu_wait: Duration,
    pub(super) loading_started: bool,
    pub(super) refused: u32,
    pub(super) over_budget: bool,
    /// The streamer that began it.
    pub(super) streamer: u64,
    pub(super) uploads_recorded: bool,
    pub(super) resolved: bool,
    pub(super) prefetch_resolved: bool,
}

impl Frame {
    /// The frame's number, from 0.
    pub fn index(&self) -> u64 {
        self.index
    }

    /// Its read-back slot (and frame-in-flight slot: `index % frames_in_flight`).
    pub fn slot(&self) -> u32 {
        self.slot
    }

    /// Time the CPU blocked waiting for the GPU to finish the frame that used this slot
    /// before; zero when it had already finished.
    pub fn cpu_wait(&self) -> Duration {
        self.cpu_wait
    }

    /// Feedback of a completed frame (or the host's records) was handed to the loader.
    pub fn loading_started(&self) -> bool {
        self.loading_started
    }

    /// Mips the cache could not take this frame (loaded again later).
    pub fn refused(&self) -> u32 {
        self.refused
    }

    /// The view needs more than the memory budget holds: loads were refused or declined
    /// for room ([`Eviction::View`]), or packing evicted a layer to stay within the
    /// budget ([`Eviction::Ring`]).
    pub fn over_budget(&self) -> bool {
        self.over_budget
    }
}

/// Distinguishes streamers, so that a frame token is used only with its own.
pub(super) static NEXT_STREAMER_ID: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);

/// What the host's submission of a frame must carry.
#[derive(Clone, Debug)]
pub struct FrameSubmit {
    /// Semaphores to wait on (the sparse binds the copies need, at the copy stage).
    pub waits: Vec<SemaphoreWait>,
    /// The frame timeline value to signal when the frame completes.
    pub signal: SemaphoreSignal,
}

impl FrameSubmit {
    /// [`waits`](Self::waits) as `vkQueueSubmit2` wait infos.
    pub fn wait_infos(&self) -> Vec<vk::SemaphoreSubmitInfo<'static>> {
        self.waits.iter().map(SemaphoreWait::submit_info).collect()
    }

    /// [`signal`](Self::signal) as a `vkQueueSubmit2` signal info (at `ALL_COMMANDS`).
    pub fn signal_info(&self) -> vk::SemaphoreSubmitInfo<'static> {
        self.signal.submit_info()
    }
}
