//! One tile's geometry in `geometry.pack` (dataset format 4, docs/DATASET.md): what a
//! reader fetches with one ranged read.
//!
//! Layout of a raw blob (encoding 0; little-endian):
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 4 | mesh count M |
//! | 4 | 4 | vertex count V |
//! | 8 | 4 | index count I |
//! | 12 | 4 | reserved (0) |
//! | 16 | 20·M | meshes: first vertex, vertex count, first index, index count, texture (5 × u32) |
//! | … | 12·V | positions, 3 × f32 relative to the tile's origin |
//! | … | 12·V | normals, 3 × f32 |
//! | … | 8·V | texture coordinates, 2 × f32 |
//! | … | 4·I | indices, u32, relative to the mesh's first vertex |
//!
//! Mesh bounds are not stored: they are computed from the positions on read, so they
//! cannot disagree with them.

use std::path::Path;

use super::error::DatasetError;
use super::io_util::{f32_at, u32_at};
use super::scene::{Aabb, Mesh, Scene};
use super::tiles::TileRecord;
use super::tiling::positions_relative_to;

const HEADER_BYTES: usize = 16;
const MESH_BYTES: usize = 20;

/// A tile's meshes and vertices, positions relative to the tile's origin.
#[derive(Clone, Debug, PartialEq)]
pub struct TileGeometry {
    /// Its meshes; `first_vertex` and `first_index` index this tile's arrays, `texture`
    /// the dataset's texture table.
    pub meshes: Vec<Mesh>,
    /// Positions relative to the tile's origin, metres; +y is up.
    pub positions: Vec<[f32; 3]>,
    /// Unit normals.
    pub normals: Vec<[f32; 3]>,
    /// Texture coordinates; outside `[0, 1]` they repeat.
    pub uvs: Vec<[f32; 2]>,
    /// Triangle-list indices, relative to each mesh's first vertex.
    pub indices: Vec<u32>,
}

impl TileGeometry {
    /// The meshes `meshes` of `scene` (in that order) with their positions relative to
    /// `origin` (absolute), computed in `f64`.
    pub fn from_scene(scene: &Scene, meshes: &[u32], origin: [f64; 3]) -> Result<Self, DatasetError> {
        let mut tile = TileGeometry {
            meshes: Vec::with_capacity(meshes.len()),
            positions: Vec::new(),
            normals: Vec::new(),
            uvs: Vec::new(),
            indices: Vec::new(),
        };
        for &id in meshes {
            let mesh = scene
                .meshes
                .get(id as usize)
                .ok_or_else(|| DatasetError::InvalidInput(format!("mesh {id} is not in the scene")))?;
            let (fv, vc) = (mesh.first_vertex as usize, mesh.vertex_count as usize);
            let (fi, ic) = (mesh.first_index as usize, mesh.index_count as usize);
            let too_big = || DatasetError::InvalidInput("a tile exceeds 2^32 vertices or indices".into());
            let positions = positions_relative_to(scene, id, origin);
            let mut bounds = Aabb::EMPTY;
            positions.iter().for_each(|p| bounds.extend(*p));
            tile.meshes.push(Mesh {
                first_vertex: u32::try_from(tile.positions.len()).map_err(|_| too_big())?,
                vertex_count: mesh.vertex_count,
                first_index: u32::try_from(tile.indices.len()).map_err(|_| too_big())?,
                index_count: mesh.index_count,
                texture: mesh.texture,
                bounds,
                origin: 0,
            });
            tile.positions.extend(positions);
            tile.normals.extend_from_slice(&scene.normals[fv..fv + vc]);
            tile.uvs.extend_from_slice(&scene.uvs[fv..fv + vc]);
            tile.indices.extend_from_slice(&scene.indices[fi..fi + ic]);
        }
        Ok(tile)
    }

