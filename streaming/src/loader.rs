//! The streaming task: `UnloadTextures` + `LoadTextures` of Algorithm 1.
//!
//! A cycle runs in three steps:
//!
//! 1. **Unload**: textures the cache invalidated since the last cycle are
//!    handed to [`MipSink::unload`] (made unsampleable) and reset to Initial.
//! 2. **Plan** ([`plan_cycle`]): the sorted records are walked in chunks;
//!    within a chunk, the per-record work (state lookup, header read of new
//!    textures, mip length) runs in parallel on the rayon pool, and the
//!    chunk's results are then taken in priority order: one mip per texture
//!    per cycle, stopping once the planned batch *exceeds* `s` (Algorithm 1
//!    checks `loadedBatchSize > s` before each load, so a batch overshoots
//!    `s` by at most one mip and always holds at least one). Taking results
//!    in priority order makes the batch the same on every run, whatever the
//!    thread timing.
//! 3. **Load**: the planned mips are read in parallel, each with exactly its
//!    own bytes ([`MipSource::read_mip`]). A worker first claims the texture
//!    with a compare-and-swap from the planned state; a mip whose claim is
//!    lost (the cache invalidated the texture meanwhile) or whose turn comes
//!    after the load-time limit is skipped and left for a later cycle. Read
//!    mips go to [`MipSink::stage`]; then [`MipSink::end_cycle`].
//!
//! A read or header error marks that texture Failed, counts it and keeps its
//! reason in a bounded log ([`Loader::failures`]); the cycle goes on. A sink
//! error flagged `invalidated` (the cache reused the region meanwhile)
//! invalidates the texture instead, so the next cycle unloads it.
//!
//! Threading: one cycle at a time, guarded by an atomic flag (Algorithm 1's
//! `isStreaming`). [`Loader::try_spawn`] runs the cycle on the rayon pool
//! and returns at once; [`Loader::run_cycle`] runs it on the caller's thread.
//! All methods take `&self` and the loader is `Sync`.

use std::collections::{HashSet, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use rayon::prelude::*;

use crate::controller::{BlockBudget, Decision};
use crate::disk_model::DiskModel;
use crate::records::MeshMetaData;
use crate::residency::AdmissionGate;
use crate::source::{MipSink, MipSource, SourceError, StagedMip};
use crate::states::{next_load, TextureState, TextureStates, TextureStatus};

/// Table 2: maximum load time of one cycle.
pub const DEFAULT_LOAD_TIME: Duration = Duration::from_millis(16);

/// Failures kept in the log; older ones are dropped (and still counted).
pub const FAILURE_LOG_CAPACITY: usize = 1024;

/// Loader parameters.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LoaderOptions {
    /// Stop starting new reads once the cycle has run this long.
    pub load_time: Duration,
    /// Records planned per parallel chunk.
    pub plan_chunk: usize,
    /// Reads of a mip before its texture is marked failed (at least 1): a
    /// failed read is retried after `retry_backoff`, doubled each time.
    pub read_attempts: u32,
    /// Wait before the first retry of a failed read.
    pub retry_backoff: Duration,
    /// Reads take modelled time on this disk ([`crate::disk_model`]): the load-time
    /// limit applies to each read's modelled start instead of the wall clock, and every
    /// mip goes to [`MipSink::stage_after`] with its modelled completion. For cycles run
    /// on the caller's thread ([`Loader::run_cycle`]) by a host with a modelled clock.
    pub disk: Option<DiskModel>,
    /// The order a cycle takes its mips in ([`PlanOrder`]).
    pub order: PlanOrder,
}

/// The order in which a cycle takes the mips its records ask for.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum PlanOrder {
    /// The paper's (§3.3): records by descending weight, one mip per texture.
    #[default]
    Weight,
    /// By the screen error each mip removes per byte it costs ([`error_per_byte`]):
    /// coarse levels of many textures before fine levels of a few, so a short budget
    /// buys the most image first.
    ErrorPerByte,
}

impl PlanOrder {
    /// The name used on command lines and in reports.
    pub fn name(self) -> &'static str {
        match self {
            PlanOrder::Weight => "weight",
            PlanOrder::ErrorPerByte => "error-per-byte",
        }
    }
}

/// Levels of detail the first load of a texture adds: from the City Colormap's one colour
/// (a 1×1 image) to the initial 4×4 level is two octaves.
pub const INITIAL_LOAD_LEVELS: f64 = 2.0;

