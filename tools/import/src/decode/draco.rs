//! `KHR_draco_mesh_compression`: a primitive whose attributes and indices are one Draco
//! stream in a buffer view, decoded by `draco-oxide` (a pure-Rust decoder of the reference
//! bitstream, written by the team behind Japan's PLATEAU 3D city models) before the glTF
//! reader sees the document.
//!
//! The extension's accessors describe the decoded data but have no buffer view; each is
//! pointed at a new buffer holding its decoded values (floats, dequantized by the decoder;
//! `u32` indices), so the primitive is then read like any other. Attributes the stream holds
//! in a form the import does not read (integer joints, say) get zeros of their size.

use std::collections::HashSet;

use draco_oxide_core::attribute::{Attribute, ComponentDataType};
use gltf::json::accessor::{ComponentType, GenericComponentType};
use gltf::json::validation::{Checked, USize64};
use serde_json::{json, Value};

use super::{slice, DecodeError, MAX_DECODED_BYTES};

/// The extension's name.
pub const EXTENSION: &str = "KHR_draco_mesh_compression";

/// Most faces, vertices or symbols a stream may declare per byte it holds: the decoder
/// allocates by the counts a stream declares, and Draco's densest meshes spend well over a
/// bit per triangle, so a count past this is a damaged or hostile header.
pub const MAX_COUNT_PER_BYTE: u64 = 256;

/// One decoded stream: per attribute named in the extension, its values as floats (`None`
/// for a form the import does not read), and the triangles.
#[derive(Debug)]
struct Decoded {
    points: usize,
    attributes: Vec<(String, Option<Vec<f32>>)>,
    indices: Vec<u32>,
}

/// Decodes every Draco primitive of `root` (whose buffers are `buffers`), appending a buffer
/// of decoded data per primitive and pointing its accessors there. Returns the buffer views
/// that hold decoded data.
pub fn decode_primitives(
    root: &mut gltf::json::Root,
    buffers: &mut Vec<Vec<u8>>,
) -> Result<HashSet<usize>, DecodeError> {
    let mut views = HashSet::new();
    let mut total = 0u64;
    for m in 0..root.meshes.len() {
        for p in 0..root.meshes[m].primitives.len() {
            let primitive = &root.meshes[m].primitives[p];
            let Some(ext) = primitive
                .extensions
                .as_ref()
                .and_then(|e| e.others.get(EXTENSION))
                .cloned()
            else {
                continue;
            };
            let what = format!("mesh {m} primitive {p} ({EXTENSION})");
            let decoded = decode_stream(root, buffers, &ext, &what)?;
            let mut data = Vec::new();
            // (accessor, byte offset, component type) of each decoded part.
            let mut parts: Vec<(usize, usize, ComponentType, usize)> = Vec::new();
            let attributes = primitive.attributes.clone();
            let indices = primitive.indices;
            for (name, values) in &decoded.attributes {
                let Some(accessor) = attributes.iter().find_map(|(semantic, index)| {
                    matches!(semantic, Checked::Valid(s) if s.to_string() == *name).then_some(index.value())
                }) else {
                    continue;
                };
                let size = root
                    .accessors
                    .get(accessor)
                    .and_then(|a| match &a.type_ {
                        Checked::Valid(t) => Some(t.multiplicity()),
                        Checked::Invalid => None,
                    })
                    .ok_or_else(|| {
                        DecodeError::invalid(
                            &what,
                            format!("attribute {name} names a missing accessor or one of no type"),
                        )
                    })?;
                let start = data.len();
                match values {
                    Some(values) if values.len() == decoded.points * size => {
                        data.extend(values.iter().flat_map(|v| v.to_le_bytes()));
                    }
                    // Not read by the import (or of another shape than its accessor): zeros.
                    _ => data.resize(start + decoded.points * size * 4, 0),
                }
                parts.push((accessor, start, ComponentType::F32, decoded.points));
            }
            if let Some(indices) = indices {
                let start = data.len();
                data.extend(decoded.indices.iter().flat_map(|i| i.to_le_bytes()));
                parts.push((indices.value(), start, ComponentType::U32, decoded.indices.len()));
            }
            total = total.saturating_add(data.len() as u64);
            if total > MAX_DECODED_BYTES {
                return Err(DecodeError::TooLarge {
                    what,
                    bytes: total,
                    limit: MAX_DECODED_BYTES,
                    why: "the import's bound on decoded geometry per file",
                });
            }
            let buffer = buffers.len();
            root.buffers
                .push(from_json(json!({"byteLength": data.len().max(1)}), &what)?);
            buffers.push(data);
            for (accessor, start, component, count) in parts {
                let view = root.buffer_views.len();
                let length = (buffers[buffer].len() - start).max(1);
                root.buffer_views.push(from_json(
                    json!({"buffer": buffer, "byteOffset": start, "byteLength": length}),
                    &what,
                )?);
                views.insert(view);
                let a = &mut root.accessors[accessor];
                a.buffer_view = Some(gltf::json::Index::new(view as u32));
                a.byte_offset = None;
                a.count = USize64(count as u64);
                a.component_type = Checked::Valid(GenericComponentType(component));
                a.normalized = false;
                a.sparse = None;
            }
            if let Some(e) = root.meshes[m].primitives[p].extensions.as_mut() {
                e.others.remove(EXTENSION);
            }
        }
    }
    Ok(views)
}

