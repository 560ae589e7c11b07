//! The headless flythrough: the path flown frame by frame, measured, written to `frames.csv`
//! and `summary.json`.

use std::io::Write;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context, Result};

use citystream_bench::image_error::{CauseFigures, ErrorCauses, ErrorSeries, FrameError, PrefixedErrorFigures};
use citystream_engine::commands::CommandContext;
use citystream_engine::cull::CullStats;
use citystream_engine::device::{describe, TextureBacking};
use citystream_engine::gpu_types::FeedbackEntry;
use citystream_engine::Device;
use citystream_gen::files::write_atomically;
use citystream_streaming::bench::stats::{Stats, SummaryBuilder};
use citystream_streaming::controller::{PolicyKind, PolicyOptions};

use super::args::{writes_frame, Args, Clock, ControllerLatency, Prefetch, FIXED_STEP_MS};
use super::camera::SceneBox;
use super::camera::{camera_path, focal_px, lowest_eye_height, pose_camera};
use super::city_gpu::{city_gpu, reference_config};
use super::dataset::open_city;
use super::depth_slabs::SlabCounts;
use super::flight::{Flight, FrameSettings, GroundSizing};
use super::measure::{error_causes, feedback_reaching, load_reference, reference_feedback};
use super::output::{status, write_csv_row, write_frame_png, CsvRow, MipCacheSummary, Run, CSV_HEADER};
use super::passes::draw_now;

/// Environment variable naming a frame at which the headless flight fails after submitting
/// it (a testing aid for error paths with frames in flight).
pub(crate) const FAIL_AT_FRAME_ENV: &str = "CITYSTREAM_FAIL_AT_FRAME";

