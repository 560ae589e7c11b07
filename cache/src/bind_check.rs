//! A CPU shadow of every sparse image's page table and of the block pool's
//! memory, to check each bind batch and each copy before it reaches the
//! driver. The validation layer checks little of sparse binding, so an
//! engine that binds a block twice, unbinds one that is not bound, points a
//! bind outside its memory or frees memory that blocks still use can pass
//! every test and crash a driver; [`BindChecker`] turns each of those into
//! a [`BindViolation`] naming the image, layer, level and block.
//!
//! The shadow follows submission order: a batch is checked against the
//! state every earlier batch left and, when it passes, applied. The GPU runs
//! batches in that order too (each waits for the one before).

use std::collections::HashMap;

use crate::binder::{BindOp, BlockKey, MemorySlot};
use crate::config::MipTail;

/// The block grid of one sparse image: its layers and, per level, how many
/// blocks wide and high the level is.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ImageShape {
    /// Array layers.
    pub layers: u32,
    /// Per mip level above the tail, (columns, rows) of sparse blocks.
    pub level_blocks: Vec<(u32, u32)>,
    /// The mip tail: its levels are bound only as a whole, through the
    /// tail's blocks ([`BlockKey::tail`]).
    pub mip_tail: Option<MipTail>,
}

/// Something the engine was about to ask of the driver that is not legal or
/// not what its own accounting says.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum BindViolation {
    /// A bind of a block that is bound already (no unbind in between).
    #[error(
        "{} is bound to chunk {} offset {} already and was bound again (chunk {} offset {}) without an unbind",
        describe(block), held.chunk, held.offset, memory.chunk, memory.offset
    )]
    DoubleBind {
        block: BlockKey,
        held: MemorySlot,
        memory: MemorySlot,
    },
    /// An unbind of a block that is not bound.
    #[error("{} was unbound but is not bound", describe(block))]
    UnbindUnbound { block: BlockKey },
    /// A block outside its image's layers, levels or block grid.
    #[error("{} lies outside its image ({reason})", describe(block))]
    OutsideImage { block: BlockKey, reason: String },
    /// Memory that is not a block-aligned block inside a live chunk.
    #[error("{} was bound to chunk {} offset {}: {reason}", describe(block), memory.chunk, memory.offset)]
    BadMemory {
        block: BlockKey,
        memory: MemorySlot,
        reason: String,
    },
    /// Memory that backs another block already.
    #[error(
        "{} was bound to chunk {} offset {}, which backs {} already",
        describe(block), memory.chunk, memory.offset, describe(other)
    )]
    SharedMemory {
        block: BlockKey,
        other: BlockKey,
        memory: MemorySlot,
    },
    /// Memory freed while a block is still bound to it.
    #[error(
        "chunk {chunk} was freed while {} is still bound to it (offset {offset})",
        describe(block)
    )]
    FreedWhileBound { chunk: u32, offset: u64, block: BlockKey },
    /// A copy into a block that is not bound.
    #[error("a copy writes {}, which is not bound", describe(block))]
    CopyIntoUnbound { block: BlockKey },
    /// A per-block bind or unbind of a level that lies in the mip tail.
    #[error(
        "{} lies in the mip tail (levels from {first_level} on), which is bound as a whole, not per block",
        describe(block)
    )]
    BlockInTail { block: BlockKey, first_level: u32 },
    /// A tail block bound again without an unbind.
    #[error(
        "the mip tail of image {} layer {} (its block {}) is bound already and was bound again",
        block.image, block.layer, block.x
    )]
    TailBoundTwice { block: BlockKey },
    /// A copy into a tail level whose tail is not (wholly) bound.
    #[error(
        "a copy writes image {image} layer {layer} level {level}, in the mip tail, whose block {index} is not bound"
    )]
    CopyIntoUnboundTail {
        image: u32,
        layer: u32,
        level: u32,
        index: u32,
    },
}

fn describe(block: &BlockKey) -> String {
    if block.is_tail() {
        return format!("image {} layer {} mip tail block {}", block.image, block.layer, block.x);
    }
    format!(
        "image {} layer {} level {} block ({}, {})",
        block.image, block.layer, block.mip, block.x, block.y
    )
}

/// The shadow page tables and memory; see the module docs.
#[derive(Debug, Default)]
pub struct BindChecker {
    block_bytes: u64,
    images: Vec<ImageShape>,
    /// Per chunk its size in bytes; `None` once freed.
    chunks: Vec<Option<u64>>,
    bound: HashMap<BlockKey, MemorySlot>,
    owners: HashMap<MemorySlot, BlockKey>,
    /// Batches and block operations checked so far.
    batches: u64,
    operations: u64,
}

