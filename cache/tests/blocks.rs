//! Block accounting: after a long random sequence of inserts, mip loads,
//! budget and ring evictions, the blocks bound (in the cache's accounting
//! and in a binder that rejects double binds) are exactly the blocks the
//! loaded mips of live textures touch. The same holds with mip tails (per
//! layer or single), checked by the bind checker as well.
#![allow(clippy::unwrap_used)]

mod common;

use std::collections::{BTreeSet, HashMap, HashSet};

use citystream_cache::{
    BindChecker, BindOp, BlockKey, CacheConfig, CacheError, DeviceLimits, Granularity, GranularityUnit, ImageConfig,
    ImageShape, MemorySlot, MipTail, Placement, SparseBinder, TexelFormat, TextureCache,
};
use common::{brute_force_blocks, model_origin, rgba_config, FakeBinder};
use proptest::prelude::*;

const BLOCK_BYTES: u64 = 4096;
const BUDGET_BLOCKS: u64 = 24;
const LAYER: u32 = 128;

/// Mip tails of the two images: none, one per layer, or one per image.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Tails {
    None,
    PerLayer,
    Single,
}

/// The tail of image `image` under `tails`: RGBA8 from level 2 (32², the
/// first level of one block) in one block, BC1 from level 1 in two.
fn tail_of(image: u32, tails: Tails) -> Option<MipTail> {
    let single = match tails {
        Tails::None => return None,
        Tails::PerLayer => false,
        Tails::Single => true,
    };
    Some(if image == 0 {
        MipTail {
            first_level: 2,
            blocks: 1,
            single,
        }
    } else {
        MipTail {
            first_level: 1,
            blocks: 2,
            single,
        }
    })
}

fn two_format_config() -> CacheConfig {
    config_with_tails(Tails::None)
}

fn config_with_tails(tails: Tails) -> CacheConfig {
    // 128x64 BC1 texels are 32x16 blocks of 8 bytes: one 4 KiB block.
    let bc1 = Granularity::from_device_report(&TexelFormat::BC1, 32, 16, GranularityUnit::TexelBlocks).unwrap();
    CacheConfig {
        images: vec![
            ImageConfig {
                format: TexelFormat::RGBA8,
                granularity: Granularity::texels(32, 32),
                layer_size: LAYER,
                layer_count: 8,
                mip_tail: tail_of(0, tails),
            },
            ImageConfig {
                format: TexelFormat::BC1,
                granularity: bc1,
                layer_size: LAYER,
                layer_count: 4,
                mip_tail: tail_of(1, tails),
            },
        ],
        limits: DeviceLimits {
            max_image_array_layers: 16,
            max_image_dimension_2d: 1024,
            sparse_block_bytes: BLOCK_BYTES,
        },
        memory_budget_bytes: BUDGET_BLOCKS * BLOCK_BYTES + 100,
        virtual_budget_bytes: 1 << 30,
        blocks_per_chunk: 8,
    }
}

fn granularity(image: u32) -> (u32, u32) {
    if image == 0 {
        (32, 32)
    } else {
        (128, 64)
    }
}

#[derive(Clone, Debug)]
enum Op {
    Insert { image: u32, log_w: u32, log_h: u32 },
    Stage { pick: usize, mip: u32 },
    Batch,
}

fn op() -> impl Strategy<Value = Op> {
    prop_oneof![
        3 => (0u32..2, 1u32..=6, 1u32..=6).prop_map(|(image, log_w, log_h)| Op::Insert { image, log_w, log_h }),
        6 => (any::<usize>(), 0u32..8).prop_map(|(pick, mip)| Op::Stage { pick, mip }),
        1 => Just(Op::Batch),
    ]
}

/// The blocks texture mip `mip` of `placement` lies on under `tails`.
fn blocks_of(placement: &Placement, mip: u32, tails: Tails) -> HashSet<BlockKey> {
    if let Some(tail) = tail_of(placement.image, tails).filter(|tail| mip >= tail.first_level) {
        if tail.single {
            return HashSet::new();
        }
        return (0..tail.blocks)
            .map(|index| BlockKey::tail(placement.image, placement.layer, index))
            .collect();
    }
    let origin = model_origin(LAYER, placement.extent, placement.region);
    brute_force_blocks(
        placement.image,
        placement.layer,
        origin,
        (placement.width, placement.height),
        mip,
        granularity(placement.image),
    )
}

struct Harness {
    cache: TextureCache,
    binder: FakeBinder,
    /// The bind checker sees every batch the binder does.
    checker: BindChecker,
    tails: Tails,
    /// Live textures with their loaded mips.
    live: Vec<(Placement, BTreeSet<u32>)>,
    /// Textures found evicted since the last batch, by key.
    dropped_since_batch: BTreeSet<u64>,
    chunks: HashMap<u32, u64>,
}