/// The screen error a load removes per byte it costs, the rank of
/// [`PlanOrder::ErrorPerByte`]. Natural images have a power spectrum falling as 1/f²
/// (Field 1987; van der Schaaf and van Hateren 1996), so every octave of detail carries
/// about the same energy: a texture shown one level too coarse over `weight` (its
/// feedback weight, Eq. 1: visible fragments weighted by distance and displayed level)
/// errs by about `weight` per missing level, and loading its next level removes one
/// level's worth ([`INITIAL_LOAD_LEVELS`] for a texture showing only its colour). A
/// level costs its bytes, or the whole sparse blocks it binds where a block budget
/// bounds the cycle.
pub fn error_per_byte(weight: u64, first_load: bool, cost_bytes: u64) -> f64 {
    let levels = if first_load { INITIAL_LOAD_LEVELS } else { 1.0 };
    weight as f64 * levels / cost_bytes.max(1) as f64
}

impl Default for LoaderOptions {
    fn default() -> Self {
        LoaderOptions {
            load_time: DEFAULT_LOAD_TIME,
            plan_chunk: 4096,
            read_attempts: 3,
            retry_backoff: Duration::from_millis(2),
            disk: None,
            order: PlanOrder::Weight,
        }
    }
}

/// Error building a loader.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum LoaderError {
    /// The mesh → texture table names a texture that does not exist.
    #[error("mesh {mesh} maps to texture {texture}, but there are only {textures} textures")]
    MeshTable {
        /// Mesh index in the table.
        mesh: usize,
        /// The texture it names.
        texture: u32,
        /// Number of textures.
        textures: usize,
    },
}

/// A texture that failed to load, and why.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TextureFailure {
    /// The texture.
    pub texture: u32,
    /// The level being read, if the failure was on a mip.
    pub level: Option<u32>,
    /// The error, worded.
    pub reason: String,
}

/// One mip the plan will load.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PlannedMip {
    /// The texture.
    pub texture: u32,
    /// The level to load.
    pub level: u32,
    /// Its bytes.
    pub bytes: u64,
    /// The texture's status when planned (claimed by compare-and-swap).
    pub from: TextureStatus,
    /// Its status once this mip is loaded.
    pub to: TextureStatus,
    /// The finest level later cycles load for this texture if its record and the mip bias
    /// stay as they are (one level per cycle down to it); `level` when this is the last.
    pub target_level: u32,
}

/// What one cycle will load, in priority order.
#[derive(Clone, Debug, Default)]
pub struct CyclePlan {
    /// The mips, highest priority first.
    pub items: Vec<PlannedMip>,
    /// Sum of their bytes.
    pub bytes: u64,
    /// Records naming a mesh outside the mesh → texture table.
    pub bad_records: u64,
    /// Textures whose header or mip length could not be read; already
    /// marked Failed in the state table.
    pub failures: Vec<TextureFailure>,
    /// Loads the admission gate declined (the cache would refuse them).
    pub declined: u64,
    /// Sparse blocks the mips take, by the decision's block budget (0 without one).
    pub blocks: u64,
    /// Of them, the whole blocks of mips of a block or more.
    pub own_blocks: u64,
    /// Bytes of the mips smaller than a block, which share blocks.
    pub shared_bytes: u64,
    /// Loads left for a later cycle because their blocks did not fit the block budget.
    pub over_block_budget: u64,
    /// Mips planned from the prefetch records (after every one of the view's).
    pub prefetched: u64,
}

impl CyclePlan {
    /// Takes `item` (wanted with feedback weight `weight`) unless `gate` declines it (the
    /// cache would refuse it) or the block budget is spent: a cycle always takes its first
    /// mip, and a later one only if its blocks fit what is left.
    fn offer(
        &mut self,
        item: PlannedMip,
        weight: u32,
        gate: Option<&AdmissionGate>,
        budget: Option<BlockBudget>,
        prefetch: bool,
    ) {
        let declined =
            gate.is_some_and(|gate| gate.is_refused(item.texture, item.level) || !gate.admit(weight, item.bytes));
        if declined {
            self.declined += 1;
            return;
        }
        if let Some(budget) = budget {
            let (own, shared) = if budget.owns_blocks(item.bytes) {
                (
                    self.own_blocks.saturating_add(budget.whole_blocks(item.bytes)),
                    self.shared_bytes,
                )
            } else {
                (self.own_blocks, self.shared_bytes.saturating_add(item.bytes))
            };
            let blocks = budget.blocks_of_cycle(own, shared);
            if !self.items.is_empty() && blocks > budget.blocks {
                self.over_block_budget += 1;
                return;
            }
            (self.own_blocks, self.shared_bytes, self.blocks) = (own, shared, blocks);
        }
        self.bytes += item.bytes;
        self.prefetched += u64::from(prefetch);
        self.items.push(item);
    }
}

