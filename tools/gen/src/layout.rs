//! City layout: districts, blocks, streets and buildings, and the surface (mesh + texture
//! description) of every facade segment, roof, block ground and street strip.
//!
//! Frame: metres, right-handed, +y up, +x east, +z south. Front faces wind counter-clockwise
//! seen from outside; UV (0,0) is the top-left of the texture as seen from the front.

use anyhow::Result;
use citystream_dataset::{Crs, Scene};

use crate::rng::{mix, Rng};

/// Side of a city block, metres.
pub const BLOCK: f32 = 96.0;
/// Street width between blocks, metres.
pub const STREET: f32 = 16.0;
const PITCH: f32 = BLOCK + STREET;
/// Sidewalk between the block edge and the buildings, metres.
const SIDEWALK: f32 = 2.0;

/// What a texture shows; the parameters make every building look different.
#[derive(Clone, Copy, Debug)]
pub enum Content {
    Facade(FacadeStyle),
    Roof { base: [f32; 3], parapet: [f32; 3] },
    Grass,
    Plaza { base: [f32; 3] },
    Street { along_u: bool },
}

#[derive(Clone, Copy, Debug)]
pub enum WallMaterial {
    Brick,
    Plaster,
    Concrete,
    Glass,
}

#[derive(Clone, Copy, Debug)]
pub struct FacadeStyle {
    pub wall: [f32; 3],
    pub material: WallMaterial,
    pub glass: [f32; 3],
    pub frame: [f32; 3],
    pub floor_height: f32,
    pub window_spacing: f32,
    pub window_width: f32,
    pub window_height: f32,
    pub shop_floor: bool,
    /// Height above ground of the bottom edge of this texture, metres (setback towers).
    pub base_height: f32,
    /// Horizontal offset of this segment along the whole wall, metres (keeps window columns aligned).
    pub along_offset: f32,
}

/// Everything needed to synthesise one texture.
#[derive(Clone, Copy, Debug)]
pub struct TextureSpec {
    pub width_log2: u8,
    pub height_log2: u8,
    /// Metres covered by the texture (u, v).
    pub size_m: [f32; 2],
    pub content: Content,
    pub seed: u64,
}

/// Size and detail of a preset.
#[derive(Clone, Copy, Debug)]
pub struct LayoutParams {
    /// The city is `blocks × blocks` blocks.
    pub blocks: u32,
    /// Largest texture side, log2.
    pub max_extent_log2: u8,
    /// Multiplies every texel density.
    pub density_scale: f32,
}

/// The generated geometry and one texture description per mesh (mesh i uses texture i).
#[derive(Debug)]
pub struct City {
    pub scene: Scene,
    pub textures: Vec<TextureSpec>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum District {
    Downtown,
    Dense,
    Sparse,
    Industrial,
    Park,
}

/// World position of the city centre (x east, y up, z south): Berlin's ETRS89 / UTM zone 33N
/// coordinates ([`CRS_EPSG`]), easting 391,250 m, northing 5,819,500 m, 34 m high, like the
/// paper's Berlin dataset. Far from (0,0,0) on purpose; positions are stored relative to it.
pub const ORIGIN: [f64; 3] = [391_250.0, 34.0, -5_819_500.0];

/// The CRS generated cities are placed in: ETRS89 / UTM zone 33N.
pub const CRS_EPSG: u32 = 25833;

struct Builder {
    city: City,
    params: LayoutParams,
}

impl Builder {
    fn extent_log2(&self, metres: f32, density: f32) -> u8 {
        let texels = (metres * density * self.params.density_scale).max(1.0);
        (texels.log2().round() as i32).clamp(2, i32::from(self.params.max_extent_log2)) as u8
    }

