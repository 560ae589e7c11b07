//! The passes of a flythrough frame: the feedback pass with its compaction and the visible
//! pass, as the flight records them and the measurements beside it (the error reference,
//! the pop-in) record them too; and the GPU timestamps around each and the culling
//! statistics read back once a frame completed, per frame slot.

use std::sync::Arc;

use anyhow::Result;

use citystream_engine::city::{Camera, CityRenderer, FeedbackView};
use citystream_engine::commands::{CommandContext, Recording};
use citystream_engine::cull::CullStats;
use citystream_engine::ground::GroundLayer;
use citystream_engine::stream::Frame;
use citystream_engine::target::RenderTarget;
use citystream_engine::timing::GpuTimer;
use citystream_engine::Device;
use citystream_streaming::bench::stats::Stats;

use super::city_gpu::CityGpu;

/// How a frame compacts its feedback (paper §3.3).
#[derive(Clone, Copy, Debug)]
pub(crate) enum Compaction {
    /// Entries reaching the streamer's own τ.
    Streamer,
    /// Entries reaching this τ (0: every seen mesh).
    Tau(u32),
}

/// Records the feedback pass for `camera` into `feedback_target` (for a visible view
/// `visible_height` tall) and its compaction into `frame`: the two passes between a
/// streamer frame's uploads and its visible pass. With `compaction` `None` the frame has no
/// feedback and records neither. `times` (the flight's) times each pass, empty or not.
#[allow(clippy::too_many_arguments)]
pub(crate) fn record_feedback(
    gpu: &mut CityGpu,
    frame: &mut Frame,
    rec: Recording<'_>,
    (feedback_target, view): (&RenderTarget, &FeedbackView),
    camera: &Camera,
    visible_height: u32,
    compaction: Option<Compaction>,
    mut times: Option<(&mut PassTimes, u32)>,
) -> Result<()> {
    if let Some((times, slot)) = times.as_mut() {
        times.begin(rec, *slot, 1);
    }
    if compaction.is_some() {
        gpu.renderer
            .record_feedback(rec, feedback_target, camera, view, visible_height)?;
    }
    if let Some((times, slot)) = times.as_mut() {
        times.end(rec, *slot, 1);
        times.begin(rec, *slot, 2);
    }
    match compaction {
        None => {}
        Some(Compaction::Tau(tau)) => gpu.streamer.record_feedback_resolve_with_tau(frame, rec, tau)?,
        Some(Compaction::Streamer) => gpu.streamer.record_feedback_resolve(frame, rec)?,
    }
    if let Some((times, slot)) = times.as_mut() {
        times.end(rec, *slot, 2);
    }
    Ok(())
}

/// Records `renderer`'s visible pass for `camera` into `target`, on the streamed ground
/// where given (its layer and the frame slot whose tiles it samples).
pub(crate) fn record_visible(
    renderer: &CityRenderer,
    rec: Recording<'_>,
    (target, camera): (&RenderTarget, &Camera),
    colormap_blend: bool,
    ground: Option<(&GroundLayer, u32)>,
) -> Result<()> {
    match ground {
        Some(ground) => renderer.record_visible_on_ground(rec, target, camera, colormap_blend, ground)?,
        None => renderer.record_visible(rec, target, camera, 1.0, colormap_blend)?,
    }
    Ok(())
}

/// The visible pass ([`record_visible`]) alone, submitted and waited for: `target` then
/// holds the view as `renderer`'s cache serves it now (the error reference's image of a
/// flight's frame, the pop-in's images).
pub(crate) fn draw_now(
    commands: &mut CommandContext,
    renderer: &CityRenderer,
    view: (&RenderTarget, &Camera),
    colormap_blend: bool,
    ground: Option<(&GroundLayer, u32)>,
) -> Result<()> {
    let rec = commands.begin()?;
    record_visible(renderer, rec, view, colormap_blend, ground)?;
    commands.submit_and_wait(&[])?;
    Ok(())
}

/// The passes of a flythrough frame, timed separately: uploads, feedback, compaction,
/// visible, and the prefetch pass (recorded between the compaction and the visible pass).
pub(crate) const TIMED_PASSES: usize = 5;

/// The index of the prefetch pass among the [`TIMED_PASSES`].
pub(crate) const PREFETCH_PASS: usize = 4;