impl Harness {
    fn blocks_of(&self, placement: &Placement, mip: u32) -> HashSet<BlockKey> {
        blocks_of(placement, mip, self.tails)
    }

    fn expected_blocks(&self) -> HashSet<BlockKey> {
        let single_tails = (0..2).flat_map(|image| {
            tail_of(image, self.tails)
                .filter(|tail| tail.single)
                .into_iter()
                .flat_map(move |tail| (0..tail.blocks).map(move |index| BlockKey::tail(image, 0, index)))
        });
        self.live
            .iter()
            .flat_map(|(placement, mips)| mips.iter().flat_map(|&mip| self.blocks_of(placement, mip)))
            .chain(single_tails)
            .collect()
    }

    /// Drops textures the cache evicted, remembering them for the batch.
    fn prune(&mut self) {
        let cache = &self.cache;
        let dropped = &mut self.dropped_since_batch;
        self.live.retain(|(placement, _)| {
            let live = cache.is_live(placement);
            if !live {
                dropped.insert(placement.key);
            }
            live
        });
    }

    fn check_accounting(&self) -> Result<(), TestCaseError> {
        let accounted: HashSet<BlockKey> = self.cache.bound_blocks().into_iter().map(|(key, _)| key).collect();
        prop_assert_eq!(&accounted, &self.expected_blocks(), "cache accounting vs loaded mips");
        prop_assert!(accounted.len() as u64 <= BUDGET_BLOCKS);
        Ok(())
    }

    fn batch(&mut self) -> Result<(), TestCaseError> {
        let batch = self.cache.take_batch();
        let invalidated: BTreeSet<u64> = batch.invalidated.iter().map(|p| p.key).collect();
        prop_assert_eq!(invalidated.len(), batch.invalidated.len(), "texture reported twice");
        prop_assert_eq!(&invalidated, &self.dropped_since_batch, "invalidated vs evicted");
        self.dropped_since_batch.clear();
        for chunk in &batch.new_chunks {
            prop_assert!(
                self.chunks.insert(chunk.chunk, chunk.bytes).is_none(),
                "chunk created twice"
            );
            prop_assert_eq!(self.checker.add_chunk(chunk.bytes), chunk.chunk);
        }
        self.checker
            .check_batch(&batch.ops)
            .map_err(|violation| TestCaseError::fail(violation.to_string()))?;
        self.binder
            .submit(&batch.ops)
            .map_err(|error| TestCaseError::fail(error.to_string()))?;
        // Parked blocks stay bound until their memory is wanted.
        let live: HashMap<BlockKey, MemorySlot> = self.cache.bound_blocks().into_iter().collect();
        let parked: HashMap<BlockKey, MemorySlot> = self.cache.parked_blocks().into_iter().collect();
        prop_assert!(
            live.keys().all(|key| !parked.contains_key(key)),
            "a block both live and parked"
        );
        let mut accounted = live;
        accounted.extend(parked);
        prop_assert_eq!(&self.binder.bound, &accounted, "binder state vs cache accounting");
        let memory: HashSet<MemorySlot> = accounted.values().copied().collect();
        prop_assert_eq!(memory.len(), accounted.len(), "one memory slot bound twice");
        prop_assert!(accounted.len() as u64 <= BUDGET_BLOCKS, "held memory over the budget");
        for memory in self.binder.bound.values() {
            let bytes = self.chunks.get(&memory.chunk).copied();
            prop_assert!(
                bytes.is_some_and(|bytes| memory.offset < bytes),
                "{:?} outside its chunk",
                memory
            );
            prop_assert_eq!(memory.offset % BLOCK_BYTES, 0);
        }
        prop_assert!(self.chunks.len() as u64 <= BUDGET_BLOCKS.div_ceil(8));
        Ok(())
    }

