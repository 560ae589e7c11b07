//! The flexible clipmap (Feldmann et al., "Flexible Clipmaps for Managing Growing
//! Textures", GRAPP 2011): the image-free half of the ground layer. Patches of georeferenced
//! imagery (any position, extent, resolution and capture time) are indexed in an R*-tree;
//! a fixed tile grid, anchored at the dataset's origin, is grouped into a quadtree whose
//! levels are the clip levels (§3.4: level 0 the finest); each level keeps a square of
//! tiles around the viewer in a toroidally addressed cache (§3.7); a tile map tells, for
//! every place, the finest level whose tile there is resident; a new patch invalidates
//! exactly the tiles it overlaps, and extends the clipmap by new levels when it reaches
//! beyond the current area (§3.5) or is finer than the finest level.
//!
//! Levels are named here by their *scale*: a tile at scale `s` covers `2^s` grid cells per
//! side. Scales stay fixed when the clipmap grows in either direction (a finer patch adds a
//! scale below the finest, a wider area one above the coarsest), so a tile's key never
//! changes; the paper's level is `s - finest scale`.

use std::collections::{HashMap, HashSet};

use rstar::{RTree, RTreeObject, AABB};

/// A tile: its scale (cells per side `2^scale`) and its index in that scale's grid.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct TileKey {
    /// Cells per side: `2^scale`.
    pub scale: i32,
    /// Index along x (east).
    pub x: i64,
    /// Index along z (south: the ground plane's second axis).
    pub z: i64,
}

/// A georeferenced image patch, in the dataset's ground coordinates (metres, x and z).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Patch {
    /// Caller's id.
    pub id: u64,
    /// Lower corner.
    pub min: [f64; 2],
    /// Upper corner.
    pub max: [f64; 2],
    /// Ground size of one of its texels, metres.
    pub metres_per_texel: f64,
    /// Capture time (or any priority): among patches of equal resolution, the later wins.
    pub captured_s: f64,
}

impl Patch {
    /// A patch over `min..max` at `metres_per_texel`, captured at `captured_s`.
    pub fn new(id: u64, min: [f64; 2], max: [f64; 2], metres_per_texel: f64, captured_s: f64) -> Patch {
        Patch {
            id,
            min,
            max,
            metres_per_texel,
            captured_s,
        }
    }
}

/// Why a patch was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ClipmapError {
    /// Corners or resolution not finite, an empty extent, or a resolution of 0 or less.
    #[error("patch {id}: {reason}")]
    BadPatch {
        /// The patch's id.
        id: u64,
        /// What is wrong.
        reason: String,
    },
    /// Options out of range.
    #[error("clipmap options: {0}")]
    BadOptions(String),
}

#[derive(PartialEq)]
struct PatchEntry(Patch);

impl RTreeObject for PatchEntry {
    type Envelope = AABB<[f64; 2]>;

    fn envelope(&self) -> Self::Envelope {
        AABB::from_corners(self.0.min, self.0.max)
    }
}

/// Options of a clipmap.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ClipmapOptions {
    /// Grid origin `o` (metres): the dataset origin's ground coordinates, so tiles stay put.
    pub origin: [f64; 2],
    /// Texels per tile side.
    pub tile_texels: u32,
    /// Tiles per side of each level's cache (the clip stack's square around the viewer).
    pub cache_side: u32,
}

/// What inserting a patch changed.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Insertion {
    /// Resident tiles the patch overlaps: their content must be composed again.
    pub invalidated: Vec<TileKey>,
    /// Scales added above the coarsest (the area grew) and below the finest (a finer patch).
    pub coarser_levels_added: u32,
    /// See `coarser_levels_added`.
    pub finer_levels_added: u32,
}

/// One level's toroidal tile cache: a `side × side` square of tiles centred on the viewer;
/// tile `(x, z)` lives in slot `(x mod side, z mod side)`, so moving by a tile replaces one
/// row or column and leaves every other slot in place.
#[derive(Clone, Debug, PartialEq)]
pub struct ToroidalCache {
    side: u32,
    /// Lower corner of the window (tile indices).
    corner: [i64; 2],
    /// Per slot: the tile it holds and whether its content is resident.
    slots: Vec<Option<(TileKey, bool)>>,
    scale: i32,
}

