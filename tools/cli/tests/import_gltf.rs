//! `citystream import` on real third-party glTF assets and on files written here.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use citystream_dataset::Dataset;
use citystream_gen::image_files::{dds_file, ktx2_file};
use citystream_testing::fuzz::quad_buffer;
use serde_json::json;

mod cli_support;
use cli_support::{import, import_verified, stderr};

fn fresh_dir(name: &str) -> PathBuf {
    cli_support::fresh_dir("import-gltf", name)
}

fn import_ok(input: &Path, name: &str, extra: &[&str]) -> (Dataset, Output) {
    import_verified(input, &fresh_dir(name), extra)
}

fn data(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../test-data/gltf")
        .join(path)
}

#[test]
fn third_party_box_textured_imports_from_gltf_and_glb_identically() {
    let (gltf, _) = import_ok(
        &data("BoxTextured/BoxTextured.gltf"),
        "box-gltf",
        &["--format", "rgba8"],
    );
    let (glb, _) = import_ok(
        &data("BoxTextured-Binary/BoxTextured.glb"),
        "box-glb",
        &["--format", "rgba8"],
    );
    assert_eq!(gltf.scene.meshes.len(), 1);
    assert_eq!(gltf.scene.triangle_count(), 12);
    assert_eq!(gltf.scene.positions.len(), 24);
    // The 211x211 PNG is resized up to 256x256 with a full mip chain.
    let info = gltf.textures.info(0).expect("texture 0");
    assert_eq!((info.width(), info.height(), info.mip_count()), (256, 256, 9));
    // The node matrix turns the box's z-up into y-up: a unit cube centred on the origin.
    let b = gltf.scene.bounds;
    for a in 0..3 {
        let (lo, hi) = (
            gltf.scene.origin[a] + f64::from(b.min[a]),
            gltf.scene.origin[a] + f64::from(b.max[a]),
        );
        assert!(
            (lo + 0.5).abs() < 1e-5 && (hi - 0.5).abs() < 1e-5,
            "axis {a}: {lo}..{hi}"
        );
    }
    assert_eq!(gltf.scene, glb.scene);
    let (mut a, mut c) = (Vec::new(), Vec::new());
    gltf.textures.read_mip(0, 0, &mut a).expect("gltf mip");
    glb.textures.read_mip(0, 0, &mut c).expect("glb mip");
    assert_eq!(a, c);
    // The Cesium logo: blue sky, green hills, white ridge; all three must survive.
    let has = |f: &dyn Fn([i32; 3]) -> bool| a.chunks(4).any(|p| f([0, 1, 2].map(|c| i32::from(p[c]))));
    assert!(has(&|p| p[2] > p[0] + 60), "blue");
    assert!(has(&|p| p[1] > p[0] + 30 && p[1] > p[2] + 30), "green");
    assert!(has(&|p| p[0] > 240 && p[1] > 240 && p[2] > 240), "white");
}

/// Writes `<dir>/scene.gltf` + `scene.bin` + `tex.png`: one quad, parent translation and a
/// child with rotation and scale, UVs up to 3 (repeat), indices as u16.
fn write_quad_gltf(dir: &Path, child: serde_json::Value, indices: [u16; 6], image_size: (u32, u32)) -> PathBuf {
    let positions: [[f32; 3]; 4] = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]];
    let normals = [[0.0f32, 0.0, 1.0]; 4];
    let uvs: [[f32; 2]; 4] = [[0.0, 3.0], [3.0, 3.0], [3.0, 0.0], [0.0, 0.0]];
    let mut bin = Vec::new();
    for v in positions.iter().chain(&normals).flatten().chain(uvs.iter().flatten()) {
        bin.extend_from_slice(&v.to_le_bytes());
    }
    for i in indices {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    std::fs::write(dir.join("scene.bin"), &bin).expect("write bin");
    let (w, h) = image_size;
    image::RgbaImage::from_fn(w, h, |x, y| {
        image::Rgba([(x * 255 / w) as u8, (y * 255 / h) as u8, 200, 255])
    })
    .save(dir.join("tex.png"))
    .expect("write png");
    let gltf = json!({
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [
            {"translation": [391000.0, 0.0, 5819000.0], "children": [1], "name": "parent"},
            child
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2}, "indices": 3, "material": 0}]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
        "textures": [{"source": 0, "sampler": 0}],
        "samplers": [{"wrapS": 10497, "wrapT": 10497}],
        "images": [{"uri": "tex.png"}],
        "buffers": [{"uri": "scene.bin", "byteLength": bin.len()}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": 48},
            {"buffer": 0, "byteOffset": 48, "byteLength": 48},
            {"buffer": 0, "byteOffset": 96, "byteLength": 32},
            {"buffer": 0, "byteOffset": 128, "byteLength": 12}
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": [0.0, 0.0, 0.0], "max": [1.0, 1.0, 0.0]},
            {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC3"},
            {"bufferView": 2, "componentType": 5126, "count": 4, "type": "VEC2"},
            {"bufferView": 3, "componentType": 5123, "count": 6, "type": "SCALAR"}
        ]
    });
    let path = dir.join("scene.gltf");
    std::fs::write(&path, serde_json::to_vec_pretty(&gltf).expect("json")).expect("write gltf");
    path
}

