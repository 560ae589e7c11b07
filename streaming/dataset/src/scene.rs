//! The scene a dataset holds (meshes and their geometry, in one frame), and `scene.bin`,
//! the file formats 1 to 3 held it in (read by `citystream upgrade`; version 4 stores the
//! scene in tiles, `tiled.rs`).
//!
//! `scene.bin`'s layout (little-endian), version 3:
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 8 | magic `CSSCENE\0` |
//! | 8 | 4 | version |
//! | 12 | 4 | flags (0) |
//! | 16 | 8 | write id |
//! | 24 | 8 | mesh count M |
//! | 32 | 8 | vertex count V |
//! | 40 | 8 | index count I |
//! | 48 | 24 | origin, 3 × f64 |
//! | 72 | 24 | scene bounds, min then max, 6 × f32 relative to the origin |
//! | 96 | 4 | CRC-32 of bytes 0..96 and of everything after the header |
//! | 100 | 4 | reserved (0) |
//! | 104 | 4 | CRS text length C in bytes (0: no CRS), at most [`MAX_CRS_BYTES`] |
//! | 108 | C | CRS text, UTF-8 (`EPSG:<code>` or WKT), then zero bytes to a multiple of 4 |
//! | 108 + ⌈C/4⌉·4 | 44·M | meshes: first vertex, vertex count, first index, index count, texture (5 × u32), bounds (6 × f32) |
//! | … | 12·V | positions, 3 × f32 relative to the origin |
//! | … | 12·V | normals, 3 × f32 |
//! | … | 8·V | texture coordinates, 2 × f32 |
//! | … | 4·I | indices, u32, relative to the mesh's first vertex |
//!
//! Version 2 had no CRS record (meshes at 104); version 1 a 96-byte header.

use std::path::Path;

use super::crs::{Crs, MAX_CRS_BYTES};
use super::error::DatasetError;
use super::io_util::{
    check_versioned_prefix, expect_end, f32_at, f64_at, header_and_body_crc, header_prefix, read_all, u32_at, u64_at,
};

const MAGIC: &[u8; 8] = b"CSSCENE\0";
const MESH_RECORD_BYTES: usize = 44;

/// Where the header fields of one format version lie.
#[derive(Clone, Copy, Debug)]
pub(crate) struct SceneLayout {
    version: u32,
    /// Header length; the mesh records start here.
    pub(crate) header_len: usize,
    counts_at: usize,
    origin_at: usize,
    bounds_at: usize,
    crc_at: usize,
    crc_covers_header: bool,
    /// Whether the CRS record follows the header (version 3 on).
    crs_record: bool,
}

impl SceneLayout {
    /// Version 3's, the last with a `scene.bin` (written by tests' fixtures and read by
    /// the upgrade).
    pub(crate) const V3: SceneLayout = SceneLayout {
        version: super::io_util::VERSION_3,
        header_len: 104,
        counts_at: 24,
        origin_at: 48,
        bounds_at: 72,
        crc_at: 96,
        crc_covers_header: true,
        crs_record: true,
    };
    /// Version 2: as version 3 without the CRS record.
    pub(crate) const V2: SceneLayout = SceneLayout {
        version: super::io_util::VERSION_2,
        crs_record: false,
        ..Self::V3
    };
    pub(crate) const LEGACY: SceneLayout = SceneLayout {
        version: super::io_util::LEGACY_VERSION,
        header_len: 96,
        counts_at: 16,
        origin_at: 40,
        bounds_at: 64,
        crc_at: 88,
        crc_covers_header: false,
        crs_record: false,
    };

    /// Bytes of the CRS record of a scene in `crs` (none before version 3).
    fn crs_record_len(self, crs: Option<&Crs>) -> usize {
        if self.crs_record {
            4 + crs.map_or(0, |c| c.as_str().len().next_multiple_of(4))
        } else {
            0
        }
    }
}

/// Axis-aligned bounding box in scene coordinates (metres, relative to [`Scene::origin`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    /// Smallest x, y, z.
    pub min: [f32; 3],
    /// Largest x, y, z.
    pub max: [f32; 3],
}

impl Aabb {
    /// An inverted box that any point extends.
    pub const EMPTY: Aabb = Aabb {
        min: [f32::INFINITY; 3],
        max: [f32::NEG_INFINITY; 3],
    };

