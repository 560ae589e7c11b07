//! `citystream import TILESET_JSON` on tilesets written here: b3dm and glb content, an
//! external tileset, nested transforms, RTC_CENTER and CESIUM_RTC, REPLACE and ADD
//! refinement and a texture two tiles share, placed at Berlin; positions are checked
//! against an east-north-up computation independent of the importer's.

use std::path::{Path, PathBuf};

use citystream_dataset::Dataset;
use citystream_import::tiles::write;
use serde_json::{json, Value};

mod cli_support;
mod tileset_support;
use cli_support::{citystream, import, import_verified, stderr};
use tileset_support::*;

fn fresh_dir(name: &str) -> PathBuf {
    cli_support::fresh_dir("import-tiles", name)
}

fn import_ok(input: &Path, name: &str, extra: &[&str]) -> (Dataset, PathBuf) {
    let out_dir = fresh_dir(name);
    (import_verified(input, &out_dir, extra).0, out_dir)
}

/// Checks every imported vertex against the independent placement: the dataset's absolute
/// scene coordinates are (east, up, −north) of an east-north-up frame at the centre of the
/// imported contents' Earth-centred bounds. Returns that centre's latitude and longitude.
fn check_positions(dataset: &Dataset, imported: &[&Written]) -> (f64, f64) {
    let corners: Vec<[f64; 3]> = imported.iter().flat_map(|w| w.corners_ecef.clone()).collect();
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in &corners {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let centre: [f64; 3] = std::array::from_fn(|a| 0.5 * (lo[a] + hi[a]));
    let (lat, lon) = geodetic(centre);
    let rows = enu_rows(lat, lon);
    let scene = &dataset.scene;
    assert_eq!(scene.meshes.len(), imported.len());
    let mut worst = 0.0f64;
    for (mesh, written) in scene.meshes.iter().zip(imported) {
        assert_eq!(mesh.vertex_count, 4, "{}", written.file);
        for (v, p) in written.corners_ecef.iter().enumerate() {
            let d: [f64; 3] = std::array::from_fn(|a| p[a] - centre[a]);
            let [e, n, u] = rows.map(|r| r[0] * d[0] + r[1] * d[1] + r[2] * d[2]);
            let expected = [e, u, -n];
            let stored = scene.positions[mesh.first_vertex as usize + v];
            for a in 0..3 {
                let got = scene.origin[a] + f64::from(stored[a]);
                worst = worst.max((got - expected[a]).abs());
            }
        }
    }
    // A millimetre: the issue's bound, and 30 times what f32 positions a few hundred metres
    // from the origin can hold.
    assert!(
        worst < 0.001,
        "a vertex lies {worst} m from where the independent ENU computation puts it"
    );
    eprintln!(
        "worst vertex {:.6} mm from the independent ENU computation",
        worst * 1000.0
    );
    let crs = scene
        .crs
        .as_ref()
        .expect("the dataset names its frame")
        .as_str()
        .to_owned();
    assert!(crs.starts_with("ENGCRS["), "{crs}");
    let written = crs
        .split("latitude ")
        .nth(1)
        .and_then(|rest| rest.split(',').next())
        .and_then(|number| number.parse::<f64>().ok())
        .unwrap_or_else(|| panic!("no latitude in {crs}"));
    assert!((written - lat.to_degrees()).abs() < 1e-6, "{crs}");
    (lat, lon)
}

#[test]
fn a_tileset_at_berlin_imports_at_the_finest_level_within_a_millimetre() {
    let src = fresh_dir("berlin-src");
    let (tileset, contents) = write_tileset(&src);
    let (dataset, out) = import_ok(&tileset, "berlin-finest", &["--format", "rgba8"]);
    let finest: Vec<&Written> = contents.iter().filter(|(_, f)| *f).map(|(w, _)| w).collect();
    let (lat, lon) = check_positions(&dataset, &finest);
    // `info --json` reports the frame's centre.
    let info = citystream(&["info", out.to_str().expect("utf-8"), "--json"]);
    assert!(info.status.success(), "{}", stderr(&info));
    let info: Value = serde_json::from_slice(&info.stdout).expect("info JSON");
    let frame = &info["local_frame"];
    let degrees = |key: &str| frame[key].as_f64().unwrap_or_else(|| panic!("{key} in {frame}"));
    assert!((degrees("latitude_deg") - lat.to_degrees()).abs() < 1e-7, "{frame}");
    assert!((degrees("longitude_deg") - lon.to_degrees()).abs() < 1e-7, "{frame}");
    // a2, rtc and shared: three images, and the shared one is a.glb's too.
    assert_eq!(dataset.textures.len(), 3);
    for (mesh, written) in dataset.scene.meshes.iter().zip(&finest) {
        let png = image::load_from_memory(&written.png).expect("png").to_rgba8();
        let mut level = Vec::new();
        dataset.textures.read_mip(mesh.texture, 0, &mut level).expect("mip 0");
        assert_eq!(level, png.into_raw(), "{}: texture bytes", written.file);
    }
}

#[test]
fn tilesets_near_the_poles_across_the_antimeridian_below_the_sea_and_on_everest_import_within_a_millimetre() {
    for (name, at) in [
        // 1.1 km from the North Pole, and 11 km from the South Pole on the ice sheet.
        ("north-pole", (89.99, 45.0, 50.0)),
        ("south-pole", (-89.9, -100.0, 2_800.0)),
        // On the antimeridian: the contents lie on both sides of ±180°.
        ("antimeridian", (-16.5, 179.999_5, 10.0)),
        // The Dead Sea's shore and Everest's summit (ellipsoidal heights near them).
        ("dead-sea", (31.5, 35.5, -430.0)),
        ("everest", (27.988, 86.925, 8_848.0)),
    ] {
        let src = fresh_dir(&format!("{name}-src"));
        let (tileset, contents) = write_tileset_at(&src, at);
        let (dataset, _) = import_ok(&tileset, name, &["--format", "rgba8"]);
        let finest: Vec<&Written> = contents.iter().filter(|(_, f)| *f).map(|(w, _)| w).collect();
        let (lat, lon) = check_positions(&dataset, &finest);
        // The frame's centre: among the contents, within a kilometre of where they were put.
        let (centre, placed) = (ecef(lat.to_degrees(), lon.to_degrees(), at.2), ecef(at.0, at.1, at.2));
        let apart = (0..3).map(|a| (centre[a] - placed[a]).powi(2)).sum::<f64>().sqrt();
        assert!(
            apart < 1_000.0,
            "{name}: the frame's centre is {apart} m from the tileset's place"
        );
        if name == "antimeridian" {
            let east = |w: &Written| w.corners_ecef.iter().any(|p| p[1] > 0.0);
            let west = |w: &Written| w.corners_ecef.iter().any(|p| p[1] < 0.0);
            assert!(
                finest.iter().any(|w| east(w)) && finest.iter().any(|w| west(w)),
                "the contents do not cross the antimeridian"
            );
        }
    }
}

#[test]
fn a_tileset_placed_far_from_the_earths_surface_is_refused_with_its_distance() {
    for (name, transform, expect) in [
        // A root transform 1,000 km up: not near the surface.
        (
            "orbit",
            enu_to_ecef(BERLIN.0, BERLIN.1, 1_000_000.0),
            "from the Earth's centre, not near its surface",
        ),
        // 10,000 km from the Earth's centre, 3,600 km above its surface.
        (
            "ten-thousand-km",
            translation([10_000_000.0 / 3f64.sqrt(); 3]),
            "from the Earth's centre, not near its surface",
        ),
        // No placement at all: contents at the Earth's centre.
        (
            "centre",
            translation([0.0; 3]),
            "from the Earth's centre, not near its surface",
        ),
    ] {
        let dir = fresh_dir(&format!("far-{name}"));
        std::fs::write(dir.join("wall.glb"), wall_glb(1)).expect("write content");
        let tileset = json!({
            "asset": {"version": "1.1"},
            "geometricError": 10.0,
            "root": {
                "boundingVolume": {"sphere": [0.0, 0.0, 0.0, 1.0e7]},
                "geometricError": 0.0,
                "transform": flat(&transform),
                "content": {"uri": "wall.glb"}
            }
        });
        std::fs::write(dir.join("tileset.json"), serde_json::to_vec(&tileset).expect("json")).expect("write");
        let out = import(&dir.join("tileset.json"), &fresh_dir(&format!("far-{name}-out")), &[]);
        assert!(!out.status.success(), "{name}: imported");
        let message = stderr(&out);
        assert!(message.contains(expect), "{name}: {message}");
        assert!(!message.contains("panicked"), "{name}: {message}");
    }
}

#[test]
fn every_level_shares_the_texture_two_tiles_use() {
    let src = fresh_dir("all-src");
    let (tileset, contents) = write_tileset(&src);
    let (dataset, _) = import_ok(&tileset, "berlin-all", &["--format", "rgba8", "--lod", "all"]);
    let all: Vec<&Written> = contents.iter().map(|(w, _)| w).collect();
    check_positions(&dataset, &all);
    // Five walls, four images: a.glb and ext/shared.b3dm share one.
    assert_eq!(dataset.scene.meshes.len(), 5);
    assert_eq!(dataset.textures.len(), 4);
    assert_eq!(dataset.scene.meshes[1].texture, dataset.scene.meshes[4].texture);
}

fn error_of(tileset: &Value, dir: &Path, name: &str) -> String {
    std::fs::write(dir.join(name), serde_json::to_vec(tileset).expect("json")).expect("write");
    let out = import(&dir.join(name), &fresh_dir(&format!("bad-{name}")), &[]);
    assert!(!out.status.success(), "{name} was imported");
    stderr(&out)
}

#[test]
fn hostile_tilesets_are_refused_naming_the_tile() {
    let dir = fresh_dir("hostile");
    let (_, _) = write_tileset(&dir);
    let tile = |extra: Value| {
        let mut root =
            json!({"boundingVolume": {"sphere": [0.0, 0.0, 0.0, 1.0]}, "geometricError": 1.0, "refine": "ADD"});
        root.as_object_mut()
            .expect("object")
            .extend(extra.as_object().expect("object").clone());
        json!({"asset": {"version": "1.1"}, "geometricError": 1.0, "root": root})
    };
    // External tilesets in a cycle.
    std::fs::write(
        dir.join("loop-b.json"),
        serde_json::to_vec(&tile(json!({"content": {"uri": "loop-a.json"}}))).expect("json"),
    )
    .expect("write");
    let e = error_of(&tile(json!({"content": {"uri": "loop-b.json"}})), &dir, "loop-a.json");
    assert!(e.contains("cycle"), "{e}");
    // A URI leaving the tileset's directory.
    std::fs::write(dir.parent().expect("parent").join("outside.glb"), b"glTF").expect("write");
    let e = error_of(
        &tile(json!({"content": {"uri": "../outside.glb"}})),
        &dir,
        "escape.json",
    );
    assert!(e.contains("outside the tileset's directory"), "{e}");
    let e = error_of(
        &tile(json!({"content": {"uri": "https://example.com/a.glb"}})),
        &dir,
        "url.json",
    );
    assert!(e.contains("not a relative path"), "{e}");
    // Numbers.
    let e = error_of(&tile(json!({"geometricError": -1.0})), &dir, "negative.json");
    assert!(e.contains("geometricError -1") && e.contains("#root"), "{e}");
    let e = error_of(&tile(json!({"transform": [1.0, 0.0, 0.0]})), &dir, "short.json");
    assert!(e.contains("transform") && e.contains("16 finite numbers"), "{e}");
    let e = error_of(
        &tile(json!({"children": [{"geometricError": 0.0, "boundingVolume": {"sphere": [0.0, 0.0, 0.0, -5.0]}}]})),
        &dir,
        "radius.json",
    );
    assert!(e.contains("negative radius") && e.contains("#root/0"), "{e}");
    let e = error_of(&tile(json!({"refine": "MERGE"})), &dir, "refine.json");
    assert!(e.contains("MERGE"), "{e}");
    // A b3dm whose header disagrees with the file, named with its tile.
    let mut b3dm = std::fs::read(dir.join("coarse.b3dm")).expect("read");
    b3dm.truncate(b3dm.len() - 3);
    std::fs::write(dir.join("cut.b3dm"), b3dm).expect("write");
    let e = error_of(&tile(json!({"content": {"uri": "cut.b3dm"}})), &dir, "cut.json");
    assert!(e.contains("cut.b3dm") && e.contains("declares"), "{e}");
    // A glTF content whose buffer lies outside the tileset's directory.
    let (mut gltf, _) = write::textured_quad(wall([0.0; 3], 1.0), &write::gradient_png(4, 4, 8), json!({}), None);
    gltf["buffers"] = json!([{"uri": "../outside.glb", "byteLength": 4}]);
    write_json(&dir.join("escape.gltf"), &gltf);
    let e = error_of(
        &tile(json!({"content": {"uri": "escape.gltf"}})),
        &dir,
        "gltf-escape.json",
    );
    assert!(
        e.contains("escape.gltf") && e.contains("outside the tileset's directory"),
        "{e}"
    );
    // Content requiring an extension the import does not decode is skipped naming it and the
    // file; with nothing else to import, the import fails.
    let (mut gltf, bin) = write::textured_quad(wall([0.0; 3], 1.0), &write::gradient_png(4, 4, 9), json!({}), None);
    gltf["extensionsRequired"] = json!(["KHR_draco_mesh_compression", "EXT_texture_webp"]);
    std::fs::write(dir.join("webp.glb"), write::glb(&gltf, &bin)).expect("write");
    let e = error_of(&tile(json!({"content": {"uri": "webp.glb"}})), &dir, "webp.json");
    assert!(
        e.contains("1 glTF content listings skipped (webp.glb)") && e.contains("require EXT_texture_webp"),
        "{e}"
    );
    // A --crs other than UTM cannot be projected into: said, not ignored.
    let out = import(&dir.join("tileset.json"), &fresh_dir("crs"), &["--crs", "EPSG:3857"]);
    assert!(
        !out.status.success() && stderr(&out).contains("not implemented"),
        "{}",
        stderr(&out)
    );
}

#[test]
fn content_that_is_not_imported_is_counted_and_strict_refuses_it() {
    let dir = fresh_dir("skipped");
    let (_, _) = write_tileset(&dir);
    std::fs::write(dir.join("cloud.pnts"), b"pnts").expect("write");
    let (lat, lon, h) = BERLIN;
    let tileset = json!({
        "asset": {"version": "1.0"},
        "geometricError": 1.0,
        "root": {
            "boundingVolume": {"sphere": [0.0, 0.0, 0.0, 1.0]},
            "geometricError": 1.0,
            "refine": "ADD",
            "transform": flat(&enu_to_ecef(lat, lon, h)),
            "content": {"uri": "a.glb"},
            "children": [
                {"geometricError": 0.0, "content": {"uri": "cloud.pnts"}},
                {"geometricError": 0.0, "content": {"uri": "cloud.pnts"}},
                {"geometricError": 0.0, "content": {"uri": "content/{level}/{x}/{y}.glb"},
                 "implicitTiling": {"subdivisionScheme": "QUADTREE", "subtreeLevels": 2,
                                    "availableLevels": 2, "subtrees": {"uri": "subtrees/{level}.subtree"}}}
            ]
        }
    });
    write_json(&dir.join("mixed.json"), &tileset);
    let out = import(&dir.join("mixed.json"), &fresh_dir("mixed"), &[]);
    let e = stderr(&out);
    assert!(out.status.success(), "{e}");
    assert!(e.contains("warning") && e.contains("2 point clouds (pnts)"), "{e}");
    assert!(e.contains("1 implicitly tiled subtrees"), "{e}");
    // Without the root transform the content is in a local frame, not Earth-centred.
    let mut local = tileset.clone();
    local["root"].as_object_mut().expect("object").remove("transform");
    let e = error_of(&local, &dir, "local.json");
    assert!(e.contains("EPSG:4978"), "{e}");
    let strict = import(&dir.join("mixed.json"), &fresh_dir("mixed-strict"), &["--strict"]);
    assert!(!strict.status.success());
    assert!(stderr(&strict).contains("--strict"), "{}", stderr(&strict));
}

/// The scene and every mip of two datasets are the same.
fn assert_same_dataset(a: &Dataset, b: &Dataset) {
    let (sa, sb) = (&a.scene, &b.scene);
    assert_eq!(sa.origin, sb.origin);
    assert_eq!(sa.crs, sb.crs);
    assert_eq!(sa.positions, sb.positions);
    assert_eq!(sa.normals, sb.normals);
    assert_eq!(sa.uvs, sb.uvs);
    assert_eq!(sa.indices, sb.indices);
    assert_eq!(sa.meshes.len(), sb.meshes.len());
    for (ma, mb) in sa.meshes.iter().zip(&sb.meshes) {
        assert_eq!(
            (
                ma.first_vertex,
                ma.vertex_count,
                ma.first_index,
                ma.index_count,
                ma.texture
            ),
            (
                mb.first_vertex,
                mb.vertex_count,
                mb.first_index,
                mb.index_count,
                mb.texture
            )
        );
    }
    assert_eq!(a.textures.len(), b.textures.len());
    let (mut la, mut lb) = (Vec::new(), Vec::new());
    for (id, info) in a.textures.textures().iter().enumerate() {
        for level in 0..info.mip_count() {
            a.textures.read_mip(id as u32, level, &mut la).expect("mip");
            b.textures.read_mip(id as u32, level, &mut lb).expect("mip");
            assert_eq!(la, lb, "texture {id} level {level}");
        }
    }
}

#[test]
#[cfg_attr(
    citystream_skip_nginx,
    ignore = "nginx is not installed and `make setup` has not run"
)]
fn a_tileset_served_over_http_imports_as_it_does_from_disk() {
    let work = fresh_dir("http");
    let served = work.join("www/city3d");
    std::fs::create_dir_all(&served).expect("mkdir");
    let (tileset, _) = write_tileset(&served);
    assert!(
        citystream_testing::nginx::binary().is_some() || !cli_support::setup_ran(),
        "nginx is missing although the setup script ran: it should have installed nginx-light"
    );
    let nginx = citystream_testing::nginx::Nginx::start(&work, &work.join("www")).expect("start nginx");
    let (local, _) = import_ok(&tileset, "http-local", &["--lod", "all"]);
    let url = nginx.url("city3d/tileset.json");
    let out = fresh_dir("http-remote");
    // What a killed import leaves: its download directory, marked with its dead process.
    let mut stale = out.as_os_str().to_owned();
    stale.push(".tileset-download");
    let stale = PathBuf::from(stale);
    let mut finished = std::process::Command::new("true").spawn().expect("spawn");
    let dead = finished.id();
    finished.wait().expect("wait");
    std::fs::create_dir_all(stale.join("city3d")).expect("mkdir");
    std::fs::write(stale.join(".citystream-tileset-download"), dead.to_string()).expect("marker");
    std::fs::write(stale.join("city3d/half.b3dm"), b"b3dm").expect("partial file");
    let imported = import(Path::new(&url), &out, &["--lod", "all"]);
    assert!(
        imported.status.success(),
        "import of {url} failed: {}",
        stderr(&imported)
    );
    assert!(
        String::from_utf8_lossy(&imported.stdout).contains(&url),
        "{}",
        String::from_utf8_lossy(&imported.stdout)
    );
    let remote = Dataset::open(&out).expect("open");
    assert_same_dataset(&local, &remote);
    // The scratch copy is gone, and a missing file is named by its URL.
    let mut scratch = out.as_os_str().to_owned();
    scratch.push(".tileset-download");
    assert!(!Path::new(&scratch).exists());
    assert!(
        stderr(&imported).contains(&format!("process {dead}")),
        "the stale download directory was not cleared with a word: {}",
        stderr(&imported)
    );
    // A hosted tileset's URL with a token: recognised as a tileset, the token sent with
    // every request.
    let with_token = format!("{url}?token=abc");
    let tokened = import(Path::new(&with_token), &fresh_dir("http-token"), &["--lod", "all"]);
    assert!(
        tokened.status.success(),
        "import of {with_token} failed: {}",
        stderr(&tokened)
    );
    let requests = nginx.requests();
    let content: Vec<&String> = requests
        .iter()
        .filter(|r| r.contains(".b3dm") || r.contains(".glb"))
        .collect();
    assert!(!content.is_empty(), "{requests:?}");
    assert!(
        requests
            .iter()
            .filter(|r| r.contains("tileset.json"))
            .any(|r| r.contains("?token=abc")),
        "{requests:?}"
    );
    assert!(
        content.iter().rev().take(3).all(|r| r.contains("token=abc")),
        "{requests:?}"
    );
    // A directory of that name that no import wrote is not deleted.
    let foreign_out = fresh_dir("http-foreign");
    let mut foreign = foreign_out.as_os_str().to_owned();
    foreign.push(".tileset-download");
    std::fs::create_dir_all(&foreign).expect("mkdir");
    std::fs::write(Path::new(&foreign).join("notes.txt"), b"mine").expect("write");
    let refused = import(Path::new(&url), &foreign_out, &[]);
    assert!(!refused.status.success(), "imported over a directory it did not write");
    assert!(Path::new(&foreign).join("notes.txt").exists());
    std::fs::remove_file(served.join("ext/shared.b3dm")).expect("remove");
    let broken = import(Path::new(&url), &fresh_dir("http-broken"), &[]);
    assert!(!broken.status.success());
    let e = stderr(&broken);
    assert!(e.contains("ext/shared.b3dm") && e.contains("http://"), "{e}");
}