impl BindChecker {
    /// A checker for blocks of `block_bytes` bytes, with no images or chunks yet.
    pub fn new(block_bytes: u64) -> Self {
        Self {
            block_bytes: block_bytes.max(1),
            ..Self::default()
        }
    }

    /// Registers the next image (`BlockKey::image` indexes them in order).
    pub fn add_image(&mut self, shape: ImageShape) -> u32 {
        self.images.push(shape);
        (self.images.len() - 1) as u32
    }

    /// Registers the next memory chunk of `bytes` (`MemorySlot::chunk`).
    pub fn add_chunk(&mut self, bytes: u64) -> u32 {
        self.chunks.push(Some(bytes));
        (self.chunks.len() - 1) as u32
    }

    /// Blocks bound now.
    pub fn bound_blocks(&self) -> usize {
        self.bound.len()
    }

    /// Batches and block operations checked so far.
    pub fn checked(&self) -> (u64, u64) {
        (self.batches, self.operations)
    }

    /// Checks `batch` in order against the shadow and applies it. On a
    /// violation the shadow is left as it was before the batch.
    pub fn check_batch(&mut self, batch: &[BindOp]) -> Result<(), BindViolation> {
        let mut undo: Vec<(BlockKey, Option<MemorySlot>)> = Vec::with_capacity(batch.len());
        for op in batch {
            if let Err(violation) = self.apply(op, &mut undo) {
                for (block, before) in undo.into_iter().rev() {
                    self.restore(block, before);
                }
                return Err(violation);
            }
        }
        self.batches += 1;
        self.operations += batch.len() as u64;
        Ok(())
    }

    fn apply(&mut self, op: &BindOp, undo: &mut Vec<(BlockKey, Option<MemorySlot>)>) -> Result<(), BindViolation> {
        let block = op.block();
        self.check_inside(block)?;
        let held = self.bound.get(&block).copied();
        match *op {
            BindOp::Bind { memory, .. } => {
                if let Some(held) = held {
                    if block.is_tail() {
                        return Err(BindViolation::TailBoundTwice { block });
                    }
                    return Err(BindViolation::DoubleBind { block, held, memory });
                }
                self.check_memory(block, memory)?;
                if let Some(&other) = self.owners.get(&memory) {
                    return Err(BindViolation::SharedMemory { block, other, memory });
                }
                self.bound.insert(block, memory);
                self.owners.insert(memory, block);
            }
            BindOp::Unbind { .. } => {
                let Some(held) = held else {
                    return Err(BindViolation::UnbindUnbound { block });
                };
                self.bound.remove(&block);
                self.owners.remove(&held);
            }
        }
        undo.push((block, held));
        Ok(())
    }

    /// Puts `block` back to `before` (bound to that memory, or unbound).
    fn restore(&mut self, block: BlockKey, before: Option<MemorySlot>) {
        if let Some(now) = self.bound.remove(&block) {
            self.owners.remove(&now);
        }
        if let Some(memory) = before {
            self.bound.insert(block, memory);
            self.owners.insert(memory, block);
        }
    }

    fn check_inside(&self, block: BlockKey) -> Result<(), BindViolation> {
        let outside = |reason: String| Err(BindViolation::OutsideImage { block, reason });
        let Some(shape) = self.images.get(block.image as usize) else {
            return outside(format!("{} images are known", self.images.len()));
        };
        if block.layer >= shape.layers {
            return outside(format!("{} layers", shape.layers));
        }
        if block.is_tail() {
            let Some(tail) = shape.mip_tail else {
                return outside("the image has no mip tail".into());
            };
            if tail.single && block.layer != 0 {
                return outside("its single mip tail is bound as layer 0".into());
            }
            if block.x >= tail.blocks || block.y != 0 {
                return outside(format!("the tail is {} blocks", tail.blocks));
            }
            return Ok(());
        }
        if let Some(tail) = shape.mip_tail.filter(|tail| block.mip >= tail.first_level) {
            return Err(BindViolation::BlockInTail {
                block,
                first_level: tail.first_level,
            });
        }
        let Some(&(columns, rows)) = shape.level_blocks.get(block.mip as usize) else {
            return outside(format!("{} levels", shape.level_blocks.len()));
        };
        if block.x >= columns || block.y >= rows {
            return outside(format!("the level is {columns} x {rows} blocks"));
        }
        Ok(())
    }

