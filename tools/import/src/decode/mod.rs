//! Compressed glTF geometry, decoded before the glTF reader sees it: Draco primitives
//! ([`draco`], `KHR_draco_mesh_compression`), meshopt buffer views ([`meshopt`],
//! `EXT_meshopt_compression` with its filters) and quantized attributes ([`quantized`],
//! `KHR_mesh_quantization`: integer positions, normals and texture coordinates).
//!
//! Every decoder reads untrusted bytes: offsets and lengths are checked against the buffers
//! before a byte is read, the sizes a stream declares are bounded against the bytes it
//! brings before anything is allocated, and every failure is a [`DecodeError`] naming what
//! and where, never a panic.

pub mod draco;
pub mod meshopt;
pub mod quantized;

/// Most bytes the compressed geometry of one glTF may decode to (as the import's other
/// per-file bounds: 1 GiB).
pub const MAX_DECODED_BYTES: u64 = 1 << 30;

/// Why compressed geometry could not be decoded.
#[derive(Debug, thiserror::Error)]
pub enum DecodeError {
    /// The glTF's description of the compressed data is wrong (a missing or out-of-range
    /// field).
    #[error("{what}: {reason}")]
    Invalid { what: String, reason: String },
    /// The compressed bytes do not decode.
    #[error("{what}: the {codec} data does not decode: {reason}")]
    Corrupt {
        what: String,
        codec: &'static str,
        reason: String,
    },
    /// The data would decode to more than the import holds.
    #[error("{what}: declares {bytes} decoded bytes, more than {limit} ({why})")]
    TooLarge {
        what: String,
        bytes: u64,
        limit: u64,
        why: &'static str,
    },
}

impl DecodeError {
    pub(crate) fn invalid(what: impl Into<String>, reason: impl Into<String>) -> Self {
        Self::Invalid {
            what: what.into(),
            reason: reason.into(),
        }
    }
}

/// The `start..start + len` bytes of `buffer`, or an error naming `what` when they do not lie
/// inside it.
pub(crate) fn slice<'a>(buffer: &'a [u8], start: u64, len: u64, what: &str) -> Result<&'a [u8], DecodeError> {
    let range = usize::try_from(start)
        .ok()
        .zip(usize::try_from(len).ok())
        .and_then(|(s, l)| Some(s..s.checked_add(l)?))
        .filter(|r| r.end <= buffer.len());
    match range {
        Some(range) => Ok(&buffer[range]),
        None => Err(DecodeError::invalid(
            what,
            format!("bytes {start}..+{len} lie outside its buffer of {} bytes", buffer.len()),
        )),
    }
}
