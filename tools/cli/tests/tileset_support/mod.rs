//! The 3D Tiles tileset the import tests write (and the flythrough's tests fly), placed at
//! Berlin, with the geometry that checks where its content lands independently of the
//! importer (each test file that needs it includes this module).

#![allow(dead_code)] // reason: each test binary uses a different subset

use std::path::{Path, PathBuf};

use citystream_import::tiles::write;
use serde_json::{json, Value};

pub type Mat4 = [[f64; 4]; 4];

/// Column-major product a × b.
pub fn mul(a: &Mat4, b: &Mat4) -> Mat4 {
    std::array::from_fn(|c| std::array::from_fn(|r| (0..4).map(|k| a[k][r] * b[c][k]).sum()))
}

pub fn apply(m: &Mat4, p: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|r| m[0][r] * p[0] + m[1][r] * p[1] + m[2][r] * p[2] + m[3][r])
}

pub fn translation(t: [f64; 3]) -> Mat4 {
    [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [t[0], t[1], t[2], 1.0],
    ]
}

pub fn flat(m: &Mat4) -> Vec<f64> {
    m.iter().flatten().copied().collect()
}

/// WGS 84, written out here rather than taken from the importer.
pub const A: f64 = 6_378_137.0;
pub const F: f64 = 1.0 / 298.257_223_563;

pub fn ecef(lat_deg: f64, lon_deg: f64, h: f64) -> [f64; 3] {
    let e2 = F * (2.0 - F);
    let (lat, lon) = (lat_deg.to_radians(), lon_deg.to_radians());
    let n = A / (1.0 - e2 * lat.sin().powi(2)).sqrt();
    [
        (n + h) * lat.cos() * lon.cos(),
        (n + h) * lat.cos() * lon.sin(),
        (n * (1.0 - e2) + h) * lat.sin(),
    ]
}

/// Geodetic latitude and longitude (radians) by fixed-point iteration on the latitude.
pub fn geodetic(p: [f64; 3]) -> (f64, f64) {
    let e2 = F * (2.0 - F);
    let r = p[0].hypot(p[1]);
    let mut lat = (p[2] / r).atan();
    for _ in 0..20 {
        let n = A / (1.0 - e2 * lat.sin().powi(2)).sqrt();
        lat = ((p[2] + e2 * n * lat.sin()) / r).atan();
    }
    (lat, p[1].atan2(p[0]))
}

/// The textbook east-north-up rotation at geodetic (lat, lon) as rows east, north, up.
pub fn enu_rows(lat: f64, lon: f64) -> [[f64; 3]; 3] {
    let (sl, cl) = lat.sin_cos();
    let (so, co) = lon.sin_cos();
    [[-so, co, 0.0], [-sl * co, -sl * so, cl], [cl * co, cl * so, sl]]
}

/// The ENU → ECEF transform at (lat, lon, h), as a tileset's root transform.
pub fn enu_to_ecef(lat_deg: f64, lon_deg: f64, h: f64) -> Mat4 {
    let [e, n, u] = enu_rows(lat_deg.to_radians(), lon_deg.to_radians());
    let o = ecef(lat_deg, lon_deg, h);
    [
        [e[0], e[1], e[2], 0.0],
        [n[0], n[1], n[2], 0.0],
        [u[0], u[1], u[2], 0.0],
        [o[0], o[1], o[2], 1.0],
    ]
}

/// glTF y-up to the tiles' z-up, as the 3D Tiles specification gives it.
pub const Y_UP_TO_Z_UP: Mat4 = [
    [1.0, 0.0, 0.0, 0.0],
    [0.0, 0.0, 1.0, 0.0],
    [0.0, -1.0, 0.0, 0.0],
    [0.0, 0.0, 0.0, 1.0],
];

/// A quad in glTF coordinates (y up): `size` metres wide and high, standing at `at`.
pub fn wall(at: [f32; 3], size: f32) -> [[f32; 3]; 4] {
    let [x, y, z] = at;
    [[x, y, z], [x + size, y, z], [x + size, y + size, z], [x, y + size, z]]
}

/// A GLB of one 8 m wall standing at the origin, textured with an 8 × 8 gradient of `seed`.
pub fn wall_glb(seed: u8) -> Vec<u8> {
    let (gltf, bin) = write::textured_quad(wall([0.0; 3], 8.0), &write::gradient_png(8, 8, seed), json!({}), None);
    write::glb(&gltf, &bin)
}

/// Writes `value` to `path` as JSON.
pub fn write_json(path: &Path, value: &Value) {
    std::fs::write(path, serde_json::to_vec(value).expect("json")).expect("write");
}