    /// Adds a quad mesh with its own texture. `corners` are in UV order (0,1), (1,1), (1,0), (0,0)
    /// i.e. bottom-left, bottom-right, top-right, top-left seen from the front.
    fn quad(
        &mut self,
        corners: [[f32; 3]; 4],
        normal: [f32; 3],
        size_m: [f32; 2],
        density: f32,
        content: Content,
        seed: u64,
    ) -> Result<()> {
        let texture = self.city.textures.len() as u32;
        let spec = TextureSpec {
            width_log2: self.extent_log2(size_m[0], density),
            height_log2: self.extent_log2(size_m[1], density),
            size_m,
            content,
            seed,
        };
        self.city.textures.push(spec);
        self.city.scene.push_mesh(
            texture,
            &corners,
            &[normal; 4],
            &[[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]],
            &[0, 1, 2, 0, 2, 3],
        )?;
        Ok(())
    }

    /// A horizontal quad over `[x0,x1] × [z0,z1]` at height `y`, facing up, north at the top.
    fn horizontal(
        &mut self,
        [x0, z0, x1, z1]: [f32; 4],
        y: f32,
        density: f32,
        content: Content,
        seed: u64,
    ) -> Result<()> {
        self.quad(
            [[x0, y, z1], [x1, y, z1], [x1, y, z0], [x0, y, z0]],
            [0.0, 1.0, 0.0],
            [x1 - x0, z1 - z0],
            density,
            content,
            seed,
        )
    }