/// GPU milliseconds per frame of each timed pass.
#[derive(Debug, serde::Serialize)]
pub(crate) struct GpuPassMs {
    /// Copies of the cycle's mips and the texture table into the cache.
    pub(crate) uploads: Stats,
    /// Depth pre-pass and feedback pass (paper §3.2), without their culling.
    pub(crate) feedback: Stats,
    /// Compaction of the mesh feedback and its read-back copy (paper §3.3).
    pub(crate) compaction: Stats,
    /// The visible pass and its image copy, without its culling.
    pub(crate) visible: Stats,
    /// The prefetch pass (`--prefetch`): a second depth pre-pass and feedback pass, from
    /// where the camera will be, and its compaction; 0 ms without one.
    pub(crate) prefetch: Stats,
    /// GPU culling for the feedback and visible passes (tests, draw compaction, depth
    /// copies and pyramids); null with `--culling off`.
    pub(crate) cull: Option<Stats>,
}

/// Per-pass GPU timestamps and culling statistics of each frame slot, read once the
/// slot's frame completed.
pub(crate) struct PassTimes {
    pub(crate) timer: GpuTimer,
    /// Whether the slot's last frame wrote timestamps not yet read.
    pub(crate) written: Vec<bool>,
    pub(crate) samples: [Vec<f64>; TIMED_PASSES],
    cull_ms: Vec<f64>,
    /// What each completed frame's culling drew (empty with `--culling off`).
    pub(crate) culled: Vec<CullStats>,
}

impl PassTimes {
    pub(crate) fn new(device: &Arc<Device>, frames_in_flight: u32) -> Result<Self> {
        Ok(Self {
            timer: GpuTimer::new(device, frames_in_flight * TIMED_PASSES as u32)?,
            written: vec![false; frames_in_flight as usize],
            samples: Default::default(),
            cull_ms: Vec::new(),
            culled: Vec::new(),
        })
    }

    pub(crate) fn query(slot: u32, pass: usize) -> u32 {
        slot * TIMED_PASSES as u32 + pass as u32
    }

    pub(crate) fn begin(&self, cmd: Recording<'_>, slot: u32, pass: usize) {
        self.timer.begin(cmd, Self::query(slot, pass));
    }

    pub(crate) fn end(&mut self, cmd: Recording<'_>, slot: u32, pass: usize) {
        self.timer.end(cmd, Self::query(slot, pass));
        if pass + 1 == TIMED_PASSES {
            self.written[slot as usize] = true;
        }
    }

    /// Reads `slot`'s timestamps and `renderer`'s culling statistics; its frame must have
    /// completed. The culling the feedback and visible passes record is moved out of
    /// their times into `cull`.
    pub(crate) fn collect(&mut self, slot: u32, renderer: &CityRenderer) -> Result<()> {
        if !std::mem::take(&mut self.written[slot as usize]) {
            return Ok(());
        }
        let mut times = [None; TIMED_PASSES];
        for (pass, time) in times.iter_mut().enumerate() {
            *time = self.timer.read_ms(Self::query(slot, pass))?;
        }
        if let Some(stats) = renderer.cull_stats(slot)? {
            self.culled.push(stats);
            if let Some([feedback, visible]) = stats.cull_ms {
                times[1] = times[1].map(|t| (t - feedback).max(0.0));
                times[3] = times[3].map(|t| (t - visible).max(0.0));
                self.cull_ms.push(feedback + visible);
            }
        }
        for (samples, time) in self.samples.iter_mut().zip(times) {
            samples.extend(time);
        }
        Ok(())
    }

    pub(crate) fn finish(&mut self, renderer: &CityRenderer) -> Result<Option<GpuPassMs>> {
        for slot in 0..self.written.len() as u32 {
            self.collect(slot, renderer)?;
        }
        if !self.timer.supported() {
            return Ok(None);
        }
        let [uploads, feedback, compaction, visible, prefetch] =
            std::mem::take(&mut self.samples).map(|s| Stats::from_samples(&s));
        Ok(Some(GpuPassMs {
            uploads,
            feedback,
            compaction,
            visible,
            prefetch,
            cull: renderer.culling().then(|| Stats::from_samples(&self.cull_ms)),
        }))
    }
}
