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

use std::path::Path;

use crate::dataset::{Aabb, Dataset, DatasetError, Scene};
use crate::records::{MeshMetaData, DEFAULT_WEIGHT_CUTOFF};

/// The tree's file, in the dataset's write directory.
pub const TREE_FILE: &str = "atlas-tree.bin";
const MAGIC: &[u8; 8] = b"CSATTREE";
/// The tree file's format version.
pub const TREE_VERSION: u32 = 1;
const HEADER_BYTES: usize = 64;
const NODE_BYTES: usize = 64;
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

/// A unit of paging (§6): a node's atlas, or a leaf's original textures.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Block {
    /// The atlas of a node.
    Atlas(u32),
    /// The original textures of a leaf.
    Originals(u32),
}

/// §6's usage categories, most urgent first.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Usage {
    /// Used by the frame if the whole tree were resident.
    Needed,
    /// Fine enough but outside the view frustum: may become visible at once.
    Culled,
    /// The next refinement of something needed (a needed atlas's children's atlases, or a
    /// leaf's originals where its atlas is needed).
    ParentNeeded,
    /// None of the above.
    NotNeeded,
}

/// A block's priority: usage, then distance, then tree level (lower first in each).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BlockPriority {
    /// The block.
    pub block: Block,
    /// Its usage category.
    pub usage: Usage,
    /// Distance from the eye to its node's bounds, metres.
    pub distance: f32,
    /// Its node's depth (root 0).
    pub level: u32,
}