    /// Grows the box to contain `p`.
    pub fn extend(&mut self, p: [f32; 3]) {
        for ((min, max), v) in self.min.iter_mut().zip(&mut self.max).zip(p) {
            *min = min.min(v);
            *max = max.max(v);
        }
    }

    /// Grows the box to contain `other`.
    pub fn union(&mut self, other: &Aabb) {
        self.extend(other.min);
        self.extend(other.max);
    }

    /// Whether `min <= max` on every axis (false for [`Aabb::EMPTY`]).
    pub fn is_valid(&self) -> bool {
        (0..3).all(|a| self.min[a].is_finite() && self.max[a].is_finite() && self.min[a] <= self.max[a])
    }

    /// Centre point.
    pub fn center(&self) -> [f32; 3] {
        [0, 1, 2].map(|a| 0.5 * (self.min[a] + self.max[a]))
    }

    /// Whether `p` lies inside, allowing `tolerance` on every side.
    pub fn contains(&self, p: [f32; 3], tolerance: f32) -> bool {
        (0..3).all(|a| p[a] >= self.min[a] - tolerance && p[a] <= self.max[a] + tolerance)
    }
}

/// One mesh: a set of triangles sharing one texture (a facade, a roof, a street).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Mesh {
    /// First vertex in the scene's vertex arrays.
    pub first_vertex: u32,
    /// Number of vertices.
    pub vertex_count: u32,
    /// First index in [`Scene::indices`].
    pub first_index: u32,
    /// Number of indices (a multiple of 3); each is relative to `first_vertex`.
    pub index_count: u32,
    /// Texture id (index into the texture table and the colormap).
    pub texture: u32,
    /// Bounds of the mesh's vertices, relative to the scene's origin.
    pub bounds: Aabb,
    /// The origin its positions are relative to: 0, the scene's; `k > 0`,
    /// [`Scene::local_origins`]`[k − 1]` (a mesh far from the scene's origin, whose positions
    /// would round in the scene's `f32` frame; [`Scene::origin_of`]).
    pub origin: u32,
}

/// All geometry of a dataset. Vertex attributes are separate flat arrays (one entry per
/// vertex); every mesh is a range of them plus a range of [`Scene::indices`].
#[derive(Clone, Debug, PartialEq)]
pub struct Scene {
    /// World position of the scene's local origin (x east, y up, z south). Positions are f32
    /// relative to it so that cities far from the world origin keep centimetre precision.
    pub origin: [f64; 3],
    /// The coordinate reference system `origin` (and so every absolute position) is given
    /// in, axes as [`Crs::from_scene`] maps them; `None`: a local frame, not georeferenced.
    pub crs: Option<Crs>,
    /// Union of all mesh bounds.
    pub bounds: Aabb,
    /// The meshes.
    pub meshes: Vec<Mesh>,
    /// Positions relative to `origin`, metres. +y is up.
    pub positions: Vec<[f32; 3]>,
    /// Unit normals.
    pub normals: Vec<[f32; 3]>,
    /// Texture coordinates; (0,0) is the first texel of the first row. Values outside `[0, 1]`
    /// repeat the texture.
    pub uvs: Vec<[f32; 2]>,
    /// Triangle-list indices, relative to each mesh's `first_vertex`.
    pub indices: Vec<u32>,
    /// Absolute origins other than the scene's that meshes' positions are relative to
    /// ([`Mesh::origin`]); empty for a scene in one frame.
    pub local_origins: Vec<[f64; 3]>,
}

impl Scene {
    /// An empty scene at `origin`.
    pub fn new(origin: [f64; 3]) -> Self {
        Self {
            origin,
            crs: None,
            bounds: Aabb::EMPTY,
            meshes: Vec::new(),
            positions: Vec::new(),
            normals: Vec::new(),
            uvs: Vec::new(),
            indices: Vec::new(),
            local_origins: Vec::new(),
        }
    }

    /// The absolute origin `mesh`'s positions are relative to (the scene's, unless it has a
    /// local one; the scene's too for an index past [`Scene::local_origins`], which
    /// validation refuses).
    pub fn origin_of(&self, mesh: &Mesh) -> [f64; 3] {
        match mesh.origin {
            0 => self.origin,
            k => self.local_origins.get(k as usize - 1).copied().unwrap_or(self.origin),
        }
    }

    /// Where `mesh`'s origin lies relative to the scene's (zero for a mesh in the scene's
    /// frame): its positions plus this, in `f64`, are in the scene's frame.
    pub fn offset_of(&self, mesh: &Mesh) -> [f64; 3] {
        let origin = self.origin_of(mesh);
        std::array::from_fn(|a| origin[a] - self.origin[a])
    }

