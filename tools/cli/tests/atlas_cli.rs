//! `citystream atlas`: far fewer textures, and every mesh samples exactly its original
//! level-0 texels from the atlas.

use std::path::{Path, PathBuf};

use citystream_dataset::{Dataset, TextureFormat};

mod cli_support;
use cli_support::citystream;

fn fresh_dir(name: &str) -> PathBuf {
    cli_support::fresh_path("atlas-cli", name)
}

fn run_ok(args: &[&str]) -> String {
    let out = citystream(args);
    assert!(
        out.status.success(),
        "{args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

/// The rectangle (x, y, w, h) in atlas texels a mesh's UVs cover (generated meshes are quads
/// with UVs spanning [0,1]²).
fn covered_rect(uvs: &[[f32; 2]], extent: u32) -> (u32, u32, u32, u32) {
    let a = extent as f32;
    let min_u = uvs.iter().map(|t| t[0]).fold(f32::INFINITY, f32::min);
    let max_u = uvs.iter().map(|t| t[0]).fold(f32::NEG_INFINITY, f32::max);
    let min_v = uvs.iter().map(|t| t[1]).fold(f32::INFINITY, f32::min);
    let max_v = uvs.iter().map(|t| t[1]).fold(f32::NEG_INFINITY, f32::max);
    let r = |v: f32| (v * a).round() as u32;
    (r(min_u), r(min_v), r(max_u) - r(min_u), r(max_v) - r(min_v))
}

/// Bytes of the texel (RGBA8) or block (BC1) rows of `rect` in a level of `side` texels.
fn region_bytes(format: TextureFormat, level: &[u8], side: u32, (x, y, w, h): (u32, u32, u32, u32)) -> Vec<u8> {
    // BC1 works in 4x4 blocks of 8 bytes, RGBA8 in texels of 4 bytes.
    let (bytes, x, y, w, h, row_len) = match format {
        TextureFormat::Bc1 => (8, x / 4, y / 4, w / 4, h / 4, side / 4),
        _ => (4, x, y, w, h, side),
    };
    let mut out = Vec::new();
    for row in y..y + h {
        let start = ((row * row_len + x) * bytes) as usize;
        out.extend_from_slice(&level[start..start + (w * bytes) as usize]);
    }
    out
}

fn check_atlas(format: &str) {
    let city = fresh_dir(&format!("city-{format}"));
    run_ok(&["gen", "--preset", "tiny", "--format", format, "--out", s(&city)]);
    let atlas = fresh_dir(&format!("atlas-{format}"));
    let report = run_ok(&["atlas", s(&city), "--out", s(&atlas), "--atlas-extent", "256"]);
    assert!(report.contains("fill ratio"), "{report}");
    run_ok(&["verify", s(&atlas)]);

    let before = Dataset::open(&city).expect("open city");
    let after = Dataset::open(&atlas).expect("open atlas");
    assert!(
        after.textures.len() * 10 <= before.textures.len(),
        "{} -> {}",
        before.textures.len(),
        after.textures.len()
    );
    assert!(after
        .textures
        .textures()
        .iter()
        .all(|t| (t.width(), t.height(), t.mip_count()) == (256, 256, 9)));
    assert_eq!(after.scene.positions, before.scene.positions);
    assert_eq!(after.scene.normals, before.scene.normals);
    assert_eq!(after.scene.indices, before.scene.indices);

    let format = after.textures.info(0).expect("atlas").format();
    for (m, (old, new)) in before.scene.meshes.iter().zip(&after.scene.meshes).enumerate() {
        let info = before.textures.info(old.texture).expect("original");
        let range = new.first_vertex as usize..(new.first_vertex + new.vertex_count) as usize;
        let rect = covered_rect(&after.scene.uvs[range], 256);
        assert_eq!(
            (rect.2, rect.3),
            (info.width(), info.height()),
            "mesh {m}: UVs cover the texture's extent"
        );
        assert_eq!(
            (rect.0 % rect.2, rect.1 % rect.3),
            (0, 0),
            "mesh {m}: placement keeps mip alignment"
        );
        // Level `level` of the mesh's atlas and of its original texture.
        let read_level = |level: u32| {
            let (mut atlas_level, mut original) = (Vec::new(), Vec::new());
            after
                .textures
                .read_mip(new.texture, level, &mut atlas_level)
                .unwrap_or_else(|e| panic!("atlas level {level}: {e:?}"));
            before
                .textures
                .read_mip(old.texture, level, &mut original)
                .unwrap_or_else(|e| panic!("original level {level}: {e:?}"));
            (atlas_level, original)
        };
        let (atlas_level, original) = read_level(0);
        assert_eq!(
            region_bytes(format, &atlas_level, 256, rect),
            original,
            "mesh {m}: level 0 differs"
        );
        // One level down the texture's own level-1 data is there too (byte-exact blocks for
        // BC1 where the mip is at least 4x4).
        if info.width() >= 8 && info.height() >= 8 {
            let (atlas_level, original) = read_level(1);
            let half = (rect.0 / 2, rect.1 / 2, rect.2 / 2, rect.3 / 2);
            assert_eq!(
                region_bytes(format, &atlas_level, 128, half),
                original,
                "mesh {m}: level 1 differs"
            );
        }
    }
}

#[test]
fn atlas_of_a_bc1_city_keeps_level_zero_blocks_exactly() {
    check_atlas("bc1");
}

#[test]
fn atlas_of_an_rgba8_city_keeps_texels_exactly() {
    check_atlas("rgba8");
}

#[test]
fn textures_larger_than_the_atlas_are_kept_unchanged() {
    let city = fresh_dir("big-city");
    run_ok(&["gen", "--preset", "tiny", "--out", s(&city)]);
    let atlas = fresh_dir("big-atlas");
    run_ok(&["atlas", s(&city), "--out", s(&atlas), "--atlas-extent", "32"]);
    run_ok(&["verify", s(&atlas)]);
    let before = Dataset::open(&city).expect("open city");
    let after = Dataset::open(&atlas).expect("open atlas");
    let (mut a, mut b) = (Vec::new(), Vec::new());
    let mut kept = 0;
    for (old, new) in before.scene.meshes.iter().zip(&after.scene.meshes) {
        let info = before.textures.info(old.texture).expect("info");
        if info.max_extent() > 32 {
            kept += 1;
            let new_info = after.textures.info(new.texture).expect("new info");
            assert_eq!((new_info.width(), new_info.height()), (info.width(), info.height()));
            for level in 0..info.mip_count() {
                before.textures.read_mip(old.texture, level, &mut a).expect("old");
                after.textures.read_mip(new.texture, level, &mut b).expect("new");
                assert_eq!(a, b);
            }
            assert_eq!(
                after.scene.uvs[new.first_vertex as usize],
                before.scene.uvs[old.first_vertex as usize]
            );
        }
    }
    assert!(kept > 0);
}

#[test]
fn bad_atlas_options_are_refused() {
    let city = fresh_dir("opts-city");
    run_ok(&["gen", "--preset", "tiny", "--out", s(&city)]);
    let out = citystream(&[
        "atlas",
        s(&city),
        "--out",
        s(&fresh_dir("opts")),
        "--atlas-extent",
        "300",
    ]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--atlas-extent 300"));
    let out = citystream(&["atlas", s(&fresh_dir("no-such-city")), "--out", s(&fresh_dir("opts2"))]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("missing file"));
}

/// Atlases are composed a batch at a time and written before the next, so the buffer stays
/// within `--buffer-mb` on a city whose atlases are many times larger.
#[test]
fn atlas_memory_stays_within_its_buffer_on_a_larger_city() {
    let city = fresh_dir("buffer-city");
    run_ok(&["gen", "--preset", "small", "--out", s(&city), "--quiet"]);
    let atlas = fresh_dir("buffer-atlas");
    let report = run_ok(&[
        "atlas",
        s(&city),
        "--out",
        s(&atlas),
        "--atlas-extent",
        "256",
        "--buffer-mb",
        "2",
    ]);
    let number_after = |label: &str| -> f64 {
        let at = report.find(label).unwrap_or_else(|| panic!("no `{label}` in {report}")) + label.len();
        report[at..]
            .split(|c: char| !(c.is_ascii_digit() || c == '.'))
            .next()
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("no number after `{label}` in {report}"))
    };
    let atlases = number_after("textures -> ");
    let per_batch = number_after("atlases composed ");
    let peak_mb = number_after("peak buffer ");
    let pack_mb = number_after("textures; ");
    assert!(per_batch < atlases, "{report}");
    assert!(peak_mb <= 2.0, "peak buffer {peak_mb} MB over a 2 MB buffer: {report}");
    assert!(
        pack_mb > 4.0 * 2.0,
        "the city ({pack_mb} MB) must be far larger than the buffer: {report}"
    );
    run_ok(&["verify", s(&atlas)]);
    let before = Dataset::open(&city).expect("open city");
    let after = Dataset::open(&atlas).expect("open atlas");
    assert_eq!(before.scene.meshes.len(), after.scene.meshes.len());
}

/// The packing shares atlases between neighbouring regions: far fuller atlases than the
/// earlier per-region packing on the same city.
#[test]
fn shelf_packing_fills_atlases_better_than_per_region_rows() {
    let city = fresh_dir("fill-city");
    run_ok(&["gen", "--preset", "tiny", "--out", s(&city)]);
    let fill = |packing: &str| -> f64 {
        let out = fresh_dir(&format!("fill-{packing}"));
        let report = run_ok(&[
            "atlas",
            s(&city),
            "--out",
            s(&out),
            "--atlas-extent",
            "512",
            "--packing",
            packing,
        ]);
        let at = report.find("fill ratio ").expect("fill ratio") + "fill ratio ".len();
        report[at..]
            .split('%')
            .next()
            .and_then(|n| n.parse().ok())
            .expect("a percentage")
    };
    let (shelves, regions) = (fill("shelves"), fill("regions"));
    assert!(
        shelves > 1.5 * regions,
        "shelves {shelves} % against regions {regions} %"
    );
}
