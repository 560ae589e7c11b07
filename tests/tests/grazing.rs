//! The feedback's needed level at grazing angles: a textured plane 1 km ahead, its normal
//! turned from the view axis by 0° to 89.5°. For each angle the level the feedback pass
//! reports for it (the least over its fragments) is within half a level of the analytic
//! anisotropic level: texel-space derivatives of the exact ray–plane mapping at every
//! feedback pixel centre the plane covers, `log2(p_max / n)` with `n = ⌈p_max / p_min⌉`
//! samples, at most A_m = 16 (`shaders/include/lod.glsl`), less the feedback's level offset,
//! clamped to the chain, least over the pixels. And the level the visible pass samples at
//! each pixel, from textures whose levels are coloured by their index: never finer than the
//! finest resident level, never coarser than the needed level + 1. Validation on; any
//! message fails.

use anyhow::{ensure, Result};
use citystream_dataset::TextureFormat;
use citystream_engine::city::{CityMesh, CityRenderer, FeedbackView};
use citystream_engine::commands::CommandContext;
use citystream_engine::feedback::FeedbackCompactor;
use citystream_engine::gpu_types::{Vertex, FEEDBACK_MIP_ONE, FEEDBACK_UNSEEN};
use citystream_engine::target::RenderTarget;
use citystream_engine::texture_cache::{CacheLayers, GpuCacheConfig, GpuTextureCache};
use citystream_tests::{assert_no_validation_errors, camera_down_negative_z, test_cache_config, validated_device};
use glam::DVec3;

/// The feedback target's side, and the visible view's height it stands for.
const SIZE: u32 = 128;
const VISIBLE: u32 = 256;
const MARGIN: f32 = 0.25;
const FOV_Y: f32 = std::f32::consts::FRAC_PI_3;
/// The plane: centred 1 km down the view axis, 6 km wide (texture u) and 1.8 km deep
/// (texture v), so that at every angle its near edge stays 100 m or more ahead.
const DISTANCE: f64 = 1_000.0;
const WIDTH_M: f64 = 6_000.0;
const DEPTH_M: f64 = 1_800.0;
/// The texture's extent: levels from 0 to 14, none clamped at these distances.
const TEXELS: u32 = 16_384;
const MAX_ANISOTROPY: f64 = 16.0;
const ANGLES_DEG: [f64; 12] = [0.0, 15.0, 30.0, 45.0, 60.0, 70.0, 80.0, 85.0, 88.0, 89.0, 89.3, 89.5];

/// The plane at `angle_deg` from facing the eye: its corner, u and v edges (f64).
fn plane(angle_deg: f64) -> (DVec3, DVec3, DVec3) {
    let a = angle_deg.to_radians();
    let centre = DVec3::new(0.0, 0.0, -DISTANCE);
    let u_edge = DVec3::new(WIDTH_M, 0.0, 0.0);
    // Turned about x: the far side tips away from the eye, as a floor does.
    let v_edge = DVec3::new(0.0, a.cos(), -a.sin()) * DEPTH_M;
    (centre - u_edge * 0.5 - v_edge * 0.5, u_edge, v_edge)
}

/// The plane at `angle_deg` as four vertices, its texture repeated `repeats` times each way.
fn plane_vertices(angle_deg: f64, repeats: f32) -> [Vertex; 4] {
    let (corner, u_edge, v_edge) = plane(angle_deg);
    let normal = u_edge.cross(v_edge).normalize().as_vec3().to_array();
    let vertex = |p: DVec3, uv: [f32; 2]| Vertex {
        position: p.as_vec3().to_array(),
        normal,
        uv,
    };
    [
        vertex(corner, [0.0, 0.0]),
        vertex(corner + u_edge, [repeats, 0.0]),
        vertex(corner + u_edge + v_edge, [repeats, repeats]),
        vertex(corner + v_edge, [0.0, repeats]),
    ]
}

