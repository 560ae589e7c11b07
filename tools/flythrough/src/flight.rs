//! A flight: the streamed city (streamer, city passes, strategy, ground) set up once
//! ([`Flight::new`]) on the device of `device.rs` and the dataset of `dataset.rs`, and the
//! frame the headless run and the window share ([`Flight::record`], [`Flight::submit`],
//! [`Flight::latency`]).

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context, Result};

use citystream_dataset::Dataset;
use citystream_engine::city::{Camera, CityMesh, CityRenderer};
use citystream_engine::commands::{CommandContext, Recording, SemaphoreSignal, SemaphoreWait};
use citystream_engine::gpu_types::{CACHE_IMAGE_SLOTS, TEXTURE_SAMPLEABLE};
use citystream_engine::stream::prefetch::{motion_pass_due, sees_beyond_margin, MotionPredictor};
use citystream_engine::stream::Frame;
use citystream_engine::target::RenderTarget;
use citystream_engine::texture_cache::{CycleReport, Eviction};
use citystream_engine::timing::CpuFrameClock;
use citystream_engine::Device;
use citystream_streaming::bench::path::CameraPath;
use citystream_streaming::bind_latency::BindLatencyModel;
use citystream_streaming::rng::SplitMix64;

use super::args::{Args, Clock, Prefetch, Strategy, FEEDBACK_PASS_SHARE};
use super::camera::pose_camera;
use super::camera::SceneBox;
use super::city_gpu::{cache_layer_size, city_targets, streamed_city_gpu, CityGeometry, CityGpu, CityTargets};
use super::controller::frame_latency;
use super::dataset::scene_extent;
use super::disk::{disk_model, DiskSummary};
use super::ground;
use super::measure::MeshesInView;
use super::passes::{self, Compaction, PassTimes};
use super::preload::{preload_city, Preload};
use super::tree::TreeRun;

/// How long a run waits, after its last frame, for the loads in flight to end.
const MAX_FINISH_LOADING: Duration = Duration::from_secs(600);

/// The dataset, the city's streamer and passes, and the strategy and ground the options ask
/// for: everything a flight renders with, set up once. Its frame is written once too
/// ([`Flight::record`], [`Flight::submit`]): the headless run adds measurement and the CSV
/// around it, the window presenting and input.
pub(crate) struct Flight {
    pub(crate) dataset: Arc<Dataset>,
    meshes_in_view: MeshesInView,
    pub(crate) city: CityGeometry,
    /// The scene's largest side, which scales the window's flying speed.
    pub(crate) extent: f32,
    /// The scene's bounds, which the camera's near plane is chosen from.
    pub(crate) scene_box: SceneBox,
    pub(crate) layer_size: u32,
    pub(crate) targets: CityTargets,
    // The ground and the tree draw with the city's streamer and passes: dropped first.
    pub(crate) ground: Option<ground::GroundRun>,
    pub(crate) tree: Option<TreeRun>,
    pub(crate) gpu: CityGpu,
    strategy: Strategy,
    /// What the texture-array strategy loaded before the first frame, where the city
    /// fits its budget.
    pub(crate) preload: Option<Preload>,
    /// One command buffer per frame in flight: a frame's is reused only after the
    /// streamer's throttle saw that frame complete.
    frame_commands: Vec<CommandContext>,
    pub(crate) pass_times: PassTimes,
    clock: Clock,
    /// `--render-ms`: a modelled frame's render cost.
    render_ms: f64,
    latency: BindLatencyModel,
    latency_rng: SplitMix64,
    /// `--disk-model`: the loader's reads take modelled time on it.
    pub(crate) disk: Option<DiskSummary>,
    cpu_clock: CpuFrameClock,
    last_feedback: Option<u64>,
    /// `--prefetch`, its lead time and modelled cost, and the camera's recent motion.
    prefetch: Prefetch,
    prefetch_lead_s: f64,
    prefetch_cost_ms: f64,
    motion: MotionPredictor,
    /// Path time of the last prefetch pass that looked ahead between cuts (motion's, or
    /// path's), which spaces the next one.
    last_ahead_pass_s: Option<f64>,
    budget_mb: Option<u64>,
    /// What the over-budget warning says the cache does about it.
    eviction: Eviction,
    warned_over_budget: bool,
    warned_failure: bool,
}

