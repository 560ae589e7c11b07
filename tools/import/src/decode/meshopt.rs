//! `EXT_meshopt_compression`: buffer views whose bytes are meshoptimizer's vertex codec
//! (`ATTRIBUTES`), index codec (`TRIANGLES`) or index sequence codec (`INDICES`), decoded
//! into the view's own place in its buffer (usually a "fallback" buffer that has no bytes of
//! its own), then filtered (`OCTAHEDRAL`, `QUATERNION`, `EXPONENTIAL`).
//!
//! The codecs are `meshopt-rs`'s (a pure-Rust port of meshoptimizer's decoders, safe on
//! untrusted input); the filters are written here from the extension's specification, as
//! `meshopt-rs` reads the quaternion filter's components as unsigned.
//!
//! Memory: a view's decoded size may be at most [`MAX_RATIO`] times its compressed bytes
//! (plus a block's tail), the most either codec reaches on valid data, and a fallback buffer
//! at most the views that decode into it, so a file cannot ask for more than a bounded
//! multiple of its own size.

use std::collections::HashSet;

use serde_json::Value;

use super::{slice, DecodeError, MAX_DECODED_BYTES};

/// The extension's name.
pub const EXTENSION: &str = "EXT_meshopt_compression";

/// The vertex codec spends at least 2 bits on 16 bytes (a byte group of zero deltas), so
/// valid data decodes to at most 64 times its size; the index codecs to less (a triangle
/// takes at least one byte).
pub const MAX_RATIO: u64 = 64;
/// Bytes a stream's tail and header may add beyond [`MAX_RATIO`].
const SLACK: u64 = 4096;