/// The texel-space footprint `(p_max, p_min)` of the plane at `angle_deg` in pixel
/// `(px, py)` of a `size`-pixel view whose half-height subtends `tan`: exact derivatives of
/// the ray–plane mapping at the pixel centre, in texels of the 16,384-texel extent. None
/// where the pixel centre misses the plane.
fn footprint(angle_deg: f64, size: u32, tan: f64, px: u32, py: u32) -> Option<(f64, f64)> {
    let (corner, u_edge, v_edge) = plane(angle_deg);
    let normal = u_edge.cross(v_edge).normalize();
    let step = 2.0 * tan / f64::from(size);
    let ray = |x: f64, y: f64| {
        DVec3::new(
            (x / f64::from(size) * 2.0 - 1.0) * tan,
            -(y / f64::from(size) * 2.0 - 1.0) * tan,
            -1.0,
        )
    };
    let texel_scale = DVec3::new(
        f64::from(TEXELS) / u_edge.length_squared(),
        f64::from(TEXELS) / v_edge.length_squared(),
        0.0,
    );
    let r = ray(f64::from(px) + 0.5, f64::from(py) + 0.5);
    let facing = normal.dot(r);
    let t = normal.dot(corner) / facing;
    if !(facing.abs() > 1e-12 && t > 0.0) {
        return None;
    }
    let p = r * t - corner;
    let (u, v) = (
        p.dot(u_edge) / u_edge.length_squared(),
        p.dot(v_edge) / v_edge.length_squared(),
    );
    if !((0.0..=1.0).contains(&u) && (0.0..=1.0).contains(&v)) {
        return None;
    }
    // d(point)/d(pixel) along x and y: t·dr + r·dt, dt = −t (n·dr) / (n·r).
    let derivative = |dr: DVec3| {
        let dp = dr * t - r * (t * normal.dot(dr) / facing);
        [dp.dot(u_edge) * texel_scale.x, dp.dot(v_edge) * texel_scale.y]
    };
    let dx = derivative(DVec3::new(step, 0.0, 0.0));
    let dy = derivative(DVec3::new(0.0, -step, 0.0));
    let (lx, ly) = (dx[0].hypot(dx[1]), dy[0].hypot(dy[1]));
    Some((lx.max(ly), lx.min(ly)))
}

/// The plane's texel coordinates (of the 16,384-texel extent) seen through the point
/// `(x, y)` of a `size`-pixel view whose half-height subtends `tan`, exactly; None off it.
fn texel_at(angle_deg: f64, size: u32, tan: f64, x: f64, y: f64) -> Option<[f64; 2]> {
    let (corner, u_edge, v_edge) = plane(angle_deg);
    let normal = u_edge.cross(v_edge).normalize();
    let r = DVec3::new(
        (x / f64::from(size) * 2.0 - 1.0) * tan,
        -(y / f64::from(size) * 2.0 - 1.0) * tan,
        -1.0,
    );
    let facing = normal.dot(r);
    let t = normal.dot(corner) / facing;
    if !(facing.abs() > 1e-12 && t > 0.0) {
        return None;
    }
    let p = r * t - corner;
    let (u, v) = (
        p.dot(u_edge) / u_edge.length_squared(),
        p.dot(v_edge) / v_edge.length_squared(),
    );
    ((0.0..=1.0).contains(&u) && (0.0..=1.0).contains(&v)).then(|| [u * f64::from(TEXELS), v * f64::from(TEXELS)])
}

/// The footprint a GPU derives for pixel `(px, py)`: differences of the exact texel
/// coordinates across its 2 × 2 quad, as implicit derivatives are defined. `fine`: the
/// differences along its own row and column; otherwise the quad's first row and column
/// for all four pixels (coarse derivatives). Either is allowed, so a bound holds for both.
fn quad_footprint(angle_deg: f64, size: u32, tan: f64, px: u32, py: u32, fine: bool) -> Option<(f64, f64)> {
    let (qx, qy) = (px & !1, py & !1);
    let (row, column) = if fine { (py, px) } else { (qy, qx) };
    let at = |x: u32, y: u32| texel_at(angle_deg, size, tan, f64::from(x) + 0.5, f64::from(y) + 0.5);
    let (x0, x1) = (at(qx, row)?, at(qx + 1, row)?);
    let (y0, y1) = (at(column, qy)?, at(column, qy + 1)?);
    let lx = (x1[0] - x0[0]).hypot(x1[1] - x0[1]);
    let ly = (y1[0] - y0[0]).hypot(y1[1] - y0[1]);
    Some((lx.max(ly), lx.min(ly)))
}

