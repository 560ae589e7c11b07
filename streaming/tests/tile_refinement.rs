//! Refinement by screen-space error on hand-made tile trees whose answers are known, and
//! over random flights with random loads and evictions: once the root has loaded every
//! frame draws every surface once, the resident tiles stay closed under parents (so no
//! resident tile waits on a missing ancestor), and nothing is requested before its parent.

use citystream_dataset::tiles::{Refine, TileRecord, TileTree};
use citystream_streaming::rng::SplitMix64;
use citystream_streaming::tile_refinement::{
    distance_to_bounds, evictable, select, RefineView, Selection, DEFAULT_MAX_ERROR_PX,
};

/// A tile of `side` metres square in x and z (0 to 50 m high) centred at `centre`, its
/// origin there (far from the frame's origin, as a tile of a country-sized city is).
fn tile(centre: [f64; 2], side: f32, error: f32, children: std::ops::Range<u32>, refine: Refine) -> TileRecord {
    let half = side / 2.0;
    TileRecord {
        origin: [1.0e6 + centre[0], 0.0, -1.0e6 + centre[1]],
        bounds_min: [-half, 0.0, -half],
        bounds_max: [half, 50.0, half],
        geometric_error: error,
        refine,
        first_child: children.start,
        child_count: children.end - children.start,
        geometry_offset: 0,
        geometry_len: 0,
        vertex_count: 0,
        index_count: 0,
        first_mesh: 0,
        mesh_count: 0,
        first_texture: 0,
        texture_count: 0,
    }
}

/// Quadrant centres of a square of `side` centred at `centre`: −x −z, +x −z, −x +z, +x +z.
fn quadrants(centre: [f64; 2], side: f64) -> [[f64; 2]; 4] {
    let q = side / 4.0;
    [[-q, -q], [q, -q], [-q, q], [q, q]].map(|[x, z]| [centre[0] + x, centre[1] + z])
}

/// A quadtree of 1,024 m: tile 0 the root (error 64 m), tiles 1-4 its quadrants (8 m),
/// tiles 5-20 theirs (leaves: tile k's children are 5 + 4 (k − 1) to 8 + 4 (k − 1)).
fn quadtree(root_refine: Refine) -> TileTree {
    let mut tiles = vec![tile([0.0, 0.0], 1024.0, 64.0, 1..5, root_refine)];
    let middles = quadrants([0.0, 0.0], 1024.0);
    for (k, centre) in middles.iter().enumerate() {
        let first = 5 + 4 * k as u32;
        tiles.push(tile(*centre, 512.0, 8.0, first..first + 4, Refine::Replace));
    }
    for centre in middles {
        for leaf in quadrants(centre, 512.0) {
            tiles.push(tile(leaf, 256.0, 0.0, 0..0, Refine::Replace));
        }
    }
    TileTree {
        write_id: 1,
        crs: None,
        origin: [1.0e6, 0.0, -1.0e6],
        roots: 0..1,
        tiles,
        mesh_ids: Vec::new(),
    }
}

/// A 60° view 1,080 pixels high from `eye` (relative to the quadtree's centre), threshold 16.
fn view(eye: [f64; 3]) -> RefineView {
    RefineView {
        eye: [1.0e6 + eye[0], eye[1], -1.0e6 + eye[2]],
        fov_y: 60f64.to_radians(),
        viewport_height: 1080,
        max_error_px: DEFAULT_MAX_ERROR_PX,
    }
}

#[test]
fn distances_and_errors_follow_the_formula_far_from_the_frames_origin() {
    let tree = quadtree(Refine::Replace);
    // 10 km above the centre: 9,950 m from the root's top; 64 × 1,080 / (2 × 9,950 × tan 30°).
    let far = view([0.0, 10_000.0, 0.0]);
    assert_eq!(distance_to_bounds(far.eye, &tree.tiles[0]), 9_950.0);
    let expected = 64.0 * 1080.0 / (2.0 * 9_950.0 * 30f64.to_radians().tan());
    assert!((far.screen_space_error(&tree.tiles[0]) - expected).abs() < 1e-9);
    // Inside a tile's bounds: refine as far as the tree goes; a leaf never asks for more.
    let inside = view([10.0, 20.0, 10.0]);
    assert_eq!(inside.screen_space_error(&tree.tiles[0]), f64::INFINITY);
    assert_eq!(inside.screen_space_error(&tree.tiles[5]), 0.0);
}

#[test]
fn refinement_picks_the_tiles_the_rule_says() {
    let tree = quadtree(Refine::Replace);
    let all = |_: u32| true;
    // 10 km up the root's error spans 6 pixels: the root alone.
    assert_eq!(select(&tree, &view([0.0, 10_000.0, 0.0]), all).draw, vec![0]);
    // 1 km up the root's spans 63 pixels, each quadrant's (950 m away) 7.9: the quadrants.
    assert_eq!(select(&tree, &view([0.0, 1_000.0, 0.0]), all).draw, vec![1, 2, 3, 4]);
    // 10 m over leaf 5 (quadrant 1's first): quadrant 1 spans 748 pixels, quadrants 2 and 3
    // (384 m away) 19.5, quadrant 4 (543 m) 13.8: the leaves of 1, 2 and 3, and 4 itself.
    let low = view([-384.0, 60.0, -384.0]);
    let expected: Vec<u32> = (5..17).chain([4]).collect();
    assert_eq!(
        select(&tree, &low, all),
        Selection {
            draw: expected,
            requests: Vec::new()
        }
    );
}

