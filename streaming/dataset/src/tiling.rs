//! Leaf tiles of dataset format 4 (docs/DATASET.md; the reasons in docs/FORMAT4.md, agreed
//! point 1), computed from a scene: the first step of every writer and of `upgrade`.
//!
//! Meshes are grouped by the centre of their bounds on a horizontal grid of
//! [`TILE_SIDE_M`] (x and z; y is up), in absolute coordinates (the scene's origin plus the
//! mesh's position), so tiles of shards built apart line up. A cell holding more than
//! [`MAX_LEAF_TRIANGLES`] splits into its four quadrants, and so on, until each is under
//! that or [`MIN_LEAF_SIDE_M`] across.
//!
//! Each tile's origin is the scene's origin plus an offset: on each axis
//! the centre of its vertices' box rounded to whole metres, or 0 where that centre lies
//! within the box's extent (plus a metre) of the scene's origin. Positions relative to
//! it are then `f32` finer than 0.03 mm anywhere in a 256 m tile, however far from the
//! scene's origin the tile lies, and re-expressing is exact: an `f32` position `p` in the
//! scene's frame moves by a whole number of metres to `q`, no larger than `p` (so no
//! coarser an `f32`), and back to the very same `p` (for positions under 2²⁴ m from the
//! scene's origin, where `f32` steps are at most a metre). A scene written, read and written
//! again (a merge of shards) is written identically.

use std::collections::BTreeMap;

use super::scene::Scene;

/// Side of a leaf tile of the generated presets, metres: a power of two, so the inner
/// tiles above are a quadtree (512 m, 1 km, …).
pub const TILE_SIDE_M: f64 = 256.0;
/// A leaf with more triangles than this splits into quadrants.
pub const MAX_LEAF_TRIANGLES: u64 = 65_536;
/// A leaf this narrow splits no further, whatever it holds.
pub const MIN_LEAF_SIDE_M: f64 = 32.0;

/// A leaf tile: where it lies on the grid, its origin and its meshes.
#[derive(Clone, Debug, PartialEq)]
pub struct LeafTile {
    /// The tile's side, metres: [`TILE_SIDE_M`] halved once per split.
    pub side_m: f64,
    /// Its lower corner on the grid, in whole sides: x and z of the corner are
    /// `cell × side_m`, in absolute coordinates.
    pub cell: [i64; 2],
    /// Absolute position of its origin: the scene's origin plus a whole number of metres on
    /// each axis (the module's docs say which).
    pub origin: [f64; 3],
    /// Its meshes, as ids of the scene it was computed from, ascending.
    pub meshes: Vec<u32>,
    /// Triangles of those meshes.
    pub triangles: u64,
}

/// A mesh's absolute bounds centre and triangle count, or `None` for a mesh with no
/// vertices or bounds that are not finite (it joins the tile of the scene's origin).
fn placed(scene: &Scene, mesh: u32) -> Option<([f64; 3], [f64; 3], [f64; 3])> {
    let m = scene.meshes.get(mesh as usize)?;
    if m.vertex_count == 0 || !m.bounds.is_valid() {
        return None;
    }
    let low: [f64; 3] = std::array::from_fn(|a| scene.origin[a] + f64::from(m.bounds.min[a]));
    let high: [f64; 3] = std::array::from_fn(|a| scene.origin[a] + f64::from(m.bounds.max[a]));
    let centre = std::array::from_fn(|a| 0.5 * (low[a] + high[a]));
    Some((centre, low, high))
}

/// The leaf tiles of `scene`, in the order of their cells (x, then z; a split cell's
/// quadrants in its place), every mesh in exactly one.
pub fn leaf_tiles(scene: &Scene) -> Vec<LeafTile> {
    let mut cells: BTreeMap<[i64; 2], Vec<u32>> = BTreeMap::new();
    for mesh in 0..scene.meshes.len() as u32 {
        let cell = placed(scene, mesh).map_or([0, 0], |(centre, _, _)| cell_of(centre, TILE_SIDE_M));
        cells.entry(cell).or_default().push(mesh);
    }
    let mut tiles = Vec::new();
    for (cell, meshes) in cells {
        split_into(scene, cell, TILE_SIDE_M, meshes, &mut tiles);
    }
    tiles
}