impl ToroidalCache {
    /// An empty cache of `side²` slots at `scale`, its window at `corner`.
    pub fn new(scale: i32, side: u32, corner: [i64; 2]) -> Self {
        let side = side.max(1);
        Self {
            side,
            corner,
            slots: vec![None; (side * side) as usize],
            scale,
        }
    }

    /// The slot of tile `(x, z)`: toroidal, whatever the signs.
    pub fn slot_of(&self, x: i64, z: i64) -> usize {
        let side = i64::from(self.side);
        (z.rem_euclid(side) * side + x.rem_euclid(side)) as usize
    }

    /// Whether tile `(x, z)` is inside the window.
    pub fn in_window(&self, x: i64, z: i64) -> bool {
        let side = i64::from(self.side);
        (self.corner[0]..self.corner[0] + side).contains(&x) && (self.corner[1]..self.corner[1] + side).contains(&z)
    }

    /// The window's lower corner.
    pub fn corner(&self) -> [i64; 2] {
        self.corner
    }

    /// Moves the window to `corner`: returns the tiles that entered (to be composed and
    /// uploaded, in their slots) and frees the slots of those that left.
    pub fn move_to(&mut self, corner: [i64; 2]) -> Vec<TileKey> {
        if corner == self.corner && self.slots.iter().all(Option::is_some) {
            return Vec::new();
        }
        self.corner = corner;
        let side = i64::from(self.side);
        let mut entered = Vec::new();
        for z in corner[1]..corner[1] + side {
            for x in corner[0]..corner[0] + side {
                let key = TileKey {
                    scale: self.scale,
                    x,
                    z,
                };
                let slot = self.slot_of(x, z);
                if self.slots[slot].map(|(held, _)| held) != Some(key) {
                    self.slots[slot] = Some((key, false));
                    entered.push(key);
                }
            }
        }
        entered
    }

    /// Marks tile `key` resident (its upload landed) if it is still in the window.
    pub fn set_resident(&mut self, key: TileKey, resident: bool) -> bool {
        if key.scale != self.scale || !self.in_window(key.x, key.z) {
            return false;
        }
        let slot = self.slot_of(key.x, key.z);
        match &mut self.slots[slot] {
            Some((held, flag)) if *held == key => {
                *flag = resident;
                true
            }
            _ => false,
        }
    }

    /// Whether tile `(x, z)` is in the window and resident.
    pub fn is_resident(&self, x: i64, z: i64) -> bool {
        self.in_window(x, z) && matches!(self.slots[self.slot_of(x, z)], Some((key, true)) if key.x == x && key.z == z)
    }

    /// Every tile the window holds, with its slot.
    pub fn tiles(&self) -> impl Iterator<Item = (usize, TileKey, bool)> + '_ {
        self.slots
            .iter()
            .enumerate()
            .filter_map(|(slot, held)| held.map(|(key, resident)| (slot, key, resident)))
    }
}

/// The flexible clipmap's bookkeeping: patches, levels, per-level caches, tile map.
pub struct Clipmap {
    options: ClipmapOptions,
    patches: RTree<PatchEntry>,
    /// Ground size of a grid cell (a finest-level tile), metres.
    cell_metres: f64,
    /// Scales from the finest to the coarsest, inclusive; `None` before the first patch.
    scales: Option<(i32, i32)>,
    /// Per scale: its cache.
    caches: HashMap<i32, ToroidalCache>,
}

impl std::fmt::Debug for Clipmap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Clipmap")
            .field("patches", &self.patches.size())
            .field("cell_metres", &self.cell_metres)
            .field("scales", &self.scales)
            .finish()
    }
}