    fn stage(&mut self, index: usize, mip: u32) -> Result<(), TestCaseError> {
        let placement = self.live[index].0;
        let mip = mip % placement.mip_count;
        let mut outcome = self.cache.stage_mip(&placement, mip);
        if let Err(CacheError::MemoryPending { .. }) = outcome {
            // Freed memory is reusable once its unbinds are handed out.
            self.prune();
            self.batch()?;
            outcome = self.cache.stage_mip(&placement, mip);
            let pending = matches!(outcome, Err(CacheError::MemoryPending { .. }));
            prop_assert!(!pending, "memory still pending after a batch");
        }
        match outcome {
            Ok(upload) => {
                let origin = model_origin(LAYER, placement.extent, placement.region);
                prop_assert_eq!(upload.rect.x, origin.0 >> mip);
                prop_assert_eq!(upload.rect.y, origin.1 >> mip);
                prop_assert_eq!((upload.layer, upload.rect.mip), (placement.layer, mip));
                let entry = self.live.iter_mut().find(|(live, _)| live.key == placement.key);
                prop_assert!(entry.is_some(), "staged a texture the cache evicted");
                if let Some((_, mips)) = entry {
                    prop_assert_eq!(upload.already_staged, mips.contains(&mip));
                    mips.insert(mip);
                }
            }
            Err(CacheError::Invalidated { key, .. }) => {
                prop_assert_eq!(key, placement.key);
                prop_assert!(!self.cache.is_live(&placement));
            }
            Err(CacheError::OverBudget { .. }) => {
                prop_assert!(self.blocks_of(&placement, mip).len() as u64 > BUDGET_BLOCKS);
            }
            Err(other) => return Err(TestCaseError::fail(format!("unexpected {other}"))),
        }
        self.prune();
        Ok(())
    }
}

/// The bind checker's view of the two images.
fn checker_for(config: &CacheConfig) -> BindChecker {
    let mut checker = BindChecker::new(BLOCK_BYTES);
    for image in &config.images {
        let levels = LAYER.trailing_zeros() + 1;
        let block_levels = image.mip_tail.map_or(levels, |tail| tail.first_level);
        let (gw, gh) = (image.granularity.width, image.granularity.height);
        checker.add_image(ImageShape {
            layers: image.layer_count,
            level_blocks: (0..block_levels)
                .map(|mip| {
                    let size = (LAYER >> mip).max(1);
                    (size.div_ceil(gw), size.div_ceil(gh))
                })
                .collect(),
            mip_tail: image.mip_tail,
        });
    }
    checker
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(32))]

    #[test]
    fn bound_blocks_equal_blocks_of_loaded_mips(ops in prop::collection::vec(op(), 200..600)) {
        run_ops(ops, Tails::None)?;
    }

    #[test]
    fn bound_blocks_equal_blocks_of_loaded_mips_with_per_layer_tails(ops in prop::collection::vec(op(), 200..600)) {
        run_ops(ops, Tails::PerLayer)?;
    }

    #[test]
    fn bound_blocks_equal_blocks_of_loaded_mips_with_single_tails(ops in prop::collection::vec(op(), 200..600)) {
        run_ops(ops, Tails::Single)?;
    }
}

fn run_ops(ops: Vec<Op>, tails: Tails) -> Result<(), TestCaseError> {
    let config = config_with_tails(tails);
    let mut harness = Harness {
        cache: TextureCache::new(&config).unwrap(),
        binder: FakeBinder::default(),
        checker: checker_for(&config),
        tails,
        live: Vec::new(),
        dropped_since_batch: BTreeSet::new(),
        chunks: HashMap::new(),
    };
    let mut next_key = 0u64;
    for op in ops {
        match op {
            Op::Insert { image, log_w, log_h } => {
                let (w, h) = if image == 1 {
                    (1 << log_w.max(2), 1 << log_h.max(2))
                } else {
                    (1 << log_w, 1 << log_h)
                };
                next_key += 1;
                let placement = harness.cache.insert(image, next_key, w, h).unwrap();
                harness.live.push((placement, BTreeSet::new()));
                harness.prune();
            }
            Op::Stage { pick, mip } => {
                if !harness.live.is_empty() {
                    let index = pick % harness.live.len();
                    harness.stage(index, mip)?;
                }
            }
            Op::Batch => harness.batch()?,
        }
        harness.check_accounting()?;
    }
    harness.batch()?;
    let utilisation = harness.cache.utilisation();
    prop_assert_eq!(
        utilisation.bound_blocks + utilisation.parked_blocks,
        harness.binder.bound.len() as u64
    );
    prop_assert_eq!(utilisation.bound_bytes, utilisation.bound_blocks * BLOCK_BYTES);
    prop_assert_eq!(
        utilisation.held_bytes(),
        harness.binder.bound.len() as u64 * BLOCK_BYTES
    );
    let tail_blocks = harness.binder.bound.keys().filter(|key| key.is_tail()).count() as u64;
    prop_assert_eq!(utilisation.tail_blocks, tail_blocks);
    prop_assert_eq!(
        harness.cache.tail_bytes_held().iter().sum::<u64>(),
        tail_blocks * BLOCK_BYTES
    );
    if tails == Tails::Single {
        prop_assert_eq!(tail_blocks, 3, "the single tails stay bound");
    }
    Ok(())
}

