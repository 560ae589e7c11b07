//! The ground layer (flexible clipmap) on lavapipe: the rendered ground against a CPU
//! composition of the same patches, and a patch inserted at run time reaching the screen
//! through exactly the tiles it overlaps.

use std::collections::HashSet;
use std::sync::Arc;

use anyhow::{ensure, Result};
use citystream_bench::image_error::psnr_db;
use citystream_engine::city::Camera;
use citystream_engine::commands::CommandContext;
use citystream_engine::ground::{GroundAllowance, GroundConfig, GroundLayer};
use citystream_engine::target::RenderTarget;
use citystream_engine::Device;
use citystream_streaming::clipmap::Patch;
use citystream_streaming::ground::{GroundImagery, PatchImage};
use citystream_tests::{assert_no_validation_errors, validated_device};
use glam::{Mat4, Vec4};

const SIZE: u32 = 256;
/// The rendered ground against the CPU composition of its patches. Measured on lavapipe:
/// 42.6 dB, and 39.8 dB after the insertion below; the stale render before the new
/// patch's tiles are uploaded, 18.8 dB.
const MIN_PSNR_DB: f64 = 35.0;
const CLEAR: [u8; 4] = [0, 0, 0, 255];

/// A smooth RGBA pattern of `width × height` texels over `min..max` on the ground (a
/// function of ground position, so patches of one `seed` agree where they overlap).
fn pattern(min: [f64; 2], max: [f64; 2], width: u32, height: u32, seed: f64) -> PatchImage {
    let mut bytes = Vec::with_capacity((width * height * 4) as usize);
    for y in 0..height {
        for x in 0..width {
            let gx = min[0] + (f64::from(x) + 0.5) / f64::from(width) * (max[0] - min[0]);
            let gz = min[1] + (f64::from(y) + 0.5) / f64::from(height) * (max[1] - min[1]);
            let channel = |f: f64, phase: f64| (128.0 + 100.0 * (gx * f + gz * f * 0.7 + phase + seed).sin()) as u8;
            bytes.extend([channel(0.05, 0.0), channel(0.031, 2.0), channel(0.017, 4.0), 255]);
        }
    }
    PatchImage::from_rgba8(width, height, &bytes).expect("pattern image")
}

fn patch(id: u64, min: [f64; 2], max: [f64; 2], metres_per_texel: f64) -> (Patch, u32, u32) {
    let width = ((max[0] - min[0]) / metres_per_texel).round() as u32;
    let height = ((max[1] - min[1]) / metres_per_texel).round() as u32;
    (Patch::new(id, min, max, metres_per_texel, id as f64), width, height)
}

fn camera() -> Camera {
    Camera {
        eye: glam::DVec3::new(3.0, 120.0, 4.0),
        target: glam::DVec3::new(3.0, 0.0, 4.01),
        fov_y: 60f32.to_radians(),
        near: 1.0,
    }
}

/// The ground point under pixel centre `(px, py)` (continuous), if the ray meets y = 0.
fn ground_under(inverse: Mat4, px: f64, py: f64) -> Option<[f64; 2]> {
    let ndc = |v: f64, size: u32| (v / f64::from(size) * 2.0 - 1.0) as f32;
    let unproject = |z: f32| {
        let p = inverse * Vec4::new(ndc(px, SIZE), ndc(py, SIZE), z, 1.0);
        p.truncate() / p.w
    };
    // Reversed depth with no far plane: 1 is the near plane, 0.5 twice as far along the ray.
    let (near, far) = (unproject(1.0), unproject(0.5));
    let direction = far - near;
    if direction.y.abs() < 1e-9 {
        return None;
    }
    let t = -near.y / direction.y;
    let hit = near + direction * t;
    (t > 0.0).then_some([f64::from(hit.x), f64::from(hit.z)])
}

/// What the ground looks like from `camera`, composed on the CPU from the patches: each
/// pixel's ground point, the best patch there at the pixel's footprint.
fn cpu_reference(imagery: &GroundImagery, camera: &Camera, fallback: [f32; 3]) -> image::RgbaImage {
    let inverse = camera.view_projection(1.0, 0.0).inverse();
    let area = imagery.clipmap().area().expect("patches");
    image::RgbaImage::from_fn(SIZE, SIZE, |x, y| {
        let (px, py) = (f64::from(x) + 0.5, f64::from(y) + 0.5);
        let Some(p) = ground_under(inverse, px, py) else {
            return image::Rgba(CLEAR);
        };
        let inside = (0..2).all(|d| area.0[d] <= p[d] && p[d] <= area.1[d]);
        if !inside {
            return image::Rgba(CLEAR);
        }
        let step = |q: Option<[f64; 2]>| q.map_or(0.0, |q| ((q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2)).sqrt());
        let footprint = step(ground_under(inverse, px + 1.0, py)).max(step(ground_under(inverse, px, py + 1.0)));
        let colour = imagery.colour_at(p, footprint).unwrap_or([
            fallback[0] * 255.0,
            fallback[1] * 255.0,
            fallback[2] * 255.0,
            255.0,
        ]);
        let alpha = colour[3] / 255.0;
        let rgb = |c: usize| (fallback[c] * 255.0 * (1.0 - alpha) + colour[c] * alpha).round() as u8;
        image::Rgba([rgb(0), rgb(1), rgb(2), 255])
    })
}

