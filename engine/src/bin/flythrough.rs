//! `flythrough`: renders a city headless along a camera path. With a
//! dataset it runs the paper's pipeline (Algorithm 1): feedback, compaction,
//! controller, loading task, sparse binds and copies, then the frame with
//! City Colormap blending. It writes PNG frames and `summary.json`.

use std::io::Write;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::{Parser, ValueEnum};
use glam::Vec3;

use citystream_engine::city::{Camera, CityMesh, CityRenderer, FeedbackView};
use citystream_engine::commands::CommandContext;
use citystream_engine::device::describe;
use citystream_engine::feedback::FeedbackCompactor;
use citystream_engine::gpu_types::{Vertex, FEEDBACK_WEIGHT_ONE};
use citystream_engine::instance::{default_validation, InstanceOptions};
use citystream_engine::pipeline::Filtering;
use citystream_engine::placeholder;
use citystream_engine::scene::MeshRenderer;
use citystream_engine::streamer::Streamer;
use citystream_engine::target::{write_png, RenderTarget};
use citystream_engine::texture_cache::{GpuCacheConfig, GpuTextureCache};
use citystream_engine::timing::CpuFrameClock;
use citystream_engine::{Device, DeviceOptions};
use citystream_streaming::bind_latency::{BindLatencyModel, BindLatencyPreset};
use citystream_streaming::controller::{PolicyKind, PolicyOptions};
use citystream_streaming::dataset::Dataset;
use citystream_streaming::loader::LoaderOptions;
use citystream_streaming::records::DEFAULT_WEIGHT_CUTOFF;
use citystream_streaming::rng::SplitMix64;
use citystream_streaming::stats::SummaryBuilder;

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum Clock {
    /// The camera follows wall-clock time; frame latency is measured.
    Real,
    /// A fixed time step per frame; frame latency is modelled (a fixed
    /// render cost plus the bind-latency model's cost of each batch), so runs
    /// are reproducible.
    Fixed,
}

#[derive(Debug, Parser)]
#[command(
    name = "flythrough",
    version,
    about = "Stream and render a textured city headless along a camera path",
    long_about = "Renders a city off-screen (no window) along a camera path and writes every N-th \
                  frame as PNG plus summary.json.\n\n\
                  With --dataset it runs the adaptive streaming pipeline: a feedback pass tells \
                  which mip each visible mesh needs, a loading task reads exactly those mips, \
                  the sparse texture cache binds memory and copies them, and the frame blends \
                  sampled colour with the City Colormap by mip level. Without --dataset it \
                  renders a small procedural placeholder city, fully resident."
)]
struct Args {
    /// City dataset directory (written by `citystream gen` or `citystream import`).
    #[arg(long)]
    dataset: Option<PathBuf>,
    /// Output directory for frames/ and summary.json.
    #[arg(long, default_value = "out/flythrough")]
    out: PathBuf,
    /// Number of frames to render.
    #[arg(long, default_value_t = 240, value_parser = clap::value_parser!(u32).range(1..=1_000_000))]
    frames: u32,
    /// Write every N-th frame as PNG (0 writes none).
    #[arg(long, default_value_t = 20)]
    frame_interval: u32,
    /// Image width in pixels.
    #[arg(long, default_value_t = 640, value_parser = clap::value_parser!(u32).range(16..=8192))]
    width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 360, value_parser = clap::value_parser!(u32).range(16..=8192))]
    height: u32,
    /// Streaming policy: adaptive (paper Eq. 4-7), baseline (s = s_max, b = 0) or fixed.
    #[arg(long, default_value = "adaptive")]
    policy: PolicyKind,
    /// Target maximum frame latency α in ms (adaptive).
    #[arg(long, default_value_t = 16.0)]
    alpha: f64,
    /// Maximum mip bias β (adaptive).
    #[arg(long, default_value_t = 8.0)]
    beta: f64,
    /// Load size in MB (fixed policy).
    #[arg(long, default_value_t = 4.0)]
    load_size_mb: f64,
    /// Mip bias (fixed policy).
    #[arg(long, default_value_t = 0.0)]
    mip_bias: f64,
    /// Modelled cost of binding sparse memory: none, lavapipe or desktop.
    #[arg(long, default_value = "none")]
    bind_latency: BindLatencyPreset,
    /// Clock: real (measured) or fixed (reproducible, modelled latency).
    #[arg(long, value_enum, default_value_t = Clock::Real)]
    clock: Clock,
    /// Memory budget of bound texture blocks in MB.
    #[arg(long, default_value_t = 512)]
    memory_budget_mb: u64,
    /// Seconds the camera takes for one orbit of the city.
    #[arg(long, default_value_t = 20.0)]
    orbit_s: f64,
    /// Pick the Vulkan device whose name contains this text (also CITYSTREAM_DEVICE).
    #[arg(long)]
    device: Option<String>,
    /// Seed of the placeholder city and of the bind-latency model's spikes.
    #[arg(long, default_value_t = 7)]
    seed: u64,
    /// Blocks per side of the placeholder city (without --dataset).
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u32).range(1..=200))]
    blocks: u32,
    /// Enable the Vulkan validation layer (default: on in debug builds).
    #[arg(long)]
    validation: Option<bool>,
}

