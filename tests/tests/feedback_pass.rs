//! The feedback pass (paper §3.2) on lavapipe against a CPU reference of the
//! same formula: textured planes at known distances and angles (one at a
//! grazing angle), one plane fully occluded by another, and one seen only in
//! the feedback's margin beyond the visible viewport.
//!
//! The reference casts a ray through every feedback pixel centre, keeps the
//! nearest plane (early depth test), differentiates the texel coordinates
//! between neighbouring pixel centres, and applies the same anisotropic LOD,
//! LOD offset and weight W = 1 + 8 w_d + 8 w_m. With nothing resident the
//! displayed level is M_max, so w_m = 1 inside the visible view.

use anyhow::{ensure, Result};
use citystream_dataset::TextureFormat;
use citystream_engine::city::{CityMesh, CityRenderer, FeedbackView};
use citystream_engine::commands::CommandContext;
use citystream_engine::feedback::FeedbackCompactor;
use citystream_engine::gpu_types::{Vertex, FEEDBACK_MIP_ONE, FEEDBACK_UNSEEN, FEEDBACK_WEIGHT_ONE};
use citystream_engine::target::RenderTarget;
use citystream_engine::texture_cache::GpuTextureCache;
use citystream_tests::{assert_clean_after_dropping, camera_down_negative_z, test_cache_config, validated_device};
use glam::Vec3;

const SIZE: u32 = 128;
/// Height of the visible view the feedback stands for: twice the feedback's.
const VISIBLE: u32 = 256;
const MARGIN: f32 = 0.25;
const FOREGROUND: f32 = 10.0;
const FOV_Y: f32 = std::f32::consts::FRAC_PI_3;

/// A planar quad: corner, texture-u edge, texture-v edge, texture extent.
#[derive(Clone, Copy, Debug)]
struct Plane {
    corner: Vec3,
    u_edge: Vec3,
    v_edge: Vec3,
    texture: u32,
}

impl Plane {
    fn normal(&self) -> Vec3 {
        self.u_edge.cross(self.v_edge).normalize()
    }

    /// Ray from the origin along `dir`: (distance along -z, uv) of the hit.
    fn hit(&self, dir: Vec3) -> Option<(f32, [f32; 2])> {
        let n = self.normal();
        let denom = n.dot(dir);
        if denom.abs() < 1e-9 {
            return None;
        }
        let t = n.dot(self.corner) / denom;
        if t <= 0.0 {
            return None;
        }
        let p = dir * t - self.corner;
        let u = p.dot(self.u_edge) / self.u_edge.length_squared();
        let v = p.dot(self.v_edge) / self.v_edge.length_squared();
        ((0.0..=1.0).contains(&u) && (0.0..=1.0).contains(&v)).then_some((-(dir * t).z, [u, v]))
    }
}

fn ray(px: f32, py: f32) -> Vec3 {
    let tan = (FOV_Y * 0.5).tan() * (1.0 + MARGIN);
    let ndc_x = px / SIZE as f32 * 2.0 - 1.0;
    let ndc_y = py / SIZE as f32 * 2.0 - 1.0;
    // Vulkan NDC y points down; the camera looks along -z with +y up.
    Vec3::new(ndc_x * tan, -ndc_y * tan, -1.0)
}

fn anisotropic_lod(dx: [f32; 2], dy: [f32; 2], max_aniso: f32) -> f32 {
    let px = (dx[0] * dx[0] + dx[1] * dx[1]).sqrt();
    let py = (dy[0] * dy[0] + dy[1] * dy[1]).sqrt();
    let (p_max, p_min) = (px.max(py), px.min(py));
    if p_max <= 0.0 {
        return 0.0;
    }
    let n = (p_max / p_min.max(1e-20) - 1.0 / 1024.0).ceil().clamp(1.0, max_aniso);
    (p_max / n).log2()
}

struct Reference {
    /// Lowest fixed-point level with forward and with backward differences.
    min_mip: Option<(u32, u32)>,
    /// Fixed-point weight sum and fragments counted.
    weight: u64,
    fragments: u64,
    visible_fragments: u64,
}