    /// Adds a local origin (absolute) for [`Scene::push_mesh_at`]; returns its index for
    /// [`Mesh::origin`].
    pub fn add_local_origin(&mut self, origin: [f64; 3]) -> Result<u32, DatasetError> {
        if !origin.iter().all(|v| v.is_finite()) {
            return Err(DatasetError::InvalidInput(format!(
                "local origin {origin:?} is not finite"
            )));
        }
        self.local_origins.push(origin);
        u32::try_from(self.local_origins.len())
            .map_err(|_| DatasetError::InvalidInput("more than 2^32 local origins".into()))
    }

    /// Number of triangles of all meshes.
    pub fn triangle_count(&self) -> u64 {
        self.meshes.iter().map(|m| u64::from(m.index_count) / 3).sum()
    }

    /// Appends a mesh from its vertices (positions relative to the scene's origin) and
    /// mesh-local indices, computing its bounds and growing the scene bounds. Returns the
    /// mesh index.
    pub fn push_mesh(
        &mut self,
        texture: u32,
        positions: &[[f32; 3]],
        normals: &[[f32; 3]],
        uvs: &[[f32; 2]],
        indices: &[u32],
    ) -> Result<u32, DatasetError> {
        self.push_mesh_at(0, texture, positions, normals, uvs, indices)
    }

    /// [`Scene::push_mesh`] of a mesh whose positions are relative to origin `origin` (0: the
    /// scene's; else what [`Scene::add_local_origin`] returned). Its bounds are computed in
    /// `f64` in the scene's frame and rounded outwards to `f32`.
    pub fn push_mesh_at(
        &mut self,
        origin: u32,
        texture: u32,
        positions: &[[f32; 3]],
        normals: &[[f32; 3]],
        uvs: &[[f32; 2]],
        indices: &[u32],
    ) -> Result<u32, DatasetError> {
        if origin as usize > self.local_origins.len() {
            return Err(DatasetError::InvalidInput(format!(
                "mesh {} at local origin {origin}, but the scene has {}",
                self.meshes.len(),
                self.local_origins.len()
            )));
        }
        if normals.len() != positions.len() || uvs.len() != positions.len() {
            return Err(DatasetError::InvalidInput(format!(
                "mesh {} has {} positions, {} normals, {} uvs",
                self.meshes.len(),
                positions.len(),
                normals.len(),
                uvs.len()
            )));
        }
        let too_big = || DatasetError::InvalidInput("scene exceeds 2^32 vertices, indices or meshes".into());
        let mesh_index = u32::try_from(self.meshes.len()).map_err(|_| too_big())?;
        let first_vertex = u32::try_from(self.positions.len()).map_err(|_| too_big())?;
        let first_index = u32::try_from(self.indices.len()).map_err(|_| too_big())?;
        let vertex_count = u32::try_from(positions.len()).map_err(|_| too_big())?;
        let index_count = u32::try_from(indices.len()).map_err(|_| too_big())?;
        first_vertex.checked_add(vertex_count).ok_or_else(too_big)?;
        first_index.checked_add(index_count).ok_or_else(too_big)?;
        let offset = self.offset_of(&Mesh { origin, ..EMPTY_MESH });
        let bounds = scene_bounds(positions, offset);
        if !positions.is_empty() {
            self.bounds.union(&bounds);
        }
        self.positions.extend_from_slice(positions);
        self.normals.extend_from_slice(normals);
        self.uvs.extend_from_slice(uvs);
        self.indices.extend_from_slice(indices);
        self.meshes.push(Mesh {
            first_vertex,
            vertex_count,
            first_index,
            index_count,
            texture,
            bounds,
            origin,
        });
        Ok(mesh_index)
    }

    /// The meshes `keep` accepts, in order, with their vertices and indices, as a scene at
    /// the same origin and CRS; each kept mesh's texture id less `texture_base` (a shard of
    /// a dataset holds the textures from `texture_base` on, numbered from 0).
    pub fn part(&self, keep: impl Fn(&Mesh) -> bool, texture_base: u32) -> Result<Scene, DatasetError> {
        let mut part = Scene::new(self.origin);
        part.crs = self.crs.clone();
        // Every local origin, so kept meshes keep their indices.
        part.local_origins = self.local_origins.clone();
        for (m, mesh) in self.meshes.iter().enumerate().filter(|(_, mesh)| keep(mesh)) {
            let texture = mesh.texture.checked_sub(texture_base).ok_or_else(|| {
                DatasetError::InvalidInput(format!(
                    "mesh {m} uses texture {}, below the part's first texture {texture_base}",
                    mesh.texture
                ))
            })?;
            let (positions, normals, uvs, indices) = self.mesh_arrays(m)?;
            part.push_mesh_at(mesh.origin, texture, positions, normals, uvs, indices)?;
        }
        Ok(part)
    }