/// Fixed clock: the time step and the modelled render cost of a frame.
const FIXED_STEP_MS: f64 = 1000.0 / 60.0;
const FIXED_RENDER_MS: f64 = 8.0;

#[derive(Debug, serde::Serialize)]
struct Run<'a> {
    device: String,
    scene: String,
    policy: &'a str,
    clock: &'a str,
    bind_latency: &'a str,
    width: u32,
    height: u32,
    duration_s: f64,
    mips_streamed: u64,
    blocks_bound: u64,
    peak_resident_bytes: u64,
    validation_errors: usize,
    frames_written: Vec<String>,
}

fn main() -> Result<()> {
    let args = Args::parse();
    let device = Arc::new(
        Device::new(&DeviceOptions {
            instance: InstanceOptions {
                validation: args.validation.unwrap_or_else(default_validation),
                app_name: "citystream flythrough".into(),
            },
            device_name: args.device.clone(),
        })
        .context("creating the Vulkan device")?,
    );
    eprintln!("device: {}", describe(&device));
    let frames_dir = args.out.join("frames");
    std::fs::create_dir_all(&frames_dir).with_context(|| format!("creating {}", frames_dir.display()))?;
    match &args.dataset {
        Some(dir) => stream_city(&args, &device, dir),
        None => placeholder_city(&args, &device),
    }
}

/// An orbit around `centre` over a scene `extent` wide and `tall` high:
/// close over a flat city, clear of a single tall model.
fn orbit_camera(centre: Vec3, extent: f32, tall: f32, t: f64) -> Camera {
    let angle = (t as f32) * std::f32::consts::TAU;
    let radius = extent * 0.55 + tall * 1.5;
    let height = extent * (0.18 + 0.12 * (angle * 2.0).sin().abs()) + tall;
    Camera {
        eye: centre + Vec3::new(angle.cos() * radius, height, angle.sin() * radius),
        target: centre,
        fov_y: 60f32.to_radians(),
        // Scaled to the scene, so a one-metre model and a city both fit the depth range.
        near: extent * 1e-3,
        far: (extent + tall) * 4.0,
    }
}

fn status(frame: u32, frames: u32, dt: f64, s_mb: f64, b: f64, mb_s: f64, resident_mb: f64) {
    eprint!(
        "\rframe {:>6}/{frames}  dt {dt:7.2} ms  s {s_mb:7.2} MB  b {b:4.2}  {mb_s:7.2} MB/s  resident {resident_mb:8.1} MB",
        frame + 1
    );
    let _ = std::io::stderr().flush();
}

