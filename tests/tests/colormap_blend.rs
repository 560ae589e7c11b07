//! Eq. 8 per pixel: the visible pass blends the sampled colour with the City
//! Colormap colour by the displayed level, c = (1 - M/M_max) c_s +
//! (M/M_max) c_o. Fronto-parallel quads whose needed level is finer than
//! their finest resident level display exactly that resident level, so a CPU
//! evaluation (ray through each pixel centre, nearest texel of level M,
//! blend) predicts every pixel.

use anyhow::{ensure, Result};
use citystream_dataset::TextureFormat;
use citystream_engine::city::{CityMesh, CityRenderer};
use citystream_engine::commands::CommandContext;
use citystream_engine::feedback::FeedbackCompactor;
use citystream_engine::gpu_types::Vertex;
use citystream_engine::placeholder::SplitMix64;
use citystream_engine::target::RenderTarget;
use citystream_engine::texture_cache::GpuTextureCache;
use citystream_tests::{
    assert_clean_after_dropping, camera_down_negative_z, compare_where_certain, test_cache_config, validated_device,
};

const SIZE: u32 = 128;
const TEXTURE: u32 = 64; // M_max = 6
const FOV_Y: f32 = std::f32::consts::FRAC_PI_3;
const DEPTH: f32 = 4.0;

struct Quad {
    x0: f32,
    y0: f32,
    side: f32,
    texture: u32,
    /// Finest resident level, or None for a texture never loaded.
    lowest: Option<u32>,
}

fn level_bytes(rng: &mut SplitMix64, level: u32) -> Vec<u8> {
    let side = TEXTURE >> level;
    (0..side * side)
        .flat_map(|_| {
            let v = rng.next_u64();
            [v as u8, (v >> 8) as u8, (v >> 16) as u8, 255]
        })
        .collect()
}

