//! Sequential dataset writer used by the generator, the importer, the atlas tool and the
//! upgrade.

use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use super::colormap::{write_checksums, Colormap};
use super::dataset::Dataset;
use super::error::DatasetError;
use super::files::{PendingWrite, CHECKSUM_FILE, COLORMAP_FILE, DATASET_FILES, META_FILE, PACK_FILE, SCENE_FILE};
use super::format::{TextureFormat, TextureInfo, TEXTURE_RECORD_BYTES};
use super::io_util::{encode_table, write_new_durably};
use super::pack::{META_MAGIC, PACK_HEADER_BYTES};
use super::scene::Scene;
use super::shard::{pack_header, part_pack_body};
use super::tiled::encode_scene_files;

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
    /// Bytes of the scene's files: `tiles.bin`, `geometry.pack` and `geometry.crc`.
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
    /// Resumable writes only: the journal of checkpoints and how many textures it holds.
    journal: Option<Journal>,
}

/// File in a resumable write's subdirectory that records its checkpoints.
const JOURNAL_FILE: &str = "resume.journal";
const JOURNAL_MAGIC: &[u8; 8] = b"CSRESUME";
/// A journal's job description is at most this long (it is a command line, not data).
const MAX_JOB_BYTES: usize = 4096;

#[derive(Debug)]
struct Journal {
    path: PathBuf,
    file: File,
    /// Textures the journal holds (those appended since are lost if the process dies).
    textures: usize,
}

/// What a journal says was written durably: the writer's state at its last checkpoint.
#[derive(Debug, Default)]
struct Checkpoint {
    textures: Vec<TextureInfo>,
    colours: Vec<[u8; 4]>,
    mip_checksums: Vec<u32>,
    pack_end: u64,
    /// Bytes of the journal up to the end of the last whole record.
    journal_len: u64,
}

fn journal_header(job: &str) -> Vec<u8> {
    let mut header = JOURNAL_MAGIC.to_vec();
    header.extend_from_slice(&(job.len() as u32).to_le_bytes());
    header.extend_from_slice(job.as_bytes());
    header.extend_from_slice(&crc32fast::hash(&header).to_le_bytes());
    header
}

/// Reads the journal of the write in `write_dir` if it was started for `job` and its pack
/// holds every byte the journal's records promise; `None` otherwise (the write is then not
/// resumed but removed). A torn last record (the process died while writing it) is ignored.
fn read_checkpoint(write_dir: &Path, job: &str) -> Option<Checkpoint> {
    let bytes = std::fs::read(write_dir.join(JOURNAL_FILE)).ok()?;
    let header = journal_header(job);
    if !bytes.starts_with(&header) {
        return None;
    }
    let mut at = header.len();
    let mut state = Checkpoint {
        pack_end: PACK_HEADER_BYTES,
        journal_len: at as u64,
        ..Checkpoint::default()
    };
    // Record: length of body (u32), body, CRC of body (u32); the body is texture count (u32),
    // then per texture its table entry and colour, then mip count (u32) and the mips' CRCs.
    while let Some(body) = bytes
        .get(at..at + 4)
        .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
        .and_then(|len| bytes.get(at + 4..at + 4 + len + 4))
    {
        let (body, crc) = body.split_at(body.len() - 4);
        if crc32fast::hash(body) != u32::from_le_bytes([crc[0], crc[1], crc[2], crc[3]]) {
            break;
        }
        // A whole record that does not continue the previous ones: not our write.
        apply_record(&mut state, body)?;
        at += 4 + body.len() + 4;
        state.journal_len = at as u64;
    }
    let pack_len = std::fs::metadata(write_dir.join(PACK_FILE)).ok()?.len();
    (pack_len >= state.pack_end).then_some(state)
}

