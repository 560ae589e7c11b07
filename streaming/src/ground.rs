//! The ground layer's imagery on the CPU (no Vulkan): patch images with box-filtered mip
//! chains over a [`Clipmap`]; the composition of a clip-level tile from the patches that
//! cover it, best first (what the engine uploads); and the ground colour at a point for a
//! footprint, the reference the rendered ground is measured against. Both sample a patch
//! at the mip level whose texels are the largest not coarser than the footprint, bilinear
//! within it, so a tile holds what the reference shows at the tile's own resolution.

use std::collections::HashMap;
use std::sync::Arc;

use crate::clipmap::{Clipmap, ClipmapError, ClipmapOptions, Insertion, Patch, TileKey};

/// Why imagery was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GroundError {
    /// The clipmap refused the patch or the options.
    #[error(transparent)]
    Clipmap(#[from] ClipmapError),
    /// The image does not fit its patch.
    #[error("patch {id}: {reason}")]
    BadImage {
        /// The patch's id.
        id: u64,
        /// What is wrong.
        reason: String,
    },
    /// A tile buffer of the wrong size.
    #[error("tile {key:?}: buffer of {got} bytes, {expected} expected")]
    TileBuffer {
        /// The tile.
        key: TileKey,
        /// Bytes given.
        got: usize,
        /// Bytes a tile takes.
        expected: usize,
    },
}

#[derive(Clone, Debug)]
struct Level {
    width: u32,
    height: u32,
    texels: Vec<[u8; 4]>,
}

impl Level {
    fn at(&self, x: u32, y: u32) -> [u8; 4] {
        self.texels[(y * self.width + x) as usize]
    }

    /// The next coarser level: 2 × 2 box filter; an odd size rounds up, its last texel
    /// filtering the edge texel twice, so every texel of a level covers exactly twice the
    /// ground of the level below (levels stay aligned with the patch's lower corner).
    fn halved(&self) -> Level {
        let (width, height) = (self.width.div_ceil(2), self.height.div_ceil(2));
        let mut texels = Vec::with_capacity((width * height) as usize);
        for y in 0..height {
            for x in 0..width {
                let (x0, y0) = ((2 * x).min(self.width - 1), (2 * y).min(self.height - 1));
                let (x1, y1) = ((x0 + 1).min(self.width - 1), (y0 + 1).min(self.height - 1));
                let quad = [self.at(x0, y0), self.at(x1, y0), self.at(x0, y1), self.at(x1, y1)];
                texels.push(std::array::from_fn(|c| {
                    let sum: u32 = quad.iter().map(|t| u32::from(t[c])).sum();
                    ((sum + 2) / 4) as u8
                }));
            }
        }
        Level { width, height, texels }
    }

    /// Bilinear sample at continuous texel coordinates `(x, y)` of this level (texel
    /// centres at `i + 0.5`), clamped to its edges.
    fn sample(&self, x: f64, y: f64) -> [f32; 4] {
        let x = (x - 0.5).clamp(0.0, f64::from(self.width - 1));
        let y = (y - 0.5).clamp(0.0, f64::from(self.height - 1));
        let (x0, y0) = (x.floor() as u32, y.floor() as u32);
        let (x1, y1) = ((x0 + 1).min(self.width - 1), (y0 + 1).min(self.height - 1));
        let (fx, fy) = ((x - f64::from(x0)) as f32, (y - f64::from(y0)) as f32);
        let (a, b, c, d) = (self.at(x0, y0), self.at(x1, y0), self.at(x0, y1), self.at(x1, y1));
        std::array::from_fn(|i| {
            let top = f32::from(a[i]) * (1.0 - fx) + f32::from(b[i]) * fx;
            let bottom = f32::from(c[i]) * (1.0 - fx) + f32::from(d[i]) * fx;
            top * (1.0 - fy) + bottom * fy
        })
    }
}

/// An RGBA8 patch image (row 0 at the patch's lower z, column 0 at its lower x) with its
/// mip chain down to 1 × 1.
#[derive(Clone, Debug)]
pub struct PatchImage {
    levels: Vec<Level>,
}

impl PatchImage {
    /// The image of `width × height` texels in `rgba` (4 bytes per texel, rows in order).
    pub fn from_rgba8(width: u32, height: u32, rgba: &[u8]) -> Result<Self, String> {
        if width == 0 || height == 0 {
            return Err(format!("an image of {width}x{height} texels"));
        }
        let expected = u64::from(width) * u64::from(height) * 4;
        if rgba.len() as u64 != expected {
            return Err(format!(
                "{} bytes for {width}x{height} RGBA8 texels ({expected} expected)",
                rgba.len()
            ));
        }
        let texels = rgba.chunks_exact(4).map(|t| [t[0], t[1], t[2], t[3]]).collect();
        let mut levels = vec![Level { width, height, texels }];
        while let Some(last) = levels.last().filter(|l| l.width > 1 || l.height > 1) {
            let next = last.halved();
            levels.push(next);
        }
        Ok(Self { levels })
    }