#[test]
fn a_tileset_projected_into_utm_lands_where_proj_puts_it() {
    // One wall standing at the Brandenburg Gate: its first corner is the frame's origin.
    let dir = fresh_dir("utm-src");
    let (lat, lon, h) = BERLIN;
    std::fs::write(dir.join("gate.glb"), wall_glb(5)).expect("write");
    let tileset = json!({
        "asset": {"version": "1.1"},
        "geometricError": 1.0,
        "root": {
            "boundingVolume": {"sphere": [0.0, 0.0, 0.0, 20.0]},
            "geometricError": 0.0,
            "refine": "REPLACE",
            "transform": flat(&enu_to_ecef(lat, lon, h)),
            "content": {"uri": "gate.glb"}
        }
    });
    write_json(&dir.join("tileset.json"), &tileset);
    let (dataset, _) = import_ok(&dir.join("tileset.json"), "utm", &["--crs", "EPSG:25833"]);
    let scene = &dataset.scene;
    assert_eq!(scene.crs.as_ref().map(|c| c.as_str()), Some("EPSG:25833"));
    let absolute = |v: usize| -> [f64; 3] {
        let p = scene.positions[v];
        let s: [f64; 3] = std::array::from_fn(|a| scene.origin[a] + f64::from(p[a]));
        // Scene axes to (easting, northing, height).
        [s[0], -s[2], s[1]]
    };
    // PROJ 9.5.1 (pyproj 3.7.2): EPSG:4326 (52.516275, 13.377704) to UTM 33N is
    // (389918.0416, 5819699.1324); UTM is conformal, so the wall's top-left corner, 8 m
    // up, lies over it.
    for (vertex, height) in [(0, 34.0), (3, 42.0)] {
        let [e, n, up] = absolute(vertex);
        assert!(
            (e - 389_918.041_6).abs() < 0.01 && (n - 5_819_699.132_4).abs() < 0.01 && (up - height).abs() < 0.01,
            "vertex {vertex}: ({e}, {n}, {up})"
        );
    }
    // 8 m east along the ground: 8 m times the scale there (PROJ: 0.9997487).
    let [e0, n0, _] = absolute(0);
    let [e1, n1, h1] = absolute(1);
    let distance = (e1 - e0).hypot(n1 - n0);
    assert!((distance - 8.0 * 0.999_748_7).abs() < 2e-4, "{distance}");
    assert!((h1 - 34.0).abs() < 0.01, "{h1}");
}

