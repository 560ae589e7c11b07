//! Algorithm 1 glue: the dataset as the loader's [`MipSource`], an upload
//! queue as its [`MipSink`], and the per-frame step that turns compacted
//! feedback into a loading task and loaded mips into cache uploads.
//!
//! Threading: the loader runs its cycle on a rayon worker and only reads
//! files and fills the queue; every Vulkan call (staging into the cache,
//! binding, copying) happens on the render thread in [`Streamer::apply`].

use std::sync::{Arc, Mutex};

use citystream_cache::geometry::cacheable_mip_count;
use citystream_cache::TexelFormat;
use citystream_streaming::controller::{Decision, LoadPolicy};
use citystream_streaming::dataset::{Dataset, DatasetError, TextureFormat};
use citystream_streaming::loader::{Loader, LoaderOptions, LoaderTotals};
use citystream_streaming::records::{prepare, MeshMetaData};
use citystream_streaming::source::{MipSink, MipSource, SinkError, SourceError, StagedMip};
use citystream_streaming::states::{MipChain, TextureStates};

use crate::commands::CommandContext;
use crate::error::{EngineError, Result};
use crate::gpu_types::{FeedbackEntry, FEEDBACK_MIP_ONE, FEEDBACK_WEIGHT_ONE};
use crate::texture_cache::{CycleReport, GpuTextureCache, StageOutcome};

fn texel_format(format: TextureFormat) -> TexelFormat {
    match format {
        TextureFormat::Bc1 => TexelFormat::BC1,
        _ => TexelFormat::RGBA8,
    }
}

/// The dataset's texture pack as a [`MipSource`]. The chain it reports
/// stops at the levels the cache can hold (both sides at least one texel
/// block), so the loader never asks for a level the cache would refuse.
#[derive(Debug, Clone)]
pub struct DatasetSource {
    dataset: Arc<Dataset>,
}

impl DatasetSource {
    /// Reads from `dataset`.
    pub fn new(dataset: Arc<Dataset>) -> Self {
        Self { dataset }
    }

    fn chain(&self, texture: u32) -> std::result::Result<MipChain, SourceError> {
        let info = self
            .dataset
            .textures
            .info(texture)
            .map_err(|_| SourceError::UnknownTexture { texture })?;
        let cacheable = cacheable_mip_count(&texel_format(info.format()), info.width(), info.height());
        Ok(MipChain {
            width: info.width(),
            height: info.height(),
            mip_count: info.mip_count().min(cacheable).max(1),
        })
    }
}

fn source_error(texture: u32, level: u32, error: DatasetError) -> SourceError {
    match error {
        DatasetError::Io { source, .. } => SourceError::Io { texture, level, source },
        other => SourceError::Other {
            texture,
            reason: other.to_string(),
        },
    }
}

impl MipSource for DatasetSource {
    fn mip_chain(&self, texture: u32) -> std::result::Result<MipChain, SourceError> {
        self.chain(texture)
    }

    fn mip_len(&self, texture: u32, level: u32) -> std::result::Result<u64, SourceError> {
        let chain = self.chain(texture)?;
        if level >= chain.mip_count {
            return Err(SourceError::UnknownLevel {
                texture,
                level,
                mip_count: chain.mip_count,
            });
        }
        let info = self
            .dataset
            .textures
            .info(texture)
            .map_err(|_| SourceError::UnknownTexture { texture })?;
        Ok(info.mip_len(level))
    }

    fn read_mip(&self, texture: u32, level: u32, buf: &mut [u8]) -> std::result::Result<(), SourceError> {
        let expected = self.mip_len(texture, level)?;
        if buf.len() as u64 != expected {
            return Err(SourceError::LengthMismatch {
                texture,
                level,
                expected,
                got: buf.len() as u64,
            });
        }
        self.dataset
            .textures
            .read_mip_into(texture, level, buf)
            .map(|_| ())
            .map_err(|e| source_error(texture, level, e))
    }
}

/// Loaded mips waiting for the render thread.
#[derive(Debug, Default)]
pub struct UploadQueue {
    staged: Mutex<Vec<StagedMip>>,
}

impl UploadQueue {
    fn take(&self) -> Vec<StagedMip> {
        std::mem::take(&mut *self.staged.lock().unwrap_or_else(|e| e.into_inner()))
    }
}

/// The loader's sink: a shared handle on the upload queue.
#[derive(Debug, Clone, Default)]
pub struct QueueSink(Arc<UploadQueue>);

impl MipSink for QueueSink {
    fn stage(&self, mip: StagedMip) -> std::result::Result<(), SinkError> {
        self.0.staged.lock().unwrap_or_else(|e| e.into_inner()).push(mip);
        Ok(())
    }

    fn unload(&self, _texture: u32) {
        // The cache already made the texture unsampleable when it evicted
        // it (before unbinding); nothing is left to do here.
    }
}

/// Converts compacted feedback entries to the loader's records: the level
/// wanted is the finest whole level covering the fractional one; the weight
/// is back in units of W per visible fragment (`fragment_area` visible pixels
/// per feedback fragment, see [`crate::city::FeedbackView::fragment_area`]).
pub fn records_from_feedback(entries: &[FeedbackEntry], fragment_area: f32) -> Vec<MeshMetaData> {
    entries
        .iter()
        .map(|e| MeshMetaData {
            mip_level: (e.mip as f32 / FEEDBACK_MIP_ONE).floor() as u32,
            weight: (e.weight as f32 / FEEDBACK_WEIGHT_ONE * fragment_area).round() as u32,
            mesh_id: e.mesh_id,
        })
        .collect()
}

