//! Datasets built in shards and joined (`docs/SHARDS.md`): the record that names a shard's
//! job, and one dataset's files joined from several.
//!
//! A shard is an ordinary dataset (atomic and resumable as every write) whose write
//! directory also holds [`SHARD_RECORD_FILE`], written before its manifest switches: the
//! job (the command's parameters and a fingerprint of what it lays out), which shard of how
//! many, and its totals. So a shard's record and its files are one write; a reader that
//! finds the record through the manifest has the files it describes.
//!
//! Joining: textures of part `k` follow those of parts `0..k` (ids offset by their
//! count), their mip chains follow in the pack in the same order (each part's pack minus
//! its header), tables and colours are concatenated, and the scenes appended in part
//! order. A part's chains must lie back to back from the pack header on, as
//! [`super::DatasetWriter`] writes them, so the joined pack is the parts' packs in order.

use std::ops::Range;
use std::path::Path;

use super::colormap::{CRC_MAGIC, MAGIC as COLORMAP_MAGIC};
use super::dataset::Dataset;
use super::error::DatasetError;
use super::files::{CHECKSUM_FILE, COLORMAP_FILE, META_FILE};
use super::format::TextureInfo;
use super::io_util::{encode_table, header_prefix};
use super::pack::{META_MAGIC, PACK_HEADER_BYTES, PACK_HEADER_CRC_AT, PACK_MAGIC};
use super::scene::Scene;
use super::tiled::encode_scene_files;

/// The folder of a sharded build's output holding shard `I` in `shards/I/`.
pub const SHARDS_DIR: &str = "shards";
/// The file in a shard's write directory that names its job ([`ShardRecord`]).
pub const SHARD_RECORD_FILE: &str = "shard.record";
const RECORD_FIRST_LINE: &str = "citystream shard record 1";
/// The most shards a job may have: far more machines than any array job runs, few enough
/// that a merge lists them in bounded memory.
pub const MAX_SHARDS: u32 = 65_536;
/// A job description is a command line and a fingerprint, not data.
const MAX_JOB_BYTES: usize = 4096;

/// What a shard is: its job, its place among the job's shards, and its totals.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ShardRecord {
    /// The job every shard of one build shares (one line of text): the command's
    /// parameters and a fingerprint of the layout it divides.
    pub job: String,
    /// Which shard, from 0.
    pub index: u32,
    /// How many shards the job has.
    pub count: u32,
    /// Textures the shard holds.
    pub textures: u32,
    /// Meshes the shard's scene holds.
    pub meshes: u32,
    /// Bytes of the shard's `textures.pack`.
    pub pack_bytes: u64,
}

impl ShardRecord {
    /// The record as text: one `key value` line each, the last the CRC-32 of the others.
    pub fn encode(&self) -> Result<Vec<u8>, DatasetError> {
        if self.job.contains(['\n', '\r']) || self.job.len() > MAX_JOB_BYTES {
            return Err(DatasetError::InvalidInput(format!(
                "a shard's job description is one line of at most {MAX_JOB_BYTES} bytes: {:?}",
                self.job
            )));
        }
        if self.index >= self.count {
            return Err(DatasetError::InvalidInput(format!(
                "shard {} of {}: the index is not below the count",
                self.index, self.count
            )));
        }
        if self.count > MAX_SHARDS {
            return Err(DatasetError::InvalidInput(format!(
                "{} shards: at most {MAX_SHARDS}",
                self.count
            )));
        }
        let mut text = format!(
            "{RECORD_FIRST_LINE}\njob {}\nindex {}\ncount {}\ntextures {}\nmeshes {}\npack_bytes {}\n",
            self.job, self.index, self.count, self.textures, self.meshes, self.pack_bytes
        );
        text.push_str(&format!("crc32 {:08x}\n", crc32fast::hash(text.as_bytes())));
        Ok(text.into_bytes())
    }