enum Candidate {
    Nothing,
    BadRecord,
    Load(PlannedMip),
    Failed(TextureFailure),
}

fn candidate<S: MipSource + ?Sized>(
    states: &TextureStates,
    mesh_textures: &[u32],
    record: &MeshMetaData,
    mip_bias: f64,
    source: &S,
) -> Candidate {
    let Some(&texture) = mesh_textures.get(record.mesh_id as usize) else {
        return Candidate::BadRecord;
    };
    let Ok(from) = states.get(texture) else {
        return Candidate::BadRecord;
    };
    let next = next_load(from, record.mip_level, mip_bias, || {
        source.mip_chain(texture).map(|c| c.initial_level())
    });
    let fail = |level: Option<u32>, e: SourceError| {
        Candidate::Failed(TextureFailure {
            texture,
            level,
            reason: e.to_string(),
        })
    };
    match next {
        Ok(None) => Candidate::Nothing,
        Ok(Some((level, to))) => match source.mip_len(texture, level) {
            Ok(bytes) => Candidate::Load(PlannedMip {
                texture,
                level,
                bytes,
                from,
                to,
                // next_load goes on while sampled + bias < current level.
                target_level: {
                    let finest = f64::from(record.mip_level) + mip_bias;
                    if finest.is_finite() {
                        (finest.ceil().max(0.0) as u32).min(level)
                    } else {
                        level
                    }
                },
            }),
            Err(e) => fail(Some(level), e),
        },
        Err(e) => fail(None, e),
    }
}

/// Plan one cycle (step 2 of the module docs): which mip of which texture
/// to load, for the records in priority order, within the decision's load
/// size and mip bias. Header failures mark their textures Failed. Loads a
/// `gate` declines are skipped (a declined load does not count against the
/// load size; the texture is not loaded this cycle).
pub fn plan_cycle<S: MipSource + ?Sized>(
    states: &TextureStates,
    mesh_textures: &[u32],
    records: &[MeshMetaData],
    decision: Decision,
    source: &S,
    plan_chunk: usize,
    gate: Option<&AdmissionGate>,
) -> CyclePlan {
    let request = CycleRequest {
        records,
        prefetch: &[],
        order: PlanOrder::Weight,
        plan_chunk,
    };
    plan_cycle_with(states, mesh_textures, &request, decision, source, gate)
}

/// What a cycle is asked to load: the view's records (filtered and sorted by weight), the
/// prefetch records (where the camera will be; each after every one of the view's, so a
/// prefetch never displaces the view's needs within a cycle), and the order.
#[derive(Clone, Copy, Debug)]
pub struct CycleRequest<'a> {
    /// The view's records, by descending weight.
    pub records: &'a [MeshMetaData],
    /// The prefetch records, by descending weight.
    pub prefetch: &'a [MeshMetaData],
    /// The order mips are taken in.
    pub order: PlanOrder,
    /// Records planned per parallel chunk ([`PlanOrder::Weight`]).
    pub plan_chunk: usize,
}

/// [`plan_cycle`] for a whole [`CycleRequest`]; with a block budget in `decision`, a mip
/// whose blocks do not fit what is left is left for a later cycle (and the walk goes on
/// to the cheaper ones).
pub fn plan_cycle_with<S: MipSource + ?Sized>(
    states: &TextureStates,
    mesh_textures: &[u32],
    request: &CycleRequest<'_>,
    decision: Decision,
    source: &S,
    gate: Option<&AdmissionGate>,
) -> CyclePlan {
    match request.order {
        PlanOrder::Weight => plan_by_weight(states, mesh_textures, request, decision, source, gate),
        PlanOrder::ErrorPerByte => plan_by_error_per_byte(states, mesh_textures, request, decision, source, gate),
    }
}

fn plan_by_weight<S: MipSource + ?Sized>(
    states: &TextureStates,
    mesh_textures: &[u32],
    request: &CycleRequest<'_>,
    decision: Decision,
    source: &S,
    gate: Option<&AdmissionGate>,
) -> CyclePlan {
    let mut plan = CyclePlan::default();
    let mut seen: HashSet<u32> = HashSet::new();
    let chunk_size = request.plan_chunk.max(1);
    let lists = [(request.records, false), (request.prefetch, true)];
    for (records, prefetch) in lists {
        for chunk in records.chunks(chunk_size) {
            let candidates: Vec<Candidate> = chunk
                .par_iter()
                .map(|r| candidate(states, mesh_textures, r, decision.mip_bias, source))
                .collect();
            for (c, record) in candidates.into_iter().zip(chunk) {
                match c {
                    Candidate::Nothing => {}
                    Candidate::BadRecord => plan.bad_records += 1,
                    Candidate::Load(item) => {
                        if seen.contains(&item.texture) {
                            continue;
                        }
                        if plan.bytes > decision.load_size_bytes {
                            return plan;
                        }
                        seen.insert(item.texture);
                        plan.offer(item, record.weight, gate, decision.block_budget, prefetch);
                    }
                    Candidate::Failed(f) => plan.fail(states, f, &mut seen),
                }
            }
        }
    }
    plan
}

