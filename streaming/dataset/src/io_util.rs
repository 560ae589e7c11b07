//! Little-endian header encoding shared by the dataset files.

use std::path::Path;

use super::error::{DatasetError, Magic};
use super::format::FORMAT_VERSION;

/// Length of the common header of `textures.meta`, `colormap.bin` and `textures.crc`:
/// magic (8), version (u32), flags (u32, 0), write id (u64), record count (u64), CRC-32 of
/// the header's first 32 bytes and the body (u32), reserved (u32).
pub(crate) const TABLE_HEADER_BYTES: usize = 40;

/// The first format version (files at the top of the directory, no manifest), which
/// `citystream upgrade` converts.
pub(crate) const LEGACY_VERSION: u32 = 1;

/// Format version 2 (no CRS), which `citystream upgrade` converts.
pub(crate) const VERSION_2: u32 = 2;

/// Format version 3 (one `scene.bin`, one origin), which `citystream upgrade` converts.
pub(crate) const VERSION_3: u32 = 3;

/// Whether a manifest of format `version` names a dataset `citystream upgrade` converts.
pub(crate) fn upgradable_manifest(version: u32) -> bool {
    matches!(version, VERSION_2 | VERSION_3)
}

/// Reads a whole file, mapping "not found" to [`DatasetError::Missing`].
pub(crate) fn read_all(path: &Path) -> Result<Vec<u8>, DatasetError> {
    ensure_regular_file(path)
        .and_then(|()| std::fs::read(path))
        .map_err(|e| DatasetError::io(path, e))
}

/// Fails unless `path` is a regular file (or a link to one): opening a FIFO
/// for reading would block until a writer appears, and a device never ends.
pub fn ensure_regular_file(path: &Path) -> std::io::Result<()> {
    if std::fs::metadata(path)?.is_file() {
        Ok(())
    } else {
        Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            "not a regular file (a directory, FIFO or device)",
        ))
    }
}

/// Creates a new file (never replacing one), writes `bytes` and flushes them to disk.
pub(crate) fn write_new_durably(path: &Path, bytes: &[u8]) -> Result<(), DatasetError> {
    use std::io::Write;
    std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(path)
        .and_then(|mut file| {
            file.write_all(bytes)?;
            file.sync_all()
        })
        .map_err(|e| DatasetError::io(path, e))
}

pub(crate) fn u32_at(bytes: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]])
}

pub(crate) fn u64_at(bytes: &[u8], at: usize) -> u64 {
    let mut b = [0u8; 8];
    b.copy_from_slice(&bytes[at..at + 8]);
    u64::from_le_bytes(b)
}

pub(crate) fn f32_at(bytes: &[u8], at: usize) -> f32 {
    f32::from_bits(u32_at(bytes, at))
}

pub(crate) fn f64_at(bytes: &[u8], at: usize) -> f64 {
    f64::from_bits(u64_at(bytes, at))
}

/// Checks length, magic, version (`version`: the current one, or the previous one for the
/// upgrade) and the zero flags word of a header of `header_len` bytes, and returns the write
/// id stored after them.
pub(crate) fn check_prefix(
    path: &Path,
    bytes: &[u8],
    magic: &[u8; 8],
    header_len: usize,
    version: u32,
) -> Result<u64, DatasetError> {
    check_versioned_prefix(path, bytes, magic, header_len, version)?;
    Ok(u64_at(bytes, 16))
}

/// The version check of [`check_prefix`] (version 1 has no write id there). A file of an
/// older version than this build's is [`DatasetError::NeedsUpgrade`].
pub(crate) fn check_versioned_prefix(
    path: &Path,
    bytes: &[u8],
    magic: &[u8; 8],
    header_len: usize,
    expected_version: u32,
) -> Result<(), DatasetError> {
    if bytes.len() < header_len {
        return Err(DatasetError::truncated(
            path,
            "the header",
            0,
            header_len as u64,
            bytes.len() as u64,
        ));
    }
    let mut found = [0u8; 8];
    found.copy_from_slice(&bytes[..8]);
    if &found != magic {
        return Err(DatasetError::BadMagic {
            path: path.to_path_buf(),
            found: Magic(found),
            expected: Magic(*magic),
        });
    }
    let version = u32_at(bytes, 8);
    if version != expected_version {
        let upgradable = version == LEGACY_VERSION || upgradable_manifest(version);
        return Err(if upgradable && expected_version == FORMAT_VERSION {
            DatasetError::NeedsUpgrade {
                path: path.to_path_buf(),
                found: version,
            }
        } else {
            DatasetError::UnsupportedVersion {
                path: path.to_path_buf(),
                found: version,
                supported: expected_version,
            }
        });
    }
    let flags = u32_at(bytes, 12);
    if flags != 0 {
        return Err(DatasetError::Corrupt {
            path: path.to_path_buf(),
            offset: 12,
            what: format!("header flags are {flags:#x}, expected 0"),
        });
    }
    Ok(())
}

