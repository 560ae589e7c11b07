//! Mip tails: a per-layer tail is bound when a texture of the layer first
//! needs one of its levels, shared by every texture of the layer, released
//! with its last user, parked and taken back like a block; a single tail is
//! bound once, from the budget, for good; tails the cache cannot serve are
//! refused at configuration.
#![allow(clippy::unwrap_used)]

mod common;

use citystream_cache::{BindOp, BlockKey, CacheConfig, ConfigError, MipTail, TextureCache};
use common::rgba_config;

/// 64² RGBA8 layers in 16² blocks (levels 64, 32, 16 in blocks), the tail
/// from level 2 in `blocks` blocks.
fn tailed(layers: u32, budget_blocks: u64, blocks: u32, single: bool) -> CacheConfig {
    tailed_from(2, layers, budget_blocks, blocks, single)
}

/// [`tailed`] with the tail from `first_level` on.
fn tailed_from(first_level: u32, layers: u32, budget_blocks: u64, blocks: u32, single: bool) -> CacheConfig {
    let mut config = rgba_config(64, layers, 16, budget_blocks);
    config.images[0].mip_tail = Some(MipTail {
        first_level,
        blocks,
        single,
    });
    config
}

fn tail_ops(ops: &[BindOp]) -> Vec<BindOp> {
    ops.iter().copied().filter(|op| op.block().is_tail()).collect()
}

#[test]
fn a_layer_tail_is_bound_once_for_all_its_textures_and_released_with_the_last() {
    let cache = TextureCache::new(&tailed(2, 64, 2, false)).unwrap();
    let a = cache.insert(0, 1, 16, 16).unwrap();
    let b = cache.insert(0, 2, 16, 16).unwrap();
    assert_eq!(a.layer, b.layer);
    // Level 0 of a 16² texture is one block; level 2 (4²) lies in the tail.
    assert_eq!(cache.stage_mip(&a, 0).unwrap().new_blocks, 1);
    let first = cache.stage_mip(&a, 2).unwrap();
    assert_eq!(first.new_blocks, 2, "the whole tail is bound");
    assert_eq!(first.rect.mip, 2);
    assert_eq!(cache.stage_mip(&a, 3).unwrap().new_blocks, 0, "level 3 shares it");
    assert_eq!(cache.stage_mip(&b, 4).unwrap().new_blocks, 0, "so does b's level 4");
    let batch = cache.take_batch();
    let tails = tail_ops(&batch.ops);
    assert_eq!(tails.len(), 2);
    assert!(tails.iter().all(|op| matches!(op, BindOp::Bind { block, .. }
        if *block == BlockKey::tail(0, a.layer, block.x))));
    assert_eq!(cache.utilisation().tail_blocks, 2);
    assert_eq!(cache.budget_use().live_blocks, 3);

    // Still used by a's level 3 and b's level 4.
    assert_eq!(cache.drop_mip(&a, 2).unwrap(), 0);
    assert_eq!(cache.exclusive_blocks(&a, 3), 0);
    assert_eq!(cache.drop_mip(&a, 3).unwrap(), 0);
    assert_eq!(cache.exclusive_blocks(&b, 4), 2);
    assert_eq!(cache.drop_mip(&b, 4).unwrap(), 2, "its last user frees the tail");
    assert_eq!(cache.budget_use().live_blocks, 1);
    // Parked, not unbound: taken back without a bind by the next tail user.
    assert_eq!(cache.utilisation().tail_blocks, 2);
    assert_eq!(cache.stage_mip(&b, 2).unwrap().new_blocks, 2);
    assert!(tail_ops(&cache.take_batch().ops).is_empty(), "reclaimed, no bind");
}

