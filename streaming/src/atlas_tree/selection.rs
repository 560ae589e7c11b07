//! The rendering traversal (§4, with §6's resident-ancestor fallback): which nodes a
//! view draws, with which atlas, and the view geometry it needs.

use super::{AtlasTree, Block};
use citystream_dataset::Aabb;

/// The camera a traversal sees with.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TreeView {
    /// Eye, relative to the scene origin.
    pub eye: [f32; 3],
    /// Frustum planes `(a, b, c, d)`, inside where `a·x + b·y + c·z + d >= 0`.
    pub planes: [[f32; 4]; 6],
    /// Screen height, pixels.
    pub screen_height: f32,
    /// Vertical field of view, radians.
    pub fov_y: f32,
    /// Target texels per pixel.
    pub texel_per_pixel: f32,
}

/// How a selected node's triangles are drawn.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DrawWith {
    /// Every leaf triangle under the node, with the atlas of this node (the node itself,
    /// or its nearest resident ancestor where its own is not resident).
    Atlas(u32),
    /// A leaf's triangles with their original textures.
    Originals,
}

/// A traversal's result: what to draw, in traversal order.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Selection {
    /// `(node, how)`: the triangles of the node's subtree, and the texture they are drawn
    /// with. Every leaf lies under exactly one drawn node (or none, where culled).
    pub draws: Vec<(u32, DrawWith)>,
    /// Draws that fell back to a resident ancestor's atlas (§6).
    pub fallbacks: u32,
}

/// The finest level of an atlas a camera `distance` away needs when level 0 suffices from
/// `min_distance` on: each level further halves the texels, so doubles the distance.
pub fn atlas_level_for(distance: f32, min_distance: f32, mip_count: u32) -> u32 {
    if !(distance > min_distance && min_distance > 0.0) {
        return 0;
    }
    let level = (distance / min_distance).log2().floor();
    (level as u32).min(mip_count.saturating_sub(1))
}

/// Distance from `p` to the box (0 inside).
pub fn distance_to(bounds: &Aabb, p: [f32; 3]) -> f32 {
    let sum: f32 = (0..3)
        .map(|a| {
            let d = (bounds.min[a] - p[a]).max(p[a] - bounds.max[a]).max(0.0);
            d * d
        })
        .sum();
    sum.sqrt()
}

/// The six planes of a view-projection matrix (column-major, Vulkan clip space: depth 0 to
/// 1), inside where `a·x + b·y + c·z + d >= 0` (Gribb and Hartmann's extraction). Under the
/// engine's reversed depth with no far plane, `w − z` is the near plane and `z` is
/// `(0, 0, 0, near)`, inside everywhere: nothing is too far. The planes are not normalised,
/// so that degenerate one divides by nothing.
pub fn frustum_planes(view_projection: [[f32; 4]; 4]) -> [[f32; 4]; 6] {
    let row = |r: usize| view_projection.map(|column| column[r]);
    let (x, y, z, w) = (row(0), row(1), row(2), row(3));
    let add = |a: [f32; 4], b: [f32; 4]| [0, 1, 2, 3].map(|i| a[i] + b[i]);
    let sub = |a: [f32; 4], b: [f32; 4]| [0, 1, 2, 3].map(|i| a[i] - b[i]);
    [add(w, x), sub(w, x), add(w, y), sub(w, y), z, sub(w, z)]
}

/// Whether the box is at least partly inside every plane.
pub fn intersects_frustum(bounds: &Aabb, planes: &[[f32; 4]; 6]) -> bool {
    planes.iter().all(|p| {
        // The box corner farthest along the plane normal.
        let corner = [0, 1, 2].map(|a| if p[a] >= 0.0 { bounds.max[a] } else { bounds.min[a] });
        p[0] * corner[0] + p[1] * corner[1] + p[2] * corner[2] + p[3] >= 0.0
    })
}

impl AtlasTree {
    /// The rendering traversal (§4, with §6's change for missing nodes): from the root,
    /// frustum-culled; a node at least its (rescaled) `min_distance` away draws its subtree
    /// with its atlas; nearer, its children are visited (a leaf draws its originals). Where
    /// a finer block is not resident (`resident`), the nearest resident ancestor's atlas
    /// draws it instead; the root's atlas is taken as resident whatever `resident` says.
    pub fn select(&self, view: &TreeView, resident: impl Fn(Block) -> bool) -> Selection {
        let mut selection = Selection::default();
        if self.nodes.is_empty() {
            return selection;
        }
        let scale = self
            .params
            .distance_scale(view.screen_height, view.fov_y, view.texel_per_pixel) as f32;
        // (node, the nearest resident atlas at or above it)
        let mut stack = vec![(0u32, 0u32)];
        while let Some((n, fallback)) = stack.pop() {
            let node = &self.nodes[n as usize];
            if !intersects_frustum(&node.bounds, &view.planes) {
                continue;
            }
            let fallback = if n == 0 || resident(Block::Atlas(n)) {
                n
            } else {
                fallback
            };
            if distance_to(&node.bounds, view.eye) >= self.draw_distance(n) * scale {
                selection.draws.push((n, DrawWith::Atlas(fallback)));
                selection.fallbacks += u32::from(fallback != n);
            } else if node.is_leaf() {
                if resident(Block::Originals(n)) {
                    selection.draws.push((n, DrawWith::Originals));
                } else {
                    selection.draws.push((n, DrawWith::Atlas(fallback)));
                    selection.fallbacks += 1;
                }
            } else {
                stack.extend(node.children().rev().map(|c| (c, fallback)));
            }
        }
        selection
    }
}
