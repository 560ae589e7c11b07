//! Writing 3D Tiles content: GLB and b3dm files, and a textured quad as glTF, for tests
//! and the fuzzer's seeds (the import reads what this writes, and third parties' files).

use serde_json::{json, Value};

/// A GLB (binary glTF 2.0) of `gltf` JSON and one binary chunk `bin` (buffer 0 when the
/// JSON declares it without a URI).
pub fn glb(gltf: &Value, bin: &[u8]) -> Vec<u8> {
    let mut json_bytes = serde_json::to_vec(gltf).expect("JSON values serialise");
    while !json_bytes.len().is_multiple_of(4) {
        json_bytes.push(b' ');
    }
    let mut bin = bin.to_vec();
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let total = 12 + 8 + json_bytes.len() + if bin.is_empty() { 0 } else { 8 + bin.len() };
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json_bytes.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json_bytes);
    if !bin.is_empty() {
        out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
        out.extend_from_slice(b"BIN\0");
        out.extend_from_slice(&bin);
    }
    out
}

/// A b3dm (3D Tiles 1.0 batched model) around `glb`, with a feature table of `feature_table`
/// JSON (e.g. `{"BATCH_LENGTH": 0, "RTC_CENTER": [x, y, z]}`) and a batch table of
/// `batch_table` JSON and `batch_binary` bytes; sections padded to 8 bytes as the
/// specification asks.
pub fn b3dm(glb: &[u8], feature_table: &Value, batch_table: Option<&Value>, batch_binary: &[u8]) -> Vec<u8> {
    let padded_json = |value: &Value, start: usize| {
        let mut bytes = serde_json::to_vec(value).expect("JSON values serialise");
        while !(start + bytes.len()).is_multiple_of(8) {
            bytes.push(b' ');
        }
        bytes
    };
    let feature_json = padded_json(feature_table, 28);
    let batch_json = batch_table.map_or_else(Vec::new, |t| padded_json(t, 28 + feature_json.len()));
    let mut batch_bin = batch_binary.to_vec();
    while !batch_bin.len().is_multiple_of(8) {
        batch_bin.push(0);
    }
    let total = 28 + feature_json.len() + batch_json.len() + batch_bin.len() + glb.len();
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"b3dm");
    for value in [1, total, feature_json.len(), 0, batch_json.len(), batch_bin.len()] {
        out.extend_from_slice(&(value as u32).to_le_bytes());
    }
    out.extend_from_slice(&feature_json);
    out.extend_from_slice(&batch_json);
    out.extend_from_slice(&batch_bin);
    out.extend_from_slice(glb);
    out
}

/// A glTF 2.0 document (JSON and binary chunk) of one textured quad: `corners` in glTF
/// coordinates (y up) counter-clockwise, UVs over the whole texture, the PNG `png`
/// embedded as buffer view 1, under one node with `node` fields merged in (a
/// `matrix`, a `translation`) and `extensions` at the top level (`CESIUM_RTC`).
pub fn textured_quad(corners: [[f32; 3]; 4], png: &[u8], node: Value, extensions: Option<Value>) -> (Value, Vec<u8>) {
    let mut bin = Vec::new();
    for v in corners.iter().flatten() {
        bin.extend_from_slice(&v.to_le_bytes());
    }
    for v in [[0.0f32, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]].iter().flatten() {
        bin.extend_from_slice(&v.to_le_bytes());
    }
    for i in [0u16, 1, 2, 0, 2, 3] {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    let png_offset = bin.len();
    bin.extend_from_slice(png);
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for c in corners {
        for a in 0..3 {
            lo[a] = lo[a].min(c[a]);
            hi[a] = hi[a].max(c[a]);
        }
    }
    let mut node_json = json!({"mesh": 0});
    if let (Some(target), Value::Object(fields)) = (node_json.as_object_mut(), node) {
        target.extend(fields);
    }
    let mut gltf = json!({
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [node_json],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2, "material": 0}]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
        "textures": [{"source": 0}],
        "images": [{"bufferView": 3, "mimeType": "image/png"}],
        "buffers": [{"byteLength": bin.len()}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": 48},
            {"buffer": 0, "byteOffset": 48, "byteLength": 32},
            {"buffer": 0, "byteOffset": 80, "byteLength": 12},
            {"buffer": 0, "byteOffset": png_offset, "byteLength": png.len()}
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": lo, "max": hi},
            {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC2"},
            {"bufferView": 2, "componentType": 5123, "count": 6, "type": "SCALAR"}
        ]
    });
    if let Some(extensions) = extensions {
        let names: Vec<String> = extensions
            .as_object()
            .map_or_else(Vec::new, |m| m.keys().cloned().collect());
        gltf["extensions"] = extensions;
        gltf["extensionsUsed"] = json!(names);
    }
    (gltf, bin)
}

/// A PNG of `width` × `height` texels of a gradient seeded by `seed` (distinct seeds,
/// distinct images).
pub fn gradient_png(width: u32, height: u32, seed: u8) -> Vec<u8> {
    let image = image::RgbaImage::from_fn(width, height, |x, y| {
        image::Rgba([
            (x * 255 / width.max(1)) as u8,
            (y * 255 / height.max(1)) as u8,
            seed.wrapping_mul(37),
            255,
        ])
    });
    let mut png = Vec::new();
    image
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .expect("PNG encoding into memory");
    png
}