/// The grid cell of side `side` that `centre` lies in.
fn cell_of(centre: [f64; 3], side: f64) -> [i64; 2] {
    // Far outside any city (1e18 m) the cell saturates instead of wrapping.
    [(centre[0] / side).floor() as i64, (centre[2] / side).floor() as i64]
}

fn triangles(scene: &Scene, meshes: &[u32]) -> u64 {
    meshes
        .iter()
        .map(|&m| u64::from(scene.meshes[m as usize].index_count) / 3)
        .sum()
}

/// Pushes the tile of `meshes` in `cell` of side `side`, or its quadrants' tiles where it
/// holds too many triangles and may still split.
fn split_into(scene: &Scene, cell: [i64; 2], side: f64, meshes: Vec<u32>, tiles: &mut Vec<LeafTile>) {
    let count = triangles(scene, &meshes);
    let half = side * 0.5;
    if count <= MAX_LEAF_TRIANGLES || half < MIN_LEAF_SIDE_M || meshes.len() < 2 {
        tiles.push(LeafTile {
            side_m: side,
            cell,
            origin: origin_of(scene, &meshes),
            meshes,
            triangles: count,
        });
        return;
    }
    let mut quadrants: BTreeMap<[i64; 2], Vec<u32>> = BTreeMap::new();
    for mesh in meshes {
        // Saturating: a cell already saturated far outside any city stays where it is.
        let (low_x, low_z) = (cell[0].saturating_mul(2), cell[1].saturating_mul(2));
        let quadrant = placed(scene, mesh).map_or([low_x, low_z], |(centre, _, _)| {
            // Clamped into this cell's four: a centre on its far edge rounds outwards.
            let [x, z] = cell_of(centre, half);
            [
                x.clamp(low_x, low_x.saturating_add(1)),
                z.clamp(low_z, low_z.saturating_add(1)),
            ]
        });
        quadrants.entry(quadrant).or_default().push(mesh);
    }
    for (quadrant, meshes) in quadrants {
        split_into(scene, quadrant, half, meshes, tiles);
    }
}

/// The origin of a tile of `meshes`: the scene's origin plus, on each axis, the centre of
/// their vertices' box rounded to whole metres, or 0 where that offset is under the box's
/// extent plus a metre (there a vertex may lie nearer the scene's origin than the tile's
/// centre, and moving it would coarsen its `f32`; the module's docs say why this makes
/// re-expressing exact); the scene's origin for meshes with no vertices.
fn origin_of(scene: &Scene, meshes: &[u32]) -> [f64; 3] {
    // From the positions themselves, not the meshes' bounds, which validation allows to be
    // a little loose: exactness needs every vertex no nearer the scene's origin than its
    // offset from the tile's.
    let mut low = [f64::INFINITY; 3];
    let mut high = [f64::NEG_INFINITY; 3];
    for &mesh in meshes {
        let Some(m) = scene.meshes.get(mesh as usize) else {
            continue;
        };
        let offset = scene.offset_of(m);
        let first = m.first_vertex as usize;
        for p in scene
            .positions
            .get(first..first + m.vertex_count as usize)
            .unwrap_or(&[])
        {
            for a in 0..3 {
                let v = offset[a] + f64::from(p[a]);
                low[a] = low[a].min(v);
                high[a] = high[a].max(v);
            }
        }
    }
    if !(0..3).all(|a| low[a].is_finite() && high[a].is_finite()) {
        return scene.origin;
    }
    std::array::from_fn(|a| {
        let offset = (0.5 * (low[a] + high[a])).round();
        if offset.abs() >= high[a] - low[a] + 1.0 {
            scene.origin[a] + offset
        } else {
            scene.origin[a]
        }
    })
}