/// One texture's records merged: the finest level any of them asks for, the summed
/// weight (its screen error, the rank) and the largest (the admission gate's, as
/// eviction values a texture), and whether only prefetch records name it.
#[derive(Clone, Copy, Debug)]
struct TextureRequest {
    record: MeshMetaData,
    weight_sum: u64,
    prefetch: bool,
}

fn plan_by_error_per_byte<S: MipSource + ?Sized>(
    states: &TextureStates,
    mesh_textures: &[u32],
    request: &CycleRequest<'_>,
    decision: Decision,
    source: &S,
    gate: Option<&AdmissionGate>,
) -> CyclePlan {
    let mut plan = CyclePlan::default();
    let mut by_texture: std::collections::HashMap<u32, usize> = std::collections::HashMap::new();
    let mut textures: Vec<TextureRequest> = Vec::new();
    for (records, prefetch) in [(request.records, false), (request.prefetch, true)] {
        for record in records {
            let Some(&texture) = mesh_textures.get(record.mesh_id as usize) else {
                plan.bad_records += 1;
                continue;
            };
            match by_texture.get(&texture) {
                // The view's records come first: a texture it names keeps its class.
                Some(&i) if textures[i].prefetch != prefetch => {}
                Some(&i) => {
                    let t = &mut textures[i];
                    t.record.mip_level = t.record.mip_level.min(record.mip_level);
                    t.record.weight = t.record.weight.max(record.weight);
                    t.weight_sum += u64::from(record.weight);
                }
                None => {
                    by_texture.insert(texture, textures.len());
                    textures.push(TextureRequest {
                        record: *record,
                        weight_sum: u64::from(record.weight),
                        prefetch,
                    });
                }
            }
        }
    }
    let candidates: Vec<Candidate> = textures
        .par_iter()
        .map(|t| candidate(states, mesh_textures, &t.record, decision.mip_bias, source))
        .collect();
    let mut ranked: Vec<(PlannedMip, &TextureRequest, f64)> = Vec::new();
    let mut seen: HashSet<u32> = HashSet::new();
    for (c, t) in candidates.into_iter().zip(&textures) {
        match c {
            Candidate::Nothing | Candidate::BadRecord => {}
            Candidate::Load(item) => {
                let cost = decision.block_budget.map_or(item.bytes, |b| {
                    (b.blocks_of(item.bytes) * b.block_bytes as f64).ceil() as u64
                });
                let first_load = item.from.state == TextureState::Initial;
                ranked.push((item, t, error_per_byte(t.weight_sum, first_load, cost)));
            }
            Candidate::Failed(f) => plan.fail(states, f, &mut seen),
        }
    }
    // The view's before the prefetch's, then by error removed per byte; ties by texture
    // so that the order never depends on the records' order or the thread timing.
    ranked.sort_by(|(a, ta, ra), (b, tb, rb)| {
        ta.prefetch
            .cmp(&tb.prefetch)
            .then_with(|| rb.total_cmp(ra))
            .then_with(|| a.texture.cmp(&b.texture))
    });
    for (item, t, _) in ranked {
        if plan.bytes > decision.load_size_bytes {
            break;
        }
        plan.offer(item, t.record.weight, gate, decision.block_budget, t.prefetch);
    }
    plan
}

impl CyclePlan {
    /// Records `failure` once per texture and marks the texture Failed.
    fn fail(&mut self, states: &TextureStates, failure: TextureFailure, seen: &mut HashSet<u32>) {
        if seen.insert(failure.texture) {
            // The id came from the table, so it is in range.
            let _ = states.mark_failed(failure.texture);
            self.failures.push(failure);
        }
    }
}

/// Why a planned mip did not reach the sink.
enum LoadFailure {
    /// The texture's cache region went away; it will be reloaded.
    Invalidated,
    /// Read or staging failed; the texture is marked failed.
    Failed(String),
}