fn world(dataset: &Dataset, vertex: usize) -> [f64; 3] {
    let p = dataset.scene.positions[vertex];
    [0, 1, 2].map(|a| dataset.scene.origin[a] + f64::from(p[a]))
}

#[test]
fn node_transforms_repeat_uvs_and_power_of_two_resizing() {
    let dir = fresh_dir("quad-src");
    // 90° about +y (x -> -z, z -> x), scale 2, below a translated parent.
    let s = std::f32::consts::FRAC_1_SQRT_2;
    let child = json!({"mesh": 0, "rotation": [0.0, s, 0.0, s], "scale": [2.0, 2.0, 2.0]});
    let input = write_quad_gltf(&dir, child, [0, 1, 2, 0, 2, 3], (100, 60));
    let (dataset, _) = import_ok(&input, "quad", &["--format", "rgba8"]);
    let expected = [
        [391000.0, 0.0, 5819000.0],
        [391000.0, 0.0, 5818998.0],
        [391000.0, 2.0, 5818998.0],
        [391000.0, 2.0, 5819000.0],
    ];
    for (v, e) in expected.iter().enumerate() {
        let p = world(&dataset, v);
        assert!((0..3).all(|a| (p[a] - e[a]).abs() < 1e-3), "vertex {v}: {p:?} != {e:?}");
    }
    // Positions are stored relative to an origin near the model, not to (0,0,0).
    assert!(dataset.scene.positions.iter().flatten().all(|v| v.abs() < 10.0));
    let n = dataset.scene.normals[0];
    assert!(
        (n[0] - 1.0).abs() < 1e-5 && n[1].abs() < 1e-5 && n[2].abs() < 1e-5,
        "normal {n:?}"
    );
    assert_eq!(dataset.scene.uvs[1], [3.0, 3.0], "repeating UVs are kept");
    assert_eq!(dataset.scene.indices, [0, 1, 2, 0, 2, 3]);
    let info = dataset.textures.info(0).expect("texture");
    assert_eq!(
        (info.width(), info.height()),
        (128, 64),
        "100x60 is resized up to 128x64"
    );
}

#[test]
fn mirroring_transform_keeps_front_faces_counter_clockwise() {
    let dir = fresh_dir("mirror-src");
    let child = json!({"mesh": 0, "scale": [-1.0, 1.0, 1.0]});
    let input = write_quad_gltf(&dir, child, [0, 1, 2, 0, 2, 3], (64, 64));
    let (dataset, _) = import_ok(&input, "mirror", &[]);
    assert_eq!(dataset.scene.indices, [0, 2, 1, 0, 3, 2]);
    // The normal of a mirrored plane z=0 stays +z.
    assert!((dataset.scene.normals[0][2] - 1.0).abs() < 1e-5);
}

#[test]
fn large_textures_are_downscaled_with_a_warning() {
    let dir = fresh_dir("big-src");
    let input = write_quad_gltf(&dir, json!({"mesh": 0}), [0, 1, 2, 0, 2, 3], (300, 200));
    let (dataset, out) = import_ok(&input, "big", &["--max-extent", "64"]);
    let info = dataset.textures.info(0).expect("texture");
    assert_eq!((info.width(), info.height()), (64, 64));
    assert!(stderr(&out).contains("downscaled"), "{}", stderr(&out));
}