/// One tile's content as written and where its corners must land (Earth-centred).
pub struct Written {
    pub file: String,
    pub corners_ecef: Vec<[f64; 3]>,
    pub png: Vec<u8>,
}

/// Writes a glb (`b3dm` wraps it) of one textured wall into `dir/file`.
#[allow(clippy::too_many_arguments)]
pub fn write_content(
    dir: &Path,
    file: &str,
    corners: [[f32; 3]; 4],
    png: Vec<u8>,
    node: Value,
    node_matrix: &Mat4,
    extensions: Option<Value>,
    b3dm_rtc: Option<[f64; 3]>,
    placed_by: &Mat4,
) -> Written {
    let (gltf, bin) = write::textured_quad(corners, &png, node, extensions);
    let glb = write::glb(&gltf, &bin);
    let bytes = match b3dm_rtc {
        Some(rtc) => write::b3dm(
            &glb,
            &json!({"BATCH_LENGTH": 1, "RTC_CENTER": rtc}),
            Some(&json!({"height": [12.5]})),
            &[],
        ),
        None if file.ends_with(".b3dm") => write::b3dm(&glb, &json!({"BATCH_LENGTH": 0}), None, &[]),
        None => glb,
    };
    std::fs::write(dir.join(file), bytes).expect("write content");
    let m = mul(placed_by, &mul(&Y_UP_TO_Z_UP, node_matrix));
    Written {
        file: file.to_owned(),
        corners_ecef: corners.iter().map(|c| apply(&m, c.map(f64::from))).collect(),
        png,
    }
}

/// Berlin (Brandenburg Gate), 34 m above the ellipsoid.
pub const BERLIN: (f64, f64, f64) = (52.516_275, 13.377_704, 34.0);

/// The test tileset at Berlin; returns its path and, in walk order, every content with the
/// level flag `finest` (whether `--lod finest` imports it).
pub fn write_tileset(dir: &Path) -> (PathBuf, Vec<(Written, bool)>) {
    write_tileset_at(dir, BERLIN)
}

/// The test tileset at `(latitude°, longitude°, height m)`: its contents span about 700 m
/// east to west and 400 m south to north of that point.
pub fn write_tileset_at(dir: &Path, (lat, lon, h): (f64, f64, f64)) -> (PathBuf, Vec<(Written, bool)>) {
    let frame = enu_to_ecef(lat, lon, h);
    let shared_png = write::gradient_png(64, 32, 1);
    let identity = translation([0.0; 3]);
    // Root (REPLACE, no transform): a coarse wall as b3dm with RTC_CENTER at the gate.
    let coarse = write_content(
        dir,
        "coarse.b3dm",
        wall([-50.0, 0.0, 0.0], 100.0),
        write::gradient_png(16, 16, 4),
        json!({}),
        &identity,
        None,
        Some(ecef(lat, lon, h)),
        &translation(ecef(lat, lon, h)),
    );
    // Tile 1: the east-north-up frame at the gate; its glb has a node translation.
    let node_t = translation([10.0, 0.0, -5.0]);
    let a = write_content(
        dir,
        "a.glb",
        wall([0.0, 0.0, 0.0], 20.0),
        shared_png.clone(),
        json!({"translation": [10.0, 0.0, -5.0]}),
        &node_t,
        None,
        None,
        &frame,
    );
    // Tile 1a: 300 m east and 1.5 m up of tile 1, nested transforms.
    let nested = translation([300.0, 0.0, 1.5]);
    let a2 = write_content(
        dir,
        "a2.glb",
        wall([0.0, 0.0, 0.0], 8.0),
        write::gradient_png(32, 32, 2),
        json!({}),
        &identity,
        None,
        None,
        &mul(&frame, &nested),
    );
    // External tileset (ADD): a glb with CESIUM_RTC 400 m north of the gate, and a child
    // b3dm with the first texture again.
    std::fs::create_dir_all(dir.join("ext")).expect("mkdir");
    let north = apply(&frame, [0.0, 400.0, 0.0]);
    let rtc = write_content(
        &dir.join("ext"),
        "rtc.glb",
        wall([0.0, 0.0, 0.0], 12.0),
        write::gradient_png(16, 64, 3),
        json!({}),
        &identity,
        Some(json!({"CESIUM_RTC": {"center": north}})),
        None,
        &translation(north),
    );
    let shared = write_content(
        &dir.join("ext"),
        "shared.b3dm",
        wall([5.0, 0.0, 5.0], 6.0),
        shared_png,
        json!({}),
        &identity,
        None,
        // RTC_CENTER under a rotated tile transform: the centre is in the tile's frame.
        Some([3.0, -4.0, 5.0]),
        &mul(
            &mul(&frame, &translation([-200.0, -100.0, 0.0])),
            &translation([3.0, -4.0, 5.0]),
        ),
    );
    let external = json!({
        "asset": {"version": "1.1"},
        "geometricError": 10.0,
        "root": {
            "boundingVolume": {"sphere": [north[0], north[1], north[2], 50.0]},
            "geometricError": 5.0,
            "refine": "ADD",
            "content": {"uri": "rtc.glb"},
            "children": [{
                "boundingVolume": {"sphere": [0.0, 0.0, 0.0, 1.0e7]},
                "geometricError": 0.0,
                "transform": flat(&mul(&frame, &translation([-200.0, -100.0, 0.0]))),
                "content": {"uri": "shared.b3dm"}
            }]
        }
    });
    std::fs::write(
        dir.join("ext/tileset.json"),
        serde_json::to_vec_pretty(&external).expect("json"),
    )
    .expect("write external");
    let tileset = json!({
        "asset": {"version": "1.0"},
        "geometricError": 500.0,
        "root": {
            "boundingVolume": {"region": region_around(lat, lon, h)},
            "geometricError": 100.0,
            "refine": "REPLACE",
            "content": {"uri": "coarse.b3dm"},
            "children": [
                {
                    "boundingVolume": {"box": [0.0, 0.0, 0.0, 500.0, 0.0, 0.0, 0.0, 500.0, 0.0, 0.0, 0.0, 50.0]},
                    "geometricError": 20.0,
                    "transform": flat(&frame),
                    "content": {"uri": "a.glb"},
                    "children": [{
                        "boundingVolume": {"sphere": [0.0, 0.0, 0.0, 20.0]},
                        "geometricError": 0.0,
                        "transform": flat(&nested),
                        "content": {"uri": "a2.glb"}
                    }]
                },
                {
                    "boundingVolume": {"sphere": [north[0], north[1], north[2], 50.0]},
                    "geometricError": 10.0,
                    "content": {"uri": "ext/tileset.json"}
                }
            ]
        }
    });
    let path = dir.join("tileset.json");
    std::fs::write(&path, serde_json::to_vec_pretty(&tileset).expect("json")).expect("write tileset");
    let contents = vec![(coarse, false), (a, false), (a2, true), (rtc, true), (shared, true)];
    (path, contents)
}