/// What one cycle did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CycleReport {
    /// Invalidated textures unloaded at the start.
    pub unloaded: u64,
    /// Mips planned.
    pub planned_mips: u64,
    /// Loads the admission gate declined.
    pub declined: u64,
    /// Loads left for a later cycle because their blocks did not fit the block budget.
    pub over_block_budget: u64,
    /// Mips planned from the prefetch records.
    pub prefetched_mips: u64,
    /// Bytes planned.
    pub planned_bytes: u64,
    /// Mips read and staged.
    pub loaded_mips: u64,
    /// Bytes read and staged.
    pub loaded_bytes: u64,
    /// Planned mips skipped because the load-time limit passed.
    pub deferred_by_time: u64,
    /// Planned mips skipped because the texture changed state meanwhile.
    pub lost_claims: u64,
    /// Mips the sink refused because the cache invalidated their texture
    /// meanwhile (the texture is queued for unloading, not failed).
    pub invalidated_while_loading: u64,
    /// Textures marked Failed this cycle.
    pub failed: u64,
    /// Records naming an unknown mesh.
    pub bad_records: u64,
    /// Wall time of the cycle.
    pub elapsed: Duration,
    /// With a disk model, when the cycle's last read completes, from its start (zero
    /// without one).
    pub modelled_read_time: Duration,
}

/// Totals over every cycle since the loader was made.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LoaderTotals {
    /// Cycles run.
    pub cycles: u64,
    /// Mips staged.
    pub loaded_mips: u64,
    /// Bytes staged.
    pub loaded_bytes: u64,
    /// Textures failed.
    pub failed: u64,
    /// Failed reads that a retry then completed.
    pub read_retries: u64,
    /// Mips deferred by the load-time limit.
    pub deferred_by_time: u64,
    /// Records naming an unknown mesh.
    pub bad_records: u64,
    /// Mips planned from prefetch records.
    pub prefetched_mips: u64,
}

#[derive(Debug, Default)]
struct Counters {
    cycles: AtomicU64,
    loaded_mips: AtomicU64,
    loaded_bytes: AtomicU64,
    failed: AtomicU64,
    read_retries: AtomicU64,
    deferred_by_time: AtomicU64,
    bad_records: AtomicU64,
    prefetched_mips: AtomicU64,
}

#[derive(Debug)]
struct Inner<S, K> {
    source: S,
    sink: K,
    states: Arc<TextureStates>,
    mesh_textures: Vec<u32>,
    options: LoaderOptions,
    streaming: AtomicBool,
    counters: Counters,
    failures: Mutex<VecDeque<TextureFailure>>,
    reports_tx: crossbeam::channel::Sender<CycleReport>,
    reports_rx: crossbeam::channel::Receiver<CycleReport>,
    gate: std::sync::OnceLock<Arc<AdmissionGate>>,
}

/// Clears the streaming flag when the cycle ends, even by panic.
struct StreamingGuard<'a>(&'a AtomicBool);

impl Drop for StreamingGuard<'_> {
    fn drop(&mut self) {
        self.0.store(false, Ordering::Release);
    }
}

/// The streaming task of Algorithm 1 over a source and a sink.
#[derive(Debug)]
pub struct Loader<S, K> {
    inner: Arc<Inner<S, K>>,
}

impl<S, K> Clone for Loader<S, K> {
    fn clone(&self) -> Self {
        Loader {
            inner: Arc::clone(&self.inner),
        }
    }
}

impl<S: MipSource + 'static, K: MipSink + 'static> Loader<S, K> {
    /// A loader for `texture_count` textures (all Initial); `mesh_textures`
    /// maps a record's mesh id to its texture.
    pub fn new(
        source: S,
        sink: K,
        mesh_textures: Vec<u32>,
        texture_count: usize,
        options: LoaderOptions,
    ) -> Result<Self, LoaderError> {
        let states = Arc::new(TextureStates::new(texture_count));
        Self::with_states(source, sink, mesh_textures, states, options)
    }

    /// A loader over existing texture states (create them first when the
    /// sink needs a handle to invalidate textures from inside a cycle).
    pub fn with_states(
        source: S,
        sink: K,
        mesh_textures: Vec<u32>,
        states: Arc<TextureStates>,
        options: LoaderOptions,
    ) -> Result<Self, LoaderError> {
        let texture_count = states.len();
        if let Some((mesh, &texture)) = mesh_textures
            .iter()
            .enumerate()
            .find(|(_, &t)| t as usize >= texture_count)
        {
            return Err(LoaderError::MeshTable {
                mesh,
                texture,
                textures: texture_count,
            });
        }
        let (reports_tx, reports_rx) = crossbeam::channel::unbounded();
        Ok(Loader {
            inner: Arc::new(Inner {
                source,
                sink,
                states,
                mesh_textures,
                options,
                streaming: AtomicBool::new(false),
                counters: Counters::default(),
                failures: Mutex::new(VecDeque::new()),
                reports_tx,
                reports_rx,
                gate: std::sync::OnceLock::new(),
            }),
        })
    }

