//! `tiles.bin` of dataset format 4 (docs/DATASET.md): the tile tree, read whole at open.
//!
//! Layout (little-endian), version 4:
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 8 | magic `CSTILES\0` |
//! | 8 | 4 | version (4) |
//! | 12 | 4 | flags (0) |
//! | 16 | 8 | write id |
//! | 24 | 8 | tile count T |
//! | 32 | 4 | first root tile |
//! | 36 | 4 | root count |
//! | 40 | 4 | CRS text length C in bytes (0: a local frame), at most [`MAX_CRS_BYTES`] |
//! | 44 | 4 | CRC-32 of bytes 0..44 and of everything after byte 48 |
//! | 48 | 24 | the scene's origin, 3 × f64: the frame camera paths and scene bounds are given in |
//! | 72 | 8 | mesh count M |
//! | 80 | C | CRS text, UTF-8, then zero bytes to a multiple of 8 |
//! | … | 128·T | tile records ([`TILE_RECORD_BYTES`]) |
//! | … | 4·M | mesh ids, u32: each tile's meshes, a tile after another; a permutation of `0..M` |
//!
//! Mesh ids are the scene's own (a texture's meshes, an atlas tree's nodes and every per-mesh
//! table keep meaning what they meant before the scene was cut into tiles), so a tile lists
//! its meshes' ids rather than owning a range of them.
//!
//! A tile record:
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 24 | origin, 3 × f64: absolute |
//! | 24 | 24 | bounds, min then max, 6 × f32 relative to the origin (its geometry's and its descendants') |
//! | 48 | 4 | geometric error, f32 metres (3D Tiles' meaning) |
//! | 52 | 1 | refine: 0 replace, 1 add |
//! | 53 | 1 | encoding of its geometry: 0 raw (the only one version 4 reads) |
//! | 54 | 2 | reserved (0) |
//! | 56 | 8 | first child, child count (2 × u32); children are contiguous and follow their parent |
//! | 64 | 16 | geometry offset and length in `geometry.pack` (2 × u64) |
//! | 80 | 8 | vertex count, index count (2 × u32) |
//! | 88 | 8 | first mesh, mesh count (2 × u32): its meshes' ids are the mesh id table's entries `first..first + count` |
//! | 96 | 8 | first texture, texture count (2 × u32) |
//! | 104 | 24 | reserved (0) |

use std::ops::Range;
use std::path::Path;

use super::crs::{Crs, MAX_CRS_BYTES};
use super::error::DatasetError;
use super::io_util::{check_versioned_prefix, f32_at, f64_at, u32_at, u64_at};

const MAGIC: &[u8; 8] = b"CSTILES\0";
/// The format version that introduces tiles.
pub const TILES_VERSION: u32 = 4;
/// Bytes of one tile record.
pub const TILE_RECORD_BYTES: usize = 128;
const HEADER_BYTES: usize = 80;
/// How far a tile's origin may lie from the scene's on any axis, metres: 2^24.
pub const MAX_TILE_OFFSET_M: f64 = 16_777_216.0;

/// How a tile's children refine it (3D Tiles' `refine`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Refine {
    /// The children replace the tile's own geometry (a proxy of them).
    Replace,
    /// The children's geometry joins the tile's.
    Add,
}