/// A region (radians west, south, east, north; metres low, high) about 1 km around
/// `(lat°, lon°)` and from 100 m below `h` to 200 m above it: west beyond east where it
/// crosses the antimeridian, as 3D Tiles allows.
fn region_around(lat: f64, lon: f64, h: f64) -> [f64; 6] {
    use std::f64::consts::{FRAC_PI_2, PI};
    let wrap = |x: f64| {
        if x > PI {
            x - 2.0 * PI
        } else if x < -PI {
            x + 2.0 * PI
        } else {
            x
        }
    };
    let (lat, lon, d) = (
        lat.to_radians(),
        lon.to_radians(),
        2e-4 / lat.to_radians().cos().max(1e-3),
    );
    [
        wrap(lon - d.min(PI)),
        (lat - 2e-4).max(-FRAC_PI_2),
        wrap(lon + d.min(PI)),
        (lat + 2e-4).min(FRAC_PI_2),
        h - 100.0,
        h + 200.0,
    ]
}

/// A tileset of `n` textured walls in a row at Berlin, one `.glb` content each
/// (`wallI.glb`), written into `dir`; its `tileset.json`.
pub fn row_of_walls(dir: &Path, n: usize) -> PathBuf {
    let (lat, lon, h) = BERLIN;
    let mut children = Vec::new();
    for i in 0..n {
        let file = format!("wall{i}.glb");
        std::fs::write(dir.join(&file), wall_glb(i as u8 + 1)).expect("write content");
        children.push(json!({
            "boundingVolume": {"sphere": [0.0, 0.0, 0.0, 1.0e7]},
            "geometricError": 0.0,
            "transform": flat(&translation([i as f64 * 30.0, 5.0 * i as f64, 0.0])),
            "content": {"uri": file}
        }));
    }
    let tileset = json!({
        "asset": {"version": "1.0"},
        "geometricError": 100.0,
        "root": {
            "boundingVolume": {"sphere": [0.0, 0.0, 0.0, 1.0e7]},
            "geometricError": 10.0,
            "refine": "ADD",
            "transform": flat(&enu_to_ecef(lat, lon, h)),
            "children": children
        }
    });
    let path = dir.join("tileset.json");
    write_json(&path, &tileset);
    path
}