/// The level of a footprint under anisotropic filtering of at most `max_anisotropy`
/// samples (`shaders/include/lod.glsl`).
fn anisotropic_level((p_max, p_min): (f64, f64), max_anisotropy: f64) -> f64 {
    let samples = (p_max / p_min.max(1e-20) - 1.0 / 1024.0)
        .ceil()
        .clamp(1.0, max_anisotropy);
    (p_max / samples).log2()
}

/// The least needed level over the feedback pixels the plane covers, from the exact
/// derivatives of its texel coordinates.
fn analytic_level(angle_deg: f64) -> f64 {
    let tan = f64::from((FOV_Y * 0.5).tan()) * (1.0 + f64::from(MARGIN));
    let lod_offset = ((1.0 + f64::from(MARGIN)) * f64::from(VISIBLE) / f64::from(SIZE)).log2();
    let max_level = f64::from(TEXELS).log2();
    let mut least = f64::INFINITY;
    for py in 0..SIZE {
        for px in 0..SIZE {
            if let Some(footprint) = footprint(angle_deg, SIZE, tan, px, py) {
                let level = (anisotropic_level(footprint, MAX_ANISOTROPY) - lod_offset).clamp(0.0, max_level);
                least = least.min(level);
            }
        }
    }
    least
}

#[test]
fn the_feedbacks_level_is_within_half_a_level_of_the_analytic_one_from_0_to_89_5_degrees() -> Result<()> {
    let device = validated_device()?;
    let mut commands = CommandContext::new(&device, "grazing test")?;
    let cache = GpuTextureCache::new(
        &device,
        &mut commands,
        &test_cache_config(&[TextureFormat::Bc1], 1),
        &[[128, 128, 128, 255]],
    )?;
    let compactor = FeedbackCompactor::new(&device, &mut commands, 1, 1)?;
    let target = RenderTarget::new(&device, SIZE, SIZE)?;
    let camera = camera_down_negative_z(FOV_Y);
    let view = FeedbackView {
        margin: MARGIN,
        foreground_distance: 10.0,
    };
    let mut report = Vec::new();
    let mut failures = Vec::new();
    for angle in ANGLES_DEG {
        let vertices = plane_vertices(angle, 1.0);
        let mesh = CityMesh {
            first_index: 0,
            index_count: 6,
            vertex_offset: 0,
            texture: 0,
            texture_width: TEXELS,
            texture_height: TEXELS,
            origin: glam::DVec3::ZERO,
        };
        let renderer = CityRenderer::new(
            &device,
            &mut commands,
            &vertices,
            &[0, 1, 2, 0, 2, 3],
            vec![mesh],
            &cache,
            &compactor,
        )?;
        let cmd = commands.begin()?;
        renderer.record_feedback(cmd, &target, &camera, &view, VISIBLE)?;
        commands.submit_and_wait(&[])?;
        let feedback = compactor.download_mesh_feedback(&mut commands)?[0];
        // Reset the array for the next angle: a compaction that keeps nothing.
        let cmd = commands.begin()?;
        compactor.record_compact(cmd, u32::MAX, 0)?;
        commands.submit_and_wait(&[])?;
        drop(renderer);
        let analytic = analytic_level(angle);
        ensure!(analytic.is_finite(), "{angle}°: the plane covers no feedback pixel");
        if feedback.min_mip == FEEDBACK_UNSEEN {
            failures.push(format!("{angle}°: the feedback did not see the plane"));
            continue;
        }
        let measured = f64::from(feedback.min_mip) / f64::from(FEEDBACK_MIP_ONE);
        report.push(format!("{angle}°: {measured:.3} against {analytic:.3}"));
        if (measured - analytic).abs() > 0.5 {
            failures.push(format!(
                "{angle}°: feedback level {measured:.3}, analytic {analytic:.3}"
            ));
        }
    }
    eprintln!("{}", report.join("\n"));
    ensure!(failures.is_empty(), "{}", failures.join("\n"));
    // The sweep means something only if the level moves with the angle.
    let (head_on, grazing) = (analytic_level(0.0), analytic_level(89.5));
    ensure!((head_on - grazing).abs() > 1.0, "levels {head_on:.2} and {grazing:.2}");
    assert_no_validation_errors(&device)
}