    /// Makes every later cycle skip the loads `gate` declines. A loader
    /// has at most one gate; `false` if one was set before.
    pub fn set_admission_gate(&self, gate: Arc<AdmissionGate>) -> bool {
        self.inner.gate.set(gate).is_ok()
    }

    /// The order its cycles take mips in.
    pub fn order(&self) -> PlanOrder {
        self.inner.options.order
    }

    /// The mesh → texture table.
    pub fn mesh_textures(&self) -> &[u32] {
        &self.inner.mesh_textures
    }

    /// The texture states (the cache calls [`TextureStates::invalidate`]).
    pub fn states(&self) -> &TextureStates {
        &self.inner.states
    }

    /// A shared handle to the texture states.
    pub fn states_handle(&self) -> Arc<TextureStates> {
        Arc::clone(&self.inner.states)
    }

    /// The sink.
    pub fn sink(&self) -> &K {
        &self.inner.sink
    }

    /// The source.
    pub fn source(&self) -> &S {
        &self.inner.source
    }

    /// Whether a cycle is running (Algorithm 1's `isStreaming`).
    pub fn is_streaming(&self) -> bool {
        self.inner.streaming.load(Ordering::Acquire)
    }

    fn try_acquire(&self) -> bool {
        self.inner
            .streaming
            .compare_exchange(false, true, Ordering::AcqRel, Ordering::Acquire)
            .is_ok()
    }

    /// Start a cycle on the rayon pool for `records` (already filtered and
    /// sorted) and return at once; `false` if a cycle is still running.
    /// The cycle's report arrives through [`Loader::try_recv_report`].
    pub fn try_spawn(&self, records: Vec<MeshMetaData>, decision: Decision) -> bool {
        self.try_spawn_with(records, Vec::new(), decision)
    }

    /// [`try_spawn`](Self::try_spawn) with prefetch records, taken after every one of
    /// `records` ([`CycleRequest`]).
    pub fn try_spawn_with(&self, records: Vec<MeshMetaData>, prefetch: Vec<MeshMetaData>, decision: Decision) -> bool {
        if !self.try_acquire() {
            return false;
        }
        let inner = Arc::clone(&self.inner);
        rayon::spawn(move || {
            let _guard = StreamingGuard(&inner.streaming);
            let report = inner.cycle(&records, &prefetch, decision);
            // The receiver lives in `inner` itself, so sending cannot fail.
            let _ = inner.reports_tx.send(report);
        });
        true
    }

    /// Run a cycle on this thread; `None` if a cycle is already running.
    pub fn run_cycle(&self, records: &[MeshMetaData], decision: Decision) -> Option<CycleReport> {
        self.run_cycle_with(records, &[], decision)
    }

    /// [`run_cycle`](Self::run_cycle) with prefetch records, taken after every one of
    /// `records` ([`CycleRequest`]).
    pub fn run_cycle_with(
        &self,
        records: &[MeshMetaData],
        prefetch: &[MeshMetaData],
        decision: Decision,
    ) -> Option<CycleReport> {
        if !self.try_acquire() {
            return None;
        }
        let _guard = StreamingGuard(&self.inner.streaming);
        Some(self.inner.cycle(records, prefetch, decision))
    }

    /// The report of a spawned cycle that finished, if any.
    pub fn try_recv_report(&self) -> Option<CycleReport> {
        self.inner.reports_rx.try_recv().ok()
    }

    /// Wait up to `timeout` for a spawned cycle's report.
    pub fn recv_report_timeout(&self, timeout: Duration) -> Option<CycleReport> {
        self.inner.reports_rx.recv_timeout(timeout).ok()
    }

    /// Totals over all cycles.
    pub fn totals(&self) -> LoaderTotals {
        let c = &self.inner.counters;
        LoaderTotals {
            cycles: c.cycles.load(Ordering::Relaxed),
            loaded_mips: c.loaded_mips.load(Ordering::Relaxed),
            loaded_bytes: c.loaded_bytes.load(Ordering::Relaxed),
            failed: c.failed.load(Ordering::Relaxed),
            read_retries: c.read_retries.load(Ordering::Relaxed),
            deferred_by_time: c.deferred_by_time.load(Ordering::Relaxed),
            bad_records: c.bad_records.load(Ordering::Relaxed),
            prefetched_mips: c.prefetched_mips.load(Ordering::Relaxed),
        }
    }

