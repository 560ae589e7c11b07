//! Renders a small depth-tested, textured scene on lavapipe and compares the
//! read-back with a CPU rasterisation of the same scene.
//!
//! The scene is drawn with an identity view-projection, so vertex positions
//! are normalised device coordinates and every quad's UVs are linear in
//! screen space; a CPU reference can then say exactly which texel of which
//! quad wins each pixel centre. Pixels whose centre lies within half a pixel
//! of an edge or a depth crossing are not compared (rasterisation rules may
//! pick either side there).

use anyhow::Result;
use citystream_engine::commands::CommandContext;
use citystream_engine::gpu_types::Vertex;
use citystream_engine::pipeline::Filtering;
use citystream_engine::scene::{MeshRenderer, SceneGeometry, TextureArrayData};
use citystream_engine::target::RenderTarget;
use citystream_tests::{assert_clean_after_dropping, compare_where_certain, validated_device};
use glam::Mat4;

const SIZE: u32 = 64;
const TEXTURE: u32 = 4;
const CLEAR: [u8; 4] = [10, 20, 30, 255];

/// An axis-aligned quad in NDC with depth varying linearly in x.
#[derive(Clone, Copy)]
struct Quad {
    x0: f32,
    x1: f32,
    y0: f32,
    y1: f32,
    z_left: f32,
    z_right: f32,
    layer: u32,
}

impl Quad {
    fn vertices(&self) -> [Vertex; 4] {
        let v = |x: f32, y: f32, z: f32, u: f32, w: f32| Vertex {
            position: [x, y, z],
            normal: [0.0, 0.0, -1.0],
            uv: [u, w],
        };
        [
            v(self.x0, self.y0, self.z_left, 0.0, 0.0),
            v(self.x1, self.y0, self.z_right, 1.0, 0.0),
            v(self.x1, self.y1, self.z_right, 1.0, 1.0),
            v(self.x0, self.y1, self.z_left, 0.0, 1.0),
        ]
    }

    fn depth_at(&self, x: f32) -> f32 {
        self.z_left + (self.z_right - self.z_left) * (x - self.x0) / (self.x1 - self.x0)
    }
}

/// Texture layers: a red/blue checker, a four-colour 2x2 pattern (nearest
/// texels repeated), and a green/white stripe.
fn textures() -> Vec<Vec<u8>> {
    let mut layers = Vec::new();
    let texel = |f: &dyn Fn(u32, u32) -> [u8; 4]| {
        let mut bytes = Vec::new();
        for y in 0..TEXTURE {
            for x in 0..TEXTURE {
                bytes.extend_from_slice(&f(x, y));
            }
        }
        bytes
    };
    layers.push(texel(&|x, y| {
        if (x + y) % 2 == 0 {
            [255, 0, 0, 255]
        } else {
            [0, 0, 255, 255]
        }
    }));
    layers.push(texel(&|x, y| match (x / 2, y / 2) {
        (0, 0) => [0, 255, 0, 255],
        (1, 0) => [255, 255, 0, 255],
        (0, 1) => [255, 255, 255, 255],
        _ => [0, 0, 0, 255],
    }));
    layers.push(texel(&|x, _| {
        if x % 2 == 0 {
            [0, 128, 0, 255]
        } else {
            [240, 240, 240, 255]
        }
    }));
    layers
}

fn scene() -> Vec<Quad> {
    vec![
        // Near quad, drawn first: depth testing must keep it in front (reversed depth, as
        // the engine draws: nearer is greater).
        Quad {
            x0: -0.5,
            x1: 0.5,
            y0: -0.5,
            y1: 0.5,
            z_left: 0.7,
            z_right: 0.7,
            layer: 1,
        },
        // Far quad covering most of the screen; the bottom rows show the clear colour.
        Quad {
            x0: -1.0,
            x1: 1.0,
            y0: -1.0,
            y1: 0.75,
            z_left: 0.2,
            z_right: 0.2,
            layer: 0,
        },
        // Slanted quad crossing both in depth.
        Quad {
            x0: 0.25,
            x1: 1.0,
            y0: -0.75,
            y1: 1.0,
            z_left: 0.9,
            z_right: 0.1,
            layer: 2,
        },
    ]
}

