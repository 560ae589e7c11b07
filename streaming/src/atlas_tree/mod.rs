//! The texture-atlas tree (Buchholz & Döllner, "View-dependent rendering of multiresolution
//! texture-atlases"): its file, and the parts of the algorithm that need no images: the
//! texel-per-pixel bound behind `minDistance` (§5.2.1), the rendering traversal that picks
//! nodes by distance (§4, with the resident-ancestor fallback of §6) and the paging
//! priorities (§6: usage, then distance, then tree level).
//!
//! A tree is a dataset (the usual files) plus `atlas-tree.bin` in its write directory. The
//! dataset's textures are the nodes' atlases (one per node, all of one extent) followed by
//! the original textures; its meshes are the leaves' triangles, one mesh per (leaf, original
//! texture), with the original texture coordinates. The tree file holds the nodes (a
//! quadtree over the ground plane, x–z, irregular: a node has 0 to 4 children) and, for
//! every vertex, its coordinates in the root atlas: node `N` samples its own atlas at
//! `root_uv * N.uv_scale - N.uv_offset` (a node at depth `k` covers a `2^-k` square of the
//! root atlas; the paper's texture matrix). Layout in `docs/ATLAS_TREE.md`.
//!
//! Split by what each part answers: `file` reads and writes the tree file, `selection` is
//! the rendering traversal and the view geometry it needs, `paging` the §6 priorities and
//! the loader records; this module holds the tree, its nodes and the §5.2.1 bound.

mod file;
mod paging;
mod selection;

pub use file::{TREE_FILE, TREE_VERSION};
pub use paging::{Block, BlockPriority, Paging, Usage};
pub use selection::{atlas_level_for, distance_to, frustum_planes, intersects_frustum, DrawWith, Selection, TreeView};

use citystream_dataset::Aabb;

/// `parent` of the root.
pub const NO_PARENT: u32 = u32::MAX;
/// What a tree was built for: its atlases' extent and the view its distances assume.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TreeParams {
    /// Side of every node's atlas, texels.
    pub atlas_extent: u32,
    /// Screen height the distances were computed for, pixels.
    pub screen_height: u32,
    /// Vertical field of view the distances were computed for, radians.
    pub fov_y: f32,
    /// Texels per screen pixel the atlases provide at their node's `min_distance`.
    pub texel_per_pixel: f32,
    /// `min_distance` of the leaves (the paper's `d_min`), metres.
    pub leaf_min_distance: f32,
}

impl TreeParams {
    /// Screen pixels per metre at distance 1 for a segment facing the camera, times the
    /// texel-per-pixel ratio: the paper's `f_proj · d` (texels needed per metre at
    /// distance `d` is this divided by `d`).
    pub fn texels_per_metre_at_unit_distance(&self) -> f64 {
        texels_per_metre_at_unit_distance(self.screen_height as f32, self.fov_y, self.texel_per_pixel)
    }

    /// The factor distances of this tree scale by for another screen height, field of view
    /// and texel-per-pixel ratio (§4: "rescale the minimum distance values").
    pub fn distance_scale(&self, screen_height: f32, fov_y: f32, texel_per_pixel: f32) -> f64 {
        texels_per_metre_at_unit_distance(screen_height, fov_y, texel_per_pixel)
            / self.texels_per_metre_at_unit_distance()
    }
}

/// `H · R / (2 tan(fov/2))`: texels per metre needed at distance 1 (§5.2.1, vertical).
pub fn texels_per_metre_at_unit_distance(screen_height: f32, fov_y: f32, texel_per_pixel: f32) -> f64 {
    f64::from(screen_height) * f64::from(texel_per_pixel) / (2.0 * (f64::from(fov_y) * 0.5).tan())
}

/// One node. Children are contiguous and come after their parent.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TreeNode {
    /// Bounds of the node's triangles, relative to the scene origin.
    pub bounds: Aabb,
    /// From this distance to `bounds` on, the atlas at level 0 has every texel the view
    /// needs (metres, for the tree's [`TreeParams`]); each doubling a level coarser. A leaf
    /// is drawn with its atlas from the nearer `TreeParams::leaf_min_distance` on already,
    /// where its atlas shows what the originals would (see [`AtlasTree::draw_distance`]).
    pub min_distance: f32,
    /// Parent index ([`NO_PARENT`] for the root, node 0).
    pub parent: u32,
    /// First child's index (0 without children).
    pub first_child: u32,
    /// Children: 0 (a leaf) to 4.
    pub child_count: u32,
    /// Texture id of the node's atlas.
    pub atlas: u32,
    /// Atlas coordinates of this node: `root_uv * uv_scale - uv_offset`.
    pub uv_scale: f32,
    /// See `uv_scale`.
    pub uv_offset: [f32; 2],
    /// Leaves: their meshes, `first_mesh..first_mesh + mesh_count` of the scene.
    pub first_mesh: u32,
    /// See `first_mesh` (0 for inner nodes).
    pub mesh_count: u32,
}

