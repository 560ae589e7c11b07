//! A scene cut into tiles (dataset format 4, docs/DATASET.md): the tile table and
//! `geometry.pack` that every writer writes, and the tiles read back, as tiles or as the
//! scene they hold.
//!
//! The tree is flat for now: every leaf of [`leaf_tiles`] is a root, with no inner tiles
//! above them. The quadtree of inner tiles and their proxies (issue 62's levels of detail)
//! slot in above the same leaves.

use std::path::Path;

use super::colormap::u32_records;
use super::error::DatasetError;
use super::files::{DatasetFiles, GEOMETRY_CRC_FILE, GEOMETRY_PACK_FILE, TILES_FILE};
use super::io_util::{decode_table, encode_table_of_version};
use super::scene::{Aabb, Scene};
use super::tile_geometry::TileGeometry;
use super::tiles::{Refine, TileLimits, TileRecord, TileTree, TILES_VERSION};
use super::tiling::leaf_tiles;

/// A scene as tiles: the table and the pack of their geometry.
#[derive(Clone, Debug, PartialEq)]
pub struct TiledScene {
    /// The tile table; its mesh ids are the scene's.
    pub tree: TileTree,
    /// `geometry.pack`'s bytes: each tile's blob at its record's offset.
    pub pack: Vec<u8>,
}

impl TiledScene {
    /// Cuts `scene` into its leaf tiles ([`leaf_tiles`]), every one a root.
    pub fn of(scene: &Scene, write_id: u64) -> Result<Self, DatasetError> {
        let leaves = leaf_tiles(scene);
        let mut tiles = Vec::with_capacity(leaves.len());
        let mut pack = Vec::new();
        let mut mesh_ids = Vec::with_capacity(scene.meshes.len());
        for leaf in &leaves {
            let geometry = TileGeometry::from_scene(scene, &leaf.meshes, leaf.origin)?;
            let mut bounds = Aabb::EMPTY;
            geometry
                .meshes
                .iter()
                .filter(|m| m.vertex_count > 0)
                .for_each(|m| bounds.union(&m.bounds));
            if !bounds.is_valid() {
                bounds = Aabb {
                    min: [0.0; 3],
                    max: [0.0; 3],
                };
            }
            let textures = leaf.meshes.iter().map(|&m| scene.meshes[m as usize].texture);
            let (first_texture, texture_end) =
                textures.fold((u32::MAX, 0u32), |(lo, hi), t| (lo.min(t), hi.max(t.saturating_add(1))));
            let blob = geometry.encode()?;
            let too_big = || DatasetError::InvalidInput("a tile exceeds 2^32 meshes, vertices or indices".into());
            tiles.push(TileRecord {
                origin: leaf.origin,
                bounds_min: bounds.min,
                bounds_max: bounds.max,
                geometric_error: 0.0,
                refine: Refine::Replace,
                first_child: 0,
                child_count: 0,
                geometry_offset: pack.len() as u64,
                geometry_len: blob.len() as u64,
                vertex_count: u32::try_from(geometry.positions.len()).map_err(|_| too_big())?,
                index_count: u32::try_from(geometry.indices.len()).map_err(|_| too_big())?,
                first_mesh: u32::try_from(mesh_ids.len()).map_err(|_| too_big())?,
                mesh_count: u32::try_from(leaf.meshes.len()).map_err(|_| too_big())?,
                first_texture: if first_texture == u32::MAX { 0 } else { first_texture },
                texture_count: texture_end.saturating_sub(first_texture.min(texture_end)),
            });
            pack.extend_from_slice(&blob);
            mesh_ids.extend_from_slice(&leaf.meshes);
        }
        let roots =
            0..u32::try_from(tiles.len()).map_err(|_| DatasetError::InvalidInput("more than 2^32 tiles".into()))?;
        Ok(TiledScene {
            tree: TileTree {
                write_id,
                crs: scene.crs.clone(),
                origin: scene.origin,
                roots,
                tiles,
                mesh_ids,
            },
            pack,
        })
    }

    /// The limits the tree is checked against: this pack, `texture_count` textures.
    pub fn limits(&self, texture_count: u32) -> TileLimits {
        TileLimits {
            geometry_len: self.pack.len() as u64,
            texture_count,
        }
    }
}