    /// Appends `other`'s meshes after this scene's, their texture ids plus `texture_offset`:
    /// the scene of datasets joined one after another. Both must have the same origin and
    /// CRS (positions are relative to the origin; re-expressing them would round).
    pub fn append(&mut self, other: &Scene, texture_offset: u32) -> Result<(), DatasetError> {
        if other.origin != self.origin || other.crs != self.crs {
            return Err(DatasetError::InvalidInput(format!(
                "scenes at different origins or CRSs cannot be joined: {:?} {} against {:?} {}",
                self.origin,
                self.crs.as_ref().map_or("(local frame)", |c| c.as_str()),
                other.origin,
                other.crs.as_ref().map_or("(local frame)", |c| c.as_str())
            )));
        }
        // `other`'s local origins after this scene's: its mesh at origin k > 0 is at
        // `base + k` here.
        let base = self.local_origins.len() as u32;
        self.local_origins.extend_from_slice(&other.local_origins);
        for (m, mesh) in other.meshes.iter().enumerate() {
            let texture = mesh
                .texture
                .checked_add(texture_offset)
                .ok_or_else(|| DatasetError::InvalidInput("more than 2^32 textures".into()))?;
            let (positions, normals, uvs, indices) = other.mesh_arrays(m)?;
            let origin = if mesh.origin == 0 { 0 } else { base + mesh.origin };
            self.push_mesh_at(origin, texture, positions, normals, uvs, indices)?;
        }
        Ok(())
    }

    /// Mesh `m`'s positions, normals, UVs and indices; an error where its ranges leave the
    /// arrays (a scene built by hand, never one that was opened).
    #[allow(clippy::type_complexity)] // reason: the four arrays of one mesh, named by the call
    fn mesh_arrays(&self, m: usize) -> Result<(&[[f32; 3]], &[[f32; 3]], &[[f32; 2]], &[u32]), DatasetError> {
        let mesh = &self.meshes[m];
        let vertices = mesh.first_vertex as usize..mesh.first_vertex as usize + mesh.vertex_count as usize;
        let indices = mesh.first_index as usize..mesh.first_index as usize + mesh.index_count as usize;
        let outside =
            || DatasetError::InvalidInput(format!("mesh {m}: vertex or index range outside the scene's arrays"));
        Ok((
            self.positions.get(vertices.clone()).ok_or_else(outside)?,
            self.normals.get(vertices.clone()).ok_or_else(outside)?,
            self.uvs.get(vertices).ok_or_else(outside)?,
            self.indices.get(indices).ok_or_else(outside)?,
        ))
    }

    /// Bytes of the scene file [`encode`](Self::encode) writes (what a writer must find free
    /// on disk), without encoding it.
    pub fn encoded_len(&self) -> u64 {
        let layout = SceneLayout::V3;
        (layout.header_len + self.body_len(layout)) as u64
    }

    fn body_len(&self, layout: SceneLayout) -> usize {
        layout.crs_record_len(self.crs.as_ref())
            + self.meshes.len() * MESH_RECORD_BYTES
            + (self.positions.len() + self.normals.len()) * 12
            + self.uvs.len() * 8
            + self.indices.len() * 4
    }