fn from_json<T: serde::de::DeserializeOwned>(value: Value, what: &str) -> Result<T, DecodeError> {
    serde_json::from_value(value).map_err(|e| DecodeError::invalid(what, format!("a decoded part: {e}")))
}

/// The stream the primitive's extension object `ext` names, decoded.
fn decode_stream(
    root: &gltf::json::Root,
    buffers: &[Vec<u8>],
    ext: &Value,
    what: &str,
) -> Result<Decoded, DecodeError> {
    let view_index = ext
        .get("bufferView")
        .and_then(Value::as_u64)
        .and_then(|v| usize::try_from(v).ok())
        .ok_or_else(|| DecodeError::invalid(what, "no bufferView index"))?;
    let view = root
        .buffer_views
        .get(view_index)
        .ok_or_else(|| DecodeError::invalid(what, format!("bufferView {view_index} does not exist")))?;
    let buffer = buffers
        .get(view.buffer.value())
        .ok_or_else(|| DecodeError::invalid(what, format!("buffer {} does not exist", view.buffer.value())))?;
    let bytes = slice(
        buffer,
        view.byte_offset.map_or(0, |o| o.0),
        view.byte_length.0,
        &format!("{what}: bufferView {view_index}"),
    )?;
    let ids = ext
        .get("attributes")
        .and_then(Value::as_object)
        .ok_or_else(|| DecodeError::invalid(what, "no attributes object"))?;
    check_declared_counts(bytes, what)?;
    let mesh = draco_oxide_decoder::Decoder::new()
        .decode_mesh(bytes)
        .map_err(|e| DecodeError::Corrupt {
            what: what.to_owned(),
            codec: "Draco",
            reason: e.to_string(),
        })?;
    let find = |name: &str, id: &Value| -> Result<&Attribute, DecodeError> {
        let id = id
            .as_u64()
            .and_then(|v| usize::try_from(v).ok())
            .ok_or_else(|| DecodeError::invalid(what, format!("attribute {name} has id {id}")))?;
        mesh.attributes
            .iter()
            .find(|a| a.get_id().as_usize() == id)
            .ok_or_else(|| {
                DecodeError::invalid(
                    what,
                    format!("attribute {name} names Draco id {id}, which the stream lacks"),
                )
            })
    };
    let position = find(
        "POSITION",
        ids.get("POSITION")
            .ok_or_else(|| DecodeError::invalid(what, "no POSITION"))?,
    )?;
    let points = position.len();
    let mut attributes = Vec::new();
    for (name, id) in ids {
        let attribute = find(name, id)?;
        if attribute.len() != points {
            return Err(DecodeError::invalid(
                what,
                format!(
                    "attribute {name} has {} points where POSITION has {points}",
                    attribute.len()
                ),
            ));
        }
        attributes.push((name.clone(), floats(attribute, points, name, what)?));
    }
    let mut indices = Vec::with_capacity(mesh.faces.len() * 3);
    for (f, face) in mesh.faces.iter().enumerate() {
        for &corner in face {
            let index = usize::from(corner);
            if index >= points {
                return Err(DecodeError::invalid(
                    what,
                    format!("face {f} uses point {index}, but the stream decodes {points} points"),
                ));
            }
            indices.push(index as u32);
        }
    }
    Ok(Decoded {
        points,
        attributes,
        indices,
    })
}