#[test]
fn a_parent_stands_in_until_all_its_children_are_resident() {
    let tree = quadtree(Refine::Replace);
    let low = view([-384.0, 60.0, -384.0]);
    // Quadrant 2's leaf 10 has not loaded: quadrant 2 is drawn and its missing leaf asked for.
    let selection = select(&tree, &low, |t| t != 10);
    assert_eq!(selection.draw, vec![5, 6, 7, 8, 2, 13, 14, 15, 16, 4]);
    assert_eq!(selection.requests, vec![10]);
    // Nothing loaded: the root is asked for and nothing is drawn.
    let selection = select(&tree, &low, |_| false);
    assert_eq!(
        selection,
        Selection {
            draw: Vec::new(),
            requests: vec![0]
        }
    );
    // Only the root: it is drawn, and its four quadrants asked for.
    let selection = select(&tree, &low, |t| t == 0);
    assert_eq!(
        selection,
        Selection {
            draw: vec![0],
            requests: vec![1, 2, 3, 4]
        }
    );
}

#[test]
fn a_tile_that_adds_is_drawn_beside_its_children() {
    let tree = quadtree(Refine::Add);
    let selection = select(&tree, &view([0.0, 1_000.0, 0.0]), |_| true);
    assert_eq!(selection.draw, vec![0, 1, 2, 3, 4]);
    // Its missing children are asked for; it and the resident ones are drawn.
    let selection = select(&tree, &view([0.0, 1_000.0, 0.0]), |t| t != 3);
    assert_eq!(
        selection,
        Selection {
            draw: vec![0, 1, 2, 4],
            requests: vec![3]
        }
    );
}

#[test]
fn eviction_takes_undrawn_tiles_without_resident_children_children_first() {
    let tree = quadtree(Refine::Replace);
    let resident = |t: u32| t <= 12;
    // Drawn: leaves 5-8 and quadrants 3 and 4 (the quadrants 1 and 2 have resident children).
    let drawn = [5, 6, 7, 8, 3, 4];
    assert_eq!(evictable(&tree, resident, &drawn), vec![12, 11, 10, 9]);
}

/// For a tree whose tiles all replace: whether every leaf has exactly one drawn tile among
/// itself and its ancestors (every surface drawn, none twice).
fn covers_once(tree: &TileTree, drawn: &[u32]) -> Result<(), String> {
    let mut parent = vec![None; tree.tiles.len()];
    for (t, tile) in tree.tiles.iter().enumerate() {
        for c in tile.first_child..tile.first_child + tile.child_count {
            parent[c as usize] = Some(t as u32);
        }
    }
    for (leaf, tile) in tree.tiles.iter().enumerate() {
        if tile.child_count > 0 {
            continue;
        }
        let mut count = 0;
        let mut at = Some(leaf as u32);
        while let Some(t) = at {
            count += drawn.iter().filter(|&&d| d == t).count();
            at = parent[t as usize];
        }
        if count != 1 {
            return Err(format!("leaf {leaf} is drawn {count} times (drawn: {drawn:?})"));
        }
    }
    Ok(())
}

#[test]
fn random_flights_with_random_loads_and_evictions_never_leave_a_hole() {
    let tree = quadtree(Refine::Replace);
    let mut frames_checked = 0;
    let mut tiles_evicted = 0;
    for seed in 0..20 {
        let mut rng = SplitMix64::new(seed);
        let mut resident = vec![false; tree.tiles.len()];
        let mut root_loaded = false;
        let parent_of = |t: usize| {
            tree.tiles
                .iter()
                .position(|p| (p.first_child..p.first_child + p.child_count).contains(&(t as u32)))
        };
        for frame in 0..300 {
            let eye = [
                rng.range(-700.0, 700.0),
                rng.range(55.0, 3_000.0),
                rng.range(-700.0, 700.0),
            ];
            let selection = select(&tree, &view(eye), |t| resident[t as usize]);
            for &t in &selection.requests {
                let parent_resident = parent_of(t as usize).is_none_or(|p| resident[p]);
                assert!(
                    parent_resident,
                    "seed {seed} frame {frame}: tile {t} requested before its parent"
                );
            }
            root_loaded |= resident[0];
            if root_loaded {
                covers_once(&tree, &selection.draw).unwrap_or_else(|e| panic!("seed {seed} frame {frame}: {e}"));
                frames_checked += 1;
            }
            // The loader finishes some requests, and memory pressure evicts some tiles.
            for &t in &selection.requests {
                if rng.next_f64() < 0.5 {
                    resident[t as usize] = true;
                }
            }
            for t in evictable(&tree, |t| resident[t as usize], &selection.draw) {
                if rng.next_f64() < 0.3 {
                    resident[t as usize] = false;
                    tiles_evicted += 1;
                }
            }
            for t in 0..tree.tiles.len() {
                let closed = !resident[t] || parent_of(t).is_none_or(|p| resident[p]);
                assert!(
                    closed,
                    "seed {seed} frame {frame}: tile {t} resident without its parent"
                );
            }
        }
    }
    // The check means something only with many frames and evictions.
    assert!(frames_checked > 5_000, "{frames_checked} frames checked");
    assert!(tiles_evicted > 1_000, "{tiles_evicted} tiles evicted");
}
