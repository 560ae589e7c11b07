//! The mechanisms view-serving eviction is built on: staging that refuses
//! instead of evicting, dropping one texture's level while its neighbours
//! keep the blocks they share, and layers freed only when the caller says.
#![allow(clippy::unwrap_used)]

mod common;

use citystream_cache::{BindOp, CacheError, EvictionReason, TextureCache};
use common::rgba_config;

#[test]
fn dropping_a_level_frees_only_blocks_no_other_texture_uses() {
    // 64-texel layers, 16-texel blocks: four 16² textures of one row share
    // level 1 blocks (8² each, all in one 16² block of level 1).
    let cache = TextureCache::new(&rgba_config(64, 2, 16, 64)).unwrap();
    let a = cache.try_insert(0, 1, 16, 16).unwrap();
    let b = cache.try_insert(0, 2, 16, 16).unwrap();
    assert_eq!((a.layer, b.layer), (0, 0));
    for placement in [&a, &b] {
        cache.try_stage_mip(placement, 1).unwrap();
        cache.try_stage_mip(placement, 0).unwrap();
    }
    // Level 0: one block each; level 1: one block shared.
    assert_eq!(cache.budget_use().live_blocks, 3);
    assert_eq!(cache.exclusive_blocks(&a, 0), 1);
    assert_eq!(cache.exclusive_blocks(&a, 1), 0);
    let batch = cache.take_batch();
    assert_eq!(batch.ops.len(), 3);

    assert_eq!(cache.drop_mip(&a, 0).unwrap(), 1);
    assert_eq!(cache.drop_mip(&a, 1).unwrap(), 0, "b still samples the shared block");
    assert!(matches!(
        cache.drop_mip(&a, 1),
        Err(CacheError::NotStaged { key: 1, mip: 1 })
    ));
    assert_eq!(cache.exclusive_blocks(&b, 1), 1, "b is now the block's only user");
    assert_eq!(cache.drop_mip(&b, 1).unwrap(), 1);
    // The budget has room: the freed blocks stay bound (parked) and no
    // unbind is handed out.
    assert!(cache.take_batch().ops.is_empty());
    assert_eq!(cache.budget_use().live_blocks, 1);
    assert_eq!(cache.utilisation().parked_blocks, 2);
    assert!(
        cache.is_live(&a) && cache.is_live(&b),
        "dropping levels keeps the places"
    );
    assert_eq!(cache.stats().dropped_mips, 3);
}

#[test]
fn a_level_dropped_and_staged_again_before_the_batch_keeps_its_memory() {
    let cache = TextureCache::new(&rgba_config(64, 1, 16, 8)).unwrap();
    let a = cache.try_insert(0, 1, 32, 32).unwrap();
    cache.try_stage_mip(&a, 0).unwrap();
    cache.take_batch();
    cache.drop_mip(&a, 0).unwrap();
    let upload = cache.try_stage_mip(&a, 0).unwrap();
    assert_eq!(upload.new_blocks, 4);
    assert!(cache.take_batch().ops.is_empty(), "no unbind and no rebind");
}

#[test]
fn staging_without_room_changes_nothing() {
    let cache = TextureCache::new(&rgba_config(64, 2, 16, 3)).unwrap();
    let a = cache.try_insert(0, 1, 32, 32).unwrap();
    let before = cache.budget_use();
    match cache.try_stage_mip(&a, 0) {
        Err(CacheError::NoRoom {
            needed_blocks: 4,
            free_blocks: 3,
        }) => {}
        other => panic!("expected NoRoom, got {other:?}"),
    }
    assert_eq!(cache.budget_use(), before);
    assert!(cache.take_batch().is_empty());
    assert_eq!(cache.stats().budget_evictions, 0);
}