    /// A box building: four walls split into segments, each with its own texture, and a roof.
    #[allow(clippy::too_many_arguments)] // reason: a box is six numbers plus its look
    fn building(
        &mut self,
        x0: f32,
        z0: f32,
        x1: f32,
        z1: f32,
        y0: f32,
        y1: f32,
        style: FacadeStyle,
        density: f32,
        rng: &mut Rng,
    ) -> Result<()> {
        // Walls as (start, end, outward normal) walking left to right seen from outside.
        let walls = [
            ([x0, z1], [x1, z1], [0.0, 0.0, 1.0]),
            ([x1, z1], [x1, z0], [1.0, 0.0, 0.0]),
            ([x1, z0], [x0, z0], [0.0, 0.0, -1.0]),
            ([x0, z0], [x0, z1], [-1.0, 0.0, 0.0]),
        ];
        let height = y1 - y0;
        let segment_max = rng.range(10.0, 30.0);
        for (a, b, normal) in walls {
            let length = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
            let segments = (length / segment_max).ceil().max(1.0) as u32;
            for s in 0..segments {
                let t0 = s as f32 / segments as f32;
                let t1 = (s + 1) as f32 / segments as f32;
                let p0 = [a[0] + (b[0] - a[0]) * t0, a[1] + (b[1] - a[1]) * t0];
                let p1 = [a[0] + (b[0] - a[0]) * t1, a[1] + (b[1] - a[1]) * t1];
                let seg_style = FacadeStyle {
                    base_height: y0,
                    along_offset: length * t0,
                    ..style
                };
                let seed = rng.next_u64();
                self.quad(
                    [
                        [p0[0], y0, p0[1]],
                        [p1[0], y0, p1[1]],
                        [p1[0], y1, p1[1]],
                        [p0[0], y1, p0[1]],
                    ],
                    normal,
                    [length / segments as f32, height],
                    density,
                    Content::Facade(seg_style),
                    seed,
                )?;
            }
        }
        let roof = Content::Roof {
            base: grey(rng, 0.28, 0.45),
            parapet: grey(rng, 0.5, 0.7),
        };
        let seed = rng.next_u64();
        self.horizontal([x0, z0, x1, z1], y1, density * 0.5, roof, seed)
    }
}

fn grey(rng: &mut Rng, lo: f32, hi: f32) -> [f32; 3] {
    let v = rng.range(lo, hi);
    let tint = rng.range(-0.03, 0.03);
    [v + tint, v, v - tint]
}

fn facade_style(rng: &mut Rng, district: District) -> FacadeStyle {
    let roll = rng.below(10);
    let material = match district {
        District::Downtown if roll < 5 => WallMaterial::Glass,
        District::Downtown if roll < 8 => WallMaterial::Concrete,
        District::Industrial => WallMaterial::Concrete,
        _ if roll < 4 => WallMaterial::Brick,
        _ if roll < 8 => WallMaterial::Plaster,
        _ => WallMaterial::Concrete,
    };
    let wall = match material {
        WallMaterial::Brick => [rng.range(0.45, 0.65), rng.range(0.18, 0.3), rng.range(0.12, 0.2)],
        WallMaterial::Plaster => {
            let palette = [
                [0.9, 0.86, 0.76],
                [0.85, 0.8, 0.7],
                [0.8, 0.85, 0.88],
                [0.93, 0.78, 0.62],
                [0.75, 0.8, 0.7],
            ];
            let c = palette[rng.below(palette.len() as u32) as usize];
            let k = rng.range(0.85, 1.05);
            [c[0] * k, c[1] * k, c[2] * k]
        }
        WallMaterial::Concrete => grey(rng, 0.5, 0.75),
        WallMaterial::Glass => [rng.range(0.15, 0.3), rng.range(0.25, 0.4), rng.range(0.35, 0.55)],
    };
    FacadeStyle {
        wall,
        material,
        glass: [rng.range(0.1, 0.25), rng.range(0.15, 0.3), rng.range(0.25, 0.45)],
        frame: if rng.chance(0.5) {
            [0.9, 0.9, 0.88]
        } else {
            [0.2, 0.2, 0.22]
        },
        floor_height: rng.range(2.9, 4.2),
        window_spacing: rng.range(2.2, 4.5),
        window_width: rng.range(0.35, 0.7),
        window_height: rng.range(0.4, 0.6),
        shop_floor: matches!(district, District::Downtown | District::Dense) && rng.chance(0.6),
        base_height: 0.0,
        along_offset: 0.0,
    }
}

fn district_of(params: &LayoutParams, seed: u64, bx: u32, bz: u32) -> District {
    // Districts span 4×4 blocks in big cities, single blocks in tiny ones (so that even the
    // test city has several kinds).
    let span = (params.blocks / 6).clamp(1, 4);
    let n = params.blocks as f32;
    let centre = |b: u32| ((b / span) * span) as f32 + span as f32 / 2.0 - n / 2.0;
    let (dx, dz) = (centre(bx), centre(bz));
    let r = ((dx * dx + dz * dz).sqrt() / (n / 2.0).max(1.0)).min(1.0);
    let mut rng = Rng::new(mix(&[seed, 0xd157, u64::from(bx / span), u64::from(bz / span)]));
    let roll = rng.unit();
    let downtown = 0.7 * (1.0 - r).powi(2);
    if r < 0.3 || roll < downtown {
        District::Downtown
    } else if roll < downtown + 0.45 * (1.0 - r) + 0.1 {
        District::Dense
    } else if roll < 0.85 {
        District::Sparse
    } else if roll < 0.93 {
        District::Industrial
    } else {
        District::Park
    }
}

/// Lays out the whole city deterministically from `seed`.
pub fn layout(params: LayoutParams, seed: u64) -> Result<City> {
    let mut b = Builder {
        city: City {
            scene: Scene {
                crs: Some(Crs::epsg(CRS_EPSG)),
                ..Scene::new(ORIGIN)
            },
            textures: Vec::new(),
        },
        params,
    };
    let half = params.blocks as f32 * PITCH / 2.0;
    for bz in 0..params.blocks {
        for bx in 0..params.blocks {
            let district = district_of(&params, seed, bx, bz);
            let mut rng = Rng::new(mix(&[seed, u64::from(bx), u64::from(bz)]));
            let x0 = bx as f32 * PITCH - half;
            let z0 = bz as f32 * PITCH - half;
            let (x1, z1) = (x0 + BLOCK, z0 + BLOCK);

            let ground = match district {
                District::Park | District::Sparse => Content::Grass,
                _ if rng.chance(0.3) => Content::Grass,
                _ => Content::Plaza {
                    base: grey(&mut rng, 0.55, 0.75),
                },
            };
            let s = rng.next_u64();
            b.horizontal([x0, z0, x1, z1], 0.0, 1.0, ground, s)?;
            let s = rng.next_u64();
            b.horizontal(
                [x1, z0, x1 + STREET, z1],
                0.0,
                1.0,
                Content::Street { along_u: false },
                s,
            )?;
            let s = rng.next_u64();
            b.horizontal(
                [x0, z1, x1 + STREET, z1 + STREET],
                0.0,
                1.0,
                Content::Street { along_u: true },
                s,
            )?;

            let (lots_x, lots_z) = match district {
                District::Downtown => (2, 2),
                District::Dense | District::Sparse => (3, 3),
                District::Industrial => (2, 1),
                District::Park => (0, 0),
            };
            let inner = BLOCK - 2.0 * SIDEWALK;
            let (lot_w, lot_d) = (inner / lots_x.max(1) as f32, inner / lots_z.max(1) as f32);
            for lz in 0..lots_z {
                for lx in 0..lots_x {
                    let lot_x = x0 + SIDEWALK + lx as f32 * lot_w;
                    let lot_z = z0 + SIDEWALK + lz as f32 * lot_d;
                    let (fill, height, density) = match district {
                        District::Downtown => (rng.range(0.7, 0.95), rng.range(30.0, 140.0), rng.range(2.5, 4.0)),
                        District::Dense => (rng.range(0.85, 1.0), rng.range(12.0, 35.0), rng.range(2.5, 5.0)),
                        District::Sparse => {
                            if rng.chance(0.3) {
                                continue;
                            }
                            (rng.range(0.35, 0.6), rng.range(4.0, 10.0), rng.range(3.0, 6.0))
                        }
                        District::Industrial => (rng.range(0.6, 0.9), rng.range(6.0, 15.0), rng.range(1.0, 2.0)),
                        District::Park => continue,
                    };
                    // Real city models mix texture resolutions (scans, photos, drafts):
                    // spread each building's density over a factor of 8.
                    let density = density * 2f32.powf(rng.range(-2.0, 1.0));
                    let (w, d) = ((lot_w - 2.0) * fill, (lot_d - 2.0) * fill * rng.range(0.8, 1.0));
                    let fx = lot_x + 1.0 + rng.range(0.0, lot_w - 2.0 - w);
                    let fz = lot_z + 1.0 + rng.range(0.0, lot_d - 2.0 - d);
                    let style = facade_style(&mut rng, district);
                    b.building(fx, fz, fx + w, fz + d, 0.0, height, style, density, &mut rng)?;
                    if district == District::Downtown && rng.chance(0.4) {
                        let inset = rng.range(3.0, 7.0).min(w.min(d) / 3.0);
                        let top = height + rng.range(15.0, 60.0);
                        let upper = facade_style(&mut rng, district);
                        b.building(
                            fx + inset,
                            fz + inset,
                            fx + w - inset,
                            fz + d - inset,
                            height,
                            top,
                            upper,
                            density,
                            &mut rng,
                        )?;
                    }
                }
            }
        }
    }
    Ok(b.city)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_is_deterministic_and_every_mesh_has_its_own_texture() {
        let params = LayoutParams {
            blocks: 3,
            max_extent_log2: 9,
            density_scale: 1.0,
        };
        let a = layout(params, 5).expect("layout");
        let b = layout(params, 5).expect("layout");
        assert_eq!(a.scene, b.scene);
        assert_eq!(a.scene.meshes.len(), a.textures.len());
        for (i, mesh) in a.scene.meshes.iter().enumerate() {
            assert_eq!(mesh.texture as usize, i);
        }
        let c = layout(params, 6).expect("layout");
        assert_ne!(
            a.scene.positions, c.scene.positions,
            "a different seed gives a different city"
        );
        assert!(a
            .textures
            .iter()
            .all(|t| (2..=9).contains(&t.width_log2) && (2..=9).contains(&t.height_log2)));
    }
}