#[test]
fn glb_with_embedded_image_and_colour_factor() {
    // Positions, indices and a PNG in one binary chunk; material tints green by half.
    let mut png = Vec::new();
    image::RgbaImage::from_pixel(8, 8, image::Rgba([200, 200, 200, 255]))
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .expect("encode png");
    let mut bin = Vec::new();
    for v in [[0.0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]].iter().flatten() {
        bin.extend_from_slice(&v.to_le_bytes());
    }
    let png_offset = bin.len();
    bin.extend_from_slice(&png);
    while bin.len() % 4 != 0 {
        bin.push(0);
    }
    let gltf = json!({
        "asset": {"version": "2.0"},
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "material": 0}]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "baseColorFactor": [1.0, 0.5, 1.0, 1.0]}}],
        "textures": [{"source": 0}],
        "images": [{"bufferView": 1, "mimeType": "image/png"}],
        "buffers": [{"byteLength": bin.len()}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": 36},
            {"buffer": 0, "byteOffset": png_offset, "byteLength": png.len()}
        ],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3", "min": [0.0, 0.0, 0.0], "max": [1.0, 1.0, 0.0]}]
    });
    let mut json_bytes = serde_json::to_vec(&gltf).expect("json");
    while !json_bytes.len().is_multiple_of(4) {
        json_bytes.push(b' ');
    }
    let mut glb = Vec::new();
    glb.extend_from_slice(b"glTF");
    glb.extend_from_slice(&2u32.to_le_bytes());
    glb.extend_from_slice(&((12 + 8 + json_bytes.len() + 8 + bin.len()) as u32).to_le_bytes());
    glb.extend_from_slice(&(json_bytes.len() as u32).to_le_bytes());
    glb.extend_from_slice(b"JSON");
    glb.extend_from_slice(&json_bytes);
    glb.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    glb.extend_from_slice(b"BIN\0");
    glb.extend_from_slice(&bin);
    let dir = fresh_dir("glb-src");
    let input = dir.join("tri.glb");
    std::fs::write(&input, glb).expect("write glb");

    let (dataset, _) = import_ok(&input, "glb", &["--format", "rgba8"]);
    assert_eq!(dataset.scene.triangle_count(), 1);
    // No NORMAL attribute: flat normals are computed (+z for this triangle).
    assert!((dataset.scene.normals[0][2] - 1.0).abs() < 1e-5);
    let colour = dataset.colormap.get(0).expect("colour");
    assert_eq!((colour[0], colour[1], colour[2]), (200, 100, 200));
}

/// [`import`] of `input` into `out_dir`, which must fail; its standard error.
fn import_error(input: &Path, out_dir: &Path) -> String {
    let out = import(input, out_dir, &[]);
    assert!(!out.status.success(), "{} imported", input.display());
    stderr(&out)
}

/// The quad glTF written into the fresh directory `name`, its JSON edited by `edit`.
fn edited_quad_gltf(name: &str, edit: impl FnOnce(&mut serde_json::Value)) -> PathBuf {
    let src = fresh_dir(name);
    let input = write_quad_gltf(&src, json!({"mesh": 0}), [0, 1, 2, 0, 2, 3], (16, 16));
    let mut doc: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&input).expect("read gltf")).expect("gltf is JSON");
    edit(&mut doc);
    std::fs::write(&input, serde_json::to_vec(&doc).expect("json")).expect("write gltf");
    input
}

/// [`import`] of the case `name`'s `input` fails, naming what is wrong (`needle`), without
/// a panic.
fn assert_refused_clearly(name: &str, input: &Path, out_dir: &Path, needle: &str) {
    let out = import(input, out_dir, &[]);
    assert!(!out.status.success(), "{name} imported");
    assert!(stderr(&out).contains(needle), "{name}: {}", stderr(&out));
    assert!(!stderr(&out).contains("panicked"), "{name}: {}", stderr(&out));
}

