//! Which geometry tiles a view draws and which it asks the loader for: the 3D Tiles rule
//! of refinement by screen-space error, over a dataset's tile tree (format 4,
//! `citystream_dataset::tiles`), and the eviction that keeps it free of holes.
//!
//! A tile is drawn when its screen-space error is within the view's threshold or it has no
//! children; otherwise its children refine it. A tile that `replace`s with its children is
//! drawn in their stead until every child is resident, and its children are requested: so
//! the view shows a coarser surface while finer tiles load, never no surface.
//!
//! The traversal descends only through resident tiles, so a tile whose children are
//! missing is itself resident and can stand in for them. Eviction keeps the resident set
//! closed under parents ([`evictable`] offers only tiles the frame does not draw with no
//! resident child: children go first), so the root stays while anything under it is
//! needed, and no resident tile waits unseen behind a missing ancestor. Then, once the root
//! has loaded, every frame's drawn tiles cover every surface the tree has, each once
//! (`streaming/tests/tile_refinement.rs` checks it over random flights with random loads
//! and evictions). Not yet wired to the engine: the tiles of dataset format 4 come first
//! (docs/FORMAT4.md).

use citystream_dataset::tiles::{Refine, TileRecord, TileTree};

/// 3D Tiles' default maximum screen-space error, pixels.
pub const DEFAULT_MAX_ERROR_PX: f64 = 16.0;

/// The view tiles are refined for.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RefineView {
    /// The eye, in the frame of the tiles' origins.
    pub eye: [f64; 3],
    /// Vertical field of view, radians.
    pub fov_y: f64,
    /// Viewport height, pixels.
    pub viewport_height: u32,
    /// The largest screen-space error a drawn tile may show, pixels.
    pub max_error_px: f64,
}

impl RefineView {
    /// Pixels `tile`'s geometric error spans on screen at its nearest point to the eye:
    /// `error × height / (2 × distance × tan(fov / 2))`, 3D Tiles' formula for a perspective
    /// view. An eye inside the tile's bounds gets infinity (refine as far as the tree goes),
    /// a leaf's zero error zero.
    pub fn screen_space_error(&self, tile: &TileRecord) -> f64 {
        let error = f64::from(tile.geometric_error);
        if error <= 0.0 {
            return 0.0;
        }
        let distance = distance_to_bounds(self.eye, tile);
        if distance <= 0.0 {
            return f64::INFINITY;
        }
        error * f64::from(self.viewport_height) / (2.0 * distance * (self.fov_y * 0.5).tan())
    }

    /// Whether the view wants `tile`'s children instead of (or, refining by adding, beside)
    /// it.
    pub fn wants_children(&self, tile: &TileRecord) -> bool {
        tile.child_count > 0 && self.screen_space_error(tile) > self.max_error_px
    }
}

/// Distance from `eye` to `tile`'s bounds (0 inside them), in `f64`: the eye relative to
/// the tile's origin first, so a tile far from the frame's origin loses nothing.
pub fn distance_to_bounds(eye: [f64; 3], tile: &TileRecord) -> f64 {
    (0..3)
        .map(|axis| {
            let relative = eye[axis] - tile.origin[axis];
            let below = f64::from(tile.bounds_min[axis]) - relative;
            let above = relative - f64::from(tile.bounds_max[axis]);
            below.max(above).max(0.0)
        })
        .map(|d| d * d)
        .sum::<f64>()
        .sqrt()
}

/// One frame's refinement.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Selection {
    /// Resident tiles to draw, in traversal order (parents before children).
    pub draw: Vec<u32>,
    /// Tiles the view wants that are not resident, parents before children, each once: the
    /// loader's requests. A root that is not resident is requested and leaves its part of
    /// the view empty (only before the roots first load).
    pub requests: Vec<u32>,
}

/// The tiles of `tree` to draw for `view`, with `resident` saying which tiles' geometry is
/// loaded, and those to request.
pub fn select(tree: &TileTree, view: &RefineView, resident: impl Fn(u32) -> bool) -> Selection {
    let mut selection = Selection::default();
    // Depth first, children in order; a stack of tiles still to visit.
    let mut stack: Vec<u32> = tree.roots.clone().rev().collect();
    while let Some(t) = stack.pop() {
        let Some(tile) = tree.tiles.get(t as usize) else {
            continue;
        };
        if !resident(t) {
            selection.requests.push(t);
            continue;
        }
        if !view.wants_children(tile) {
            selection.draw.push(t);
            continue;
        }
        let children = tile.first_child..tile.first_child.saturating_add(tile.child_count);
        match tile.refine {
            Refine::Add => {
                // Its geometry stays beside its children's: drawn whatever they are.
                selection.draw.push(t);
                stack.extend(children.rev());
            }
            Refine::Replace => {
                let missing: Vec<u32> = children.clone().filter(|&c| !resident(c)).collect();
                if missing.is_empty() {
                    stack.extend(children.rev());
                } else {
                    // Drawn in its children's stead until they are all resident: no hole.
                    selection.draw.push(t);
                    selection.requests.extend(missing);
                }
            }
        }
    }
    selection
}

/// The resident tiles that may be evicted after a frame drew `drawn`: those it did not draw
/// with no resident child, so the resident set stays closed under parents and every
/// missing tile's parent can stand in for it. Children come before their parents (the
/// order of the tree reversed), so a caller freeing memory takes them from the front.
pub fn evictable(tree: &TileTree, resident: impl Fn(u32) -> bool, drawn: &[u32]) -> Vec<u32> {
    let mut drawn_flags = vec![false; tree.tiles.len()];
    for &t in drawn {
        if let Some(flag) = drawn_flags.get_mut(t as usize) {
            *flag = true;
        }
    }
    (0..tree.tiles.len() as u32)
        .rev()
        .filter(|&t| {
            let tile = &tree.tiles[t as usize];
            let children = tile.first_child..tile.first_child.saturating_add(tile.child_count);
            resident(t) && !drawn_flags[t as usize] && !children.clone().any(&resident)
        })
        .collect()
}
