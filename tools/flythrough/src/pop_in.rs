//! The pop-in measurement (`--pop-in`): one static view refined level by level, with and
//! without City Colormap blending (Eq. 8).

use std::sync::Arc;

use anyhow::{bail, Context, Result};

use citystream_bench::image_error::mse;
use citystream_engine::commands::CommandContext;
use citystream_engine::gpu_types::FEEDBACK_MIP_ONE;
use citystream_engine::Device;
use citystream_gen::files::{write_atomically, write_png};
use citystream_streaming::controller::{PolicyKind, PolicyOptions};
use citystream_streaming::source::MipSource;

use super::args::{frame_interval, frames_dir_path, Args};
use super::camera::{camera_path, pose_camera, SceneBox};
use super::city_gpu::{cache_layer_size, city_gpu, city_targets, reference_config, CityGpu, CityTargets};
use super::dataset::open_city;
use super::measure::feedback_frame_now;
use super::passes::{self, Compaction};

#[derive(Debug, serde::Serialize)]
pub(crate) struct PopIn {
    pub(crate) frames: u32,
    pub(crate) max_mse_direct: f64,
    pub(crate) max_mse_blended: f64,
    pub(crate) mse_direct: Vec<f64>,
    pub(crate) mse_blended: Vec<f64>,
    pub(crate) paper_max_mse_direct: f64,
    pub(crate) paper_max_mse_blended: f64,
}

pub(crate) fn pop_in(args: &Args, device: &Arc<Device>, dir: &std::path::Path) -> Result<()> {
    let (dataset, city, _) = open_city(args, dir)?;
    let meshes = &city.1;
    let scene = &dataset.scene;
    let layer_size = cache_layer_size(&dataset, device);
    let mut commands = CommandContext::new(device, "pop-in frame")?;
    let CityTargets {
        target,
        feedback_target,
        view,
        fragment_area,
    } = city_targets(device, args.width, args.height)?;
    // Levels are loaded explicitly, one per frame: the policy never runs.
    let mut gpu = city_gpu(
        device,
        &mut commands,
        &dataset,
        &city,
        PolicyKind::Baseline.build(&PolicyOptions::default())?,
        &reference_config(fragment_area, layer_size),
        None,
        None,
        args.culling,
    )?;
    // The view of the path's first pause: the static view a user replaying
    // the benchmark sees longest.
    let path = camera_path(args.path.as_deref().unwrap_or("standard"), scene)?;
    let at = path.pauses().first().map_or(0.0, |p| p.start_s);
    let camera = pose_camera(&path.sample_between(None, at), SceneBox::of(scene));
    // What the static view needs: one streamer frame of feedback.
    let index = feedback_frame_now(
        &mut gpu,
        &mut commands,
        (&feedback_target, &view),
        &camera,
        args.height,
        Compaction::Streamer,
    )?;
    let entries = gpu
        .streamer
        .feedback_of(index)?
        .context("the pop-in view's feedback frame did not complete")?
        .entries;
    let source = gpu.streamer.source().inner().clone();
    let mut wanted: Vec<(u32, u32, u32)> = Vec::new(); // (texture, needed level, next level to load)
    for entry in &entries {
        let Some(mesh) = meshes.get(entry.mesh_id as usize) else {
            continue;
        };
        let chain = source.mip_chain(mesh.texture)?;
        let needed = (entry.mip / FEEDBACK_MIP_ONE as u32).min(chain.mip_count - 1);
        wanted.push((mesh.texture, needed, chain.mip_count - 1));
    }
    wanted.sort_unstable();
    wanted.dedup_by_key(|w| w.0);
    eprintln!("pop-in: {} textures refine from their coarsest level", wanted.len());

    // Not a [`Flight`](super::flight::Flight)'s frames: a flight's policy loads what its
    // feedback asks for over frames, where here the levels are loaded explicitly, one a
    // step, and the view drawn twice a step (direct, blended) and waited for. The visible
    // pass is the one the flight records ([`passes::draw_now`]).
    let render = |gpu: &CityGpu, commands: &mut CommandContext, blend: bool| -> Result<image::RgbaImage> {
        passes::draw_now(commands, &gpu.renderer, (&target, &camera), blend, None)?;
        Ok(target.read_pixels()?)
    };
    let mut previous: Option<(image::RgbaImage, image::RgbaImage)> = None;
    let (mut mse_direct, mut mse_blended) = (Vec::new(), Vec::new());
    let mut frames = 0;
    loop {
        // Frame 0 shows nothing resident; each later frame loads one level,
        // the next finer one, of every texture still coarser than needed.
        let mut levels = Vec::new();
        for (texture, needed, next) in wanted.iter_mut() {
            if frames == 0 || *next == u32::MAX || *next < *needed {
                continue;
            }
            levels.push((*texture, *next));
            *next = next.checked_sub(1).unwrap_or(u32::MAX);
        }
        let loaded = levels.len();
        gpu.streamer.load_levels_now(&levels, &mut commands)?;
        let direct = render(&gpu, &mut commands, false)?;
        let blended = render(&gpu, &mut commands, true)?;
        if frame_interval(args) > 0 && frames % frame_interval(args) == 0 {
            write_png(
                &direct,
                &frames_dir_path(args).join(format!("popin_direct_{frames:03}.png")),
            )?;
            write_png(
                &blended,
                &frames_dir_path(args).join(format!("popin_blended_{frames:03}.png")),
            )?;
        }
        if let Some((d, b)) = &previous {
            mse_direct.push(mse(d, &direct));
            mse_blended.push(mse(b, &blended));
        }
        previous = Some((direct, blended));
        frames += 1;
        if (frames > 1 && loaded == 0) || frames > 64 {
            break;
        }
    }
    device.wait_idle()?;
    let max = |v: &[f64]| v.iter().copied().fold(0.0f64, f64::max);
    let result = PopIn {
        frames,
        max_mse_direct: max(&mse_direct),
        max_mse_blended: max(&mse_blended),
        mse_direct,
        mse_blended,
        paper_max_mse_direct: 438.0,
        paper_max_mse_blended: 62.0,
    };
    let path = args.out.join("popin.json");
    write_atomically(&path, serde_json::to_string_pretty(&result)?.as_bytes())?;
    println!(
        "pop-in over {} frames: max inter-frame MSE {:.1} with direct sampling, {:.1} with colormap blending \
         (paper: 438 -> 62); wrote {}",
        result.frames,
        result.max_mse_direct,
        result.max_mse_blended,
        path.display()
    );
    drop(gpu);
    let errors = device.validation_log().error_count();
    if errors > 0 {
        bail!("{errors} Vulkan validation error(s) during the run");
    }
    Ok(())
}