/// Starts a header of this version: magic, version, zero flags, write id.
pub(crate) fn header_prefix(magic: &[u8; 8], write_id: u64) -> Vec<u8> {
    header_prefix_of_version(magic, FORMAT_VERSION, write_id)
}

/// [`header_prefix`] of a file of format `version` (the files of format 4, written ahead
/// of the version's switch).
pub(crate) fn header_prefix_of_version(magic: &[u8; 8], version: u32, write_id: u64) -> Vec<u8> {
    let mut out = Vec::with_capacity(TABLE_HEADER_BYTES);
    out.extend_from_slice(magic);
    out.extend_from_slice(&version.to_le_bytes());
    out.extend_from_slice(&0u32.to_le_bytes());
    out.extend_from_slice(&write_id.to_le_bytes());
    out
}

/// CRC-32 of the header bytes before the checksum field and of the body, so a flipped
/// bit anywhere in the file (counts, write id and origin included) is caught.
pub(crate) fn header_and_body_crc(header: &[u8], body: &[u8]) -> u32 {
    let mut hasher = crc32fast::Hasher::new();
    hasher.update(header);
    hasher.update(body);
    hasher.finalize()
}

/// Encodes a table file: common header then `body`, whose records number `count`.
pub(crate) fn encode_table(magic: &[u8; 8], write_id: u64, count: u64, body: &[u8]) -> Vec<u8> {
    encode_table_of_version(magic, FORMAT_VERSION, write_id, count, body)
}

/// [`encode_table`] of a file of format `version`.
pub(crate) fn encode_table_of_version(
    magic: &[u8; 8],
    version: u32,
    write_id: u64,
    count: u64,
    body: &[u8],
) -> Vec<u8> {
    let mut out = header_prefix_of_version(magic, version, write_id);
    out.extend_from_slice(&count.to_le_bytes());
    let crc = header_and_body_crc(&out, body);
    out.extend_from_slice(&crc.to_le_bytes());
    out.extend_from_slice(&0u32.to_le_bytes());
    debug_assert_eq!(out.len(), TABLE_HEADER_BYTES);
    out.extend_from_slice(body);
    out
}

/// A table file's record count, its body and the write id in its header.
pub(crate) struct Table<'a> {
    pub count: u64,
    pub body: &'a [u8],
    pub write_id: u64,
}

/// Decodes a table file written by [`encode_table`] whose records are `record_len` bytes:
/// checks header, exact size and checksum (header and body).
pub(crate) fn decode_table<'a>(
    path: &Path,
    bytes: &'a [u8],
    magic: &[u8; 8],
    record_len: usize,
    version: u32,
) -> Result<Table<'a>, DatasetError> {
    let write_id = check_prefix(path, bytes, magic, TABLE_HEADER_BYTES, version)?;
    let count = u64_at(bytes, 24);
    let body = table_body(path, bytes, count, record_len, TABLE_HEADER_BYTES)?;
    let stored = u32_at(bytes, 32);
    let computed = header_and_body_crc(&bytes[..32], body);
    if stored != computed {
        return Err(DatasetError::Checksum {
            path: path.to_path_buf(),
            what: "the table (header and records)".into(),
            offset: 0,
            end: bytes.len() as u64,
            stored,
            computed,
        });
    }
    Ok(Table { count, body, write_id })
}

/// The body of a table of `count` records after a `header_len`-byte header, checking that
/// the file holds exactly that many.
pub(crate) fn table_body<'a>(
    path: &Path,
    bytes: &'a [u8],
    count: u64,
    record_len: usize,
    header_len: usize,
) -> Result<&'a [u8], DatasetError> {
    let count_offset = if header_len == TABLE_HEADER_BYTES { 24 } else { 16 };
    let body_len = count
        .checked_mul(record_len as u64)
        .ok_or_else(|| DatasetError::Corrupt {
            path: path.to_path_buf(),
            offset: count_offset,
            what: format!("record count {count} is absurd"),
        })?;
    let end = body_len.saturating_add(header_len as u64);
    expect_end(path, bytes, header_len as u64, end, || {
        format!("{count} records of {record_len} bytes")
    })?;
    Ok(&bytes[header_len..])
}

/// Refuses a file that does not end exactly at `end`: its header says what it holds (`what`,
/// bytes `offset..end`), so a shorter file lost data and a longer one is not what was written.
pub(crate) fn expect_end(
    path: &Path,
    bytes: &[u8],
    offset: u64,
    end: u64,
    what: impl FnOnce() -> String,
) -> Result<(), DatasetError> {
    if end == bytes.len() as u64 {
        Ok(())
    } else {
        Err(DatasetError::truncated(path, what(), offset, end, bytes.len() as u64))
    }
}