    /// Reads a record [`ShardRecord::encode`] wrote; `path` names it in errors.
    pub fn decode(path: &Path, bytes: &[u8]) -> Result<Self, DatasetError> {
        let corrupt = |offset: usize, what: String| DatasetError::Corrupt {
            path: path.to_path_buf(),
            offset: offset as u64,
            what,
        };
        let text = std::str::from_utf8(bytes).map_err(|e| corrupt(e.valid_up_to(), "not UTF-8 text".into()))?;
        let crc_at = text
            .rfind("crc32 ")
            .ok_or_else(|| corrupt(0, "no crc32 line: not a shard record".into()))?;
        let stored = text[crc_at + 6..].trim_end_matches('\n');
        let computed = crc32fast::hash(&text.as_bytes()[..crc_at]);
        match u32::from_str_radix(stored, 16) {
            Ok(stored) if stored == computed && text.ends_with('\n') => {}
            Ok(stored) => {
                return Err(DatasetError::Checksum {
                    path: path.to_path_buf(),
                    what: "the shard record".into(),
                    offset: 0,
                    end: crc_at as u64,
                    stored,
                    computed,
                })
            }
            Err(_) => return Err(corrupt(crc_at, format!("crc32 {stored:?} is not 8 hex digits"))),
        }
        let mut lines = text[..crc_at].lines();
        if lines.next() != Some(RECORD_FIRST_LINE) {
            return Err(corrupt(
                0,
                format!("not a shard record (first line is not {RECORD_FIRST_LINE:?})"),
            ));
        }
        let mut field = |key: &str| -> Result<&str, DatasetError> {
            let line = lines.next().unwrap_or("");
            line.strip_prefix(key)
                .and_then(|rest| rest.strip_prefix(' '))
                .ok_or_else(|| corrupt(0, format!("expected the {key} line, found {line:?}")))
        };
        let job = field("job")?.to_owned();
        fn number<T: std::str::FromStr>(path: &Path, key: &str, text: &str) -> Result<T, DatasetError> {
            text.parse().map_err(|_| DatasetError::Corrupt {
                path: path.to_path_buf(),
                offset: 0,
                what: format!("{key} {text:?} is not a number"),
            })
        }
        let index = number(path, "index", field("index")?)?;
        let count = number(path, "count", field("count")?)?;
        let textures = number(path, "textures", field("textures")?)?;
        let meshes = number(path, "meshes", field("meshes")?)?;
        let pack_bytes = number(path, "pack_bytes", field("pack_bytes")?)?;
        let record = Self {
            job,
            index,
            count,
            textures,
            meshes,
            pack_bytes,
        };
        if record.index >= record.count {
            return Err(corrupt(
                0,
                format!("index {} is not below count {}", record.index, record.count),
            ));
        }
        if record.count > MAX_SHARDS {
            return Err(corrupt(
                0,
                format!("count {} is more than the most shards, {MAX_SHARDS}", record.count),
            ));
        }
        Ok(record)
    }
}

/// The byte range of `part`'s pack that holds its mip chains: from the header to the end,
/// which its chains must fill back to back in id order (as [`super::DatasetWriter`] writes
/// them), so that the range placed after another pack's keeps every chain whole.
pub fn part_pack_body(part: &Dataset) -> Result<Range<u64>, DatasetError> {
    let mut end = PACK_HEADER_BYTES;
    for (t, info) in part.textures.textures().iter().enumerate() {
        if info.offset() != end {
            return Err(DatasetError::Corrupt {
                path: part.files().path(META_FILE),
                offset: (40 + t * 10) as u64,
                what: format!(
                    "texture {t}'s mip chain starts at {} of the pack, not right after the previous one ({end}): \
                     only packs written in id order can be joined",
                    info.offset()
                ),
            });
        }
        end += info.chain_len();
    }
    if end != part.textures.pack_len() {
        return Err(DatasetError::Corrupt {
            path: part.files().path(super::files::PACK_FILE),
            offset: end,
            what: format!(
                "the mip chains end at {end} but the pack is {} bytes: only packs written in id order can be joined",
                part.textures.pack_len()
            ),
        });
    }
    Ok(PACK_HEADER_BYTES..end)
}

/// One dataset's tables and scene joined from parts, for a store written object by object
/// (the local writer joins with [`super::DatasetWriter::append_pack_of`] instead).
#[derive(Debug, Default)]
pub struct JoinedTables {
    textures: Vec<TextureInfo>,
    colours: Vec<[u8; 4]>,
    checksums: Vec<u32>,
    scene: Option<Scene>,
    pack_len: u64,
}

impl JoinedTables {
    /// Nothing joined yet.
    pub fn new() -> Self {
        Self {
            pack_len: PACK_HEADER_BYTES,
            ..Self::default()
        }
    }

