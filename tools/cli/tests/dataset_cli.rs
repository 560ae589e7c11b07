//! End-to-end checks of `citystream gen`, `info` and `verify` on the tiny city.

use std::path::{Path, PathBuf};

use citystream_dataset::{Dataset, DatasetFiles, META_FILE, PACK_FILE};

mod cli_support;
use cli_support::{citystream, copy_tree, stderr};

fn fresh_dir(name: &str) -> PathBuf {
    cli_support::fresh_path("dataset-cli", name)
}

fn gen(name: &str, extra: &[&str]) -> PathBuf {
    let dir = fresh_dir(name);
    let dir_str = dir.to_str().expect("utf-8 temp path");
    let mut args = vec!["gen", "--preset", "tiny", "--out", dir_str];
    args.extend_from_slice(extra);
    let out = citystream(&args);
    assert!(
        out.status.success(),
        "gen failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    dir
}

fn copy_dir(from: &Path, name: &str) -> PathBuf {
    let to = fresh_dir(name);
    copy_tree(from, &to);
    to
}

/// [`gen`] into `source`, and a copy of it in `copy` to damage: both directories.
fn gen_and_copy(source: &str, copy: &str) -> (PathBuf, PathBuf) {
    let good = gen(source, &[]);
    let dir = copy_dir(&good, copy);
    (good, dir)
}

/// `citystream verify` of the dataset in `dir`, which must fail: its standard error.
fn verify_error(dir: &Path) -> String {
    let out = citystream(&["verify", dir.to_str().expect("utf-8")]);
    assert!(!out.status.success(), "{} verified", dir.display());
    stderr(&out)
}

/// Path of one data file of the dataset in `dir`.
fn data_file(dir: &Path, name: &str) -> PathBuf {
    DatasetFiles::resolve(dir).expect("manifest").path(name)
}

/// Whether two datasets hold the same content: scene, texture table, colours, every mip and
/// its checksum (their write ids differ).
fn same_content(a: &Path, b: &Path) -> bool {
    let (a, b) = (Dataset::open(a).expect("open a"), Dataset::open(b).expect("open b"));
    if a.scene != b.scene || a.textures.textures() != b.textures.textures() || a.colormap != b.colormap {
        return false;
    }
    let (mut mip_a, mut mip_b) = (Vec::new(), Vec::new());
    a.textures.textures().iter().enumerate().all(|(id, info)| {
        (0..info.mip_count()).all(|level| {
            a.textures.read_mip(id as u32, level, &mut mip_a).expect("mip a");
            b.textures.read_mip(id as u32, level, &mut mip_b).expect("mip b");
            mip_a == mip_b
        })
    })
}

#[test]
fn tiny_city_verifies_and_info_totals_agree() {
    let dir = gen("tiny-ok", &[]);
    let out = citystream(&["verify", dir.to_str().expect("utf-8")]);
    assert!(out.status.success(), "verify failed: {}", stderr(&out));

    let out = citystream(&["info", "--json", dir.to_str().expect("utf-8")]);
    assert!(out.status.success(), "info failed: {}", stderr(&out));
    let info: serde_json::Value = serde_json::from_slice(&out.stdout).expect("info --json is JSON");
    let dataset = Dataset::open(&dir).expect("open");
    let textures = dataset.textures.len() as u64;
    assert!(textures > 50, "tiny city has {textures} textures");
    assert_eq!(info["textures"], textures);
    assert_eq!(info["meshes"], dataset.scene.meshes.len() as u64);
    assert_eq!(info["triangles"], dataset.scene.triangle_count());
    let by_extent = info["textures_by_extent"].as_array().expect("array");
    let summed: u64 = by_extent.iter().map(|e| e["textures"].as_u64().expect("count")).sum();
    assert_eq!(summed, textures);
    assert_eq!(info["bytes_by_format"]["bc1"], dataset.textures.pack_len() - 64);
    // Each facade, roof, ground and street is its own mesh with its own texture.
    assert_eq!(dataset.scene.meshes.len() as u64, textures);
    assert!(dataset
        .scene
        .meshes
        .iter()
        .enumerate()
        .all(|(i, m)| m.texture as usize == i));
    // Extents are powers of two between 4 and the tiny preset's 64, and some are rectangular.
    let infos = dataset.textures.textures();
    assert!(infos
        .iter()
        .all(|t| (4..=64).contains(&t.width()) && (4..=64).contains(&t.height())));
    assert!(infos.iter().any(|t| t.width() != t.height()));
    // The scene lies far from the world origin; positions are relative to it.
    assert!(dataset.scene.origin[0].abs() > 100_000.0);

    let text = citystream(&["info", dir.to_str().expect("utf-8")]);
    assert!(text.status.success());
    let stdout = String::from_utf8_lossy(&text.stdout);
    let line = stdout
        .lines()
        .find(|l| l.starts_with("textures "))
        .expect("a textures line");
    assert_eq!(
        line.split_whitespace().nth(1),
        Some(textures.to_string().as_str()),
        "{line}"
    );
}

#[test]
fn same_seed_same_bytes_other_seed_other_city() {
    let a = gen("seed-a", &["--seed", "9"]);
    let b = gen("seed-b", &["--seed", "9"]);
    let c = gen("seed-c", &["--seed", "10"]);
    assert!(same_content(&a, &b), "one seed gave two cities");
    assert!(!same_content(&a, &c), "two seeds gave one city");
    // Each write has its own id, so files of the two are never mistaken for one dataset.
    let id = |dir: &Path| DatasetFiles::resolve(dir).expect("manifest").write_id();
    assert_ne!(id(&a), id(&b));
    let pack_a = std::fs::read(data_file(&a, PACK_FILE)).expect("a");
    let pack_b = std::fs::read(data_file(&b, PACK_FILE)).expect("b");
    assert_eq!(pack_a[64..], pack_b[64..], "mip data differs for one seed");
}

#[test]
fn mips_of_generated_textures_differ_and_colormap_is_their_mean() {
    let dir = gen("mips-differ", &["--format", "rgba8"]);
    let dataset = Dataset::open(&dir).expect("open");
    let mut buf = Vec::new();
    let mut differing = 0;
    let mut checked = 0;
    for (id, info) in dataset.textures.textures().iter().enumerate() {
        let id = id as u32;
        assert_eq!(
            info.mip_count(),
            info.width().max(info.height()).trailing_zeros() + 1,
            "full chain"
        );
        // The last level is 1x1: the box-filtered mean, within rounding of the colormap entry.
        dataset
            .textures
            .read_mip(id, info.mip_count() - 1, &mut buf)
            .expect("read 1x1");
        let colour = dataset.colormap.get(id).expect("colour");
        for c in 0..3 {
            let diff = (i32::from(buf[c]) - i32::from(colour[c])).abs();
            assert!(diff <= 6, "texture {id}: 1x1 mip {:?} vs mean {colour:?}", &buf[..4]);
        }
        // Upsample level 1 back to level 0 and compare: procedural detail makes them differ.
        if info.width() >= 16 && info.height() >= 16 {
            let mut level0 = Vec::new();
            dataset.textures.read_mip(id, 0, &mut level0).expect("level 0");
            dataset.textures.read_mip(id, 1, &mut buf).expect("level 1");
            let (w, h) = (info.width() as usize, info.height() as usize);
            let mut error = 0u64;
            for y in 0..h {
                for x in 0..w {
                    for c in 0..3 {
                        let a = i64::from(level0[(y * w + x) * 4 + c]);
                        let b = i64::from(buf[((y / 2) * (w / 2) + x / 2) * 4 + c]);
                        error += (a - b).unsigned_abs();
                    }
                }
            }
            checked += 1;
            if error > (w * h) as u64 {
                differing += 1;
            }
        }
    }
    assert!(checked > 20);
    assert!(
        differing * 10 >= checked * 9,
        "{differing} of {checked} textures have visible detail lost at level 1"
    );
}

#[test]
fn verify_fails_clearly_on_a_truncated_pack() {
    let (_, dir) = gen_and_copy("truncate-src", "truncated");
    let pack = data_file(&dir, PACK_FILE);
    let len = std::fs::metadata(&pack).expect("pack").len();
    std::fs::OpenOptions::new()
        .write(true)
        .open(&pack)
        .expect("open")
        .set_len(len - 1000)
        .expect("truncate");
    let message = verify_error(&dir);
    assert!(
        message.contains("textures.pack") && message.contains("truncated"),
        "{message}"
    );
    assert!(
        message.contains(&(len - 1000).to_string()),
        "names the actual length: {message}"
    );
}

#[test]
fn verify_fails_clearly_on_a_corrupted_offset() {
    let (good, dir) = gen_and_copy("offset-src", "bad-offset");
    let meta = data_file(&dir, META_FILE);
    let mut bytes = std::fs::read(&meta).expect("meta");
    // Texture 5's base offset (record at 40 + 10·5) now points 1 GB into a small pack; the
    // table checksum (header bytes 0..32 and records) is updated so that the offset check
    // itself reports it.
    let record = 40 + 10 * 5;
    bytes[record..record + 6].copy_from_slice(&(1u64 << 30).to_le_bytes()[..6]);
    let mut hasher = crc32fast::Hasher::new();
    hasher.update(&bytes[..32]);
    hasher.update(&bytes[40..]);
    let crc = hasher.finalize();
    bytes[32..36].copy_from_slice(&crc.to_le_bytes());
    std::fs::write(&meta, &bytes).expect("write meta");
    let message = verify_error(&dir);
    for needle in [
        "textures.meta",
        "texture 5",
        &record.to_string(),
        &(1u64 << 30).to_string(),
    ] {
        assert!(message.contains(needle), "missing {needle:?}: {message}");
    }

    // Without the checksum update the damage is caught by the table checksum.
    let dir = copy_dir(&good, "bad-offset-crc");
    let meta = data_file(&dir, META_FILE);
    let mut bytes = std::fs::read(&meta).expect("meta");
    bytes[record + 2] ^= 0x10;
    std::fs::write(&meta, &bytes).expect("write");
    let message = verify_error(&dir);
    assert!(message.contains("checksum mismatch"), "{message}");
}

#[test]
fn bad_arguments_and_missing_datasets_fail_with_messages() {
    let dir = fresh_dir("bad-args");
    let out = citystream(&[
        "gen",
        "--preset",
        "tiny",
        "--max-extent",
        "100",
        "--out",
        dir.to_str().expect("utf-8"),
    ]);
    assert!(!out.status.success());
    assert!(stderr(&out).contains("--max-extent 100"), "{}", stderr(&out));

    let missing = fresh_dir("does-not-exist");
    for command in ["info", "verify"] {
        let out = citystream(&[command, missing.to_str().expect("utf-8")]);
        assert!(!out.status.success());
        assert!(stderr(&out).contains("missing file"), "{command}: {}", stderr(&out));
    }
}

#[test]
fn max_extent_caps_texture_sizes() {
    let dir = gen("capped", &["--max-extent", "16"]);
    let dataset = Dataset::open(&dir).expect("open");
    assert!(dataset.textures.textures().iter().all(|t| t.max_extent() <= 16));
    assert!(dataset.textures.textures().iter().any(|t| t.max_extent() == 16));
}

/// A minimal RGBA8 KTX2 file: header, one level, an empty data format descriptor.
fn ktx2_rgba8(w: u32, h: u32, rgba: &[u8]) -> Vec<u8> {
    let mut f = vec![0xAB, 0x4B, 0x54, 0x58, 0x20, 0x32, 0x30, 0xBB, 0x0D, 0x0A, 0x1A, 0x0A];
    for v in [37u32, 1, w, h, 0, 0, 1, 1, 0, 104, 4, 0, 0] {
        f.extend_from_slice(&v.to_le_bytes());
    }
    for v in [0u64, 0, 108, rgba.len() as u64, rgba.len() as u64] {
        f.extend_from_slice(&v.to_le_bytes());
    }
    f.extend_from_slice(&4u32.to_le_bytes());
    f.extend_from_slice(rgba);
    f
}

#[test]
fn textures_from_dresses_facades_with_user_images() {
    let images = fresh_dir("user-images");
    std::fs::create_dir_all(images.join("sub")).expect("create image dir");
    let gradient = image::RgbaImage::from_fn(100, 37, |x, y| image::Rgba([x as u8 * 2, y as u8 * 6, 90, 255]));
    gradient.save(images.join("a.png")).expect("write png");
    let checker = image::RgbImage::from_fn(300, 300, |x, y| {
        if (x / 30 + y / 30) % 2 == 0 {
            image::Rgb([240, 240, 240])
        } else {
            image::Rgb([20, 20, 20])
        }
    });
    checker.save(images.join("sub").join("b.jpg")).expect("write jpeg");
    std::fs::write(images.join("bad.png"), b"this is not a png").expect("write junk");
    std::fs::write(images.join("notes.txt"), b"ignored").expect("write txt");
    let ktx_texels: Vec<u8> = (0..4 * 2 * 4).map(|i| 40 + i as u8).collect();
    std::fs::write(images.join("c.ktx2"), ktx2_rgba8(4, 2, &ktx_texels)).expect("write ktx2");

    let dir = fresh_dir("dressed");
    let out = citystream(&[
        "gen",
        "--preset",
        "tiny",
        "--format",
        "rgba8",
        "--textures-from",
        images.to_str().expect("utf-8"),
        "--out",
        dir.to_str().expect("utf-8"),
    ]);
    assert!(out.status.success(), "gen failed: {}", stderr(&out));
    assert!(
        stderr(&out).contains("bad.png"),
        "unreadable file is reported: {}",
        stderr(&out)
    );
    let out = citystream(&["verify", dir.to_str().expect("utf-8")]);
    assert!(out.status.success(), "{}", stderr(&out));

    let dataset = Dataset::open(&dir).expect("open");
    let infos = dataset.textures.textures();
    // Sorted by path: a.png (100x37 -> 128x32, capped by tiny's 64), c.ktx2 (4x2 -> 4x4), sub/b.jpg (300² -> 256², capped).
    let extents: Vec<_> = infos[..3].iter().map(|t| (t.width(), t.height())).collect();
    assert_eq!(extents, [(64, 32), (4, 4), (64, 64)]);
    // The checkerboard keeps its contrast after resizing: dark and light texels both present.
    let mut buf = Vec::new();
    dataset.textures.read_mip(2, 0, &mut buf).expect("read");
    assert!(buf.chunks(4).any(|p| p[0] < 60) && buf.chunks(4).any(|p| p[0] > 200));
    // Facades share the three images; everything else has its own texture.
    let shared = dataset.scene.meshes.iter().filter(|m| m.texture < 3).count();
    assert!(shared > 20, "{shared} meshes use user images");
    let mut own: Vec<u32> = dataset
        .scene
        .meshes
        .iter()
        .map(|m| m.texture)
        .filter(|&t| t >= 3)
        .collect();
    let before = own.len();
    own.sort_unstable();
    own.dedup();
    assert_eq!(own.len(), before);
    assert_eq!(own.len() as u32 + 3, dataset.textures.len());

    let empty = fresh_dir("no-images");
    std::fs::create_dir_all(&empty).expect("create");
    let out = citystream(&[
        "gen",
        "--preset",
        "tiny",
        "--textures-from",
        empty.to_str().expect("utf-8"),
        "--out",
        fresh_dir("no-images-out").to_str().expect("utf-8"),
    ]);
    assert!(!out.status.success());
    assert!(stderr(&out).contains("no usable"), "{}", stderr(&out));
}

#[test]
fn cache_report_packs_every_texture_and_reports_utilisation() {
    let dir = gen("cache-report", &[]);
    let dir_str = dir.to_str().expect("utf-8 temp path");
    let out = citystream(&["cache-report", dir_str, "--json", "--layer-size", "256"]);
    assert!(
        out.status.success(),
        "cache-report failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let reports: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON report");
    let dataset = Dataset::open(&dir).expect("tiny city opens");
    let reported: u64 = reports
        .as_array()
        .expect("one report per cache image")
        .iter()
        .map(|r| r["textures"].as_u64().expect("textures"))
        .sum();
    assert_eq!(
        reported,
        u64::from(dataset.textures.len()),
        "every texture is packed once"
    );
    for report in reports.as_array().expect("array") {
        let utilisation = report["utilisation"].as_f64().expect("utilisation");
        let texture = report["texture_bytes"].as_f64().expect("texture bytes");
        let bound = report["bound_bytes"].as_f64().expect("bound bytes");
        assert!(utilisation > 0.0 && utilisation <= 1.0, "utilisation {utilisation}");
        assert!((utilisation - texture / bound).abs() < 1e-9);
        assert_eq!(
            report["bound_bytes"].as_u64(),
            report["bound_blocks"].as_u64().map(|b| b * 65536)
        );
    }
    let bad = citystream(&["cache-report", dir_str, "--rgba8-granularity", "0x4"]);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("--rgba8-granularity"));
}