fn reference(planes: &[Plane], extent: &[(u32, u32)]) -> Vec<Reference> {
    let mut out: Vec<Reference> = planes
        .iter()
        .map(|_| Reference {
            min_mip: None,
            weight: 0,
            fragments: 0,
            visible_fragments: 0,
        })
        .collect();
    let nearest = |x: f32, y: f32| -> Option<(usize, f32, [f32; 2])> {
        planes
            .iter()
            .enumerate()
            .filter_map(|(i, p)| p.hit(ray(x, y)).map(|(d, uv)| (i, d, uv)))
            .min_by(|a, b| a.1.total_cmp(&b.1))
    };
    // A feedback pixel spans (1 + MARGIN) * VISIBLE / SIZE visible pixels.
    let lod_offset = ((1.0 + MARGIN) * VISIBLE as f32 / SIZE as f32).log2();
    for py in 0..SIZE {
        for px in 0..SIZE {
            let (x, y) = (px as f32 + 0.5, py as f32 + 0.5);
            let Some((i, depth, uv)) = nearest(x, y) else { continue };
            let (w, h) = extent[planes[i].texture as usize];
            let max_level = (w.max(h) as f32).log2();
            let texel = |uv: [f32; 2]| [uv[0] * w as f32, uv[1] * h as f32];
            let plane = &planes[i];
            let uv_at = |dx: f32, dy: f32| plane.hit(ray(x + dx, y + dy)).map(|(_, uv)| texel(uv));
            let centre = texel(uv);
            let diff =
                |a: Option<[f32; 2]>, b: [f32; 2], sign: f32| a.map(|a| [(a[0] - b[0]) * sign, (a[1] - b[1]) * sign]);
            let lods: Vec<f32> = [1.0f32, -1.0]
                .iter()
                .filter_map(|&s| {
                    let dx = diff(uv_at(s, 0.0), centre, s)?;
                    let dy = diff(uv_at(0.0, s), centre, s)?;
                    Some((anisotropic_lod(dx, dy, 16.0) - lod_offset).clamp(0.0, max_level))
                })
                .collect();
            let r = &mut out[i];
            if lods.len() == 2 {
                let fixed = |l: f32| (l * FEEDBACK_MIP_ONE).round() as u32;
                let (a, b) = (fixed(lods[0]), fixed(lods[1]));
                r.min_mip = Some(match r.min_mip {
                    None => (a, b),
                    Some((ma, mb)) => (ma.min(a), mb.min(b)),
                });
            }
            let ndc = [x / SIZE as f32 * 2.0 - 1.0, y / SIZE as f32 * 2.0 - 1.0];
            let visible = ndc.iter().all(|c| (c * (1.0 + MARGIN)).abs() <= 1.0);
            let weight = if visible {
                let c_w = (depth / FOREGROUND).min(1.0);
                1.0 + 8.0 * (1.0 - c_w).powi(4) + 8.0
            } else {
                1.0
            };
            r.weight += (weight * FEEDBACK_WEIGHT_ONE).round() as u64;
            r.fragments += 1;
            r.visible_fragments += u64::from(visible);
        }
    }
    out
}

fn quad(plane: &Plane) -> ([Vertex; 4], [u32; 6]) {
    let n = plane.normal().to_array();
    let v = |p: Vec3, uv: [f32; 2]| Vertex {
        position: p.to_array(),
        normal: n,
        uv,
    };
    let c = plane.corner;
    (
        [
            v(c, [0.0, 0.0]),
            v(c + plane.u_edge, [1.0, 0.0]),
            v(c + plane.u_edge + plane.v_edge, [1.0, 1.0]),
            v(c + plane.v_edge, [0.0, 1.0]),
        ],
        [0, 1, 2, 0, 2, 3],
    )
}

