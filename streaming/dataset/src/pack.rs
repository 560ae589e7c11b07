//! `textures.meta` + `textures.pack`: texture metadata and every mip of every texture.

use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::colormap::decode_checksums;
use super::error::DatasetError;
use super::files::{DatasetFiles, CHECKSUM_FILE, META_FILE, PACK_FILE};
use super::format::{TextureInfo, TEXTURE_RECORD_BYTES};
use super::io_util::{check_prefix, decode_table, u32_at, u64_at, TABLE_HEADER_BYTES};
use super::mip_cache::{CacheNamespace, MipCache};
use super::store::DatasetStore;

pub(crate) const META_MAGIC: &[u8; 8] = b"CSTXMETA";
pub(crate) const PACK_MAGIC: &[u8; 8] = b"CSTXPACK";
/// Bytes before the first mip in `textures.pack`: magic, version, flags, write id, texture
/// count (u64), file length (u64), CRC-32 of bytes 0..40 (u32), zeros.
pub const PACK_HEADER_BYTES: u64 = 64;
/// Where the pack header's checksum lies; it covers the bytes before it.
pub(crate) const PACK_HEADER_CRC_AT: usize = 40;

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
    reader: PackReader,
    pack_len: u64,
    textures: Vec<TextureInfo>,
    /// CRC-32 of every mip, textures in id order, finest level first.
    mip_checksums: Vec<u32>,
    /// Index of each texture's level 0 in `mip_checksums`.
    first_checksum: Vec<u32>,
}

/// How mips are read: positioned reads of the local file, or ranged reads of a store
/// (through its on-disk mip cache where it has one).
#[derive(Debug)]
enum PackReader {
    File(File),
    Store {
        store: Arc<dyn DatasetStore>,
        cache: Option<(Arc<MipCache>, CacheNamespace)>,
    },
}

/// Opens `textures.pack` (a regular file only) and reads its header: the file, its length
/// and the header bytes.
pub(crate) fn open_pack(path: &Path) -> Result<(File, u64, [u8; PACK_HEADER_BYTES as usize]), DatasetError> {
    let file = super::io_util::ensure_regular_file(path)
        .and_then(|()| File::open(path))
        .map_err(|e| DatasetError::io(path, e))?;
    let len = file.metadata().map_err(|e| DatasetError::io(path, e))?.len();
    if len < PACK_HEADER_BYTES {
        return Err(DatasetError::truncated(path, "the header", 0, PACK_HEADER_BYTES, len));
    }
    let mut header = [0u8; PACK_HEADER_BYTES as usize];
    file.read_exact_at(&mut header, 0)
        .map_err(|e| DatasetError::io(path, e))?;
    Ok((file, len, header))
}

impl TexturePack {
    /// Reads `textures.meta` and `textures.crc` of the dataset in `dir` and opens
    /// `textures.pack`, checking its header and that every texture's mip chain lies inside
    /// it. Reads no mip data.
    pub fn open(dir: &Path) -> Result<Self, DatasetError> {
        Self::open_files(&DatasetFiles::resolve(dir)?)
    }

    /// [`TexturePack::open`] of resolved dataset files: every file must carry their write id.
    pub fn open_files(files: &DatasetFiles) -> Result<Self, DatasetError> {
        Self::open_files_in(None, files)
    }