#[test]
fn an_external_tileset_inherits_the_up_axis_above_it() {
    // The root says its glTF content is z-up (before 3D Tiles 1.0); the external tileset
    // says nothing, so its wall's glTF y axis points north, not up.
    let dir = fresh_dir("up-axis-src");
    let (lat, lon, h) = BERLIN;
    std::fs::write(dir.join("wall.glb"), wall_glb(6)).expect("write");
    let external = json!({
        "asset": {"version": "1.0"},
        "geometricError": 1.0,
        "root": {"geometricError": 0.0, "content": {"uri": "wall.glb"}}
    });
    write_json(&dir.join("ext.json"), &external);
    let root = json!({
        "asset": {"version": "0.0", "gltfUpAxis": "Z"},
        "geometricError": 1.0,
        "root": {
            "geometricError": 1.0,
            "refine": "REPLACE",
            "transform": flat(&enu_to_ecef(lat, lon, h)),
            "content": {"uri": "ext.json"}
        }
    });
    write_json(&dir.join("tileset.json"), &root);
    let (dataset, _) = import_ok(&dir.join("tileset.json"), "up-axis", &[]);
    let p = &dataset.scene.positions;
    // Vertex 3 is 8 along the glTF's y: 8 m north (scene −z), at the same height.
    let d: [f32; 3] = std::array::from_fn(|a| p[3][a] - p[0][a]);
    assert!(
        d[0].abs() < 1e-3 && d[1].abs() < 1e-3 && (d[2] + 8.0).abs() < 1e-3,
        "{d:?}"
    );
}