/// One tile of the tree.
#[derive(Clone, Debug, PartialEq)]
pub struct TileRecord {
    /// Absolute position of the tile's origin; its positions are `f32` relative to it.
    pub origin: [f64; 3],
    /// Least corner of its bounds (its geometry's and its descendants'), relative to the origin.
    pub bounds_min: [f32; 3],
    /// Greatest corner of its bounds, relative to the origin.
    pub bounds_max: [f32; 3],
    /// Metres of error in showing this tile instead of its children (0 for leaves).
    pub geometric_error: f32,
    /// How its children refine it.
    pub refine: Refine,
    /// Its first child; its children are `first_child..first_child + child_count`, all after it.
    pub first_child: u32,
    /// Its children's count (0 for a leaf).
    pub child_count: u32,
    /// Where its geometry starts in `geometry.pack`.
    pub geometry_offset: u64,
    /// Its geometry's bytes.
    pub geometry_len: u64,
    /// Vertices of its geometry.
    pub vertex_count: u32,
    /// Indices of its geometry.
    pub index_count: u32,
    /// Where its meshes' ids start in [`TileTree::mesh_ids`]; its meshes are
    /// `mesh_ids[first_mesh..first_mesh + mesh_count]`.
    pub first_mesh: u32,
    /// Its meshes' count.
    pub mesh_count: u32,
    /// The first texture its meshes use; they use `first_texture..first_texture + texture_count`.
    pub first_texture: u32,
    /// Textures its meshes use.
    pub texture_count: u32,
}

/// What the rest of the dataset says a tile tree may reference.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileLimits {
    /// Bytes of `geometry.pack`.
    pub geometry_len: u64,
    /// Textures of the texture table.
    pub texture_count: u32,
}

/// The tile tree of a dataset.
#[derive(Clone, Debug, PartialEq)]
pub struct TileTree {
    /// The write that made it (the manifest's).
    pub write_id: u64,
    /// The frame tile origins are given in (`None`: a local frame).
    pub crs: Option<Crs>,
    /// The scene's origin (absolute): scene coordinates, in which camera paths and the
    /// scene's bounds are given, are relative to it.
    pub origin: [f64; 3],
    /// The root tiles: `roots.start..roots.end`.
    pub roots: Range<u32>,
    /// Every tile, parents before their children.
    pub tiles: Vec<TileRecord>,
    /// The scene's mesh ids of every tile's meshes, a tile's after another's: a permutation
    /// of `0..` the mesh count.
    pub mesh_ids: Vec<u32>,
}

fn corrupt(path: &Path, offset: usize, what: String) -> DatasetError {
    DatasetError::Corrupt {
        path: path.to_path_buf(),
        offset: offset as u64,
        what,
    }
}

/// `start..start + count` as a range, or `None` where it overflows `u32`.
fn span(start: u32, count: u32) -> Option<Range<u32>> {
    Some(start..start.checked_add(count)?)
}

impl TileTree {
    /// The CRS record's bytes (its text padded to a multiple of 8).
    fn crs_len(&self) -> usize {
        self.crs.as_ref().map_or(0, |c| c.as_str().len().next_multiple_of(8))
    }

    /// Byte offset of tile `index`'s record in the file.
    fn record_offset(&self, index: usize) -> usize {
        HEADER_BYTES + self.crs_len() + index * TILE_RECORD_BYTES
    }