#[test]
fn a_block_is_bound_once_for_thousands_of_small_bc1_textures() {
    // Lavapipe's shape: 64 KiB blocks, BC1 granularity 128x64 blocks =
    // 512x256 texels. A 4x4 BC1 texture is 8 bytes: 8192 fill one block.
    let limits = DeviceLimits::lavapipe_reference();
    let bc1 = Granularity::from_device_report(&TexelFormat::BC1, 128, 64, GranularityUnit::TexelBlocks).unwrap();
    let config = CacheConfig {
        images: vec![ImageConfig {
            format: TexelFormat::BC1,
            granularity: bc1,
            layer_size: 512,
            layer_count: 2,
            mip_tail: None,
        }],
        limits,
        memory_budget_bytes: 16 * limits.sparse_block_bytes,
        virtual_budget_bytes: 1 << 30,
        blocks_per_chunk: 4,
    };
    let cache = TextureCache::new(&config).unwrap();
    let mut binder = FakeBinder::default();
    for key in 0..8192 {
        let placement = cache.insert(0, key, 4, 4).unwrap();
        let upload = cache.stage_mip(&placement, 0).unwrap();
        assert_eq!(upload.new_blocks, u32::from(key == 0));
    }
    let batch = cache.take_batch();
    assert_eq!(batch.ops.len(), 1);
    assert_eq!(batch.new_chunks.len(), 1);
    binder.submit(&batch.ops).unwrap();
    let utilisation = cache.utilisation();
    assert_eq!(utilisation.bound_bytes, limits.sparse_block_bytes);
    assert_eq!(
        utilisation.texture_bytes, limits.sparse_block_bytes,
        "the block is full"
    );

    // The 8193rd starts the block below.
    let next = cache.insert(0, 9000, 4, 4).unwrap();
    assert_eq!((next.origin_x, next.origin_y), (0, 256));
    assert_eq!(cache.stage_mip(&next, 0).unwrap().new_blocks, 1);
    let ops = cache.take_batch().ops;
    assert_eq!(ops.len(), 1);
    binder.submit(&ops).unwrap();
    assert_eq!(binder.bound.len(), 2);
}

#[test]
fn budget_eviction_takes_the_oldest_layer_and_reuses_its_memory() {
    // RGBA8 64² layers, 32² blocks: a 64x64 texture's mip 0 is 4 blocks,
    // the full chain 4+1+1+1+1+1+1 = 10. Budget: 12 blocks.
    let cache = TextureCache::new(&rgba_config(64, 4, 32, 12)).unwrap();
    let mut binder = FakeBinder::default();
    let first = cache.insert(0, 1, 64, 64).unwrap();
    for mip in 0..first.mip_count {
        cache.stage_mip(&first, mip).unwrap();
    }
    binder.submit(&cache.take_batch().ops).unwrap();
    assert_eq!(binder.bound.len(), 10);
    let first_memory: HashSet<MemorySlot> = binder.bound.values().copied().collect();

    let second = cache.insert(0, 2, 64, 64).unwrap();
    assert_eq!(second.layer, 1);
    // 10 + 4 > 12: layer 0 is evicted, but its memory waits for the unbinds.
    assert!(matches!(
        cache.stage_mip(&second, 0),
        Err(CacheError::MemoryPending {
            needed_blocks: 4,
            free_blocks: 2
        })
    ));
    assert!(!cache.is_live(&first));
    let batch = cache.take_batch();
    assert_eq!(batch.invalidated, vec![first]);
    assert_eq!(
        batch.evicted_layers[0].reason,
        citystream_cache::EvictionReason::MemoryBudget
    );
    // Only the two blocks staging lacked are unbound, those parked first
    // (level 0's, in key order); the other eight stay bound.
    let mut level_0 = cache.blocks_for_mip(&first, 0).unwrap();
    level_0.sort_unstable();
    let parked_first = &level_0[..2];
    let unbound: Vec<BlockKey> = batch
        .ops
        .iter()
        .map(|op| match op {
            BindOp::Unbind { block } => *block,
            BindOp::Bind { .. } => panic!("a bind in an unbind-only batch: {op:?}"),
        })
        .collect();
    assert_eq!(unbound, parked_first);
    let before_unbind = binder.bound.clone();
    binder.submit(&batch.ops).unwrap();
    assert_eq!(binder.bound.len(), 8);
    assert_eq!(cache.utilisation().parked_blocks, 8);

    cache.stage_mip(&second, 0).unwrap();
    let batch = cache.take_batch();
    assert!(batch.new_chunks.is_empty(), "freed slots are reused, no new chunk");
    binder.submit(&batch.ops).unwrap();
    assert_eq!(binder.bound.len(), 12, "4 live and 8 parked: the whole budget");
    assert_eq!(cache.budget_use().live_blocks, 4);
    let freed: Vec<MemorySlot> = parked_first.iter().map(|key| before_unbind[key]).collect();
    let second_memory: HashSet<MemorySlot> = cache.bound_blocks().into_iter().map(|(_, memory)| memory).collect();
    assert!(
        freed.iter().all(|memory| second_memory.contains(memory)),
        "the unbound slots back the new blocks"
    );
    assert_eq!(
        second_memory.difference(&first_memory).count(),
        2,
        "and two never used before"
    );
    // A mip larger than the whole budget is refused.
    let tiny_budget = TextureCache::new(&rgba_config(64, 2, 32, 2)).unwrap();
    let big = tiny_budget.insert(0, 3, 64, 64).unwrap();
    assert!(matches!(
        tiny_budget.stage_mip(&big, 0),
        Err(CacheError::OverBudget {
            needed_blocks: 4,
            budget_blocks: 2
        })
    ));
}