    fn check_memory(&self, block: BlockKey, memory: MemorySlot) -> Result<(), BindViolation> {
        let bad = |reason: String| Err(BindViolation::BadMemory { block, memory, reason });
        match self.chunks.get(memory.chunk as usize) {
            None => bad(format!("{} chunks exist", self.chunks.len())),
            Some(None) => bad("the chunk was freed".into()),
            Some(Some(bytes)) if !memory.offset.is_multiple_of(self.block_bytes) => bad(format!(
                "not a multiple of the {}-byte block (chunk of {bytes} bytes)",
                self.block_bytes
            )),
            Some(Some(bytes))
                if memory
                    .offset
                    .checked_add(self.block_bytes)
                    .is_none_or(|end| end > *bytes) =>
            {
                bad(format!("the block would end past the chunk's {bytes} bytes"))
            }
            Some(Some(_)) => Ok(()),
        }
    }

    /// Frees `chunk`: refused while any block is bound to its memory.
    pub fn free_chunk(&mut self, chunk: u32) -> Result<(), BindViolation> {
        let still_bound = self
            .owners
            .iter()
            .filter(|(memory, _)| memory.chunk == chunk)
            .min_by_key(|(memory, _)| memory.offset);
        if let Some((memory, &block)) = still_bound {
            return Err(BindViolation::FreedWhileBound {
                chunk,
                offset: memory.offset,
                block,
            });
        }
        if let Some(slot) = self.chunks.get_mut(chunk as usize) {
            *slot = None;
        }
        Ok(())
    }