    /// The file's bytes, after [`validate`](Self::validate) with `limits`.
    pub fn encode(&self, path: &Path, limits: TileLimits) -> Result<Vec<u8>, DatasetError> {
        self.validate(path, limits)?;
        let crs_text = self.crs.as_ref().map_or("", Crs::as_str).as_bytes();
        let mut out = Vec::with_capacity(self.record_offset(self.tiles.len()));
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&TILES_VERSION.to_le_bytes());
        out.extend_from_slice(&0u32.to_le_bytes());
        out.extend_from_slice(&self.write_id.to_le_bytes());
        out.extend_from_slice(&(self.tiles.len() as u64).to_le_bytes());
        out.extend_from_slice(&self.roots.start.to_le_bytes());
        out.extend_from_slice(&(self.roots.end - self.roots.start).to_le_bytes());
        out.extend_from_slice(&(crs_text.len() as u32).to_le_bytes());
        out.extend_from_slice(&0u32.to_le_bytes());
        for v in self.origin {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(&(self.mesh_ids.len() as u64).to_le_bytes());
        out.extend_from_slice(crs_text);
        out.resize(HEADER_BYTES + self.crs_len(), 0);
        for tile in &self.tiles {
            let start = out.len();
            for v in tile.origin {
                out.extend_from_slice(&v.to_le_bytes());
            }
            for v in tile.bounds_min.iter().chain(&tile.bounds_max) {
                out.extend_from_slice(&v.to_le_bytes());
            }
            out.extend_from_slice(&tile.geometric_error.to_le_bytes());
            out.push(match tile.refine {
                Refine::Replace => 0,
                Refine::Add => 1,
            });
            out.push(0); // raw geometry
            out.extend_from_slice(&[0, 0]);
            for v in [tile.first_child, tile.child_count] {
                out.extend_from_slice(&v.to_le_bytes());
            }
            for v in [tile.geometry_offset, tile.geometry_len] {
                out.extend_from_slice(&v.to_le_bytes());
            }
            for v in [
                tile.vertex_count,
                tile.index_count,
                tile.first_mesh,
                tile.mesh_count,
                tile.first_texture,
                tile.texture_count,
            ] {
                out.extend_from_slice(&v.to_le_bytes());
            }
            out.resize(start + TILE_RECORD_BYTES, 0);
        }
        for id in &self.mesh_ids {
            out.extend_from_slice(&id.to_le_bytes());
        }
        let crc = crc_of(&out);
        out[44..48].copy_from_slice(&crc.to_le_bytes());
        Ok(out)
    }

    /// Reads and checks the file at `path` whose bytes are `bytes`: header, size, checksum,
    /// every record ([`validate`](Self::validate) with `limits`). Every error names the
    /// file, the byte and, for a record, the tile.
    pub fn decode(path: &Path, bytes: &[u8], limits: TileLimits) -> Result<Self, DatasetError> {
        // Length, magic, version and the zero flags word, as every file of the dataset.
        check_versioned_prefix(path, bytes, MAGIC, HEADER_BYTES, TILES_VERSION)?;
        let write_id = u64_at(bytes, 16);
        let count = u64_at(bytes, 24);
        let (first_root, root_count) = (u32_at(bytes, 32), u32_at(bytes, 36));
        let crs_len = u32_at(bytes, 40) as usize;
        if crs_len > MAX_CRS_BYTES {
            return Err(corrupt(
                path,
                40,
                format!("CRS text of {crs_len} bytes, at most {MAX_CRS_BYTES} are allowed"),
            ));
        }
        let origin = [0, 1, 2].map(|i| f64_at(bytes, 48 + i * 8));
        let mesh_count = u64_at(bytes, 72);
        let records_at = HEADER_BYTES + crs_len.next_multiple_of(8);
        let ids_at = count
            .checked_mul(TILE_RECORD_BYTES as u64)
            .and_then(|b| b.checked_add(records_at as u64))
            .ok_or_else(|| corrupt(path, 24, format!("tile count {count} is absurd")))?;
        let end = mesh_count
            .checked_mul(4)
            .and_then(|b| b.checked_add(ids_at))
            .ok_or_else(|| corrupt(path, 72, format!("mesh count {mesh_count} is absurd")))?;
        if end != bytes.len() as u64 {
            return Err(DatasetError::truncated(
                path,
                format!("{count} tile records"),
                records_at as u64,
                end,
                bytes.len() as u64,
            ));
        }
        let (stored, computed) = (u32_at(bytes, 44), crc_of(bytes));
        if stored != computed {
            return Err(DatasetError::Checksum {
                path: path.to_path_buf(),
                what: "the tile table (header and records)".into(),
                offset: 0,
                end,
                stored,
                computed,
            });
        }
        if let Some(at) = (HEADER_BYTES + crs_len..records_at).find(|&at| bytes[at] != 0) {
            return Err(corrupt(path, at, "the CRS record's padding is not zero".into()));
        }
        let crs = match crs_len {
            0 => None,
            n => {
                let text = std::str::from_utf8(&bytes[HEADER_BYTES..HEADER_BYTES + n])
                    .map_err(|e| corrupt(path, HEADER_BYTES, format!("the CRS text is not UTF-8: {e}")))?;
                Some(Crs::parse(text).map_err(|e| corrupt(path, HEADER_BYTES, format!("the CRS: {e}")))?)
            }
        };
        let roots = span(first_root, root_count)
            .ok_or_else(|| corrupt(path, 32, format!("roots {first_root} + {root_count} overflow")))?;
        let mut tiles = Vec::with_capacity(count as usize);
        for index in 0..count as usize {
            let at = records_at + index * TILE_RECORD_BYTES;
            let r = &bytes[at..at + TILE_RECORD_BYTES];
            let refine = match r[52] {
                0 => Refine::Replace,
                1 => Refine::Add,
                other => {
                    return Err(corrupt(
                        path,
                        at + 52,
                        format!("tile {index}: refine {other} (0 replace, 1 add)"),
                    ));
                }
            };
            if r[53] != 0 {
                return Err(corrupt(
                    path,
                    at + 53,
                    format!(
                        "tile {index}: geometry encoding {} (version 4 reads raw geometry, 0, only)",
                        r[53]
                    ),
                ));
            }
            if r[54..56] != [0, 0] || r[104..].iter().any(|&b| b != 0) {
                return Err(corrupt(
                    path,
                    at + 54,
                    format!("tile {index}: reserved bytes are not 0"),
                ));
            }
            tiles.push(TileRecord {
                origin: [0, 1, 2].map(|i| f64_at(r, i * 8)),
                bounds_min: [0, 1, 2].map(|i| f32_at(r, 24 + i * 4)),
                bounds_max: [0, 1, 2].map(|i| f32_at(r, 36 + i * 4)),
                geometric_error: f32_at(r, 48),
                refine,
                first_child: u32_at(r, 56),
                child_count: u32_at(r, 60),
                geometry_offset: u64_at(r, 64),
                geometry_len: u64_at(r, 72),
                vertex_count: u32_at(r, 80),
                index_count: u32_at(r, 84),
                first_mesh: u32_at(r, 88),
                mesh_count: u32_at(r, 92),
                first_texture: u32_at(r, 96),
                texture_count: u32_at(r, 100),
            });
        }
        let ids_at = ids_at as usize;
        let mesh_ids = (0..mesh_count as usize)
            .map(|i| u32_at(bytes, ids_at + 4 * i))
            .collect();
        let tree = TileTree {
            write_id,
            crs,
            origin,
            roots,
            tiles,
            mesh_ids,
        };
        tree.validate(path, limits)?;
        Ok(tree)
    }