/// Flies the path (`--path`, the dataset's standard path by default) headless: every frame
/// through [`Flight`], PNG frames and the error against the fully resident reference at
/// their intervals, a `frames.csv` row per frame and `summary.json` at the end.
pub(crate) fn stream_city(args: &Args, device: &Arc<Device>, dir: &std::path::Path) -> Result<()> {
    if args.depth_slabs.is_some() && args.psnr_interval == 0 {
        anyhow::bail!(
            "--depth-slabs checks the slabs on the frames whose error is measured; --psnr-interval 0 measures none"
        );
    }
    let (dataset, city, slabs) = open_city(args, dir)?;
    let opened = (dataset, city);
    let mut slab_counts = SlabCounts::default();
    let scene = &opened.0.scene;
    let scene_box = SceneBox::of(scene);
    let path_name = args.path.as_deref().unwrap_or("standard");
    // With --depth-slabs the path was derived before the slabs joined the scene.
    let path = match &slabs {
        Some(slabs) => slabs.path.clone(),
        None => camera_path(path_name, scene)?,
    };
    path.restart();
    let duration_s = args.duration_s.unwrap_or(path.duration_s()).max(0.0);
    let ground_y = scene.bounds.min[1];
    let mut commands = CommandContext::new(device, "flythrough setup and measurements")?;
    let mut flight = Flight::new(
        args,
        device,
        &mut commands,
        dir,
        opened,
        (args.width, args.height),
        |scene_box| GroundSizing {
            focal_px: focal_px(args.height, &pose_camera(&path.sample_between(None, 0.0), scene_box)),
            lowest_eye_m: Some(lowest_eye_height(&path, duration_s, ground_y)),
        },
    )?;
    let dataset = Arc::clone(&flight.dataset);
    let scene = &dataset.scene;
    // The error reference: every needed level resident, no budget, loaded
    // synchronously between frames (its policy never runs).
    let mut reference = if args.psnr_interval > 0 {
        Some(city_gpu(
            device,
            &mut commands,
            &dataset,
            &flight.city,
            PolicyKind::Baseline.build(&PolicyOptions::default())?,
            &reference_config(flight.targets.fragment_area, flight.layer_size),
            None,
            None,
            args.culling,
        )?)
    } else {
        None
    };
    if let (Some(log), Some(_)) = (
        std::env::var_os("CITYSTREAM_BIND_LOG").filter(|log| !log.is_empty()),
        &reference,
    ) {
        if device.texture_backing() == TextureBacking::Sparse {
            eprintln!(
                "bind log: {} holds the streamed cache's binds; the error reference's are not logged",
                log.to_string_lossy()
            );
        }
    }

    // With the fixed clock the frame count follows from the duration; with
    // the modelled one it is at most that.
    let shortest_frame_ms = match args.clock {
        // A modelled frame lasts its render cost at the least, and the display period.
        Clock::Modelled => args.display_period_ms.max(args.render_ms),
        _ => FIXED_STEP_MS,
    };
    let frames = args
        .frames
        .unwrap_or_else(|| ((duration_s * 1000.0 / shortest_frame_ms).ceil() as u32).max(1));
    eprintln!(
        "path: {} ({:.1} s, pauses at {:?} s, jumps at {:?} s)",
        path_name,
        path.duration_s(),
        path.pauses()
            .iter()
            .map(|p| (p.start_s * 10.0).round() / 10.0)
            .collect::<Vec<_>>(),
        path.jumps()
            .iter()
            .map(|t| (t * 10.0).round() / 10.0)
            .collect::<Vec<_>>()
    );
    eprintln!(
        "scene: {} ({} meshes, {} textures), {} frame(s) in flight",
        dir.display(),
        scene.meshes.len(),
        dataset.textures.len(),
        args.frames_in_flight
    );

    let csv_path = args.out.join("frames.csv");
    let mut csv = std::io::BufWriter::new(
        std::fs::File::create(&csv_path).with_context(|| format!("creating {}", csv_path.display()))?,
    );
    writeln!(csv, "{CSV_HEADER}")?;
    let mut summary = SummaryBuilder::new();
    let mut deficits = Vec::new();
    let mut errors = ErrorSeries::new();
    let started = std::time::Instant::now();
    let mut written = Vec::new();
    let mut frame_ms = FIXED_STEP_MS;
    let (mut mips_total, mut blocks_total, mut peak_resident) = (0u64, 0u64, 0u64);
    let mut peak_device_memory = 0u64;
    let mut reference_incomplete = 0u32;
    let mut frames_run = 0u32;
    let mut loading_cycles = 0u64;
    let mut prefetch_frames = 0u64;
    let fail_at_frame = std::env::var(FAIL_AT_FRAME_ENV)
        .ok()
        .and_then(|v| v.parse::<u32>().ok());
    let mut waits = WaitCounts::default();
    let mut uploads_at: Vec<(f64, u64)> = Vec::new();
    let mut cause_frames: Vec<(f64, ErrorCauses)> = Vec::new();
    let (mut nodes_drawn, mut draw_call_samples) = (Vec::new(), Vec::new());
    let mut meshes_seen = Vec::new();
    for frame in 0..frames {
        let time_s = match args.clock {
            // The path so far: every frame before this one pushed its advance.
            Clock::Fixed | Clock::Modelled => summary.elapsed_s(),
            Clock::Real => started.elapsed().as_secs_f64(),
        };
        let path_done = match args.clock {
            Clock::Real => time_s > duration_s,
            Clock::Modelled => time_s >= duration_s,
            Clock::Fixed => false,
        };
        if args.frames.is_none() && path_done {
            break;
        }
        frames_run += 1;
        let camera = pose_camera(&path.sample(time_s), scene_box);
        let measure_error = reference.is_some() && frame % args.psnr_interval.max(1) == 0;
        let write_frame = writes_frame(args, frame);

        let mut recorded = flight.record(
            frame,
            &camera,
            &FrameSettings {
                time_s,
                feedback: true,
                // The error reference needs every seen mesh: τ = 0 then.
                every_seen_mesh: measure_error,
                colormap_blend: true,
                share_visible_culling: reference
                    .as_ref()
                    .filter(|_| measure_error)
                    .map(|reference| &reference.renderer),
                path: Some(&path),
            },
        )?;
        let deficit = recorded.feedback.and_then(|f| f.deficit);
        meshes_seen.extend(recorded.feedback.map(|f| f.meshes_seen as f64));
        draw_call_samples.push(f64::from(recorded.draw_calls));
        nodes_drawn.extend(recorded.nodes_drawn.map(f64::from));
        // The controller step with the previous frame's latency.
        let fed_ms = match (args.clock, args.controller_latency) {
            (Clock::Modelled, ControllerLatency::Period) => frame_ms.max(args.display_period_ms),
            _ => frame_ms,
        };
        flight.submit(&mut recorded, fed_ms, &[], &[])?;
        if fail_at_frame == Some(frame) {
            // A testing aid: an error while frames are in flight, as a driver or dataset
            // error mid-run would be, so the teardown on error paths is exercised.
            anyhow::bail!("failing at frame {frame} as {FAIL_AT_FRAME_ENV} asks");
        }
        waits.count(recorded.cpu_wait, false);

        let (mut error, mut ground_error, mut causes) = (None, None, None);
        if write_frame || measure_error {
            let target = &flight.targets.target;
            // Reading this frame's image back is a wait outside the steady state.
            waits.count(flight.gpu.streamer.wait_for_frame(recorded.index)?, true);
            let pixels = target.read_pixels()?;
            if write_frame {
                write_frame_png(args, frame, &pixels, &mut written)?;
            }
            if let (true, Some(reference)) = (measure_error, reference.as_mut()) {
                // The reference sees what the view sees: every seen mesh's level (this
                // frame compacted at τ = 0), lighter than τ or not, and every level the
                // streamed frame shows of them.
                let entries: Vec<FeedbackEntry> = if flight.has_feedback() {
                    feedback_reaching(&flight.gpu.streamer, recorded.index, 0)?
                } else {
                    reference_feedback(reference, &mut commands, &flight.targets, &camera, args.height)?
                };
                let shown = Some(&flight.gpu.streamer);
                reference_incomplete += load_reference(reference, &mut commands, &entries, flight.meshes(), shown)?;
                // On the streamed ground, so that this error is the facades' alone
                // (`ground_psnr_db` measures the ground's).
                let ground = flight.ground.as_ref().map(|run| (&run.layer, recorded.slot));
                draw_now(&mut commands, &reference.renderer, (target, &camera), true, ground)?;
                let reference_pixels = target.read_pixels()?;
                error = Some(FrameError::of_images(&pixels, &reference_pixels));
                causes = Some(error_causes(
                    &mut commands,
                    reference,
                    &flight.gpu.streamer,
                    (target, &camera),
                    (&pixels, &reference_pixels),
                )?);
                if let Some(slabs) = &slabs {
                    // The reference draws the probe's view (its culling too), then which
                    // texture each pixel shows; the frame's own images are read already.
                    let probe = slabs.probe_camera(&camera);
                    draw_now(&mut commands, &reference.renderer, (target, &probe), true, None)?;
                    let rec = commands.begin()?;
                    reference.renderer.record_texture_ids(rec, target, &probe)?;
                    commands.submit_and_wait(&[])?;
                    slabs.check(&target.read_pixels()?, &probe, &mut slab_counts);
                }
            }
            if let (true, Some(run)) = (measure_error, flight.ground.as_mut()) {
                ground_error = run.measure(
                    &mut commands,
                    &flight.gpu.renderer,
                    target,
                    &camera,
                    recorded.slot,
                    time_s,
                )?;
            }
        }

        loading_cycles += u64::from(recorded.cycle_started);
        prefetch_frames += u64::from(recorded.prefetched);
        frame_ms = flight.latency(&recorded);
        let applied = &recorded.applied;
        let bytes = applied.bytes_uploaded;
        let mips = u64::from(applied.mips_uploaded);
        mips_total += mips;
        blocks_total += u64::from(applied.blocks_bound);
        let resident = flight.gpu.streamer.bound_bytes();
        peak_resident = peak_resident.max(resident);
        if frame % 30 == 0 {
            peak_device_memory = peak_device_memory.max(device.device_memory_bytes().unwrap_or(0));
        }

        let path_ms = args.clock.path_advance_ms(frame_ms, args.display_period_ms);
        let t = flight.gpu.streamer.policy().telemetry();
        summary.push_frame(frame_ms, path_ms, t.tw_ms, t.load_size_mb, t.mip_bias, mips, bytes);
        deficits.extend(deficit);
        if let Some(error) = error {
            errors.push(time_s, error);
        }
        if let Some(causes) = causes {
            cause_frames.push((time_s, causes));
        }
        uploads_at.push((time_s, mips));
        write_csv_row(
            &mut csv,
            &CsvRow {
                frame,
                time_s,
                frame_ms,
                telemetry: &t,
                applied,
                resident,
                deficit,
                error,
                ground_error,
                camera: &camera,
                cycle_started: recorded.cycle_started,
                reads_in_flight_bytes: recorded.reads_in_flight_bytes,
                prefetch_pass: recorded.prefetched,
                causes,
            },
        )?;
        let mb_per_s = bytes as f64 / 1e6 / (path_ms / 1000.0).max(1e-6);
        status(
            frame,
            frames,
            frame_ms,
            t.load_size_mb,
            t.mip_bias,
            mb_per_s,
            resident as f64 / 1e6,
        );
    }
    if std::io::IsTerminal::is_terminal(&std::io::stderr()) {
        eprintln!();
    }
    csv.flush()?;
    flight.finish_loading()?;
    device.wait_idle()?;
    let gpu_pass_ms = flight.pass_times.finish(&flight.gpu.renderer)?;
    let culled = &flight.pass_times.culled;
    let city_meshes = flight.meshes().iter().filter(|m| m.index_count > 0).count() as f64;
    let (meshes_drawn, meshes_culled) = if flight.gpu.renderer.culling() {
        let drawn: Vec<f64> = culled.iter().map(|c| f64::from(c.meshes_drawn)).collect();
        let skipped: Vec<f64> = culled.iter().map(|c| f64::from(c.meshes_culled)).collect();
        (Stats::from_samples(&drawn), Stats::from_samples(&skipped))
    } else {
        // Every frame draws every mesh with geometry.
        let frames = vec![city_meshes; frames_run as usize];
        (
            Stats::from_samples(&frames),
            Stats::from_samples(&vec![0.0; frames_run as usize]),
        )
    };
    let culled_stats = |f: fn(&CullStats) -> u32| {
        (!culled.is_empty()).then(|| Stats::from_samples(&culled.iter().map(|c| f64::from(f(c))).collect::<Vec<_>>()))
    };
    let peak_device_memory = peak_device_memory.max(device.device_memory_bytes().unwrap_or(0));
    if reference_incomplete > 0 {
        eprintln!("warning: the error reference evicted {reference_incomplete} textures; PSNR is optimistic");
    }
    let validation_errors = device.validation_log().error_count();
    let path_s = summary.elapsed_s();
    let summary = summary.finish();
    let residency = flight.gpu.streamer.residency_totals();
    let pause_uploads_second_half = path
        .pauses()
        .iter()
        .map(|pause| {
            let from = pause.start_s + pause.duration_s / 2.0;
            let to = pause.start_s + pause.duration_s;
            uploads_at
                .iter()
                .filter(|(t, _)| *t >= from && *t < to)
                .map(|(_, mips)| mips)
                .sum()
        })
        .collect();
    let run = Run {
        device: describe(device),
        scene: dir.display().to_string(),
        strategy: args.strategy.name(),
        culling: args.culling.name(),
        texture_backing: flight.gpu.streamer.texture_backing().name(),
        preloaded: flight.preload,
        meshes_drawn,
        meshes_culled,
        feedback_meshes_drawn: culled_stats(|c| c.feedback_meshes_drawn),
        meshes_passed: culled_stats(|c| c.meshes_passed),
        cull_overflow_frames: flight
            .gpu
            .renderer
            .culling()
            .then(|| culled.iter().filter(|c| c.overflowed).count()),
        meshes_seen_by_feedback: Stats::from_samples(&meshes_seen),
        draw_calls: Stats::from_samples(&draw_call_samples),
        nodes_drawn: (!nodes_drawn.is_empty()).then(|| Stats::from_samples(&nodes_drawn)),
        atlas_tree: flight
            .tree
            .as_ref()
            .map(|run| run.summary(args.memory_budget_mb().bytes())),
        policy: flight.gpu.streamer.policy().kind().name(),
        alpha_ms: args.alpha,
        display_period_ms: (args.clock == Clock::Modelled).then_some(args.display_period_ms),
        render_ms: (args.clock != Clock::Real).then_some(args.render_ms),
        disk_model: flight.disk.clone(),
        loading_cycles,
        path_cuts_s: path.jumps().into_iter().filter(|&t| t <= path_s).collect(),
        priority: flight.gpu.streamer.loader_order().name(),
        prefetch: args.prefetch.name(),
        prefetch_lead_s: (args.prefetch != Prefetch::None).then_some(args.prefetch_lead_s),
        prefetch_frames,
        prefetched_mips: flight.gpu.streamer.totals().prefetched_mips,
        prefetch_cost_ms: (args.prefetch != Prefetch::None && args.clock != Clock::Real)
            .then(|| flight.prefetch_cost_ms()),
        controller_latency: (args.clock == Clock::Modelled).then_some(args.controller_latency.name()),
        mip_deficit: (!deficits.is_empty()).then(|| Stats::from_samples(&deficits)),
        error: PrefixedErrorFigures {
            prefix: "",
            figures: errors.figures(),
        },
        error_causes: CauseFigures::of(&cause_frames),
        ground_tiles_uploaded: flight.ground.as_ref().map(|g| g.layer.totals().tiles_uploaded),
        ground_mb_streamed: flight
            .ground
            .as_ref()
            .map(|g| g.layer.totals().bytes_uploaded as f64 / f64::from(1 << 20)),
        ground_error: PrefixedErrorFigures {
            prefix: "ground_",
            figures: flight.ground.as_ref().and_then(|g| g.errors.figures()),
        },
        ground: flight
            .ground
            .as_ref()
            .zip(args.ground.as_deref())
            .map(|(g, dir)| g.summary(dir)),
        clock: args.clock.name(),
        bind_latency: args.bind_latency.name(),
        width: args.width,
        height: args.height,
        duration_s: match args.clock {
            Clock::Real => started.elapsed().as_secs_f64(),
            Clock::Fixed | Clock::Modelled => path_s,
        },
        wall_s: started.elapsed().as_secs_f64(),
        wall_ms_per_frame: started.elapsed().as_secs_f64() * 1000.0 / f64::from(frames_run.max(1)),
        frames_in_flight: args.frames_in_flight,
        cpu_wait_frames: waits.throttle_frames,
        cpu_wait_ms: waits.throttle_ms,
        readback_wait_frames: waits.readback_frames,
        mips_streamed: mips_total,
        unique_bytes_streamed: residency.unique_bytes_uploaded,
        blocks_bound: blocks_total,
        peak_resident_bytes: peak_resident,
        peak_device_memory_bytes: peak_device_memory,
        memory_budget_bytes: args.memory_budget_mb().bytes(),
        eviction: args.eviction.name(),
        cache_layers: flight.gpu.streamer.cache_layers(),
        cache_tails: flight
            .gpu
            .streamer
            .cache()
            .format_tails()
            .into_iter()
            .map(Into::into)
            .collect(),
        frames_over_budget: residency.frames_over_budget,
        pause_uploads_second_half,
        dropped_levels: residency.dropped_levels,
        evicted_layers: residency.evicted_layers,
        refused_for_room: residency.refused_for_room,
        declined_loads: residency.declined_loads,
        load_failures: flight.gpu.streamer.totals().failed,
        read_retries: flight.gpu.streamer.totals().read_retries,
        deferred_by_time: flight.gpu.streamer.totals().deferred_by_time,
        textures_failed: flight.gpu.streamer.failed_textures(),
        reference_textures_failed: reference.as_ref().map(|r| r.streamer.failed_textures()),
        cache_layer_size: flight.layer_size,
        gpu_pass_ms,
        validation_errors,
        depth_slabs: slabs.is_some().then_some(slab_counts),
        frames_written: written,
        mip_cache: dataset.textures.mip_cache().map(|cache| MipCacheSummary {
            dir: cache.dir().display().to_string(),
            capacity_bytes: cache.capacity_bytes(),
            stats: cache.stats(),
        }),
    };
    let mut json = serde_json::to_value(summary)?;
    if let (Some(object), serde_json::Value::Object(extra)) = (json.as_object_mut(), serde_json::to_value(&run)?) {
        object.extend(extra);
    }
    let path = args.out.join("summary.json");
    write_atomically(&path, serde_json::to_string_pretty(&json)?.as_bytes())?;
    eprintln!(
        "{} frames, {} mips streamed, wrote {} frames, {} and {}; the CPU waited for the GPU in {} frame(s) \
         ({:.1} ms) plus {} image read-back(s)",
        frames_run,
        mips_total,
        run.frames_written.len(),
        csv_path.display(),
        path.display(),
        waits.throttle_frames,
        waits.throttle_ms,
        waits.readback_frames,
    );
    if let Some(cache) = &run.mip_cache {
        eprintln!(
            "mip cache {}: {} hits, {} misses, {:.1} MB written, {} evicted, {} damaged (capacity {:.0} MB)",
            cache.dir,
            cache.stats.hits,
            cache.stats.misses,
            cache.stats.written_bytes as f64 / f64::from(1 << 20),
            cache.stats.evicted,
            cache.stats.damaged,
            cache.capacity_bytes as f64 / f64::from(1 << 20)
        );
    }
    let failures = flight.gpu.streamer.load_failures();
    let reference_failures = reference
        .as_ref()
        .map(|r| r.streamer.load_failures())
        .unwrap_or_default();
    drop(reference);
    drop(flight);
    if validation_errors > 0 {
        bail!("{validation_errors} Vulkan validation error(s) during the run");
    }
    if let Some(counts) = run.depth_slabs {
        eprintln!(
            "depth slabs at {} m: {} frame(s) checked, {} pixel(s) of the nearer slab, {} of the farther, {} of other meshes",
            counts.distance_m, counts.frames_checked, counts.near_pixels, counts.far_pixels, counts.other_pixels
        );
        if counts.far_pixels > 0 {
            bail!(
                "depth did not resolve the slabs {} m apart at {} m: {} pixel(s) inside the nearer slab showed the farther",
                super::depth_slabs::SLAB_GAP_M,
                counts.distance_m,
                counts.far_pixels
            );
        }
        if counts.frames_checked == 0 {
            bail!(
                "the depth slabs at {} m were in no measured frame's view (behind its eye or past their plane): \
                 nothing was shown about depth there",
                counts.distance_m
            );
        }
        let inside = counts.near_pixels + counts.far_pixels + counts.other_pixels;
        if counts.near_pixels == 0 || counts.near_pixels * 2 < inside {
            bail!(
                "the depth slabs at {} m were hidden ({} of {} pixel(s) inside them over {} frame(s) showed the nearer): \
                 nothing was shown about depth there",
                counts.distance_m,
                counts.near_pixels,
                inside,
                counts.frames_checked
            );
        }
    }
    if run.textures_failed > 0 {
        let first = failures
            .first()
            .map(|f| format!("; the first: {}", f.reason))
            .unwrap_or_default();
        let message = format!(
            "{} texture(s) failed to load ({} failure(s)){first}",
            run.textures_failed, run.load_failures
        );
        if !args.allow_load_failures {
            bail!("{message}; the frames show their colormap colour or coarser levels (--allow-load-failures exits 0)");
        }
        eprintln!("warning: {message}");
    }
    if let Some(first) = reference_failures.first() {
        let message = format!(
            "the error reference could not load {} texture(s); the first: {} (its frames show them at the levels it has, \
             so the error measured there is against an incomplete reference)",
            run.reference_textures_failed.unwrap_or(0),
            first.reason
        );
        if !args.allow_load_failures {
            bail!("{message} (--allow-load-failures exits 0)");
        }
        eprintln!("warning: {message}");
    }
    Ok(())
}

/// Frames in which the render thread blocked on the GPU.
#[derive(Debug, Default)]
pub(crate) struct WaitCounts {
    /// Frames whose slot was still in use by the GPU (the throttle blocked).
    pub(crate) throttle_frames: u32,
    pub(crate) throttle_ms: f64,
    /// Frames whose image was read back (PNG frames, PSNR), which waits.
    pub(crate) readback_frames: u32,
}

impl WaitCounts {
    pub(crate) fn count(&mut self, waited: Duration, readback: bool) {
        if readback {
            self.readback_frames += 1;
        } else if !waited.is_zero() {
            self.throttle_frames += 1;
            self.throttle_ms += waited.as_secs_f64() * 1000.0;
        }
    }
}