    /// Texels across at full resolution.
    pub fn width(&self) -> u32 {
        self.levels[0].width
    }

    /// Texels down at full resolution.
    pub fn height(&self) -> u32 {
        self.levels[0].height
    }

    /// Mip levels, 1 × 1 included.
    pub fn level_count(&self) -> usize {
        self.levels.len()
    }
}

/// Patches with their images over a clipmap.
pub struct GroundImagery {
    clipmap: Clipmap,
    /// Shared with the host, which may hand the same image to another clipmap (a reference).
    images: HashMap<u64, Arc<PatchImage>>,
}

impl std::fmt::Debug for GroundImagery {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GroundImagery")
            .field("clipmap", &self.clipmap)
            .field("images", &self.images.len())
            .finish()
    }
}

/// The mip level of a patch whose texels of `metres_per_texel · 2^level` are the largest
/// not coarser than `footprint` metres.
fn patch_level(patch: &Patch, image: &PatchImage, footprint: f64) -> usize {
    let ratio = footprint / patch.metres_per_texel;
    // NaN (a zero footprint over zero) reads as full resolution too.
    if ratio.is_nan() || ratio < 2.0 {
        return 0;
    }
    (ratio.log2().floor() as usize).min(image.level_count() - 1)
}

fn contains(patch: &Patch, p: [f64; 2]) -> bool {
    (0..2).all(|d| patch.min[d] <= p[d] && p[d] < patch.max[d])
}

impl GroundImagery {
    /// Empty imagery over a clipmap with `options`.
    pub fn new(options: ClipmapOptions) -> Result<Self, GroundError> {
        Ok(Self {
            clipmap: Clipmap::new(options)?,
            images: HashMap::new(),
        })
    }

    /// The clipmap's bookkeeping.
    pub fn clipmap(&self) -> &Clipmap {
        &self.clipmap
    }

    /// The clipmap, to recentre and mark residency.
    pub fn clipmap_mut(&mut self) -> &mut Clipmap {
        &mut self.clipmap
    }

    /// Patches inserted.
    pub fn patch_count(&self) -> usize {
        self.images.len()
    }

    /// Inserts a patch with its image (see [`Clipmap::insert`]). An id already inserted is
    /// refused: ids name images.
    pub fn insert(&mut self, patch: Patch, image: impl Into<Arc<PatchImage>>) -> Result<Insertion, GroundError> {
        if self.images.contains_key(&patch.id) {
            return Err(GroundError::BadImage {
                id: patch.id,
                reason: "a patch of this id is already in the clipmap".into(),
            });
        }
        let insertion = self.clipmap.insert(patch)?;
        self.images.insert(patch.id, image.into());
        Ok(insertion)
    }

    /// Ground size of a texel of a tile at `scale`, metres.
    pub fn texel_metres(&self, scale: i32) -> f64 {
        self.clipmap.tile_metres(scale) / f64::from(self.clipmap.options().tile_texels)
    }

    fn colour_from(&self, patches: &[Patch], p: [f64; 2], footprint: f64) -> Option<[f32; 4]> {
        let patch = patches.iter().find(|patch| contains(patch, p))?;
        let image = self.images.get(&patch.id)?;
        let index = patch_level(patch, image, footprint);
        // In texels of level 0, then of the level: a level-k texel covers 2^k of level 0's.
        let shrink = 0.5f64.powi(index as i32);
        let x = (p[0] - patch.min[0]) / (patch.max[0] - patch.min[0]) * f64::from(image.width()) * shrink;
        let y = (p[1] - patch.min[1]) / (patch.max[1] - patch.min[1]) * f64::from(image.height()) * shrink;
        Some(image.levels[index].sample(x, y))
    }

    /// The ground's colour at `p` (RGBA, 0 to 255) seen with texels of `footprint` metres:
    /// the best patch covering `p`, at the mip level that footprint needs; `None` where no
    /// patch covers it.
    pub fn colour_at(&self, p: [f64; 2], footprint: f64) -> Option<[f32; 4]> {
        let patches = self.clipmap.patches_in(p, p);
        self.colour_from(&patches, p, footprint)
    }

    /// Whether the tile holds detail its parent lacks: some patch over it is finer than
    /// the parent's texels (the coarsest level always counts). Tiles without are not
    /// uploaded; the tile map sends fragments there to the parent.
    pub fn tile_adds_detail(&self, key: TileKey) -> bool {
        let patches = self.clipmap.shown_patches_for(key);
        let Some(finest) = patches.first() else {
            return false;
        };
        let coarsest = self.clipmap.scales().is_some_and(|(_, coarsest)| key.scale >= coarsest);
        coarsest || finest.metres_per_texel < self.texel_metres(key.scale + 1) * (1.0 - 1e-9)
    }