/// What a buffer view asks for: its `EXT_meshopt_compression` object, read and checked.
#[derive(Debug, Clone, PartialEq)]
struct Compressed {
    buffer: usize,
    offset: u64,
    length: u64,
    stride: usize,
    count: usize,
    mode: Mode,
    filter: Filter,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Mode {
    Attributes,
    Triangles,
    Indices,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Filter {
    None,
    Octahedral,
    Quaternion,
    Exponential,
}

fn extension(others: Option<&serde_json::Map<String, Value>>) -> Option<&Value> {
    others?.get(EXTENSION)
}

/// The compressed description of buffer view `index`, if it has one.
fn compressed(index: usize, view: &gltf::json::buffer::View) -> Result<Option<Compressed>, DecodeError> {
    let Some(ext) = extension(view.extensions.as_ref().map(|e| &e.others)) else {
        return Ok(None);
    };
    let what = format!("bufferView {index} ({EXTENSION})");
    let number = |key: &str, default: Option<u64>| -> Result<u64, DecodeError> {
        match ext.get(key) {
            Some(v) => v
                .as_u64()
                .ok_or_else(|| DecodeError::invalid(&what, format!("{key} is {v}, not a non-negative integer"))),
            None => default.ok_or_else(|| DecodeError::invalid(&what, format!("{key} is missing"))),
        }
    };
    let text = |key: &str| ext.get(key).and_then(Value::as_str);
    let mode = match text("mode") {
        Some("ATTRIBUTES") => Mode::Attributes,
        Some("TRIANGLES") => Mode::Triangles,
        Some("INDICES") => Mode::Indices,
        other => {
            return Err(DecodeError::invalid(
                &what,
                format!("mode {other:?} (ATTRIBUTES, TRIANGLES or INDICES)"),
            ))
        }
    };
    let filter = match text("filter") {
        None | Some("NONE") => Filter::None,
        Some("OCTAHEDRAL") => Filter::Octahedral,
        Some("QUATERNION") => Filter::Quaternion,
        Some("EXPONENTIAL") => Filter::Exponential,
        Some(other) => {
            return Err(DecodeError::invalid(
                &what,
                format!("filter {other:?} is not one of the extension's"),
            ))
        }
    };
    let to_usize = |v: u64, key: &str| {
        usize::try_from(v).map_err(|_| DecodeError::invalid(&what, format!("{key} {v} is out of range")))
    };
    let c = Compressed {
        buffer: to_usize(number("buffer", None)?, "buffer")?,
        offset: number("byteOffset", Some(0))?,
        length: number("byteLength", None)?,
        stride: to_usize(number("byteStride", None)?, "byteStride")?,
        count: to_usize(number("count", None)?, "count")?,
        mode,
        filter,
    };
    let stride_ok = match c.mode {
        Mode::Attributes => c.stride > 0 && c.stride <= 256 && c.stride.is_multiple_of(4),
        Mode::Triangles | Mode::Indices => c.stride == 2 || c.stride == 4,
    };
    if !stride_ok {
        return Err(DecodeError::invalid(
            &what,
            format!("byteStride {} for mode {:?}", c.stride, c.mode),
        ));
    }
    let filter_ok = match c.filter {
        Filter::None => true,
        _ if c.mode != Mode::Attributes => false,
        Filter::Octahedral => c.stride == 4 || c.stride == 8,
        Filter::Quaternion => c.stride == 8,
        Filter::Exponential => true,
    };
    if !filter_ok {
        return Err(DecodeError::invalid(
            &what,
            format!(
                "filter {:?} with mode {:?} and byteStride {}",
                c.filter, c.mode, c.stride
            ),
        ));
    }
    if c.mode == Mode::Triangles && !c.count.is_multiple_of(3) {
        return Err(DecodeError::invalid(&what, format!("TRIANGLES of {} indices", c.count)));
    }
    let decoded = (c.count as u64).saturating_mul(c.stride as u64);
    let bound = c.length.saturating_mul(MAX_RATIO).saturating_add(SLACK);
    if decoded > bound {
        return Err(DecodeError::TooLarge {
            what,
            bytes: decoded,
            limit: bound,
            why: "meshopt data decodes to at most 64 times its size",
        });
    }
    if decoded > view.byte_length.0 {
        return Err(DecodeError::invalid(
            &what,
            format!(
                "{} elements of {} bytes overrun the view's {} bytes",
                c.count, c.stride, view.byte_length.0
            ),
        ));
    }
    Ok(Some(c))
}

/// For each buffer of `root`: the bytes to allocate for it when it is a meshopt fallback
/// buffer without data of its own (zeros the decoded views are written over), `None` for a
/// buffer that has its own bytes. A fallback buffer may be at most as long as the compressed
/// views that decode into it (each bounded by [`MAX_RATIO`]).
pub fn fallback_lengths(root: &gltf::json::Root) -> Result<Vec<Option<u64>>, DecodeError> {
    let mut covered = vec![0u64; root.buffers.len()];
    for (i, view) in root.buffer_views.iter().enumerate() {
        if compressed(i, view)?.is_some() {
            if let Some(c) = covered.get_mut(view.buffer.value()) {
                // Views start 4-byte aligned: allow the padding between them.
                *c = c.saturating_add(view.byte_length.0).saturating_add(4);
            }
        }
    }
    let mut total = 0u64;
    let mut lengths = Vec::with_capacity(root.buffers.len());
    for (i, buffer) in root.buffers.iter().enumerate() {
        let fallback = extension(buffer.extensions.as_ref().map(|e| &e.others))
            .and_then(|e| e.get("fallback"))
            .and_then(Value::as_bool)
            == Some(true);
        if !fallback || buffer.uri.is_some() {
            lengths.push(None);
            continue;
        }
        let length = buffer.byte_length.0;
        let what = format!("buffer {i} ({EXTENSION} fallback)");
        if length > covered[i] {
            return Err(DecodeError::TooLarge {
                what,
                bytes: length,
                limit: covered[i],
                why: "a fallback buffer holds only the compressed views decoded into it",
            });
        }
        total = total.saturating_add(length);
        if total > MAX_DECODED_BYTES {
            return Err(DecodeError::TooLarge {
                what,
                bytes: total,
                limit: MAX_DECODED_BYTES,
                why: "the import's bound on decoded geometry per file",
            });
        }
        lengths.push(Some(length));
    }
    Ok(lengths)
}

/// Decodes every compressed buffer view of `root` into its place in `buffers` (which hold
/// the document's buffers, fallback buffers as zeros); returns the indices of the views
/// decoded.
pub fn decode_views(root: &gltf::json::Root, buffers: &mut [Vec<u8>]) -> Result<HashSet<usize>, DecodeError> {
    let mut decoded_views = HashSet::new();
    for (i, view) in root.buffer_views.iter().enumerate() {
        let Some(c) = compressed(i, view)? else {
            continue;
        };
        let what = format!("bufferView {i} ({EXTENSION})");
        let source = buffers
            .get(c.buffer)
            .ok_or_else(|| DecodeError::invalid(&what, format!("buffer {} does not exist", c.buffer)))?;
        let data = slice(source, c.offset, c.length, &what)?.to_vec();
        let decoded = decode(&c, &data).map_err(|reason| DecodeError::Corrupt {
            what: what.clone(),
            codec: "meshopt",
            reason,
        })?;
        let target = buffers
            .get_mut(view.buffer.value())
            .ok_or_else(|| DecodeError::invalid(&what, format!("buffer {} does not exist", view.buffer.value())))?;
        let start = view.byte_offset.map_or(0, |o| o.0);
        let place = usize::try_from(start)
            .ok()
            .and_then(|s| Some(s..s.checked_add(decoded.len())?))
            .filter(|r| r.end <= target.len())
            .ok_or_else(|| {
                DecodeError::invalid(
                    &what,
                    format!(
                        "{} decoded bytes at byte {start} lie outside buffer {} of {} bytes",
                        decoded.len(),
                        view.buffer.value(),
                        target.len()
                    ),
                )
            })?;
        target[place].copy_from_slice(&decoded);
        decoded_views.insert(i);
    }
    Ok(decoded_views)
}

/// One view's bytes decoded and filtered.
fn decode(c: &Compressed, data: &[u8]) -> Result<Vec<u8>, String> {
    let bytes = match c.mode {
        Mode::Attributes => vertices(data, c.count, c.stride)?,
        Mode::Triangles | Mode::Indices => {
            let mut indices = vec![0u32; c.count];
            let result = if c.mode == Mode::Triangles {
                meshopt_rs::index::buffer::decode_index_buffer(&mut indices, data)
            } else {
                meshopt_rs::index::sequence::decode_index_sequence(&mut indices, data)
            };
            result.map_err(|e| format!("{e:?}"))?;
            if c.stride == 2 {
                // As meshoptimizer writes 16-bit indices: the low half.
                indices.iter().flat_map(|&i| (i as u16).to_le_bytes()).collect()
            } else {
                indices.iter().flat_map(|&i| i.to_le_bytes()).collect()
            }
        }
    };
    let mut bytes = bytes;
    match c.filter {
        Filter::None => {}
        Filter::Octahedral => octahedral(&mut bytes, c.stride),
        Filter::Quaternion => quaternion(&mut bytes),
        Filter::Exponential => exponential(&mut bytes),
    }
    Ok(bytes)
}

/// The vertex codec's output for `count` vertices of `stride` bytes (a multiple of 4 up to
/// 256, checked by the caller): `meshopt-rs` takes the vertex size from its element type, so
/// each stride has its own.
fn vertices(data: &[u8], count: usize, stride: usize) -> Result<Vec<u8>, String> {
    fn decode_as<const N: usize>(data: &[u8], count: usize) -> Result<Vec<u8>, String> {
        let mut out = vec![[0u8; N]; count];
        meshopt_rs::vertex::buffer::decode_vertex_buffer(&mut out, data).map_err(|e| format!("{e:?}"))?;
        Ok(out.into_iter().flatten().collect())
    }
    macro_rules! strides {
        ($($n:literal)*) => {
            match stride {
                $($n => decode_as::<$n>(data, count),)*
                _ => Err(format!("byteStride {stride} is not a multiple of 4 up to 256")),
            }
        };
    }
    strides!(4 8 12 16 20 24 28 32 36 40 44 48 52 56 60 64 68 72 76 80 84 88 92 96 100 104 108 112 116
        120 124 128 132 136 140 144 148 152 156 160 164 168 172 176 180 184 188 192 196 200 204 208 212 216
        220 224 228 232 236 240 244 248 252 256)
}

/// Rounds to the nearest integer, halves away from zero (as the filters' reference code).
fn round(v: f32) -> i32 {
    (v + if v >= 0.0 { 0.5 } else { -0.5 }) as i32
}

/// `OCTAHEDRAL`: signed normalized x and y of an octahedral map (z holds 1.0 at the same bit
/// count) to a unit vector, in 8-bit (stride 4) or 16-bit (stride 8) components; w as is.
fn octahedral(bytes: &mut [u8], stride: usize) {
    let wide = stride == 8;
    let max = if wide { 32767.0 } else { 127.0 };
    for element in bytes.chunks_exact_mut(stride) {
        let get = |k: usize| {
            if wide {
                f32::from(i16::from_le_bytes([element[2 * k], element[2 * k + 1]]))
            } else {
                f32::from(element[k] as i8)
            }
        };
        let (mut x, mut y) = (get(0), get(1));
        let z = get(2) - x.abs() - y.abs();
        let t = z.min(0.0);
        x += if x >= 0.0 { t } else { -t };
        y += if y >= 0.0 { t } else { -t };
        let s = max / (x * x + y * y + z * z).sqrt();
        for (k, v) in [x, y, z].into_iter().enumerate() {
            let q = round(v * s);
            if wide {
                element[2 * k..2 * k + 2].copy_from_slice(&(q as i16).to_le_bytes());
            } else {
                element[k] = q as i8 as u8;
            }
        }
    }
}

/// `QUATERNION`: three signed 16-bit components and the index of the fourth (reconstructed,
/// non-negative) in the low bits of the last, whose upper bits give the scale.
fn quaternion(bytes: &mut [u8]) {
    let scale = std::f32::consts::FRAC_1_SQRT_2;
    for element in bytes.chunks_exact_mut(8) {
        let q: [i16; 4] = std::array::from_fn(|k| i16::from_le_bytes([element[2 * k], element[2 * k + 1]]));
        let ss = scale / f32::from(q[3] | 3);
        let [x, y, z] = [q[0], q[1], q[2]].map(|c| f32::from(c) * ss);
        let w = (1.0 - x * x - y * y - z * z).max(0.0).sqrt();
        let qc = (q[3] & 3) as usize;
        let mut out = [0i16; 4];
        out[(qc + 1) & 3] = round(x * 32767.0) as i16;
        out[(qc + 2) & 3] = round(y * 32767.0) as i16;
        out[(qc + 3) & 3] = round(z * 32767.0) as i16;
        out[qc] = round(w * 32767.0) as i16;
        for (k, v) in out.iter().enumerate() {
            element[2 * k..2 * k + 2].copy_from_slice(&v.to_le_bytes());
        }
    }
}

/// `EXPONENTIAL`: each 32-bit component a signed 24-bit mantissa and an 8-bit exponent,
/// `m · 2^e`, as an f32.
fn exponential(bytes: &mut [u8]) {
    for word in bytes.chunks_exact_mut(4) {
        let v = u32::from_le_bytes([word[0], word[1], word[2], word[3]]);
        let m = ((v << 8) as i32) >> 8;
        let e = (v as i32) >> 24;
        let value = f32::from_bits(((e + 127) as u32) << 23) * m as f32;
        word.copy_from_slice(&value.to_le_bytes());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn filters_give_the_values_the_specification_defines() {
        // Exponential: 3 · 2^-1 and -5 · 2^2.
        let mut bytes: Vec<u8> = [(0xFFu32 << 24) | 3, (2u32 << 24) | (0x00FF_FFFB)]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        exponential(&mut bytes);
        let values: Vec<f32> = bytes
            .chunks(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        assert_eq!(values, [1.5, -20.0]);
        // Octahedral, 8 bits: (0, 0) with z = 1 is +z; (127, 0) is +x; w kept.
        let mut oct = vec![0, 0, 127, 9, 127, 0, 127, 0];
        octahedral(&mut oct, 4);
        assert_eq!(oct, [0, 0, 127, 9, 127, 0, 0, 0]);
        // Quaternion: index 3 (w) reconstructed from x = y = z = 0, largest scale.
        let mut quat: Vec<u8> = [0i16, 0, 0, (0x7FFC | 3) as i16]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        quaternion(&mut quat);
        let q: Vec<i16> = quat.chunks(2).map(|b| i16::from_le_bytes([b[0], b[1]])).collect();
        assert_eq!(q, [0, 0, 0, 32767]);
        // A negative component stays negative (read as signed).
        let mut quat: Vec<u8> = [-16383i16, 0, 0, (0x7FFC | 3) as i16]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        quaternion(&mut quat);
        assert!(i16::from_le_bytes([quat[0], quat[1]]) < 0);
    }

    #[test]
    fn declared_sizes_beyond_what_the_codec_can_produce_are_refused() {
        let view = |ext: Value| -> gltf::json::buffer::View {
            serde_json::from_value(serde_json::json!({
                "buffer": 1, "byteLength": 1 << 20, "extensions": {EXTENSION: ext}
            }))
            .expect("view")
        };
        let huge = view(
            serde_json::json!({"buffer": 0, "byteLength": 10, "byteStride": 16, "count": 60000, "mode": "ATTRIBUTES"}),
        );
        let error = compressed(0, &huge).expect_err("refused").to_string();
        assert!(error.contains("at most 64 times"), "{error}");
        let stride =
            view(serde_json::json!({"buffer": 0, "byteLength": 10, "byteStride": 6, "count": 1, "mode": "ATTRIBUTES"}));
        assert!(compressed(0, &stride)
            .expect_err("refused")
            .to_string()
            .contains("byteStride 6"));
        let mode =
            view(serde_json::json!({"buffer": 0, "byteLength": 10, "byteStride": 4, "count": 1, "mode": "POINTS"}));
        assert!(compressed(0, &mode)
            .expect_err("refused")
            .to_string()
            .contains("POINTS"));
        let triangles =
            view(serde_json::json!({"buffer": 0, "byteLength": 10, "byteStride": 2, "count": 4, "mode": "TRIANGLES"}));
        assert!(compressed(0, &triangles)
            .expect_err("refused")
            .to_string()
            .contains("TRIANGLES of 4"));
    }

    #[test]
    fn damaged_streams_are_errors_not_panics() {
        let c = Compressed {
            buffer: 0,
            offset: 0,
            length: 0,
            stride: 12,
            count: 100,
            mode: Mode::Attributes,
            filter: Filter::None,
        };
        for data in [&[][..], &[0xA0][..], &[0xA0; 40][..], &[0xFF; 300][..]] {
            assert!(decode(&c, data).is_err(), "{data:?}");
        }
        let t = Compressed {
            mode: Mode::Triangles,
            stride: 4,
            count: 3,
            ..c.clone()
        };
        assert!(decode(&t, &[0xE1; 4]).is_err());
        let i = Compressed {
            mode: Mode::Indices,
            stride: 2,
            count: 3,
            ..c
        };
        assert!(decode(&i, &[0xD1]).is_err());
    }
}
