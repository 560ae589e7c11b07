//! The embeddable streaming module: Algorithm 1 of the paper, one frame at
//! a time, with frames in flight.
//!
//! A host renderer owns its frame loop, its passes and its submissions;
//! [`TextureStreamer`] owns the rest: the sparse texture cache, the feedback
//! buffers, the loader over any [`MipSource`], the load policy and a frame
//! timeline semaphore. Per frame the host calls, in order:
//!
//! 1. [`TextureStreamer::begin_frame`]: waits only if the frame that used
//!    this frame's slot `frames_in_flight` frames ago is still running (the
//!    usual frames-in-flight throttle; counted in [`Frame::cpu_wait`]),
//!    retires what the GPU finished (read-back slots, staging space,
//!    one-off buffers), hands the newest completed feedback to the loader
//!    when no loading task runs, packs what the loader staged into the
//!    cache and submits the sparse binds (which wait on the GPU, not the
//!    host, for frames that may still sample evicted blocks).
//! 2. [`TextureStreamer::record_uploads`] into the frame's command buffer
//!    (a [`Recording`], the frame's [`Frame`] token beside it),
//!    before any pass that samples streamed textures: the copies of new mips
//!    and the table update.
//! 3. The host's feedback pass (writing [`TextureStreamer::compactor`]'s
//!    per-mesh array), then [`TextureStreamer::record_feedback_resolve`]:
//!    compaction into this frame's read-back slot.
//! 4. The host's visible passes.
//! 5. [`TextureStreamer::end_frame`], consuming the token, with the latency the host
//!    measured for its previous frame: the controller step (Eq. 4–7). It returns the
//!    [`FrameSubmit`] waits and signal the host's submission of this frame
//!    must carry.
//!
//! A host with another way of knowing what the view needs (the texture-atlas tree's §6
//! paging, `citystream_streaming::atlas_tree`) hands the loader its records with
//! [`TextureStreamer::set_host_records`] before `begin_frame` instead: that frame's records
//! replace the feedback, and steps 3's pass and resolve may be left out.
//!
//! Read-backs are consumed one or more frames after they were recorded:
//! as soon as their frame completed, or, with
//! [`StreamConfig::deterministic`], exactly `frames_in_flight` frames later
//! with the loading cycle run on the calling thread, so that fixed-clock
//! runs repeat exactly.
//!
//! Threading: the streamer is used from one thread (the render thread); its
//! loader runs on rayon workers and touches no Vulkan object.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use ash::vk;
use citystream_dataset::TextureFormat;
use citystream_streaming::controller::{Decision, LoadPolicy};
use citystream_streaming::disk_model::ModelledReads;
use citystream_streaming::loader::{Loader, LoaderOptions, LoaderTotals, PlanOrder, TextureFailure};
use citystream_streaming::records::{prepare, MeshMetaData};
use citystream_streaming::residency::planner::BudgetPressure;
use citystream_streaming::residency::{AdmissionGate, NeedTable};
use citystream_streaming::shortfall::TextureShortfall;
use citystream_streaming::source::{MipSink, MipSource, SinkError, SourceError, StagedMip};
use citystream_streaming::states::{MipChain, TextureStates};

use crate::commands::{CommandContext, Recording, SemaphoreSignal, SemaphoreWait, TimelineSemaphore};
use crate::device::Device;
#[cfg(doc)]
use crate::device::TextureBacking;
use crate::error::{EngineError, Result};
use crate::feedback::{CompactedFeedback, FeedbackCompactor};
use crate::gpu_types::{FeedbackEntry, BINDING_FEEDBACK_MESHES};
use crate::pipeline::{DescriptorResource, Filtering};
use crate::texture_cache::{CacheLayers, CycleReport, Eviction, GpuCacheConfig, GpuTextureCache, CACHE_FORMATS};

mod descriptors;
mod feedback_records;
mod frame;
mod immediate;
pub mod prefetch;
mod residency;
mod telemetry;

pub use descriptors::StreamDescriptors;
pub use feedback_records::{feedback_tau, records_from_feedback};
use frame::NEXT_STREAMER_ID;
pub use frame::{Frame, FrameSubmit};
pub use telemetry::ServedLevels;

/// Per cache format, how many textures of each extent the source holds.
fn texture_extents<S: MipSource + ?Sized>(source: &S) -> Result<Vec<Vec<(u32, u64)>>> {
    let mut counts: Vec<std::collections::BTreeMap<u32, u64>> = vec![Default::default(); CACHE_FORMATS.len()];
    for texture in 0..source.texture_count() {
        let format = source.texture_format(texture).map_err(source_failure)?;
        let Some(format) = GpuTextureCache::format_index(format) else {
            continue; // Refused with a typed error when it is staged.
        };
        let chain = source.mip_chain(texture).map_err(source_failure)?;
        let extent = chain.width.max(chain.height).max(1).next_power_of_two();
        *counts[format].entry(extent).or_default() += 1;
    }
    Ok(counts.into_iter().map(|c| c.into_iter().collect()).collect())
}

/// Loaded mips waiting for the render thread.
#[derive(Debug, Default)]
struct UploadQueue {
    staged: Mutex<Vec<StagedMip>>,
    /// Mips read on a modelled disk, each with its completion from its cycle's start.
    modelled: Mutex<Vec<(Duration, StagedMip)>>,
}

impl UploadQueue {
    fn take(&self) -> Vec<StagedMip> {
        std::mem::take(&mut *self.staged.lock().unwrap_or_else(|e| e.into_inner()))
    }