/// Buffer URIs that a reader would interpret itself: `file:` with a decoy of the same
/// name inside the tileset's directory (the outside file must not be read), `file:` of a
/// device (refused before reading), and a percent-escape that is not UTF-8: each refused
/// with a clear error naming the URI, never a panic.
#[test]
fn buffer_uris_with_a_scheme_or_bad_escapes_are_refused_naming_them() {
    let dir = fresh_dir("uri-shapes");
    let (_, _) = write_tileset(&dir);
    let tile = |uri: &str| {
        json!({"asset": {"version": "1.1"}, "geometricError": 1.0, "root": {
            "boundingVolume": {"sphere": [0.0, 0.0, 0.0, 1.0]}, "geometricError": 1.0, "refine": "ADD",
            "content": {"uri": uri}}})
    };
    let outside = dir.parent().expect("parent").join("outside-buffer.bin");
    std::fs::write(&outside, vec![0u8; 256]).expect("write");
    let file_uri = format!("file:{}", outside.display());
    // The decoy: a file named like the URI, inside the tileset's directory.
    let decoy = dir.join(&file_uri);
    std::fs::create_dir_all(decoy.parent().expect("parent")).expect("decoy dirs");
    std::fs::write(&decoy, vec![0u8; 256]).expect("decoy");
    std::fs::write(dir.join("\u{fffd}.bin"), vec![0u8; 256]).expect("replacement-named file");
    for (name, uri, needle) in [
        ("file-decoy", file_uri.as_str(), "names a scheme"),
        ("dev-zero", "file:/dev/zero", "names a scheme"),
        ("bad-escape", "%FF.bin", "does not percent-decode to UTF-8"),
    ] {
        let (mut gltf, _) = write::textured_quad(wall([0.0; 3], 1.0), &write::gradient_png(4, 4, 8), json!({}), None);
        gltf["buffers"] = json!([{"uri": uri, "byteLength": 256}]);
        std::fs::write(
            dir.join(format!("{name}.gltf")),
            serde_json::to_vec(&gltf).expect("json"),
        )
        .expect("write");
        let e = error_of(&tile(&format!("{name}.gltf")), &dir, &format!("{name}.json"));
        assert!(e.contains(needle) && e.contains(&format!("{name}.gltf")), "{name}: {e}");
        assert!(!e.contains("panicked"), "{name}: {e}");
    }
}