#[test]
fn evicted_blocks_needed_again_keep_their_memory() {
    // One layer: a ring reuse before the batch is taken re-needs the same
    // block; it must be neither unbound nor bound again.
    let cache = TextureCache::new(&rgba_config(64, 1, 64, 8)).unwrap();
    let mut binder = FakeBinder::default();
    let first = cache.insert(0, 1, 32, 32).unwrap();
    cache.stage_mip(&first, 0).unwrap();
    binder.submit(&cache.take_batch().ops).unwrap();
    let before = binder.bound.clone();
    let second = cache.insert(0, 2, 16, 16).unwrap();
    assert!(!cache.is_live(&first));
    assert_eq!(cache.stage_mip(&second, 0).unwrap().new_blocks, 1);
    let batch = cache.take_batch();
    assert!(batch.ops.is_empty(), "{:?}", batch.ops);
    assert_eq!(batch.invalidated, vec![first]);
    binder.submit(&batch.ops).unwrap();
    assert_eq!(binder.bound, before);
}

#[test]
fn concurrent_loaders_keep_the_accounting_exact() {
    // Four loader threads insert and stage every mip while ring reuse and
    // the budget evict layers under them.
    let cache = TextureCache::new(&two_format_config()).unwrap();
    let start = std::sync::Barrier::new(4);
    let staged: Vec<(Placement, Vec<u32>)> = std::thread::scope(|scope| {
        let handles: Vec<_> = (0..4u64)
            .map(|thread| {
                let cache = &cache;
                let start = &start;
                scope.spawn(move || {
                    let mut state = 0x2545_f491_4f6c_dd1d_u64 ^ (thread + 1);
                    let mut done = Vec::new();
                    start.wait();
                    for index in 0..300u64 {
                        state ^= state << 13;
                        state ^= state >> 7;
                        state ^= state << 17;
                        let image = (state % 2) as u32;
                        let w = 1u32 << (2 + (state >> 8) % 5);
                        let h = 1u32 << (2 + (state >> 16) % 5);
                        let placement = cache.insert(image, thread << 32 | index, w, h).unwrap();
                        let mut mips = Vec::new();
                        for mip in (0..placement.mip_count).rev() {
                            match cache.stage_mip(&placement, mip) {
                                Ok(_) => mips.push(mip),
                                Err(CacheError::Invalidated { .. }) => break,
                                Err(other) => panic!("unexpected {other}"),
                            }
                        }
                        done.push((placement, mips));
                    }
                    done
                })
            })
            .collect();
        handles.into_iter().flat_map(|handle| handle.join().unwrap()).collect()
    });
    let mut expected = HashSet::new();
    let mut live = 0;
    for (placement, mips) in &staged {
        if cache.is_live(placement) {
            live += 1;
            for &mip in mips {
                expected.extend(blocks_of(placement, mip, Tails::None));
            }
        }
    }
    assert!(live > 0);
    let stats = cache.stats();
    assert!(stats.ring_evictions > 0 && stats.budget_evictions > 0, "{stats:?}");
    let accounted: HashSet<BlockKey> = cache.bound_blocks().into_iter().map(|(key, _)| key).collect();
    assert_eq!(accounted, expected);
    let batch = cache.take_batch();
    assert_eq!(batch.invalidated.len() + live, staged.len());
    let mut binder = FakeBinder::default();
    binder.submit(&batch.ops).unwrap();
    let accounted: HashMap<BlockKey, MemorySlot> = cache.bound_blocks().into_iter().collect();
    assert_eq!(binder.bound, accounted);
}