#[test]
fn feedback_matches_cpu_reference() -> Result<()> {
    let extents = [(512u32, 512u32), (1024, 1024), (256, 64), (128, 128)];
    let planes = vec![
        // 0: fronto-parallel, near (inside the foreground).
        Plane {
            corner: Vec3::new(-1.7, 0.13, -5.0),
            u_edge: Vec3::new(1.3, 0.0, 0.0),
            v_edge: Vec3::new(0.0, 1.1, 0.0),
            texture: 0,
        },
        // 1: fronto-parallel, far.
        Plane {
            corner: Vec3::new(0.37, -4.1, -20.0),
            u_edge: Vec3::new(3.1, 0.0, 0.0),
            v_edge: Vec3::new(0.0, 2.2, 0.0),
            texture: 1,
        },
        // 2: a floor seen at a grazing angle.
        Plane {
            corner: Vec3::new(-1.03, -1.5, -2.5),
            u_edge: Vec3::new(2.1, 0.0, 0.0),
            v_edge: Vec3::new(0.0, 0.0, -30.0),
            texture: 1,
        },
        // 3: occluder, and 4: fully behind it.
        Plane {
            corner: Vec3::new(0.93, 0.07, -8.0),
            u_edge: Vec3::new(2.2, 0.0, 0.0),
            v_edge: Vec3::new(0.0, 2.1, 0.0),
            texture: 2,
        },
        Plane {
            corner: Vec3::new(1.53, 0.55, -12.0),
            u_edge: Vec3::new(0.9, 0.0, 0.0),
            v_edge: Vec3::new(0.0, 0.9, 0.0),
            texture: 3,
        },
        // 5: beyond the visible edge, inside the feedback margin.
        Plane {
            corner: Vec3::new(6.05, -0.47, -10.0),
            u_edge: Vec3::new(1.0, 0.0, 0.0),
            v_edge: Vec3::new(0.0, 0.93, 0.0),
            texture: 3,
        },
    ];
    let mut vertices = Vec::new();
    let mut indices = Vec::new();
    let mut meshes = Vec::new();
    for plane in &planes {
        let (v, i) = quad(plane);
        meshes.push(CityMesh {
            first_index: indices.len() as u32,
            index_count: 6,
            vertex_offset: vertices.len() as u32,
            texture: plane.texture,
            texture_width: extents[plane.texture as usize].0,
            texture_height: extents[plane.texture as usize].1,
            origin: glam::DVec3::ZERO,
        });
        vertices.extend_from_slice(&v);
        indices.extend_from_slice(&i);
    }

    let device = validated_device()?;
    let mut commands = CommandContext::new(&device, "feedback test")?;
    let cache = GpuTextureCache::new(
        &device,
        &mut commands,
        &test_cache_config(&[TextureFormat::Bc1, TextureFormat::Rgba8], extents.len() as u32),
        &[[128, 128, 128, 255]; 4],
    )?;
    let compactor = FeedbackCompactor::new(&device, &mut commands, planes.len() as u32, planes.len() as u32)?;
    let renderer = CityRenderer::new(&device, &mut commands, &vertices, &indices, meshes, &cache, &compactor)?;
    let target = RenderTarget::new(&device, SIZE, SIZE)?;
    let camera = camera_down_negative_z(FOV_Y);
    let view = FeedbackView {
        margin: MARGIN,
        foreground_distance: FOREGROUND,
    };
    let cmd = commands.begin()?;
    renderer.record_feedback(cmd, &target, &camera, &view, VISIBLE)?;
    commands.submit_and_wait(&[])?;
    let gpu = compactor.download_mesh_feedback(&mut commands)?;
    let cpu = reference(&planes, &extents);

    for (i, (g, c)) in gpu.iter().zip(&cpu).enumerate() {
        if c.fragments == 0 {
            ensure!(
                g.min_mip == FEEDBACK_UNSEEN && g.weight == 0,
                "plane {i} is occluded but got {g:?}"
            );
            continue;
        }
        let (forward, backward) = c.min_mip.expect("covered planes have a level");
        let (low, high) = (forward.min(backward), forward.max(backward));
        // A twentieth of a level for rounding and derivative placement.
        let slack = (FEEDBACK_MIP_ONE / 20.0) as u32;
        ensure!(
            g.min_mip + slack >= low && g.min_mip <= high + slack,
            "plane {i}: GPU level {:.3}, CPU {:.3}..{:.3}",
            g.min_mip as f32 / FEEDBACK_MIP_ONE,
            low as f32 / FEEDBACK_MIP_ONE,
            high as f32 / FEEDBACK_MIP_ONE
        );
        let relative = (f64::from(g.weight) - c.weight as f64).abs() / c.weight as f64;
        ensure!(
            relative < 0.03,
            "plane {i}: GPU weight {} vs CPU {} ({:.1} % off)",
            g.weight,
            c.weight,
            relative * 100.0
        );
    }
    // Independent of the reference's pixel geometry: plane 0 is fronto-parallel
    // at depth 5, 512 texels over 1.3 units across and 1.1 units down; a
    // visible pixel spans 2 tan(30°) 5 / VISIBLE units. The footprint ratio
    // 1.3 / 1.1 rounds up to 2 samples, which takes one level off log2(p_max).
    let unit_per_pixel = 2.0 * (FOV_Y * 0.5).tan() * 5.0 / VISIBLE as f32;
    let (p_u, p_v) = (512.0 / 1.3 * unit_per_pixel, 512.0 / 1.1 * unit_per_pixel);
    let samples = (p_v / p_u).ceil();
    ensure!(samples == 2.0);
    let analytic = (p_v / samples).log2();
    let measured = gpu[0].min_mip as f32 / FEEDBACK_MIP_ONE;
    ensure!(
        (measured - analytic).abs() < 0.05,
        "plane 0 needs level {analytic:.3}, feedback says {measured:.3}"
    );
    // The plan of the scene holds: 4 is hidden, 5 lives only in the margin.
    ensure!(
        cpu[4].fragments == 0 && gpu[4].min_mip == FEEDBACK_UNSEEN,
        "plane 4 must be fully occluded"
    );
    ensure!(
        cpu[5].fragments > 20 && cpu[5].visible_fragments == 0,
        "plane 5 must be margin-only"
    );
    // Margin fragments weigh exactly W = 1 each.
    ensure!(
        gpu[5].weight % FEEDBACK_WEIGHT_ONE as u32 == 0,
        "margin weights must be whole fragments"
    );
    let margin_fragments = gpu[5].weight / FEEDBACK_WEIGHT_ONE as u32;
    ensure!(
        (i64::from(margin_fragments) - cpu[5].fragments as i64).unsigned_abs() <= cpu[5].fragments / 20 + 2,
        "plane 5: {margin_fragments} fragments of weight 1 vs {} covered pixels",
        cpu[5].fragments
    );
    // The grazing floor needs a much finer level near the camera than far away: its minimum is fine.
    ensure!(
        gpu[2].min_mip < gpu[1].min_mip,
        "the near end of the floor needs finer mips than the far plane"
    );

    assert_clean_after_dropping(&device, (renderer, compactor, cache, commands))
}