    /// [`TexturePack::open_files`] of a dataset in `store` (`None`: the local directory):
    /// the tables are read whole, the pack's header and length by range.
    pub fn open_files_in(store: Option<&Arc<dyn DatasetStore>>, files: &DatasetFiles) -> Result<Self, DatasetError> {
        let read_file = |path: &Path| super::store::read_file(store, path);
        let meta_path = files.path(META_FILE);
        let meta = read_file(&meta_path)?;
        let table = decode_table(&meta_path, &meta, META_MAGIC, TEXTURE_RECORD_BYTES, files.version())?;
        files.check_write_id(&meta_path, table.write_id)?;
        let (count, body) = (table.count, table.body);
        if count > u64::from(u32::MAX) {
            return Err(DatasetError::Corrupt {
                path: meta_path,
                offset: 24,
                what: format!("texture count {count} exceeds 2^32 - 1"),
            });
        }

        let pack_path = files.path(PACK_FILE);
        let (reader, pack_len, header) = match store {
            None => {
                let (file, len, header) = open_pack(&pack_path)?;
                (PackReader::File(file), len, header)
            }
            Some(store) => {
                let len = store.len(&pack_path)?;
                if len < PACK_HEADER_BYTES {
                    return Err(DatasetError::truncated(
                        pack_path,
                        "the header",
                        0,
                        PACK_HEADER_BYTES,
                        len,
                    ));
                }
                let mut header = [0u8; PACK_HEADER_BYTES as usize];
                store.read_at(&pack_path, 0, &mut header)?;
                // The pack's length and header (its write id, random per write, and the
                // header's CRC) name its entries, not its URL: a mirror of the same write
                // shares them.
                let cache = store.mip_cache().map(|cache| {
                    let mut identity = len.to_le_bytes().to_vec();
                    identity.extend_from_slice(&header);
                    let namespace = cache.namespace(&identity, &pack_path.to_string_lossy());
                    (Arc::clone(cache), namespace)
                });
                let reader = PackReader::Store {
                    store: Arc::clone(store),
                    cache,
                };
                (reader, len, header)
            }
        };
        let write_id = check_prefix(&pack_path, &header, PACK_MAGIC, header.len(), files.version())?;
        let stored = u32_at(&header, PACK_HEADER_CRC_AT);
        let computed = crc32fast::hash(&header[..PACK_HEADER_CRC_AT]);
        if stored != computed {
            return Err(DatasetError::Checksum {
                path: pack_path,
                what: "the pack header".into(),
                offset: 0,
                end: PACK_HEADER_CRC_AT as u64,
                stored,
                computed,
            });
        }
        if header[PACK_HEADER_CRC_AT + 4..].iter().any(|&b| b != 0) {
            return Err(DatasetError::Corrupt {
                path: pack_path,
                offset: PACK_HEADER_CRC_AT as u64 + 4,
                what: "reserved header bytes are not 0".into(),
            });
        }
        files.check_write_id(&pack_path, write_id)?;
        let pack_count = u64_at(&header, 24);
        if pack_count != count {
            return Err(DatasetError::Corrupt {
                path: pack_path,
                offset: 24,
                what: format!("pack holds {pack_count} textures but {} lists {count}", META_FILE),
            });
        }
        let recorded_len = u64_at(&header, 32);
        if recorded_len != pack_len {
            return Err(DatasetError::truncated(
                pack_path,
                "the mip data the header records",
                PACK_HEADER_BYTES,
                recorded_len,
                pack_len,
            ));
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

        let checksum_path = files.path(CHECKSUM_FILE);
        let (mip_checksums, write_id) = decode_checksums(&checksum_path, &read_file(&checksum_path)?, files.version())?;
        files.check_write_id(&checksum_path, write_id)?;
        let mut first_checksum = Vec::with_capacity(textures.len());
        let mut mips = 0u64;
        for info in &textures {
            // At most 15 levels per texture and 2^32 - 1 textures: no u64 overflow.
            first_checksum.push(u32::try_from(mips).unwrap_or(u32::MAX));
            mips += u64::from(info.mip_count());
        }
        if mips != mip_checksums.len() as u64 || mips > u64::from(u32::MAX) {
            return Err(DatasetError::Corrupt {
                path: checksum_path,
                offset: 24,
                what: format!(
                    "{} mip checksums, but {META_FILE} lists {mips} mips (at most 2^32 - 1)",
                    mip_checksums.len()
                ),
            });
        }
        Ok(Self {
            pack_path,
            reader,
            pack_len,
            textures,
            mip_checksums,
            first_checksum,
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
    /// mip's length (its capacity is reused across calls), and checks it against the mip's
    /// stored CRC-32 ([`DatasetError::Checksum`] on a mismatch).
    pub fn read_mip(&self, texture: u32, level: u32, buf: &mut Vec<u8>) -> Result<MipLocation, DatasetError> {
        let location = self.mip_location(texture, level)?;
        let len =
            usize::try_from(location.len).map_err(|_| DatasetError::InvalidInput("mip larger than memory".into()))?;
        buf.resize(len, 0);
        self.load_mip(texture, level, location, buf)?;
        Ok(location)
    }

    /// The stored CRC-32 of one mip.
    pub fn mip_checksum(&self, texture: u32, level: u32) -> Result<u32, DatasetError> {
        self.mip_location(texture, level)?;
        Ok(self.stored_checksum(texture, level))
    }

    /// The stored CRC-32 of a `(texture, level)` pair [`TexturePack::mip_location`] accepted.
    fn stored_checksum(&self, texture: u32, level: u32) -> u32 {
        self.mip_checksums[self.first_checksum[texture as usize] as usize + level as usize]
    }

    /// Checks a mip just read; `location` is what `mip_location` returned for it, so the
    /// pair is known to exist.
    fn check_mip(&self, texture: u32, level: u32, location: MipLocation, bytes: &[u8]) -> Result<(), DatasetError> {
        let stored = self.stored_checksum(texture, level);
        let computed = crc32fast::hash(bytes);
        if stored == computed {
            return Ok(());
        }
        Err(DatasetError::Checksum {
            path: self.pack_path.clone(),
            what: format!(
                "texture {texture} level {level} ({}x{} {})",
                location.width,
                location.height,
                self.textures[texture as usize].format().name()
            ),
            offset: location.offset,
            end: location.offset + location.len,
            stored,
            computed,
        })
    }

    /// Reads exactly one mip into `dst` (for example mapped staging memory), which must be
    /// exactly [`MipLocation::len`] bytes long, and checks it as [`TexturePack::read_mip`]
    /// does.
    pub fn read_mip_into(&self, texture: u32, level: u32, dst: &mut [u8]) -> Result<MipLocation, DatasetError> {
        let location = self.mip_location(texture, level)?;
        if dst.len() as u64 != location.len {
            return Err(DatasetError::InvalidInput(format!(
                "texture {texture} level {level} is {} bytes, destination is {}",
                location.len,
                dst.len()
            )));
        }
        self.load_mip(texture, level, location, dst)?;
        Ok(location)
    }

    /// Reads a mip `mip_location` accepted into `dst` and checks it: from the mip cache
    /// where it holds the mip, otherwise from the pack (then caching it).
    fn load_mip(&self, texture: u32, level: u32, location: MipLocation, dst: &mut [u8]) -> Result<(), DatasetError> {
        let cache = match &self.reader {
            PackReader::Store { cache: Some(cache), .. } => Some(cache),
            _ => None,
        };
        let crc = self.stored_checksum(texture, level);
        if let Some((cache, namespace)) = cache {
            if cache.read(namespace, texture, level, crc, dst) {
                return Ok(());
            }
        }
        self.read_at(location, dst)?;
        self.check_mip(texture, level, location, dst)?;
        if let Some((cache, namespace)) = cache {
            cache.write(namespace, texture, level, crc, dst);
        }
        Ok(())
    }

    /// The on-disk mip cache this pack reads through, if any (remote datasets opened with
    /// one).
    pub fn mip_cache(&self) -> Option<&MipCache> {
        match &self.reader {
            PackReader::Store {
                cache: Some((cache, _)),
                ..
            } => Some(cache),
            _ => None,
        }
    }

    /// Reads `len` bytes at `offset` of the pack, unchecked (checksums cover whole mips).
    pub fn read_range(&self, offset: u64, dst: &mut [u8]) -> Result<(), DatasetError> {
        let end = offset.saturating_add(dst.len() as u64);
        if end > self.pack_len {
            return Err(self.truncated(offset, end));
        }
        match &self.reader {
            PackReader::File(file) => file.read_exact_at(dst, offset).map_err(|e| {
                if e.kind() == std::io::ErrorKind::UnexpectedEof {
                    self.truncated(offset, end)
                } else {
                    DatasetError::io(&self.pack_path, e)
                }
            }),
            PackReader::Store { store, .. } => store.read_at(&self.pack_path, offset, dst),
        }
    }

    /// Hints that `mips` (highest priority first) are about to be read: a remote store
    /// starts fetching those its mip cache does not hold ([`DatasetStore::prefetch`]); a
    /// local pack ignores it. Pairs that do not exist are skipped (their read reports the
    /// error).
    pub fn prefetch(&self, mips: &[(u32, u32)]) {
        if let PackReader::Store { store, cache } = &self.reader {
            let ranges: Vec<(u64, u64)> = mips
                .iter()
                .filter_map(|&(texture, level)| {
                    let location = self.mip_location(texture, level).ok()?;
                    let cached = cache.as_ref().is_some_and(|(cache, namespace)| {
                        cache.contains(namespace, texture, level, self.stored_checksum(texture, level))
                    });
                    (!cached).then_some((location.offset, location.len))
                })
                .collect();
            store.prefetch(&self.pack_path, &ranges);
        }
    }

    fn read_at(&self, location: MipLocation, dst: &mut [u8]) -> Result<(), DatasetError> {
        self.read_range(location.offset, dst)
    }

    fn truncated(&self, offset: u64, end: u64) -> DatasetError {
        // The file may have shrunk after opening; report its current length.
        let file_len = match &self.reader {
            PackReader::File(file) => file.metadata().map(|m| m.len()).unwrap_or(self.pack_len),
            PackReader::Store { .. } => self.pack_len,
        };
        DatasetError::truncated(&self.pack_path, "a mip", offset, end, file_len)
    }

    /// Path of `textures.pack`.
    pub fn pack_path(&self) -> &Path {
        &self.pack_path
    }

    /// Length of `textures.pack` when it was opened.
    pub fn pack_len(&self) -> u64 {
        self.pack_len
    }

    /// Host bytes the texture table and mip checksums occupy (what opening a dataset costs,
    /// colormap not included).
    pub fn metadata_bytes(&self) -> usize {
        self.textures.len() * (std::mem::size_of::<TextureInfo>() + std::mem::size_of::<u32>())
            + self.mip_checksums.len() * std::mem::size_of::<u32>()
    }
}