/// The three files of `scene` in format 4, of write `write_id` whose texture table holds
/// `texture_count` textures, by name: `tiles.bin`, `geometry.crc`, `geometry.pack`. The
/// scene is checked first (every mesh's texture, finite attributes, indices inside their
/// mesh, bounds that hold their vertices); `dir` names the files in errors.
pub(crate) fn encode_scene_files(
    scene: &Scene,
    dir: &Path,
    write_id: u64,
    texture_count: u32,
) -> Result<[(&'static str, Vec<u8>); 3], DatasetError> {
    if let Err(e) = scene.validate(Path::new("the scene")) {
        // The scene is the writer's input, not a file: what is wrong with it, without offsets.
        return Err(match e {
            DatasetError::Corrupt { what, .. } => DatasetError::InvalidInput(format!("the scene to write: {what}")),
            other => other,
        });
    }
    if let Some((m, mesh)) = scene
        .meshes
        .iter()
        .enumerate()
        .find(|(_, m)| m.texture >= texture_count)
    {
        return Err(DatasetError::InvalidInput(format!(
            "mesh {m} uses texture {} but only {texture_count} textures were written",
            mesh.texture
        )));
    }
    let tiled = TiledScene::of(scene, write_id)?;
    let checksums = tiled.checksums()?;
    let tiles = tiled.tree.encode(&dir.join(TILES_FILE), tiled.limits(texture_count))?;
    Ok([
        (TILES_FILE, tiles),
        (GEOMETRY_CRC_FILE, encode_geometry_checksums(write_id, &checksums)),
        (GEOMETRY_PACK_FILE, tiled.pack),
    ])
}

/// The scene of format-4 `files` whose texture table holds `texture_count` textures, each
/// file read with `read_file`: `geometry.crc`, `geometry.pack` and `tiles.bin` checked
/// (write ids, the tree, every tile's geometry against its CRC-32 and its record), then the
/// tiles' geometry as one scene ([`scene_of_tiles`]). Returns it and the bytes read.
pub(crate) fn read_scene_files(
    files: &DatasetFiles,
    read_file: impl Fn(&Path) -> Result<Vec<u8>, DatasetError>,
    texture_count: u32,
) -> Result<(Scene, u64), DatasetError> {
    let crc_path = files.path(GEOMETRY_CRC_FILE);
    let (checksums, write_id) = decode_geometry_checksums(&crc_path, &read_file(&crc_path)?)?;
    files.check_write_id(&crc_path, write_id)?;
    let pack_path = files.path(GEOMETRY_PACK_FILE);
    let pack = read_file(&pack_path)?;
    let tiles_path = files.path(TILES_FILE);
    let tiles_bytes = read_file(&tiles_path)?;
    let limits = TileLimits {
        geometry_len: pack.len() as u64,
        texture_count,
    };
    let tree = TileTree::decode(&tiles_path, &tiles_bytes, limits)?;
    files.check_write_id(&tiles_path, tree.write_id)?;
    let geometry = read_checked_tile_geometry(&pack_path, &tree, &pack, &checksums)?;
    let bytes = (pack.len() + tiles_bytes.len()) as u64;
    // The pack's bytes go before the scene is built: at most two copies of the geometry.
    drop(pack);
    Ok((scene_of_tiles(&tree, &geometry)?, bytes))
}

/// The magic of `geometry.crc`.
const GEOMETRY_CRC_MAGIC: &[u8; 8] = b"CSGEOCRC";

/// `geometry.crc`'s bytes: the table header (format 4, `write_id`) and the CRC-32 of each
/// tile's blob in `geometry.pack`, in the tile table's order.
pub fn encode_geometry_checksums(write_id: u64, checksums: &[u32]) -> Vec<u8> {
    let body: Vec<u8> = checksums.iter().flat_map(|c| c.to_le_bytes()).collect();
    encode_table_of_version(
        GEOMETRY_CRC_MAGIC,
        TILES_VERSION,
        write_id,
        checksums.len() as u64,
        &body,
    )
}

/// `geometry.crc` read back (the bytes of `path`): each tile's CRC-32 and the file's write
/// id, its header, size and own checksum checked.
pub fn decode_geometry_checksums(path: &Path, bytes: &[u8]) -> Result<(Vec<u32>, u64), DatasetError> {
    let table = decode_table(path, bytes, GEOMETRY_CRC_MAGIC, 4, TILES_VERSION)?;
    Ok((u32_records(table.body), table.write_id))
}

impl TiledScene {
    /// The CRC-32 of each tile's blob, in the tile table's order: `geometry.crc`'s records.
    pub fn checksums(&self) -> Result<Vec<u32>, DatasetError> {
        let path = Path::new("geometry.pack");
        self.tree
            .tiles
            .iter()
            .enumerate()
            .map(|(index, record)| Ok(crc32fast::hash(tile_blob(path, index, record, &self.pack)?)))
            .collect()
    }
}

/// [`read_tile_geometry`] with every tile's blob checked against its CRC-32 from
/// `geometry.crc` (`checksums`, one per tile) before it is decoded; a mismatch names the
/// tile and its bytes in `path`.
pub fn read_checked_tile_geometry(
    path: &Path,
    tree: &TileTree,
    pack: &[u8],
    checksums: &[u32],
) -> Result<Vec<TileGeometry>, DatasetError> {
    if checksums.len() != tree.tiles.len() {
        return Err(DatasetError::Corrupt {
            path: path.to_path_buf(),
            offset: 0,
            what: format!("{} tile checksums for {} tiles", checksums.len(), tree.tiles.len()),
        });
    }
    for (index, (record, &stored)) in tree.tiles.iter().zip(checksums).enumerate() {
        let blob = tile_blob(path, index, record, pack)?;
        let computed = crc32fast::hash(blob);
        if computed != stored {
            return Err(DatasetError::Checksum {
                path: path.to_path_buf(),
                what: format!("tile {index}'s geometry"),
                offset: record.geometry_offset,
                end: record.geometry_offset + record.geometry_len,
                stored,
                computed,
            });
        }
    }
    read_tile_geometry(path, tree, pack)
}

/// Tile `index`'s blob in `pack` (the bytes of `path`), or an error naming it where the
/// pack ends before it does.
fn tile_blob<'a>(path: &Path, index: usize, record: &TileRecord, pack: &'a [u8]) -> Result<&'a [u8], DatasetError> {
    let end = record.geometry_offset.saturating_add(record.geometry_len);
    usize::try_from(record.geometry_offset)
        .ok()
        .zip(usize::try_from(end).ok())
        .and_then(|(start, end)| pack.get(start..end))
        .ok_or_else(|| {
            DatasetError::truncated(
                path,
                format!("tile {index}'s geometry"),
                record.geometry_offset,
                end,
                pack.len() as u64,
            )
        })
}

