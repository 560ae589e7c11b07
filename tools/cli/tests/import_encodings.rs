//! `citystream import` of the same four buildings as a 3D Tiles tileset in each encoding real
//! tilesets ship (tools/test-data/encoded-tilesets, made by gltf-pipeline, gltfpack, basisu
//! and 3d-tiles-tools): Draco and meshopt geometry land within the Draco quantization step of
//! the plain import's, Basis textures within their codecs' error of the plain import's
//! texels, and content requiring an extension the import does not decode is skipped with a
//! warning naming it (an error under `--strict`).

use std::path::{Path, PathBuf};

use citystream_dataset::Dataset;
use citystream_gen::texture::decode_level;
use serde_json::Value;

mod cli_support;
use cli_support::{citystream, import, import_verified, stderr};

/// Draco's position quantization in the fixtures (`gltf-pipeline --draco.quantizePositionBits`).
const DRACO_POSITION_BITS: i32 = 11;
/// And its texture coordinates' (`--draco.quantizeTexcoordBits`).
const DRACO_UV_BITS: i32 = 10;

fn tileset(encoding: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../test-data/encoded-tilesets")
        .join(encoding)
        .join("tileset.json")
}

/// Imports `encoding` in BC7 and in a shared UTM frame (so the imports' coordinates compare
/// directly), verified.
fn import_encoding(encoding: &str, test: &str, extra: &[&str]) -> (Dataset, String, PathBuf) {
    let out = cli_support::fresh_dir("import-encodings", &format!("{test}-{encoding}"));
    let mut args = vec!["--crs", "EPSG:25833"];
    if !extra.contains(&"--format") {
        args.extend(["--format", "bc7"]);
    }
    args.extend_from_slice(extra);
    let (dataset, output) = import_verified(&tileset(encoding), &out, &args);
    (dataset, String::from_utf8_lossy(&output.stdout).into_owned(), out)
}

/// Every vertex of the dataset: absolute position (metres) and UV.
fn vertices(dataset: &Dataset) -> Vec<([f64; 3], [f32; 2])> {
    let scene = &dataset.scene;
    scene
        .positions
        .iter()
        .zip(&scene.uvs)
        .map(|(p, uv)| (std::array::from_fn(|a| scene.origin[a] + f64::from(p[a])), *uv))
        .collect()
}

/// The largest distance (per coordinate) from a vertex of `a` to the vertex of `b` nearest
/// to it in position among those whose UV lies within `uv_tolerance`, and the largest UV
/// difference to that vertex.
fn farthest(a: &[([f64; 3], [f32; 2])], b: &[([f64; 3], [f32; 2])], uv_tolerance: f32) -> (f64, f32) {
    let mut worst = (0.0f64, 0.0f32);
    for (p, uv) in a {
        let nearest = b
            .iter()
            .filter(|(_, u)| (0..2).all(|k| (u[k] - uv[k]).abs() <= uv_tolerance))
            .map(|(q, u)| {
                let d = (0..3).map(|k| (p[k] - q[k]).abs()).fold(0.0, f64::max);
                let e = (0..2).map(|k| (u[k] - uv[k]).abs()).fold(0.0, f32::max);
                (d, e)
            })
            .min_by(|x, y| x.0.total_cmp(&y.0))
            .unwrap_or((f64::INFINITY, f32::INFINITY));
        worst = (worst.0.max(nearest.0), worst.1.max(nearest.1));
    }
    worst
}

