//! Packing: concurrent insertion against a sequential reference model, ring
//! eviction, region geometry and UV transforms.
#![allow(clippy::unwrap_used)]

mod common;

use std::collections::{BTreeMap, HashMap};

use citystream_cache::{CacheError, EvictionReason, Placement, TexelFormat, TexelRect, TextureCache};
use common::{model_origin, rgba_config, PackingModel};
use proptest::prelude::*;

/// Extent shapes: (log2 width, log2 height), both sides 1..=64 texels.
fn shape() -> impl Strategy<Value = (u32, u32)> {
    (0u32..=6, 0u32..=6).prop_map(|(w, h)| (1 << w, 1 << h))
}

fn level0(placement: &Placement) -> TexelRect {
    TexelRect {
        mip: 0,
        x: placement.origin_x,
        y: placement.origin_y,
        width: placement.width,
        height: placement.height,
    }
}

/// No two textures of a layer share a texel, every region lies inside the
/// layer and every layer holds one extent only.
fn check_layout(placements: &[Placement], layer_size: u32) {
    let mut by_layer: HashMap<u32, Vec<&Placement>> = HashMap::new();
    for placement in placements {
        assert!(
            placement.origin_x + placement.extent <= layer_size,
            "{placement:?} outside layer"
        );
        assert!(
            placement.origin_y + placement.extent <= layer_size,
            "{placement:?} outside layer"
        );
        assert_eq!(placement.origin_x % placement.extent, 0);
        assert_eq!(placement.origin_y % placement.extent, 0);
        by_layer.entry(placement.layer).or_default().push(placement);
    }
    for (layer, members) in by_layer {
        let extent = members[0].extent;
        for (index, a) in members.iter().enumerate() {
            assert_eq!(a.extent, extent, "layer {layer} mixes extents");
            for b in &members[index + 1..] {
                assert!(!level0(a).overlaps(&level0(b)), "{a:?} overlaps {b:?}");
                assert_ne!(a.region, b.region);
            }
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// Many threads insert a random mix of extents at once. The layout is
    /// valid and, per extent, the layers used and the regions filled in each
    /// are exactly what sequential insertion of the same textures gives.
    #[test]
    fn concurrent_insertion_agrees_with_sequential_model(
        shapes in prop::collection::vec(shape(), 50..400),
        threads in 2usize..6,
    ) {
        let layer_size = 128;
        let layer_count = 128;
        // Layers are plentiful: no ring reuse, so the outcome is determined.
        let mut model = PackingModel::new(layer_size, layer_count);
        let mut model_regions: BTreeMap<u32, Vec<(u32, u32)>> = BTreeMap::new();
        let mut model_layers: BTreeMap<u32, Vec<u32>> = BTreeMap::new();
        for (key, &(w, h)) in shapes.iter().enumerate() {
            let step = model.insert(key as u64, w, h);
            let extent = w.max(h);
            let layers = model_layers.entry(extent).or_default();
            if !layers.contains(&step.assignment) {
                layers.push(step.assignment);
            }
            let rank = layers.iter().position(|&a| a == step.assignment).unwrap() as u32;
            model_regions.entry(extent).or_default().push((rank, step.region));
        }
        // At most 400 textures need at most 100 layers of extent 64.
        prop_assert!(model.next_assignment <= layer_count);

        let cache = TextureCache::new(&rgba_config(layer_size, layer_count, 16, 1 << 20)).unwrap();
        let chunk = shapes.len().div_ceil(threads);
        // Start all threads together so their inserts interleave.
        let start = std::sync::Barrier::new(shapes.chunks(chunk).len());
        let placements: Vec<Placement> = std::thread::scope(|scope| {
            let handles: Vec<_> = shapes
                .chunks(chunk)
                .enumerate()
                .map(|(part, slice)| {
                    let cache = &cache;
                    let start = &start;
                    scope.spawn(move || {
                        start.wait();
                        slice
                            .iter()
                            .enumerate()
                            .map(|(i, &(w, h))| cache.insert(0, (part * chunk + i) as u64, w, h).unwrap())
                            .collect::<Vec<_>>()
                    })
                })
                .collect();
            handles.into_iter().flat_map(|handle| handle.join().unwrap()).collect()
        });

        prop_assert_eq!(placements.len(), shapes.len());
        check_layout(&placements, layer_size);
        for placement in &placements {
            let (w, h) = shapes[placement.key as usize];
            prop_assert_eq!((placement.width, placement.height), (w, h));
            prop_assert!(cache.is_live(placement));
        }
        let batch = cache.take_batch();
        prop_assert!(batch.invalidated.is_empty());
        prop_assert_eq!(cache.stats().layer_assignments, u64::from(model.next_assignment));

        // Per extent: (rank of the layer among the extent's layers, region).
        let mut assignments: BTreeMap<u32, Vec<u32>> = BTreeMap::new();
        for placement in &placements {
            assignments.entry(placement.extent).or_default().push(placement.assignment);
        }
        let mut got: BTreeMap<u32, Vec<(u32, u32)>> = BTreeMap::new();
        for placement in &placements {
            let mut order = assignments[&placement.extent].clone();
            order.sort_unstable();
            order.dedup();
            let rank = order.iter().position(|&a| a == placement.assignment).unwrap() as u32;
            got.entry(placement.extent).or_default().push((rank, placement.region));
        }
        for regions in got.values_mut().chain(model_regions.values_mut()) {
            regions.sort_unstable();
        }
        prop_assert_eq!(got, model_regions);
    }

    /// Sequential insertion with ring reuse matches the model exactly:
    /// layer, region and the textures each insert invalidates.
    #[test]
    fn sequential_insertion_with_ring_reuse_matches_model(
        shapes in prop::collection::vec(shape(), 1..300),
        layer_count in 1u32..5,
    ) {
        let layer_size = 32;
        let shapes: Vec<(u32, u32)> = shapes.into_iter().map(|(w, h)| (w.min(32), h.min(32))).collect();
        let mut model = PackingModel::new(layer_size, layer_count);
        let cache = TextureCache::new(&rgba_config(layer_size, layer_count, 16, 1 << 20)).unwrap();
        let mut live: HashMap<u64, Placement> = HashMap::new();
        for (key, &(w, h)) in shapes.iter().enumerate() {
            let key = key as u64;
            let expected = model.insert(key, w, h);
            let placement = cache.insert(0, key, w, h).unwrap();
            prop_assert_eq!((placement.layer, placement.region), (expected.layer, expected.region));
            let (x, y) = model_origin(layer_size, w.max(h), expected.region);
            prop_assert_eq!((placement.origin_x, placement.origin_y), (x, y));
            let batch = cache.take_batch();
            let mut invalidated: Vec<u64> = batch.invalidated.iter().map(|p| p.key).collect();
            invalidated.sort_unstable();
            let mut expected_invalidated = expected.invalidated.clone();
            expected_invalidated.sort_unstable();
            prop_assert_eq!(&invalidated, &expected_invalidated);
            for gone in &invalidated {
                let old = live.remove(gone).unwrap();
                prop_assert!(!cache.is_live(&old));
            }
            live.insert(key, placement);
            for placement in live.values() {
                prop_assert!(cache.is_live(placement));
            }
        }
        let live: Vec<Placement> = live.into_values().collect();
        check_layout(&live, layer_size);
    }
}

#[test]
fn inserting_past_capacity_evicts_exactly_the_oldest_layer() {
    // 64² layers, 3 of them: 16 textures of extent 16 fill layer 0, 4 of
    // extent 32 fill layer 1, 2 of extent 8 start layer 2.
    let cache = TextureCache::new(&rgba_config(64, 3, 16, 1 << 20)).unwrap();
    let mut key = 0u64;
    let mut insert = |w: u32, h: u32| {
        key += 1;
        cache.insert(0, key, w, h).unwrap()
    };
    let sixteens: Vec<Placement> = (0..16).map(|i| insert(16, if i % 2 == 0 { 16 } else { 4 })).collect();
    let thirty_twos: Vec<Placement> = (0..4).map(|_| insert(8, 32)).collect();
    let eights: Vec<Placement> = (0..2).map(|_| insert(8, 8)).collect();
    assert!(sixteens.iter().all(|p| p.layer == 0));
    assert!(thirty_twos.iter().all(|p| p.layer == 1));
    assert!(eights.iter().all(|p| p.layer == 2));
    assert!(cache.take_batch().invalidated.is_empty());

    // Extent 16 is full and every layer is assigned: layer 0 is reused.
    let newcomer = insert(16, 16);
    assert_eq!((newcomer.layer, newcomer.region), (0, 0));
    let batch = cache.take_batch();
    assert_eq!(
        batch.invalidated, sixteens,
        "exactly layer 0's textures, in region order"
    );
    assert_eq!(batch.evicted_layers.len(), 1);
    assert_eq!(batch.evicted_layers[0].layer, 0);
    assert_eq!(batch.evicted_layers[0].extent, 16);
    assert_eq!(batch.evicted_layers[0].reason, EvictionReason::RingReuse);
    assert_eq!(batch.evicted_layers[0].textures, 16);
    assert!(sixteens.iter().all(|p| !cache.is_live(p)));
    assert!(thirty_twos.iter().chain(&eights).all(|p| cache.is_live(p)));
    assert!(cache.is_live(&newcomer));
    for old in &sixteens {
        assert!(matches!(cache.stage_mip(old, 0), Err(CacheError::Invalidated { .. })));
    }

    // Extent 8 still fills layer 2; a new extent takes layer 1, the oldest.
    let more_eights: Vec<Placement> = (0..3).map(|_| insert(8, 8)).collect();
    assert!(more_eights.iter().all(|p| p.layer == 2));
    assert_eq!(more_eights.iter().map(|p| p.region).collect::<Vec<_>>(), vec![2, 3, 4]);
    assert!(cache.take_batch().invalidated.is_empty());
    let sixty_four = insert(64, 64);
    assert_eq!(sixty_four.layer, 1);
    let batch = cache.take_batch();
    assert_eq!(batch.invalidated, thirty_twos);
    assert!(eights
        .iter()
        .chain(&more_eights)
        .chain([&newcomer])
        .all(|p| cache.is_live(p)));
    assert_eq!(cache.stats().ring_evictions, 2);
    assert_eq!(cache.stats().invalidated_textures, 20);
}

#[test]
fn uv_transform_maps_every_mip_onto_its_rectangle() {
    let cache = TextureCache::new(&rgba_config(256, 4, 16, 1 << 20)).unwrap();
    let mut placements = Vec::new();
    for (key, &(w, h)) in [(4, 32), (32, 4), (32, 32), (16, 32), (32, 8)]
        .iter()
        .cycle()
        .take(40)
        .enumerate()
    {
        placements.push(cache.insert(0, key as u64, w, h).unwrap());
    }
    for placement in &placements {
        assert_eq!(placement.mip_count, placement.width.min(placement.height).ilog2() + 1);
        for mip in 0..placement.mip_count {
            let rect = placement.mip_rect(mip).unwrap();
            let level = (256u32 >> mip) as f32;
            let corner0 = placement.uv.apply([0.0, 0.0]);
            let corner1 = placement.uv.apply([1.0, 1.0]);
            assert_eq!(corner0[0] * level, rect.x as f32);
            assert_eq!(corner0[1] * level, rect.y as f32);
            assert_eq!(corner1[0] * level, (rect.x + rect.width) as f32);
            assert_eq!(corner1[1] * level, (rect.y + rect.height) as f32);
            assert_eq!(rect.width, placement.width >> mip);
            assert_eq!(rect.height, placement.height >> mip);
        }
        assert!(matches!(
            placement.mip_rect(placement.mip_count),
            Err(CacheError::BadMip { .. })
        ));
    }
}

#[test]
fn bad_extents_are_errors() {
    let cache = TextureCache::new(&rgba_config(64, 2, 16, 1 << 20)).unwrap();
    assert!(matches!(
        cache.insert(0, 1, 48, 16),
        Err(CacheError::BadExtent { width: 48, .. })
    ));
    assert!(matches!(cache.insert(0, 1, 0, 16), Err(CacheError::BadExtent { .. })));
    assert!(matches!(
        cache.insert(0, 1, 128, 16),
        Err(CacheError::BadExtent { width: 128, .. })
    ));
    assert!(matches!(
        cache.insert(3, 1, 16, 16),
        Err(CacheError::UnknownImage { image: 3, .. })
    ));
}

#[test]
fn block_compressed_mips_stop_at_one_texel_block() {
    let mut config = rgba_config(256, 2, 16, 1 << 20);
    config.images[0].format = TexelFormat::BC1;
    config.images[0].granularity = citystream_cache::Granularity::texels(64, 32);
    let cache = TextureCache::new(&config).unwrap();
    let square = cache.insert(0, 1, 32, 32).unwrap();
    assert_eq!(square.mip_count, 4, "32, 16, 8, 4");
    let thin = cache.insert(0, 2, 4, 32).unwrap();
    assert_eq!(thin.mip_count, 1);
    assert!(matches!(cache.insert(0, 3, 2, 32), Err(CacheError::BadExtent { .. })));
    // Every BC mip rectangle is whole 4x4 blocks.
    for mip in 0..square.mip_count {
        let rect = square.mip_rect(mip).unwrap();
        assert_eq!(rect.x % 4 + rect.y % 4 + rect.width % 4 + rect.height % 4, 0);
    }
}