/// A content file listed by many tiles is read once and placed for each listing: the
/// import says so in its progress, and gives exactly the dataset that as many copies of
/// the file, each listed once, give.
#[test]
fn a_content_listed_by_many_tiles_is_read_once_and_placed_for_each() {
    let dir = fresh_dir("listed-many");
    let (lat, lon, h) = BERLIN;
    let glb = wall_glb(5);
    std::fs::write(dir.join("a.glb"), &glb).expect("write");
    std::fs::create_dir_all(dir.join("copies")).expect("mkdir");
    let listings = 400;
    let children = |uri: &dyn Fn(usize) -> String| -> Vec<Value> {
        (0..listings)
            .map(|i| {
                json!({
                    "boundingVolume": {"sphere": [0.0, 0.0, 0.0, 20.0]},
                    "geometricError": 0.0,
                    "transform": flat(&translation([i as f64 * 10.0, 0.0, (i % 7) as f64])),
                    "content": {"uri": uri(i)}
                })
            })
            .collect()
    };
    let tileset = |children: Vec<Value>| {
        json!({
            "asset": {"version": "1.1"},
            "geometricError": 1.0,
            "root": {
                "boundingVolume": {"sphere": [0.0, 0.0, 0.0, 5000.0]},
                "geometricError": 1.0,
                "refine": "ADD",
                "transform": flat(&enu_to_ecef(lat, lon, h)),
                "children": children
            }
        })
    };
    for i in 0..listings {
        std::fs::write(dir.join(format!("copies/a{i}.glb")), &glb).expect("write copy");
    }
    let one = dir.join("one.json");
    std::fs::write(
        &one,
        serde_json::to_vec(&tileset(children(&|_| "a.glb".to_owned()))).expect("json"),
    )
    .expect("write");
    let many = dir.join("many.json");
    std::fs::write(
        &many,
        serde_json::to_vec(&tileset(children(&|i| format!("copies/a{i}.glb")))).expect("json"),
    )
    .expect("write");
    let out = fresh_dir("listed-many-one");
    let imported = import(&one, &out, &[]);
    assert!(imported.status.success(), "{}", stderr(&imported));
    assert!(
        stderr(&imported).contains(&format!("{listings}/{listings} contents (1/1 files read)")),
        "{}",
        stderr(&imported)
    );
    let (copies, _) = import_ok(&many, "listed-many-copies", &[]);
    let once = Dataset::open(&out).expect("open");
    assert_eq!(once.scene.meshes.len(), listings);
    assert_same_dataset(&once, &copies);
}