/// Mean absolute difference per channel between a decoded block-compressed
/// level and the RGBA8 level it was encoded from.
fn block_error(format: citystream_dataset::TextureFormat, blocks: &[u8], rgba: &[u8], width: u32) -> f64 {
    use citystream_dataset::TextureFormat;
    let height = (rgba.len() / 4) as u32 / width;
    let mut total = 0u64;
    for by in 0..height.div_ceil(4) {
        for bx in 0..width.div_ceil(4) {
            let at = ((by * width.div_ceil(4) + bx) * 16) as usize;
            let mut texels = [0u8; 64];
            match format {
                TextureFormat::Bc3 => bcdec_rs::bc3(&blocks[at..at + 16], &mut texels, 16),
                _ => bcdec_rs::bc7(&blocks[at..at + 16], &mut texels, 16),
            }
            for y in 0..4.min(height) {
                for x in 0..4.min(width) {
                    let source = (((by * 4 + y) * width + bx * 4 + x) * 4) as usize;
                    let decoded = ((y * 4 + x) * 4) as usize;
                    for c in 0..4 {
                        total += u64::from(rgba[source + c].abs_diff(texels[decoded + c]));
                    }
                }
            }
        }
    }
    total as f64 / rgba.len() as f64
}

#[test]
fn bc3_and_bc7_cities_encode_the_same_textures_as_rgba8() {
    use citystream_dataset::TextureFormat;
    let rgba = Dataset::open(gen("formats-rgba8", &["--format", "rgba8"])).expect("open rgba8");
    for (format, name, tolerance) in [(TextureFormat::Bc3, "bc3", 6.0), (TextureFormat::Bc7, "bc7", 3.0)] {
        let dir = gen(&format!("formats-{name}"), &["--format", name]);
        let out = citystream(&["verify", dir.to_str().expect("utf-8")]);
        assert!(out.status.success(), "{name}: verify failed: {}", stderr(&out));
        let dataset = Dataset::open(&dir).expect("open");
        assert_eq!(dataset.textures.len(), rgba.textures.len());
        let (mut blocks, mut source) = (Vec::new(), Vec::new());
        let (mut sum, mut levels) = (0.0f64, 0u32);
        for (id, info) in dataset.textures.textures().iter().enumerate() {
            let id = id as u32;
            assert_eq!(info.format(), format);
            // Every level of four texels or more a side, against the same level in RGBA8.
            for level in 0..info.mip_count() {
                let width = (info.width() >> level).max(1);
                if width < 4 || (info.height() >> level) < 4 {
                    break;
                }
                dataset.textures.read_mip(id, level, &mut blocks).expect("read");
                rgba.textures.read_mip(id, level, &mut source).expect("read rgba8");
                sum += block_error(format, &blocks, &source, width);
                levels += 1;
            }
        }
        let mean = sum / f64::from(levels.max(1));
        assert!(
            mean <= tolerance,
            "{name}: mean error {mean} per channel over {levels} levels"
        );
    }
}
