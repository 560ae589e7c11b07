//! The placeholder city (`--placeholder`): the engine's generated blocks and textures, no
//! dataset and no streaming, flown around on an orbit.

use std::sync::Arc;

use anyhow::{bail, Result};
use glam::Vec3;

use citystream_engine::city::Camera;
use citystream_engine::commands::CommandContext;
use citystream_engine::device::describe;
use citystream_engine::pipeline::Filtering;
use citystream_engine::placeholder;
use citystream_engine::scene::MeshRenderer;
use citystream_engine::target::RenderTarget;
use citystream_engine::timing::CpuFrameClock;
use citystream_engine::Device;
use citystream_gen::files::write_atomically;
use citystream_streaming::bench::stats::SummaryBuilder;

use super::args::{writes_frame, Args};
use super::output::{status, write_frame_png};

/// An orbit around `centre` over a scene `extent` wide and `tall` high:
/// close over a flat city, clear of a single tall model.
fn orbit_camera(centre: Vec3, extent: f32, tall: f32, t: f64) -> Camera {
    let angle = (t as f32) * std::f32::consts::TAU;
    let radius = extent * 0.55 + tall * 1.5;
    let height = extent * (0.18 + 0.12 * (angle * 2.0).sin().abs()) + tall;
    Camera {
        eye: (centre + Vec3::new(angle.cos() * radius, height, angle.sin() * radius)).as_dvec3(),
        target: centre.as_dvec3(),
        fov_y: 60f32.to_radians(),
        // Scaled to the scene: the orbit stays outside it, a one-metre model and a city alike.
        near: extent * 1e-3,
    }
}

/// Flies the orbit around the placeholder city (`--placeholder`), writing PNG frames and
/// `summary.json`.
///
/// Not through [`Flight`](super::flight::Flight): a flight is a streamed dataset (its
/// streamer, cache and city passes), where the placeholder city is the engine's meshes with
/// their textures whole, drawn by a `MeshRenderer` and waited for frame by frame. Its frames
/// are written as the headless flight writes its own ([`write_frame_png`]).
pub(crate) fn placeholder_city(args: &Args, device: &Arc<Device>) -> Result<()> {
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
    let frames = args.frames.unwrap_or(240);
    for frame in 0..frames {
        let camera = orbit_camera(Vec3::new(0.0, 15.0, 0.0), extent, 0.0, frame as f64 / frames as f64);
        let cmd = commands.begin()?;
        target.begin(device, cmd, [0.55, 0.7, 0.9, 1.0]);
        renderer.record(cmd, camera.view_projection(aspect, 0.0), [0.4, 0.8, 0.3, 1.0]);
        target.end_and_copy(device, cmd);
        commands.submit_and_wait(&[])?;
        if writes_frame(args, frame) {
            write_frame_png(args, frame, &target.read_pixels()?, &mut written)?;
        }
        let dt = clock.tick().as_secs_f64() * 1000.0;
        summary.push_frame(dt, dt, dt, 0.0, 0.0, 0, 0);
        status(frame, frames, dt, 0.0, 0.0, 0.0, 0.0);
    }
    if std::io::IsTerminal::is_terminal(&std::io::stderr()) {
        eprintln!();
    }
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
    write_atomically(&path, serde_json::to_string_pretty(&json)?.as_bytes())?;
    eprintln!("wrote {}", path.display());
    if validation_errors > 0 {
        bail!("{validation_errors} Vulkan validation error(s) during the run");
    }
    Ok(())
}
