//! Paging (§6): every block's usage, distance and level, the ideal block set within a
//! capacity, and the loader records that ask for it.

use super::{atlas_level_for, distance_to, intersects_frustum, AtlasTree, TreeView, NO_PARENT};
use crate::records::{MeshMetaData, DEFAULT_WEIGHT_CUTOFF};
use citystream_dataset::Scene;

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

impl AtlasTree {
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
}