fn stream_city(args: &Args, device: &Arc<Device>, dir: &std::path::Path) -> Result<()> {
    let dataset = Arc::new(Dataset::open(dir).with_context(|| format!("opening dataset {}", dir.display()))?);
    let scene = &dataset.scene;
    let vertices: Vec<Vertex> = scene
        .positions
        .iter()
        .zip(&scene.normals)
        .zip(&scene.uvs)
        .map(|((p, n), uv)| Vertex {
            position: *p,
            normal: *n,
            uv: *uv,
        })
        .collect();
    let meshes = scene
        .meshes
        .iter()
        .map(|m| {
            let info = dataset.textures.info(m.texture)?;
            Ok(CityMesh {
                first_index: m.first_index,
                index_count: m.index_count,
                vertex_offset: m.first_vertex,
                texture: m.texture,
                texture_width: info.width(),
                texture_height: info.height(),
            })
        })
        .collect::<Result<Vec<_>, citystream_streaming::dataset::DatasetError>>()?;
    let mut commands = CommandContext::new(device, "flythrough frame")?;
    let mut cache = GpuTextureCache::new(
        device,
        &mut commands,
        &GpuCacheConfig {
            layer_size: 2048,
            layer_count: 64,
            memory_budget_bytes: args.memory_budget_mb << 20,
            virtual_budget_bytes: None,
            blocks_per_chunk: 256,
            texture_count: dataset.textures.len(),
            filtering: Filtering::BilinearNearestLevel,
        },
        dataset.colormap.colours(),
    )?;
    let mesh_count = meshes.len() as u32;
    let compactor = FeedbackCompactor::new(device, &mut commands, mesh_count, mesh_count)?;
    let renderer = CityRenderer::new(
        device,
        &mut commands,
        &vertices,
        &scene.indices,
        meshes,
        &cache,
        &compactor,
    )?;
    let target = RenderTarget::new(device, args.width, args.height)?;
    let feedback_target = RenderTarget::new(device, (args.width / 4).max(16), (args.height / 4).max(16))?;
    let policy = args
        .policy
        .build(&PolicyOptions {
            alpha_ms: args.alpha,
            beta: args.beta,
            s_max_mb: 64.0,
            s_min_bytes: 64 * 1024,
            fixed_load_size_mb: args.load_size_mb,
            fixed_mip_bias: args.mip_bias,
        })
        .context("building the streaming policy")?;
    let mut streamer = Streamer::new(
        Arc::clone(&dataset),
        policy,
        DEFAULT_WEIGHT_CUTOFF,
        LoaderOptions::default(),
    )?;
    let latency = BindLatencyModel::preset(args.bind_latency);
    let mut latency_rng = SplitMix64::new(args.seed);

    let bounds = scene.bounds;
    let centre = Vec3::from(bounds.center());
    let size = Vec3::from(bounds.max) - Vec3::from(bounds.min);
    let extent = size.x.max(size.z).max(1.0);
    let view = FeedbackView::default();
    eprintln!(
        "scene: {} ({} meshes, {} textures)",
        dir.display(),
        scene.meshes.len(),
        dataset.textures.len()
    );

    let mut summary = SummaryBuilder::new();
    let mut clock = CpuFrameClock::new();
    let started = std::time::Instant::now();
    let mut written = Vec::new();
    let mut sim_time_s = 0.0f64;
    let mut frame_ms = FIXED_STEP_MS;
    let (mut mips_total, mut blocks_total, mut peak_resident) = (0u64, 0u64, 0u64);
    for frame in 0..args.frames {
        let t = match args.clock {
            Clock::Fixed => sim_time_s,
            Clock::Real => started.elapsed().as_secs_f64(),
        } / args.orbit_s.max(0.1);
        let camera = orbit_camera(centre, extent, size.y.max(0.0), t);

        // Algorithm 1: feedback and compaction, then the frame. The
        // compacted records go to the host only when no loading task runs.
        let idle = !streamer.is_streaming();
        let cmd = commands.begin()?;
        renderer.record_feedback(cmd, &feedback_target, &camera, &view, args.height)?;
        compactor.record_compact(cmd, (DEFAULT_WEIGHT_CUTOFF as f32 * FEEDBACK_WEIGHT_ONE) as u32, idle);
        renderer.record_visible(cmd, &target, &camera, 1.0);
        commands.submit_and_wait(&[])?;
        if args.frame_interval > 0 && frame % args.frame_interval == 0 {
            let path = frames_dir_path(args).join(format!("frame_{frame:05}.png"));
            write_png(&target.read_pixels()?, &path)?;
            written.push(path.display().to_string());
        }

        // Controller, then a loading task if none runs.
        let decision = streamer.update_policy(frame_ms);
        let mut bytes_this_frame = 0;
        let mut mips_this_frame = 0;
        let mut bind_cost_ms = 0.0;
        if idle {
            let feedback = compactor.read_back(&mut commands)?;
            match args.clock {
                Clock::Fixed => {
                    streamer.run_cycle_now(&feedback.entries, decision);
                }
                Clock::Real => {
                    streamer.start_cycle(&feedback.entries, decision);
                }
            }
        }
        // Upload what the loader staged (all of it with the fixed clock).
        let applied = streamer.apply(&mut cache, &mut commands)?;
        if applied.cache.blocks_bound + applied.cache.blocks_unbound > 0 {
            let runs = u64::from(applied.cache.bind_entries);
            let blocks = u64::from(applied.cache.blocks_bound + applied.cache.blocks_unbound);
            bind_cost_ms = latency.cost_s(blocks, runs, &mut latency_rng) * 1000.0;
            if args.clock == Clock::Real && bind_cost_ms > 0.0 {
                std::thread::sleep(Duration::from_secs_f64(bind_cost_ms / 1000.0));
            }
        }
        bytes_this_frame += applied.cache.bytes_uploaded;
        mips_this_frame += u64::from(applied.cache.mips_uploaded);
        mips_total += mips_this_frame;
        blocks_total += u64::from(applied.cache.blocks_bound);
        peak_resident = peak_resident.max(cache.utilisation().bound_bytes);

        let measured = clock.tick().as_secs_f64() * 1000.0;
        frame_ms = match args.clock {
            Clock::Real => measured,
            Clock::Fixed => FIXED_RENDER_MS + bind_cost_ms,
        };
        sim_time_s += FIXED_STEP_MS / 1000.0;
        let telemetry = streamer.policy().telemetry();
        summary.push_frame(
            frame_ms,
            telemetry.tw_ms,
            telemetry.load_size_mb,
            telemetry.mip_bias,
            mips_this_frame,
            bytes_this_frame,
        );
        let mb_per_s = bytes_this_frame as f64 / 1e6 / (frame_ms / 1000.0).max(1e-6);
        status(
            frame,
            args.frames,
            frame_ms,
            telemetry.load_size_mb,
            telemetry.mip_bias,
            mb_per_s,
            cache.utilisation().bound_bytes as f64 / 1e6,
        );
    }
    eprintln!();
    device.wait_idle()?;
    let validation_errors = device.validation_log().error_count();
    let summary = summary.finish();
    let run = Run {
        device: describe(device),
        scene: dir.display().to_string(),
        policy: streamer.policy().kind().name(),
        clock: match args.clock {
            Clock::Real => "real",
            Clock::Fixed => "fixed",
        },
        bind_latency: args.bind_latency.name(),
        width: args.width,
        height: args.height,
        duration_s: started.elapsed().as_secs_f64(),
        mips_streamed: mips_total,
        blocks_bound: blocks_total,
        peak_resident_bytes: peak_resident,
        validation_errors,
        frames_written: written,
    };
    let mut json = serde_json::to_value(summary)?;
    if let (Some(object), serde_json::Value::Object(extra)) = (json.as_object_mut(), serde_json::to_value(&run)?) {
        object.extend(extra);
    }
    let path = args.out.join("summary.json");
    std::fs::write(&path, serde_json::to_string_pretty(&json)?)
        .with_context(|| format!("writing {}", path.display()))?;
    eprintln!(
        "{} frames, {} mips streamed, wrote {} frames and {}",
        args.frames,
        mips_total,
        run.frames_written.len(),
        path.display()
    );
    drop(renderer);
    drop(compactor);
    drop(cache);
    if validation_errors > 0 {
        bail!("{validation_errors} Vulkan validation error(s) during the run");
    }
    Ok(())
}