    /// The blob's bytes (encoding 0); refused past 2^32 meshes, vertices or indices.
    pub fn encode(&self) -> Result<Vec<u8>, DatasetError> {
        let v = self.positions.len();
        let mut out =
            Vec::with_capacity(HEADER_BYTES + MESH_BYTES * self.meshes.len() + 32 * v + 4 * self.indices.len());
        for n in [self.meshes.len(), v, self.indices.len(), 0] {
            let n = u32::try_from(n)
                .map_err(|_| DatasetError::InvalidInput(format!("a tile of {n} meshes, vertices or indices")))?;
            out.extend_from_slice(&n.to_le_bytes());
        }
        for m in &self.meshes {
            for x in [m.first_vertex, m.vertex_count, m.first_index, m.index_count, m.texture] {
                out.extend_from_slice(&x.to_le_bytes());
            }
        }
        let floats = self
            .positions
            .iter()
            .flatten()
            .chain(self.normals.iter().flatten())
            .chain(self.uvs.iter().flatten());
        for x in floats {
            out.extend_from_slice(&x.to_le_bytes());
        }
        for x in &self.indices {
            out.extend_from_slice(&x.to_le_bytes());
        }
        Ok(out)
    }

    /// Decodes tile `tile`'s blob `bytes` read from `path` (`geometry.pack`, the blob at
    /// `record.geometry_offset`) and checks it against its record: counts, textures in the
    /// record's range, finite attributes, mesh ranges inside the arrays, whole triangles,
    /// indices inside their mesh. Errors name the file, the byte and the tile.
    pub fn decode(path: &Path, tile: usize, record: &TileRecord, bytes: &[u8]) -> Result<Self, DatasetError> {
        let base = record.geometry_offset;
        let bad = |offset: usize, what: String| DatasetError::Corrupt {
            path: path.to_path_buf(),
            offset: base + offset as u64,
            what: format!("tile {tile}'s geometry: {what}"),
        };
        if bytes.len() < HEADER_BYTES {
            return Err(DatasetError::truncated(
                path,
                format!("tile {tile}'s geometry header"),
                base,
                base + HEADER_BYTES as u64,
                base + bytes.len() as u64,
            ));
        }
        let (m, v, i) = (u32_at(bytes, 0), u32_at(bytes, 4), u32_at(bytes, 8));
        if u32_at(bytes, 12) != 0 {
            return Err(bad(12, "reserved word is not 0".into()));
        }
        if (m, v, i) != (record.mesh_count, record.vertex_count, record.index_count) {
            return Err(bad(
                0,
                format!(
                    "{m} meshes, {v} vertices, {i} indices; its record says {}, {}, {}",
                    record.mesh_count, record.vertex_count, record.index_count
                ),
            ));
        }
        let (m, v, i) = (m as usize, v as usize, i as usize);
        let positions_at = HEADER_BYTES + MESH_BYTES * m;
        let (normals_at, uvs_at) = (positions_at + 12 * v, positions_at + 24 * v);
        let indices_at = positions_at + 32 * v;
        let end = indices_at + 4 * i;
        if bytes.len() != end {
            return Err(DatasetError::truncated(
                path,
                format!("tile {tile}'s geometry ({m} meshes, {v} vertices, {i} indices)"),
                base,
                base + end as u64,
                base + bytes.len() as u64,
            ));
        }
        let read_floats = |at: usize, count: usize, what: &str| -> Result<Vec<f32>, DatasetError> {
            (0..count)
                .map(|k| {
                    let x = f32_at(bytes, at + 4 * k);
                    if x.is_finite() {
                        Ok(x)
                    } else {
                        Err(bad(at + 4 * k, format!("{what} {x} is not finite")))
                    }
                })
                .collect()
        };
        let triples = |f: Vec<f32>| f.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect::<Vec<_>>();
        let positions = triples(read_floats(positions_at, 3 * v, "a position")?);
        let normals = triples(read_floats(normals_at, 3 * v, "a normal")?);
        let uvs: Vec<[f32; 2]> = read_floats(uvs_at, 2 * v, "a texture coordinate")?
            .chunks_exact(2)
            .map(|c| [c[0], c[1]])
            .collect();
        let indices: Vec<u32> = (0..i).map(|k| u32_at(bytes, indices_at + 4 * k)).collect();
        let textures =
            u64::from(record.first_texture)..u64::from(record.first_texture) + u64::from(record.texture_count);
        let mut meshes = Vec::with_capacity(m);
        let (mut next_vertex, mut next_index) = (0u64, 0u64);
        for k in 0..m {
            let at = HEADER_BYTES + MESH_BYTES * k;
            let [first_vertex, vertex_count, first_index, index_count, texture] =
                [0, 4, 8, 12, 16].map(|o| u32_at(bytes, at + o));
            // Meshes lie end to end in the arrays, as written: each vertex and index is
            // checked once, whatever a hostile blob claims.
            let vertices = u64::from(first_vertex)..u64::from(first_vertex) + u64::from(vertex_count);
            if vertices.start != next_vertex || vertices.end > v as u64 {
                return Err(bad(
                    at,
                    format!("mesh {k}: vertices {vertices:?}, expected to start at {next_vertex} within its {v}"),
                ));
            }
            let range = u64::from(first_index)..u64::from(first_index) + u64::from(index_count);
            if range.start != next_index || range.end > i as u64 || index_count % 3 != 0 {
                return Err(bad(
                    at + 8,
                    format!("mesh {k}: indices {range:?} are not whole triangles from {next_index} within its {i}"),
                ));
            }
            (next_vertex, next_index) = (vertices.end, range.end);
            if !textures.contains(&u64::from(texture)) {
                return Err(bad(
                    at + 16,
                    format!("mesh {k}: texture {texture} outside the tile's textures {textures:?}"),
                ));
            }
            for at_index in range.clone() {
                let index = indices[at_index as usize];
                if index >= vertex_count {
                    return Err(bad(
                        indices_at + 4 * at_index as usize,
                        format!("mesh {k}: index {index} beyond its {vertex_count} vertices"),
                    ));
                }
            }
            let mut bounds = Aabb::EMPTY;
            positions[vertices.start as usize..vertices.end as usize]
                .iter()
                .for_each(|p| bounds.extend(*p));
            meshes.push(Mesh {
                first_vertex,
                vertex_count,
                first_index,
                index_count,
                texture,
                bounds,
                origin: 0,
            });
        }
        if (next_vertex, next_index) != (v as u64, i as u64) {
            return Err(bad(
                0,
                format!("its meshes cover {next_vertex} of {v} vertices and {next_index} of {i} indices"),
            ));
        }
        Ok(TileGeometry {
            meshes,
            positions,
            normals,
            uvs,
            indices,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tiles::Refine;

    /// Two meshes of a scene 1,000 km out: a triangle of texture 3 and a quad of texture 4.
    fn scene() -> Scene {
        let mut scene = Scene::new([1.0e6, 0.0, -1.0e6]);
        let n = [[0.0, 1.0, 0.0]; 4];
        scene
            .push_mesh(
                3,
                &[[1.0, 0.0, 1.0], [2.0, 0.0, 1.0], [1.0, 0.0, 2.0]],
                &n[..3],
                &[[0.0; 2]; 3],
                &[0, 1, 2],
            )
            .expect("valid");
        scene
            .push_mesh(
                4,
                &[[5.0, 1.0, 5.0], [6.0, 1.0, 5.0], [6.0, 1.0, 6.0], [5.0, 1.0, 6.0]],
                &n,
                &[[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]],
                &[0, 1, 2, 0, 2, 3],
            )
            .expect("valid");
        scene
    }

    fn record(geometry: &TileGeometry, len: usize) -> TileRecord {
        TileRecord {
            origin: [1.0e6 + 3.5, 0.5, -1.0e6 + 3.5],
            bounds_min: [-3.0; 3],
            bounds_max: [3.0; 3],
            geometric_error: 0.0,
            refine: Refine::Replace,
            first_child: 0,
            child_count: 0,
            geometry_offset: 4096,
            geometry_len: len as u64,
            vertex_count: geometry.positions.len() as u32,
            index_count: geometry.indices.len() as u32,
            first_mesh: 0,
            mesh_count: geometry.meshes.len() as u32,
            first_texture: 3,
            texture_count: 2,
        }
    }

    fn path() -> &'static Path {
        Path::new("city/write-1/geometry.pack")
    }

    #[test]
    fn a_tile_round_trips_with_positions_relative_to_its_origin() {
        let scene = scene();
        let origin = [1.0e6 + 3.5, 0.5, -1.0e6 + 3.5];
        // In reverse order: a tile keeps the order it is given.
        let tile = TileGeometry::from_scene(&scene, &[1, 0], origin).expect("meshes exist");
        assert_eq!(tile.meshes[0].texture, 4);
        assert_eq!(tile.positions[0], [1.5, 0.5, 1.5]);
        assert_eq!(tile.meshes[1].first_vertex, 4);
        assert_eq!(tile.meshes[1].bounds.min, [-2.5, -0.5, -2.5]);
        let bytes = tile.encode().expect("encodes");
        assert_eq!(bytes.len(), 16 + 2 * 20 + 7 * 32 + 9 * 4);
        let back = TileGeometry::decode(path(), 7, &record(&tile, bytes.len()), &bytes).expect("decodes");
        assert_eq!(back, tile);
    }

    #[test]
    fn a_damaged_tile_is_refused_naming_the_tile_and_byte() {
        let tile = TileGeometry::from_scene(&scene(), &[0, 1], [1.0e6 + 3.5, 0.5, -1.0e6 + 3.5]).expect("exist");
        let bytes = tile.encode().expect("encodes");
        let good = record(&tile, bytes.len());
        let refused = |bytes: &[u8], record: &TileRecord| {
            TileGeometry::decode(path(), 7, record, bytes)
                .expect_err("refused")
                .to_string()
        };
        let with = |at: usize, value: u32| {
            let mut b = bytes.clone();
            b[at..at + 4].copy_from_slice(&value.to_le_bytes());
            b
        };
        let positions_at = 16 + 40;
        let indices_at = positions_at + 7 * 32;
        for (bytes, record, expected) in [
            (with(4, 8), good.clone(), "8 vertices"),
            (with(16 + 20 + 16, 9), good.clone(), "mesh 1: texture 9 outside"),
            (with(16 + 4, 30), good.clone(), "mesh 0: vertices 0..30"),
            (
                with(16 + 12, 4),
                good.clone(),
                "mesh 0: indices 0..4 are not whole triangles",
            ),
            (
                with(16 + 20, 0),
                good.clone(),
                "mesh 1: vertices 0..4, expected to start at 3",
            ),
            (
                with(16 + 20 + 8, 0),
                good.clone(),
                "mesh 1: indices 0..6 are not whole triangles from 3",
            ),
            (
                with(indices_at + 4 * 5, 4),
                good.clone(),
                "mesh 1: index 4 beyond its 4 vertices",
            ),
            (
                with(positions_at + 8, f32::NAN.to_bits()),
                good.clone(),
                "a position NaN",
            ),
            (bytes[..bytes.len() - 1].to_vec(), good.clone(), "truncated"),
            (
                bytes.clone(),
                TileRecord {
                    index_count: 6,
                    ..good.clone()
                },
                "its record says",
            ),
        ] {
            let text = refused(&bytes, &record);
            assert!(
                text.contains(expected) && text.contains("geometry.pack") && text.contains("tile 7"),
                "{expected}: {text}"
            );
        }
    }
}
