//! Sequential dataset writer used by the generator, the importer and the atlas tool.

use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use super::colormap::{write_checksums, Colormap};
use super::error::DatasetError;
use super::format::{TextureFormat, TextureInfo};
use super::io_util::{encode_table, header_prefix, write_all};
use super::pack::{META_MAGIC, PACK_HEADER_BYTES, PACK_MAGIC};
use super::scene::Scene;
use super::{CHECKSUM_FILE, COLORMAP_FILE, META_FILE, PACK_FILE, SCENE_FILE};

/// Totals of a written dataset.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct WriteSummary {
    /// Textures written.
    pub textures: u32,
    /// Mips written (all levels of all textures).
    pub mips: u64,
    /// Meshes in the scene.
    pub meshes: u32,
    /// Triangles in the scene.
    pub triangles: u64,
    /// Bytes of `textures.pack`.
    pub pack_bytes: u64,
    /// Bytes of `scene.bin`.
    pub scene_bytes: u64,
    /// Bytes of `textures.meta` + `colormap.bin` + `textures.crc`.
    pub metadata_bytes: u64,
}

/// Writes a dataset directory: textures are appended one mip chain at a time (so the pack is
/// never held in memory), the scene and tables are written by [`DatasetWriter::finish`].
///
/// Threading: single-owner (`&mut self`); produce textures in parallel and append them in
/// texture-id order from one thread.
#[derive(Debug)]
pub struct DatasetWriter {
    dir: PathBuf,
    pack_path: PathBuf,
    pack: BufWriter<File>,
    next_offset: u64,
    textures: Vec<TextureInfo>,
    colours: Vec<[u8; 4]>,
    checksums: Vec<u32>,
    mips: u64,
}

impl DatasetWriter {
    /// Creates `dir` (and parents) and starts `textures.pack` in it, replacing an existing one.
    pub fn create(dir: &Path) -> Result<Self, DatasetError> {
        std::fs::create_dir_all(dir).map_err(|e| DatasetError::io(dir, e))?;
        let pack_path = dir.join(PACK_FILE);
        let file = File::create(&pack_path).map_err(|e| DatasetError::io(&pack_path, e))?;
        let mut pack = BufWriter::with_capacity(1 << 20, file);
        // Placeholder header; the real one (counts, length) is written by `finish`, so a
        // pack left behind by an interrupted run fails its checks.
        pack.write_all(&[0u8; PACK_HEADER_BYTES as usize])
            .map_err(|e| DatasetError::io(&pack_path, e))?;
        Ok(Self {
            dir: dir.to_path_buf(),
            pack_path,
            pack,
            next_offset: PACK_HEADER_BYTES,
            textures: Vec::new(),
            colours: Vec::new(),
            checksums: Vec::new(),
            mips: 0,
        })
    }

    /// Number of textures appended so far (the id the next one gets).
    pub fn texture_count(&self) -> u32 {
        self.textures.len() as u32
    }

    /// Appends one texture. `chain` holds its `mip_count` levels back to back, finest first,
    /// each exactly [`TextureFormat::mip_bytes`] long. `mean_colour` goes to the City Colormap.
    /// Returns the texture id.
    pub fn add_texture(
        &mut self,
        format: TextureFormat,
        width: u32,
        height: u32,
        mip_count: u32,
        chain: &[u8],
        mean_colour: [u8; 4],
    ) -> Result<u32, DatasetError> {
        let id = u32::try_from(self.textures.len())
            .ok()
            .filter(|&id| id < u32::MAX)
            .ok_or_else(|| DatasetError::InvalidInput("more than 2^32 - 1 textures".into()))?;
        if !width.is_power_of_two() || !height.is_power_of_two() {
            return Err(DatasetError::InvalidInput(format!(
                "texture {id}: extent {width}x{height} is not a power of two"
            )));
        }
        let mips = u8::try_from(mip_count).unwrap_or(u8::MAX);
        let info = TextureInfo::new(
            format,
            width.trailing_zeros() as u8,
            height.trailing_zeros() as u8,
            mips,
            self.next_offset,
        )
        .map_err(|e| DatasetError::InvalidInput(format!("texture {id}: {e}")))?;
        if info.chain_len() != chain.len() as u64 {
            return Err(DatasetError::InvalidInput(format!(
                "texture {id}: {width}x{height} {} with {mip_count} mips needs {} bytes, got {}",
                format.name(),
                info.chain_len(),
                chain.len()
            )));
        }
        self.pack
            .write_all(chain)
            .map_err(|e| DatasetError::io(&self.pack_path, e))?;
        self.next_offset += chain.len() as u64;
        self.textures.push(info);
        self.colours.push(mean_colour);
        self.checksums.push(crc32fast::hash(chain));
        self.mips += u64::from(mip_count);
        Ok(id)
    }

    /// Validates `scene` (every mesh texture must exist), writes it and the tables, and
    /// completes the pack header.
    pub fn finish(self, scene: &Scene) -> Result<WriteSummary, DatasetError> {
        let scene_path = self.dir.join(SCENE_FILE);
        let count = self.textures.len() as u32;
        if let Some((m, mesh)) = scene.meshes.iter().enumerate().find(|(_, m)| m.texture >= count) {
            return Err(DatasetError::InvalidInput(format!(
                "mesh {m} uses texture {} but only {count} textures were written",
                mesh.texture
            )));
        }
        let scene_bytes = scene.encode(&scene_path)?;
        write_all(&scene_path, &scene_bytes)?;

        let mut file = self
            .pack
            .into_inner()
            .map_err(|e| DatasetError::io(&self.pack_path, e.into_error()))?;
        let mut header = header_prefix(PACK_MAGIC);
        header.extend_from_slice(&(self.textures.len() as u64).to_le_bytes());
        header.extend_from_slice(&self.next_offset.to_le_bytes());
        header.resize(PACK_HEADER_BYTES as usize, 0);
        file.seek(SeekFrom::Start(0))
            .and_then(|_| file.write_all(&header))
            .and_then(|_| file.sync_all())
            .map_err(|e| DatasetError::io(&self.pack_path, e))?;

        let meta_body: Vec<u8> = self.textures.iter().flat_map(|t| t.encode()).collect();
        let meta = encode_table(META_MAGIC, self.textures.len() as u64, &meta_body);
        write_all(&self.dir.join(META_FILE), &meta)?;
        let colormap = Colormap::new(self.colours);
        colormap.write(&self.dir.join(COLORMAP_FILE))?;
        write_checksums(&self.dir.join(CHECKSUM_FILE), &self.checksums)?;

        Ok(WriteSummary {
            textures: count,
            mips: self.mips,
            meshes: scene.meshes.len() as u32,
            triangles: scene.triangle_count(),
            pack_bytes: self.next_offset,
            scene_bytes: scene_bytes.len() as u64,
            metadata_bytes: meta.len() as u64 + 32 + 8 * u64::from(count) + 32,
        })
    }
}