impl Drop for Flight {
    fn drop(&mut self) {
        // The targets, the ground's and the tree's resources and the command buffers go
        // before the streamer (field order), and frames may still be in flight on an error
        // path, which skips `finish_loading`: the GPU finishes with them first.
        let _ = self.gpu.streamer.device().wait_idle();
    }
}

/// How the ground layer is sized: the view's focal length and the lowest the eye comes
/// above the ground (`None`: anywhere, so every level of the imagery may be needed).
pub(crate) struct GroundSizing {
    pub(crate) focal_px: f64,
    pub(crate) lowest_eye_m: Option<f64>,
}

/// What one frame of a flight does besides the standard sequence.
#[derive(Clone, Copy, Debug)]
pub(crate) struct FrameSettings<'a> {
    /// Camera time, seconds: when ground patches arrive.
    pub(crate) time_s: f64,
    /// Record the feedback pass and its compaction (the window can pause streaming).
    pub(crate) feedback: bool,
    /// Compact every seen mesh (τ = 0): the error reference loads what this frame saw.
    pub(crate) every_seen_mesh: bool,
    /// City Colormap blending (Eq. 8).
    pub(crate) colormap_blend: bool,
    /// A renderer that draws this frame's view next (the error reference): it is given
    /// the visible pass's culling state, so that it draws the same meshes in the same
    /// phases and its image differs from the frame's by texels alone.
    pub(crate) share_visible_culling: Option<&'a CityRenderer>,
    /// The path the camera follows, where the host knows it (`--prefetch path` looks
    /// from its pose a lead time ahead; without it the motion is extrapolated).
    pub(crate) path: Option<&'a CameraPath>,
}

/// A frame recorded into its command buffer and not yet submitted.
pub(crate) struct RecordedFrame {
    /// The frame's number, from 0 ([`Frame::index`]).
    pub(crate) index: u64,
    /// Its slot among the frames in flight.
    pub(crate) slot: u32,
    /// Time `begin_frame` blocked for the slot's previous frame.
    pub(crate) cpu_wait: std::time::Duration,
    /// The streamer's token, until [`Flight::submit`] ends the frame with it.
    token: Option<Frame>,
    /// This frame's uploads into the cache.
    pub(crate) applied: CycleReport,
    /// Bytes of ground imagery uploaded in this frame.
    pub(crate) ground_bytes: u64,
    /// Draws of a renderer binding one texture per draw ([`super::output::Run`]'s `draw_calls`).
    pub(crate) draw_calls: u32,
    /// Nodes the atlas tree drew.
    pub(crate) nodes_drawn: Option<u32>,
    /// A loading cycle started in this frame's `begin_frame`.
    pub(crate) cycle_started: bool,
    /// With a disk model, bytes read by the cycle in flight and not yet in the cache.
    pub(crate) reads_in_flight_bytes: Option<u64>,
    /// The frame recorded the prefetch pass.
    pub(crate) prefetched: bool,
    /// Where the frame consumed feedback not seen before: its mip deficit and the
    /// textures still a level or more coarser than needed, against the cache as
    /// `begin_frame` left it (this frame's evictions applied, its uploads not yet).
    pub(crate) feedback: Option<FeedbackStatus>,
}

/// What streaming still owes the view, from one read-back.
#[derive(Clone, Copy, Debug)]
pub(crate) struct FeedbackStatus {
    pub(crate) deficit: Option<f64>,
    pub(crate) pending: usize,
    /// Meshes the read-back lists (those whose weight reached τ).
    pub(crate) meshes_seen: usize,
}