#[test]
fn an_evicted_layer_parks_its_tail_and_the_memory_goes_where_it_is_wanted() {
    // Budget of 3 blocks: one layer's tail (2) and one block.
    let cache = TextureCache::new(&tailed(4, 3, 2, false)).unwrap();
    let a = cache.insert(0, 1, 64, 64).unwrap();
    cache.stage_mip(&a, 2).unwrap();
    cache.take_batch();
    let b = cache.insert(0, 2, 64, 64).unwrap();
    // b's tail needs 2 more blocks: the budget evicts a's layer, whose tail
    // parks; one block of memory is free, so the next batch unbinds one of
    // the parked tail's blocks, the other stays parked.
    let staged = cache.stage_mip(&b, 2);
    assert!(
        staged.is_err(),
        "memory of the parked tail waits for the unbind: {staged:?}"
    );
    assert!(!cache.is_live(&a));
    let batch = cache.take_batch();
    let unbinds: Vec<_> = batch
        .ops
        .iter()
        .filter(|op| matches!(op, BindOp::Unbind { .. }))
        .collect();
    assert_eq!(unbinds.len(), 1);
    assert!(unbinds
        .iter()
        .all(|op| op.block().is_tail() && op.block().layer == a.layer));
    assert_eq!(cache.stage_mip(&b, 2).unwrap().new_blocks, 2);
    let binds = tail_ops(&cache.take_batch().ops);
    assert!(binds.iter().all(|op| op.block().layer == b.layer), "{binds:?}");
    let utilisation = cache.utilisation();
    assert_eq!((utilisation.bound_blocks, utilisation.parked_blocks), (2, 1));
    assert_eq!(utilisation.tail_blocks, 3);
    assert_eq!(utilisation.held_bytes(), 3 * 16 * 16 * 4);
}

#[test]
fn a_single_tail_is_bound_with_the_first_batch_from_the_budget_and_never_released() {
    let cache = TextureCache::new(&tailed(2, 8, 3, true)).unwrap();
    // Taken from the budget at creation: the planner sees 5 blocks of 8.
    assert_eq!(
        (cache.budget_use().live_blocks, cache.budget_use().budget_blocks),
        (0, 5)
    );
    let first = cache.take_batch();
    assert_eq!(first.ops.len(), 3);
    assert!(first
        .ops
        .iter()
        .all(|op| matches!(op, BindOp::Bind { block, .. } if block.is_tail() && block.layer == 0)));
    let a = cache.insert(0, 1, 64, 64).unwrap();
    assert_eq!(
        cache.stage_mip(&a, 2).unwrap().new_blocks,
        0,
        "the single tail is bound"
    );
    assert_eq!(cache.stage_mip(&a, 6).unwrap().new_blocks, 0);
    // Budget: 8 blocks - 3 of tail leave 5; level 0 of 64² is 16 blocks.
    assert!(cache.stage_mip(&a, 0).is_err());
    cache.evict_layer(0, a.layer).unwrap();
    assert!(
        tail_ops(&cache.take_batch().ops).is_empty(),
        "evicting a layer keeps the single tail"
    );
    assert_eq!(cache.utilisation().tail_blocks, 3);
    assert_eq!(cache.tail_bytes_held(), vec![3 * 16 * 16 * 4]);
    assert_eq!(cache.bound_blocks().len(), 3);
}

#[test]
fn tails_the_cache_cannot_serve_are_refused_naming_the_format() {
    let from_zero = tailed_from(0, 2, 64, 1, false);
    let error = TextureCache::new(&from_zero).unwrap_err();
    assert!(matches!(error, ConfigError::UnservedMipTail { .. }), "{error}");
    assert!(
        error.to_string().contains("RGBA8") && error.to_string().contains("level 0"),
        "{error}"
    );

    let error = TextureCache::new(&tailed(2, 4, 4, true)).unwrap_err();
    assert!(matches!(error, ConfigError::TailsOverBudget { .. }), "{error}");

    // A tail below the last level is no tail.
    let past_the_end = tailed_from(7, 2, 64, 1, false);
    let cache = TextureCache::new(&past_the_end).unwrap();
    assert_eq!(cache.images()[0].mip_tail, None);
}

#[test]
fn the_virtual_size_counts_each_layer_tail_and_a_single_tail_once() {
    let per_layer = TextureCache::new(&tailed(4, 64, 2, false)).unwrap().images()[0];
    // Levels 0..2 in blocks: 16 + 4 = 20, and the tail's 2.
    assert_eq!(per_layer.blocks_per_layer, 22);
    assert_eq!(per_layer.virtual_bytes(), 4 * 22 * 1024);
    let single = TextureCache::new(&tailed(4, 64, 2, true)).unwrap().images()[0];
    assert_eq!(single.blocks_per_layer, 20);
    assert_eq!(single.virtual_bytes(), (4 * 20 + 2) * 1024);
}