    /// Bytes of one composed tile (RGBA8).
    pub fn tile_bytes(&self) -> usize {
        let side = self.clipmap.options().tile_texels as usize;
        side * side * 4
    }

    /// Composes tile `key` into `out` (RGBA8, row 0 at the tile's lower z): each texel from
    /// the best patch covering its centre at the tile's resolution; alpha 0 where none does.
    pub fn compose_tile(&self, key: TileKey, out: &mut [u8]) -> Result<(), GroundError> {
        if out.len() != self.tile_bytes() {
            return Err(GroundError::TileBuffer {
                key,
                got: out.len(),
                expected: self.tile_bytes(),
            });
        }
        let side = self.clipmap.options().tile_texels as usize;
        let (min, _) = self.clipmap.tile_bounds(key);
        let texel = self.texel_metres(key.scale);
        let patches = self.clipmap.shown_patches_for(key);
        for (i, rgba) in out.chunks_exact_mut(4).enumerate() {
            let (x, z) = (i % side, i / side);
            let p = [min[0] + (x as f64 + 0.5) * texel, min[1] + (z as f64 + 0.5) * texel];
            let colour = self.colour_from(&patches, p, texel).unwrap_or([0.0; 4]);
            for (byte, value) in rgba.iter_mut().zip(colour) {
                *byte = value.round().clamp(0.0, 255.0) as u8;
            }
        }
        Ok(())
    }