    /// The most recent failures (up to [`FAILURE_LOG_CAPACITY`]), oldest first.
    pub fn failures(&self) -> Vec<TextureFailure> {
        self.inner.failure_log().iter().cloned().collect()
    }

    /// Reads one mip of `texture` into `bytes` outside a cycle (immediate loads of a
    /// reference) with the cycles' failure lifecycle: retried as
    /// [`LoaderOptions::read_attempts`] says; on the last failure the texture is marked
    /// failed and the failure recorded (counted in [`Loader::totals`], listed by
    /// [`Loader::failures`]) before the error is returned.
    pub fn read_now(&self, texture: u32, level: u32, bytes: &mut [u8]) -> Result<(), TextureFailure> {
        self.inner.read_with_retries(texture, level, bytes).map_err(|reason| {
            let failure = TextureFailure {
                texture,
                level: Some(level),
                reason,
            };
            self.fail_texture(failure.clone());
            failure
        })
    }

    /// Gives up `failure.texture` for a reason found after loading (the
    /// cache cannot hold it): marks it failed, so it is not read again,
    /// and counts and logs the failure like a failed read.
    pub fn fail_texture(&self, failure: TextureFailure) {
        let _ = self.inner.states.mark_failed(failure.texture);
        self.inner.record_failure(failure);
    }
}

impl<S: MipSource, K: MipSink> Inner<S, K> {
    fn failure_log(&self) -> std::sync::MutexGuard<'_, VecDeque<TextureFailure>> {
        self.failures.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn record_failure(&self, failure: TextureFailure) {
        self.counters.failed.fetch_add(1, Ordering::Relaxed);
        let mut log = self.failure_log();
        if log.len() == FAILURE_LOG_CAPACITY {
            log.pop_front();
        }
        log.push_back(failure);
    }

    fn cycle(&self, records: &[MeshMetaData], prefetch: &[MeshMetaData], decision: Decision) -> CycleReport {
        let start = Instant::now();
        let unloaded = self.states.unload_invalidated(|texture| self.sink.unload(texture)) as u64;
        let request = CycleRequest {
            records,
            prefetch,
            order: self.options.order,
            plan_chunk: self.options.plan_chunk,
        };
        let plan = plan_cycle_with(
            &self.states,
            &self.mesh_textures,
            &request,
            decision,
            &self.source,
            self.gate.get().map(Arc::as_ref),
        );
        // Priority order: a remote source issues the requests in this order. After this
        // cycle's mips, the finer levels the next cycles will load for the same records,
        // breadth first: every record's next level before any record's level after that,
        // so a store that holds only so much ahead spends it on the next cycles of every
        // texture, not on the last cycles of a few. (A texture's levels lie back to back in
        // a pack, so a store with room fetches its remaining chain in one request.)
        let mut hints: Vec<(u32, u32)> = plan.items.iter().map(|item| (item.texture, item.level)).collect();
        let deepest = plan
            .items
            .iter()
            .map(|item| item.level.saturating_sub(item.target_level))
            .max()
            .unwrap_or(0);
        for ahead in 1..=deepest {
            hints.extend(
                plan.items
                    .iter()
                    .filter(|item| item.level >= item.target_level + ahead)
                    .map(|item| (item.texture, item.level - ahead)),
            );
        }
        self.source.prefetch(&hints);
        let header_failures = plan.failures.len() as u64;
        for f in plan.failures.iter().cloned() {
            self.record_failure(f);
        }
        let loaded_mips = AtomicU64::new(0);
        let loaded_bytes = AtomicU64::new(0);
        let deferred = AtomicU64::new(0);
        let lost = AtomicU64::new(0);
        let read_failures = AtomicU64::new(0);
        let invalidated = AtomicU64::new(0);
        // With a disk model every planned read has its modelled start and completion,
        // in priority order, before any is made: the same plan gives the same times.
        let schedule = self.options.disk.map(|disk| {
            let sizes: Vec<u64> = plan.items.iter().map(|item| item.bytes).collect();
            disk.schedule(&sizes)
        });
        let modelled_read_time = schedule
            .as_ref()
            .and_then(|reads| {
                reads
                    .iter()
                    .filter(|read| read.start <= self.options.load_time)
                    .map(|read| read.done)
                    .max()
            })
            .unwrap_or_default();
        plan.items.par_iter().enumerate().for_each(|(index, item)| {
            let modelled = schedule.as_ref().map(|reads| reads[index]);
            let too_late = match modelled {
                Some(read) => read.start > self.options.load_time,
                None => start.elapsed() > self.options.load_time,
            };
            if too_late {
                deferred.fetch_add(1, Ordering::Relaxed);
                return;
            }
            if !matches!(self.states.try_transition(item.texture, item.from, item.to), Ok(true)) {
                lost.fetch_add(1, Ordering::Relaxed);
                return;
            }
            match self.load(item, modelled.map(|read| read.done)) {
                Ok(()) => {
                    loaded_mips.fetch_add(1, Ordering::Relaxed);
                    loaded_bytes.fetch_add(item.bytes, Ordering::Relaxed);
                }
                Err(LoadFailure::Invalidated) => {
                    let _ = self.states.invalidate(item.texture);
                    invalidated.fetch_add(1, Ordering::Relaxed);
                }
                Err(LoadFailure::Failed(reason)) => {
                    let _ = self.states.mark_failed(item.texture);
                    read_failures.fetch_add(1, Ordering::Relaxed);
                    self.record_failure(TextureFailure {
                        texture: item.texture,
                        level: Some(item.level),
                        reason,
                    });
                }
            }
        });
        self.sink.end_cycle();
        let report = CycleReport {
            unloaded,
            planned_mips: plan.items.len() as u64,
            planned_bytes: plan.bytes,
            loaded_mips: loaded_mips.into_inner(),
            loaded_bytes: loaded_bytes.into_inner(),
            deferred_by_time: deferred.into_inner(),
            lost_claims: lost.into_inner(),
            invalidated_while_loading: invalidated.into_inner(),
            failed: header_failures + read_failures.into_inner(),
            bad_records: plan.bad_records,
            declined: plan.declined,
            over_block_budget: plan.over_block_budget,
            prefetched_mips: plan.prefetched,
            elapsed: start.elapsed(),
            modelled_read_time,
        };
        let c = &self.counters;
        c.cycles.fetch_add(1, Ordering::Relaxed);
        c.loaded_mips.fetch_add(report.loaded_mips, Ordering::Relaxed);
        c.loaded_bytes.fetch_add(report.loaded_bytes, Ordering::Relaxed);
        c.deferred_by_time.fetch_add(report.deferred_by_time, Ordering::Relaxed);
        c.bad_records.fetch_add(report.bad_records, Ordering::Relaxed);
        c.prefetched_mips.fetch_add(report.prefetched_mips, Ordering::Relaxed);
        report
    }