fn frames_dir_path(args: &Args) -> PathBuf {
    args.out.join("frames")
}

fn placeholder_city(args: &Args, device: &Arc<Device>) -> Result<()> {
    let geometry = placeholder::city(args.seed, args.blocks);
    let textures = placeholder::textures(args.seed)?;
    let mut commands = CommandContext::new(device, "flythrough frame")?;
    let renderer = MeshRenderer::new(
        device,
        &mut commands,
        &geometry,
        &textures,
        Filtering::Trilinear { max_anisotropy: 8 },
    )?;
    let target = RenderTarget::new(device, args.width, args.height)?;
    let extent = args.blocks as f32 * 30.0;
    let aspect = args.width as f32 / args.height as f32;
    let mut clock = CpuFrameClock::new();
    let mut summary = SummaryBuilder::new();
    let mut written = Vec::new();
    let started = std::time::Instant::now();
    for frame in 0..args.frames {
        let camera = orbit_camera(
            Vec3::new(0.0, 15.0, 0.0),
            extent,
            0.0,
            frame as f64 / args.frames as f64,
        );
        let cmd = commands.begin()?;
        target.begin(device, cmd, [0.55, 0.7, 0.9, 1.0]);
        renderer.record(cmd, camera.view_projection(aspect, 0.0), [0.4, 0.8, 0.3, 1.0]);
        target.end_and_copy(device, cmd);
        commands.submit_and_wait(&[])?;
        if args.frame_interval > 0 && frame % args.frame_interval == 0 {
            let path = frames_dir_path(args).join(format!("frame_{frame:05}.png"));
            write_png(&target.read_pixels()?, &path)?;
            written.push(path.display().to_string());
        }
        let dt = clock.tick().as_secs_f64() * 1000.0;
        summary.push_frame(dt, dt, 0.0, 0.0, 0, 0);
        status(frame, args.frames, dt, 0.0, 0.0, 0.0, 0.0);
    }
    eprintln!();
    device.wait_idle()?;
    let validation_errors = device.validation_log().error_count();
    let mut json = serde_json::to_value(summary.finish())?;
    if let Some(object) = json.as_object_mut() {
        object.insert("device".into(), describe(device).into());
        object.insert(
            "scene".into(),
            format!(
                "placeholder city (seed {}, {}x{} blocks)",
                args.seed, args.blocks, args.blocks
            )
            .into(),
        );
        object.insert("duration_s".into(), started.elapsed().as_secs_f64().into());
        object.insert("validation_errors".into(), validation_errors.into());
        object.insert("frames_written".into(), written.into());
    }
    let path = args.out.join("summary.json");
    std::fs::write(&path, serde_json::to_string_pretty(&json)?)
        .with_context(|| format!("writing {}", path.display()))?;
    eprintln!("wrote {}", path.display());
    if validation_errors > 0 {
        bail!("{validation_errors} Vulkan validation error(s) during the run");
    }
    Ok(())
}