    /// Checks what the records claim: finite origins, bounds and errors; the roots and
    /// every child range inside the table, children after their parent and each tile the
    /// child of one parent at most (so the tree has no cycle and nothing hangs off two
    /// branches), roots nobody's child; geometry inside `geometry.pack`; texture ranges
    /// inside the table; mesh ranges that partition the mesh id table, and ids that are a
    /// permutation of `0..` the mesh count.
    pub fn validate(&self, path: &Path, limits: TileLimits) -> Result<(), DatasetError> {
        if !self.origin.iter().all(|v| v.is_finite()) {
            return Err(corrupt(
                path,
                48,
                format!("the scene's origin {:?} is not finite", self.origin),
            ));
        }
        let count = self.tiles.len();
        let tile_count =
            u32::try_from(count).map_err(|_| corrupt(path, 24, format!("{count} tiles, more than a u32 numbers")))?;
        if self.roots.start > self.roots.end || self.roots.end > tile_count {
            return Err(corrupt(
                path,
                32,
                format!("roots {:?} outside the {count} tiles", self.roots),
            ));
        }
        let mut parent = vec![None::<u32>; count];
        let mut meshes: Vec<(u32, u32, usize)> = Vec::with_capacity(count);
        for (index, tile) in self.tiles.iter().enumerate() {
            let at = self.record_offset(index);
            let bad = |offset: usize, what: String| corrupt(path, at + offset, format!("tile {index}: {what}"));
            if !tile.origin.iter().all(|v| v.is_finite()) {
                return Err(bad(0, format!("origin {:?} is not finite", tile.origin)));
            }
            // Within 2^24 m of the scene's origin, positions re-expressed there stay finite
            // `f32`s, and whole-metre offsets stay exact (tiling.rs).
            if (0..3).any(|a| (tile.origin[a] - self.origin[a]).abs() >= MAX_TILE_OFFSET_M) {
                return Err(bad(
                    0,
                    format!(
                        "origin {:?} lies 2^24 m or more from the scene's origin {:?} on an axis",
                        tile.origin, self.origin
                    ),
                ));
            }
            let bounded = (0..3).all(|a| {
                tile.bounds_min[a].is_finite()
                    && tile.bounds_max[a].is_finite()
                    && tile.bounds_min[a] <= tile.bounds_max[a]
            });
            if !bounded {
                return Err(bad(
                    24,
                    format!("bounds {:?}..{:?} are not a box", tile.bounds_min, tile.bounds_max),
                ));
            }
            if !(tile.geometric_error.is_finite() && tile.geometric_error >= 0.0) {
                return Err(bad(
                    48,
                    format!("geometric error {} is not a distance", tile.geometric_error),
                ));
            }
            let children = span(tile.first_child, tile.child_count)
                .filter(|c| c.end <= tile_count && (tile.child_count == 0 || c.start as usize > index))
                .ok_or_else(|| {
                    bad(
                        56,
                        format!(
                            "children {} + {} are not tiles after it (of {count})",
                            tile.first_child, tile.child_count
                        ),
                    )
                })?;
            for child in children {
                if let Some(other) = parent[child as usize].replace(index as u32) {
                    return Err(bad(56, format!("tile {child} is also a child of tile {other}")));
                }
            }
            let geometry_end = tile.geometry_offset.checked_add(tile.geometry_len);
            if geometry_end.is_none_or(|end| end > limits.geometry_len) {
                return Err(bad(
                    64,
                    format!(
                        "geometry bytes {} + {} beyond geometry.pack's {}",
                        tile.geometry_offset, tile.geometry_len, limits.geometry_len
                    ),
                ));
            }
            let textures = span(tile.first_texture, tile.texture_count);
            if textures.is_none_or(|t| t.end > limits.texture_count) {
                return Err(bad(
                    96,
                    format!(
                        "textures {} + {} beyond the table's {}",
                        tile.first_texture, tile.texture_count, limits.texture_count
                    ),
                ));
            }
            if span(tile.first_mesh, tile.mesh_count).is_none() {
                return Err(bad(
                    88,
                    format!("meshes {} + {} overflow", tile.first_mesh, tile.mesh_count),
                ));
            }
            if tile.mesh_count > 0 {
                meshes.push((tile.first_mesh, tile.mesh_count, index));
            }
        }
        // Each tile's geometry is its own: tiles sharing bytes would make a small file
        // decode into any number of copies of a large blob.
        let mut ranges: Vec<(u64, u64, usize)> = self
            .tiles
            .iter()
            .enumerate()
            .filter(|(_, t)| t.geometry_len > 0)
            .map(|(index, t)| (t.geometry_offset, t.geometry_offset + t.geometry_len, index))
            .collect();
        ranges.sort_unstable();
        for pair in ranges.windows(2) {
            let ((_, end, a), (start, _, b)) = (pair[0], pair[1]);
            if start < end {
                return Err(corrupt(
                    path,
                    self.record_offset(b) + 64,
                    format!("tile {b}: geometry from byte {start} overlaps tile {a}'s, which ends at {end}"),
                ));
            }
        }
        for root in self.roots.clone() {
            if let Some(p) = parent[root as usize] {
                return Err(corrupt(
                    path,
                    32,
                    format!("root tile {root} is also a child of tile {p}"),
                ));
            }
        }
        // Every tile hangs from a root: an orphan would never be drawn.
        if let Some(orphan) = (0..tile_count).find(|&t| parent[t as usize].is_none() && !self.roots.contains(&t)) {
            return Err(corrupt(
                path,
                self.record_offset(orphan as usize),
                format!("tile {orphan} is neither a root nor any tile's child"),
            ));
        }
        // Global mesh ids: every tile's range, laid end to end, covers 0.. with no gap.
        meshes.sort_unstable();
        let mut next = 0u32;
        for (first, mesh_count, index) in meshes {
            if first != next {
                return Err(corrupt(
                    path,
                    self.record_offset(index) + 88,
                    format!(
                        "tile {index}: meshes start at {first}, but the ids before end at {next} (ranges must partition the mesh ids)"
                    ),
                ));
            }
            next = first + mesh_count;
        }
        let ids_at = self.record_offset(count);
        if next as usize != self.mesh_ids.len() {
            return Err(corrupt(
                path,
                72,
                format!("{} mesh ids, but the tiles' meshes end at {next}", self.mesh_ids.len()),
            ));
        }
        let mut seen = vec![false; self.mesh_ids.len()];
        for (entry, &id) in self.mesh_ids.iter().enumerate() {
            match seen.get_mut(id as usize) {
                Some(slot) if !*slot => *slot = true,
                Some(_) => return Err(corrupt(path, ids_at + 4 * entry, format!("mesh {id} is listed twice"))),
                None => {
                    return Err(corrupt(
                        path,
                        ids_at + 4 * entry,
                        format!("mesh id {id} is past the {} meshes", self.mesh_ids.len()),
                    ))
                }
            }
        }
        Ok(())
    }