/// Sum of the triangles' areas (m²).
fn area(dataset: &Dataset) -> f64 {
    let all = vertices(dataset);
    let scene = &dataset.scene;
    let mut sum = 0.0;
    for mesh in &scene.meshes {
        let first = mesh.first_index as usize;
        for tri in scene.indices[first..first + mesh.index_count as usize].chunks_exact(3) {
            let [a, b, c] = [0, 1, 2].map(|k| all[mesh.first_vertex as usize + tri[k] as usize].0);
            let (u, v) = ([0, 1, 2].map(|k| b[k] - a[k]), [0, 1, 2].map(|k| c[k] - a[k]));
            let n = [
                u[1] * v[2] - u[2] * v[1],
                u[2] * v[0] - u[0] * v[2],
                u[0] * v[1] - u[1] * v[0],
            ];
            sum += 0.5 * (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        }
    }
    sum
}

/// Draco's quantization step for the plain import's largest primitive extent: the
/// tolerance the compressed imports' positions must meet.
fn draco_step(plain: &Dataset) -> f64 {
    let scene = &plain.scene;
    let extent = scene
        .meshes
        .iter()
        .map(|m| {
            (0..3)
                .map(|a| f64::from(m.bounds.max[a] - m.bounds.min[a]))
                .fold(0.0, f64::max)
        })
        .fold(0.0, f64::max);
    extent / f64::from((1 << DRACO_POSITION_BITS) - 1)
}

/// The largest UV range of a plain vertex over Draco's UV steps: the UV tolerance.
fn draco_uv_step(plain: &Dataset) -> f32 {
    let range = plain.scene.uvs.iter().flatten().fold(0.0f32, |m, v| m.max(v.abs()));
    range / ((1 << DRACO_UV_BITS) - 1) as f32
}

/// Level `level` of every texture of `dataset` as RGBA8, with its extent.
fn texels(dataset: &Dataset, level: u32) -> Vec<(u32, u32, Vec<u8>)> {
    let mut buf = Vec::new();
    dataset
        .textures
        .textures()
        .iter()
        .enumerate()
        .map(|(id, t)| {
            dataset.textures.read_mip(id as u32, level, &mut buf).expect("read mip");
            let (w, h) = ((t.width() >> level).max(1), (t.height() >> level).max(1));
            (w, h, decode_level(t.format(), &buf, w, h))
        })
        .collect()
}

/// PSNR (dB) of `b`'s level-0 textures against `a`'s, over all their RGB texels.
fn psnr(a: &Dataset, b: &Dataset) -> f64 {
    let (ta, tb) = (texels(a, 0), texels(b, 0));
    assert_eq!(ta.len(), tb.len(), "texture counts");
    let (mut sum, mut n) = (0.0f64, 0u64);
    for ((wa, ha, pa), (wb, hb, pb)) in ta.iter().zip(&tb) {
        assert_eq!((wa, ha), (wb, hb), "extents");
        for (x, y) in pa.chunks_exact(4).zip(pb.chunks_exact(4)) {
            for c in 0..3 {
                let d = f64::from(x[c]) - f64::from(y[c]);
                sum += d * d;
                n += 1;
            }
        }
    }
    10.0 * (255.0f64 * 255.0 / (sum / n as f64)).log10()
}

fn info_json(dir: &Path) -> Value {
    let out = citystream(&["info", dir.to_str().expect("utf-8"), "--json"]);
    assert!(out.status.success(), "info: {}", stderr(&out));
    serde_json::from_slice(&out.stdout).expect("info JSON")
}

#[test]
fn compressed_geometry_lands_within_the_draco_step_of_the_plain_import() {
    const TEST: &str = "geometry";
    let (plain, _, _) = import_encoding("plain", TEST, &[]);
    let step = draco_step(&plain);
    let uv_step = draco_uv_step(&plain);
    // The buildings' tallest wall is 40 m: about 2 cm at 11 bits.
    assert!((0.015..0.025).contains(&step), "Draco step {step} m");
    let plain_vertices = vertices(&plain);
    let plain_area = area(&plain);
    for (encoding, mesh_kind) in [("draco", "draco"), ("meshopt", "meshopt+quantized")] {
        let (dataset, stdout, out) = import_encoding(encoding, TEST, &[]);
        assert_eq!(
            dataset.scene.triangle_count(),
            plain.scene.triangle_count(),
            "{encoding}"
        );
        let compressed = vertices(&dataset);
        let (there, uv_there) = farthest(&compressed, &plain_vertices, uv_step);
        let (back, uv_back) = farthest(&plain_vertices, &compressed, uv_step);
        println!("{encoding}: positions within {there:.4} / {back:.4} m, UVs {uv_there:.5} / {uv_back:.5} (step {step:.4} m, {uv_step:.5})");
        assert!(
            there <= step && back <= step,
            "{encoding}: {there} / {back} m, step {step} m"
        );
        assert!(
            uv_there <= uv_step && uv_back <= uv_step,
            "{encoding}: UVs {uv_there} / {uv_back}"
        );
        let ratio = area(&dataset) / plain_area;
        assert!((ratio - 1.0).abs() < 1e-3, "{encoding}: area ratio {ratio}");
        // Every mesh is counted as what it was stored as, in the import's output and in info.
        let meshes = dataset.scene.meshes.len() as u64;
        assert!(stdout.contains(&format!("meshes {mesh_kind} {meshes};")), "{stdout}");
        let info = info_json(&out);
        assert_eq!(info["import_encodings"]["meshes"][mesh_kind], meshes, "{info}");
        assert_eq!(info["import_encodings"]["textures"]["png"], 2, "{info}");
    }
}

#[test]
fn basis_textures_transcode_within_their_codecs_error_of_the_plain_import() {
    const TEST: &str = "textures";
    // The reference: the PNGs' own texels (RGBA8 keeps them exactly).
    let (plain, _, _) = import_encoding("plain", TEST, &["--format", "rgba8"]);
    // Tilesets repeat each image in every tile: four tiles, two distinct images.
    assert_eq!(plain.textures.len(), 2);
    for (encoding, floor) in [("ktx2-uastc", 35.0), ("ktx2-uastc-zstd", 35.0), ("ktx2-etc1s", 28.0)] {
        let (dataset, stdout, out) = import_encoding(encoding, TEST, &[]);
        assert_eq!(dataset.textures.len(), 2, "{encoding}: identical images imported once");
        assert!(
            stdout.contains("2 transcoded from Basis Universal into bc7"),
            "{stdout}"
        );
        let db = psnr(&plain, &dataset);
        println!("{encoding}: {db:.2} dB against the plain import's texels");
        assert!(db >= floor, "{encoding}: {db:.2} dB, below {floor}");
        let info = info_json(&out);
        assert_eq!(info["import_encodings"]["textures"][encoding], 2, "{info}");
        assert_eq!(info["import_encodings"]["meshes"]["plain"], 8, "{info}");
        // Transcoded straight into BC7, every level as shipped (basisu -mipmap: full chains).
        for t in dataset.textures.textures() {
            assert_eq!(t.format(), citystream_dataset::TextureFormat::Bc7);
            assert_eq!(t.mip_count(), t.width().max(t.height()).trailing_zeros() + 1);
        }
    }
    // Under --max-extent the finer shipped levels are dropped, the others kept bit for bit.
    let (full, _, _) = import_encoding("ktx2-uastc", TEST, &[]);
    let (half, _, _) = import_encoding("ktx2-uastc", "max-extent", &["--max-extent", "64"]);
    let facade = |d: &Dataset| {
        d.textures
            .textures()
            .iter()
            .position(|t| t.width() == 128 || t.width() == 64)
    };
    let (f, h) = (facade(&full).expect("facade"), facade(&half).expect("facade"));
    assert_eq!(half.textures.textures()[h].width(), 64);
    let (mut a, mut b) = (Vec::new(), Vec::new());
    full.textures.read_mip(f as u32, 1, &mut a).expect("level 1");
    half.textures.read_mip(h as u32, 0, &mut b).expect("level 0");
    assert_eq!(a, b, "the shipped 64x64 level, transcoded the same way");
}

#[test]
fn content_requiring_an_undecoded_extension_is_skipped_loudly_or_refused_with_strict() {
    let out = cli_support::fresh_dir("import-encodings", "unsupported");
    let input = tileset("unsupported");
    let (dataset, output) = import_verified(&input, &out, &[]);
    let warning = stderr(&output);
    assert!(
        warning.contains("1 glTF content listings skipped") && warning.contains("KHR_materials_pbrSpecularGlossiness"),
        "{warning}"
    );
    // Three of the four buildings, two primitives each.
    assert_eq!(dataset.scene.meshes.len(), 6);
    let strict_out = cli_support::fresh_dir("import-encodings", "unsupported-strict");
    let strict = import(&input, &strict_out, &["--strict"]);
    assert!(!strict.status.success(), "--strict must refuse");
    let error = stderr(&strict);
    assert!(
        error.contains("b3.glb") && error.contains("KHR_materials_pbrSpecularGlossiness") && error.contains("--strict"),
        "{error}"
    );
}