#[test]
fn broken_gltf_files_give_clear_errors() {
    let dir = fresh_dir("broken");
    let out_dir = fresh_dir("broken-out");

    let invalid = dir.join("invalid.gltf");
    std::fs::write(&invalid, b"{\"asset\": {\"version\": \"2.0\"}, \"scenes\": [").expect("write");
    let error = import_error(&invalid, &out_dir);
    assert!(error.contains("invalid.gltf") && error.contains("line"), "{error}");

    let mut non_utf8 = b"{\"asset\": {\"version\": \"2.0\"}, \"nodes\": [{\"name\": \"".to_vec();
    non_utf8.extend_from_slice(&[0xff, 0xfe, 0x80]);
    non_utf8.extend_from_slice(b"\"}], \"scenes\": [{\"nodes\": [0]}]}");
    let path = dir.join("non-utf8.gltf");
    std::fs::write(&path, non_utf8).expect("write");
    let error = import_error(&path, &out_dir);
    assert!(error.contains("non-utf8.gltf") && error.contains("line 1"), "{error}");

    // A required extension the import does not decode: refused naming it.
    let input = edited_quad_gltf("required", |doc| {
        doc["extensionsRequired"] = json!(["KHR_draco_mesh_compression", "KHR_materials_pbrSpecularGlossiness"]);
    });
    assert_refused_clearly(
        "required",
        &input,
        &out_dir,
        "requires KHR_materials_pbrSpecularGlossiness, which citystream does not decode",
    );

    let src = fresh_dir("index-src");
    let input = write_quad_gltf(&src, json!({"mesh": 0}), [0, 1, 2, 0, 2, 9], (16, 16));
    let error = import_error(&input, &out_dir);
    assert!(
        error.contains("primitive 0") && error.contains("index 5 is 9"),
        "{error}"
    );

    // Accessors the gltf crate would panic on or silently skip: named.
    for (name, accessor, edit, needle) in [
        (
            "float-indices",
            3,
            ("componentType", json!(5126)),
            "accessor 3 (indices) is Scalar F32",
        ),
        (
            "long-positions",
            0,
            ("count", json!(40)),
            "accessor 0 (POSITION): 40 elements",
        ),
        ("uv-vec3", 2, ("type", json!("VEC3")), "accessor 2 (TEXCOORD_0) is Vec3"),
        (
            "far-offset",
            1,
            ("byteOffset", json!(1u64 << 62)),
            "accessor 1 (NORMAL)",
        ),
    ] {
        let input = edited_quad_gltf(&format!("accessor-{name}"), |doc| {
            doc["accessors"][accessor][edit.0] = edit.1;
        });
        assert_refused_clearly(name, &input, &out_dir, needle);
    }

    // What the fuzz harness found panicking inside the gltf crate: each a clear error now.
    type Edit = fn(&mut serde_json::Value);
    let cases: [(&str, Edit, &str); 4] = [
        (
            "missing-position-accessor",
            |doc| doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"] = json!(7),
            "refers to accessor 7, but the file has 4 accessors",
        ),
        (
            "empty-accessor",
            |doc| doc["accessors"][1]["count"] = json!(0),
            "accessor 1 (NORMAL) has count 0",
        ),
        (
            "short-stride",
            |doc| doc["bufferViews"][0]["byteStride"] = json!(4),
            "byteStride 4, smaller than the 12-byte element",
        ),
        (
            "image-without-mime-type",
            |doc| doc["images"][0] = json!({"bufferView": 3}),
            "image 0 lies in a buffer view but names no mimeType",
        ),
    ];
    for (name, edit, needle) in cases {
        let input = edited_quad_gltf(&format!("fuzz-found-{name}"), edit);
        assert_refused_clearly(name, &input, &out_dir, needle);
    }
    // A GLB whose header declares fewer bytes than the header itself.
    let mut glb = std::fs::read(data("BoxTextured-Binary/BoxTextured.glb")).expect("glb");
    glb[8..12].copy_from_slice(&4u32.to_le_bytes());
    let path = dir.join("short-length.glb");
    std::fs::write(&path, glb).expect("write");
    let error = import_error(&path, &out_dir);
    assert!(error.contains("GLB header declares Some(4) bytes"), "{error}");
    assert!(!error.contains("panicked"), "{error}");

    let src = fresh_dir("missing-src");
    let input = write_quad_gltf(&src, json!({"mesh": 0}), [0, 1, 2, 0, 2, 3], (16, 16));
    std::fs::remove_file(src.join("tex.png")).expect("remove png");
    let error = import_error(&input, &out_dir);
    assert!(error.contains("tex.png"), "{error}");
    std::fs::remove_file(src.join("scene.bin")).expect("remove bin");
    let error = import_error(&input, &out_dir);
    assert!(error.contains("missing file") && error.contains("scene.bin"), "{error}");
}