    /// Meshes over all tiles.
    pub fn mesh_count(&self) -> u64 {
        self.mesh_ids.len() as u64
    }
}

/// CRC-32 of a tile table's bytes, its checksum field (44..48) left out.
fn crc_of(bytes: &[u8]) -> u32 {
    let mut hasher = crc32fast::Hasher::new();
    hasher.update(&bytes[..44]);
    hasher.update(&bytes[48.min(bytes.len())..]);
    hasher.finalize()
}

#[cfg(test)]
mod tests {
    use super::*;

    const LIMITS: TileLimits = TileLimits {
        geometry_len: 10_000,
        texture_count: 8,
    };

    fn tile(first_child: u32, child_count: u32, meshes: Range<u32>, geometry: Range<u64>) -> TileRecord {
        TileRecord {
            origin: [1.0e6 + 0.125, 34.0, -2.5e6],
            bounds_min: [-128.0, -1.0, -128.0],
            bounds_max: [128.0, 80.0, 128.0],
            geometric_error: if child_count > 0 { 12.5 } else { 0.0 },
            refine: Refine::Replace,
            first_child,
            child_count,
            geometry_offset: geometry.start,
            geometry_len: geometry.end - geometry.start,
            vertex_count: 40,
            index_count: 60,
            first_mesh: meshes.start,
            mesh_count: meshes.end - meshes.start,
            first_texture: 0,
            texture_count: 2,
        }
    }

