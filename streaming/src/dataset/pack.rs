//! `textures.meta` + `textures.pack`: texture metadata and every mip of every texture.

use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

use super::error::DatasetError;
use super::format::{TextureInfo, TEXTURE_RECORD_BYTES};
use super::io_util::{check_prefix, decode_table, read_all, u64_at, TABLE_HEADER_BYTES};
use super::{META_FILE, PACK_FILE};

pub(crate) const META_MAGIC: &[u8; 8] = b"CSTXMETA";
pub(crate) const PACK_MAGIC: &[u8; 8] = b"CSTXPACK";
/// Bytes before the first mip in `textures.pack`.
pub const PACK_HEADER_BYTES: u64 = 64;

/// Where one mip lies in `textures.pack` and how big it is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MipLocation {
    /// Absolute byte offset in `textures.pack`.
    pub offset: u64,
    /// Length in bytes.
    pub len: u64,
    /// Width of the mip in texels.
    pub width: u32,
    /// Height of the mip in texels.
    pub height: u32,
}

/// The texture table plus an open handle on the pack file.
///
/// Threading: `TexturePack` is `Send + Sync`. [`TexturePack::read_mip`] takes `&self` and
/// uses positioned reads (`pread`), so any number of loader threads may read mips
/// concurrently from one shared instance without locking.
#[derive(Debug)]
pub struct TexturePack {
    pack_path: PathBuf,
    file: File,
    pack_len: u64,
    textures: Vec<TextureInfo>,
}

impl TexturePack {
    /// Reads `textures.meta` from `dir` and opens `textures.pack`, checking its header and
    /// that every texture's mip chain lies inside it. Reads no mip data.
    pub fn open(dir: &Path) -> Result<Self, DatasetError> {
        let meta_path = dir.join(META_FILE);
        let meta = read_all(&meta_path)?;
        let (count, body) = decode_table(&meta_path, &meta, META_MAGIC, TEXTURE_RECORD_BYTES)?;
        if count > u64::from(u32::MAX) {
            return Err(DatasetError::Corrupt {
                path: meta_path,
                offset: 16,
                what: format!("texture count {count} exceeds 2^32 - 1"),
            });
        }

        let pack_path = dir.join(PACK_FILE);
        let file = super::io_util::ensure_regular_file(&pack_path)
            .and_then(|()| File::open(&pack_path))
            .map_err(|e| DatasetError::io(&pack_path, e))?;
        let pack_len = file.metadata().map_err(|e| DatasetError::io(&pack_path, e))?.len();
        let mut header = [0u8; PACK_HEADER_BYTES as usize];
        if pack_len < PACK_HEADER_BYTES {
            return Err(DatasetError::Truncated {
                path: pack_path,
                what: "the header".into(),
                offset: 0,
                end: PACK_HEADER_BYTES,
                file_len: pack_len,
            });
        }
        file.read_exact_at(&mut header, 0)
            .map_err(|e| DatasetError::io(&pack_path, e))?;
        check_prefix(&pack_path, &header, PACK_MAGIC, header.len())?;
        let pack_count = u64_at(&header, 16);
        if pack_count != count {
            return Err(DatasetError::Corrupt {
                path: pack_path,
                offset: 16,
                what: format!("pack holds {pack_count} textures but {} lists {count}", META_FILE),
            });
        }
        let recorded_len = u64_at(&header, 24);
        if recorded_len != pack_len {
            return Err(DatasetError::Truncated {
                path: pack_path,
                what: "the mip data the header records".into(),
                offset: PACK_HEADER_BYTES,
                end: recorded_len,
                file_len: pack_len,
            });
        }

        let mut textures = Vec::with_capacity(count as usize);
        for (index, chunk) in body.chunks_exact(TEXTURE_RECORD_BYTES).enumerate() {
            let record_offset = (TABLE_HEADER_BYTES + index * TEXTURE_RECORD_BYTES) as u64;
            let mut record = [0u8; TEXTURE_RECORD_BYTES];
            record.copy_from_slice(chunk);
            let info = TextureInfo::decode(&record).map_err(|what| DatasetError::Corrupt {
                path: meta_path.clone(),
                offset: record_offset,
                what: format!("texture {index}: {what}"),
            })?;
            let end = info.offset() + info.chain_len();
            if info.offset() < PACK_HEADER_BYTES || end > pack_len {
                return Err(DatasetError::Corrupt {
                    path: meta_path,
                    offset: record_offset,
                    what: format!(
                        "texture {index}: mip chain at {}..{end} of {} lies outside the mip data {PACK_HEADER_BYTES}..{pack_len}",
                        info.offset(),
                        PACK_FILE
                    ),
                });
            }
            textures.push(info);
        }
        Ok(Self {
            pack_path,
            file,
            pack_len,
            textures,
        })
    }