#[cfg(unix)]
#[test]
fn shared_children_are_capped_under_a_memory_limit() {
    // 41 nodes, each listing the next twice as a child: 2^40 paths to the
    // quad's mesh. The import must stop with a clear error, not exhaust
    // memory (2 GB of address space here).
    let src = fresh_dir("dag-src");
    let input = write_quad_gltf(&src, json!({"mesh": 0}), [0, 1, 2, 0, 2, 3], (16, 16));
    let mut doc: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&input).expect("read gltf")).expect("gltf is JSON");
    let mut nodes: Vec<serde_json::Value> = (0..40).map(|i| json!({"children": [i + 1, i + 1]})).collect();
    nodes.push(json!({"mesh": 0}));
    doc["nodes"] = json!(nodes);
    std::fs::write(&input, serde_json::to_vec(&doc).expect("json")).expect("write gltf");
    let out_dir = fresh_dir("dag-out");
    let output = Command::new("sh")
        .arg("-c")
        .arg(r#"ulimit -v 2000000 && exec "$0" import "$1" --out "$2""#)
        .arg(env!("CARGO_BIN_EXE_citystream"))
        .arg(&input)
        .arg(&out_dir)
        .output()
        .expect("import runs");
    let text = stderr(&output);
    assert!(!output.status.success(), "the DAG imported");
    assert_eq!(output.status.code(), Some(1), "killed instead of an error: {text}");
    assert!(text.contains("node instances") && text.contains("trees"), "{text}");
}

/// Deterministic block bytes for a `w`×`h` level of 16-byte blocks. Mode bits are forced to
/// BC7 mode 6 (and are harmless BC3 alpha bits), so every block decodes to real colours.
fn blocks(w: u32, h: u32, salt: u8) -> Vec<u8> {
    let count = (w.div_ceil(4) * h.div_ceil(4)) as usize;
    (0..count * 16)
        .map(|i| {
            if i % 16 == 0 {
                0x40
            } else {
                (i as u8).wrapping_mul(37).wrapping_add(salt)
            }
        })
        .collect()
}

#[test]
fn block_compressed_ktx2_and_dds_sources_keep_their_blocks() {
    let dir = fresh_dir("kept-blocks-src");
    // BC7 KTX2, 16x8 with its full chain of 5 levels; BC3 DDS, 8x8 with 4 levels.
    let bc7: Vec<Vec<u8>> = (0..5)
        .map(|l| blocks((16 >> l).max(1), (8 >> l).max(1), l as u8))
        .collect();
    let bc3: Vec<Vec<u8>> = (0..4).map(|l| blocks(8 >> l, 8 >> l, 100 + l as u8)).collect();
    std::fs::write(dir.join("facade.ktx2"), ktx2_file(145, 16, 8, &bc7)).expect("ktx2");
    std::fs::write(dir.join("sign.dds"), dds_file(b"DXT5", 0, 8, 8, &bc3)).expect("dds");
    let quad = quad_buffer(1.0, 1.0);
    std::fs::write(dir.join("quad.bin"), &quad.bytes).expect("bin");
    let primitive =
        |material: u32| json!({"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2, "material": material});
    let gltf = json!({
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2]}],
        "nodes": [{"mesh": 0}, {"mesh": 1, "translation": [2.0, 0.0, 0.0]}, {"mesh": 2, "translation": [4.0, 0.0, 0.0]}],
        "meshes": [{"primitives": [primitive(0)]}, {"primitives": [primitive(1)]}, {"primitives": [primitive(2)]}],
        "materials": [
            {"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}},
            {"pbrMetallicRoughness": {"baseColorTexture": {"index": 1}}},
            // Tinted: the blocks must be decoded to apply the factor.
            {"pbrMetallicRoughness": {"baseColorTexture": {"index": 1}, "baseColorFactor": [0.5, 0.5, 0.5, 1.0]}}
        ],
        "textures": [{"source": 0}, {"source": 1}],
        "images": [{"uri": "facade.ktx2"}, {"uri": "sign.dds"}],
        "buffers": [{"uri": "quad.bin", "byteLength": quad.bytes.len()}],
        "bufferViews": quad.buffer_views,
        "accessors": quad.accessors
    });
    let input = dir.join("scene.gltf");
    std::fs::write(&input, serde_json::to_vec(&gltf).expect("json")).expect("gltf");

    // --max-extent 8 drops the BC7 source's finest level (16x8) and keeps the other four.
    let (dataset, out) = import_ok(&input, "kept-blocks", &["--max-extent", "8"]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains("3 textures (2 with their KTX2/DDS blocks kept, the others encoded as bc1)"),
        "{stdout}"
    );
    let infos = dataset.textures.textures();
    let chain = |id: u32| -> Vec<u8> {
        let mut all = Vec::new();
        let mut level = Vec::new();
        for l in 0..infos[id as usize].mip_count() {
            dataset.textures.read_mip(id, l, &mut level).expect("mip");
            all.extend_from_slice(&level);
        }
        all
    };
    use citystream_dataset::TextureFormat;
    // Textures are numbered in traversal order; find each by its format.
    let id_of = |format: TextureFormat| -> u32 {
        let ids: Vec<usize> = (0..infos.len()).filter(|&i| infos[i].format() == format).collect();
        assert_eq!(ids.len(), 1, "{format:?}: {infos:?}");
        ids[0] as u32
    };
    let (bc7_id, bc3_id, bc1_id) = (
        id_of(TextureFormat::Bc7),
        id_of(TextureFormat::Bc3),
        id_of(TextureFormat::Bc1),
    );
    let info = |id: u32| {
        let i = &infos[id as usize];
        (i.width(), i.height(), i.mip_count())
    };
    assert_eq!(info(bc7_id), (8, 4, 4));
    assert_eq!(chain(bc7_id), bc7[1..].concat(), "BC7 blocks changed");
    assert_eq!(info(bc3_id), (8, 8, 4));
    assert_eq!(chain(bc3_id), bc3.concat(), "BC3 blocks (and their alpha) changed");
    // The tinted texture was decoded, tinted and re-encoded as --format (bc1).
    assert_eq!(info(bc1_id), (8, 8, 4));
    // The colormap holds the mean of the decoded level 0.
    let mut texels = [0u8; 8 * 4 * 4];
    let mut block = [0u8; 64];
    for (b, data) in bc7[1].chunks_exact(16).enumerate() {
        bcdec_rs::bc7(data, &mut block, 16);
        for y in 0..4 {
            let to = (y * 8 + b * 4) * 4;
            texels[to..to + 16].copy_from_slice(&block[y * 16..y * 16 + 16]);
        }
    }
    let mean: Vec<u8> = (0..4)
        .map(|c| {
            let sum: u32 = texels.chunks_exact(4).map(|p| u32::from(p[c])).sum();
            ((sum + 16) / 32) as u8
        })
        .collect();
    assert_eq!(dataset.colormap.colours()[bc7_id as usize].to_vec(), mean);
}