/// Adds one record's textures to `state`; `None` when the record does not continue it.
fn apply_record(state: &mut Checkpoint, body: &[u8]) -> Option<()> {
    let count = u32::from_le_bytes(body.get(..4)?.try_into().ok()?) as usize;
    let entries = body.get(4..4 + count * (TEXTURE_RECORD_BYTES + 4))?;
    let rest = &body[4 + entries.len()..];
    let mip_count = u32::from_le_bytes(rest.get(..4)?.try_into().ok()?) as usize;
    let checksums = rest.get(4..4 + mip_count * 4).filter(|c| c.len() + 4 == rest.len())?;
    let mut mips = 0usize;
    for entry in entries.chunks_exact(TEXTURE_RECORD_BYTES + 4) {
        let info = TextureInfo::decode(entry[..TEXTURE_RECORD_BYTES].try_into().ok()?).ok()?;
        // Each texture starts where the previous one ended, as `add_texture` appends them.
        if info.offset() != state.pack_end {
            return None;
        }
        state.pack_end += info.chain_len();
        mips += info.mip_count() as usize;
        state.textures.push(info);
        state.colours.push(entry[TEXTURE_RECORD_BYTES..].try_into().ok()?);
    }
    if mips != mip_count {
        return None;
    }
    state.mip_checksums.extend(
        checksums
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])),
    );
    Some(())
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

    /// Starts a write that survives the process: [`DatasetWriter::checkpoint`] makes every
    /// texture appended so far durable, and a later `create_resumable` of the same `dir` and
    /// `job` (a description of what is written: same job, same bytes) continues after the
    /// last checkpoint instead of starting over; [`DatasetWriter::texture_count`] says where.
    /// An error, a panic or a killed process keeps the partial write for that; any other
    /// writer of `dir` removes it. For writes that take hours (`gen --preset berlin`).
    pub fn create_resumable(dir: &Path, job: &str) -> Result<Self, DatasetError> {
        if job.len() > MAX_JOB_BYTES {
            return Err(DatasetError::InvalidInput(format!(
                "resumable job description of {} bytes (at most {MAX_JOB_BYTES})",
                job.len()
            )));
        }
        let mut found = None;
        let pending = PendingWrite::begin_resumable(dir, &mut |write_dir| {
            found = read_checkpoint(write_dir, job);
            found.is_some()
        })?;
        let journal_path = pending.path(JOURNAL_FILE);
        let Some(state) = found.filter(|_| pending.resumed()) else {
            let mut writer = Self::start(pending)?;
            std::fs::write(&journal_path, journal_header(job)).map_err(|e| DatasetError::io(&journal_path, e))?;
            let file = std::fs::OpenOptions::new()
                .append(true)
                .open(&journal_path)
                .and_then(|f| f.sync_all().map(|()| f))
                .map_err(|e| DatasetError::io(&journal_path, e))?;
            writer.journal = Some(Journal {
                path: journal_path,
                file,
                textures: 0,
            });
            return Ok(writer);
        };
        // Whatever follows the last checkpoint (a torn record, bytes of textures it does not
        // list) is cut off, so that appending continues exactly after it.
        fn io(path: &Path) -> impl Fn(std::io::Error) -> DatasetError + '_ {
            move |e| DatasetError::io(path, e)
        }
        let journal = std::fs::OpenOptions::new()
            .write(true)
            .open(&journal_path)
            .map_err(io(&journal_path))?;
        journal.set_len(state.journal_len).map_err(io(&journal_path))?;
        let pack_path = pending.path(PACK_FILE);
        let mut file = std::fs::OpenOptions::new()
            .write(true)
            .open(&pack_path)
            .map_err(io(&pack_path))?;
        file.set_len(state.pack_end)
            .and_then(|()| file.seek(SeekFrom::End(0)).map(|_| ()))
            .map_err(io(&pack_path))?;
        let mut journal_file = journal;
        journal_file.seek(SeekFrom::End(0)).map_err(io(&journal_path))?;
        let textures = state.textures.len();
        Ok(Self {
            pending,
            pack_path,
            pack: BufWriter::with_capacity(1 << 20, file),
            next_offset: state.pack_end,
            mips: state.mip_checksums.len() as u64,
            textures: state.textures,
            colours: state.colours,
            mip_checksums: state.mip_checksums,
            journal: Some(Journal {
                path: journal_path,
                file: journal_file,
                textures,
            }),
        })
    }

    /// Whether this writer continues a write an earlier process left (see
    /// [`DatasetWriter::create_resumable`]).
    pub fn resumed(&self) -> bool {
        self.pending.resumed()
    }

    /// Makes every texture appended so far durable for a later
    /// [`DatasetWriter::create_resumable`]: flushes the pack to the disk, then records the
    /// new textures in the journal and flushes it. Does nothing for other writers.
    pub fn checkpoint(&mut self) -> Result<(), DatasetError> {
        let Some(journal) = &mut self.journal else {
            return Ok(());
        };
        let new = journal.textures..self.textures.len();
        if new.is_empty() {
            return Ok(());
        }
        self.pack
            .flush()
            .and_then(|()| self.pack.get_ref().sync_data())
            .map_err(|e| DatasetError::io(&self.pack_path, e))?;
        let first_mip: usize = self.textures[..new.start].iter().map(|t| t.mip_count() as usize).sum();
        let mut body = (new.len() as u32).to_le_bytes().to_vec();
        for t in new.clone() {
            body.extend_from_slice(&self.textures[t].encode());
            body.extend_from_slice(&self.colours[t]);
        }
        let checksums = &self.mip_checksums[first_mip..];
        body.extend_from_slice(&(checksums.len() as u32).to_le_bytes());
        body.extend(checksums.iter().flat_map(|c| c.to_le_bytes()));
        let mut record = (body.len() as u32).to_le_bytes().to_vec();
        record.extend_from_slice(&body);
        record.extend_from_slice(&crc32fast::hash(&body).to_le_bytes());
        journal
            .file
            .write_all(&record)
            .and_then(|()| journal.file.sync_data())
            .map_err(|e| DatasetError::io(&journal.path, e))?;
        journal.textures = new.end;
        Ok(())
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
            journal: None,
        })
    }

    /// Bytes of the pack so far, header included (the pack's length once finished).
    pub fn pack_len(&self) -> u64 {
        self.next_offset
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

    /// Appends every texture of `part` after those written so far, in its id order: its
    /// pack's mip chains are copied file to file (`copy_file_range` where the file system
    /// has it, so the bytes need not pass through this process), its table entries moved,
    /// its colours and mip checksums taken as they are. The chains must fill `part`'s pack
    /// back to back ([`super::shard::part_pack_body`]). Returns the bytes copied.
    ///
    /// The checksums are `part`'s own, not recomputed: check its mips first
    /// ([`super::verify_dataset`]) where they may be damaged.
    pub fn append_pack_of(&mut self, part: &Dataset) -> Result<u64, DatasetError> {
        let body = part_pack_body(part)?;
        let source_path = part.textures.pack_path().to_path_buf();
        let mut moved = Vec::with_capacity(part.textures.textures().len());
        for (t, info) in part.textures.textures().iter().enumerate() {
            let offset = info.offset() - body.start + self.next_offset;
            moved.push(info.moved_to(offset).map_err(|e| {
                DatasetError::InvalidInput(format!(
                    "texture {} ({t} of {}): {e}",
                    self.textures.len() + t,
                    part.dir().display()
                ))
            })?);
        }
        let mut checksums = Vec::new();
        for (t, info) in part.textures.textures().iter().enumerate() {
            for level in 0..info.mip_count() {
                checksums.push(part.textures.mip_checksum(t as u32, level)?);
            }
        }
        u32::try_from(self.textures.len() + moved.len())
            .ok()
            .filter(|&n| n < u32::MAX)
            .ok_or_else(|| DatasetError::InvalidInput("more than 2^32 - 1 textures".into()))?;
        self.pack.flush().map_err(|e| DatasetError::io(&self.pack_path, e))?;
        let mut source = File::open(&source_path).map_err(|e| DatasetError::io(&source_path, e))?;
        source
            .seek(SeekFrom::Start(body.start))
            .map_err(|e| DatasetError::io(&source_path, e))?;
        let len = body.end - body.start;
        // `File` to `File`: std copies inside the kernel (copy_file_range, then sendfile).
        let copied = std::io::copy(&mut std::io::Read::take(&mut source, len), self.pack.get_mut())
            .map_err(|e| DatasetError::io(&self.pack_path, e))?;
        if copied != len {
            return Err(DatasetError::truncated(
                &source_path,
                "the pack ended while it was copied".to_string(),
                body.start,
                body.end,
                body.start + copied,
            ));
        }
        self.next_offset += len;
        self.mips += checksums.len() as u64;
        self.textures.extend(moved);
        self.colours.extend_from_slice(part.colormap.colours());
        self.mip_checksums.extend(checksums);
        Ok(len)
    }

    /// Adds a file `name` beside the dataset's own in this write (written and flushed now),
    /// so it appears with them, atomically, at [`DatasetWriter::finish`]: a shard's record.
    /// `name` is a plain file name other than the format's.
    pub fn add_file(&mut self, name: &str, bytes: &[u8]) -> Result<(), DatasetError> {
        let reserved = DATASET_FILES.contains(&name) || name == SCENE_FILE || name == JOURNAL_FILE;
        if name.is_empty() || name.contains(['/', '\\']) || name.starts_with('.') || reserved {
            return Err(DatasetError::InvalidInput(format!(
                "{name:?} cannot be added to a dataset's write (a plain file name other than the format's)"
            )));
        }
        let path = self.pending.path(name);
        // A resumed write may hold one from before: the new one replaces it.
        let _ = std::fs::remove_file(&path);
        write_new_durably(&path, bytes)
    }

    /// Validates `scene` (every mesh texture must exist), writes it in tiles (`tiles.bin`,
    /// `geometry.pack`, `geometry.crc`) and the tables, completes the pack header, flushes everything, reopens the new dataset with every check
    /// [`Dataset::open`] makes, and only then makes it the directory's dataset.
    pub fn finish(self, scene: &Scene) -> Result<WriteSummary, DatasetError> {
        let count = self.textures.len() as u32;
        let write_id = self.pending.write_id();
        let mut scene_bytes = 0;
        for (name, bytes) in encode_scene_files(scene, &self.pending.path(""), write_id, count)? {
            write_new_durably(&self.pending.path(name), &bytes)?;
            scene_bytes += bytes.len() as u64;
        }

        let mut file = self
            .pack
            .into_inner()
            .map_err(|e| DatasetError::io(&self.pack_path, e.into_error()))?;
        let header = pack_header(write_id, self.textures.len() as u64, self.next_offset);
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
        let journal = self.journal.map(|j| j.path);
        self.pending.commit()?;
        if let Some(journal) = journal {
            // The dataset is complete without it; a failure here leaves an unread file.
            let _ = std::fs::remove_file(journal);
        }

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
