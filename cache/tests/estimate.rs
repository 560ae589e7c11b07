//! Utilisation: the offline estimate against the live cache and a
//! hand-computed case.
#![allow(clippy::unwrap_used)]

mod common;

use citystream_cache::{estimate_utilisation, CacheError, TextureCache};
use common::rgba_config;
use proptest::prelude::*;

#[test]
fn single_texture_by_hand() {
    // One 128² RGBA8 texture in a 256² layer with 128² blocks: mips 128..1
    // hold 4 * (128² + 64² + ... + 1) = 4 * 21845 bytes, one block per level.
    let cache = TextureCache::new(&rgba_config(256, 1, 128, 64)).unwrap();
    let image = cache.images()[0];
    let estimate = estimate_utilisation(&image, &[(128, 128)]).unwrap();
    assert_eq!(estimate.texture_bytes, 4 * 21845);
    assert_eq!(estimate.bound_blocks, 8);
    assert_eq!(estimate.bound_bytes, 8 * 128 * 128 * 4);
    assert_eq!(estimate.layers_used, 1);
    assert!((estimate.ratio() - 87380.0 / 524288.0).abs() < 1e-12);
}

#[test]
fn bad_extents_name_their_index() {
    let cache = TextureCache::new(&rgba_config(256, 1, 128, 64)).unwrap();
    let image = cache.images()[0];
    match estimate_utilisation(&image, &[(4, 4), (4, 12)]) {
        Err(CacheError::BadExtent { reason, .. }) => assert!(reason.contains("#1"), "{reason}"),
        other => panic!("expected BadExtent, got {other:?}"),
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(16))]

    /// The estimate equals what the cache reports after inserting the same
    /// textures in order and staging every cacheable mip.
    #[test]
    fn estimate_matches_the_live_cache(shapes in prop::collection::vec((0u32..=6, 0u32..=6), 1..200)) {
        let shapes: Vec<(u32, u32)> = shapes.into_iter().map(|(w, h)| (1 << w, 1 << h)).collect();
        let cache = TextureCache::new(&rgba_config(128, 256, 32, 1 << 20)).unwrap();
        let estimate = estimate_utilisation(&cache.images()[0], &shapes).unwrap();
        for (key, &(w, h)) in shapes.iter().enumerate() {
            let placement = cache.insert(0, key as u64, w, h).unwrap();
            for mip in 0..placement.mip_count {
                cache.stage_mip(&placement, mip).unwrap();
            }
        }
        let live = cache.utilisation();
        prop_assert_eq!(estimate.textures, live.live_textures);
        prop_assert_eq!(estimate.texture_bytes, live.texture_bytes);
        prop_assert_eq!(estimate.bound_blocks, live.bound_blocks);
        prop_assert_eq!(estimate.bound_bytes, live.bound_bytes);
        prop_assert_eq!(estimate.layers_used, cache.stats().layer_assignments);
        prop_assert!(live.texture_bytes <= live.bound_bytes);
    }
}
