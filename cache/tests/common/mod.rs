//! Shared helpers of the cache's integration tests: configurations, a
//! sequential reference model of the packing, and a fake binder.
#![allow(dead_code)]

use std::collections::{HashMap, HashSet};

use citystream_cache::{
    BindError, BindOp, BindReport, BlockKey, CacheConfig, DeviceLimits, Granularity, ImageConfig, MemorySlot,
    SparseBinder, TexelFormat,
};

/// An RGBA8-only configuration with small test blocks.
pub fn rgba_config(layer_size: u32, layer_count: u32, granularity: u32, budget_blocks: u64) -> CacheConfig {
    let block_bytes = u64::from(granularity) * u64::from(granularity) * 4;
    CacheConfig {
        images: vec![ImageConfig {
            format: TexelFormat::RGBA8,
            granularity: Granularity::texels(granularity, granularity),
            layer_size,
            layer_count,
            mip_tail: None,
        }],
        limits: DeviceLimits {
            max_image_array_layers: 2048,
            max_image_dimension_2d: 16384,
            sparse_block_bytes: block_bytes,
        },
        memory_budget_bytes: budget_blocks * block_bytes,
        virtual_budget_bytes: u64::MAX,
        blocks_per_chunk: 8,
    }
}

/// Sequential reference model of the paper's packing: per extent the open
/// (assignment, next region); assignments walk the layers in ring order and
/// reassigning a layer invalidates everything in it.
#[derive(Debug)]
pub struct PackingModel {
    pub layer_size: u32,
    pub layer_count: u32,
    pub next_assignment: u32,
    open: HashMap<u32, (u32, u64)>,
    /// Per layer: (assignment, extent, keys).
    owners: Vec<Option<(u32, u32, Vec<u64>)>>,
}

/// What the model says one insert does.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ModelInsert {
    pub layer: u32,
    pub region: u32,
    pub assignment: u32,
    pub invalidated: Vec<u64>,
}

impl PackingModel {
    pub fn new(layer_size: u32, layer_count: u32) -> Self {
        PackingModel {
            layer_size,
            layer_count,
            next_assignment: 0,
            open: HashMap::new(),
            owners: vec![None; layer_count as usize],
        }
    }

    pub fn capacity(&self, extent: u32) -> u64 {
        let per_row = u64::from(self.layer_size / extent);
        per_row * per_row
    }

    pub fn insert(&mut self, key: u64, width: u32, height: u32) -> ModelInsert {
        let extent = width.max(height);
        let capacity = self.capacity(extent);
        if let Some(&(assignment, next)) = self.open.get(&extent) {
            let layer = assignment % self.layer_count;
            let live = matches!(&self.owners[layer as usize], Some((owner, _, _)) if *owner == assignment);
            if live && next < capacity {
                self.open.insert(extent, (assignment, next + 1));
                if let Some((_, _, keys)) = &mut self.owners[layer as usize] {
                    keys.push(key);
                }
                return ModelInsert {
                    layer,
                    region: next as u32,
                    assignment,
                    invalidated: Vec::new(),
                };
            }
        }
        let assignment = self.next_assignment;
        self.next_assignment += 1;
        let layer = assignment % self.layer_count;
        let invalidated = self.owners[layer as usize]
            .take()
            .map(|(_, _, keys)| keys)
            .unwrap_or_default();
        self.owners[layer as usize] = Some((assignment, extent, vec![key]));
        self.open.insert(extent, (assignment, 1));
        ModelInsert {
            layer,
            region: 0,
            assignment,
            invalidated,
        }
    }
}

/// Texel origin of a region, derived independently of the cache.
pub fn model_origin(layer_size: u32, extent: u32, region: u32) -> (u32, u32) {
    let per_row = layer_size / extent;
    ((region % per_row) * extent, (region / per_row) * extent)
}

/// Every block a mip touches, by visiting each of its texels.
pub fn brute_force_blocks(
    image: u32,
    layer: u32,
    origin: (u32, u32),
    size: (u32, u32),
    mip: u32,
    granularity: (u32, u32),
) -> HashSet<BlockKey> {
    let x0 = origin.0 >> mip;
    let y0 = origin.1 >> mip;
    let width = (size.0 >> mip).max(1);
    let height = (size.1 >> mip).max(1);
    let mut blocks = HashSet::new();
    for y in y0..y0 + height {
        for x in x0..x0 + width {
            blocks.insert(BlockKey {
                image,
                layer,
                mip,
                x: x / granularity.0,
                y: y / granularity.1,
            });
        }
    }
    blocks
}

/// A binder that tracks residency and rejects binding a bound block,
/// unbinding an unbound one, or backing two blocks with one memory slot.
#[derive(Debug, Default)]
pub struct FakeBinder {
    pub bound: HashMap<BlockKey, MemorySlot>,
    pub batches: u32,
}

impl SparseBinder for FakeBinder {
    fn submit(&mut self, batch: &[BindOp]) -> Result<BindReport, BindError> {
        let mut seen = HashSet::new();
        for op in batch {
            if !seen.insert(op.block()) {
                return Err(BindError::Rejected {
                    blocks: batch.len() as u32,
                    reason: format!("block {:?} appears twice in one batch", op.block()),
                });
            }
            match *op {
                BindOp::Bind { block, memory } => {
                    if self.bound.insert(block, memory).is_some() {
                        return Err(BindError::Rejected {
                            blocks: batch.len() as u32,
                            reason: format!("double bind of {block:?}"),
                        });
                    }
                }
                BindOp::Unbind { block } => {
                    if self.bound.remove(&block).is_none() {
                        return Err(BindError::Rejected {
                            blocks: batch.len() as u32,
                            reason: format!("unbind of unbound {block:?}"),
                        });
                    }
                }
            }
        }
        let slots: HashSet<MemorySlot> = self.bound.values().copied().collect();
        if slots.len() != self.bound.len() {
            return Err(BindError::Rejected {
                blocks: batch.len() as u32,
                reason: "one memory slot backs two blocks".into(),
            });
        }
        self.batches += 1;
        Ok(BindReport {
            blocks: batch.len() as u32,
            entries: batch.len() as u32,
            seconds: 0.0,
        })
    }
}
