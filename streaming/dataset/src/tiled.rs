//! A scene cut into tiles (dataset format 4, docs/FORMAT4.md): the tile table and
//! `geometry.pack` that `upgrade` and the writers will write, and the tiles read back. Not
//! yet written by any tool.
//!
//! The tree is flat for now: every leaf of [`leaf_tiles`] is a root, with no inner tiles
//! above them. The quadtree of inner tiles and their proxies (issue 62's levels of detail)
//! slot in above the same leaves.

use std::path::Path;

use super::colormap::u32_records;
use super::error::DatasetError;
use super::io_util::{decode_table, encode_table_of_version};
use super::scene::{Aabb, Scene};
use super::tile_geometry::TileGeometry;
use super::tiles::{Refine, TileLimits, TileRecord, TileTree, TILES_VERSION};
use super::tiling::leaf_tiles;

/// A scene as tiles: the table, the pack of their geometry, and where each mesh went.
#[derive(Clone, Debug, PartialEq)]
pub struct TiledScene {
    /// The tile table.
    pub tree: TileTree,
    /// `geometry.pack`'s bytes: each tile's blob at its record's offset.
    pub pack: Vec<u8>,
    /// For each global mesh id of the tiles, the scene's mesh it came from: meshes are
    /// renumbered so that each tile's are contiguous.
    pub source_mesh: Vec<u32>,
}

impl TiledScene {
    /// Cuts `scene` into its leaf tiles ([`leaf_tiles`]), every one a root.
    pub fn of(scene: &Scene, write_id: u64) -> Result<Self, DatasetError> {
        let leaves = leaf_tiles(scene);
        let mut tiles = Vec::with_capacity(leaves.len());
        let mut pack = Vec::new();
        let mut source_mesh = Vec::with_capacity(scene.meshes.len());
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
                first_mesh: u32::try_from(source_mesh.len()).map_err(|_| too_big())?,
                mesh_count: u32::try_from(leaf.meshes.len()).map_err(|_| too_big())?,
                first_texture: if first_texture == u32::MAX { 0 } else { first_texture },
                texture_count: texture_end.saturating_sub(first_texture.min(texture_end)),
            });
            pack.extend_from_slice(&blob);
            source_mesh.extend_from_slice(&leaf.meshes);
        }
        let roots =
            0..u32::try_from(tiles.len()).map_err(|_| DatasetError::InvalidInput("more than 2^32 tiles".into()))?;
        Ok(TiledScene {
            tree: TileTree {
                write_id,
                crs: scene.crs.clone(),
                roots,
                tiles,
            },
            pack,
            source_mesh,
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

/// Every tile's geometry read back from `pack` (the bytes of `path`), checked against its
/// record.
pub fn read_tile_geometry(path: &Path, tree: &TileTree, pack: &[u8]) -> Result<Vec<TileGeometry>, DatasetError> {
    tree.tiles
        .iter()
        .enumerate()
        .map(|(index, record)| TileGeometry::decode(path, index, record, tile_blob(path, index, record, pack)?))
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
        // position comes back within a micrometre, each mesh in one tile, ids renumbered.
        for origin in [[0.0, 0.0, 0.0], [1.0e6, 0.0, -1.0e6]] {
            let mut scene = Scene::new(origin);
            push_quad(&mut scene, [5.0e5, 0.0, 10.0], [5.0e5 + 20.0, 15.0, 30.0], 2);
            push_quad(&mut scene, [10.0, 0.0, 10.0], [40.0, 8.0, 25.0], 0);
            push_quad(&mut scene, [5.0e5 + 30.0, 0.0, 12.0], [5.0e5 + 50.0, 9.0, 20.0], 1);
            push_quad(&mut scene, [-300.0, 0.0, 900.0], [-280.0, 3.0, 920.0], 2);
            let tiled = TiledScene::of(&scene, 9).expect("tiles");
            assert_eq!(tiled.tree.tiles.len(), 3);
            let mut sorted = tiled.source_mesh.clone();
            sorted.sort_unstable();
            assert_eq!(sorted, vec![0, 1, 2, 3]);
            let path = Path::new("tiles.bin");
            let bytes = tiled.tree.encode(path, tiled.limits(3)).expect("valid");
            let tree = TileTree::decode(path, &bytes, tiled.limits(3)).expect("decodes");
            let geometry = read_tile_geometry(Path::new("geometry.pack"), &tree, &tiled.pack).expect("reads");
            for (record, tile) in tree.tiles.iter().zip(&geometry) {
                for (k, mesh) in tile.meshes.iter().enumerate() {
                    let source = tiled.source_mesh[(record.first_mesh as usize) + k] as usize;
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