fn check_patch(patch: &Patch) -> Result<(), ClipmapError> {
    let bad = |reason: &str| ClipmapError::BadPatch {
        id: patch.id,
        reason: reason.into(),
    };
    let corners = patch.min.iter().chain(&patch.max).all(|c| c.is_finite());
    if !corners {
        return Err(bad("corners are not finite"));
    }
    if patch.max[0] <= patch.min[0] || patch.max[1] <= patch.min[1] {
        return Err(bad("empty extent"));
    }
    if !(patch.metres_per_texel.is_finite() && patch.metres_per_texel > 0.0) {
        return Err(bad("metres per texel must be finite and above 0"));
    }
    if !patch.captured_s.is_finite() {
        return Err(bad("capture time is not finite"));
    }
    Ok(())
}

impl Clipmap {
    /// An empty clipmap; levels appear with the first patch.
    pub fn new(options: ClipmapOptions) -> Result<Self, ClipmapError> {
        if !options.origin.iter().all(|c| c.is_finite()) {
            return Err(ClipmapError::BadOptions("the origin is not finite".into()));
        }
        if !(16..=4096).contains(&options.tile_texels) || !options.tile_texels.is_power_of_two() {
            return Err(ClipmapError::BadOptions(format!(
                "{} texels per tile: a power of two from 16 to 4096",
                options.tile_texels
            )));
        }
        if !(2..=64).contains(&options.cache_side) {
            return Err(ClipmapError::BadOptions(format!(
                "{} tiles per cache side: 2 to 64",
                options.cache_side
            )));
        }
        Ok(Self {
            options,
            patches: RTree::new(),
            cell_metres: 0.0,
            scales: None,
            caches: HashMap::new(),
        })
    }

    /// The options it was built with.
    pub fn options(&self) -> &ClipmapOptions {
        &self.options
    }

    /// Ground size of a grid cell (a tile at scale 0), metres; 0 before the first patch.
    pub fn cell_metres(&self) -> f64 {
        self.cell_metres
    }

    /// Levels (the paper's `L`), 0 before the first patch.
    pub fn level_count(&self) -> u32 {
        self.scales.map_or(0, |(fine, coarse)| (coarse - fine + 1) as u32)
    }

    /// Finest and coarsest scale.
    pub fn scales(&self) -> Option<(i32, i32)> {
        self.scales
    }

    /// Ground size of a tile at `scale`, metres.
    pub fn tile_metres(&self, scale: i32) -> f64 {
        self.cell_metres * 2f64.powi(scale)
    }

    /// The index of the tile at `scale` holding ground point `p` (the paper's `n(l, r)`;
    /// the coarsest level is indexed like the others, so a tile's key never changes).
    pub fn tile_at(&self, scale: i32, p: [f64; 2]) -> TileKey {
        let size = self.tile_metres(scale);
        let index = |d: usize| ((p[d] - self.options.origin[d]) / size).floor() as i64;
        TileKey {
            scale,
            x: index(0),
            z: index(1),
        }
    }

    /// Ground bounds of a tile.
    pub fn tile_bounds(&self, key: TileKey) -> ([f64; 2], [f64; 2]) {
        let size = self.tile_metres(key.scale);
        let min = [
            self.options.origin[0] + key.x as f64 * size,
            self.options.origin[1] + key.z as f64 * size,
        ];
        (min, [min[0] + size, min[1] + size])
    }

    /// The area every patch covers together (the R*-tree root's bounds, `A`).
    pub fn area(&self) -> Option<([f64; 2], [f64; 2])> {
        (self.patches.size() > 0).then(|| {
            let envelope = self.patches.root().envelope();
            (envelope.lower(), envelope.upper())
        })
    }

    /// The coarsest scale whose tiles group `A` into at most 2 × 2 (§3.4, Eq. 1): the
    /// smallest scale at which the lower and upper corners' tiles differ by at most one
    /// index along both axes, plus one.
    fn coarsest_scale_for(&self, low: [f64; 2], high: [f64; 2], finest: i32) -> i32 {
        let mut scale = finest;
        loop {
            let (a, b) = (self.tile_at(scale, low), self.tile_at(scale, high));
            if (b.x - a.x) <= 1 && (b.z - a.z) <= 1 {
                return scale + 1;
            }
            scale += 1;
        }
    }