    /// A root (a proxy of its two children, meshes 0..1) over two leaves (1..4 and 4..6).
    fn tree() -> TileTree {
        TileTree {
            write_id: 0x1234_5678_9abc_def0,
            crs: Some(Crs::epsg(25833)),
            origin: [1.0e6, 0.0, -2.5e6],
            roots: 0..1,
            tiles: vec![
                tile(1, 2, 0..1, 0..100),
                tile(0, 0, 1..4, 100..400),
                tile(0, 0, 4..6, 400..600),
            ],
            mesh_ids: vec![5, 0, 2, 1, 4, 3],
        }
    }

    fn path() -> &'static Path {
        Path::new("city/write-1/tiles.bin")
    }

    fn message(result: Result<TileTree, DatasetError>) -> String {
        result.expect_err("refused").to_string()
    }

    #[test]
    fn a_tree_round_trips_through_its_bytes() {
        let tree = tree();
        let bytes = tree.encode(path(), LIMITS).expect("valid");
        assert_eq!(bytes.len(), HEADER_BYTES + 16 + 3 * TILE_RECORD_BYTES + 6 * 4);
        let back = TileTree::decode(path(), &bytes, LIMITS).expect("decodes");
        assert_eq!(back, tree);
        assert_eq!(back.mesh_count(), 6);
        let local = TileTree { crs: None, ..tree };
        let bytes = local.encode(path(), LIMITS).expect("valid");
        assert_eq!(TileTree::decode(path(), &bytes, LIMITS).expect("decodes"), local);
    }

    #[test]
    fn damaged_bytes_are_refused_naming_the_file_and_where() {
        let bytes = tree().encode(path(), LIMITS).expect("valid");
        // Every single flipped bit is caught (by the checksum, or before it).
        for at in (0..bytes.len()).step_by(7) {
            let mut bad = bytes.clone();
            bad[at] ^= 0x10;
            let text = message(TileTree::decode(path(), &bad, LIMITS));
            assert!(text.starts_with("city/write-1/tiles.bin:"), "byte {at}: {text}");
        }
        for len in [0, 20, HEADER_BYTES, bytes.len() - 1] {
            let text = message(TileTree::decode(path(), &bytes[..len], LIMITS));
            assert!(text.contains("truncated"), "{len} bytes: {text}");
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert!(message(TileTree::decode(path(), &longer, LIMITS)).contains("truncated"));
        let mut version = bytes;
        version[8] = 3;
        assert!(message(TileTree::decode(path(), &version, LIMITS)).contains("format version 3"));
    }

    type Change = dyn FnOnce(&mut TileTree);

    /// `tree` with `change` applied, encoded without checks and with a fresh checksum, then
    /// decoded: the message.
    fn refused(change: impl FnOnce(&mut TileTree)) -> String {
        let mut tree = tree();
        let bytes = tree.encode(path(), LIMITS).expect("valid");
        change(&mut tree);
        // Re-encode the changed records over the valid bytes, bypassing validation.
        let mut bad = bytes;
        for (index, t) in tree.tiles.iter().enumerate() {
            let at = HEADER_BYTES + 16 + index * TILE_RECORD_BYTES;
            for (i, v) in t.origin.iter().enumerate() {
                bad[at + i * 8..at + i * 8 + 8].copy_from_slice(&v.to_le_bytes());
            }
            for (i, v) in t.bounds_min.iter().chain(&t.bounds_max).enumerate() {
                bad[at + 24 + i * 4..at + 28 + i * 4].copy_from_slice(&v.to_le_bytes());
            }
            bad[at + 48..at + 52].copy_from_slice(&t.geometric_error.to_le_bytes());
            for (i, v) in [t.first_child, t.child_count].iter().enumerate() {
                bad[at + 56 + i * 4..at + 60 + i * 4].copy_from_slice(&v.to_le_bytes());
            }
            bad[at + 64..at + 72].copy_from_slice(&t.geometry_offset.to_le_bytes());
            bad[at + 72..at + 80].copy_from_slice(&t.geometry_len.to_le_bytes());
            for (i, v) in [t.first_mesh, t.mesh_count, t.first_texture, t.texture_count]
                .iter()
                .enumerate()
            {
                bad[at + 88 + i * 4..at + 92 + i * 4].copy_from_slice(&v.to_le_bytes());
            }
        }
        bad[32..36].copy_from_slice(&tree.roots.start.to_le_bytes());
        bad[36..40].copy_from_slice(&(tree.roots.end.wrapping_sub(tree.roots.start)).to_le_bytes());
        bad[48..56].copy_from_slice(&tree.origin[0].to_le_bytes());
        let ids_at = HEADER_BYTES + 16 + tree.tiles.len() * TILE_RECORD_BYTES;
        for (i, id) in tree.mesh_ids.iter().enumerate() {
            bad[ids_at + 4 * i..ids_at + 4 * i + 4].copy_from_slice(&id.to_le_bytes());
        }
        let crc = crc_of(&bad);
        bad[44..48].copy_from_slice(&crc.to_le_bytes());
        message(TileTree::decode(path(), &bad, LIMITS))
    }

    #[test]
    fn impossible_trees_are_refused_naming_the_tile() {
        let cases: Vec<(&str, Box<Change>)> = vec![
            ("tile 1: origin", Box::new(|t| t.tiles[1].origin[0] = f64::NAN)),
            ("tile 2: bounds", Box::new(|t| t.tiles[2].bounds_min[1] = 100.0)),
            (
                "tile 0: geometric error",
                Box::new(|t| t.tiles[0].geometric_error = -1.0),
            ),
            ("tile 0: children 1 + 3", Box::new(|t| t.tiles[0].child_count = 3)),
            ("tile 2: children 0 + 1", Box::new(|t| t.tiles[2].child_count = 1)),
            (
                "also a child of tile 0",
                Box::new(|t| {
                    t.tiles[1].first_child = 2;
                    t.tiles[1].child_count = 1;
                }),
            ),
            (
                "tile 2: geometry bytes 400 + 9700",
                Box::new(|t| t.tiles[2].geometry_len = 9_700),
            ),
            (
                "tile 1: geometry bytes",
                Box::new(|t| t.tiles[1].geometry_offset = u64::MAX),
            ),
            ("tile 1: textures 7 + 2", Box::new(|t| t.tiles[1].first_texture = 7)),
            ("meshes start at 5", Box::new(|t| t.tiles[2].first_mesh = 5)),
            ("meshes start at 3", Box::new(|t| t.tiles[2].first_mesh = 3)),
            (
                "6 mesh ids, but the tiles' meshes end at 5",
                Box::new(|t| t.tiles[2].mesh_count = 1),
            ),
            (
                "tile 2: geometry from byte 300 overlaps tile 1's",
                Box::new(|t| t.tiles[2].geometry_offset = 300),
            ),
            (
                "lies 2^24 m or more from the scene's origin",
                Box::new(|t| t.tiles[1].origin[2] = -2.5e6 - 2.0e7),
            ),
            ("mesh 4 is listed twice", Box::new(|t| t.mesh_ids[0] = 4)),
            ("mesh id 6 is past the 6 meshes", Box::new(|t| t.mesh_ids[5] = 6)),
            ("the scene's origin", Box::new(|t| t.origin[0] = f64::INFINITY)),
            ("roots 0..4", Box::new(|t| t.roots = 0..4)),
            ("root tile 1 is also a child of tile 0", Box::new(|t| t.roots = 0..2)),
            (
                "tile 0 is neither a root nor any tile's child",
                Box::new(|t| t.roots = 0..0),
            ),
            (
                "tile 2 is neither a root nor any tile's child",
                Box::new(|t| t.tiles[0].child_count = 1),
            ),
        ];
        for (expected, change) in cases {
            let text = refused(change);
            assert!(
                text.contains(expected) && text.starts_with("city/write-1/tiles.bin: at offset"),
                "{expected}: {text}"
            );
        }
    }

    #[test]
    fn an_encoding_other_than_raw_is_refused_by_tile() {
        let mut bytes = tree().encode(path(), LIMITS).expect("valid");
        let at = HEADER_BYTES + 16 + 2 * TILE_RECORD_BYTES + 53;
        bytes[at] = 1;
        let crc = crc_of(&bytes);
        bytes[44..48].copy_from_slice(&crc.to_le_bytes());
        let text = message(TileTree::decode(path(), &bytes, LIMITS));
        assert!(text.contains("tile 2: geometry encoding 1"), "{text}");
    }
}