    /// Encodes the scene file of write `write_id`. Validates first, so a written scene always
    /// reads back.
    pub fn encode(&self, path_for_errors: &Path, write_id: u64) -> Result<Vec<u8>, DatasetError> {
        let layout = SceneLayout::V3;
        if !self.local_origins.is_empty() {
            return Err(DatasetError::InvalidInput(format!(
                "{}: version 3's scene.bin has one origin; this scene has {} local ones",
                path_for_errors.display(),
                self.local_origins.len()
            )));
        }
        self.validate_with(path_for_errors, layout)?;
        let mut body = Vec::with_capacity(self.body_len(layout));
        let crs_text = self.crs.as_ref().map_or("", Crs::as_str).as_bytes();
        body.extend_from_slice(&(crs_text.len() as u32).to_le_bytes());
        body.extend_from_slice(crs_text);
        body.resize(layout.crs_record_len(self.crs.as_ref()), 0);
        for m in &self.meshes {
            for v in [m.first_vertex, m.vertex_count, m.first_index, m.index_count, m.texture] {
                body.extend_from_slice(&v.to_le_bytes());
            }
            for v in m.bounds.min.iter().chain(&m.bounds.max) {
                body.extend_from_slice(&v.to_le_bytes());
            }
        }
        for p in self.positions.iter().chain(&self.normals) {
            for v in p {
                body.extend_from_slice(&v.to_le_bytes());
            }
        }
        for uv in &self.uvs {
            for v in uv {
                body.extend_from_slice(&v.to_le_bytes());
            }
        }
        for i in &self.indices {
            body.extend_from_slice(&i.to_le_bytes());
        }
        let mut out = header_prefix(MAGIC, write_id);
        for count in [self.meshes.len(), self.positions.len(), self.indices.len()] {
            out.extend_from_slice(&(count as u64).to_le_bytes());
        }
        for v in self.origin {
            out.extend_from_slice(&v.to_le_bytes());
        }
        let bounds = self.stored_bounds();
        for v in bounds.min.iter().chain(&bounds.max) {
            out.extend_from_slice(&v.to_le_bytes());
        }
        debug_assert_eq!(out.len(), layout.crc_at);
        let crc = header_and_body_crc(&out, &body);
        out.extend_from_slice(&crc.to_le_bytes());
        out.extend_from_slice(&0u32.to_le_bytes());
        debug_assert_eq!(out.len(), layout.header_len);
        out.extend_from_slice(&body);
        debug_assert_eq!(out.len() as u64, self.encoded_len());
        Ok(out)
    }

    /// Byte offset of mesh `mesh`'s record in a scene file of `layout`.
    pub(crate) fn mesh_record_offset(&self, layout: SceneLayout, mesh: usize) -> u64 {
        (layout.header_len + layout.crs_record_len(self.crs.as_ref()) + mesh * MESH_RECORD_BYTES) as u64
    }

    /// The bounds as stored: all zero for a scene without meshes.
    fn stored_bounds(&self) -> Aabb {
        if self.meshes.is_empty() {
            Aabb {
                min: [0.0; 3],
                max: [0.0; 3],
            }
        } else {
            self.bounds
        }
    }

    /// Reads and validates a scene file (its whole content is under its checksum).
    pub fn read(path: &Path) -> Result<Scene, DatasetError> {
        Ok(Self::read_with_write_id(path, SceneLayout::V3)?.0)
    }

    /// Reads a scene file of `layout`'s version; returns the scene and its write id (0 for
    /// version 1, which had none).
    pub(crate) fn read_with_write_id(path: &Path, layout: SceneLayout) -> Result<(Scene, u64), DatasetError> {
        let bytes = read_all(path)?;
        Self::decode_with(path, &bytes, layout)
    }

    /// Decodes and validates scene bytes; `path` is only used in error messages.
    pub fn decode(path: &Path, bytes: &[u8]) -> Result<Scene, DatasetError> {
        Ok(Self::decode_with(path, bytes, SceneLayout::V3)?.0)
    }