#[test]
fn the_analytic_level_of_a_fronto_parallel_plane_is_its_footprint() {
    // Head on, 1 km away: a visible pixel spans 2 tan 30° · 1,000 / 256 m, a feedback pixel
    // (1 + margin) · 256 / 128 visible pixels (the offset takes that back off), and the
    // texture puts 16,384 texels over 6,000 m in u and over 1,800 m in v: v is the major
    // axis, ⌈v / u⌉ = 4 samples.
    let metres = 2.0 * f64::from((FOV_Y * 0.5).tan()) * DISTANCE / f64::from(VISIBLE);
    let (u, v) = (metres * 16_384.0 / WIDTH_M, metres * 16_384.0 / DEPTH_M);
    let expected = (v / (v / u).ceil()).log2();
    assert!(
        (analytic_level(0.0) - expected).abs() < 1e-3,
        "{} against {expected}",
        analytic_level(0.0)
    );
}

/// The visible pass's texture: 256 texels repeated 64 times over the plane, the same
/// 16,384 texels across as the feedback's; each level one colour that names it.
const LEVEL_TEXTURE: u32 = 256;
const LEVEL_REPEATS: f32 = (TEXELS / LEVEL_TEXTURE) as f32;
const LEVEL_MAX: f64 = 8.0;
/// Anisotropy of the visible pass's sampling (A_s) and the feedback's (A_m), Table 2.
const SAMPLE_ANISOTROPY: f64 = 8.0;
/// Red is 16 × the level, green 255 − 16 × the level: a blend of two levels decodes to
/// the level between them, and black (a read of what is not resident) decodes to nothing.
const LEVEL_STEP: f64 = 16.0;

fn level_colour(level: u32) -> [u8; 4] {
    let red = (f64::from(level) * LEVEL_STEP) as u8;
    [red, 255 - red, 0, 255]
}

/// The level a pixel shows, or None where it shows no level of the texture.
fn decoded_level(pixel: [u8; 4]) -> Option<f64> {
    let [red, green, blue, _] = pixel.map(i32::from);
    (blue == 0 && (red + green - 255).abs() <= 2).then(|| f64::from(red) / LEVEL_STEP)
}