/// Refuses a mesh stream whose header declares more faces, vertices or symbols than
/// [`MAX_COUNT_PER_BYTE`] allows for its length, before the decoder allocates for them.
/// Streams this does not recognise are left to the decoder to refuse.
fn check_declared_counts(bytes: &[u8], what: &str) -> Result<(), DecodeError> {
    // "DRACO", version 2.2, geometry type, encoder method, flags (u16).
    if bytes.len() < 11 || &bytes[..5] != b"DRACO" || bytes[7] != 1 {
        return Ok(());
    }
    let too_large = |name: &str, count: u64| -> Result<(), DecodeError> {
        let limit = (bytes.len() as u64).saturating_mul(MAX_COUNT_PER_BYTE);
        if count > limit {
            return Err(DecodeError::TooLarge {
                what: format!("{what}: the Draco stream's {name}"),
                bytes: count,
                limit,
                why: "a Draco stream holds at most 256 of them per byte",
            });
        }
        Ok(())
    };
    if u16::from_le_bytes([bytes[9], bytes[10]]) & 0x8000 != 0 {
        return Err(DecodeError::invalid(
            what,
            "the Draco stream has a metadata section, which the import does not read",
        ));
    }
    let mut at = 11;
    let counts: Vec<(&str, Option<u64>)> = match bytes[8] {
        // Sequential: faces, points.
        0 => vec![("faces", varint(bytes, &mut at)), ("points", varint(bytes, &mut at))],
        // Edgebreaker: traversal type, then vertices, faces, attribute data (a byte),
        // symbols and split symbols.
        1 => {
            at += 1;
            let (vertices, faces) = (varint(bytes, &mut at), varint(bytes, &mut at));
            at += 1;
            vec![
                ("vertices", vertices),
                ("faces", faces),
                ("symbols", varint(bytes, &mut at)),
                ("split symbols", varint(bytes, &mut at)),
            ]
        }
        _ => return Ok(()),
    };
    for (name, count) in counts {
        match count {
            Some(count) => too_large(name, count)?,
            None => {
                return Err(DecodeError::invalid(
                    what,
                    format!("the Draco stream's {name} count is not a varint"),
                ))
            }
        }
    }
    Ok(())
}

/// The LEB128 varint at `*at`, moving `at` past it; `None` past the end or beyond 64 bits.
fn varint(bytes: &[u8], at: &mut usize) -> Option<u64> {
    let mut value = 0u64;
    for shift in (0..64).step_by(7) {
        let byte = *bytes.get(*at)?;
        *at += 1;
        value |= u64::from(byte & 0x7F) << shift;
        if byte & 0x80 == 0 {
            return Some(value);
        }
    }
    None
}

