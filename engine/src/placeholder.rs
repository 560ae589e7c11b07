//! A small procedural city of textured boxes, rendered fully resident. The
//! flythrough uses it when no dataset is given, and it gives frame-loop
//! tests a real scene independent of the dataset format.

use glam::Vec3;

use crate::gpu_types::Vertex;
use crate::scene::{SceneGeometry, TextureArrayData};

/// Side length of the placeholder textures.
pub const TEXTURE_SIZE: u32 = 64;
/// Number of facade textures (layer 0 is the ground).
pub const FACADE_TEXTURES: u32 = 12;

/// A small deterministic generator (SplitMix64), so the scene depends only on the seed.
#[derive(Debug, Clone)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    /// Seeds the generator.
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    /// Next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn next_f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// Appends an axis-aligned quad given four corners in counter-clockwise order.
fn quad(geometry: &mut SceneGeometry, corners: [Vec3; 4], normal: Vec3, uv_scale: [f32; 2], layer: u32) {
    let uvs = [
        [0.0, uv_scale[1]],
        [uv_scale[0], uv_scale[1]],
        [uv_scale[0], 0.0],
        [0.0, 0.0],
    ];
    let vertices: Vec<Vertex> = corners
        .iter()
        .zip(uvs)
        .map(|(p, uv)| Vertex {
            position: p.to_array(),
            normal: normal.to_array(),
            uv,
        })
        .collect();
    geometry.push_mesh(&vertices, &[0, 1, 2, 0, 2, 3], layer);
}

/// Builds a `blocks` × `blocks` grid of buildings on a ground plane.
pub fn city(seed: u64, blocks: u32) -> SceneGeometry {
    let mut rng = SplitMix64::new(seed);
    let mut geometry = SceneGeometry::default();
    let spacing = 30.0;
    let extent = blocks as f32 * spacing;
    let half = extent / 2.0;
    quad(
        &mut geometry,
        [
            Vec3::new(-half, 0.0, half),
            Vec3::new(half, 0.0, half),
            Vec3::new(half, 0.0, -half),
            Vec3::new(-half, 0.0, -half),
        ],
        Vec3::Y,
        [blocks as f32, blocks as f32],
        0,
    );
    for bz in 0..blocks {
        for bx in 0..blocks {
            let cx = -half + (bx as f32 + 0.5) * spacing;
            let cz = -half + (bz as f32 + 0.5) * spacing;
            let w = 8.0 + rng.next_f32() * 12.0;
            let d = 8.0 + rng.next_f32() * 12.0;
            let h = 10.0 + rng.next_f32().powi(2) * 90.0;
            let layer = 1 + (rng.next_u64() % u64::from(FACADE_TEXTURES)) as u32;
            let (x0, x1, z0, z1) = (cx - w / 2.0, cx + w / 2.0, cz - d / 2.0, cz + d / 2.0);
            let floors = (h / 4.0).round().max(1.0);
            let faces = [
                (
                    [
                        Vec3::new(x0, 0.0, z1),
                        Vec3::new(x1, 0.0, z1),
                        Vec3::new(x1, h, z1),
                        Vec3::new(x0, h, z1),
                    ],
                    Vec3::Z,
                    w,
                ),
                (
                    [
                        Vec3::new(x1, 0.0, z0),
                        Vec3::new(x0, 0.0, z0),
                        Vec3::new(x0, h, z0),
                        Vec3::new(x1, h, z0),
                    ],
                    -Vec3::Z,
                    w,
                ),
                (
                    [
                        Vec3::new(x1, 0.0, z1),
                        Vec3::new(x1, 0.0, z0),
                        Vec3::new(x1, h, z0),
                        Vec3::new(x1, h, z1),
                    ],
                    Vec3::X,
                    d,
                ),
                (
                    [
                        Vec3::new(x0, 0.0, z0),
                        Vec3::new(x0, 0.0, z1),
                        Vec3::new(x0, h, z1),
                        Vec3::new(x0, h, z0),
                    ],
                    -Vec3::X,
                    d,
                ),
            ];
            for (corners, normal, width) in faces {
                quad(
                    &mut geometry,
                    corners,
                    normal,
                    [(width / 4.0).round().max(1.0), floors],
                    layer,
                );
            }
            quad(
                &mut geometry,
                [
                    Vec3::new(x0, h, z1),
                    Vec3::new(x1, h, z1),
                    Vec3::new(x1, h, z0),
                    Vec3::new(x0, h, z0),
                ],
                Vec3::Y,
                [1.0, 1.0],
                0,
            );
        }
    }
    geometry
}

/// Procedural textures: layer 0 is asphalt-like ground, the others facades
/// with windows and floors in a per-texture colour.
pub fn textures(seed: u64) -> crate::Result<TextureArrayData> {
    let mut rng = SplitMix64::new(seed ^ 0x7E57);
    let size = TEXTURE_SIZE;
    let mut bases = Vec::new();
    let mut ground = Vec::with_capacity((size * size * 4) as usize);
    for y in 0..size {
        for x in 0..size {
            let noise = (rng.next_f32() * 24.0) as u8;
            let line = if x == size / 2 && (y / 4) % 2 == 0 { 120 } else { 0 };
            let v = 70u8.saturating_add(noise).saturating_add(line);
            ground.extend_from_slice(&[v, v, v.saturating_add(6), 255]);
        }
    }
    bases.push(ground);
    for _ in 0..FACADE_TEXTURES {
        let wall = [
            90 + (rng.next_f32() * 150.0) as u8,
            80 + (rng.next_f32() * 130.0) as u8,
            70 + (rng.next_f32() * 120.0) as u8,
        ];
        let glass = [
            30 + (rng.next_f32() * 60.0) as u8,
            60 + (rng.next_f32() * 80.0) as u8,
            110 + (rng.next_f32() * 100.0) as u8,
        ];
        let mut texels = Vec::with_capacity((size * size * 4) as usize);
        for y in 0..size {
            for x in 0..size {
                // One window per texture repeat: the UVs tile one per floor and bay.
                let in_window = (14..50).contains(&x) && (18..52).contains(&y);
                let frame = x == 31 || x == 32;
                let noise = rng.next_f32() * 16.0;
                let c = if in_window && !frame { glass } else { wall };
                texels.extend_from_slice(&[
                    (c[0] as f32 + noise).min(255.0) as u8,
                    (c[1] as f32 + noise).min(255.0) as u8,
                    (c[2] as f32 + noise).min(255.0) as u8,
                    255,
                ]);
            }
        }
        bases.push(texels);
    }
    TextureArrayData::from_base_levels(size, bases)
}