    pub(crate) fn decode_with(path: &Path, bytes: &[u8], layout: SceneLayout) -> Result<(Scene, u64), DatasetError> {
        let header_len = layout.header_len;
        check_versioned_prefix(path, bytes, MAGIC, header_len, layout.version)?;
        let write_id = if layout.crc_covers_header { u64_at(bytes, 16) } else { 0 };
        let corrupt = |offset: u64, what: String| DatasetError::Corrupt {
            path: path.to_path_buf(),
            offset,
            what,
        };
        let at = layout.counts_at;
        let mesh_count = u64_at(bytes, at);
        let vertex_count = u64_at(bytes, at + 8);
        let index_count = u64_at(bytes, at + 16);
        for (count, offset, name) in [
            (mesh_count, at, "mesh"),
            (vertex_count, at + 8, "vertex"),
            (index_count, at + 16, "index"),
        ] {
            if count > u64::from(u32::MAX) {
                return Err(corrupt(offset as u64, format!("{name} count {count} exceeds 2^32 - 1")));
            }
        }
        let crs_len = if layout.crs_record {
            if bytes.len() < header_len + 4 {
                return Err(DatasetError::truncated(
                    path,
                    "the CRS record",
                    header_len as u64,
                    header_len as u64 + 4,
                    bytes.len() as u64,
                ));
            }
            let len = u32_at(bytes, header_len) as usize;
            if len > MAX_CRS_BYTES {
                return Err(corrupt(
                    header_len as u64,
                    format!("CRS text length {len} exceeds {MAX_CRS_BYTES} bytes"),
                ));
            }
            len
        } else {
            0
        };
        let meshes_at = if layout.crs_record {
            header_len + 4 + crs_len.next_multiple_of(4)
        } else {
            header_len
        };
        // Counts are below 2^32, so these products cannot overflow u64.
        let body_len = mesh_count * MESH_RECORD_BYTES as u64 + vertex_count * 32 + index_count * 4;
        let end = meshes_at as u64 + body_len;
        expect_end(path, bytes, meshes_at as u64, end, || {
            format!("{mesh_count} meshes, {vertex_count} vertices and {index_count} indices")
        })?;
        // What the checksum covers after the header: the CRS record and the meshes' data.
        let body = &bytes[header_len..];
        let stored = u32_at(bytes, layout.crc_at);
        let (computed, covered_from) = if layout.crc_covers_header {
            (header_and_body_crc(&bytes[..layout.crc_at], body), 0)
        } else {
            (crc32fast::hash(body), header_len as u64)
        };
        if stored != computed {
            return Err(DatasetError::Checksum {
                path: path.to_path_buf(),
                what: if layout.crc_covers_header {
                    "the scene (header and body)".into()
                } else {
                    "the scene body".into()
                },
                offset: covered_from,
                end,
                stored,
                computed,
            });
        }
        if u32_at(bytes, layout.crc_at + 4) != 0 {
            return Err(corrupt(layout.crc_at as u64 + 4, "reserved word is not 0".into()));
        }
        let o = layout.origin_at;
        let origin = [f64_at(bytes, o), f64_at(bytes, o + 8), f64_at(bytes, o + 16)];
        let b = layout.bounds_at;
        let bounds = Aabb {
            min: [f32_at(bytes, b), f32_at(bytes, b + 4), f32_at(bytes, b + 8)],
            max: [f32_at(bytes, b + 12), f32_at(bytes, b + 16), f32_at(bytes, b + 20)],
        };
        let crs = if crs_len == 0 {
            None
        } else {
            let text_at = header_len + 4;
            let text = std::str::from_utf8(&bytes[text_at..text_at + crs_len])
                .map_err(|e| corrupt(text_at as u64, format!("CRS text is not UTF-8: {e}")))?;
            let crs = Crs::parse(text).map_err(|e| corrupt(text_at as u64, format!("CRS: {e}")))?;
            if let Some(at) = (text_at + crs_len..meshes_at).find(|&at| bytes[at] != 0) {
                return Err(corrupt(at as u64, "CRS padding is not 0".into()));
            }
            Some(crs)
        };
        let (mesh_bytes, rest) = bytes[meshes_at..].split_at(mesh_count as usize * MESH_RECORD_BYTES);
        let (position_bytes, rest) = rest.split_at(vertex_count as usize * 12);
        let (normal_bytes, rest) = rest.split_at(vertex_count as usize * 12);
        let (uv_bytes, index_bytes) = rest.split_at(vertex_count as usize * 8);
        let meshes = mesh_bytes
            .chunks_exact(MESH_RECORD_BYTES)
            .map(|r| Mesh {
                first_vertex: u32_at(r, 0),
                vertex_count: u32_at(r, 4),
                first_index: u32_at(r, 8),
                index_count: u32_at(r, 12),
                texture: u32_at(r, 16),
                bounds: Aabb {
                    min: [f32_at(r, 20), f32_at(r, 24), f32_at(r, 28)],
                    max: [f32_at(r, 32), f32_at(r, 36), f32_at(r, 40)],
                },
                origin: 0,
            })
            .collect();
        let vec3s = |b: &[u8]| {
            b.chunks_exact(12)
                .map(|c| [f32_at(c, 0), f32_at(c, 4), f32_at(c, 8)])
                .collect()
        };
        let scene = Scene {
            origin,
            crs,
            bounds,
            meshes,
            positions: vec3s(position_bytes),
            normals: vec3s(normal_bytes),
            uvs: uv_bytes.chunks_exact(8).map(|c| [f32_at(c, 0), f32_at(c, 4)]).collect(),
            indices: index_bytes.chunks_exact(4).map(|c| u32_at(c, 0)).collect(),
            local_origins: Vec::new(),
        };
        scene.validate_with(path, layout)?;
        Ok((scene, write_id))
    }