/// The float values of `attribute` for each of `points` points, components interleaved
/// (through the attribute's point-to-value map where it has one); `None` for an attribute
/// that is not of floats.
fn floats(attribute: &Attribute, points: usize, name: &str, what: &str) -> Result<Option<Vec<f32>>, DecodeError> {
    if attribute.get_component_type() != ComponentDataType::F32 {
        return Ok(None);
    }
    let n = attribute.get_num_components();
    let data = attribute.get_data_as_bytes();
    let element = 4 * n;
    let unique = data.len().checked_div(element).unwrap_or(0);
    let mut out = Vec::with_capacity(points * n);
    let mut push = |v: usize| -> Result<(), DecodeError> {
        let bytes = data
            .get(v * element..(v + 1) * element)
            .filter(|_| v < unique)
            .ok_or_else(|| {
                DecodeError::invalid(what, format!("attribute {name}: value {v} of {unique} does not exist"))
            })?;
        out.extend(
            bytes
                .chunks_exact(4)
                .map(|b| f32::from_ne_bytes([b[0], b[1], b[2], b[3]])),
        );
        Ok(())
    };
    match attribute.point_map_as_slice() {
        Some(map) => map.iter().try_for_each(|&v| push(usize::from(v)))?,
        None => (0..points).try_for_each(&mut push)?,
    }
    Ok(Some(out))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An edgebreaker mesh header declaring `faces` faces, padded to `len` bytes.
    fn header(faces: u64, len: usize) -> Vec<u8> {
        fn varint(bytes: &mut Vec<u8>, mut v: u64) {
            loop {
                let byte = (v & 0x7F) as u8;
                v >>= 7;
                bytes.push(if v > 0 { byte | 0x80 } else { byte });
                if v == 0 {
                    break;
                }
            }
        }
        let mut bytes = b"DRACO".to_vec();
        bytes.extend_from_slice(&[2, 2, 1, 1, 0, 0, 0]);
        varint(&mut bytes, 4); // vertices
        varint(&mut bytes, faces);
        bytes.push(0); // attribute data
        varint(&mut bytes, faces); // symbols
        varint(&mut bytes, 0); // split symbols
        bytes.resize(len, 0);
        bytes
    }

    #[test]
    fn declared_counts_beyond_the_stream_are_refused_before_decoding() {
        let error = check_declared_counts(&header(1 << 30, 64), "p")
            .expect_err("refused")
            .to_string();
        assert!(error.contains("faces") && error.contains("256"), "{error}");
        assert!(check_declared_counts(&header(2, 64), "p").is_ok());
        let mut metadata = header(2, 64);
        metadata[10] = 0x80;
        assert!(check_declared_counts(&metadata, "p")
            .expect_err("refused")
            .to_string()
            .contains("metadata"));
        // A varint longer than 64 bits is refused, not shifted past them.
        let mut long = header(2, 64);
        long[12..30].fill(0xFF);
        assert!(check_declared_counts(&long, "p").is_err());
    }

    fn root_with_stream(stream: &[u8]) -> (gltf::json::Root, Vec<Vec<u8>>) {
        let root = serde_json::from_value(json!({
            "asset": {"version": "2.0"},
            "buffers": [{"byteLength": stream.len()}],
            "bufferViews": [{"buffer": 0, "byteLength": stream.len()}],
            "accessors": [
                {"componentType": 5126, "count": 3, "type": "VEC3"},
                {"componentType": 5123, "count": 3, "type": "SCALAR"}
            ],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1,
                "extensions": {EXTENSION: {"bufferView": 0, "attributes": {"POSITION": 0}}}}]}]
        }))
        .expect("root");
        (root, vec![stream.to_vec()])
    }

    #[test]
    fn damaged_streams_and_references_are_errors_naming_the_primitive() {
        for stream in [&b"DRACO"[..], &header(2, 40), &[0xFF; 64]] {
            let (mut root, mut buffers) = root_with_stream(stream);
            let error = decode_primitives(&mut root, &mut buffers)
                .expect_err("refused")
                .to_string();
            assert!(error.contains("mesh 0 primitive 0"), "{error}");
        }
        let (mut root, mut buffers) = root_with_stream(&header(2, 40));
        root.buffer_views[0].byte_length = USize64(1000);
        let error = decode_primitives(&mut root, &mut buffers)
            .expect_err("refused")
            .to_string();
        assert!(error.contains("outside its buffer"), "{error}");
    }
}