    fn take_modelled(&self) -> Vec<(Duration, StagedMip)> {
        std::mem::take(&mut *self.modelled.lock().unwrap_or_else(|e| e.into_inner()))
    }
}

/// The loader's sink: a shared handle on the upload queue.
#[derive(Debug, Clone, Default)]
struct QueueSink(Arc<UploadQueue>);

impl MipSink for QueueSink {
    fn stage(&self, mip: StagedMip) -> std::result::Result<(), SinkError> {
        self.0.staged.lock().unwrap_or_else(|e| e.into_inner()).push(mip);
        Ok(())
    }

    fn stage_after(&self, mip: StagedMip, done: Duration) -> std::result::Result<(), SinkError> {
        self.0
            .modelled
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push((done, mip));
        Ok(())
    }

    fn unload(&self, _texture: u32) {
        // The cache already made the texture unsampleable when it evicted
        // it (before unbinding); nothing is left to do here.
    }
}

/// How a [`TextureStreamer`] is built. Each field's documentation gives its
/// [`Default`] value.
///
/// The fields mean the same for both backings ([`TextureBacking`], read from the
/// [`Device`]) except [`memory_budget_bytes`](Self::memory_budget_bytes): texture
/// arrays spend it on whole layers when the streamer is made, and refuse a budget
/// below one layer's full mip chain per format.
#[derive(Clone, Debug)]
pub struct StreamConfig {
    /// Frames the host may have submitted and not yet completed (at least 1). Default: 2.
    pub frames_in_flight: u32,
    /// Side of every cache array layer in texels (a power of two). Default: 2048.
    pub layer_size: u32,
    /// Layers of the one cache image per format; `None` derives images and
    /// layers from the textures each format must place, the memory budget
    /// and the device ([`citystream_cache::derive_image_layers`]). Default: `None`.
    pub layer_count: Option<u32>,
    /// A lower layer limit per image than the device's
    /// `maxImageArrayLayers` (hosts sharing the device, tests of small
    /// devices); a format needing more layers gets more images. Default: `None`.
    pub max_layers: Option<u32>,
    /// How memory is freed at the budget. Default: [`Eviction::View`].
    pub eviction: Eviction,
    /// Bytes of device memory the cache may hold for texels. Default: 512 MiB (`512 << 20`).
    ///
    /// - Sparse images ([`TextureBacking::Sparse`]): the blocks bound at once (parked
    ///   ones included), bound as levels load and unbound as they are dropped.
    /// - Texture arrays ([`TextureBacking::Arrays`]): every layer is allocated with its
    ///   full mip chain (`layer_size`² down to 1×1) when the streamer is made, as many
    ///   layers as this budget (capped at half the device's largest device-local heap)
    ///   holds, at most those the textures need. Each format the source has textures of
    ///   needs at least one layer, so a budget below the sum over those formats of one
    ///   layer's chain, as the device's memory requirements size it, makes
    ///   [`TextureStreamer::new`] fail with [`EngineError::InvalidRequest`]; at 2048²
    ///   layers that is about 22.4 MB for RGBA8, 5.6 MB for BC3 or BC7 and 2.8 MB for
    ///   BC1. Fixed [`layer_count`](Self::layer_count) layers needing more than the
    ///   budget are refused the same way.
    pub memory_budget_bytes: u64,
    /// Blocks per device-memory chunk of the block pool. Default: 256.
    pub blocks_per_chunk: u32,
    /// Bytes of the host-visible staging ring uploads go through. Default: 16 MiB (`16 << 20`).
    pub staging_bytes: u64,
    /// Filtering of the cache sampler. Default: [`Filtering::BilinearNearestLevel`].
    pub filtering: Filtering,
    /// Compacted feedback entries per frame; `None`: one per mesh. Default: `None`.
    pub feedback_capacity: Option<u32>,
    /// τ: records lighter than this (W per visible fragment) are not loaded.
    /// Default: [`DEFAULT_WEIGHT_CUTOFF`](citystream_streaming::records::DEFAULT_WEIGHT_CUTOFF) (150).
    pub weight_cutoff: u32,
    /// Visible pixels one feedback fragment stands for
    /// ([`crate::city::FeedbackView::fragment_area`]). Default: 1.0 (a feedback
    /// pass at the visible resolution).
    pub fragment_area: f32,
    /// Options of the loader. Default: [`LoaderOptions::default`] (16 ms load time per
    /// cycle, 4096 records per planning chunk, 3 read attempts, 2 ms first retry backoff).
    pub loader: LoaderOptions,
    /// Reproducible runs: each frame's feedback is consumed exactly
    /// `frames_in_flight` frames later and the loading cycle runs on the
    /// calling thread, so results do not depend on GPU or disk timing: two runs of the
    /// same inputs load the same mips in the same frames. Without a disk model the
    /// loader's wall-clock limit ([`LoaderOptions::load_time`]) does not apply (a cycle
    /// loads what its load size allows, however long the reads take). Default: `false`.
    /// With a disk model ([`LoaderOptions::disk`], deterministic runs only) a cycle's
    /// mips reach the cache when the host's modelled clock
    /// ([`TextureStreamer::set_modelled_time`]) passes their reads' completion, and the
    /// next cycle starts after that: a cycle spans the frames its reads take.
    pub deterministic: bool,
    /// The host records a second feedback pass per frame, from where the camera will be
    /// ([`TextureStreamer::record_prefetch_resolve`]); its records join each loading
    /// cycle after the view's. Doubles the feedback read-back slots. Default: `false`.
    pub prefetch: bool,
}