    /// Inserts a patch: it is indexed, the levels grow where it is finer than the finest
    /// level or reaches beyond the coarsest tile, and the resident tiles it overlaps (at
    /// every level) are returned for recomposition. A patch inside a better one (finer, or
    /// as fine and captured later: the order tiles take texels in) can never show and is
    /// not kept, nor are the patches a new one hides: a set listing one image many times
    /// costs each tile what one copy does.
    pub fn insert(&mut self, patch: Patch) -> Result<Insertion, ClipmapError> {
        check_patch(&patch)?;
        let envelope = AABB::from_corners(patch.min, patch.max);
        let hidden = self
            .patches
            .locate_in_envelope_intersecting(&envelope)
            .any(|entry| covers(bounds(&entry.0), bounds(&patch)) && better_first(&entry.0, &patch).is_lt());
        if hidden {
            return Ok(Insertion::default());
        }
        let hides: Vec<Patch> = self
            .patches
            .locate_in_envelope(&envelope)
            .map(|entry| entry.0)
            .filter(|inner| better_first(&patch, inner).is_lt())
            .collect();
        for inner in hides {
            self.patches.remove(&PatchEntry(inner));
        }
        let mut insertion = Insertion::default();
        let needed_cell = patch.metres_per_texel * f64::from(self.options.tile_texels);
        let (mut finest, coarsest) = match self.scales {
            None => {
                self.cell_metres = needed_cell;
                (0, 0)
            }
            Some(scales) => scales,
        };
        // Finer than the finest level: halve the cell until it resolves the patch. Scales
        // stay keyed to the same ground sizes, so existing tiles keep their keys.
        while self.tile_metres(finest) > needed_cell * (1.0 + 1e-9) {
            finest -= 1;
            if self.scales.is_some() {
                insertion.finer_levels_added += 1;
            }
        }
        self.patches.insert(PatchEntry(patch));
        let (low, high) = self.area().unwrap_or((patch.min, patch.max));
        let wanted_coarsest = self.coarsest_scale_for(low, high, finest).max(coarsest);
        if self.scales.is_some() {
            insertion.coarser_levels_added = (wanted_coarsest - coarsest) as u32;
        }
        self.scales = Some((finest, wanted_coarsest));
        for cache in self.caches.values() {
            for (_, key, resident) in cache.tiles() {
                if resident && overlaps(self.tile_bounds(key), (patch.min, patch.max)) {
                    insertion.invalidated.push(key);
                }
            }
        }
        insertion.invalidated.sort_unstable();
        Ok(insertion)
    }

    /// Recentres every level's cache on the viewer at ground point `eye`; returns the
    /// tiles that entered, finest level first (to compose and upload).
    pub fn recentre(&mut self, eye: [f64; 2]) -> Vec<TileKey> {
        let Some((finest, coarsest)) = self.scales else {
            return Vec::new();
        };
        let side = i64::from(self.options.cache_side);
        let mut entered = Vec::new();
        self.caches.retain(|scale, _| (finest..=coarsest).contains(scale));
        for scale in finest..=coarsest {
            let centre = self.tile_at(scale, eye);
            let corner = [centre.x - side / 2, centre.z - side / 2];
            let cache = self
                .caches
                .entry(scale)
                .or_insert_with(|| ToroidalCache::new(scale, side as u32, corner));
            entered.extend(cache.move_to(corner));
        }
        entered
    }

    /// Marks a tile's upload landed (or undone); false if its level's window no longer
    /// holds it.
    pub fn set_resident(&mut self, key: TileKey, resident: bool) -> bool {
        self.caches
            .get_mut(&key.scale)
            .is_some_and(|cache| cache.set_resident(key, resident))
    }

