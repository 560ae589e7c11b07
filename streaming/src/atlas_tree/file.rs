//! The tree's file (`atlas-tree.bin` in the dataset's write directory; layout in
//! `docs/ATLAS_TREE.md`): encoding, and decoding checked against the dataset.

use std::path::Path;

use super::{AtlasTree, TreeNode, TreeParams, NO_PARENT};
use citystream_dataset::{Aabb, Dataset, DatasetError};

/// The tree's file, in the dataset's write directory.
pub const TREE_FILE: &str = "atlas-tree.bin";
const MAGIC: &[u8; 8] = b"CSATTREE";
/// The tree file's format version.
pub const TREE_VERSION: u32 = 1;
const HEADER_BYTES: usize = 64;
const NODE_BYTES: usize = 64;

impl AtlasTree {
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