/// The values each field's documentation states:
///
/// ```
/// # use std::time::Duration;
/// # use citystream_engine::pipeline::Filtering;
/// # use citystream_engine::stream::StreamConfig;
/// # use citystream_engine::texture_cache::Eviction;
/// let config = StreamConfig::default();
/// assert_eq!(config.frames_in_flight, 2);
/// assert_eq!(config.layer_size, 2048);
/// assert_eq!(config.layer_count, None);
/// assert_eq!(config.max_layers, None);
/// assert_eq!(config.eviction, Eviction::View);
/// assert_eq!(config.memory_budget_bytes, 512 << 20);
/// assert_eq!(config.blocks_per_chunk, 256);
/// assert_eq!(config.staging_bytes, 16 << 20);
/// assert_eq!(config.filtering, Filtering::BilinearNearestLevel);
/// assert_eq!(config.feedback_capacity, None);
/// assert_eq!(config.weight_cutoff, 150);
/// assert_eq!(config.fragment_area, 1.0);
/// assert_eq!(config.loader.load_time, Duration::from_millis(16));
/// assert_eq!(config.loader.plan_chunk, 4096);
/// assert_eq!(config.loader.read_attempts, 3);
/// assert_eq!(config.loader.retry_backoff, Duration::from_millis(2));
/// assert!(!config.deterministic);
/// assert!(!config.prefetch);
/// ```
impl Default for StreamConfig {
    fn default() -> Self {
        Self {
            frames_in_flight: 2,
            layer_size: 2048,
            layer_count: None,
            max_layers: None,
            eviction: Eviction::View,
            memory_budget_bytes: 512 << 20,
            blocks_per_chunk: 256,
            staging_bytes: 16 << 20,
            filtering: Filtering::BilinearNearestLevel,
            feedback_capacity: None,
            weight_cutoff: citystream_streaming::records::DEFAULT_WEIGHT_CUTOFF,
            fragment_area: 1.0,
            loader: LoaderOptions::default(),
            deterministic: false,
            prefetch: false,
        }
    }
}

/// What the last [`TextureStreamer::begin_frame`] did to residency.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ResidencyCycle {
    /// `(texture, level)` staged for upload.
    pub staged: Vec<(u32, u32)>,
    /// `(texture, level)` dropped to make room.
    pub dropped: Vec<(u32, u32)>,
    /// Layers evicted to place textures (with [`Eviction::Ring`], those the
    /// ring reused or the budget took).
    pub evicted_layers: u32,
    /// Loaded mips refused because the budget had no room for them.
    pub refused_for_room: u32,
}

/// Running residency counts of a streamer.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ResidencyTotals {
    /// Levels dropped to make room.
    pub dropped_levels: u64,
    /// Bytes of those levels.
    pub dropped_bytes: u64,
    /// Layers evicted to place textures (with [`Eviction::Ring`], those the
    /// ring reused or the budget took).
    pub evicted_layers: u64,
    /// Loaded mips refused for room.
    pub refused_for_room: u64,
    /// Loads the admission gate declined.
    pub declined_loads: u64,
    /// Frames that were over budget.
    pub frames_over_budget: u64,
    /// Bytes of the distinct `(texture, level)` pairs uploaded, each once.
    pub unique_bytes_uploaded: u64,
}

#[derive(Clone, Copy, Debug, Default)]
struct FrameSlot {
    /// Timeline value of the frame that last used the slot (0: none).
    value: u64,
    /// The cache cycle that frame carried.
    ticket: u64,
    /// That frame recorded a feedback resolve into the slot.
    resolved: bool,
    /// Its compaction is meant for the loader and not consumed yet.
    unread: bool,
    /// That frame recorded a prefetch resolve into the slot's prefetch half.
    prefetch_resolved: bool,
}

/// Algorithm 1 for a host renderer; see the module docs for the per-frame calls.
pub struct TextureStreamer<S: MipSource + 'static> {
    device: Arc<Device>,
    cache: GpuTextureCache,
    compactor: FeedbackCompactor,
    loader: Loader<S, QueueSink>,
    queue: Arc<UploadQueue>,
    states: Arc<TextureStates>,
    policy: Box<dyn LoadPolicy>,
    decision: Decision,
    frames: TimelineSemaphore,
    slots: Vec<FrameSlot>,
    /// Frames begun so far; the frame being recorded has value `begun`.
    begun: u64,
    /// A [`Frame`] was begun and not yet ended.
    in_frame: bool,
    /// Matches the [`Frame`]s this streamer hands out.
    id: u64,
    tau: u32,
    gpu_tau: u32,
    /// The compaction's threshold: 0 (every seen mesh) when eviction ranks
    /// by the view and the read-back holds every mesh, else `gpu_tau`.
    compact_tau: u32,
    fragment_area: f32,
    deterministic: bool,
    /// The host records a prefetch pass ([`StreamConfig::prefetch`]).
    prefetch: bool,
    latest_feedback: Option<(u64, Vec<FeedbackEntry>)>,
    /// Records the host set for the next `begin_frame`, in place of the feedback.
    host_records: Option<Vec<MeshMetaData>>,
    /// Bytes the host uploaded outside the cache since the last loading cycle started.
    host_upload_bytes: u64,
    eviction: Eviction,
    needs: NeedTable,
    gate: Arc<AdmissionGate>,
    /// Loaded mips whose memory waits for the next unbind batch.
    deferred: Vec<StagedMip>,
    /// With a disk model: the mips of the cycle whose reads are in flight.
    modelled_reads: Option<ModelledReads>,
    /// The host's modelled clock ([`TextureStreamer::set_modelled_time`]).
    modelled_now: Duration,
    totals: ResidencyTotals,
    last_cycle: ResidencyCycle,
    pressure: BudgetPressure,
}