impl TreeNode {
    /// Whether the node has no children.
    pub fn is_leaf(&self) -> bool {
        self.child_count == 0
    }

    /// Its children's indices.
    pub fn children(&self) -> std::ops::Range<u32> {
        self.first_child..self.first_child + self.child_count
    }
}

/// A texture-atlas tree: parameters, nodes, and every vertex's root-atlas coordinates.
#[derive(Clone, Debug, PartialEq)]
pub struct AtlasTree {
    /// What it was built for.
    pub params: TreeParams,
    /// Nodes; 0 is the root.
    pub nodes: Vec<TreeNode>,
    /// Per scene vertex: coordinates in the root atlas.
    pub atlas_uvs: Vec<[f32; 2]>,
}

/// §5.2.1 for one triangle: the world length of the unit texture-space vectors `(1, 0)` and
/// `(0, 1)` (one repetition of the texture along u and v) on the triangle, metres. `None`
/// for a triangle degenerate in world space; a degenerate texture mapping uses its longest
/// texture-space edge for both (a single point in texture space gives `(0, 0)`).
pub fn world_length_of_texture_axes(positions: [[f32; 3]; 3], uvs: [[f32; 2]; 3]) -> Option<(f64, f64)> {
    let p = positions.map(|v| v.map(f64::from));
    let t = uvs.map(|v| v.map(f64::from));
    let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let len = |v: [f64; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    let (v1, v2) = (sub(p[1], p[0]), sub(p[2], p[0]));
    let cross = [
        v1[1] * v2[2] - v1[2] * v2[1],
        v1[2] * v2[0] - v1[0] * v2[2],
        v1[0] * v2[1] - v1[1] * v2[0],
    ];
    // NaN counts as degenerate too.
    if len(cross).partial_cmp(&1e-12) != Some(std::cmp::Ordering::Greater) {
        return None;
    }
    let (t1, t2) = (
        [t[1][0] - t[0][0], t[1][1] - t[0][1]],
        [t[2][0] - t[0][0], t[2][1] - t[0][1]],
    );
    let det = t1[0] * t2[1] - t1[1] * t2[0];
    if det.abs() < 1e-12 {
        // Degenerate mapping: world length over texture length along the longest edge.
        let edges = [(0usize, 1usize), (1, 2), (0, 2)];
        let (i, j) = edges
            .into_iter()
            .max_by(|&(a, b), &(c, d)| {
                let l = |i: usize, j: usize| (t[i][0] - t[j][0]).hypot(t[i][1] - t[j][1]);
                l(a, b).total_cmp(&l(c, d))
            })
            .unwrap_or((0, 1));
        let tex = (t[i][0] - t[j][0]).hypot(t[i][1] - t[j][1]);
        if tex < 1e-12 {
            return Some((0.0, 0.0));
        }
        let world = len(sub(p[i], p[j])) / tex;
        return Some((world, world));
    }
    // Tex_T^-1(x): (a, b) with a·t1 + b·t2 = x; then P_T(a, b) = a·v1 + b·v2.
    let inverse = |x: [f64; 2]| {
        let a = (x[0] * t2[1] - x[1] * t2[0]) / det;
        let b = (t1[0] * x[1] - t1[1] * x[0]) / det;
        len([0, 1, 2].map(|k| a * v1[k] + b * v2[k]))
    };
    Some((inverse([1.0, 0.0]), inverse([0.0, 1.0])))
}

impl AtlasTree {
    /// Depth of the deepest node (the root alone: 1).
    pub fn depth(&self) -> u32 {
        self.levels().into_iter().max().map_or(0, |level| level + 1)
    }

    /// The distance (for the tree's [`TreeParams`]) from which node `n` is drawn with its
    /// atlas: an inner node's `min_distance`; a leaf's `d_min`
    /// ([`TreeParams::leaf_min_distance`]), nearer than its `min_distance` where an original
    /// has fewer texels than `d_min` needs: the leaf atlas holds those at their own
    /// resolution, so it shows what the originals would from `d_min` on (and at level 0 up
    /// to its `min_distance`, [`atlas_level_for`]).
    pub fn draw_distance(&self, n: u32) -> f32 {
        let node = &self.nodes[n as usize];
        if node.is_leaf() {
            node.min_distance.min(self.params.leaf_min_distance)
        } else {
            node.min_distance
        }
    }

    /// Depth of every node (root 0), in one pass: children come after their parent.
    pub fn levels(&self) -> Vec<u32> {
        let mut levels = vec![0u32; self.nodes.len()];
        for n in 0..self.nodes.len() {
            let parent = self.nodes[n].parent;
            if parent != NO_PARENT && (parent as usize) < n {
                levels[n] = levels[parent as usize] + 1;
            }
        }
        levels
    }

    /// Depth of node `n` (root 0).
    pub fn level(&self, mut n: u32) -> u32 {
        let mut level = 0;
        while let Some(node) = self.nodes.get(n as usize).filter(|node| node.parent != NO_PARENT) {
            n = node.parent;
            level += 1;
        }
        level
    }

    /// Leaves of the subtree under `n`, in order.
    pub fn leaves_under(&self, n: u32) -> Vec<u32> {
        let mut out = Vec::new();
        let mut stack = vec![n];
        while let Some(n) = stack.pop() {
            let node = &self.nodes[n as usize];
            if node.is_leaf() {
                out.push(n);
            } else {
                stack.extend(node.children().rev());
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::records::DEFAULT_WEIGHT_CUTOFF;
    use citystream_dataset::Scene;

    fn aabb(min: [f32; 3], max: [f32; 3]) -> Aabb {
        Aabb { min, max }
    }

    /// No plane culls anything.
    const EVERYWHERE: [[f32; 4]; 6] = [[0.0, 0.0, 0.0, 1.0]; 6];

    fn view(eye: [f32; 3], planes: [[f32; 4]; 6]) -> TreeView {
        TreeView {
            eye,
            planes,
            screen_height: 1000.0,
            fov_y: std::f32::consts::FRAC_PI_2,
            texel_per_pixel: 1.0,
        }
    }

    /// The row tree and the paging tests' view of it: from (140, 15, 5) m, the first plane
    /// keeping x ≥ 150 m.
    fn row_tree_seen_from_x_140() -> (AtlasTree, TreeView) {
        let mut planes = EVERYWHERE;
        planes[0] = [1.0, 0.0, 0.0, -150.0];
        (row_tree(), view([140.0, 15.0, 5.0], planes))
    }

    /// A root over x 0..400 with four leaves of 100 m each along x (children 1..5); leaf
    /// distances 10 m, root 20 m.
    fn row_tree() -> AtlasTree {
        let mut nodes = vec![TreeNode {
            bounds: aabb([0.0, 0.0, 0.0], [400.0, 10.0, 10.0]),
            min_distance: 20.0,
            parent: NO_PARENT,
            first_child: 1,
            child_count: 4,
            atlas: 0,
            uv_scale: 1.0,
            uv_offset: [0.0, 0.0],
            first_mesh: 0,
            mesh_count: 0,
        }];
        for k in 0..4u32 {
            let x = k as f32 * 100.0;
            nodes.push(TreeNode {
                bounds: aabb([x, 0.0, 0.0], [x + 100.0, 10.0, 10.0]),
                min_distance: 10.0,
                parent: 0,
                first_child: 0,
                child_count: 0,
                atlas: 1 + k,
                uv_scale: 2.0,
                uv_offset: [(k % 2) as f32, (k / 2) as f32],
                first_mesh: k,
                mesh_count: 1,
            });
        }
        AtlasTree {
            params: TreeParams {
                atlas_extent: 64,
                screen_height: 1000,
                fov_y: std::f32::consts::FRAC_PI_2,
                texel_per_pixel: 1.0,
                leaf_min_distance: 10.0,
            },
            nodes,
            atlas_uvs: Vec::new(),
        }
    }

    #[test]
    fn atlas_tree_min_distance_bound_on_a_hand_computed_triangle() {
        // A 4 m × 2 m wall quad's triangle in the x–y plane, the texture once across it:
        // one repetition along u spans 4 m, along v 2 m.
        let positions = [[0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [0.0, 2.0, 0.0]];
        let uvs = [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]];
        let (su, sv) = world_length_of_texture_axes(positions, uvs).expect("not degenerate");
        assert!((su - 4.0).abs() < 1e-9 && (sv - 2.0).abs() < 1e-9, "{su} {sv}");
        // Repeated 3 times along u: one repetition spans 4/3 m.
        let repeated = [[0.0, 0.0], [3.0, 0.0], [0.0, 1.0]];
        let (su, _) = world_length_of_texture_axes(positions, repeated).expect("not degenerate");
        assert!((su - 4.0 / 3.0).abs() < 1e-9);
        // Screen 1000 px high, 90° field of view, 1 texel per pixel: at distance d a metre
        // facing the camera covers 1000 / (2 d tan 45°) = 500 / d pixels. At d = 50 m the
        // 4 m wall covers 40 px, so 40 texels across are the least that avoid
        // magnification there.
        let params = row_tree().params;
        let per_metre = params.texels_per_metre_at_unit_distance();
        assert!((per_metre - 500.0).abs() < 1e-3, "{per_metre}");
        assert!((4.0 * per_metre / 50.0 - 40.0).abs() < 1e-3);
        // Twice the screen height or ratio doubles the distances; 60° instead of 90°
        // multiplies them by tan 45° / tan 30°.
        assert!((params.distance_scale(2000.0, std::f32::consts::FRAC_PI_2, 1.0) - 2.0).abs() < 1e-6);
        assert!((params.distance_scale(1000.0, std::f32::consts::FRAC_PI_2, 0.5) - 0.5).abs() < 1e-6);
        let sixty = params.distance_scale(1000.0, 60f32.to_radians(), 1.0);
        assert!((sixty - 1.0 / (30f64.to_radians().tan())).abs() < 1e-4, "{sixty}");
        // Degenerate cases: a world-space sliver has no bound; a texture-space line uses its
        // longest edge; a texture-space point needs nothing.
        assert_eq!(
            world_length_of_texture_axes([[0.0; 3], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]], uvs),
            None
        );
        // (Longest texture edge: vertex 0 to 2, 1 texture unit over 2 m.)
        let line = world_length_of_texture_axes(positions, [[0.0, 0.0], [0.5, 0.0], [1.0, 0.0]]).expect("line");
        assert_eq!(line, (2.0, 2.0));
        assert_eq!(
            world_length_of_texture_axes(positions, [[0.5, 0.5]; 3]),
            Some((0.0, 0.0))
        );
    }

    #[test]
    fn atlas_tree_traversal_picks_nodes_by_distance_and_falls_back_to_resident_ancestors() {
        let tree = row_tree();
        let all = |_: Block| true;
        // Far away: the root's atlas draws everything.
        let far = tree.select(&view([200.0, 500.0, 5.0], EVERYWHERE), all);
        assert_eq!(far.draws, vec![(0, DrawWith::Atlas(0))]);
        // Over leaf 1 (x 0..100), 5 m above: leaf 1 is nearer than its 10 m, so originals;
        // leaf 2 (x 100..200) is 60 m away: its atlas; the root is too near to draw.
        let near = tree.select(&view([40.0, 15.0, 5.0], EVERYWHERE), all);
        assert_eq!(
            near.draws,
            vec![
                (1, DrawWith::Originals),
                (2, DrawWith::Atlas(2)),
                (3, DrawWith::Atlas(3)),
                (4, DrawWith::Atlas(4))
            ]
        );
        // A frustum that keeps only x >= 150 culls leaves 1.
        let mut planes = EVERYWHERE;
        planes[0] = [1.0, 0.0, 0.0, -150.0];
        let culled = tree.select(&view([40.0, 15.0, 5.0], planes), all);
        assert_eq!(
            culled.draws,
            vec![
                (2, DrawWith::Atlas(2)),
                (3, DrawWith::Atlas(3)),
                (4, DrawWith::Atlas(4))
            ]
        );
        // Leaf 1's originals missing: its own atlas draws it; leaf 2's atlas missing: the
        // root's draws it (only its triangles).
        let missing = tree.select(&view([40.0, 15.0, 5.0], EVERYWHERE), |b| {
            !matches!(b, Block::Originals(1) | Block::Atlas(2))
        });
        assert_eq!(
            missing.draws,
            vec![
                (1, DrawWith::Atlas(1)),
                (2, DrawWith::Atlas(0)),
                (3, DrawWith::Atlas(3)),
                (4, DrawWith::Atlas(4))
            ]
        );
        assert_eq!(missing.fallbacks, 2);
        // Every cut covers every leaf exactly once.
        for eye in [
            [40.0, 15.0, 5.0],
            [200.0, 500.0, 5.0],
            [390.0, 1.0, 5.0],
            [150.0, 30.0, 5.0],
        ] {
            let cut = tree.select(&view(eye, EVERYWHERE), all);
            let mut leaves: Vec<u32> = cut.draws.iter().flat_map(|&(n, _)| tree.leaves_under(n)).collect();
            leaves.sort_unstable();
            assert_eq!(leaves, vec![1, 2, 3, 4], "eye {eye:?}");
        }
    }

    #[test]
    fn atlas_tree_paging_records_are_the_ideal_block_set_in_priority_order() {
        let (tree, view) = row_tree_seen_from_x_140();
        let order: Vec<Block> = tree
            .block_priorities(&view)
            .iter()
            .filter(|p| p.usage != Usage::NotNeeded)
            .map(|p| p.block)
            .collect();
        // Scene meshes 0..4 (one per leaf); atlases are pseudo-meshes 4 + node.
        let paging = tree.paging(&view, 3, 4, 7);
        assert_eq!(paging.ideal, order[..3].to_vec());
        assert_eq!(paging.over_capacity, order.len() - 3);
        // Leaf 2's originals (its mesh 1), leaf 3's atlas (pseudo-mesh 7), leaf 4's (8),
        // weights strictly falling, all above the cut-off.
        let meshes: Vec<u32> = paging.records.iter().map(|r| r.mesh_id).collect();
        assert_eq!(meshes, vec![1, 7, 8]);
        assert!(paging.records.windows(2).all(|w| w[0].weight > w[1].weight));
        assert!(paging.records.iter().all(|r| r.weight > DEFAULT_WEIGHT_CUTOFF));
        // Leaf 3 is 60 m away, its atlas good from 10 m: two levels coarser do (40 m);
        // leaf 4 at 160 m: four.
        let levels: Vec<u32> = paging.records.iter().map(|r| r.mip_level).collect();
        assert_eq!(levels, vec![0, 2, 4]);
        assert_eq!(atlas_level_for(5.0, 10.0, 7), 0);
        assert_eq!(atlas_level_for(1e9, 10.0, 7), 6);
        assert_eq!(atlas_level_for(f32::NAN, 10.0, 7), 0);
        assert_eq!(tree.loader_mesh_textures(&Scene::new([0.0; 3])), vec![0, 1, 2, 3, 4]);
    }

    #[test]
    fn atlas_tree_paging_within_bytes_stops_at_the_first_block_that_overflows() {
        let (tree, view) = row_tree_seen_from_x_140();
        // Originals weigh 100 bytes, an atlas 64 >> level: leaf 2's originals (100), leaf
        // 3's atlas at level 2 (16), leaf 4's at level 4 (4) fit 120 bytes; the next does not.
        let bytes = |block: Block, level: u32| match block {
            Block::Originals(_) => 100,
            Block::Atlas(_) => 64u64 >> level,
        };
        let by_bytes = tree.paging_within(&view, 120, bytes, 4, 7);
        assert_eq!(by_bytes.ideal, tree.paging(&view, 3, 4, 7).ideal);
        assert_eq!(tree.paging_within(&view, 99, bytes, 4, 7).ideal, Vec::<Block>::new());
        // Sums saturate instead of wrapping round to fit.
        assert!(tree
            .paging_within(&view, 1 << 40, |_, _| u64::MAX, 4, 7)
            .ideal
            .is_empty());
        assert_eq!(
            tree.levels(),
            (0..tree.nodes.len() as u32).map(|n| tree.level(n)).collect::<Vec<_>>()
        );
    }

    #[test]
    fn atlas_tree_frustum_planes_of_a_projection_keep_what_it_sees() {
        // A camera at the origin looking down -z, 90° fov, square, depth 1..100, in
        // Vulkan's clip space (depth 0..1): clip = P · p, column-major.
        let (near, far) = (1.0f32, 100.0f32);
        let a = far / (near - far);
        let b = near * far / (near - far);
        let projection = [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, a, -1.0],
            [0.0, 0.0, b, 0.0],
        ];
        let planes = frustum_planes(projection);
        let point = |p: [f32; 3]| aabb(p, p);
        assert!(intersects_frustum(&point([0.0, 0.0, -10.0]), &planes));
        assert!(intersects_frustum(&point([9.0, -9.0, -10.0]), &planes));
        assert!(
            !intersects_frustum(&point([11.0, 0.0, -10.0]), &planes),
            "right of the view"
        );
        assert!(!intersects_frustum(&point([0.0, 11.0, -10.0]), &planes), "above it");
        assert!(!intersects_frustum(&point([0.0, 0.0, 10.0]), &planes), "behind the eye");
        assert!(
            !intersects_frustum(&point([0.0, 0.0, -0.5]), &planes),
            "nearer than the near plane"
        );
        assert!(
            !intersects_frustum(&point([0.0, 0.0, -101.0]), &planes),
            "beyond the far plane"
        );
        assert!(intersects_frustum(
            &aabb([-50.0, -1.0, -20.0], [50.0, 1.0, -10.0]),
            &planes
        ));
    }

    #[test]
    fn atlas_tree_frustum_planes_of_a_reversed_infinite_projection_keep_everything_far() {
        // The engine's projection: reversed depth, no far plane (clip z = near, w = −z_view).
        let near = 1.0f32;
        let projection = [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 0.0, -1.0],
            [0.0, 0.0, near, 0.0],
        ];
        let planes = frustum_planes(projection);
        let point = |p: [f32; 3]| aabb(p, p);
        assert!(intersects_frustum(&point([0.0, 0.0, -10.0]), &planes));
        assert!(
            intersects_frustum(&point([0.0, 0.0, -1.0e7]), &planes),
            "nothing is too far"
        );
        assert!(
            !intersects_frustum(&point([0.0, 0.0, -0.5]), &planes),
            "nearer than the near plane"
        );
        assert!(!intersects_frustum(&point([0.0, 0.0, 10.0]), &planes), "behind the eye");
        assert!(
            !intersects_frustum(&point([11.0, 0.0, -10.0]), &planes),
            "right of the view"
        );
    }

    #[test]
    fn atlas_tree_paging_order_follows_usage_then_distance_then_level() {
        let tree = row_tree();
        let mut planes = EVERYWHERE;
        planes[0] = [1.0, 0.0, 0.0, -150.0]; // leaf 1 (x 0..100) is culled
        let order = tree.block_priorities(&view([140.0, 15.0, 5.0], planes));
        let usage_of = |b: Block| order.iter().find(|p| p.block == b).expect("listed").usage;
        // Leaf 2 (x 100..200) is under the eye: its originals are needed, its atlas is the
        // parent-needed fallback; leaves 3 and 4 are far enough for their atlases (needed,
        // originals parent-needed); leaf 1 is fine at its atlas but culled.
        assert_eq!(usage_of(Block::Originals(2)), Usage::Needed);
        assert_eq!(usage_of(Block::Atlas(3)), Usage::Needed);
        assert_eq!(usage_of(Block::Atlas(4)), Usage::Needed);
        assert_eq!(usage_of(Block::Atlas(1)), Usage::Culled);
        assert_eq!(usage_of(Block::Originals(3)), Usage::ParentNeeded);
        assert_eq!(usage_of(Block::Atlas(0)), Usage::ParentNeeded);
        assert_eq!(usage_of(Block::Originals(1)), Usage::NotNeeded);
        // Sorted: usage first, then distance, then level.
        for pair in order.windows(2) {
            let (a, b) = (pair[0], pair[1]);
            assert!(
                a.usage < b.usage
                    || (a.usage == b.usage && a.distance < b.distance)
                    || (a.usage == b.usage && a.distance == b.distance && a.level <= b.level),
                "{a:?} before {b:?}"
            );
        }
        let needed: Vec<Block> = order
            .iter()
            .take_while(|p| p.usage == Usage::Needed)
            .map(|p| p.block)
            .collect();
        // Nearest first: leaf 2's originals (0 m), then leaf 3's atlas (60 m), leaf 4's (160 m).
        assert_eq!(needed, vec![Block::Originals(2), Block::Atlas(3), Block::Atlas(4)]);
        // Equal usage and distance: the lower level first (the root at 0 m before leaf 2's
        // atlas at 0 m).
        let root = order.iter().position(|p| p.block == Block::Atlas(0)).expect("root");
        let leaf2 = order.iter().position(|p| p.block == Block::Atlas(2)).expect("leaf 2");
        assert!(root < leaf2, "{order:?}");
    }
}
