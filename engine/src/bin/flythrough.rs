//! `flythrough`: renders a city headless along a camera path, writing PNG
//! frames and a JSON report of frame timings.

use std::io::Write;
use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use clap::Parser;
use glam::Vec3;

use citystream_engine::commands::CommandContext;
use citystream_engine::device::describe;
use citystream_engine::instance::{default_validation, InstanceOptions};
use citystream_engine::pipeline::Filtering;
use citystream_engine::placeholder;
use citystream_engine::scene::{colormap_geometry, MeshRenderer, TextureArrayData};
use citystream_streaming::dataset::Dataset;
use citystream_engine::target::{write_png, RenderTarget};
use citystream_engine::timing::{CpuFrameClock, GpuTimer};
use citystream_engine::{Device, DeviceOptions};

#[derive(Debug, Parser)]
#[command(
    name = "flythrough",
    version,
    about = "Render a textured city headless along a camera path and report frame timings",
    long_about = "Renders a textured city off-screen (no window) along a camera path, writes every \
                  N-th frame as PNG and a report.json with CPU and GPU frame times.\n\n\
                  With --dataset, every mesh is drawn in its City Colormap colour (what the \
                  streaming renderer shows before any mip is resident). Without --dataset it \
                  renders a small procedural city of textured boxes."
)]
struct Args {
    /// City dataset directory (written by `citystream gen` or `citystream import`).
    /// Without it, a small procedural placeholder city is rendered.
    #[arg(long)]
    dataset: Option<PathBuf>,
    /// Output directory for frames/ and report.json.
    #[arg(long, default_value = "out/flythrough")]
    out: PathBuf,
    /// Number of frames to render.
    #[arg(long, default_value_t = 120, value_parser = clap::value_parser!(u32).range(1..=1_000_000))]
    frames: u32,
    /// Write every N-th frame as PNG (0 writes none).
    #[arg(long, default_value_t = 10)]
    frame_interval: u32,
    /// Image width in pixels.
    #[arg(long, default_value_t = 640, value_parser = clap::value_parser!(u32).range(16..=8192))]
    width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 360, value_parser = clap::value_parser!(u32).range(16..=8192))]
    height: u32,
    /// Pick the Vulkan device whose name contains this text (also CITYSTREAM_DEVICE).
    #[arg(long)]
    device: Option<String>,
    /// Seed of the procedural placeholder city.
    #[arg(long, default_value_t = 7)]
    seed: u64,
    /// Blocks per side of the placeholder city.
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u32).range(1..=200))]
    blocks: u32,
    /// Enable the Vulkan validation layer (default: on in debug builds).
    #[arg(long)]
    validation: Option<bool>,
}

#[derive(Debug, serde::Serialize)]
struct Stats {
    median: f64,
    mean: f64,
    max: f64,
    min: f64,
}

impl Stats {
    fn of(values: &[f64]) -> Option<Self> {
        if values.is_empty() {
            return None;
        }
        let mut sorted = values.to_vec();
        sorted.sort_by(f64::total_cmp);
        let n = sorted.len();
        let median = if n % 2 == 1 {
            sorted[n / 2]
        } else {
            (sorted[n / 2 - 1] + sorted[n / 2]) / 2.0
        };
        Some(Self {
            median,
            mean: sorted.iter().sum::<f64>() / n as f64,
            max: sorted[n - 1],
            min: sorted[0],
        })
    }
}

#[derive(Debug, serde::Serialize)]
struct Report {
    device: String,
    scene: String,
    frames: u32,
    width: u32,
    height: u32,
    meshes: usize,
    triangles: usize,
    duration_s: f64,
    frame_ms: Option<Stats>,
    gpu_ms: Option<Stats>,
    frames_written: Vec<String>,
    validation_errors: usize,
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