    /// Joins `part` after those joined so far; returns the range of its pack that follows
    /// the joined pack's bytes so far ([`part_pack_body`]).
    pub fn push(&mut self, part: &Dataset) -> Result<Range<u64>, DatasetError> {
        let body = part_pack_body(part)?;
        let offset = u32::try_from(self.textures.len())
            .map_err(|_| DatasetError::InvalidInput("more than 2^32 textures".into()))?;
        for info in part.textures.textures() {
            let moved = info
                .moved_to(info.offset() - PACK_HEADER_BYTES + self.pack_len)
                .map_err(|e| DatasetError::InvalidInput(format!("{}: {e}", part.dir().display())))?;
            self.textures.push(moved);
        }
        self.colours.extend_from_slice(part.colormap.colours());
        let count = part.textures.len();
        for t in 0..count {
            for level in 0..part.textures.textures()[t as usize].mip_count() {
                self.checksums.push(part.textures.mip_checksum(t, level)?);
            }
        }
        match &mut self.scene {
            None => self.scene = Some(part.scene.clone()),
            Some(scene) => scene
                .append(&part.scene, offset)
                .map_err(|e| DatasetError::InvalidInput(format!("{}: {e}", part.dir().display())))?,
        }
        self.pack_len += body.end - body.start;
        Ok(body)
    }

    /// Textures joined so far.
    pub fn texture_count(&self) -> usize {
        self.textures.len()
    }

    /// Bytes of the joined pack, header included.
    pub fn pack_len(&self) -> u64 {
        self.pack_len
    }

    /// The joined scene (an empty one at the origin before any part).
    pub fn scene(&self) -> Scene {
        self.scene.clone().unwrap_or_else(|| Scene::new([0.0; 3]))
    }

    /// The 64-byte header of the joined pack of write `write_id`.
    pub fn pack_header(&self, write_id: u64) -> Vec<u8> {
        pack_header(write_id, self.textures.len() as u64, self.pack_len)
    }

    /// The six files other than the pack, of write `write_id`, by name: `tiles.bin`,
    /// `geometry.crc`, `geometry.pack`, `textures.meta`, `colormap.bin`, `textures.crc`.
    /// `root` names the scene's files in errors.
    pub fn encode(&self, root: &Path, write_id: u64) -> Result<Vec<(&'static str, Vec<u8>)>, DatasetError> {
        let scene = self.scene();
        let texture_count = u32::try_from(self.textures.len())
            .map_err(|_| DatasetError::InvalidInput(format!("{} textures, more than 2^32", self.textures.len())))?;
        let meta: Vec<u8> = self.textures.iter().flat_map(|t| t.encode()).collect();
        let colours: Vec<u8> = self.colours.iter().flatten().copied().collect();
        let checksums: Vec<u8> = self.checksums.iter().flat_map(|c| c.to_le_bytes()).collect();
        let count = self.textures.len() as u64;
        let mut files: Vec<_> = encode_scene_files(&scene, root, write_id, texture_count)?.into();
        files.extend([
            (META_FILE, encode_table(META_MAGIC, write_id, count, &meta)),
            (COLORMAP_FILE, encode_table(COLORMAP_MAGIC, write_id, count, &colours)),
            (
                CHECKSUM_FILE,
                encode_table(CRC_MAGIC, write_id, self.checksums.len() as u64, &checksums),
            ),
        ]);
        Ok(files)
    }
}

/// The 64-byte header of a pack of write `write_id` holding `textures` textures in
/// `pack_len` bytes.
pub(crate) fn pack_header(write_id: u64, textures: u64, pack_len: u64) -> Vec<u8> {
    let mut header = header_prefix(PACK_MAGIC, write_id);
    header.extend_from_slice(&textures.to_le_bytes());
    header.extend_from_slice(&pack_len.to_le_bytes());
    debug_assert_eq!(header.len(), PACK_HEADER_CRC_AT);
    header.extend_from_slice(&crc32fast::hash(&header).to_le_bytes());
    header.resize(PACK_HEADER_BYTES as usize, 0);
    header
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record() -> ShardRecord {
        ShardRecord {
            job: "citystream gen --preset tiny --seed 1, layout 1234abcd".into(),
            index: 2,
            count: 4,
            textures: 60,
            meshes: 61,
            pack_bytes: 12345,
        }
    }

    #[test]
    fn a_record_reads_back_and_a_changed_byte_is_refused() {
        let path = Path::new("shards/2/write-1/shard.record");
        let bytes = record().encode().expect("encode");
        assert_eq!(ShardRecord::decode(path, &bytes).expect("decode"), record());
        for at in 0..bytes.len() {
            let mut damaged = bytes.clone();
            damaged[at] ^= 0x01;
            assert!(
                ShardRecord::decode(path, &damaged).is_err(),
                "byte {at} flipped was accepted"
            );
        }
        assert!(ShardRecord::decode(path, &bytes[..bytes.len() - 1]).is_err());
    }

    #[test]
    fn bad_records_are_not_written() {
        let mut two_lines = record();
        two_lines.job.push_str("\nindex 0");
        assert!(two_lines.encode().is_err());
        let mut past_the_end = record();
        past_the_end.index = 4;
        assert!(past_the_end.encode().is_err());
    }
}