    /// Checks every invariant a renderer relies on: mesh ranges inside the arrays, indices
    /// inside their mesh, whole triangles, finite attributes, bounds that hold their
    /// vertices. Errors carry the byte offset the value has (or would have) in the file.
    pub fn validate(&self, path: &Path) -> Result<(), DatasetError> {
        self.validate_with(path, SceneLayout::V3)
    }

    fn validate_with(&self, path: &Path, layout: SceneLayout) -> Result<(), DatasetError> {
        let corrupt = |offset: u64, what: String| DatasetError::Corrupt {
            path: path.to_path_buf(),
            offset,
            what,
        };
        let vertex_count = self.positions.len() as u64;
        if self.normals.len() as u64 != vertex_count || self.uvs.len() as u64 != vertex_count {
            return Err(DatasetError::InvalidInput(format!(
                "{} positions, {} normals, {} uvs",
                self.positions.len(),
                self.normals.len(),
                self.uvs.len()
            )));
        }
        if self.origin.iter().any(|v| !v.is_finite()) {
            return Err(corrupt(
                layout.origin_at as u64,
                format!("scene origin {:?} is not finite", self.origin),
            ));
        }
        let mesh_base = (layout.header_len + layout.crs_record_len(self.crs.as_ref())) as u64;
        let positions_base = mesh_base + self.meshes.len() as u64 * MESH_RECORD_BYTES as u64;
        let normals_base = positions_base + vertex_count * 12;
        let uvs_base = normals_base + vertex_count * 12;
        let indices_base = uvs_base + vertex_count * 8;
        for (i, p) in self.positions.iter().enumerate() {
            if p.iter().any(|v| !v.is_finite()) {
                return Err(corrupt(
                    positions_base + i as u64 * 12,
                    format!("vertex {i} has non-finite position {p:?}"),
                ));
            }
        }
        for (i, n) in self.normals.iter().enumerate() {
            if n.iter().any(|v| !v.is_finite()) {
                return Err(corrupt(
                    normals_base + i as u64 * 12,
                    format!("vertex {i} has non-finite normal {n:?}"),
                ));
            }
        }
        for (i, uv) in self.uvs.iter().enumerate() {
            if uv.iter().any(|v| !v.is_finite()) {
                return Err(corrupt(
                    uvs_base + i as u64 * 8,
                    format!("vertex {i} has non-finite uv {uv:?}"),
                ));
            }
        }
        if let Some((k, o)) = self
            .local_origins
            .iter()
            .enumerate()
            .find(|(_, o)| !o.iter().all(|v| v.is_finite()))
        {
            return Err(DatasetError::InvalidInput(format!(
                "local origin {} {o:?} is not finite",
                k + 1
            )));
        }
        let mut all = Aabb::EMPTY;
        for (m, mesh) in self.meshes.iter().enumerate() {
            let record = mesh_base + m as u64 * MESH_RECORD_BYTES as u64;
            if mesh.origin as usize > self.local_origins.len() {
                return Err(DatasetError::InvalidInput(format!(
                    "mesh {m} at local origin {}, but the scene has {}",
                    mesh.origin,
                    self.local_origins.len()
                )));
            }
            let vertex_end = u64::from(mesh.first_vertex) + u64::from(mesh.vertex_count);
            if vertex_end > vertex_count {
                return Err(corrupt(
                    record,
                    format!(
                        "mesh {m}: vertices {}..{vertex_end} exceed the {vertex_count} vertices",
                        mesh.first_vertex
                    ),
                ));
            }
            let index_end = u64::from(mesh.first_index) + u64::from(mesh.index_count);
            if index_end > self.indices.len() as u64 {
                return Err(corrupt(
                    record + 8,
                    format!(
                        "mesh {m}: indices {}..{index_end} exceed the {} indices",
                        mesh.first_index,
                        self.indices.len()
                    ),
                ));
            }
            if mesh.index_count % 3 != 0 {
                return Err(corrupt(
                    record + 12,
                    format!("mesh {m}: index count {} is not a multiple of 3", mesh.index_count),
                ));
            }
            let first = mesh.first_index as usize;
            for (k, &index) in self.indices[first..first + mesh.index_count as usize]
                .iter()
                .enumerate()
            {
                if index >= mesh.vertex_count {
                    let at = first + k;
                    return Err(corrupt(
                        indices_base + at as u64 * 4,
                        format!(
                            "mesh {m}: index {at} is {index}, out of range (the mesh has {} vertices)",
                            mesh.vertex_count
                        ),
                    ));
                }
            }
            if mesh.vertex_count == 0 {
                continue;
            }
            if !mesh.bounds.is_valid() {
                return Err(corrupt(
                    record + 20,
                    format!("mesh {m}: bounds {:?} are not finite and ordered", mesh.bounds),
                ));
            }
            let fv = mesh.first_vertex as usize;
            let mut tight = Aabb::EMPTY;
            let offset = self.offset_of(mesh);
            for (k, local) in self.positions[fv..fv + mesh.vertex_count as usize].iter().enumerate() {
                // In the scene's frame, where the bounds are (the position itself at the
                // scene's origin).
                let p = &std::array::from_fn::<f32, 3, _>(|a| (offset[a] + f64::from(local[a])) as f32);
                let tolerance = bounds_tolerance(p);
                if !mesh.bounds.contains(*p, tolerance) {
                    return Err(corrupt(
                        record + 20,
                        format!(
                            "mesh {m}: vertex {} at {p:?} lies outside the mesh bounds {:?}",
                            fv + k,
                            mesh.bounds
                        ),
                    ));
                }
                tight.extend(*p);
            }
            // Bounds drive culling and the overview camera: loose ones (a flipped exponent
            // bit makes 1e7 of 10) would hide the city or park the camera far outside it.
            if !close_boxes(&mesh.bounds, &tight) {
                return Err(corrupt(
                    record + 20,
                    format!(
                        "mesh {m}: bounds {:?} do not match its vertices, which span {tight:?}",
                        mesh.bounds
                    ),
                ));
            }
            all.union(&mesh.bounds);
        }
        let stored = self.stored_bounds();
        let consistent = if all.is_valid() {
            close_boxes(&stored, &all)
        } else {
            // No mesh has vertices: the writer stores zeros, or the empty box.
            stored.min == [0.0; 3] && stored.max == [0.0; 3] || stored == Aabb::EMPTY
        };
        if !consistent {
            return Err(corrupt(
                layout.bounds_at as u64,
                format!(
                    "scene bounds {:?} are not the union of the mesh bounds {all:?}",
                    self.bounds
                ),
            ));
        }
        Ok(())
    }
}