/// What the loader should load for a view (§6's ideal block set), as its records.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Paging {
    /// The ideal block set, highest priority first.
    pub ideal: Vec<Block>,
    /// Blocks §6 would keep that did not fit the capacity.
    pub over_capacity: usize,
    /// Loader records, heaviest (most urgent) first: an atlas as the pseudo-mesh
    /// `scene meshes + node` ([`AtlasTree::loader_mesh_textures`]), a leaf's originals as
    /// its meshes; levels as fine as the block's distance needs.
    pub records: Vec<MeshMetaData>,
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
/// 1), inside where `a·x + b·y + c·z + d >= 0` (Gribb and Hartmann's extraction).
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

    /// §6: every block's usage, distance and level, sorted by priority (usage, then
    /// distance, then level). The ideal block set of capacity `k` is the first `k` that are
    /// not [`Usage::NotNeeded`].
    pub fn block_priorities(&self, view: &TreeView) -> Vec<BlockPriority> {
        let scale = self
            .params
            .distance_scale(view.screen_height, view.fov_y, view.texel_per_pixel) as f32;
        let mut usage: std::collections::HashMap<Block, Usage> = std::collections::HashMap::new();
        fn raise(usage: &mut std::collections::HashMap<Block, Usage>, block: Block, to: Usage) {
            let entry = usage.entry(block).or_insert(Usage::NotNeeded);
            *entry = (*entry).min(to);
        }
        // The traversal as if every block were resident; outside the frustum it goes on,
        // marking what it finds `Culled` instead of `Needed`.
        let mut stack = vec![(0u32, true)];
        while let Some((n, visible)) = stack.pop() {
            let Some(node) = self.nodes.get(n as usize) else {
                continue;
            };
            let visible = visible && intersects_frustum(&node.bounds, &view.planes);
            let category = if visible { Usage::Needed } else { Usage::Culled };
            if distance_to(&node.bounds, view.eye) >= self.draw_distance(n) * scale {
                raise(&mut usage, Block::Atlas(n), category);
                // Prefetch the next refinement.
                if visible {
                    for c in node.children() {
                        raise(&mut usage, Block::Atlas(c), Usage::ParentNeeded);
                    }
                    if node.is_leaf() {
                        raise(&mut usage, Block::Originals(n), Usage::ParentNeeded);
                    }
                }
            } else if node.is_leaf() {
                raise(&mut usage, Block::Originals(n), category);
            } else {
                stack.extend(node.children().map(|c| (c, visible)));
            }
        }
        // Ancestors of what is needed are at least parent-needed (the path to a resident
        // atlas stays resident, §6).
        let needed: Vec<Block> = usage
            .iter()
            .filter(|(_, u)| **u <= Usage::Culled)
            .map(|(b, _)| *b)
            .collect();
        for block in needed {
            let n = match block {
                Block::Atlas(n) => self.nodes[n as usize].parent,
                Block::Originals(n) => n,
            };
            let mut n = n;
            while n != NO_PARENT {
                raise(&mut usage, Block::Atlas(n), Usage::ParentNeeded);
                n = self.nodes[n as usize].parent;
            }
        }
        let levels = self.levels();
        let mut all: Vec<BlockPriority> = (0..self.nodes.len() as u32)
            .flat_map(|n| {
                let leaf = self.nodes[n as usize].is_leaf();
                std::iter::once(Block::Atlas(n)).chain(leaf.then_some(Block::Originals(n)))
            })
            .map(|block| {
                let n = match block {
                    Block::Atlas(n) | Block::Originals(n) => n,
                };
                BlockPriority {
                    block,
                    usage: usage.get(&block).copied().unwrap_or(Usage::NotNeeded),
                    distance: distance_to(&self.nodes[n as usize].bounds, view.eye),
                    level: levels[n as usize] + u32::from(matches!(block, Block::Originals(_))),
                }
            })
            .collect();
        all.sort_by(|a, b| {
            a.usage
                .cmp(&b.usage)
                .then(a.distance.total_cmp(&b.distance))
                .then(a.level.cmp(&b.level))
                .then(a.block.cmp(&b.block))
        });
        all
    }

    /// The loader's mesh → texture table for this tree: the scene's meshes, then one
    /// pseudo-mesh per node whose texture is the node's atlas.
    pub fn loader_mesh_textures(&self, scene: &Scene) -> Vec<u32> {
        scene
            .meshes
            .iter()
            .map(|m| m.texture)
            .chain(self.nodes.iter().map(|n| n.atlas))
            .collect()
    }

    /// §6 for a view: the ideal block set (the first `capacity_blocks` of
    /// [`AtlasTree::block_priorities`] that are not [`Usage::NotNeeded`]) as loader records
    /// in priority order. `scene_meshes` is the scene's mesh count (where the atlas
    /// pseudo-meshes start); `atlas_mips` the atlases' mip count.
    pub fn paging(&self, view: &TreeView, capacity_blocks: usize, scene_meshes: u32, atlas_mips: u32) -> Paging {
        self.paging_within(view, capacity_blocks as u64, |_, _| 1, scene_meshes, atlas_mips)
    }

    /// [`AtlasTree::paging`] with the capacity in bytes: the ideal block set is the longest
    /// run of wanted blocks, in priority order, whose `block_bytes(block, level)` (an atlas
    /// from the level its distance needs, a leaf's originals whole: `level` 0) sum to at most
    /// `capacity_bytes`, so the capacity follows from a memory budget whatever the blocks
    /// weigh.
    pub fn paging_within(
        &self,
        view: &TreeView,
        capacity_bytes: u64,
        block_bytes: impl Fn(Block, u32) -> u64,
        scene_meshes: u32,
        atlas_mips: u32,
    ) -> Paging {
        let scale = self
            .params
            .distance_scale(view.screen_height, view.fov_y, view.texel_per_pixel) as f32;
        let level_of = |priority: &BlockPriority| match priority.block {
            Block::Atlas(n) => atlas_level_for(
                priority.distance,
                self.nodes[n as usize].min_distance * scale,
                atlas_mips,
            ),
            Block::Originals(_) => 0,
        };
        let wanted: Vec<BlockPriority> = self
            .block_priorities(view)
            .into_iter()
            .take_while(|p| p.usage != Usage::NotNeeded)
            .collect();
        let mut used = 0u64;
        let fitting = wanted
            .iter()
            .take_while(|p| {
                used = used.saturating_add(block_bytes(p.block, level_of(p)));
                used <= capacity_bytes
            })
            .count();
        let over_capacity = wanted.len() - fitting;
        let ideal: Vec<BlockPriority> = wanted.into_iter().take(fitting).collect();
        let count = ideal.len() as u32;
        let mut records = Vec::new();
        for (rank, priority) in ideal.iter().enumerate() {
            // Heaviest first, all above the loader's cut-off.
            let weight = DEFAULT_WEIGHT_CUTOFF.saturating_add(count - rank as u32);
            match priority.block {
                Block::Atlas(n) => records.push(MeshMetaData {
                    mip_level: level_of(priority),
                    weight,
                    mesh_id: scene_meshes.saturating_add(n),
                }),
                // Nearer than d_min: the originals at full resolution (the paper loads
                // them whole).
                Block::Originals(n) => {
                    let node = &self.nodes[n as usize];
                    records.extend(
                        (node.first_mesh..node.first_mesh + node.mesh_count).map(|mesh_id| MeshMetaData {
                            mip_level: 0,
                            weight,
                            mesh_id,
                        }),
                    );
                }
            }
        }
        Paging {
            ideal: ideal.iter().map(|p| p.block).collect(),
            over_capacity,
            records,
        }
    }

    /// Opens the tree of an opened dataset (its write directory's [`TREE_FILE`], locally or
    /// from the store it was opened from), checked against the dataset.
    pub fn open(dataset: &Dataset) -> Result<Self, DatasetError> {
        Self::open_if_any(dataset)?.ok_or_else(|| DatasetError::Missing {
            path: dataset.files().path(TREE_FILE),
        })
    }

    /// [`AtlasTree::open`], or `None` where the dataset is no tree (has no [`TREE_FILE`]).
    pub fn open_if_any(dataset: &Dataset) -> Result<Option<Self>, DatasetError> {
        let path = dataset.files().path(TREE_FILE);
        match dataset.read_write_file(TREE_FILE)? {
            Some(bytes) => Self::decode(&path, &bytes, dataset).map(Some),
            None => Ok(None),
        }
    }

    /// Encodes the tree for the dataset write `write_id`.
    pub fn encode(&self, write_id: u64) -> Vec<u8> {
        let mut out = Vec::with_capacity(HEADER_BYTES + self.nodes.len() * NODE_BYTES + self.atlas_uvs.len() * 8 + 4);
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&TREE_VERSION.to_le_bytes());
        out.extend_from_slice(&0u32.to_le_bytes());
        out.extend_from_slice(&write_id.to_le_bytes());
        out.extend_from_slice(&(self.nodes.len() as u32).to_le_bytes());
        out.extend_from_slice(&(self.atlas_uvs.len() as u32).to_le_bytes());
        let p = &self.params;
        out.extend_from_slice(&p.atlas_extent.to_le_bytes());
        out.extend_from_slice(&p.screen_height.to_le_bytes());
        for f in [p.fov_y, p.texel_per_pixel, p.leaf_min_distance] {
            out.extend_from_slice(&f.to_le_bytes());
        }
        out.resize(HEADER_BYTES, 0);
        for node in &self.nodes {
            for f in node.bounds.min.iter().chain(&node.bounds.max) {
                out.extend_from_slice(&f.to_le_bytes());
            }
            out.extend_from_slice(&node.min_distance.to_le_bytes());
            for u in [node.parent, node.first_child, node.child_count, node.atlas] {
                out.extend_from_slice(&u.to_le_bytes());
            }
            for f in [node.uv_scale, node.uv_offset[0], node.uv_offset[1]] {
                out.extend_from_slice(&f.to_le_bytes());
            }
            out.extend_from_slice(&node.first_mesh.to_le_bytes());
            out.extend_from_slice(&node.mesh_count.to_le_bytes());
        }
        for uv in &self.atlas_uvs {
            out.extend_from_slice(&uv[0].to_le_bytes());
            out.extend_from_slice(&uv[1].to_le_bytes());
        }
        let crc = crc32fast::hash(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }

    /// Decodes and checks a tree file of `dataset` (read from `path`): every error names
    /// the file and the offset or node at fault.
    pub fn decode(path: &Path, bytes: &[u8], dataset: &Dataset) -> Result<Self, DatasetError> {
        let corrupt = |offset: usize, what: String| DatasetError::Corrupt {
            path: path.to_path_buf(),
            offset: offset as u64,
            what,
        };
        if bytes.len() < HEADER_BYTES + 4 {
            return Err(DatasetError::Truncated {
                path: path.to_path_buf(),
                what: "the atlas-tree header".into(),
                offset: 0,
                end: (HEADER_BYTES + 4) as u64,
                file_len: bytes.len() as u64,
            });
        }
        if &bytes[..8] != MAGIC {
            return Err(corrupt(0, "not an atlas-tree file (magic is not CSATTREE)".into()));
        }
        let u32_at = |at: usize| u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]]);
        let f32_at = |at: usize| f32::from_bits(u32_at(at));
        let version = u32_at(8);
        if version != TREE_VERSION {
            return Err(corrupt(
                8,
                format!("version {version}; this build reads version {TREE_VERSION}"),
            ));
        }
        if u32_at(12) != 0 {
            return Err(corrupt(12, "flags are not 0".into()));
        }
        let (node_count, vertex_count) = (u32_at(24) as usize, u32_at(28) as usize);
        let expected = HEADER_BYTES as u64 + node_count as u64 * NODE_BYTES as u64 + vertex_count as u64 * 8 + 4;
        if bytes.len() as u64 != expected {
            return Err(DatasetError::Truncated {
                path: path.to_path_buf(),
                what: format!("{node_count} nodes and {vertex_count} vertices"),
                offset: 0,
                end: expected,
                file_len: bytes.len() as u64,
            });
        }
        let body = bytes.len() - 4;
        let (stored, computed) = (u32_at(body), crc32fast::hash(&bytes[..body]));
        if stored != computed {
            return Err(DatasetError::Checksum {
                path: path.to_path_buf(),
                what: "the atlas tree".into(),
                offset: 0,
                end: body as u64,
                stored,
                computed,
            });
        }
        let write_id = u64::from_le_bytes(bytes[16..24].try_into().unwrap_or_default());
        if write_id != dataset.files().write_id() {
            return Err(corrupt(
                16,
                format!(
                    "written for dataset write {write_id:016x}, but the dataset is write {:016x}",
                    dataset.files().write_id()
                ),
            ));
        }
        let params = TreeParams {
            atlas_extent: u32_at(32),
            screen_height: u32_at(36),
            fov_y: f32_at(40),
            texel_per_pixel: f32_at(44),
            leaf_min_distance: f32_at(48),
        };
        let in_range = params.atlas_extent.is_power_of_two()
            && params.screen_height > 0
            && params.fov_y > 0.0
            && params.fov_y < std::f32::consts::PI
            && params.texel_per_pixel.is_finite()
            && params.texel_per_pixel > 0.0
            && params.leaf_min_distance.is_finite()
            && params.leaf_min_distance >= 0.0;
        if !in_range {
            return Err(corrupt(32, format!("parameters out of range: {params:?}")));
        }
        let scene = &dataset.scene;
        if vertex_count != scene.positions.len() {
            return Err(corrupt(
                28,
                format!(
                    "{vertex_count} atlas coordinates for a scene of {} vertices",
                    scene.positions.len()
                ),
            ));
        }
        if node_count == 0 {
            return Err(corrupt(24, "no nodes".into()));
        }
        let texture_count = dataset.textures.len();
        let mut nodes = Vec::with_capacity(node_count);
        for i in 0..node_count {
            let at = HEADER_BYTES + i * NODE_BYTES;
            let f = |k: usize| f32_at(at + 4 * k);
            let node = TreeNode {
                bounds: Aabb {
                    min: [f(0), f(1), f(2)],
                    max: [f(3), f(4), f(5)],
                },
                min_distance: f(6),
                parent: u32_at(at + 28),
                first_child: u32_at(at + 32),
                child_count: u32_at(at + 36),
                atlas: u32_at(at + 40),
                uv_scale: f(11),
                uv_offset: [f(12), f(13)],
                first_mesh: u32_at(at + 56),
                mesh_count: u32_at(at + 60),
            };
            let bad = |what: String| corrupt(at, format!("node {i}: {what}"));
            let finite = [node.min_distance, node.uv_scale, node.uv_offset[0], node.uv_offset[1]]
                .iter()
                .chain(&node.bounds.min)
                .chain(&node.bounds.max)
                .all(|v| v.is_finite());
            if !finite || node.min_distance < 0.0 || node.uv_scale <= 0.0 {
                return Err(bad(
                    "a distance, bound or texture matrix is not finite (or negative)".into()
                ));
            }
            if (0..3).any(|a| node.bounds.min[a] > node.bounds.max[a]) {
                return Err(bad("bounds with min above max".into()));
            }
            if (i == 0) != (node.parent == NO_PARENT) {
                return Err(bad(format!("parent {} (only node 0, the root, has none)", node.parent)));
            }
            if i > 0 && node.parent as usize >= i {
                return Err(bad(format!("parent {} does not come before it", node.parent)));
            }
            if node.child_count > 4
                || (node.child_count > 0
                    && (node.first_child as usize <= i
                        || node.first_child as usize + node.child_count as usize > node_count))
            {
                return Err(bad(format!(
                    "children {}..{} are not 0 to 4 nodes after it",
                    node.first_child,
                    u64::from(node.first_child) + u64::from(node.child_count)
                )));
            }
            if node.atlas >= texture_count {
                return Err(bad(format!("atlas texture {} of {texture_count}", node.atlas)));
            }
            let meshes = u64::from(node.first_mesh)..u64::from(node.first_mesh) + u64::from(node.mesh_count);
            if (!node.is_leaf() && node.mesh_count > 0) || meshes.end > scene.meshes.len() as u64 {
                return Err(bad(format!(
                    "meshes {meshes:?} (inner nodes have none; the scene has {})",
                    scene.meshes.len()
                )));
            }
            if i > 0 {
                let parent = &nodes[node.parent as usize];
                let TreeNode {
                    first_child,
                    child_count,
                    ..
                } = *parent;
                if !(first_child..first_child + child_count).contains(&(i as u32)) {
                    return Err(bad(format!("parent {} does not list it as a child", node.parent)));
                }
            }
            nodes.push(node);
        }
        // Every listed child names this node as its parent: child ranges never overlap, so
        // the nodes form a tree (walks over it end, and visit each node once).
        for (i, node) in nodes.iter().enumerate() {
            if let Some(c) = node.children().find(|&c| nodes[c as usize].parent != i as u32) {
                return Err(corrupt(
                    HEADER_BYTES + c as usize * NODE_BYTES,
                    format!(
                        "node {c}: listed as a child of node {i}, but its parent is {}",
                        nodes[c as usize].parent
                    ),
                ));
            }
        }
        // Every mesh in exactly one leaf.
        let mut owner = vec![false; scene.meshes.len()];
        for (i, node) in nodes.iter().enumerate() {
            for m in node.first_mesh..node.first_mesh + node.mesh_count {
                if std::mem::replace(&mut owner[m as usize], true) {
                    return Err(corrupt(
                        HEADER_BYTES + i * NODE_BYTES,
                        format!("node {i}: mesh {m} belongs to another leaf too"),
                    ));
                }
            }
        }
        if let Some(m) = owner.iter().position(|o| !o) {
            return Err(corrupt(24, format!("mesh {m} belongs to no leaf")));
        }
        let uv_at = HEADER_BYTES + node_count * NODE_BYTES;
        let atlas_uvs: Vec<[f32; 2]> = (0..vertex_count)
            .map(|v| [f32_at(uv_at + v * 8), f32_at(uv_at + v * 8 + 4)])
            .collect();
        if let Some(v) = atlas_uvs.iter().position(|uv| !uv.iter().all(|c| c.is_finite())) {
            return Err(corrupt(
                uv_at + v * 8,
                format!("vertex {v}: atlas coordinates are not finite"),
            ));
        }
        Ok(Self {
            params,
            nodes,
            atlas_uvs,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let tree = row_tree();
        let mut planes = EVERYWHERE;
        planes[0] = [1.0, 0.0, 0.0, -150.0];
        let view = view([140.0, 15.0, 5.0], planes);
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
        let tree = row_tree();
        let mut planes = EVERYWHERE;
        planes[0] = [1.0, 0.0, 0.0, -150.0];
        let view = view([140.0, 15.0, 5.0], planes);
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