/// What is wrong in giving `tiles` as the geometry of `tree`'s tiles, in its order: another
/// count of tiles, or a tile holding another count of meshes than its record; `None` where
/// they agree (what [`scene_of_tiles`] and the engine's drawing of tiles rely on).
pub fn geometry_mismatch(tree: &TileTree, tiles: &[TileGeometry]) -> Option<String> {
    if tiles.len() != tree.tiles.len() {
        return Some(format!(
            "{} tiles' geometry for {} tiles",
            tiles.len(),
            tree.tiles.len()
        ));
    }
    tree.tiles
        .iter()
        .zip(tiles)
        .enumerate()
        .find_map(|(t, (record, tile))| {
            (tile.meshes.len() as u64 != u64::from(record.mesh_count)).then(|| {
                format!(
                    "tile {t} holds {} meshes, its record {}",
                    tile.meshes.len(),
                    record.mesh_count
                )
            })
        })
}

/// The scene `tiles` (the geometry of `tree`'s tiles, in its order) hold, meshes in the
/// order of their ids. A mesh goes into the scene's frame (its positions plus its tile's
/// offset from the scene's origin, in `f64`, rounded to `f32`) where that loses nothing (every
/// position comes back exactly: always for a scene written from one frame, tiling.rs says
/// why); otherwise it keeps its positions relative to its tile's origin, which becomes a
/// local origin of the scene ([`Scene::local_origins`]), so a scene far larger than a city
/// keeps what the tiles stored. Errors where a tile's geometry disagrees with its record's
/// mesh count.
pub fn scene_of_tiles(tree: &TileTree, tiles: &[TileGeometry]) -> Result<Scene, DatasetError> {
    let invalid = |what: String| DatasetError::InvalidInput(format!("tiled scene: {what}"));
    if let Some(what) = geometry_mismatch(tree, tiles) {
        return Err(invalid(what));
    }
    // Where each mesh id lies: (tile, the mesh's place in it).
    let mut location = vec![None::<(u32, u32)>; tree.mesh_ids.len()];
    for (t, record) in tree.tiles.iter().enumerate() {
        for k in 0..record.mesh_count {
            let id = tree.mesh_ids[(record.first_mesh + k) as usize];
            location[id as usize] = Some((t as u32, k));
        }
    }
    let mut scene = Scene::new(tree.origin);
    scene.crs = tree.crs.clone();
    // Each tile's index among the scene's local origins, once one of its meshes needs it.
    let mut local_origin = vec![None::<u32>; tree.tiles.len()];
    let mut positions = Vec::new();
    for (id, at) in location.into_iter().enumerate() {
        let (t, k) = at.ok_or_else(|| invalid(format!("no tile holds mesh {id}")))?;
        let (record, tile) = (&tree.tiles[t as usize], &tiles[t as usize]);
        let mesh = &tile.meshes[k as usize];
        let offset: [f64; 3] = [0, 1, 2].map(|a| record.origin[a] - tree.origin[a]);
        let (fv, vc) = (mesh.first_vertex as usize, mesh.vertex_count as usize);
        let (fi, ic) = (mesh.first_index as usize, mesh.index_count as usize);
        let stored = &tile.positions[fv..fv + vc];
        positions.clear();
        positions.extend(
            stored
                .iter()
                .map(|p| [0, 1, 2].map(|a| (offset[a] + f64::from(p[a])) as f32)),
        );
        let exact = positions
            .iter()
            .zip(stored)
            .all(|(p, q)| (0..3).all(|a| (f64::from(p[a]) - offset[a]) as f32 == q[a]));
        let (origin, positions) = if exact {
            (0, &positions[..])
        } else {
            let origin = match local_origin[t as usize] {
                Some(index) => index,
                None => *local_origin[t as usize].insert(scene.add_local_origin(record.origin)?),
            };
            (origin, stored)
        };
        scene.push_mesh_at(
            origin,
            mesh.texture,
            positions,
            &tile.normals[fv..fv + vc],
            &tile.uvs[fv..fv + vc],
            &tile.indices[fi..fi + ic],
        )?;
    }
    Ok(scene)
}