#[test]
fn layers_are_freed_only_when_the_caller_chooses() {
    // Two layers of 64 texels: one 64² texture per layer.
    let cache = TextureCache::new(&rgba_config(64, 2, 16, 64)).unwrap();
    let a = cache.try_insert(0, 1, 64, 64).unwrap();
    let b = cache.try_insert(0, 2, 64, 64).unwrap();
    cache.try_stage_mip(&b, 2).unwrap();
    assert!(matches!(
        cache.try_insert(0, 3, 64, 64),
        Err(CacheError::NoLayer { image: 0, extent: 64 })
    ));
    assert!(cache.is_live(&a) && cache.is_live(&b));
    // Evict the newer layer: the ring would have taken the older one.
    cache.evict_layer(0, b.layer).unwrap();
    assert!(cache.is_live(&a) && !cache.is_live(&b));
    let c = cache.try_insert(0, 3, 64, 64).unwrap();
    assert_eq!(c.layer, b.layer);
    assert_ne!(c.assignment, b.assignment, "a reused layer gets a new assignment");
    assert!(cache.is_live(&c) && !cache.is_live(&b));
    let batch = cache.take_batch();
    assert_eq!(batch.invalidated.len(), 1);
    assert_eq!(batch.invalidated[0].key, 2);
    assert_eq!(batch.evicted_layers[0].reason, EvictionReason::Chosen);
    assert!(matches!(
        cache.evict_layer(0, 7),
        Err(CacheError::LayerNotLive { image: 0, layer: 7 })
    ));
}

#[test]
fn an_evicted_layer_costs_no_unbind_until_its_memory_is_wanted() {
    // 64² RGBA8 layers, 16² blocks: a 64² texture's chain is 16+4+1+1+1+1+1
    // = 25 blocks. Two layers, budget 30 blocks.
    let cache = TextureCache::new(&rgba_config(64, 2, 16, 30)).unwrap();
    let a = cache.try_insert(0, 1, 64, 64).unwrap();
    for mip in (0..a.mip_count).rev() {
        cache.try_stage_mip(&a, mip).unwrap();
    }
    let binds = cache.take_batch().ops.len();
    assert_eq!(binds, 25);
    let c = cache.try_insert(0, 3, 64, 64).unwrap();
    assert_ne!(c.layer, a.layer);
    cache.evict_layer(0, a.layer).unwrap();
    let batch = cache.take_batch();
    assert_eq!(batch.invalidated.len(), 1);
    assert!(batch.ops.is_empty(), "eviction alone unbinds nothing: {:?}", batch.ops);
    assert_eq!(cache.utilisation().parked_blocks, 25);

    // A texture placed in the same layer takes the parked blocks back: its
    // coarse levels need no bind.
    let b = cache.try_insert(0, 2, 64, 64).unwrap();
    assert_eq!(b.layer, a.layer, "the free layer is reused");
    for mip in (2..b.mip_count).rev() {
        assert_eq!(cache.try_stage_mip(&b, mip).unwrap().new_blocks, 1);
    }
    assert!(cache.take_batch().ops.is_empty(), "no unbind and no rebind");
    assert_eq!(cache.utilisation().parked_blocks, 20);

    // The texture in the other layer wants 16 blocks for its level 0: 5 are
    // free, so 11 parked blocks are unbound (the oldest parked first) and
    // the level waits one batch for their memory.
    assert!(matches!(
        cache.try_stage_mip(&c, 0),
        Err(CacheError::MemoryPending {
            needed_blocks: 16,
            free_blocks: 5
        })
    ));
    let unbinds = cache.take_batch().ops;
    assert_eq!(unbinds.len(), 11);
    assert!(unbinds
        .iter()
        .all(|op| matches!(op, BindOp::Unbind { block } if block.layer == a.layer && block.mip == 0)));
    assert_eq!(cache.try_stage_mip(&c, 0).unwrap().new_blocks, 16);
    let batch = cache.take_batch();
    assert_eq!(batch.ops.len(), 16);
    assert!(batch.ops.iter().all(|op| matches!(op, BindOp::Bind { .. })));
    assert_eq!(cache.utilisation().parked_blocks, 9);
    assert_eq!(
        cache.utilisation().held_bytes(),
        30 * 16 * 16 * 4,
        "the whole budget, never more"
    );
}
