//! The feedback's needed level at grazing angles: a textured plane 1 km ahead, its normal
//! turned from the view axis by 0° to 89.5°. For each angle the level the feedback pass
//! reports for it (the least over its fragments) is within half a level of the analytic
//! anisotropic level: texel-space derivatives of the exact ray–plane mapping at every
//! feedback pixel centre the plane covers, `log2(p_max / n)` with `n = ⌈p_max / p_min⌉`
//! samples, at most A_m = 16 (`shaders/include/lod.glsl`), less the feedback's level offset,
//! clamped to the chain, least over the pixels. Validation on; any message fails.

use anyhow::{ensure, Result};
use citystream_dataset::TextureFormat;
use citystream_engine::city::{CityMesh, CityRenderer, FeedbackView};
use citystream_engine::commands::CommandContext;
use citystream_engine::feedback::FeedbackCompactor;
use citystream_engine::gpu_types::{Vertex, FEEDBACK_MIP_ONE, FEEDBACK_UNSEEN};
use citystream_engine::target::RenderTarget;
use citystream_engine::texture_cache::GpuTextureCache;
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

/// The least needed level over the feedback pixels the plane covers, from the exact
/// derivatives of its texel coordinates.
fn analytic_level(angle_deg: f64) -> f64 {
    let (corner, u_edge, v_edge) = plane(angle_deg);
    let normal = u_edge.cross(v_edge).normalize();
    let tan = f64::from((FOV_Y * 0.5).tan()) * (1.0 + f64::from(MARGIN));
    let step = 2.0 * tan / f64::from(SIZE);
    let ray = |x: f64, y: f64| {
        DVec3::new(
            (x / f64::from(SIZE) * 2.0 - 1.0) * tan,
            -(y / f64::from(SIZE) * 2.0 - 1.0) * tan,
            -1.0,
        )
    };
    let texel_scale = DVec3::new(
        f64::from(TEXELS) / u_edge.length_squared(),
        f64::from(TEXELS) / v_edge.length_squared(),
        0.0,
    );
    let lod_offset = ((1.0 + f64::from(MARGIN)) * f64::from(VISIBLE) / f64::from(SIZE)).log2();
    let max_level = f64::from(TEXELS).log2();
    let mut least = f64::INFINITY;
    for py in 0..SIZE {
        for px in 0..SIZE {
            let r = ray(f64::from(px) + 0.5, f64::from(py) + 0.5);
            let facing = normal.dot(r);
            let t = normal.dot(corner) / facing;
            if !(facing.abs() > 1e-12 && t > 0.0) {
                continue;
            }
            let p = r * t - corner;
            let (u, v) = (
                p.dot(u_edge) / u_edge.length_squared(),
                p.dot(v_edge) / v_edge.length_squared(),
            );
            if !((0.0..=1.0).contains(&u) && (0.0..=1.0).contains(&v)) {
                continue;
            }
            // d(point)/d(pixel) along x and y: t·dr + r·dt, dt = −t (n·dr) / (n·r).
            let derivative = |dr: DVec3| {
                let dp = dr * t - r * (t * normal.dot(dr) / facing);
                [dp.dot(u_edge) * texel_scale.x, dp.dot(v_edge) * texel_scale.y]
            };
            let dx = derivative(DVec3::new(step, 0.0, 0.0));
            let dy = derivative(DVec3::new(0.0, -step, 0.0));
            let (lx, ly) = (dx[0].hypot(dx[1]), dy[0].hypot(dy[1]));
            let (p_max, p_min) = (lx.max(ly), lx.min(ly));
            let samples = (p_max / p_min.max(1e-20) - 1.0 / 1024.0)
                .ceil()
                .clamp(1.0, MAX_ANISOTROPY);
            let level = ((p_max / samples).log2() - lod_offset).clamp(0.0, max_level);
            least = least.min(level);
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
        let (corner, u_edge, v_edge) = plane(angle);
        let normal = u_edge.cross(v_edge).normalize().as_vec3().to_array();
        let vertex = |p: DVec3, uv: [f32; 2]| Vertex {
            position: p.as_vec3().to_array(),
            normal,
            uv,
        };
        let vertices = [
            vertex(corner, [0.0, 0.0]),
            vertex(corner + u_edge, [1.0, 0.0]),
            vertex(corner + u_edge + v_edge, [1.0, 1.0]),
            vertex(corner + v_edge, [0.0, 1.0]),
        ];
        let mesh = CityMesh {
            first_index: 0,
            index_count: 6,
            vertex_offset: 0,
            texture: 0,
            texture_width: TEXELS,
            texture_height: TEXELS,
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