/// `mesh`'s positions relative to `origin` (absolute), computed in `f64` from the origin they
/// are relative to (the scene's or the mesh's local one) and rounded once.
pub fn positions_relative_to(scene: &Scene, mesh: u32, origin: [f64; 3]) -> Vec<[f32; 3]> {
    let Some(m) = scene.meshes.get(mesh as usize) else {
        return Vec::new();
    };
    // The tile's origin from the scene's first: two nearby large numbers cancel exactly,
    // and the small positions are then moved by a small offset.
    let from = scene.origin_of(m);
    let offset: [f64; 3] = std::array::from_fn(|a| origin[a] - from[a]);
    let first = m.first_vertex as usize;
    scene
        .positions
        .get(first..first + m.vertex_count as usize)
        .unwrap_or(&[])
        .iter()
        .map(|p| std::array::from_fn(|a| (f64::from(p[a]) - offset[a]) as f32))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A box mesh of `triangles` triangles (a fan of `triangles + 2` vertices) spanning
    /// `low..high`, relative to the scene's origin.
    fn push_mesh(scene: &mut Scene, low: [f32; 3], high: [f32; 3], triangles: u32) {
        let vertices = triangles + 2;
        let positions: Vec<[f32; 3]> = (0..vertices)
            .map(|i| {
                let t = i as f32 / (vertices - 1) as f32;
                std::array::from_fn(|a| low[a] + (high[a] - low[a]) * if a == 1 { 1.0 - t } else { t })
            })
            .collect();
        let normals = vec![[0.0, 1.0, 0.0]; positions.len()];
        let uvs = vec![[0.0, 0.0]; positions.len()];
        let indices: Vec<u32> = (0..triangles).flat_map(|i| [0, i + 1, i + 2]).collect();
        scene
            .push_mesh(0, &positions, &normals, &uvs, &indices)
            .expect("a valid mesh");
    }

    #[test]
    fn meshes_group_by_their_centre_on_the_grid_each_in_one_tile() {
        let mut scene = Scene::new([0.0; 3]);
        // Two meshes in cell (0, 0), one in (1, 0), one straddling into (−1, −1) by its centre.
        push_mesh(&mut scene, [10.0, 0.0, 10.0], [20.0, 5.0, 20.0], 4);
        push_mesh(&mut scene, [200.0, 0.0, 100.0], [250.0, 9.0, 120.0], 4);
        push_mesh(&mut scene, [300.0, 0.0, 10.0], [310.0, 5.0, 20.0], 4);
        push_mesh(&mut scene, [-30.0, 0.0, -30.0], [10.0, 5.0, 10.0], 4);
        let tiles = leaf_tiles(&scene);
        let cells: Vec<([i64; 2], Vec<u32>)> = tiles.iter().map(|t| (t.cell, t.meshes.clone())).collect();
        assert_eq!(
            cells,
            vec![([-1, -1], vec![3]), ([0, 0], vec![0, 1]), ([1, 0], vec![2])],
            "{tiles:?}"
        );
        // The origin is the centre of the tile's meshes' bounds to whole metres, or the
        // scene's origin on an axis where the bounds reach within their extent of it.
        assert_eq!(tiles[1].origin, [0.0, 0.0, 0.0]);
        assert_eq!(tiles[2].origin, [305.0, 0.0, 15.0]);
        let mut far = Scene::new([0.0; 3]);
        push_mesh(&mut far, [5_000.5, 0.0, 2_000.25], [5_010.0, 9.0, 2_100.0], 4);
        assert_eq!(leaf_tiles(&far)[0].origin, [5_005.0, 0.0, 2_050.0]);
        assert!(tiles.iter().all(|t| t.side_m == TILE_SIDE_M));
    }

    #[test]
    fn a_crowded_cell_splits_into_quadrants_down_to_the_least_side() {
        let mut scene = Scene::new([0.0; 3]);
        // 40,000 triangles in each quadrant of cell (0, 0): 160,000 > 65,536, so it splits
        // once; each quadrant's 40,000 fit.
        for (x, z) in [(10.0, 10.0), (200.0, 10.0), (10.0, 200.0), (200.0, 200.0)] {
            push_mesh(&mut scene, [x, 0.0, z], [x + 5.0, 5.0, z + 5.0], 20_000);
            push_mesh(&mut scene, [x + 6.0, 0.0, z], [x + 9.0, 5.0, z + 5.0], 20_000);
        }
        let tiles = leaf_tiles(&scene);
        assert_eq!(
            tiles.len(),
            4,
            "{:?}",
            tiles.iter().map(|t| (t.cell, t.side_m)).collect::<Vec<_>>()
        );
        assert!(tiles.iter().all(|t| t.side_m == 128.0 && t.triangles == 40_000));
        // 200,000 triangles in one spot split down to 32 m and stop there.
        let mut dense = Scene::new([0.0; 3]);
        for _ in 0..5 {
            push_mesh(&mut dense, [1.0, 0.0, 1.0], [2.0, 1.0, 2.0], 40_000);
        }
        let tiles = leaf_tiles(&dense);
        assert_eq!(tiles.len(), 1);
        assert_eq!((tiles[0].side_m, tiles[0].triangles), (32.0, 200_000));
    }

    #[test]
    fn positions_a_thousand_kilometres_out_keep_their_millimetres_relative_to_the_tile() {
        // A scene whose origin is 1,000 km out: positions relative to the tile's origin are
        // those of the same meshes near the origin.
        let far = [1.0e6, 0.0, -1.0e6];
        let mut out = Scene::new(far);
        let mut home = Scene::new([0.0; 3]);
        for scene in [&mut out, &mut home] {
            push_mesh(scene, [10.123, 0.0, 10.456], [20.789, 5.5, 20.001], 3);
        }
        let (tile_out, tile_home) = (&leaf_tiles(&out)[0], &leaf_tiles(&home)[0]);
        let moved: Vec<f64> = (0..3)
            .map(|a| tile_out.origin[a] - far[a] - tile_home.origin[a])
            .collect();
        assert!(moved.iter().all(|d| d.abs() < 1e-9), "{moved:?}");
        let a = positions_relative_to(&out, 0, tile_out.origin);
        let b = positions_relative_to(&home, 0, tile_home.origin);
        // Equal to a nanometre: the origins differ only by f64's rounding at 10⁶ m.
        assert_eq!(a.len(), b.len());
        for (p, q) in a.iter().zip(&b) {
            assert!((0..3).all(|i| (p[i] - q[i]).abs() < 1e-9), "{p:?} against {q:?}");
        }
        assert!(a.iter().flatten().all(|v| v.abs() < 10.0));
    }

    #[test]
    fn meshes_without_bounds_join_the_tile_at_the_origin() {
        let mut scene = Scene::new([0.0; 3]);
        push_mesh(&mut scene, [600.0, 0.0, 600.0], [610.0, 5.0, 610.0], 2);
        scene.meshes.push(crate::Mesh {
            first_vertex: 0,
            vertex_count: 0,
            first_index: 0,
            index_count: 0,
            texture: 0,
            bounds: crate::Aabb::EMPTY,
            origin: 0,
        });
        let tiles = leaf_tiles(&scene);
        let cells: Vec<([i64; 2], Vec<u32>)> = tiles.iter().map(|t| (t.cell, t.meshes.clone())).collect();
        assert_eq!(cells, vec![([0, 0], vec![1]), ([2, 2], vec![0])]);
        assert_eq!(tiles[0].origin, [0.0; 3]);
    }
}