    let (geometry, textures, scene_name, centre, extent) = match &args.dataset {
        Some(dir) => {
            let dataset = Dataset::open(dir).with_context(|| format!("opening dataset {}", dir.display()))?;
            let geometry = colormap_geometry(&dataset)?;
            let white = TextureArrayData::from_base_levels(1, vec![vec![255; 4]])?;
            let bounds = dataset.scene.bounds;
            let centre = Vec3::from(bounds.center());
            let size = Vec3::from(bounds.max) - Vec3::from(bounds.min);
            let name = format!(
                "dataset {} ({} meshes, {} textures, City Colormap colours)",
                dir.display(),
                dataset.scene.meshes.len(),
                dataset.textures.len()
            );
            (geometry, white, name, centre, size.x.max(size.z).max(1.0))
        }
        None => {
            let name = format!("placeholder city (seed {}, {}x{} blocks)", args.seed, args.blocks, args.blocks);
            let extent = args.blocks as f32 * 30.0;
            (
                placeholder::city(args.seed, args.blocks),
                placeholder::textures(args.seed)?,
                name,
                Vec3::new(0.0, 15.0, 0.0),
                extent,
            )
        }
    };
    eprintln!("scene: {scene_name}");
    let mut commands = CommandContext::new(&device, "flythrough frame")?;
    let renderer = MeshRenderer::new(
        &device,
        &mut commands,
        &geometry,
        &textures,
        Filtering::Trilinear { max_anisotropy: 8 },
    )?;
    let target = RenderTarget::new(&device, args.width, args.height)?;
    let timer = GpuTimer::new(&device, 1)?;
    let frames_dir = args.out.join("frames");
    std::fs::create_dir_all(&frames_dir).with_context(|| format!("creating {}", frames_dir.display()))?;

    let radius = extent * 0.7;
    let aspect = args.width as f32 / args.height as f32;
    let mut clock = CpuFrameClock::new();
    let started = std::time::Instant::now();
    let mut frame_ms = Vec::with_capacity(args.frames as usize);
    let mut gpu_ms = Vec::with_capacity(args.frames as usize);
    let mut written = Vec::new();
    for frame in 0..args.frames {
        let t = frame as f32 / args.frames as f32;
        let angle = t * std::f32::consts::TAU;
        let height = radius * (0.3 + 0.2 * (angle * 2.0).sin().abs());
        let eye = centre + Vec3::new(angle.cos() * radius, height, angle.sin() * radius);
        let view_proj = placeholder::view_projection(eye, centre, aspect, 1.0, radius * 4.0);

        let cmd = commands.begin()?;
        timer.begin(cmd, 0);
        target.begin(&device, cmd, [0.55, 0.7, 0.9, 1.0]);
        renderer.record(cmd, view_proj, [0.4, 0.8, 0.3, 1.0]);
        target.end_and_copy(&device, cmd);
        timer.end(cmd, 0);
        commands.submit_and_wait(&[])?;
        if let Some(ms) = timer.read_ms(0)? {
            gpu_ms.push(ms);
        }
        if args.frame_interval > 0 && frame % args.frame_interval == 0 {
            let path = frames_dir.join(format!("frame_{frame:05}.png"));
            write_png(&target.read_pixels()?, &path)?;
            written.push(path.display().to_string());
        }
        let dt = clock.tick().as_secs_f64() * 1000.0;
        frame_ms.push(dt);
        eprint!("\rframe {:>5}/{}  dt {:7.2} ms", frame + 1, args.frames, dt);
        let _ = std::io::stderr().flush();
    }
    eprintln!();
    device.wait_idle()?;

    let validation_errors = device.validation_log().error_count();
    let report = Report {
        device: describe(&device),
        scene: scene_name,
        frames: args.frames,
        width: args.width,
        height: args.height,
        meshes: geometry.meshes.len(),
        triangles: geometry.indices.len() / 3,
        duration_s: started.elapsed().as_secs_f64(),
        frame_ms: Stats::of(&frame_ms),
        gpu_ms: Stats::of(&gpu_ms),
        frames_written: written,
        validation_errors,
    };
    let report_path = args.out.join("report.json");
    std::fs::write(&report_path, serde_json::to_string_pretty(&report)?)
        .with_context(|| format!("writing {}", report_path.display()))?;
    eprintln!(
        "wrote {} frames to {} and {}",
        report.frames_written.len(),
        frames_dir.display(),
        report_path.display()
    );
    if validation_errors > 0 {
        bail!("{validation_errors} Vulkan validation error(s) during the run");
    }
    Ok(())
}