/// A plain glTF's buffer URIs are read by citystream as files beside it, never handed to a
/// reader that interprets schemes: `file:` (with a decoy of that name beside the glTF) and
/// `file:/dev/zero` are refused naming the URI, and `%FF` is a clear error, not a panic.
#[test]
fn buffer_uris_with_a_scheme_or_bad_escapes_are_refused_naming_them() {
    let out_dir = fresh_dir("uri-shapes-out");
    let outside_dir = fresh_dir("uri-shapes-outside");
    let outside = outside_dir.join("scene.bin");
    for (name, needle) in [
        ("file-decoy", "names a scheme"),
        ("dev-zero", "names a scheme"),
        ("bad-escape", "does not percent-decode to UTF-8"),
    ] {
        let src = fresh_dir(&format!("uri-{name}"));
        let input = write_quad_gltf(&src, json!({"mesh": 0}), [0, 1, 2, 0, 2, 3], (16, 16));
        std::fs::copy(src.join("scene.bin"), &outside).expect("copy the buffer outside");
        let uri = match name {
            "file-decoy" => {
                let uri = format!("file:{}", outside.display());
                let decoy = src.join(&uri);
                std::fs::create_dir_all(decoy.parent().expect("parent")).expect("decoy dirs");
                std::fs::copy(src.join("scene.bin"), &decoy).expect("decoy");
                uri
            }
            "dev-zero" => "file:/dev/zero".to_owned(),
            _ => {
                std::fs::copy(src.join("scene.bin"), src.join("\u{fffd}.bin")).expect("replacement-named file");
                "%FF.bin".to_owned()
            }
        };
        let mut doc: serde_json::Value =
            serde_json::from_slice(&std::fs::read(&input).expect("read gltf")).expect("gltf is JSON");
        doc["buffers"][0]["uri"] = json!(uri);
        std::fs::write(&input, serde_json::to_vec(&doc).expect("json")).expect("write gltf");
        let out = import(&input, &out_dir, &[]);
        assert!(!out.status.success(), "{name} imported");
        assert!(
            stderr(&out).contains(needle) && stderr(&out).contains("buffer 0"),
            "{name}: {}",
            stderr(&out)
        );
        assert!(!stderr(&out).contains("panicked"), "{name}: {}", stderr(&out));
    }
}
