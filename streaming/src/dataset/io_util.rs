//! Little-endian header encoding shared by the dataset files.

use std::path::Path;

use super::error::{DatasetError, Magic};
use super::FORMAT_VERSION;

/// Length of the common header of `textures.meta`, `colormap.bin` and `textures.crc`:
/// magic (8), version (u32), flags (u32, 0), record count (u64), body CRC-32 (u32), reserved (u32).
pub(crate) const TABLE_HEADER_BYTES: usize = 32;

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

/// Writes a whole file.
pub(crate) fn write_all(path: &Path, bytes: &[u8]) -> Result<(), DatasetError> {
    std::fs::write(path, bytes).map_err(|e| DatasetError::io(path, e))
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

/// Checks length, magic, version and the zero flags word of a header of `header_len` bytes.
pub(crate) fn check_prefix(path: &Path, bytes: &[u8], magic: &[u8; 8], header_len: usize) -> Result<(), DatasetError> {
    if bytes.len() < header_len {
        return Err(DatasetError::Truncated {
            path: path.to_path_buf(),
            what: "the header".into(),
            offset: 0,
            end: header_len as u64,
            file_len: bytes.len() as u64,
        });
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
    if version != FORMAT_VERSION {
        return Err(DatasetError::UnsupportedVersion {
            path: path.to_path_buf(),
            found: version,
            supported: FORMAT_VERSION,
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

/// Starts a header: magic, version, zero flags.
pub(crate) fn header_prefix(magic: &[u8; 8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(TABLE_HEADER_BYTES);
    out.extend_from_slice(magic);
    out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    out.extend_from_slice(&0u32.to_le_bytes());
    out
}

/// Encodes a table file: common header then `body`, whose records number `count`.
pub(crate) fn encode_table(magic: &[u8; 8], count: u64, body: &[u8]) -> Vec<u8> {
    let mut out = header_prefix(magic);
    out.extend_from_slice(&count.to_le_bytes());
    out.extend_from_slice(&crc32fast::hash(body).to_le_bytes());
    out.extend_from_slice(&0u32.to_le_bytes());
    out.extend_from_slice(body);
    out
}

/// Decodes a table file written by [`encode_table`] whose records are `record_len` bytes:
/// checks header, exact size and body checksum, and returns `(count, body)`.
pub(crate) fn decode_table<'a>(
    path: &Path,
    bytes: &'a [u8],
    magic: &[u8; 8],
    record_len: usize,
) -> Result<(u64, &'a [u8]), DatasetError> {
    check_prefix(path, bytes, magic, TABLE_HEADER_BYTES)?;
    let count = u64_at(bytes, 16);
    let body_len = count
        .checked_mul(record_len as u64)
        .ok_or_else(|| DatasetError::Corrupt {
            path: path.to_path_buf(),
            offset: 16,
            what: format!("record count {count} is absurd"),
        })?;
    let end = body_len.saturating_add(TABLE_HEADER_BYTES as u64);
    if end != bytes.len() as u64 {
        return Err(DatasetError::Truncated {
            path: path.to_path_buf(),
            what: format!("{count} records of {record_len} bytes"),
            offset: TABLE_HEADER_BYTES as u64,
            end,
            file_len: bytes.len() as u64,
        });
    }
    let body = &bytes[TABLE_HEADER_BYTES..];
    let stored = u32_at(bytes, 24);
    let computed = crc32fast::hash(body);
    if stored != computed {
        return Err(DatasetError::Checksum {
            path: path.to_path_buf(),
            what: "the record table".into(),
            offset: TABLE_HEADER_BYTES as u64,
            end,
            stored,
            computed,
        });
    }
    Ok((count, body))
}