    /// The tile map's answer for ground point `p`: the finest scale whose tile there is
    /// resident (the level a fragment there may sample at best), if any.
    pub fn finest_resident_at(&self, p: [f64; 2]) -> Option<i32> {
        let (finest, coarsest) = self.scales?;
        (finest..=coarsest).find(|&scale| {
            let key = self.tile_at(scale, p);
            self.caches
                .get(&scale)
                .is_some_and(|cache| cache.is_resident(key.x, key.z))
        })
    }

    /// The patches that cover tile `key`, best first: finest resolution, then latest
    /// capture, then id. A tile is composed by taking, for each texel, the first patch that
    /// covers it.
    pub fn patches_for(&self, key: TileKey) -> Vec<Patch> {
        let (min, max) = self.tile_bounds(key);
        self.patches_in(min, max)
    }

    /// The patches whose interior overlaps the box `min..max` (a point where both are
    /// equal), best first as in [`patches_for`](Self::patches_for).
    pub fn patches_in(&self, min: [f64; 2], max: [f64; 2]) -> Vec<Patch> {
        let mut found: Vec<Patch> = self.overlapping(min, max).collect();
        found.sort_by(better_first);
        found
    }

    /// The patches that can show in tile `key`, best first: [`patches_for`](Self::patches_for)
    /// up to and including the best patch that covers the whole tile, which hides every
    /// patch after it (a tile takes each texel from the first patch covering it). Without
    /// sorting the hidden ones: a set of many patches over one place stays cheap.
    pub fn shown_patches_for(&self, key: TileKey) -> Vec<Patch> {
        let (min, max) = self.tile_bounds(key);
        let cover = self
            .overlapping(min, max)
            .filter(|p| covers(bounds(p), (min, max)))
            .min_by(better_first);
        let mut shown: Vec<Patch> = match cover {
            Some(cover) => self
                .overlapping(min, max)
                .filter(|p| better_first(p, &cover) != std::cmp::Ordering::Greater)
                .collect(),
            None => self.overlapping(min, max).collect(),
        };
        shown.sort_by(better_first);
        shown
    }

    fn overlapping(&self, min: [f64; 2], max: [f64; 2]) -> impl Iterator<Item = Patch> + '_ {
        self.patches
            .locate_in_envelope_intersecting(&AABB::from_corners(min, max))
            .map(|entry| entry.0)
            .filter(move |p| overlaps((min, max), (p.min, p.max)))
    }

    /// Every tile the caches hold, with its residency.
    pub fn cached_tiles(&self) -> Vec<(TileKey, bool)> {
        let mut out: Vec<(TileKey, bool)> = self
            .caches
            .values()
            .flat_map(|cache| cache.tiles().map(|(_, key, resident)| (key, resident)))
            .collect();
        out.sort_unstable();
        out
    }
}

/// Whether two open boxes overlap (touching edges do not).
/// Finest resolution first, then latest capture, then id: the order patches are used in.
fn better_first(a: &Patch, b: &Patch) -> std::cmp::Ordering {
    a.metres_per_texel
        .total_cmp(&b.metres_per_texel)
        .then(b.captured_s.total_cmp(&a.captured_s))
        .then(a.id.cmp(&b.id))
}

/// A patch's ground box.
fn bounds(patch: &Patch) -> ([f64; 2], [f64; 2]) {
    (patch.min, patch.max)
}

/// Whether box `outer` covers all of box `inner`.
fn covers(outer: ([f64; 2], [f64; 2]), inner: ([f64; 2], [f64; 2])) -> bool {
    (0..2).all(|d| outer.0[d] <= inner.0[d] && inner.1[d] <= outer.1[d])
}

fn overlaps(a: ([f64; 2], [f64; 2]), b: ([f64; 2], [f64; 2])) -> bool {
    (0..2).all(|d| a.0[d] < b.1[d] && b.0[d] < a.1[d])
}