impl<S: MipSource> std::fmt::Debug for TextureStreamer<S> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TextureStreamer")
            .field("frames_in_flight", &self.slots.len())
            .field("begun", &self.begun)
            .field("tau", &self.tau)
            .finish()
    }
}

impl<S: MipSource + 'static> TextureStreamer<S> {
    /// A streamer over `source`, whose meshes use `mesh_textures[mesh]`;
    /// `colormap` holds one RGBA8 colour per texture (Eq. 8).
    pub fn new(
        device: &Arc<Device>,
        source: S,
        mesh_textures: Vec<u32>,
        colormap: &[[u8; 4]],
        policy: Box<dyn LoadPolicy>,
        config: &StreamConfig,
    ) -> Result<Self> {
        if config.frames_in_flight == 0 {
            return Err(EngineError::InvalidRequest(
                "frames in flight must be at least 1".into(),
            ));
        }
        if let Some(disk) = config.loader.disk {
            if !config.deterministic {
                return Err(EngineError::InvalidRequest(
                    "a disk model times the reads of deterministic runs; without one the reads take what the disk takes"
                        .into(),
                ));
            }
            disk.validate()
                .map_err(|e| EngineError::InvalidRequest(e.to_string()))?;
        }
        let texture_count = source.texture_count();
        let mesh_count = u32::try_from(mesh_textures.len())
            .ok()
            .filter(|&n| n > 0)
            .ok_or_else(|| {
                EngineError::InvalidRequest(format!(
                    "{} meshes: the streamer needs between 1 and 2^32 - 1",
                    mesh_textures.len()
                ))
            })?;
        let extents = texture_extents(&source)?;
        // An image for each format the source has textures of.
        let formats: Vec<TextureFormat> = CACHE_FORMATS
            .iter()
            .zip(&extents)
            .filter(|(_, counts)| !counts.is_empty())
            .map(|((format, _, _), _)| *format)
            .collect();
        let formats = if formats.is_empty() {
            vec![TextureFormat::Bc1]
        } else {
            formats
        };
        let layers = match config.layer_count {
            Some(count) => CacheLayers::Fixed(count),
            None => CacheLayers::Derived {
                extents,
                max_layers: config.max_layers,
            },
        };
        let mut commands = CommandContext::new(device, "texture streamer setup")?;
        let cache = GpuTextureCache::new(
            device,
            &mut commands,
            &GpuCacheConfig {
                layer_size: config.layer_size,
                layers,
                formats,
                eviction: config.eviction,
                memory_budget_bytes: config.memory_budget_bytes,
                virtual_budget_bytes: None,
                blocks_per_chunk: config.blocks_per_chunk,
                texture_count,
                filtering: config.filtering,
                staging_bytes: config.staging_bytes,
            },
            colormap,
        )?;
        let feedback_capacity = config.feedback_capacity.unwrap_or(mesh_count);
        let gpu_tau = feedback_tau(config.weight_cutoff, config.fragment_area);
        // With prefetch, slots `frames_in_flight..2 × frames_in_flight` hold the prefetch
        // pass's compaction of the frame in the slot `frames_in_flight` below.
        let compactor = FeedbackCompactor::with_slots(
            device,
            &mut commands,
            mesh_count,
            feedback_capacity,
            config.frames_in_flight * if config.prefetch { 2 } else { 1 },
        )?;
        let queue = Arc::new(UploadQueue::default());
        let states = Arc::new(TextureStates::new(texture_count as usize));
        // Deterministic without a disk model: no wall-clock limit on a cycle's reads, which
        // would make what a cycle loads depend on the machine (the load size bounds it).
        let loader_options = if config.deterministic && config.loader.disk.is_none() {
            LoaderOptions {
                load_time: Duration::MAX,
                ..config.loader
            }
        } else {
            config.loader
        };
        let loader = Loader::with_states(
            source,
            QueueSink(Arc::clone(&queue)),
            mesh_textures,
            Arc::clone(&states),
            loader_options,
        )
        .map_err(|e| EngineError::InvalidRequest(format!("building the loader: {e}")))?;
        let gate = Arc::new(AdmissionGate::new());
        if config.eviction == Eviction::View {
            loader.set_admission_gate(Arc::clone(&gate));
        }
        Ok(Self {
            device: Arc::clone(device),
            cache,
            compactor,
            loader,
            queue,
            states,
            policy,
            decision: Decision::new(0, 0.0),
            frames: TimelineSemaphore::new(device, 0, "streamed frames")?,
            slots: vec![FrameSlot::default(); config.frames_in_flight as usize],
            begun: 0,
            in_frame: false,
            id: NEXT_STREAMER_ID.fetch_add(1, std::sync::atomic::Ordering::Relaxed),
            tau: config.weight_cutoff,
            gpu_tau,
            compact_tau: if config.eviction == Eviction::View && feedback_capacity >= mesh_count {
                0
            } else {
                gpu_tau
            },
            fragment_area: config.fragment_area,
            deterministic: config.deterministic,
            prefetch: config.prefetch,
            latest_feedback: None,
            host_records: None,
            host_upload_bytes: 0,
            eviction: config.eviction,
            needs: NeedTable::new(texture_count as usize),
            gate,
            deferred: Vec::new(),
            modelled_reads: config.loader.disk.map(|_| ModelledReads::new()),
            modelled_now: Duration::ZERO,
            totals: ResidencyTotals::default(),
            last_cycle: ResidencyCycle::default(),
            pressure: BudgetPressure::default(),
        })
    }

    /// Running residency counts.
    pub fn residency_totals(&self) -> ResidencyTotals {
        ResidencyTotals {
            declined_loads: self.gate.declined(),
            dropped_bytes: self.cache.dropped_bytes(),
            unique_bytes_uploaded: self.cache.unique_bytes_uploaded(),
            ..self.totals
        }
    }

    /// What the last `begin_frame` staged, dropped and refused.
    pub fn last_cycle(&self) -> &ResidencyCycle {
        &self.last_cycle
    }

    /// The latest feedback per texture, as eviction ranks it.
    pub fn needs(&self) -> &NeedTable {
        &self.needs
    }

    /// Frames in flight.
    pub fn frames_in_flight(&self) -> u32 {
        self.slots.len() as u32
    }

    /// The texture cache, for the engine's own passes ([`crate::city::CityRenderer`],
    /// [`crate::atlas_tree::AtlasTreeRenderer`]) and tests; a host reads
    /// [`served_levels`](Self::served_levels), [`texture_data`](Self::texture_data)
    /// and [`bound_bytes`](Self::bound_bytes) instead.
    pub fn cache(&self) -> &GpuTextureCache {
        &self.cache
    }

    /// The feedback buffers, for the engine's own passes; a host's feedback
    /// pass reaches them through [`descriptor_bindings`](Self::descriptor_bindings).
    pub fn compactor(&self) -> &FeedbackCompactor {
        &self.compactor
    }

    /// Everything a host's shaders reach through `citystream_host.glsl`, for
    /// the host's own descriptor set (at the set index it gives
    /// `CITYSTREAM_SET`): binding number, descriptor type and resource. The
    /// resources live as long as the streamer.
    pub fn descriptor_bindings(&self) -> Vec<(u32, vk::DescriptorType, DescriptorResource)> {
        let mut bindings: Vec<(u32, DescriptorResource)> = self.cache.descriptors().to_vec();
        bindings.push((
            BINDING_FEEDBACK_MESHES,
            DescriptorResource::StorageBuffer(self.compactor.mesh_feedback_buffer()),
        ));
        bindings
            .into_iter()
            .map(|(binding, resource)| (binding, resource.descriptor_type(), resource))
            .collect()
    }

    /// [`descriptor_bindings`](Self::descriptor_bindings) as a ready descriptor
    /// set for the host's pipelines, every binding visible to `stages` (those
    /// whose shaders include `citystream_host.glsl`, usually `FRAGMENT`).
    pub fn create_descriptors(&self, stages: vk::ShaderStageFlags) -> Result<StreamDescriptors> {
        StreamDescriptors::new(&self.device, &self.descriptor_bindings(), stages)
    }

    /// The load policy, for telemetry.
    pub fn policy(&self) -> &dyn LoadPolicy {
        self.policy.as_ref()
    }

    /// The mip source.
    pub fn source(&self) -> &S {
        self.loader.source()
    }

    /// Loader totals so far.
    pub fn totals(&self) -> LoaderTotals {
        self.loader.totals()
    }

    /// The order the loader's cycles take mips in ([`LoaderOptions::order`]).
    pub fn loader_order(&self) -> PlanOrder {
        self.loader.order()
    }

    /// The most recent load failures (a bounded log, oldest first): which
    /// texture and level, and why.
    pub fn load_failures(&self) -> Vec<TextureFailure> {
        self.loader.failures()
    }

    /// Textures whose loading failed and that the loader no longer tries.
    pub fn failed_textures(&self) -> usize {
        self.loader.states().census()[3]
    }

    /// Whether a loading task is running.
    pub fn is_streaming(&self) -> bool {
        self.loader.is_streaming()
    }

    /// Waits up to `timeout` for the loading task in flight to finish, so that what it
    /// read or failed to read counts in [`totals`](Self::totals) and
    /// [`load_failures`](Self::load_failures) (its mips are not uploaded). A host calls it
    /// when a run ends: reads still waiting on a slow or silent source then end, as read or
    /// as failures, instead of going unreported. Whether no task is left running.
    pub fn finish_loading(&self, timeout: Duration) -> bool {
        let until = Instant::now() + timeout;
        while self.loader.is_streaming() {
            if Instant::now() >= until {
                return false;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        true
    }

    /// τ in the feedback's fixed point: entries at or above it are loaded.
    /// With [`Eviction::View`] the compaction keeps lighter entries too
    /// (eviction needs to know they are in view), so read-backs may list
    /// entries below it.
    pub fn gpu_tau(&self) -> u32 {
        self.gpu_tau
    }

    /// Frame timeline value the GPU has completed (frames are numbered from
    /// 1 on the timeline: frame `i` signals `i + 1`).
    pub fn completed_value(&self) -> Result<u64> {
        self.frames.value()
    }

    /// Blocks until frame `index` has completed on the GPU. Not part of the
    /// steady state: hosts call it to read back that frame's image. The
    /// frame must have been submitted (with its [`FrameSubmit::signal`]).
    pub fn wait_for_frame(&self, index: u64) -> Result<Duration> {
        let ended = self.begun - u64::from(self.in_frame);
        if index >= ended {
            return Err(EngineError::InvalidRequest(format!(
                "frame {index} has not been ended and submitted ({ended} frames so far)"
            )));
        }
        let started = Instant::now();
        self.frames.wait(index + 1)?;
        Ok(started.elapsed())
    }

    /// The compacted feedback of frame `index` if it recorded a resolve,
    /// has completed and its slot was not reused since; does not consume it.
    pub fn feedback_of(&self, index: u64) -> Result<Option<CompactedFeedback>> {
        let slot = (index % self.slots.len() as u64) as usize;
        let of_frame = &self.slots[slot];
        if of_frame.value != index + 1 || !of_frame.resolved || self.frames.value()? < index + 1 {
            return Ok(None);
        }
        self.compactor.read_back(slot as u32).map(Some)
    }

    /// The feedback most recently handed to the loader, with its frame
    /// (with [`Eviction::View`] it lists meshes lighter than τ too, which
    /// the loader skips; see [`gpu_tau`](Self::gpu_tau)).
    pub fn latest_feedback(&self) -> Option<(u64, &[FeedbackEntry])> {
        self.latest_feedback.as_ref().map(|(f, e)| (*f, e.as_slice()))
    }

    /// What the next [`begin_frame`](Self::begin_frame) hands the loader instead of the
    /// feedback: records whose mesh ids index the mesh → texture table the streamer was
    /// built with, weights as the loader's priorities (heaviest first; lighter than the
    /// weight cut-off τ are skipped) and levels as the finest each needs. Replaces records
    /// set before and not yet taken. A mesh id outside the table is refused.
    pub fn set_host_records(&mut self, records: Vec<MeshMetaData>) -> Result<()> {
        let meshes = self.loader.mesh_textures().len();
        if let Some(bad) = records.iter().find(|r| r.mesh_id as usize >= meshes) {
            return Err(EngineError::InvalidRequest(format!(
                "host record for mesh {} of a mesh table of {meshes}",
                bad.mesh_id
            )));
        }
        self.host_records = Some(records);
        Ok(())
    }

    /// Sets the host's modelled clock (time since the run started), which a disk model
    /// ([`StreamConfig::deterministic`]) times reads against: call it before each
    /// [`begin_frame`](Self::begin_frame) with the time of the frame about to begin. It
    /// never goes back: an earlier time is refused.
    pub fn set_modelled_time(&mut self, now: Duration) -> Result<()> {
        if now < self.modelled_now {
            return Err(EngineError::InvalidRequest(format!(
                "the modelled clock went back from {:?} to {now:?}",
                self.modelled_now
            )));
        }
        self.modelled_now = now;
        Ok(())
    }

    /// With a disk model, the mips read and not yet in the cache and their bytes.
    pub fn reads_in_flight(&self) -> Option<(usize, u64)> {
        self.modelled_reads
            .as_ref()
            .map(|reads| (reads.held(), reads.held_bytes()))
    }

    /// Loaded mips ready for the cache: all the loader staged, or with a disk model those
    /// whose reads completed by the modelled clock.
    fn take_loaded(&mut self) -> Vec<StagedMip> {
        match self.modelled_reads.as_mut() {
            Some(reads) => reads.release(self.modelled_now),
            None => self.queue.take(),
        }
    }

    /// Step 1 of a frame; see the module docs.
    pub fn begin_frame(&mut self) -> Result<Frame> {
        if self.in_frame {
            return Err(EngineError::InvalidRequest(
                "begin_frame called while the frame begun before was not ended with end_frame".into(),
            ));
        }
        let index = self.begun;
        let value = index + 1;
        let n = self.slots.len() as u64;
        let slot = (index % n) as usize;
        // The frames-in-flight throttle: the slot's previous frame must be done.
        let reuse = self.slots[slot].value;
        let mut completed = self.frames.value()?;
        let mut cpu_wait = Duration::ZERO;
        if completed < reuse {
            let started = Instant::now();
            self.frames.wait(reuse)?;
            cpu_wait = started.elapsed();
            completed = self.frames.value()?.max(reuse);
        }
        if let Some(ticket) = self
            .slots
            .iter()
            .filter(|s| s.value > 0 && s.value <= completed)
            .map(|s| s.ticket)
            .max()
        {
            self.cache.retire(ticket);
        }

        // Feedback for the loader: deterministic runs take exactly the
        // reused slot's; otherwise the newest completed one.
        let mut newest: Option<(u64, usize)> = None;
        for (i, s) in self.slots.iter().enumerate() {
            let eligible = s.unread
                && s.value <= completed
                && (!self.deterministic || i == slot)
                && newest.is_none_or(|(v, _)| s.value > v);
            if eligible {
                newest = Some((s.value, i));
            }
        }
        let mut loading_started = false;
        if let Some(records) = self.host_records.take() {
            // The host decided what the view needs: feedback read back meanwhile is stale.
            for s in self.slots.iter_mut().filter(|s| s.value <= completed) {
                s.unread = false;
            }
            self.needs.observe(&records, self.loader.mesh_textures());
            let records = prepare(records, self.tau);
            loading_started = self.start_loading(records, Vec::new());
        } else if let Some((feedback_value, i)) = newest {
            for s in self.slots.iter_mut().filter(|s| s.unread && s.value <= feedback_value) {
                s.unread = false;
            }
            let entries = self.compactor.read_back(i as u32)?.entries;
            // Eviction sees every mesh the view shows (below τ too: a texture
            // seen only by small meshes is still sampled, not out of view);
            // the loader sees those reaching τ, as compacted before.
            let seen = records_from_feedback(&entries, self.fragment_area);
            // Where the camera will be: compacted at τ, in the same frame's submission.
            let ahead = if self.slots[i].prefetch_resolved {
                let half = self.slots.len() as u32;
                let entries = self.compactor.read_back(half + i as u32)?.entries;
                records_from_feedback(&entries, self.fragment_area)
            } else {
                Vec::new()
            };
            // What the camera is about to see counts as seen, so that eviction keeps
            // the levels prefetched for it until it gets there.
            if ahead.is_empty() {
                self.needs.observe(&seen, self.loader.mesh_textures());
            } else {
                let both: Vec<MeshMetaData> = seen.iter().chain(&ahead).copied().collect();
                self.needs.observe(&both, self.loader.mesh_textures());
            }
            let heavy = seen
                .into_iter()
                .zip(&entries)
                .filter(|(_, entry)| entry.weight >= self.gpu_tau)
                .map(|(record, _)| record)
                .collect();
            let records = prepare(heavy, self.tau);
            loading_started = self.start_loading(records, prepare(ahead, self.tau));
            self.latest_feedback = Some((feedback_value - 1, entries));
        }
        // Pack what the loader staged, then bind.
        let (refused, over_budget) = match self.eviction {
            Eviction::Ring => self.stage_by_ring()?,
            Eviction::View => {
                let refused = self.stage_by_view()?;
                (refused, self.update_pressure(loading_started))
            }
        };
        let ticket = self.cache.prepare_cycle(Some(SemaphoreWait {
            semaphore: self.frames.raw(),
            stages: vk::PipelineStageFlags2::ALL_COMMANDS,
            value: index,
        }))?;
        self.slots[slot] = FrameSlot {
            value,
            ticket,
            resolved: false,
            unread: false,
            prefetch_resolved: false,
        };
        self.begun += 1;
        self.in_frame = true;
        Ok(Frame {
            index,
            slot: slot as u32,
            cpu_wait,
            loading_started,
            refused,
            over_budget,
            streamer: self.id,
            uploads_recorded: false,
            resolved: false,
            prefetch_resolved: false,
        })
    }

    /// Hands `records` to the loader unless a loading task still runs (Algorithm 1's
    /// gate): on this thread in deterministic runs, else on a worker. Whether a cycle ran
    /// or started.
    fn start_loading(&mut self, records: Vec<MeshMetaData>, prefetch: Vec<MeshMetaData>) -> bool {
        let now = self.modelled_now;
        if self.loader.is_streaming() || self.modelled_reads.as_ref().is_some_and(|r| r.busy(now)) {
            return false;
        }
        // One load size for everything streamed: what the host uploaded of its own since
        // the last cycle is this cycle's less.
        let decision = Decision {
            load_size_bytes: self.decision.load_size_bytes.saturating_sub(self.host_upload_bytes),
            ..self.decision
        };
        let started = if self.deterministic {
            let report = self.loader.run_cycle_with(&records, &prefetch, decision);
            if let (Some(reads), Some(report)) = (self.modelled_reads.as_mut(), report.as_ref()) {
                reads.hold_cycle(now, self.queue.take_modelled(), report.modelled_read_time);
            }
            report.is_some()
        } else {
            self.loader.try_spawn_with(records, prefetch, decision)
        };
        if started {
            // What this cycle could not absorb stays owed to the next ones.
            self.host_upload_bytes -= self.host_upload_bytes.min(self.decision.load_size_bytes);
        }
        started
    }

    /// The controller's current decision: the load size `s` and mip bias `b` of the next
    /// loading cycle (Eq. 4–7).
    pub fn decision(&self) -> Decision {
        self.decision
    }

    /// The finest level the shaders sample of `texture` now; `None` while it is not
    /// sampleable (or outside the dataset).
    pub fn shown_level(&self, texture: u32) -> Option<u32> {
        self.cache
            .texture_data(texture)
            .filter(|data| data.state == crate::gpu_types::TEXTURE_SAMPLEABLE)
            .map(|data| data.lowest_mip)
    }

    /// What the streamer knows of `texture` now, from which
    /// [`TextureShortfall::cause`] says why it may show coarser than the view asks (the
    /// error attribution of docs/CONTROLLER.md); `None` outside the dataset.
    pub fn shortfall(&self, texture: u32) -> Option<TextureShortfall> {
        self.cache.texture_data(texture)?;
        let shown = self.shown_level(texture);
        Some(TextureShortfall {
            shown,
            finest_ever: self.cache.finest_ever_sampleable(texture),
            requested: self.needs.need(texture).map(|need| need.level),
            refused_for_room: shown.is_some_and(|level| level > 0 && self.gate.is_refused(texture, level - 1)),
            mip_bias: self.decision.mip_bias,
        })
    }

    /// Charges `bytes` the host uploaded of its own streamed data (a ground layer's tiles)
    /// to the controller's load size: the next loading cycles load that much less (what one
    /// cycle cannot absorb is carried to the next), so over a run everything streamed
    /// together stays within the adaptive load size; within one frame the host's share
    /// can come on top of a cycle that started before it.
    pub fn charge_host_uploads(&mut self, bytes: u64) {
        self.host_upload_bytes = self.host_upload_bytes.saturating_add(bytes);
    }

    /// Step 2: records the copies of `frame`'s new mips and the table update into `rec`,
    /// outside any render pass and before every pass that samples streamed textures.
    /// Once per frame.
    pub fn record_uploads(&mut self, frame: &mut Frame, rec: Recording<'_>) -> Result<CycleReport> {
        self.check_frame(frame, "record_uploads")?;
        if frame.uploads_recorded {
            return Err(EngineError::InvalidRequest(
                "record_uploads called twice in one frame".into(),
            ));
        }
        let report = self.cache.record_cycle(rec)?;
        frame.uploads_recorded = true;
        self.policy.observe_batch(report.bind_shape, report.bytes_uploaded);
        for &texture in &report.invalidated_textures {
            let _ = self.states.invalidate(texture);
        }
        Ok(report)
    }

    /// Step 3: records the compaction of the per-mesh feedback the host's feedback pass
    /// wrote into `frame`'s read-back slot (resetting the array for the next frame). Must
    /// follow that pass; at most once per frame.
    pub fn record_feedback_resolve(&mut self, frame: &mut Frame, rec: Recording<'_>) -> Result<()> {
        self.record_feedback_resolve_with_tau(frame, rec, self.compact_tau)
    }

    /// As [`record_feedback_resolve`](Self::record_feedback_resolve) with
    /// another compaction threshold (0 keeps every seen mesh, e.g. for an
    /// error reference); the loader still applies the streamer's τ.
    pub fn record_feedback_resolve_with_tau(
        &mut self,
        frame: &mut Frame,
        rec: Recording<'_>,
        gpu_tau: u32,
    ) -> Result<()> {
        self.check_frame(frame, "record_feedback_resolve")?;
        if frame.resolved {
            return Err(EngineError::InvalidRequest(
                "record_feedback_resolve called twice in one frame".into(),
            ));
        }
        let slot = frame.slot as usize;
        self.compactor.record_compact(rec, gpu_tau, frame.slot)?;
        // Algorithm 1's gate: feedback goes to the host only when no loading
        // task runs (deterministic runs load on this thread, so always).
        self.slots[slot].unread = self.deterministic || !self.loader.is_streaming();
        self.slots[slot].resolved = true;
        frame.resolved = true;
        Ok(())
    }

    /// Step 3b, with [`StreamConfig::prefetch`]: records the compaction of a second
    /// feedback pass the host recorded for where the camera will be (a known path's pose a
    /// lead time ahead, or the motion's extrapolation), after the view's resolve, in the
    /// same frame's submission. Its records join the loading cycle that reads this frame's
    /// feedback, each after every one of the view's: a prefetch never displaces what the
    /// view needs within a cycle. At most once per frame.
    pub fn record_prefetch_resolve(&mut self, frame: &mut Frame, rec: Recording<'_>) -> Result<()> {
        self.check_frame(frame, "record_prefetch_resolve")?;
        if !self.prefetch {
            return Err(EngineError::InvalidRequest(
                "record_prefetch_resolve needs a streamer made with StreamConfig::prefetch".into(),
            ));
        }
        if !frame.resolved {
            return Err(EngineError::InvalidRequest(
                "record_prefetch_resolve before record_feedback_resolve: the view's feedback is resolved first".into(),
            ));
        }
        if frame.prefetch_resolved {
            return Err(EngineError::InvalidRequest(
                "record_prefetch_resolve called twice in one frame".into(),
            ));
        }
        let half = self.slots.len() as u32;
        self.compactor.record_compact(rec, self.gpu_tau, half + frame.slot)?;
        self.slots[frame.slot as usize].prefetch_resolved = true;
        frame.prefetch_resolved = true;
        Ok(())
    }

    /// Whether the streamer takes a prefetch pass ([`StreamConfig::prefetch`]).
    pub fn prefetches(&self) -> bool {
        self.prefetch
    }

    /// Step 5: ends `frame` with the controller step on the latency (ms) the host
    /// measured for its previous frame; returns what this frame's submission carries.
    pub fn end_frame(&mut self, frame: Frame, frame_latency_ms: f64) -> Result<FrameSubmit> {
        self.check_frame(&frame, "end_frame")?;
        if !frame.uploads_recorded {
            // The cycle begin_frame bound would never be copied or retired.
            return Err(EngineError::InvalidRequest(
                "end_frame without record_uploads: every frame records its uploads".into(),
            ));
        }
        self.decision = self.policy.update(frame_latency_ms);
        self.in_frame = false;
        Ok(FrameSubmit {
            waits: self.cache.bind_wait().into_iter().collect(),
            signal: SemaphoreSignal {
                semaphore: self.frames.raw(),
                value: self.begun,
            },
        })
    }

    /// `frame` is this streamer's frame in progress (a token is consumed when its frame
    /// ends, so only another streamer's can fail here).
    fn check_frame(&self, frame: &Frame, call: &str) -> Result<()> {
        if frame.streamer != self.id || !self.in_frame || frame.index + 1 != self.begun {
            return Err(EngineError::InvalidRequest(format!(
                "{call} was given frame {} of another streamer",
                frame.index
            )));
        }
        Ok(())
    }

    /// The device.
    pub fn device(&self) -> &Arc<Device> {
        &self.device
    }
}

impl<S: MipSource + 'static> Drop for TextureStreamer<S> {
    fn drop(&mut self) {
        // Nothing of the streamer may be destroyed while a submitted frame
        // still uses it: wait for the last one (device loss leaves nothing
        // better to do than destroy anyway).
        let _ = self.device.wait_idle();
    }
}

/// A texture's mip chain and format, as the source reports them.
fn chain_and_format<S: MipSource + ?Sized>(source: &S, texture: u32) -> Result<(MipChain, TextureFormat)> {
    let chain = source.mip_chain(texture).map_err(source_failure)?;
    let format = source.texture_format(texture).map_err(source_failure)?;
    Ok((chain, format))
}

fn source_failure(error: SourceError) -> EngineError {
    EngineError::InvalidRequest(format!("reading a texture: {error}"))
}