#[test]
fn visible_pass_blends_by_displayed_level() -> Result<()> {
    let quads = [
        Quad {
            x0: -2.1,
            y0: 0.13,
            side: 1.9,
            texture: 0,
            lowest: Some(0),
        },
        Quad {
            x0: 0.17,
            y0: 0.11,
            side: 1.9,
            texture: 1,
            lowest: Some(2),
        },
        Quad {
            x0: -2.1,
            y0: -2.07,
            side: 1.9,
            texture: 2,
            lowest: Some(4),
        },
        Quad {
            x0: 0.17,
            y0: -2.07,
            side: 1.9,
            texture: 3,
            lowest: None,
        },
    ];
    let colormap = [
        [200u8, 40, 40, 255],
        [40, 200, 40, 255],
        [40, 40, 200, 255],
        [220, 220, 30, 255],
    ];
    let mut rng = SplitMix64::new(8);
    // levels[texture][level]
    let levels: Vec<Vec<Vec<u8>>> = (0..4)
        .map(|_| (0..7).map(|l| level_bytes(&mut rng, l)).collect())
        .collect();

    let device = validated_device()?;
    let mut commands = CommandContext::new(&device, "blend test")?;
    let mut cache = GpuTextureCache::new(
        &device,
        &mut commands,
        &test_cache_config(&[TextureFormat::Bc1, TextureFormat::Rgba8], 4),
        &colormap,
    )?;
    for quad in &quads {
        if let Some(lowest) = quad.lowest {
            for level in (lowest..7).rev() {
                cache.stage(
                    quad.texture,
                    TextureFormat::Rgba8,
                    TEXTURE,
                    TEXTURE,
                    level,
                    &levels[quad.texture as usize][level as usize],
                )?;
            }
        }
    }
    cache.finish_cycle(&mut commands)?;

    let mut vertices = Vec::new();
    let mut indices = Vec::new();
    let mut meshes = Vec::new();
    for quad in &quads {
        let v = |x: f32, y: f32, u: f32, w: f32| Vertex {
            position: [x, y, -DEPTH],
            normal: [0.0, 0.0, 1.0],
            uv: [u, w],
        };
        let (x1, y1) = (quad.x0 + quad.side, quad.y0 + quad.side);
        // v grows downwards on screen, like texture rows.
        meshes.push(CityMesh {
            first_index: indices.len() as u32,
            index_count: 6,
            vertex_offset: vertices.len() as u32,
            texture: quad.texture,
            texture_width: TEXTURE,
            texture_height: TEXTURE,
            origin: glam::DVec3::ZERO,
        });
        vertices.extend_from_slice(&[
            v(quad.x0, y1, 0.0, 0.0),
            v(x1, y1, 1.0, 0.0),
            v(x1, quad.y0, 1.0, 1.0),
            v(quad.x0, quad.y0, 0.0, 1.0),
        ]);
        indices.extend_from_slice(&[0, 1, 2, 0, 2, 3]);
    }
    let compactor = FeedbackCompactor::new(&device, &mut commands, 4, 4)?;
    let renderer = CityRenderer::new(&device, &mut commands, &vertices, &indices, meshes, &cache, &compactor)?;
    let target = RenderTarget::new(&device, SIZE, SIZE)?;
    let camera = camera_down_negative_z(FOV_Y);
    let cmd = commands.begin()?;
    renderer.record_visible(cmd, &target, &camera, 0.0, true)?;
    commands.submit_and_wait(&[])?;
    let actual = target.read_pixels()?;

    // CPU evaluation.
    let tan = (FOV_Y * 0.5).tan();
    let mut expected = image::RgbaImage::from_pixel(SIZE, SIZE, image::Rgba([140, 178, 229, 255]));
    let mut certain = vec![false; (SIZE * SIZE) as usize];
    let mut checked_levels = std::collections::HashSet::new();
    for py in 0..SIZE {
        for px in 0..SIZE {
            let ndc = [
                (px as f32 + 0.5) / SIZE as f32 * 2.0 - 1.0,
                (py as f32 + 0.5) / SIZE as f32 * 2.0 - 1.0,
            ];
            let (x, y) = (ndc[0] * tan * DEPTH, -ndc[1] * tan * DEPTH);
            let Some(quad) = quads
                .iter()
                .find(|q| x > q.x0 && x < q.x0 + q.side && y > q.y0 && y < q.y0 + q.side)
            else {
                continue;
            };
            let (u, v) = ((x - quad.x0) / quad.side, 1.0 - (y - quad.y0) / quad.side);
            let c_o = colormap[quad.texture as usize].map(f32::from);
            let colour = match quad.lowest {
                None => c_o,
                Some(level) => {
                    // The displayed level is the needed LOD where that is
                    // coarser than the finest resident level (only for the
                    // level-0 quad here); fronto-parallel quads have one
                    // isotropic LOD. The shader samples the two levels around
                    // it (nearest texel each, Filtering::Nearest) and blends.
                    let texels_per_pixel = TEXTURE as f32 * (2.0 * tan * DEPTH / SIZE as f32) / quad.side;
                    let displayed = texels_per_pixel.log2().max(level as f32);
                    let fine = displayed.floor() as u32;
                    let blend = displayed - fine as f32;
                    let sample = |l: u32| -> Option<[f32; 4]> {
                        let side = (TEXTURE >> l) as f32;
                        let (tx, ty) = (u * side, v * side);
                        let near_edge = |t: f32| (t - t.round()).abs() < 0.05;
                        if near_edge(tx) || near_edge(ty) {
                            return None;
                        }
                        let at = ((ty as u32 * side as u32 + tx as u32) * 4) as usize;
                        let texel = &levels[quad.texture as usize][l as usize][at..at + 4];
                        Some([0, 1, 2, 3].map(|i| f32::from(texel[i])))
                    };
                    if !(0.05..=0.95).contains(&u) || !(0.05..=0.95).contains(&v) {
                        continue;
                    }
                    let (Some(a), Some(b)) = (sample(fine), sample((fine + 1).min(6))) else {
                        continue;
                    };
                    let c_s = [0, 1, 2, 3].map(|i| (1.0 - blend) * a[i] + blend * b[i]);
                    let t = displayed / 6.0;
                    checked_levels.insert(fine);
                    [0, 1, 2, 3].map(|i| (1.0 - t) * c_s[i] + t * c_o[i])
                }
            };
            expected.put_pixel(px, py, image::Rgba(colour.map(|c| c.round() as u8)));
            certain[(py * SIZE + px) as usize] = true;
        }
    }
    ensure!(
        checked_levels.len() == 3,
        "levels 0, 2 and 4 must all be displayed: {checked_levels:?}"
    );
    let out_dir = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("blend");
    let comparison = compare_where_certain(&actual, &expected, &certain, &out_dir, "colormap_blend")?;
    ensure!(
        comparison.compared > 3000,
        "only {} pixels compared",
        comparison.compared
    );
    assert_clean_after_dropping(&device, (renderer, compactor, cache, commands))
}