    /// Reads one mip into `bytes` as the failure lifecycle says: a failed read is retried
    /// after `retry_backoff`, doubled each time, up to `read_attempts` reads in all; the
    /// error, worded with the attempts made, if the last one fails.
    fn read_with_retries(&self, texture: u32, level: u32, bytes: &mut [u8]) -> Result<(), String> {
        // A read that fails can succeed later (a file being replaced, a
        // network share, a device hiccup); a wrong request cannot.
        fn is_transient(error: &SourceError) -> bool {
            !matches!(
                error,
                SourceError::UnknownTexture { .. }
                    | SourceError::UnknownLevel { .. }
                    | SourceError::LengthMismatch { .. }
            )
        }
        let mut backoff = self.options.retry_backoff;
        for attempt in 1.. {
            match self.source.read_mip(texture, level, bytes) {
                Ok(()) => return Ok(()),
                Err(e) if attempt < self.options.read_attempts && is_transient(&e) => {
                    self.counters.read_retries.fetch_add(1, Ordering::Relaxed);
                    std::thread::sleep(backoff);
                    backoff = backoff.saturating_mul(2);
                }
                Err(e) => {
                    let tries = if attempt > 1 {
                        format!(" (after {attempt} attempts)")
                    } else {
                        String::new()
                    };
                    return Err(format!("{e}{tries}"));
                }
            }
        }
        unreachable!("the attempts above end in a return")
    }

    /// Reads `item` and stages it (after `modelled_done` of modelled time, where a disk
    /// model gives one).
    fn load(&self, item: &PlannedMip, modelled_done: Option<Duration>) -> Result<(), LoadFailure> {
        let len = usize::try_from(item.bytes)
            .map_err(|_| LoadFailure::Failed(format!("mip of {} bytes does not fit in memory", item.bytes)))?;
        let mut bytes = vec![0u8; len];
        self.read_with_retries(item.texture, item.level, &mut bytes)
            .map_err(LoadFailure::Failed)?;
        let mip = StagedMip {
            texture: item.texture,
            level: item.level,
            bytes,
        };
        match modelled_done {
            Some(done) => self.sink.stage_after(mip, done),
            None => self.sink.stage(mip),
        }
        .map_err(|e| {
            if e.invalidated {
                LoadFailure::Invalidated
            } else {
                LoadFailure::Failed(e.to_string())
            }
        })
    }
}