    /// Number of textures.
    pub fn len(&self) -> u32 {
        // `open` rejects more than u32::MAX textures.
        self.textures.len() as u32
    }

    /// Whether the dataset has no textures.
    pub fn is_empty(&self) -> bool {
        self.textures.is_empty()
    }

    /// Metadata of every texture, indexed by texture id.
    pub fn textures(&self) -> &[TextureInfo] {
        &self.textures
    }

    /// Metadata of one texture.
    pub fn info(&self, texture: u32) -> Result<&TextureInfo, DatasetError> {
        self.textures.get(texture as usize).ok_or(DatasetError::NoSuchTexture {
            texture,
            count: self.len(),
        })
    }

    /// Location and extent of one mip (level 0 = finest).
    pub fn mip_location(&self, texture: u32, level: u32) -> Result<MipLocation, DatasetError> {
        let info = self.info(texture)?;
        if level >= info.mip_count() {
            return Err(DatasetError::NoSuchMip {
                texture,
                level,
                mip_count: info.mip_count(),
            });
        }
        let (width, height) = info.mip_extent(level);
        Ok(MipLocation {
            offset: info.mip_offset(level),
            len: info.mip_len(level),
            width,
            height,
        })
    }

    /// Reads exactly one mip with one positioned read into `buf`, which is resized to the
    /// mip's length (its capacity is reused across calls).
    pub fn read_mip(&self, texture: u32, level: u32, buf: &mut Vec<u8>) -> Result<MipLocation, DatasetError> {
        let location = self.mip_location(texture, level)?;
        let len =
            usize::try_from(location.len).map_err(|_| DatasetError::InvalidInput("mip larger than memory".into()))?;
        buf.resize(len, 0);
        self.read_at(location, buf)?;
        Ok(location)
    }

    /// Reads exactly one mip into `dst` (for example mapped staging memory), which must be
    /// exactly [`MipLocation::len`] bytes long.
    pub fn read_mip_into(&self, texture: u32, level: u32, dst: &mut [u8]) -> Result<MipLocation, DatasetError> {
        let location = self.mip_location(texture, level)?;
        if dst.len() as u64 != location.len {
            return Err(DatasetError::InvalidInput(format!(
                "texture {texture} level {level} is {} bytes, destination is {}",
                location.len,
                dst.len()
            )));
        }
        self.read_at(location, dst)?;
        Ok(location)
    }

    /// Reads `len` bytes at `offset` of the pack (used by `verify` for whole chains).
    pub fn read_range(&self, offset: u64, dst: &mut [u8]) -> Result<(), DatasetError> {
        let end = offset.saturating_add(dst.len() as u64);
        if end > self.pack_len {
            return Err(self.truncated(offset, end));
        }
        self.file.read_exact_at(dst, offset).map_err(|e| {
            if e.kind() == std::io::ErrorKind::UnexpectedEof {
                self.truncated(offset, end)
            } else {
                DatasetError::io(&self.pack_path, e)
            }
        })
    }

    fn read_at(&self, location: MipLocation, dst: &mut [u8]) -> Result<(), DatasetError> {
        self.read_range(location.offset, dst)
    }

    fn truncated(&self, offset: u64, end: u64) -> DatasetError {
        // The file may have shrunk after opening; report its current length.
        let file_len = self.file.metadata().map(|m| m.len()).unwrap_or(self.pack_len);
        DatasetError::Truncated {
            path: self.pack_path.clone(),
            what: "a mip".into(),
            offset,
            end,
            file_len,
        }
    }

    /// Path of `textures.pack`.
    pub fn pack_path(&self) -> &Path {
        &self.pack_path
    }

    /// Length of `textures.pack` when it was opened.
    pub fn pack_len(&self) -> u64 {
        self.pack_len
    }

    /// Host bytes the texture table occupies (what opening a dataset costs per texture,
    /// colormap not included).
    pub fn metadata_bytes(&self) -> usize {
        self.textures.len() * std::mem::size_of::<TextureInfo>()
    }
}