/// Tileset JSON is bounded before it is parsed (a parsed tile takes some 80 times the
/// bytes of `{}`): 8 MB of empty tiles is refused, naming the count, within 400 MB of
/// address space (it took 685 MB parsed); a file hard-linked as its own external tileset
/// a few levels deep is refused once the levels held together pass the bound.
#[test]
fn tileset_json_is_bounded_before_it_is_parsed() {
    let dir = fresh_dir("json-bound");
    let empty_tiles = |n: usize, child: Option<&str>| {
        let content = child.map_or(String::new(), |uri| format!(",\"content\":{{\"uri\":\"{uri}\"}}"));
        format!(
            "{{\"asset\":{{\"version\":\"1.1\"}},\"geometricError\":1,\"root\":{{\"geometricError\":1,\
             \"boundingVolume\":{{\"sphere\":[0,0,0,1]}}{content},\"children\":[{}]}}}}",
            vec!["{}"; n].join(",")
        )
    };
    let big = dir.join("big.json");
    std::fs::write(&big, empty_tiles(2_700_000, None)).expect("write");
    assert!(std::fs::metadata(&big).expect("size").len() > 8_000_000);
    let output = std::process::Command::new("sh")
        .arg("-c")
        .arg(r#"ulimit -v 400000 && exec "$0" import "$1" --out "$2""#)
        .arg(env!("CARGO_BIN_EXE_citystream"))
        .arg(&big)
        .arg(fresh_dir("json-bound-out"))
        .output()
        .expect("import runs");
    let text = stderr(&output);
    assert_eq!(
        output.status.code(),
        Some(1),
        "killed or imported instead of an error: {text}"
    );
    assert!(text.contains("2700004 JSON objects"), "{text}");

    // 600,000 objects a level, each level the same file (hard-linked one directory down):
    // the third level held with the two above passes the bound.
    let top = dir.join("chain");
    std::fs::create_dir_all(top.join("sub/sub")).expect("mkdir");
    std::fs::write(top.join("tileset.json"), empty_tiles(600_000, Some("sub/tileset.json"))).expect("write");
    std::fs::hard_link(top.join("tileset.json"), top.join("sub/tileset.json")).expect("hard link");
    std::fs::hard_link(top.join("tileset.json"), top.join("sub/sub/tileset.json")).expect("hard link");
    let out = import(&top.join("tileset.json"), &fresh_dir("json-bound-chain"), &[]);
    let text = stderr(&out);
    assert!(!out.status.success(), "imported");
    assert!(text.contains("JSON objects") && text.contains("held at once"), "{text}");
}