#[test]
fn the_visible_pass_samples_between_the_resident_level_and_one_past_the_needed_one() -> Result<()> {
    // Per visible pixel, the level sampled (decoded from its colour) against the exact
    // mapping: never finer than the finest resident level, never coarser than the level the
    // feedback's formula asks for there (A_m = 16) + 1, whichever is coarser; from 0° to
    // 89.5° and with the finest resident level at 0, 3 and 6. The needed level takes its
    // derivatives as a GPU does, across the pixel's quad; against the derivative at the
    // pixel's centre the quad's difference is up to a third of a level coarser at 89.5°
    // (reported, not bounded: it is the rasteriser's, not the engine's).
    const RESIDENT: [u32; 3] = [0, 3, 6];
    // An 8-bit channel holds the level to a 16th: rounding moves it by half a step.
    const DECODE: f64 = 0.75 / LEVEL_STEP;
    let device = validated_device()?;
    let mut commands = CommandContext::new(&device, "grazing visible test")?;
    let mut cache = GpuTextureCache::new(
        &device,
        &mut commands,
        &GpuCacheConfig {
            layers: CacheLayers::Fixed(RESIDENT.len() as u32),
            ..test_cache_config(&[TextureFormat::Rgba8], RESIDENT.len() as u32)
        },
        &[[128, 128, 128, 255]; RESIDENT.len()],
    )?;
    for (texture, &finest) in RESIDENT.iter().enumerate() {
        for level in (finest..=LEVEL_MAX as u32).rev() {
            let side = LEVEL_TEXTURE >> level;
            let bytes: Vec<u8> = (0..side * side).flat_map(|_| level_colour(level)).collect();
            cache.stage(
                texture as u32,
                TextureFormat::Rgba8,
                LEVEL_TEXTURE,
                LEVEL_TEXTURE,
                level,
                &bytes,
            )?;
        }
    }
    cache.finish_cycle(&mut commands)?;
    let compactor = FeedbackCompactor::new(&device, &mut commands, 1, 1)?;
    let target = RenderTarget::new(&device, VISIBLE, VISIBLE)?;
    let camera = camera_down_negative_z(FOV_Y);
    let tan = f64::from((FOV_Y * 0.5).tan());
    let mut failures = Vec::new();
    let mut report = Vec::new();
    let mut pixels_checked = 0u64;
    let mut levels_seen = [false; LEVEL_MAX as usize + 1];
    for angle in ANGLES_DEG {
        let vertices = plane_vertices(angle, LEVEL_REPEATS);
        for (texture, &finest) in RESIDENT.iter().enumerate() {
            let mesh = CityMesh {
                first_index: 0,
                index_count: 6,
                vertex_offset: 0,
                texture: texture as u32,
                texture_width: LEVEL_TEXTURE,
                texture_height: LEVEL_TEXTURE,
                origin: glam::DVec3::ZERO,
            };
            let renderer = CityRenderer::new(
                &device,
                &mut commands,
                &vertices,
                &[0, 1, 2, 0, 2, 3],
                vec![mesh],
                &cache,
                &compactor,
            )?;
            let cmd = commands.begin()?;
            renderer.record_visible(cmd, &target, &camera, 0.0, false)?;
            commands.submit_and_wait(&[])?;
            let image = target.read_pixels()?;
            drop(renderer);
            let (mut finer, mut coarser, mut off) = (0.0f64, 0.0f64, 0.0f64);
            let mut past_centre = 0.0f64;
            for py in 0..VISIBLE {
                for px in 0..VISIBLE {
                    // Derivatives come from the 2 × 2 quad: all four on the plane, and
                    // the quads around them too, so no edge is near.
                    let (qx, qy) = (px & !1, py & !1);
                    let inside = (qx.saturating_sub(2)..(qx + 4).min(VISIBLE)).all(|x| {
                        (qy.saturating_sub(2)..(qy + 4).min(VISIBLE))
                            .all(|y| footprint(angle, VISIBLE, tan, x, y).is_some())
                    });
                    if !inside {
                        continue;
                    }
                    let Some(foot) = footprint(angle, VISIBLE, tan, px, py) else {
                        continue;
                    };
                    let needed = [false, true]
                        .map(|fine| quad_footprint(angle, VISIBLE, tan, px, py, fine))
                        .into_iter()
                        .flatten()
                        .map(|quad| anisotropic_level(quad, MAX_ANISOTROPY).clamp(0.0, LEVEL_MAX))
                        .fold(f64::NEG_INFINITY, f64::max);
                    let at_centre = anisotropic_level(foot, MAX_ANISOTROPY).clamp(0.0, LEVEL_MAX);
                    let expected = anisotropic_level(foot, SAMPLE_ANISOTROPY)
                        .max(f64::from(finest))
                        .clamp(0.0, LEVEL_MAX);
                    let Some(sampled) = decoded_level(image.get_pixel(px, py).0) else {
                        failures.push(format!(
                            "{angle}°, finest resident {finest}: pixel ({px}, {py}) shows {:?}, no level",
                            image.get_pixel(px, py).0
                        ));
                        continue;
                    };
                    pixels_checked += 1;
                    levels_seen[sampled.floor().clamp(0.0, LEVEL_MAX) as usize] = true;
                    finer = finer.max(f64::from(finest) - sampled);
                    coarser = coarser.max(sampled - (needed + 1.0).max(f64::from(finest)));
                    off = off.max((sampled - expected).abs());
                    past_centre = past_centre.max(sampled - (at_centre + 1.0).max(f64::from(finest)));
                }
            }
            report.push(format!(
                "{angle}°, finest resident {finest}: finer than resident by {finer:.3}, past needed + 1 by {coarser:.3} \
                 (by {past_centre:.3} with centre derivatives), off the centre footprint's A_s level by {off:.3}"
            ));
            if finer > DECODE {
                failures.push(format!(
                    "{angle}°: sampled {finer:.3} levels finer than resident level {finest}"
                ));
            }
            if coarser > DECODE {
                failures.push(format!(
                    "{angle}°, finest resident {finest}: sampled {coarser:.3} levels coarser than needed + 1"
                ));
            }
        }
    }
    eprintln!("{}", report.join("\n"));
    failures.truncate(20);
    ensure!(failures.is_empty(), "{}", failures.join("\n"));
    // The bounds mean something only over many pixels and a range of levels.
    ensure!(pixels_checked > 100_000, "{pixels_checked} pixels checked");
    let seen = levels_seen.iter().filter(|&&s| s).count();
    ensure!(seen >= 6, "sampled levels {levels_seen:?}");
    assert_no_validation_errors(&device)
}