/// A mesh with nothing in it, at the scene's origin.
const EMPTY_MESH: Mesh = Mesh {
    first_vertex: 0,
    vertex_count: 0,
    first_index: 0,
    index_count: 0,
    texture: 0,
    bounds: Aabb::EMPTY,
    origin: 0,
};

/// The box of `positions` moved by `offset` into the scene's frame: at a zero offset the
/// positions' own box, else computed in `f64` and rounded outwards to `f32`.
fn scene_bounds(positions: &[[f32; 3]], offset: [f64; 3]) -> Aabb {
    let mut bounds = Aabb::EMPTY;
    if offset == [0.0; 3] || positions.is_empty() {
        positions.iter().for_each(|p| bounds.extend(*p));
        return bounds;
    }
    let (mut low, mut high) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in positions {
        for a in 0..3 {
            let v = offset[a] + f64::from(p[a]);
            low[a] = low[a].min(v);
            high[a] = high[a].max(v);
        }
    }
    let down = |v: f64| {
        let f = v as f32;
        if f64::from(f) > v {
            f.next_down()
        } else {
            f
        }
    };
    let up = |v: f64| {
        let f = v as f32;
        if f64::from(f) < v {
            f.next_up()
        } else {
            f
        }
    };
    Aabb {
        min: low.map(down),
        max: high.map(up),
    }
}

/// How far a bound may lie from a coordinate of magnitude `|p|`: f32 rounding, relative.
fn bounds_tolerance(p: &[f32; 3]) -> f32 {
    1e-4 * (1.0 + p.iter().fold(0.0f32, |a, v| a.max(v.abs())))
}

/// Whether two boxes agree within [`bounds_tolerance`] of their corners (finite ones only).
fn close_boxes(a: &Aabb, b: &Aabb) -> bool {
    a.is_valid()
        && b.is_valid()
        && [(a.min, b.min), (a.max, b.max)]
            .iter()
            .all(|(x, y)| (0..3).all(|i| (x[i] - y[i]).abs() <= bounds_tolerance(x).max(bounds_tolerance(y))))
}