/// Uploads every pending tile the view's windows hold, then renders the ground alone.
fn render(
    device: &Arc<Device>,
    commands: &mut CommandContext,
    ground: &mut GroundLayer,
    target: &RenderTarget,
    camera: &Camera,
    upload: bool,
) -> Result<image::RgbaImage> {
    let eye = [camera.eye.x, camera.eye.z];
    for _ in 0..64 {
        let frame = ground.update(
            0,
            eye,
            if upload {
                GroundAllowance::Everything
            } else {
                GroundAllowance::LoadSize(0)
            },
        )?;
        let cmd = commands.begin()?;
        ground.record_uploads(cmd, 0)?;
        commands.submit_and_wait(&[])?;
        if frame.pending == 0 || !upload {
            break;
        }
    }
    let cmd = commands.begin()?;
    target.begin(device, cmd, [0.0, 0.0, 0.0, 1.0]);
    ground.record_draw(cmd, 0, camera.view_projection(1.0, 0.0))?;
    target.end_and_copy(device, cmd);
    commands.submit_and_wait(&[])?;
    Ok(target.read_pixels()?)
}

#[test]
fn clipmap_rendered_ground_matches_the_cpu_composited_reference() -> Result<()> {
    let device = validated_device()?;
    let mut commands = CommandContext::new(&device, "clipmap ground test")?;
    let target = RenderTarget::new(&device, SIZE, SIZE)?;
    let config = GroundConfig {
        tile_texels: 64,
        cache_side: 4,
        level_slots: 8,
        staging_tiles: 128,
        frames_in_flight: 1,
        depth_bias: 0.0,
        ..GroundConfig::default()
    };
    let fallback = config.fallback;
    let mut ground = GroundLayer::new(&device, config)?;
    // A coarse base of 400 m at 2 m per texel, a finer survey inside it, and a later
    // survey of the same resolution overlapping the first: three resolutions of imagery,
    // replaced by capture time where they agree in resolution.
    let surveys = [
        (patch(0, [-200.0, -200.0], [200.0, 200.0], 2.0), 0.0),
        (patch(1, [-40.0, -30.0], [30.0, 40.0], 0.5), 1.0),
        (patch(2, [0.0, 0.0], [50.0, 50.0], 0.5), 2.0),
    ];
    for ((p, width, height), seed) in surveys {
        ground.insert(p, pattern(p.min, p.max, width, height, seed))?;
    }
    let camera = camera();
    let rendered = render(&device, &mut commands, &mut ground, &target, &camera, true)?;
    let expected = cpu_reference(ground.imagery(), &camera, fallback);
    let psnr = psnr_db(&rendered, &expected);
    eprintln!("rendered ground against the CPU composition: {psnr:.2} dB");
    if psnr < MIN_PSNR_DB {
        let dir = std::env::temp_dir();
        rendered.save(dir.join("clipmap-ground-rendered.png"))?;
        expected.save(dir.join("clipmap-ground-expected.png"))?;
    }
    ensure!(
        psnr >= MIN_PSNR_DB,
        "rendered ground {psnr:.2} dB from its CPU composition (at least {MIN_PSNR_DB}; images in the temp dir)"
    );

    // A new survey arrives over part of the view: only tiles it overlaps are composed
    // again, and until they are uploaded the screen shows the old imagery.
    let clipmap = ground.imagery().clipmap();
    let resident_before: HashSet<_> = clipmap
        .cached_tiles()
        .into_iter()
        .filter_map(|(key, resident)| resident.then_some(key))
        .collect();
    let (new, width, height) = patch(3, [-30.0, -20.0], [-5.0, 10.0], 0.25);
    // Half a period out of phase with the survey under it: unmistakable where it shows.
    let inverted = 1.0 + std::f64::consts::PI;
    let invalidated = ground.insert(new, pattern(new.min, new.max, width, height, inverted))?;
    let clipmap = ground.imagery().clipmap();
    let overlapping: HashSet<_> = resident_before
        .iter()
        .filter(|key| {
            let (min, max) = clipmap.tile_bounds(**key);
            (0..2).all(|d| min[d] < new.max[d] && new.min[d] < max[d])
        })
        .copied()
        .collect();
    ensure!(
        invalidated == overlapping.len() && invalidated > 0,
        "{invalidated} tiles invalidated, {} resident ones overlap the patch",
        overlapping.len()
    );
    let stale = render(&device, &mut commands, &mut ground, &target, &camera, false)?;
    let expected = cpu_reference(ground.imagery(), &camera, fallback);
    let stale_psnr = psnr_db(&stale, &expected);
    ensure!(
        stale_psnr < MIN_PSNR_DB,
        "the ground before uploading the new patch's tiles is already {stale_psnr:.2} dB from the new composition"
    );
    let uploaded_before = ground.totals().tiles_uploaded;
    let refreshed = render(&device, &mut commands, &mut ground, &target, &camera, true)?;
    let uploaded = ground.totals().tiles_uploaded - uploaded_before;
    // The patch is finer than every level so far: a new finest level's tiles over it enter
    // too; every other tile uploaded must overlap the patch.
    let clipmap = ground.imagery().clipmap();
    let finest = clipmap.scales().expect("levels").0;
    let new_level_tiles = clipmap
        .cached_tiles()
        .into_iter()
        .filter(|(key, resident)| *resident && key.scale == finest)
        .count();
    ensure!(
        uploaded as usize <= overlapping.len() + new_level_tiles && uploaded as usize >= overlapping.len(),
        "{uploaded} tiles uploaded for {} overlapping ones and {new_level_tiles} of the new level",
        overlapping.len()
    );
    let refreshed_psnr = psnr_db(&refreshed, &expected);
    eprintln!("after the insertion: stale {stale_psnr:.2} dB, refreshed {refreshed_psnr:.2} dB ({uploaded} tiles)");
    ensure!(
        refreshed_psnr >= MIN_PSNR_DB,
        "the refreshed ground is {refreshed_psnr:.2} dB from the composition with the new patch"
    );
    assert_no_validation_errors(&device)?;
    Ok(())
}