    /// Checks that every block of `image`'s `layer` and `level` in columns
    /// `columns` and rows `rows` (block coordinates) is bound, before a copy
    /// writes them.
    pub fn check_copy(
        &self,
        image: u32,
        layer: u32,
        level: u32,
        columns: std::ops::Range<u32>,
        rows: std::ops::Range<u32>,
    ) -> Result<(), BindViolation> {
        let shape = self.images.get(image as usize);
        if let Some(tail) = shape.and_then(|s| s.mip_tail).filter(|tail| level >= tail.first_level) {
            let tail_layer = if tail.single { 0 } else { layer };
            if layer >= shape.map_or(0, |s| s.layers) {
                return self.check_inside(BlockKey::tail(image, layer, 0));
            }
            for index in 0..tail.blocks {
                if !self.bound.contains_key(&BlockKey::tail(image, tail_layer, index)) {
                    return Err(BindViolation::CopyIntoUnboundTail {
                        image,
                        layer,
                        level,
                        index,
                    });
                }
            }
            return Ok(());
        }
        for y in rows {
            for x in columns.clone() {
                let block = BlockKey {
                    image,
                    layer,
                    mip: level,
                    x,
                    y,
                };
                self.check_inside(block)?;
                if !self.bound.contains_key(&block) {
                    return Err(BindViolation::CopyIntoUnbound { block });
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const BLOCK: u64 = 65536;

    /// One image of 2 layers, levels of 4x4, 2x2 and 1x1 blocks; one chunk of 4 blocks.
    fn checker() -> BindChecker {
        let mut checker = BindChecker::new(BLOCK);
        checker.add_image(ImageShape {
            layers: 2,
            level_blocks: vec![(4, 4), (2, 2), (1, 1)],
            mip_tail: None,
        });
        checker.add_chunk(4 * BLOCK);
        checker
    }

    fn block(layer: u32, mip: u32, x: u32, y: u32) -> BlockKey {
        BlockKey {
            image: 0,
            layer,
            mip,
            x,
            y,
        }
    }

    fn bind(block: BlockKey, slot: u64) -> BindOp {
        BindOp::Bind {
            block,
            memory: MemorySlot {
                chunk: 0,
                offset: slot * BLOCK,
            },
        }
    }

    #[test]
    fn binds_unbinds_and_rebinds_in_order_pass() {
        let mut checker = checker();
        let a = block(1, 0, 3, 3);
        checker
            .check_batch(&[bind(a, 0), bind(block(0, 2, 0, 0), 1)])
            .expect("fresh binds");
        // Unbind, then bind the freed memory elsewhere, in one batch.
        checker
            .check_batch(&[BindOp::Unbind { block: a }, bind(block(0, 1, 1, 1), 0)])
            .expect("memory reused after its unbind");
        assert_eq!(checker.bound_blocks(), 2);
        assert_eq!(checker.checked(), (2, 4));
    }

    #[test]
    fn a_double_bind_is_caught_and_named_and_leaves_the_shadow_unchanged() {
        let mut checker = checker();
        let a = block(1, 0, 2, 1);
        checker.check_batch(&[bind(a, 0)]).expect("first bind");
        let error = checker
            .check_batch(&[bind(block(0, 0, 0, 0), 1), bind(a, 2)])
            .expect_err("a bound block bound again");
        assert!(matches!(error, BindViolation::DoubleBind { .. }), "{error}");
        assert!(
            error.to_string().contains("image 0 layer 1 level 0 block (2, 1)"),
            "{error}"
        );
        // The batch's first bind was rolled back with it.
        assert_eq!(checker.bound_blocks(), 1);
        checker
            .check_batch(&[bind(block(0, 0, 0, 0), 1)])
            .expect("slot 1 is still free");
    }

    #[test]
    fn an_unbind_of_an_unbound_block_is_caught() {
        let mut checker = checker();
        let error = checker
            .check_batch(&[BindOp::Unbind {
                block: block(0, 1, 0, 1),
            }])
            .expect_err("nothing bound");
        assert_eq!(
            error,
            BindViolation::UnbindUnbound {
                block: block(0, 1, 0, 1)
            }
        );
    }

    #[test]
    fn freeing_memory_a_block_is_bound_to_is_caught() {
        let mut checker = checker();
        checker.check_batch(&[bind(block(0, 0, 1, 0), 3)]).expect("bind");
        let error = checker.free_chunk(0).expect_err("a block still uses the chunk");
        assert_eq!(
            error,
            BindViolation::FreedWhileBound {
                chunk: 0,
                offset: 3 * BLOCK,
                block: block(0, 0, 1, 0)
            }
        );
        checker
            .check_batch(&[BindOp::Unbind {
                block: block(0, 0, 1, 0),
            }])
            .expect("unbind");
        checker.free_chunk(0).expect("nothing bound any more");
        let error = checker
            .check_batch(&[bind(block(0, 0, 0, 0), 0)])
            .expect_err("freed chunk");
        assert!(matches!(error, BindViolation::BadMemory { .. }), "{error}");
    }

    #[test]
    fn memory_outside_its_chunk_misaligned_or_shared_is_caught() {
        let mut checker = checker();
        let at = |chunk, offset| BindOp::Bind {
            block: block(0, 0, 0, 0),
            memory: MemorySlot { chunk, offset },
        };
        let bad_memory = [at(0, 4 * BLOCK), at(0, BLOCK / 2), at(1, 0), at(0, u64::MAX - 3)];
        let refused: Vec<_> = bad_memory.iter().map(|op| checker.check_batch(&[*op])).collect();
        assert!(
            refused
                .iter()
                .all(|r| matches!(r, Err(BindViolation::BadMemory { .. }))),
            "{refused:?}"
        );
        checker.check_batch(&[bind(block(0, 0, 0, 0), 2)]).expect("bind");
        let shared = checker.check_batch(&[bind(block(1, 0, 0, 0), 2)]);
        assert!(matches!(shared, Err(BindViolation::SharedMemory { .. })), "{shared:?}");
    }

    #[test]
    fn blocks_outside_the_image_are_caught() {
        let mut checker = checker();
        for outside in [
            block(2, 0, 0, 0),
            block(0, 3, 0, 0),
            block(0, 1, 2, 0),
            block(0, 0, 0, 4),
        ]
        .map(|outside| checker.check_batch(&[bind(outside, 0)]))
        {
            assert!(
                matches!(outside, Err(BindViolation::OutsideImage { .. })),
                "{outside:?}"
            );
        }
        let other_image = BlockKey {
            image: 1,
            ..block(0, 0, 0, 0)
        };
        assert!(checker.check_batch(&[bind(other_image, 0)]).is_err());
    }

    #[test]
    fn a_copy_into_a_block_that_is_not_bound_is_caught() {
        let mut checker = checker();
        checker
            .check_batch(&[bind(block(0, 0, 0, 0), 0), bind(block(0, 0, 1, 0), 1)])
            .expect("binds");
        checker.check_copy(0, 0, 0, 0..2, 0..1).expect("both bound");
        let error = checker.check_copy(0, 0, 0, 0..2, 0..2).expect_err("row 1 is not bound");
        assert_eq!(
            error,
            BindViolation::CopyIntoUnbound {
                block: block(0, 0, 0, 1)
            }
        );
    }

    /// One image of 3 layers: levels 0 and 1 in blocks (2x2, 1x1), levels
    /// from 2 on in a tail of two blocks, per layer or single.
    fn tail_checker(single: bool) -> BindChecker {
        let mut checker = BindChecker::new(BLOCK);
        checker.add_image(ImageShape {
            layers: 3,
            level_blocks: vec![(2, 2), (1, 1)],
            mip_tail: Some(MipTail {
                first_level: 2,
                blocks: 2,
                single,
            }),
        });
        checker.add_chunk(8 * BLOCK);
        checker
    }

    #[test]
    fn a_per_block_bind_into_a_tail_level_is_refused_naming_it() {
        let mut checker = tail_checker(false);
        for level in [2, 5] {
            let error = checker
                .check_batch(&[bind(block(1, level, 0, 0), 0)])
                .expect_err("tail levels are not bound per block");
            assert_eq!(
                error,
                BindViolation::BlockInTail {
                    block: block(1, level, 0, 0),
                    first_level: 2
                }
            );
            assert!(
                error
                    .to_string()
                    .contains(&format!("image 0 layer 1 level {level} block (0, 0)")),
                "{error}"
            );
            let unbind = checker.check_batch(&[BindOp::Unbind {
                block: block(1, level, 0, 0),
            }]);
            assert!(matches!(unbind, Err(BindViolation::BlockInTail { .. })), "{unbind:?}");
        }
        // Levels above the tail still bind per block.
        checker
            .check_batch(&[bind(block(1, 1, 0, 0), 0)])
            .expect("level 1 is a block");
        assert_eq!(checker.bound_blocks(), 1);
    }

    #[test]
    fn a_tail_bound_twice_is_refused_and_unbinding_it_allows_a_rebind() {
        let mut checker = tail_checker(false);
        let tail = |layer, index| BlockKey::tail(0, layer, index);
        checker
            .check_batch(&[bind(tail(2, 0), 0), bind(tail(2, 1), 1)])
            .expect("layer 2's tail");
        let error = checker
            .check_batch(&[bind(tail(2, 1), 2)])
            .expect_err("the tail is bound already");
        assert_eq!(error, BindViolation::TailBoundTwice { block: tail(2, 1) });
        assert!(error.to_string().contains("mip tail of image 0 layer 2"), "{error}");
        // Another layer's tail is its own.
        checker.check_batch(&[bind(tail(0, 0), 2)]).expect("layer 0's tail");
        checker
            .check_batch(&[BindOp::Unbind { block: tail(2, 1) }, bind(tail(2, 1), 3)])
            .expect("rebound after its unbind");
        // Blocks past the tail, or a tail of a layer that does not exist.
        for outside in [tail(0, 2), tail(3, 0), BlockKey { y: 1, ..tail(0, 1) }] {
            let refused = checker.check_batch(&[bind(outside, 4)]);
            assert!(
                matches!(refused, Err(BindViolation::OutsideImage { .. })),
                "{refused:?}"
            );
        }
    }

    #[test]
    fn a_copy_into_a_tail_level_needs_the_whole_tail_bound() {
        let mut checker = tail_checker(false);
        checker
            .check_batch(&[bind(BlockKey::tail(0, 1, 0), 0)])
            .expect("half the tail");
        let error = checker.check_copy(0, 1, 3, 0..1, 0..1).expect_err("block 1 unbound");
        assert_eq!(
            error,
            BindViolation::CopyIntoUnboundTail {
                image: 0,
                layer: 1,
                level: 3,
                index: 1
            }
        );
        assert!(error.to_string().contains("image 0 layer 1 level 3"), "{error}");
        checker
            .check_batch(&[bind(BlockKey::tail(0, 1, 1), 1)])
            .expect("the rest of it");
        checker.check_copy(0, 1, 3, 0..1, 0..1).expect("bound");
        assert!(
            checker.check_copy(0, 0, 2, 0..1, 0..1).is_err(),
            "layer 0's tail is not bound"
        );
    }

    #[test]
    fn a_single_tail_is_bound_once_as_layer_0_and_serves_every_layer() {
        let mut checker = tail_checker(true);
        let refused = checker.check_batch(&[bind(BlockKey::tail(0, 1, 0), 0)]);
        assert!(
            matches!(refused, Err(BindViolation::OutsideImage { .. })),
            "{refused:?}"
        );
        checker
            .check_batch(&[bind(BlockKey::tail(0, 0, 0), 0), bind(BlockKey::tail(0, 0, 1), 1)])
            .expect("the single tail");
        for layer in 0..3 {
            checker
                .check_copy(0, layer, 2, 0..1, 0..1)
                .expect("every layer's tail levels");
        }
        let twice = checker.check_batch(&[bind(BlockKey::tail(0, 0, 0), 2)]);
        assert!(matches!(twice, Err(BindViolation::TailBoundTwice { .. })), "{twice:?}");
    }
}