impl Flight {
    /// Sets up the streamed city of `dataset` (opened from `dir` by [`super::dataset::open_city`]) for
    /// `width` × `height` frames: the strategy (`--strategy`), the ground (`--ground`,
    /// sized by `sizing`, given the scene's extent) and the streamer the options ask for.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn new(
        args: &Args,
        device: &Arc<Device>,
        commands: &mut CommandContext,
        dir: &Path,
        (dataset, city): (Arc<Dataset>, CityGeometry),
        (width, height): (u32, u32),
        sizing: impl FnOnce(SceneBox) -> GroundSizing,
    ) -> Result<Self> {
        let tree = match args.strategy {
            Strategy::AtlasTree => Some(citystream_gen::atlas_tree::open_tree(&dataset, dir)?),
            Strategy::Feedback | Strategy::TextureArrays => None,
        };
        let scene = &dataset.scene;
        let layer_size = cache_layer_size(&dataset, device);
        let targets = city_targets(device, width, height)?;
        let extent = scene_extent(scene);
        let scene_box = SceneBox::of(scene);
        let frames_in_flight = args.frames_in_flight;
        let ground = match &args.ground {
            Some(ground_dir) => {
                let set = ground::GroundSet::open(ground_dir, &dataset)?;
                let sizing = sizing(scene_box);
                let (config, reference) = ground::ground_config(
                    &set,
                    scene,
                    frames_in_flight,
                    sizing.focal_px,
                    sizing.lowest_eye_m.unwrap_or(f64::MIN_POSITIVE),
                    args.memory_budget_mb().bytes(),
                    device,
                )?;
                Some((set, config, reference))
            }
            None => None,
        };
        let disk = disk_model(args, &dataset, dir)?;
        let mut gpu = streamed_city_gpu(
            args,
            device,
            commands,
            &dataset,
            &city,
            targets.fragment_area,
            layer_size,
            tree.as_ref(),
            // The ground's tile array and staging come out of the same budget.
            ground.as_ref().map_or(0, |(_, config, _)| config.memory_bytes()),
            disk.as_ref().map(|(model, _)| *model),
        )?;
        let ground = match ground {
            Some((set, config, reference)) => Some(ground::GroundRun::new(
                device,
                set,
                config,
                // The window measures no error.
                (!args.window && args.psnr_interval > 0).then_some(reference),
                args.memory_budget_mb().bytes(),
            )?),
            None => None,
        };
        let tree = match tree {
            Some(tree) => Some(TreeRun::new(args, commands, &gpu, &dataset, tree)?),
            None => None,
        };
        let preload = match args.strategy {
            // No budget (none given, or `unlimited`): the city loads whole where it fits.
            Strategy::TextureArrays if args.memory_budget_mb().0.is_none() => preload_city(&mut gpu, commands)?,
            Strategy::TextureArrays => {
                eprintln!("texture arrays: streaming within the memory budget given");
                None
            }
            Strategy::Feedback | Strategy::AtlasTree => None,
        };
        let frame_commands = (0..frames_in_flight)
            .map(|i| CommandContext::new(device, &format!("flythrough frame (slot {i})")))
            .collect::<std::result::Result<Vec<_>, _>>()?;
        let pass_times = PassTimes::new(device, frames_in_flight)?;
        Ok(Self {
            meshes_in_view: MeshesInView::new(&dataset.scene),
            dataset,
            city,
            extent,
            scene_box,
            layer_size,
            targets,
            gpu,
            ground,
            tree,
            strategy: args.strategy,
            preload,
            frame_commands,
            pass_times,
            clock: args.clock,
            render_ms: args.render_ms,
            latency: BindLatencyModel::preset(args.bind_latency),
            latency_rng: SplitMix64::new(args.seed),
            disk: disk.map(|(_, summary)| summary),
            cpu_clock: CpuFrameClock::new(),
            last_feedback: None,
            prefetch: args.prefetch,
            prefetch_lead_s: args.prefetch_lead_s,
            prefetch_cost_ms: args.prefetch_cost_ms.unwrap_or(args.render_ms * FEEDBACK_PASS_SHARE),
            motion: MotionPredictor::new(),
            last_ahead_pass_s: None,
            budget_mb: args.memory_budget_mb().0,
            eviction: args.eviction,
            warned_over_budget: false,
            warned_failure: false,
        })
    }

    /// Whether frames record the feedback pass: not for the atlas tree, nor for a city
    /// loaded whole into texture arrays.
    pub(crate) fn has_feedback(&self) -> bool {
        self.tree.is_none() && self.preload.is_none()
    }

    /// The city's meshes in the engine's layout.
    pub(crate) fn meshes(&self) -> &[CityMesh] {
        &self.city.1
    }

    /// Records frame `frame` for `camera` into its slot's command buffer, in the order
    /// the streamer asks for (module docs of `citystream_engine::stream`): `begin_frame`
    /// (retire, hand feedback to the loader, pack and bind), the ground's arrivals and its
    /// share of the load size, then the uploads, the feedback pass and its compaction, and
    /// the visible pass of the strategy, each timed. The host may record more (a blit to
    /// the swapchain) before [`Self::submit`].
    pub(crate) fn record(
        &mut self,
        frame: u32,
        camera: &Camera,
        settings: &FrameSettings<'_>,
    ) -> Result<RecordedFrame> {
        if self.disk.is_some() {
            // The read model's clock: this frame's time on the path.
            self.gpu
                .streamer
                .set_modelled_time(Duration::from_secs_f64(settings.time_s.max(0.0)))?;
        }
        let mut begun = self.gpu.streamer.begin_frame()?;
        let cycle_started = begun.loading_started();
        let reads_in_flight_bytes = self.gpu.streamer.reads_in_flight().map(|(_, bytes)| bytes);
        self.warn_once(frame, begun.over_budget());
        let feedback = match self.gpu.streamer.latest_feedback() {
            Some((from, entries)) if self.last_feedback != Some(from) => {
                self.last_feedback = Some(from);
                let served = self.gpu.streamer.served_levels(entries)?;
                Some(FeedbackStatus {
                    deficit: served.mip_deficit,
                    pending: served.pending_textures,
                    meshes_seen: entries.len(),
                })
            }
            _ => None,
        };
        // The streamer's throttle saw this slot's last frame complete.
        let slot = begun.slot();
        // Patches that arrived, and the ground tiles this frame's share of the load size
        // pays for (charged to the facades' next loading cycle).
        let ground_bytes = match self.ground.as_mut() {
            Some(run) => {
                run.update(settings.time_s, &mut self.gpu.streamer, &begun, camera)?
                    .bytes
            }
            None => 0,
        };
        self.pass_times.collect(slot, &self.gpu.renderer)?;
        self.gpu.renderer.set_cull_slot(slot)?;
        let feedback_pass = self.has_feedback() && settings.feedback;
        let rec = self.frame_commands[slot as usize].begin_completed()?;
        let times = &mut self.pass_times;
        times.begin(rec, slot, 0);
        let applied = self.gpu.streamer.record_uploads(&mut begun, rec)?;
        if let Some(run) = self.ground.as_mut() {
            run.layer.record_uploads(rec, slot)?;
        }
        times.end(rec, slot, 0);
        // Without feedback (`has_feedback`) the two passes stay empty (0 ms).
        let CityTargets {
            target,
            feedback_target,
            view,
            ..
        } = &self.targets;
        let compaction = match (feedback_pass, settings.every_seen_mesh) {
            (false, _) => None,
            (true, true) => Some(Compaction::Tau(0)),
            (true, false) => Some(Compaction::Streamer),
        };
        passes::record_feedback(
            &mut self.gpu,
            &mut begun,
            rec,
            (feedback_target, view),
            camera,
            target.height(),
            compaction,
            Some((&mut *times, slot)),
        )?;
        // The prefetch pass, timed whether or not it is recorded (0 ms without it).
        times.begin(rec, slot, passes::PREFETCH_PASS);
        let lead = self.prefetch_lead_s;
        let ahead = match (self.prefetch, settings.path) {
            (Prefetch::None, _) => None,
            _ if !feedback_pass || !self.gpu.streamer.prefetches() => None,
            // A known path: the view after its next cut, from a lead time before it; between
            // cuts, the pose a lead ahead where it sees beyond the view's margin, at most
            // once per quarter of the lead (docs/CONTROLLER.md, "Prefetch").
            (Prefetch::Path, Some(path)) => {
                let now = settings.time_s;
                let after_cut = path
                    .jumps()
                    .into_iter()
                    .find(|&cut| cut > now && cut <= now + lead)
                    .map(|cut| pose_camera(&path.sample_between(None, cut), self.scene_box));
                after_cut.or_else(|| {
                    // Between cuts: the pose a lead ahead where it sees beyond the view's
                    // margin, spaced as motion's passes are.
                    if !motion_pass_due(self.last_ahead_pass_s, now, lead) {
                        return None;
                    }
                    let ahead = pose_camera(&path.sample_between(Some(now), now + lead), self.scene_box);
                    let beyond = sees_beyond_margin(camera, &ahead, view.margin);
                    if beyond {
                        self.last_ahead_pass_s = Some(now);
                    }
                    beyond.then_some(ahead)
                })
            }
            // Motion (or a path flown by hand): carried forward, where it sees beyond what
            // the view's own feedback covers, at most once per quarter of the lead.
            _ if !motion_pass_due(self.last_ahead_pass_s, settings.time_s, lead) => None,
            _ => {
                let ahead = self
                    .motion
                    .predict(camera, lead)
                    .filter(|ahead| sees_beyond_margin(camera, ahead, view.margin));
                if ahead.is_some() {
                    self.last_ahead_pass_s = Some(settings.time_s);
                }
                ahead
            }
        };
        self.motion.observe(settings.time_s, camera);
        if let Some(ahead) = &ahead {
            self.gpu
                .renderer
                .record_prefetch_feedback(rec, feedback_target, ahead, view, target.height())?;
            self.gpu.streamer.record_prefetch_resolve(&mut begun, rec)?;
        }
        times.end(rec, slot, passes::PREFETCH_PASS);
        if let Some(other) = settings.share_visible_culling {
            self.gpu.renderer.record_share_visible_culling(rec, other)?;
        }
        times.begin(rec, slot, 3);
        let ground_layer = self.ground.as_ref().map(|g| (&g.layer, slot));
        let (draw_calls, nodes_drawn) = match self.tree.as_mut() {
            Some(run) => {
                let drawn = run.record_frame(
                    rec,
                    &begun,
                    &mut self.gpu,
                    (target, camera),
                    ground_layer.map(|(layer, _)| layer),
                )?;
                (drawn.draw_calls, Some(drawn.nodes_drawn))
            }
            None => {
                passes::record_visible(
                    &self.gpu.renderer,
                    rec,
                    (target, camera),
                    settings.colormap_blend,
                    ground_layer,
                )?;
                let size = (target.width(), target.height());
                let draws = match self.strategy {
                    Strategy::TextureArrays => {
                        let cache = self.gpu.streamer.cache();
                        let image_of = |texture: u32| {
                            cache
                                .texture_data(texture)
                                .filter(|t| t.state == TEXTURE_SAMPLEABLE)
                                .map(|t| t.image)
                        };
                        // The engine binds CACHE_IMAGE_SLOTS arrays at once: Alg. 1's a_max.
                        self.meshes_in_view.array_batches(
                            &self.dataset.scene,
                            camera,
                            size,
                            CACHE_IMAGE_SLOTS,
                            image_of,
                        )
                    }
                    _ => self.meshes_in_view.count(&self.dataset.scene, camera, size.0, size.1),
                };
                (draws, None)
            }
        };
        times.end(rec, slot, 3);
        Ok(RecordedFrame {
            index: begun.index(),
            slot,
            cpu_wait: begun.cpu_wait(),
            token: Some(begun),
            applied,
            cycle_started,
            reads_in_flight_bytes,
            prefetched: ahead.is_some(),
            ground_bytes,
            draw_calls,
            nodes_drawn,
            feedback,
        })
    }

    /// Ends `frame` with the controller step on `frame_ms`, the latency of the frame
    /// before (Eq. 4–7), and submits it with the streamer's waits and signal and the
    /// host's own (`waits`, `signals`: a swapchain image's).
    pub(crate) fn submit(
        &mut self,
        frame: &mut RecordedFrame,
        frame_ms: f64,
        waits: &[SemaphoreWait],
        signals: &[SemaphoreSignal],
    ) -> Result<()> {
        let token = frame
            .token
            .take()
            .with_context(|| format!("frame {} was submitted twice", frame.index))?;
        let submit = self.gpu.streamer.end_frame(token, frame_ms)?;
        let waits: Vec<SemaphoreWait> = submit.waits.iter().chain(waits).copied().collect();
        let signals: Vec<SemaphoreSignal> = std::iter::once(submit.signal).chain(signals.iter().copied()).collect();
        self.frame_commands[frame.slot as usize].submit_frame(&waits, &signals)?;
        Ok(())
    }

    /// `frame`'s command buffer, recorded and not yet submitted, for what the host records
    /// after the flight's passes (the window's blit to the swapchain).
    /// With it, the frame's render target.
    pub(crate) fn recording(&mut self, frame: &RecordedFrame) -> Result<(Recording<'_>, &RenderTarget)> {
        let rec = self.frame_commands[frame.slot as usize].recording()?;
        Ok((rec, &self.targets.target))
    }

    /// The latency of `frame` the controller is given next: measured since the last call
    /// with the real clock, modelled with the others ([`frame_latency`]).
    pub(crate) fn latency(&mut self, frame: &RecordedFrame) -> f64 {
        let cpu_clock = &mut self.cpu_clock;
        // A modelled frame pays for its prefetch pass like any other pass.
        let prefetch_ms = if frame.prefetched && self.clock != Clock::Real {
            self.prefetch_cost_ms
        } else {
            0.0
        };
        prefetch_ms
            + frame_latency(
                self.clock,
                self.render_ms,
                &frame.applied,
                frame.ground_bytes,
                &self.latency,
                &mut self.latency_rng,
                || cpu_clock.tick().as_secs_f64() * 1000.0,
            )
    }

    /// What the prefetch pass costs a modelled frame (ms).
    pub(crate) fn prefetch_cost_ms(&self) -> f64 {
        self.prefetch_cost_ms
    }

    /// Starts the latency clock afresh: time since the last frame (hidden, waiting) is not
    /// the next frame's latency.
    pub(crate) fn restart_latency_clock(&mut self) {
        self.cpu_clock.tick();
    }

    /// Lets the loading task in flight end when the run does, so that its reads count as
    /// read or failed (a remote source that stopped answering fails them within its
    /// timeouts and retries) and a run never ends with reads silently outstanding.
    pub(crate) fn finish_loading(&self) -> Result<()> {
        let streamer = &self.gpu.streamer;
        if streamer.finish_loading(Duration::from_secs(1)) {
            return Ok(());
        }
        eprintln!("waiting for the loads in flight to end (a remote source may take up to its timeouts and retries)");
        if !streamer.finish_loading(MAX_FINISH_LOADING) {
            bail!(
                "the loads in flight did not end within {} s of the last frame",
                MAX_FINISH_LOADING.as_secs()
            );
        }
        Ok(())
    }

    /// The first frame over budget and the first failed load are worth a line each.
    fn warn_once(&mut self, frame: u32, over_budget: bool) {
        if over_budget && !self.warned_over_budget {
            self.warned_over_budget = true;
            let response = match self.eviction {
                Eviction::View => "showing the most important levels that fit",
                Eviction::Ring => "the ring evicts its oldest layers, whatever the view shows",
            };
            eprintln!(
                "\nwarning: from frame {frame} the view needs more texture memory than the {} MB budget holds; \
                 {response} (frames over budget are counted in summary.json)",
                self.budget_mb.unwrap_or(0)
            );
        }
        if !self.warned_failure && self.gpu.streamer.totals().failed > 0 {
            self.warned_failure = true;
            if let Some(first) = self.gpu.streamer.load_failures().first() {
                eprintln!(
                    "\nwarning: from frame {frame} textures fail to load; the first{}: {} \
                     (counted in summary.json; the run will exit non-zero unless --allow-load-failures)",
                    first.level.map(|l| format!(", at level {l}")).unwrap_or_default(),
                    first.reason
                );
            }
        }
    }
}