/// The compaction threshold in the feedback's fixed-point units for a τ in
/// W per visible fragment.
pub fn feedback_tau(tau: u32, fragment_area: f32) -> u32 {
    (tau as f32 * FEEDBACK_WEIGHT_ONE / fragment_area.max(1e-6)).floor() as u32
}

/// What one [`Streamer::apply`] did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ApplyReport {
    /// The cache cycle.
    pub cache: CycleReport,
    /// Mips the cache refused (their textures are loaded again later).
    pub refused: u32,
}

/// The loader, its upload queue and the policy, for one dataset.
pub struct Streamer {
    dataset: Arc<Dataset>,
    loader: Loader<DatasetSource, QueueSink>,
    queue: Arc<UploadQueue>,
    states: Arc<TextureStates>,
    policy: Box<dyn LoadPolicy>,
    tau: u32,
    fragment_area: f32,
}

impl std::fmt::Debug for Streamer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Streamer").field("tau", &self.tau).finish()
    }
}

impl Streamer {
    /// A streamer over `dataset` with `policy`; records lighter than `tau`
    /// (W per visible fragment) are dropped; each feedback fragment stands for
    /// `fragment_area` visible ones.
    pub fn new(
        dataset: Arc<Dataset>,
        policy: Box<dyn LoadPolicy>,
        tau: u32,
        fragment_area: f32,
        options: LoaderOptions,
    ) -> Result<Self> {
        let queue = Arc::new(UploadQueue::default());
        let mesh_textures: Vec<u32> = dataset.scene.meshes.iter().map(|m| m.texture).collect();
        let texture_count = dataset.textures.len() as usize;
        let states = Arc::new(TextureStates::new(texture_count));
        let loader = Loader::with_states(
            DatasetSource::new(Arc::clone(&dataset)),
            QueueSink(Arc::clone(&queue)),
            mesh_textures,
            Arc::clone(&states),
            options,
        )
        .map_err(|e| EngineError::InvalidRequest(format!("building the loader: {e}")))?;
        Ok(Self {
            dataset,
            loader,
            queue,
            states,
            policy,
            tau,
            fragment_area,
        })
    }

    /// The controller step with the measured frame latency (ms).
    pub fn update_policy(&mut self, frame_ms: f64) -> Decision {
        self.policy.update(frame_ms)
    }

    /// The policy, for telemetry.
    pub fn policy(&self) -> &dyn LoadPolicy {
        self.policy.as_ref()
    }

    /// Whether a loading task is running (then feedback is not read back).
    pub fn is_streaming(&self) -> bool {
        self.loader.is_streaming()
    }

    /// Starts a loading task from compacted feedback, unless one runs.
    /// Returns whether it started.
    pub fn start_cycle(&self, entries: &[FeedbackEntry], decision: Decision) -> bool {
        let records = prepare(records_from_feedback(entries, self.fragment_area), self.tau);
        self.loader.try_spawn(records, decision)
    }

    /// Runs a loading task on this thread (reproducible runs); `None` if one is running.
    pub fn run_cycle_now(&self, entries: &[FeedbackEntry], decision: Decision) -> bool {
        let records = prepare(records_from_feedback(entries, self.fragment_area), self.tau);
        self.loader.run_cycle(&records, decision).is_some()
    }

    /// Loader totals so far.
    pub fn totals(&self) -> LoaderTotals {
        self.loader.totals()
    }

    /// Moves every loaded mip into the cache and runs its cycle. Mips the
    /// cache cannot take now, and textures it evicted, are invalidated in the
    /// streaming states so Algorithm 1 loads them again later. Call only when
    /// no submitted frame still reads the cache (see [`GpuTextureCache`]).
    pub fn apply(&self, cache: &mut GpuTextureCache, commands: &mut CommandContext) -> Result<ApplyReport> {
        let mut refused = 0;
        // Loader workers stage in whatever order they finish; packing in a
        // fixed order keeps cache placement, and so runs, reproducible.
        let mut staged = self.queue.take();
        staged.sort_unstable_by_key(|m| (m.texture, std::cmp::Reverse(m.level)));
        for mip in staged {
            let info = self
                .dataset
                .textures
                .info(mip.texture)
                .map_err(|e| EngineError::InvalidRequest(e.to_string()))?;
            let outcome = cache.stage(
                mip.texture,
                info.format(),
                info.width(),
                info.height(),
                mip.level,
                &mip.bytes,
            );
            let accepted = matches!(outcome, Ok(StageOutcome::Staged { .. }));
            if !accepted {
                refused += 1;
                let _ = self.states.invalidate(mip.texture);
            }
        }
        let report = cache.finish_cycle(commands)?;
        for &texture in &report.invalidated_textures {
            let _ = self.states.invalidate(texture);
        }
        Ok(ApplyReport { cache: report, refused })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn feedback_weights_become_visible_fragment_weights() {
        // One feedback fragment covers a 4x4 block of visible pixels (area 16).
        // A weight of 10 W in fixed point (80) stands for 160 W of visible fragments.
        let entries = [FeedbackEntry {
            mip: 3 * 256 + 200, // level 3.78: the finest whole level covering it is 3
            weight: 80,
            mesh_id: 7,
        }];
        let records = records_from_feedback(&entries, 16.0);
        assert_eq!(
            records,
            vec![MeshMetaData {
                mip_level: 3,
                weight: 160,
                mesh_id: 7
            }]
        );
        // τ = 150 W per visible fragment is 150 * 8 / 16 = 75 in feedback fixed point:
        // the entry above (80) passes on the GPU and its record (160) on the host.
        assert_eq!(feedback_tau(150, 16.0), 75);
        assert_eq!(feedback_tau(150, 1.0), 1200);
        // A degenerate area never divides by zero.
        assert!(feedback_tau(150, 0.0) > 0);
    }
}