/// CPU rasterisation: the texel of the nearest quad at each pixel centre, and
/// whether the pixel is unambiguous.
fn reference(quads: &[Quad], layers: &[Vec<u8>]) -> (image::RgbaImage, Vec<bool>) {
    let mut expected = image::RgbaImage::from_pixel(SIZE, SIZE, image::Rgba(CLEAR));
    let mut certain = vec![true; (SIZE * SIZE) as usize];
    let half_pixel = 1.0 / SIZE as f32; // half a pixel in NDC units (NDC spans 2)
    for py in 0..SIZE {
        for px in 0..SIZE {
            let x = (px as f32 + 0.5) / SIZE as f32 * 2.0 - 1.0;
            let y = (py as f32 + 0.5) / SIZE as f32 * 2.0 - 1.0;
            let mut best: Option<(f32, &Quad)> = None;
            let mut depths = Vec::new();
            for quad in quads {
                let near_edge = [(x - quad.x0), (x - quad.x1), (y - quad.y0), (y - quad.y1)]
                    .iter()
                    .any(|d| d.abs() < half_pixel);
                let inside = x > quad.x0 && x < quad.x1 && y > quad.y0 && y < quad.y1;
                if near_edge {
                    certain[(py * SIZE + px) as usize] = false;
                }
                if inside {
                    let z = quad.depth_at(x);
                    depths.push((z, quad));
                    if best.is_none_or(|(bz, _)| z > bz) {
                        best = Some((z, quad));
                    }
                }
            }
            // A depth crossing within half a pixel is ambiguous too.
            for (i, (za, qa)) in depths.iter().enumerate() {
                for (zb, qb) in &depths[i + 1..] {
                    let slope =
                        ((qa.z_right - qa.z_left) / (qa.x1 - qa.x0) - (qb.z_right - qb.z_left) / (qb.x1 - qb.x0)).abs();
                    if (za - zb).abs() <= slope * half_pixel {
                        certain[(py * SIZE + px) as usize] = false;
                    }
                }
            }
            if let Some((_, quad)) = best {
                let u = (x - quad.x0) / (quad.x1 - quad.x0);
                let v = (y - quad.y0) / (quad.y1 - quad.y0);
                let tx = ((u * TEXTURE as f32) as u32).min(TEXTURE - 1);
                let ty = ((v * TEXTURE as f32) as u32).min(TEXTURE - 1);
                let at = ((ty * TEXTURE + tx) * 4) as usize;
                let layer = &layers[quad.layer as usize];
                expected.put_pixel(
                    px,
                    py,
                    image::Rgba([layer[at], layer[at + 1], layer[at + 2], layer[at + 3]]),
                );
            }
        }
    }
    (expected, certain)
}

#[test]
fn depth_tested_textured_scene_matches_cpu_reference() -> Result<()> {
    let device = validated_device()?;
    let mut commands = CommandContext::new(&device, "golden test")?;
    let quads = scene();
    let mut geometry = SceneGeometry::default();
    for quad in &quads {
        geometry.push_mesh(&quad.vertices(), &[0, 1, 2, 0, 2, 3], quad.layer);
    }
    let layers = textures();
    let textures = TextureArrayData::from_base_levels(TEXTURE, layers.clone())?;
    let renderer = MeshRenderer::new(&device, &mut commands, &geometry, &textures, Filtering::Nearest)?;
    let target = RenderTarget::new(&device, SIZE, SIZE)?;
    let clear = CLEAR.map(|c| f32::from(c) / 255.0);
    let actual = renderer.render_once(&mut commands, &target, Mat4::IDENTITY, [0.0, 0.0, -1.0, 0.0], clear)?;

    let (expected, certain) = reference(&quads, &layers);
    let out_dir = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("golden");
    let comparison = compare_where_certain(&actual, &expected, &certain, &out_dir, "depth_tested_textured_scene")?;
    // Most of the image must have been compared, or the mask hides the test.
    assert!(
        comparison.compared > (SIZE * SIZE * 3 / 4) as usize,
        "only {} pixels were unambiguous",
        comparison.compared
    );
    assert_clean_after_dropping(&device, (renderer, target, commands))
}

#[test]
fn reference_changes_when_depth_order_changes() {
    // Guards the reference itself: swapping the near and far depths must
    // change the expected image, or the depth comparison proves nothing.
    let layers = textures();
    let quads = scene();
    let (a, _) = reference(&quads, &layers);
    let mut swapped = quads.clone();
    swapped[0].z_left = 0.05;
    swapped[0].z_right = 0.05;
    let (b, _) = reference(&swapped, &layers);
    assert_ne!(a, b);
}