/// Every tile's geometry read back from `pack` (the bytes of `path`), checked against its
/// record, its vertices inside the record's bounds (which refinement and culling trust).
pub fn read_tile_geometry(path: &Path, tree: &TileTree, pack: &[u8]) -> Result<Vec<TileGeometry>, DatasetError> {
    tree.tiles
        .iter()
        .enumerate()
        .map(|(index, record)| {
            let tile = TileGeometry::decode(path, index, record, tile_blob(path, index, record, pack)?)?;
            let bounds = Aabb {
                min: record.bounds_min,
                max: record.bounds_max,
            };
            // Bounds are the union of the positions as stored, so any slack is damage.
            if let Some((v, p)) = tile
                .positions
                .iter()
                .enumerate()
                .find(|(_, p)| !bounds.contains(**p, 0.0))
            {
                return Err(DatasetError::Corrupt {
                    path: path.to_path_buf(),
                    offset: record.geometry_offset,
                    what: format!(
                        "tile {index}'s vertex {v} at {p:?} lies outside the tile's bounds {:?}..{:?}",
                        record.bounds_min, record.bounds_max
                    ),
                });
            }
            Ok(tile)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A mesh of two triangles over `low..high` (relative to the scene's origin), texture
    /// `texture`.
    fn push_quad(scene: &mut Scene, low: [f32; 3], high: [f32; 3], texture: u32) {
        let positions = [low, [high[0], low[1], low[2]], high, [low[0], high[1], high[2]]];
        scene
            .push_mesh(
                texture,
                &positions,
                &[[0.0, 1.0, 0.0]; 4],
                &[[0.0; 2]; 4],
                &[0, 1, 2, 0, 2, 3],
            )
            .expect("a valid quad");
    }

    #[test]
    fn a_scene_of_a_country_keeps_every_vertex_through_its_tiles() {
        // Meshes 500 km apart in one frame (the scene's origin at 0, positions f32 at
        // 500 km: 3 cm steps), and a scene 1,000 km out: through tiles every absolute
        // position comes back within a micrometre, each mesh in one tile under its own id.
        for origin in [[0.0, 0.0, 0.0], [1.0e6, 0.0, -1.0e6]] {
            let mut scene = Scene::new(origin);
            push_quad(&mut scene, [5.0e5, 0.0, 10.0], [5.0e5 + 20.0, 15.0, 30.0], 2);
            push_quad(&mut scene, [10.0, 0.0, 10.0], [40.0, 8.0, 25.0], 0);
            push_quad(&mut scene, [5.0e5 + 30.0, 0.0, 12.0], [5.0e5 + 50.0, 9.0, 20.0], 1);
            push_quad(&mut scene, [-300.0, 0.0, 900.0], [-280.0, 3.0, 920.0], 2);
            let tiled = TiledScene::of(&scene, 9).expect("tiles");
            assert_eq!(tiled.tree.tiles.len(), 3);
            let mut sorted = tiled.tree.mesh_ids.clone();
            sorted.sort_unstable();
            assert_eq!(sorted, vec![0, 1, 2, 3]);
            let path = Path::new("tiles.bin");
            let bytes = tiled.tree.encode(path, tiled.limits(3)).expect("valid");
            let tree = TileTree::decode(path, &bytes, tiled.limits(3)).expect("decodes");
            let geometry = read_tile_geometry(Path::new("geometry.pack"), &tree, &tiled.pack).expect("reads");
            for (record, tile) in tree.tiles.iter().zip(&geometry) {
                for (k, mesh) in tile.meshes.iter().enumerate() {
                    let source = tree.mesh_ids[(record.first_mesh as usize) + k] as usize;
                    let original = &scene.meshes[source];
                    assert_eq!(mesh.texture, original.texture);
                    for v in 0..mesh.vertex_count as usize {
                        let got = tile.positions[mesh.first_vertex as usize + v];
                        let want = scene.positions[original.first_vertex as usize + v];
                        for a in 0..3 {
                            let (g, w) = (
                                record.origin[a] + f64::from(got[a]),
                                scene.origin[a] + f64::from(want[a]),
                            );
                            assert!((g - w).abs() < 1e-6, "mesh {source} vertex {v}: {g} against {w}");
                        }
                    }
                }
                // Within its tile every position is small: f32 holds it to a micrometre.
                assert!(tile.positions.iter().flatten().all(|p| p.abs() < 256.0));
            }
        }
    }

    #[test]
    fn a_scene_read_back_from_its_tiles_is_the_scene() {
        // Meshes in no spatial order (the tiles list them apart), one empty, the scene 1,000 km
        // out: the same meshes under the same ids, with the same attributes and indices.
        let mut scene = Scene::new([1.0e6, 12.0, -1.0e6]);
        scene.crs = Some(crate::Crs::epsg(25833));
        push_quad(&mut scene, [900.0, 0.0, 10.0], [920.0, 8.0, 25.0], 1);
        push_quad(&mut scene, [10.0, 0.0, 10.0], [40.0, 8.0, 25.0], 0);
        scene.push_mesh(2, &[], &[], &[], &[]).expect("an empty mesh");
        push_quad(&mut scene, [905.5, 1.0, 30.25], [915.0, 6.0, 40.0], 2);
        push_quad(&mut scene, [-3000.0, -2.0, 5000.0], [-2990.0, 3.0, 5010.0], 0);
        let tiled = TiledScene::of(&scene, 3).expect("tiles");
        assert_ne!(
            tiled.tree.mesh_ids,
            (0..5).collect::<Vec<u32>>(),
            "the tiles list the meshes in another order"
        );
        let tiles = read_tile_geometry(Path::new("geometry.pack"), &tiled.tree, &tiled.pack).expect("reads");
        let back = scene_of_tiles(&tiled.tree, &tiles).expect("a scene");
        // Tile origins lie whole metres from the scene's: every position comes back as the
        // very `f32` written, so the scene is equal, bounds and all.
        assert_eq!(back, scene);
        // A tile whose geometry lost a mesh is refused.
        let mut short = tiles.clone();
        short[0].meshes.pop();
        assert!(scene_of_tiles(&tiled.tree, &short).is_err());
    }

    #[test]
    fn positions_come_back_as_the_very_f32_written_anywhere_in_a_city() {
        // Random meshes over 40 km, many near the scene's origin (where a tile's origin can
        // lie farther from the scene's than a vertex does) and some large ones: exact.
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = move || {
            state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = state;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            (z ^ (z >> 31)) as f64 / u64::MAX as f64
        };
        let mut scene = Scene::new([391_250.0, 34.0, -5_819_500.0]);
        for m in 0..400 {
            let reach = if m % 2 == 0 { 300.0 } else { 20_000.0 };
            let centre = [0, 1, 2].map(|_| (next() * 2.0 - 1.0) * reach);
            let size = if m % 7 == 0 { 200.0 } else { 12.0 };
            let positions: Vec<[f32; 3]> = (0..6)
                .map(|_| [0, 1, 2].map(|a| (centre[a] + (next() - 0.5) * size) as f32))
                .collect();
            scene
                .push_mesh(
                    m % 5,
                    &positions,
                    &[[0.0, 1.0, 0.0]; 6],
                    &[[0.5; 2]; 6],
                    &[0, 1, 2, 3, 4, 5],
                )
                .expect("a mesh");
        }
        let tiled = TiledScene::of(&scene, 1).expect("tiles");
        let tiles = read_tile_geometry(Path::new("geometry.pack"), &tiled.tree, &tiled.pack).expect("reads");
        let back = scene_of_tiles(&tiled.tree, &tiles).expect("a scene");
        assert_eq!(back, scene);
        // And so a scene read back is written again byte for byte (a merge of shards).
        assert_eq!(TiledScene::of(&back, 1).expect("tiles"), tiled);
    }

    #[test]
    fn a_vertex_outside_its_slightly_loose_bounds_still_comes_back_exactly() {
        // Validation lets bounds be loose by 1e-4 (1 + |coordinate|): a vertex at x =
        // 8191.99951171875 under bounds from 8192.6 would, with the origin taken from the
        // bounds (16,384), round to -8192 in its tile and come back as 8192.
        let mut scene = Scene::new([391_250.0, 34.0, -5_819_500.0]);
        let x = 8_191.999_5_f32;
        let positions = [[x, 0.0, 0.0], [24_575.0, 0.0, 0.0], [24_575.0, 5.0, 0.0]];
        scene
            .push_mesh(0, &positions, &[[0.0, 1.0, 0.0]; 3], &[[0.0; 2]; 3], &[0, 1, 2])
            .expect("a mesh");
        scene.meshes[0].bounds.min[0] = 8192.6;
        scene.validate(Path::new("scene")).expect("loose within the tolerance");
        let tiled = TiledScene::of(&scene, 1).expect("tiles");
        let tiles = read_tile_geometry(Path::new("geometry.pack"), &tiled.tree, &tiled.pack).expect("reads");
        let back = scene_of_tiles(&tiled.tree, &tiles).expect("a scene");
        assert_eq!(back.positions, scene.positions);
    }

    #[test]
    fn a_mesh_at_a_local_origin_keeps_its_micrometres_through_the_tiles() {
        // A mesh 500 km from the scene's origin, at its own origin with positions a
        // micrometre apart (the scene's f32 frame steps by 3 cm there), beside one at home:
        // read back, the far mesh is at its tile's origin with every position as written
        // relative to it, the near one in the scene's frame as written.
        let mut scene = Scene::new([391_250.0, 34.0, -5_819_500.0]);
        push_quad(&mut scene, [10.0, 0.0, 10.0], [40.0, 8.0, 25.0], 0);
        let far = [391_250.0 + 5.0e5, 40.0, -5_819_500.0];
        let local = scene.add_local_origin(far).expect("an origin");
        let fine: Vec<[f32; 3]> = [[0.0, 0.0, 0.0], [1e-6, 0.0, 0.0], [1e-6, 3e-6, 0.0], [0.0, 3e-6, 2e-6]].into();
        scene
            .push_mesh_at(
                local,
                1,
                &fine,
                &[[0.0, 1.0, 0.0]; 4],
                &[[0.0; 2]; 4],
                &[0, 1, 2, 0, 2, 3],
            )
            .expect("a mesh at its own origin");
        // Its bounds are in the scene's frame, rounded outwards.
        let bounds = scene.meshes[1].bounds;
        assert!(f64::from(bounds.min[0]) <= 5.0e5 && f64::from(bounds.max[0]) >= 5.0e5 + 1e-6);
        scene.validate(Path::new("scene")).expect("valid");
        let tiled = TiledScene::of(&scene, 1).expect("tiles");
        let tiles = read_tile_geometry(Path::new("geometry.pack"), &tiled.tree, &tiled.pack).expect("reads");
        let back = scene_of_tiles(&tiled.tree, &tiles).expect("a scene");
        assert_eq!(back.meshes[0].origin, 0);
        assert_eq!(&back.positions[..4], &scene.positions[..4]);
        let mesh = back.meshes[1];
        let origin = back.origin_of(&mesh);
        for (v, (p, want)) in back.positions[4..].iter().zip(&fine).enumerate() {
            for a in 0..3 {
                let (got, want) = (origin[a] + f64::from(p[a]), far[a] + f64::from(want[a]));
                assert!((got - want).abs() < 1e-9, "vertex {v}: {got} against {want}");
            }
        }
        back.validate(Path::new("scene")).expect("valid");
        // Written again, the same tiles.
        assert_eq!(TiledScene::of(&back, 1).expect("tiles"), tiled);
        // Version 3's one frame cannot hold it: refused, not rounded.
        assert!(matches!(
            back.encode(Path::new("scene.bin"), 1),
            Err(DatasetError::InvalidInput(_))
        ));
    }

    #[test]
    fn texture_ranges_cover_each_tiles_textures() {
        let mut scene = Scene::new([0.0; 3]);
        push_quad(&mut scene, [10.0, 0.0, 10.0], [20.0, 5.0, 20.0], 7);
        push_quad(&mut scene, [30.0, 0.0, 10.0], [40.0, 5.0, 20.0], 4);
        let tiled = TiledScene::of(&scene, 1).expect("tiles");
        let tile = &tiled.tree.tiles[0];
        assert_eq!((tile.first_texture, tile.texture_count), (4, 4));
        assert!(tiled.tree.validate(Path::new("tiles.bin"), tiled.limits(8)).is_ok());
        // With fewer textures than a tile names, the table is refused.
        assert!(tiled.tree.validate(Path::new("tiles.bin"), tiled.limits(7)).is_err());
        assert_eq!(tiled.tree.crs, None);
    }

    #[test]
    fn geometry_checksums_catch_a_flipped_byte_naming_the_tile() {
        let mut scene = Scene::new([0.0; 3]);
        push_quad(&mut scene, [10.0, 0.0, 10.0], [40.0, 8.0, 25.0], 0);
        push_quad(&mut scene, [900.0, 0.0, 10.0], [920.0, 8.0, 25.0], 1);
        let tiled = TiledScene::of(&scene, 5).expect("tiles");
        assert_eq!(tiled.tree.tiles.len(), 2);
        let checksums = tiled.checksums().expect("checksums");
        let path = Path::new("geometry.crc");
        let bytes = encode_geometry_checksums(5, &checksums);
        assert_eq!(
            decode_geometry_checksums(path, &bytes).expect("decodes"),
            (checksums.clone(), 5)
        );
        // The file's own checksum, its size and its version are checked.
        let mut flipped = bytes.clone();
        *flipped.last_mut().expect("bytes") ^= 1;
        assert!(matches!(
            decode_geometry_checksums(path, &flipped),
            Err(DatasetError::Checksum { .. })
        ));
        assert!(decode_geometry_checksums(path, &bytes[..bytes.len() - 4]).is_err());
        let mut version_3 = bytes.clone();
        version_3[8..12].copy_from_slice(&3u32.to_le_bytes());
        assert!(decode_geometry_checksums(path, &version_3).is_err());
        // A byte flipped in the second tile's blob is caught before decoding, naming it.
        let pack_path = Path::new("geometry.pack");
        let read = read_checked_tile_geometry(pack_path, &tiled.tree, &tiled.pack, &checksums).expect("reads");
        assert_eq!(read.len(), 2);
        let mut pack = tiled.pack.clone();
        let second = &tiled.tree.tiles[1];
        pack[(second.geometry_offset + second.geometry_len / 2) as usize] ^= 0x10;
        match read_checked_tile_geometry(pack_path, &tiled.tree, &pack, &checksums) {
            Err(DatasetError::Checksum { what, offset, .. }) => {
                assert_eq!(what, "tile 1's geometry");
                assert_eq!(offset, second.geometry_offset);
            }
            other => panic!("expected a checksum error, got {other:?}"),
        }
        // One checksum short is refused.
        assert!(read_checked_tile_geometry(pack_path, &tiled.tree, &tiled.pack, &checksums[..1]).is_err());
    }
}