/// Distinct slots of a window, for tests and checks.
pub fn window_slots(cache: &ToroidalCache) -> HashSet<usize> {
    cache.tiles().map(|(slot, _, _)| slot).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn options() -> ClipmapOptions {
        ClipmapOptions {
            origin: [1000.0, -2000.0],
            tile_texels: 256,
            cache_side: 4,
        }
    }

    fn patch(id: u64, min: [f64; 2], max: [f64; 2], metres_per_texel: f64) -> Patch {
        Patch::new(id, min, max, metres_per_texel, id as f64)
    }

    #[test]
    fn clipmap_toroidal_addressing_wraps_in_every_direction() {
        let mut cache = ToroidalCache::new(0, 4, [-2, -2]);
        assert_eq!(cache.move_to([-2, -2]).len(), 16);
        let mut corner = [-2i64, -2];
        // One tile at a time in each direction, across 0 and far from it.
        let steps: [[i64; 2]; 8] = [[1, 0], [0, 1], [-1, 0], [0, -1], [1, 1], [-1, -1], [1, -1], [-1, 1]];
        for (i, step) in steps.iter().cycle().take(64).enumerate() {
            let before: HashMap<TileKey, usize> = cache.tiles().map(|(slot, key, _)| (key, slot)).collect();
            corner = [corner[0] + step[0] * (1 + (i as i64 % 3)), corner[1] + step[1]];
            let entered = cache.move_to(corner);
            let after: HashMap<TileKey, usize> = cache.tiles().map(|(slot, key, _)| (key, slot)).collect();
            // The window is exactly the 4 × 4 tiles from the corner, each in its own slot.
            assert_eq!(window_slots(&cache).len(), 16);
            for z in corner[1]..corner[1] + 4 {
                for x in corner[0]..corner[0] + 4 {
                    let key = TileKey { scale: 0, x, z };
                    assert_eq!(after.get(&key), Some(&cache.slot_of(x, z)), "{key:?}");
                }
            }
            // Tiles that stayed kept their slots; only the entering ones were loaded.
            for (key, slot) in &after {
                if let Some(old) = before.get(key) {
                    assert_eq!(old, slot);
                    assert!(!entered.contains(key));
                } else {
                    assert!(entered.contains(key));
                }
            }
            let moved = [
                (step[0] * (1 + (i as i64 % 3))).unsigned_abs().min(4),
                step[1].unsigned_abs(),
            ];
            let stayed = (4 - moved[0]) * (4 - moved[1]);
            assert_eq!(entered.len() as u64, 16 - stayed, "step {i}: {step:?}");
        }
        // Far from the origin, negative and positive: still one slot per tile.
        for corner in [[-1_000_000_007i64, 3], [i64::MAX / 4, -(i64::MAX / 4)]] {
            cache.move_to(corner);
            assert_eq!(window_slots(&cache).len(), 16);
        }
    }

    #[test]
    fn clipmap_tile_map_points_at_the_finest_resident_level() {
        let mut map = Clipmap::new(options()).expect("options");
        // A coarse survey of 2 km, then a fine one of 100 m inside it.
        map.insert(patch(1, [0.0, -3000.0], [2000.0, -1000.0], 4.0))
            .expect("coarse");
        map.insert(patch(2, [900.0, -2100.0], [1000.0, -2000.0], 0.5))
            .expect("fine");
        let (finest, coarsest) = map.scales().expect("levels");
        assert!(coarsest > finest + 2, "{:?}", map.scales());
        let eye = [950.0, -2050.0];
        let entered = map.recentre(eye);
        assert!(!entered.is_empty());
        // Make a pseudo-random half of the tiles resident, then check the tile map against
        // a brute-force search at many places, as residency changes.
        let mut state = 12345u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            state >> 33
        };
        for round in 0..20 {
            for key in map.cached_tiles().into_iter().map(|(k, _)| k) {
                map.set_resident(key, next() % 2 == 0);
            }
            for _ in 0..200 {
                let p = [
                    eye[0] + (next() % 4000) as f64 - 2000.0,
                    eye[1] + (next() % 4000) as f64 - 2000.0,
                ];
                let brute = (finest..=coarsest).find(|&s| {
                    let key = map.tile_at(s, p);
                    map.cached_tiles().contains(&(key, true))
                });
                assert_eq!(map.finest_resident_at(p), brute, "round {round}, {p:?}");
            }
            map.recentre([eye[0] + round as f64 * 37.0, eye[1] - round as f64 * 11.0]);
        }
    }

    #[test]
    fn clipmap_inserting_a_patch_invalidates_only_the_tiles_it_overlaps() {
        let mut map = Clipmap::new(options()).expect("options");
        map.insert(patch(1, [0.0, -3000.0], [2000.0, -1000.0], 1.0))
            .expect("base");
        let eye = [1000.0, -2000.0];
        map.recentre(eye);
        for (key, _) in map.cached_tiles() {
            map.set_resident(key, true);
        }
        // A patch covering a quarter of one finest tile near the eye.
        let cell = map.tile_metres(map.scales().expect("levels").0);
        let small = patch(
            2,
            [1000.0 + 0.25 * cell, -2000.0 + 0.25 * cell],
            [1000.0 + 0.5 * cell, -2000.0 + 0.5 * cell],
            1.0,
        );
        let insertion = map.insert(small).expect("small");
        let expected: Vec<TileKey> = map
            .cached_tiles()
            .into_iter()
            .filter(|(key, _)| overlaps(map.tile_bounds(*key), (small.min, small.max)))
            .map(|(key, _)| key)
            .collect();
        assert_eq!(insertion.invalidated, expected);
        // One tile per level contains it (it lies within one finest tile).
        assert_eq!(insertion.invalidated.len() as u32, map.level_count());
        assert!(insertion.invalidated.len() < map.cached_tiles().len() / 4);
        // Tiles it does not touch are not invalidated, whatever the level.
        let far = map.tile_at(map.scales().expect("levels").0, [1000.0 + 2.5 * cell, -2000.0]);
        assert!(!insertion.invalidated.contains(&far));
        assert_eq!((insertion.coarser_levels_added, insertion.finer_levels_added), (0, 0));
        // The tile's patches come best first: the finer, then the later.
        let tile = insertion.invalidated[0];
        let ids: Vec<u64> = map.patches_for(tile).iter().map(|p| p.id).collect();
        assert_eq!(ids, vec![2, 1]);
    }

    #[test]
    fn clipmap_shows_patches_up_to_the_best_that_covers_the_tile() {
        let mut map = Clipmap::new(options()).expect("options");
        // A coarse base over everything, then a thousand copies of one patch over it all:
        // only the best copy (the latest captured) can show; a finer small patch still shows
        // first.
        map.insert(patch(1, [0.0, -3000.0], [2000.0, -1000.0], 4.0))
            .expect("base");
        for id in 10..1010 {
            map.insert(patch(id, [0.0, -3000.0], [2000.0, -1000.0], 2.0))
                .expect("copy");
        }
        map.recentre([1000.0, -2000.0]);
        let cell = map.tile_metres(map.scales().expect("levels").0);
        let tile = map.tile_at(
            map.scales().expect("levels").0,
            [1000.0 + 0.1 * cell, -2000.0 + 0.1 * cell],
        );
        let (min, _) = map.tile_bounds(tile);
        map.insert(patch(5, [min[0], min[1]], [min[0] + 1.0, min[1] + 1.0], 1.0))
            .expect("small");
        let shown: Vec<u64> = map.shown_patches_for(tile).iter().map(|p| p.id).collect();
        assert_eq!(shown, vec![5, 1009]);
        // Patches that can never show are not kept: the base lies inside the finer copies,
        // each copy inside the later one.
        let all: Vec<u64> = map.patches_for(tile).iter().map(|p| p.id).collect();
        assert_eq!(all, vec![5, 1009]);
    }

    #[test]
    fn clipmap_keeps_no_patch_that_a_better_one_hides() {
        let mut map = Clipmap::new(options()).expect("options");
        let everywhere = |id, mpt| patch(id, [0.0, -3000.0], [2000.0, -1000.0], mpt);
        map.insert(everywhere(1, 2.0)).expect("first");
        // Coarser and inside it: hidden whenever it arrives.
        assert_eq!(map.insert(everywhere(2, 4.0)), Ok(Insertion::default()));
        map.insert(patch(3, [100.0, -2900.0], [200.0, -2800.0], 4.0))
            .expect("inside");
        // Finer and inside it: kept; partly outside: kept.
        map.insert(patch(4, [100.0, -2900.0], [200.0, -2800.0], 1.0))
            .expect("finer");
        map.insert(patch(5, [1900.0, -1100.0], [2100.0, -900.0], 4.0))
            .expect("partly out");
        let ids = |map: &Clipmap| {
            let mut ids: Vec<u64> = map.patches_in([-1e9, -1e9], [1e9, 1e9]).iter().map(|p| p.id).collect();
            ids.sort_unstable();
            ids
        };
        assert_eq!(ids(&map), vec![1, 4, 5]);
        // A later capture of the same extent and resolution hides the first, which goes.
        map.insert(Patch {
            captured_s: 10.0,
            ..everywhere(6, 2.0)
        })
        .expect("later");
        assert_eq!(ids(&map), vec![4, 5, 6]);
    }

    #[test]
    fn clipmap_grows_levels_for_a_larger_or_finer_patch() {
        let mut map = Clipmap::new(options()).expect("options");
        map.insert(patch(1, [0.0, 0.0], [500.0, 500.0], 1.0)).expect("first");
        let (finest, coarsest) = map.scales().expect("levels");
        assert_eq!(map.tile_metres(finest), 256.0);
        // 500 m from the origin at 1000 m: the tiles at the coarsest scale but one group
        // it into at most 2 × 2.
        let below = coarsest - 1;
        let (a, b) = (map.tile_at(below, [0.0, 0.0]), map.tile_at(below, [500.0, 500.0]));
        assert!(b.x - a.x <= 1 && b.z - a.z <= 1);
        // Eight times farther: three more levels above.
        let wider = map.insert(patch(2, [0.0, 0.0], [4500.0, 500.0], 1.0)).expect("wider");
        assert!(wider.coarser_levels_added >= 3, "{wider:?}");
        assert_eq!(wider.finer_levels_added, 0);
        // Four times finer: two levels below, existing tiles keep their keys.
        let before = map.tile_at(finest, [100.0, 100.0]);
        let finer = map
            .insert(patch(3, [100.0, 100.0], [120.0, 120.0], 0.25))
            .expect("finer");
        assert_eq!(finer.finer_levels_added, 2);
        assert_eq!(map.scales().expect("levels").0, finest - 2);
        assert_eq!(map.tile_at(finest, [100.0, 100.0]), before);
        assert_eq!(map.tile_metres(finest - 2), 64.0);
        // A patch inside everything, no finer: nothing grows.
        let same = map.insert(patch(4, [10.0, 10.0], [20.0, 20.0], 1.0)).expect("same");
        assert_eq!((same.coarser_levels_added, same.finer_levels_added), (0, 0));
    }

    #[test]
    fn clipmap_refuses_bad_patches_and_options() {
        let mut map = Clipmap::new(options()).expect("options");
        for bad in [
            patch(1, [f64::NAN, 0.0], [1.0, 1.0], 1.0),
            patch(2, [0.0, 0.0], [0.0, 1.0], 1.0),
            patch(3, [0.0, 0.0], [1.0, 1.0], 0.0),
            patch(4, [0.0, 0.0], [1.0, 1.0], f64::INFINITY),
        ] {
            let error = map.insert(bad).expect_err("refused");
            assert!(error.to_string().contains(&format!("patch {}", bad.id)), "{error}");
        }
        assert_eq!(map.level_count(), 0);
        for options in [
            ClipmapOptions {
                tile_texels: 100,
                ..options()
            },
            ClipmapOptions {
                cache_side: 1,
                ..options()
            },
            ClipmapOptions {
                origin: [f64::NAN, 0.0],
                ..options()
            },
        ] {
            assert!(Clipmap::new(options).is_err());
        }
    }
}
