//! Sequential dataset writer used by the generator, the importer, the atlas tool and the
//! upgrade.

use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use super::colormap::{write_checksums, Colormap};
use super::error::DatasetError;
use super::files::PendingWrite;
use super::format::{TextureFormat, TextureInfo};
use super::io_util::{encode_table, header_prefix, write_new_durably};
use super::pack::{META_MAGIC, PACK_HEADER_BYTES, PACK_HEADER_CRC_AT, PACK_MAGIC};
use super::scene::Scene;
use super::{Dataset, CHECKSUM_FILE, COLORMAP_FILE, META_FILE, PACK_FILE, SCENE_FILE};

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
/// Atomic: everything goes to a new write subdirectory (see [`super::DatasetFiles`]); the
/// dataset in `dir` stays what it was until `finish` has written, flushed and reopened every
/// file and switched the manifest in one rename. Dropping the writer (an error, a panic)
/// removes the partial write; a killed process leaves it for the next writer to remove. The
/// directory's write lock is held from `create` to the end of `finish`.
///
/// Threading: single-owner (`&mut self`); produce textures in parallel and append them in
/// texture-id order from one thread.
#[derive(Debug)]
pub struct DatasetWriter {
    pending: PendingWrite,
    pack_path: PathBuf,
    pack: BufWriter<File>,
    next_offset: u64,
    textures: Vec<TextureInfo>,
    colours: Vec<[u8; 4]>,
    mip_checksums: Vec<u32>,
    mips: u64,
}

impl DatasetWriter {
    /// Creates `dir` (and parents), takes its write lock ([`DatasetError::Locked`] when
    /// another writer holds it) and starts a new write in it. The current dataset, if any,
    /// is untouched until [`DatasetWriter::finish`]; a file named `dataset.manifest` that is
    /// not a dataset manifest is an error, never replaced.
    pub fn create(dir: &Path) -> Result<Self, DatasetError> {
        Self::start(PendingWrite::begin(dir, false)?)
    }

    /// [`DatasetWriter::create`], waiting for another writer of `dir` to finish instead of
    /// failing with [`DatasetError::Locked`].
    pub fn create_waiting(dir: &Path) -> Result<Self, DatasetError> {
        Self::start(PendingWrite::begin(dir, true)?)
    }

    /// Whether `dir` held a dataset (a manifest) when this writer took its lock.
    pub fn replaces_a_dataset(&self) -> bool {
        self.pending.previous().is_some()
    }

    fn start(pending: PendingWrite) -> Result<Self, DatasetError> {
        let pack_path = pending.path(PACK_FILE);
        let file = std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&pack_path)
            .map_err(|e| DatasetError::io(&pack_path, e))?;
        let mut pack = BufWriter::with_capacity(1 << 20, file);
        // Placeholder header; the real one (counts, length) is written by `finish`, so a
        // pack left behind by an interrupted run fails its checks.
        pack.write_all(&[0u8; PACK_HEADER_BYTES as usize])
            .map_err(|e| DatasetError::io(&pack_path, e))?;
        Ok(Self {
            pending,
            pack_path,
            pack,
            next_offset: PACK_HEADER_BYTES,
            textures: Vec::new(),
            colours: Vec::new(),
            mip_checksums: Vec::new(),
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
        let mut level_start = 0usize;
        for level in 0..info.mip_count() {
            // Fits: the whole chain's length was checked against `chain` above.
            let level_end = level_start + info.mip_len(level) as usize;
            self.mip_checksums.push(crc32fast::hash(&chain[level_start..level_end]));
            level_start = level_end;
        }
        self.textures.push(info);
        self.colours.push(mean_colour);
        self.mips += u64::from(mip_count);
        Ok(id)
    }

    /// Validates `scene` (every mesh texture must exist), writes it and the tables, completes
    /// the pack header, flushes everything, reopens the new dataset with every check
    /// [`Dataset::open`] makes, and only then makes it the directory's dataset.
    pub fn finish(self, scene: &Scene) -> Result<WriteSummary, DatasetError> {
        let count = self.textures.len() as u32;
        if let Some((m, mesh)) = scene.meshes.iter().enumerate().find(|(_, m)| m.texture >= count) {
            return Err(DatasetError::InvalidInput(format!(
                "mesh {m} uses texture {} but only {count} textures were written",
                mesh.texture
            )));
        }
        let write_id = self.pending.write_id();
        let scene_bytes = scene.write_new(&self.pending.path(SCENE_FILE), write_id)?;

        let mut file = self
            .pack
            .into_inner()
            .map_err(|e| DatasetError::io(&self.pack_path, e.into_error()))?;
        let mut header = header_prefix(PACK_MAGIC, write_id);
        header.extend_from_slice(&(self.textures.len() as u64).to_le_bytes());
        header.extend_from_slice(&self.next_offset.to_le_bytes());
        debug_assert_eq!(header.len(), PACK_HEADER_CRC_AT);
        header.extend_from_slice(&crc32fast::hash(&header).to_le_bytes());
        header.resize(PACK_HEADER_BYTES as usize, 0);
        file.seek(SeekFrom::Start(0))
            .and_then(|_| file.write_all(&header))
            .and_then(|_| file.sync_all())
            .map_err(|e| DatasetError::io(&self.pack_path, e))?;

        let meta_body: Vec<u8> = self.textures.iter().flat_map(|t| t.encode()).collect();
        let meta = encode_table(META_MAGIC, write_id, self.textures.len() as u64, &meta_body);
        write_new_durably(&self.pending.path(META_FILE), &meta)?;
        let colormap_bytes = Colormap::new(self.colours).write_new(&self.pending.path(COLORMAP_FILE), write_id)?;
        let checksum_bytes = write_checksums(&self.pending.path(CHECKSUM_FILE), write_id, &self.mip_checksums)?;

        // Reopen before switching: a write that does not read back never becomes the dataset.
        Dataset::open_files(&self.pending.files())?;
        self.pending.commit()?;

        Ok(WriteSummary {
            textures: count,
            mips: self.mips,
            meshes: scene.meshes.len() as u32,
            triangles: scene.triangle_count(),
            pack_bytes: self.next_offset,
            scene_bytes,
            metadata_bytes: meta.len() as u64 + colormap_bytes + checksum_bytes,
        })
    }
}