    /// Composes `keys` into consecutive tiles of `out`, on rayon's workers (the loader's
    /// pool): a frame's tiles are composed while no other streaming work waits on them.
    pub fn compose_tiles(&self, keys: &[TileKey], out: &mut [u8]) -> Result<(), GroundError> {
        use rayon::prelude::*;
        let bytes = self.tile_bytes();
        let Some(&first) = keys.first() else {
            return Ok(());
        };
        let needed = keys.len() * bytes;
        if out.len() < needed {
            return Err(GroundError::TileBuffer {
                key: first,
                got: out.len(),
                expected: needed,
            });
        }
        out[..needed]
            .par_chunks_mut(bytes)
            .zip(keys.par_iter())
            .try_for_each(|(tile, &key)| self.compose_tile(key, tile))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn options() -> ClipmapOptions {
        ClipmapOptions {
            origin: [0.0, 0.0],
            tile_texels: 16,
            cache_side: 4,
        }
    }

    fn solid(width: u32, height: u32, rgba: [u8; 4]) -> PatchImage {
        let bytes: Vec<u8> = (0..width * height).flat_map(|_| rgba).collect();
        PatchImage::from_rgba8(width, height, &bytes).expect("image")
    }

    #[test]
    fn clipmap_patch_mips_box_filter_to_one_texel() {
        // A 3 × 2 checker of black and white: the chain is 3x2, 2x1 (odd sizes round up, so
        // every level covers the patch at twice the texel size), 1x1.
        let bytes: Vec<u8> = (0..6)
            .flat_map(|i| if i % 2 == 0 { [0u8; 4] } else { [255u8; 4] })
            .collect();
        let image = PatchImage::from_rgba8(3, 2, &bytes).expect("image");
        assert_eq!(image.level_count(), 3);
        let middle = &image.levels[1];
        assert_eq!((middle.width, middle.height), (2, 1));
        // Texel 0 from (0,0), (1,0), (0,1), (1,1): black, white, white, black; texel 1 from
        // the last column twice: (2,0) black, (2,1) white.
        assert_eq!(middle.texels, vec![[128; 4], [128; 4]]);
        let last = &image.levels[2];
        assert_eq!((last.width, last.height, last.texels[0]), (1, 1, [128; 4]));
        // A level's texels stay where the patch's are: a 4 × 1 ramp's level 1 holds the
        // means of texels 0-1 and 2-3, sampled at their own centres.
        let ramp: Vec<u8> = [0u8, 40, 80, 120].iter().flat_map(|&v| [v, v, v, 255]).collect();
        let ramp = PatchImage::from_rgba8(4, 1, &ramp).expect("ramp");
        assert_eq!(ramp.levels[1].sample(0.5, 0.5)[0], 20.0);
        assert_eq!(ramp.levels[1].sample(1.5, 0.5)[0], 100.0);
        assert!(PatchImage::from_rgba8(2, 2, &[0; 15]).is_err());
        assert!(PatchImage::from_rgba8(0, 2, &[]).is_err());
    }

    #[test]
    fn clipmap_tiles_compose_best_patch_first() {
        let mut ground = GroundImagery::new(options()).expect("options");
        // A coarse red base of 64 m at 1 m per texel, a fine green patch of 8 m at 0.25 m
        // per texel inside it, then a later blue one of the base's resolution over the
        // green: the green stays (finer wins), the blue replaces red elsewhere (later wins).
        ground
            .insert(
                Patch::new(0, [0.0, 0.0], [64.0, 64.0], 1.0, 0.0),
                solid(64, 64, [255, 0, 0, 255]),
            )
            .expect("base");
        ground
            .insert(
                Patch::new(1, [16.0, 16.0], [24.0, 24.0], 0.25, 1.0),
                solid(32, 32, [0, 255, 0, 255]),
            )
            .expect("fine");
        let (finest, _) = ground.clipmap().scales().expect("levels");
        assert!((ground.texel_metres(finest) - 0.25).abs() < 1e-9);
        let at = |g: &GroundImagery, p| g.colour_at(p, 0.25).map(|c| c.map(|v| v.round() as u8));
        assert_eq!(at(&ground, [20.0, 20.0]), Some([0, 255, 0, 255]));
        assert_eq!(at(&ground, [40.0, 40.0]), Some([255, 0, 0, 255]));
        assert_eq!(at(&ground, [70.0, 40.0]), None);
        ground
            .insert(
                Patch::new(2, [0.0, 0.0], [32.0, 32.0], 1.0, 2.0),
                solid(32, 32, [0, 0, 255, 255]),
            )
            .expect("later");
        assert_eq!(at(&ground, [20.0, 20.0]), Some([0, 255, 0, 255]));
        assert_eq!(at(&ground, [10.0, 10.0]), Some([0, 0, 255, 255]));
        assert_eq!(at(&ground, [40.0, 40.0]), Some([255, 0, 0, 255]));

        // The finest tile holding the green patch: green where it lies, blue around it.
        let key = ground.clipmap().tile_at(finest, [17.0, 17.0]);
        let mut tile = vec![0u8; ground.tile_bytes()];
        ground.compose_tile(key, &mut tile).expect("compose");
        let (min, max) = ground.clipmap().tile_bounds(key);
        let texel = ground.texel_metres(finest);
        for (i, rgba) in tile.chunks_exact(4).enumerate() {
            let (x, z) = ((i % 16) as f64, (i / 16) as f64);
            let p = [min[0] + (x + 0.5) * texel, min[1] + (z + 0.5) * texel];
            let inside = (16.0..24.0).contains(&p[0]) && (16.0..24.0).contains(&p[1]);
            let expected: &[u8] = if inside { &[0, 255, 0, 255] } else { &[0, 0, 255, 255] };
            assert_eq!(rgba, expected, "texel {i} at {p:?} of {min:?}..{max:?}");
        }
        // A finest tile with only 1 m imagery over it adds nothing to its parent; the one
        // holding the 0.25 m patch does; a tile past every patch is empty.
        assert!(ground.tile_adds_detail(key));
        assert!(!ground.tile_adds_detail(ground.clipmap().tile_at(finest, [40.0, 40.0])));
        let outside = ground.clipmap().tile_at(finest, [200.0, 200.0]);
        assert!(!ground.tile_adds_detail(outside));
        ground.compose_tile(outside, &mut tile).expect("compose");
        assert!(tile.iter().all(|&b| b == 0), "uncovered texels are transparent");
        assert!(matches!(
            ground.compose_tile(key, &mut [0u8; 3]),
            Err(GroundError::TileBuffer { got: 3, .. })
        ));
        assert!(matches!(
            ground.insert(Patch::new(1, [0.0, 0.0], [1.0, 1.0], 1.0, 3.0), solid(1, 1, [0; 4])),
            Err(GroundError::BadImage { id: 1, .. })
        ));
    }

    #[test]
    fn clipmap_coarse_tiles_sample_coarse_patch_levels() {
        let mut ground = GroundImagery::new(options()).expect("options");
        // Stripes one texel wide: at twice the footprint they average to grey.
        let bytes: Vec<u8> = (0..64 * 64)
            .flat_map(|i| {
                if (i % 64) % 2 == 0 {
                    [0u8, 0, 0, 255]
                } else {
                    [255, 255, 255, 255]
                }
            })
            .collect();
        ground
            .insert(
                Patch::new(0, [0.0, 0.0], [64.0, 64.0], 1.0, 0.0),
                PatchImage::from_rgba8(64, 64, &bytes).expect("image"),
            )
            .expect("insert");
        let fine = ground.colour_at([10.5, 10.5], 1.0).expect("covered");
        let coarse = ground.colour_at([10.5, 10.5], 2.0).expect("covered");
        assert!(fine[0] < 1.0 || fine[0] > 254.0, "{fine:?}");
        assert!((coarse[0] - 128.0).abs() < 1.5, "{coarse:?}");
    }
}
