//! Camera paths: file format, validation, sampling, and the standard benchmark path.

use citystream_dataset::{Aabb, Scene};
use citystream_streaming::bench::path::{
    standard_path, CameraPath, CameraPose, Keyframe, PathError, Pause, MIN_STANDARD_DURATION_S, PATH_FORMAT_VERSION,
    STANDARD_JUMPS, STANDARD_PAUSES, STANDARD_PAUSE_S,
};

/// A path with a pause at keyframe 1 and a jump at keyframe 3 (to a view 1 km away).
fn sample_path() -> CameraPath {
    CameraPath::new(vec![
        Keyframe::new(0.0, [0.0, 50.0, 0.0], [0.0, 0.0, 40.0]),
        Keyframe {
            hold_s: 2.0,
            ..Keyframe::new(4.0, [20.0, 50.0, 10.0], [20.0, 5.0, 50.0])
        },
        Keyframe::new(9.0, [40.0, 55.0, 30.0], [40.0, 0.0, 70.0]),
        Keyframe {
            jump: true,
            ..Keyframe::new(9.0, [1000.0, 60.0, 1000.0], [1000.0, 0.0, 1040.0])
        },
        Keyframe::new(12.0, [1030.0, 60.0, 1010.0], [1030.0, 0.0, 1050.0]),
        Keyframe::new(15.5, [1050.0, 62.0, 1040.0], [1060.0, 3.0, 1080.0]),
    ])
    .expect("valid path")
}

fn err_of(json: &str) -> PathError {
    match CameraPath::from_json(json) {
        Ok(_) => panic!("accepted invalid path: {json}"),
        Err(e) => e,
    }
}

fn doc(keyframes: &str) -> String {
    format!("{{ \"version\": 1, \"keyframes\": [{keyframes}] }}")
}

fn finite(v: [f32; 3]) -> bool {
    v.iter().all(|x| x.is_finite())
}

fn unit_dir(p: &CameraPose) -> [f64; 3] {
    let d = [0, 1, 2].map(|a| f64::from(p.look_at[a]) - f64::from(p.position[a]));
    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    d.map(|x| x / n)
}

fn angle_deg(a: [f64; 3], b: [f64; 3]) -> f64 {
    (a[0] * b[0] + a[1] * b[1] + a[2] * b[2])
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

/// Upper bound of how far (per axis) the camera may move in `dt` seconds: the Hermite
/// derivative is at most 1.5 × the chord speed plus both tangents, each at most the
/// fastest chord speed.
fn step_bound(path: &CameraPath, dt: f64) -> f64 {
    let k = path.keyframes();
    let mut fastest: f64 = 0.0;
    for w in k.windows(2).filter(|w| !w[1].jump) {
        let span = w[1].t - w[0].end_s();
        for a in 0..3 {
            for (p, q) in [(w[0].position, w[1].position), (w[0].look_at, w[1].look_at)] {
                fastest = fastest.max((f64::from(q[a]) - f64::from(p[a])).abs() / span);
            }
        }
    }
    3.5 * fastest * dt + 1e-3
}

fn max_axis_step(a: &CameraPose, b: &CameraPose) -> f64 {
    (0..3)
        .map(|i| {
            let p = (f64::from(a.position[i]) - f64::from(b.position[i])).abs();
            let l = (f64::from(a.look_at[i]) - f64::from(b.look_at[i])).abs();
            p.max(l)
        })
        .fold(0.0, f64::max)
}

#[test]
fn json_round_trip_is_exact() {
    let path = sample_path().with_description("round trip");
    let text = path.to_json().expect("serialise");
    let back = CameraPath::from_json(&text).expect("parse back");
    assert_eq!(back, path);
    assert_eq!(back.description(), Some("round trip"));

    let dir = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("camera-path");
    std::fs::create_dir_all(&dir).expect("temp dir");
    let file = dir.join("round_trip.json");
    path.save(&file).expect("save");
    assert_eq!(CameraPath::load(&file).expect("load"), path);
}

#[test]
fn documented_keys_parse_as_pauses_and_jumps() {
    let text = r#"{
        "version": 1,
        "keyframes": [
            { "t": 0, "position": [0, 80, -60], "look_at": [0, 10, 0] },
            { "t": 6, "position": [40, 80, -20], "look_at": [40, 10, 40], "hold_s": 2.5 },
            { "t": 14, "position": [90, 80, 10], "look_at": [90, 10, 70] },
            { "t": 14, "position": [-50, 80, 0], "look_at": [0, 10, 0], "jump": true },
            { "t": 20, "position": [-40, 80, 0], "look_at": [0, 10, 10] }
        ]
    }"#;
    let path = CameraPath::from_json(text).expect("documented example parses");
    assert_eq!(path.keyframes().len(), 5);
    assert_eq!(
        path.pauses(),
        vec![Pause {
            start_s: 6.0,
            duration_s: 2.5
        }]
    );
    assert_eq!(path.jumps(), vec![14.0]);
    assert_eq!(path.duration_s(), 20.0);
    // Optional keys at their defaults are not written.
    let written = path.to_json().expect("serialise");
    assert_eq!(written.matches("hold_s").count(), 1, "{written}");
    assert_eq!(written.matches("\"jump\"").count(), 1, "{written}");
    assert!(written.contains(&format!("\"version\": {PATH_FORMAT_VERSION}")));
}

#[test]
fn bad_documents_are_rejected_with_clear_errors() {
    let ok = r#"{ "t": 0, "position": [0, 10, 0], "look_at": [0, 0, 5] }"#;

    let e = err_of(&format!("{{ \"version\": 2, \"keyframes\": [{ok}] }}"));
    assert!(
        matches!(e, PathError::UnsupportedVersion { ref found } if found == "2"),
        "{e}"
    );
    assert!(e.to_string().contains("version 2"), "{e}");
    let e = err_of(&format!("{{ \"version\": \"1\", \"keyframes\": [{ok}] }}"));
    assert!(matches!(e, PathError::UnsupportedVersion { .. }), "{e}");
    let e = err_of(&format!("{{ \"keyframes\": [{ok}] }}"));
    assert!(matches!(e, PathError::MissingVersion), "{e}");
    let e = err_of(&format!("{{ \"version\": 1, \"frames\": [{ok}], \"keyframes\": [] }}"));
    assert!(matches!(e, PathError::UnknownKey(ref k) if k == "frames"), "{e}");
    let e = err_of("{ \"version\": 1, \"keyframes\": [] }");
    assert!(matches!(e, PathError::Empty), "{e}");
    let e = err_of("{ \"version\": 1 }");
    assert!(matches!(e, PathError::Json(_)), "{e}");
    assert!(e.to_string().contains("keyframes"), "{e}");
    let e = err_of("[1, 2]");
    assert!(matches!(e, PathError::Json(_)), "{e}");
    let e = err_of("{ \"version\": 1, ");
    assert!(matches!(e, PathError::Json(_)), "{e}");

    // Too large for an f32: infinite after conversion.
    for (keyframe, field) in [
        (
            r#"{ "t": 1, "position": [1e39, 10, 0], "look_at": [0, 0, 5] }"#,
            "position",
        ),
        (
            r#"{ "t": 1, "position": [1, 10, 0], "look_at": [0, -1e39, 5] }"#,
            "look_at",
        ),
    ] {
        let e = err_of(&doc(&format!("{ok}, {keyframe}")));
        assert!(
            matches!(e, PathError::NonFinite { index: 1, field: f } if f == field),
            "{field}: {e}"
        );
        assert!(e.to_string().contains("keyframe 1"), "{field}: {e}");
    }
    // Out of f64 range: rejected by the JSON parser with a line and column.
    let e = err_of(&doc(r#"{ "t": 1e400, "position": [0, 10, 0], "look_at": [0, 0, 5] }"#));
    assert!(e.to_string().contains("line"), "{e}");

    let e = err_of(&doc(r#"{ "t": -1, "position": [0, 10, 0], "look_at": [0, 0, 5] }"#));
    assert!(
        matches!(
            e,
            PathError::Negative {
                index: 0,
                field: "t",
                ..
            }
        ),
        "{e}"
    );
    let e = err_of(&doc(&format!(
        r#"{ok}, {{ "t": 1, "position": [0, 10, 0], "look_at": [0, 0, 5], "hold_s": -2 }}"#
    )));
    assert!(
        matches!(
            e,
            PathError::Negative {
                index: 1,
                field: "hold_s",
                ..
            }
        ),
        "{e}"
    );

    let e = err_of(&doc(&format!(
        r#"{ok}, {{ "t": 2, "position": [0, 10, 0], "look_at": [0, 0, 5] }},
           {{ "t": 1.5, "position": [0, 10, 0], "look_at": [0, 0, 5] }}"#
    )));
    assert!(matches!(e, PathError::NotIncreasing { index: 2, .. }), "{e}");
    assert!(e.to_string().contains("keyframe 2"), "{e}");
    // A path that would take longer than a day to replay.
    let e = err_of(&doc(&format!(
        r#"{ok}, {{ "t": 1e300, "position": [0, 10, 0], "look_at": [0, 0, 5] }}"#
    )));
    assert!(matches!(e, PathError::TooLong { index: 1, .. }), "{e}");
    let e = err_of(&doc(&format!(
        r#"{ok}, {{ "t": 86000, "position": [0, 10, 0], "look_at": [0, 0, 5], "hold_s": 1000 }}"#
    )));
    assert!(matches!(e, PathError::TooLong { index: 1, .. }), "{e}");
    // Equal times are only allowed for a jump.
    let e = err_of(&doc(&format!(
        r#"{ok}, {{ "t": 0, "position": [0, 10, 1], "look_at": [0, 0, 5] }}"#
    )));
    assert!(matches!(e, PathError::NotIncreasing { index: 1, .. }), "{e}");
    // A jump may not happen during the previous keyframe's pause.
    let e = err_of(&doc(
        r#"{ "t": 0, "position": [0, 10, 0], "look_at": [0, 0, 5], "hold_s": 3 },
           { "t": 2, "position": [9, 10, 0], "look_at": [9, 0, 5], "jump": true }"#,
    ));
    assert!(
        matches!(e, PathError::NotIncreasing { index: 1, previous_end, .. } if previous_end == 3.0),
        "{e}"
    );

    let e = err_of(&doc(
        r#"{ "t": 0, "position": [0, 10, 0], "look_at": [0, 0, 5], "jump": true }"#,
    ));
    assert!(matches!(e, PathError::FirstKeyframeJump), "{e}");
    let e = err_of(&doc(&format!(
        r#"{ok}, {{ "t": 1, "position": [3, 4, 5], "look_at": [3, 4, 5] }}"#
    )));
    assert!(matches!(e, PathError::DegenerateView { index: 1 }), "{e}");
    // A misspelt key is an error, not a silently missing pause.
    let e = err_of(&doc(&format!(
        r#"{ok}, {{ "t": 1, "position": [0, 10, 0], "look_at": [0, 0, 5], "hold": 2 }}"#
    )));
    assert!(matches!(e, PathError::KeyframeJson { index: 1, .. }), "{e}");
    assert!(e.to_string().contains("hold"), "{e}");
    let e = err_of(&doc(&format!(
        r#"{ok}, {{ "t": 1, "position": [0, 10], "look_at": [0, 0, 5] }}"#
    )));
    assert!(matches!(e, PathError::KeyframeJson { index: 1, .. }), "{e}");

    let missing = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("no-such-path.json");
    let e = CameraPath::load(&missing).expect_err("missing file");
    assert!(matches!(e, PathError::Io { .. }), "{e}");
    assert!(e.to_string().contains("no-such-path.json"), "{e}");
}

#[test]
fn save_replaces_a_file_whole_and_leaves_no_temporary_files() {
    let dir = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("camera-path-save");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("temp dir");
    let file = dir.join("flight.json");
    std::fs::write(&file, "an older file the user keeps").expect("write");
    let path = sample_path();
    path.save(&file).expect("save over an existing file");
    assert_eq!(CameraPath::load(&file).expect("load"), path);
    let names: Vec<String> = std::fs::read_dir(&dir)
        .expect("list")
        .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names, ["flight.json"], "only the saved file remains");

    // A failed replacement (the name is a directory) keeps what was there and leaves no
    // half-written file behind.
    let blocked = dir.join("a_directory.json");
    std::fs::create_dir(&blocked).expect("dir");
    std::fs::write(blocked.join("inside"), "kept").expect("write");
    let e = path.save(&blocked).expect_err("cannot replace a directory");
    assert!(e.to_string().contains("a_directory.json"), "{e}");
    assert_eq!(std::fs::read_to_string(blocked.join("inside")).expect("read"), "kept");
    let mut names: Vec<String> = std::fs::read_dir(&dir)
        .expect("list")
        .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(names, ["a_directory.json", "flight.json"]);
}

#[test]
fn load_errors_name_the_file() {
    let dir = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("camera-path");
    std::fs::create_dir_all(&dir).expect("temp dir");
    let file = dir.join("bad_version.json");
    std::fs::write(&file, "{ \"version\": 7, \"keyframes\": [] }").expect("write");
    let e = CameraPath::load(&file).expect_err("bad version");
    let text = e.to_string();
    assert!(
        text.contains("bad_version.json") && text.contains("version 7"),
        "{text}"
    );
}

#[test]
fn sampling_is_continuous_except_at_jumps() {
    let path = sample_path();
    let dt = 1.0 / 120.0;
    let bound = step_bound(&path, dt);
    let jumps = path.jumps();
    let steps = (path.duration_s() / dt).ceil() as usize;
    let mut previous = path.sample_between(None, 0.0);
    let mut crossings = 0;
    for i in 1..=steps {
        let t = i as f64 * dt;
        let pose = path.sample_between(Some((i - 1) as f64 * dt), t);
        assert!(finite(pose.position) && finite(pose.look_at), "t = {t}");
        assert_ne!(pose.position, pose.look_at, "t = {t}");
        let step = max_axis_step(&previous, &pose);
        let crosses_jump = jumps.iter().any(|&j| j > (i - 1) as f64 * dt && j <= t);
        assert_eq!(pose.jumped, crosses_jump, "t = {t}");
        if crosses_jump {
            crossings += 1;
            assert!(step > 100.0 * bound, "the jump at t = {t} moved only {step} m");
        } else {
            assert!(step <= bound, "t = {t}: moved {step} m in {dt} s (bound {bound})");
        }
        previous = pose;
    }
    assert_eq!(crossings, jumps.len());
}

#[test]
fn motion_is_smooth_through_a_keyframe_without_pause() {
    let path = sample_path();
    // Keyframe 4 (t = 12) lies inside a run and has no pause: velocity is continuous there.
    let h = 1e-4;
    let v = |t0: f64, t1: f64| {
        let (a, b) = (path.sample_between(None, t0), path.sample_between(None, t1));
        [0, 1, 2].map(|i| (f64::from(b.position[i]) - f64::from(a.position[i])) / (t1 - t0))
    };
    let before = v(12.0 - 2.0 * h, 12.0 - h);
    let after = v(12.0 + h, 12.0 + 2.0 * h);
    let speed = before.iter().map(|x| x * x).sum::<f64>().sqrt();
    assert!(
        speed > 1.0,
        "the camera should be moving through keyframe 4, speed {speed}"
    );
    for a in 0..3 {
        assert!(
            (before[a] - after[a]).abs() < 0.05 * speed + 0.05,
            "axis {a}: {before:?} vs {after:?}"
        );
    }
}

#[test]
fn pauses_hold_the_camera_still() {
    let path = sample_path();
    let k = path.keyframes()[1];
    for t in [k.t, k.t + 0.5, k.t + 1.999, k.t + 2.0] {
        let pose = path.sample_between(None, t);
        assert_eq!(pose.position, k.position, "t = {t}");
        assert_eq!(pose.look_at, k.look_at, "t = {t}");
        assert_eq!(pose.in_pause, t < k.t + 2.0, "t = {t}");
    }
    for t in [k.t - 0.01, k.t + 2.01, 0.0, path.duration_s()] {
        assert!(!path.sample_between(None, t).in_pause, "t = {t}");
    }
    let moving = path.sample_between(None, k.t - 0.5);
    assert_ne!(moving.position, k.position);
}

#[test]
fn jumped_is_reported_once_on_the_first_sample_after_a_jump() {
    let path = sample_path();
    let jump = path.jumps()[0];
    let dt = 1.0 / 30.0;
    let mut flagged = Vec::new();
    for i in 0..=((path.duration_s() / dt) as usize) {
        let t = i as f64 * dt;
        if path.sample(t).jumped {
            flagged.push(t);
        }
    }
    assert_eq!(flagged.len(), 1, "{flagged:?}");
    assert!(
        flagged[0] >= jump && flagged[0] - dt < jump,
        "{flagged:?} vs jump at {jump}"
    );

    // The first call after a restart reports no jump; sampling the same time again neither.
    path.restart();
    assert!(!path.sample(jump).jumped);
    assert!(!path.sample(jump).jumped);
    // Going back across the jump is a discontinuity too.
    assert!(path.sample(jump - 1.0).jumped);
    assert!(!path.sample(jump - 0.5).jumped);
    assert!(path.sample(jump).jumped);
}

#[test]
fn out_of_range_times_clamp_to_the_ends() {
    let path = sample_path();
    let first = path.keyframes()[0];
    let last = *path.keyframes().last().expect("keyframes");
    for t in [-5.0, f64::NEG_INFINITY, f64::NAN] {
        let pose = path.sample_between(None, t);
        assert_eq!(
            (pose.position, pose.look_at),
            (first.position, first.look_at),
            "t = {t}"
        );
    }
    for t in [path.duration_s(), 1e9, f64::INFINITY] {
        let pose = path.sample_between(None, t);
        assert_eq!((pose.position, pose.look_at), (last.position, last.look_at), "t = {t}");
    }
}

#[test]
fn samples_stay_in_the_box_of_the_keyframes() {
    // Sharp turns make unclamped Catmull-Rom curves overshoot.
    let path = CameraPath::new(vec![
        Keyframe::new(0.0, [0.0, 10.0, 0.0], [0.0, 0.0, 1.0]),
        Keyframe::new(1.0, [100.0, 10.0, 0.0], [100.0, 0.0, 1.0]),
        Keyframe::new(1.5, [100.0, 10.0, 100.0], [100.0, 0.0, 101.0]),
        Keyframe::new(6.0, [0.0, 10.0, 100.0], [0.0, 0.0, 101.0]),
        Keyframe::new(6.2, [0.0, 30.0, 0.0], [0.0, 20.0, 1.0]),
    ])
    .expect("valid");
    for i in 0..=620 {
        let pose = path.sample_between(None, i as f64 * 0.01);
        for a in 0..3 {
            let (lo, hi) = [(0.0, 100.0), (10.0, 30.0), (0.0, 100.0)][a];
            assert!(
                (lo..=hi).contains(&pose.position[a]),
                "t = {}: {:?}",
                i as f64 * 0.01,
                pose
            );
        }
    }
}

/// Appends an axis-aligned box as one mesh.
fn push_box(scene: &mut Scene, min: [f32; 3], max: [f32; 3]) {
    let corners: Vec<[f32; 3]> = (0..8)
        .map(|c| {
            [
                if c & 1 == 0 { min[0] } else { max[0] },
                if c & 2 == 0 { min[1] } else { max[1] },
                if c & 4 == 0 { min[2] } else { max[2] },
            ]
        })
        .collect();
    let indices = [
        0, 1, 3, 0, 3, 2, 4, 6, 7, 4, 7, 5, 0, 4, 5, 0, 5, 1, 2, 3, 7, 2, 7, 6, 0, 2, 6, 0, 6, 4, 1, 5, 7, 1, 7, 3,
    ];
    let texture = scene.meshes.len() as u32;
    scene
        .push_mesh(texture, &corners, &[[0.0, 1.0, 0.0]; 8], &[[0.0, 0.0]; 8], &indices)
        .expect("push box");
}

/// A 500 m × 500 m city offset by `offset`: a 10 × 10 block of towers at x, z ∈ [20, 80] and
/// a dozen scattered houses, on a ground slab.
fn synthetic_city(origin: [f64; 3], offset: [f32; 3]) -> Scene {
    let at = |p: [f32; 3]| [p[0] + offset[0], p[1] + offset[1], p[2] + offset[2]];
    let mut scene = Scene::new(origin);
    push_box(&mut scene, at([0.0, -1.0, 0.0]), at([500.0, 0.0, 500.0]));
    for i in 0..10 {
        for j in 0..10 {
            let (x, z) = (20.0 + 6.0 * i as f32, 20.0 + 6.0 * j as f32);
            let h = 10.0 + ((i * 7 + j * 3) % 5) as f32 * 5.0;
            push_box(&mut scene, at([x, 0.0, z]), at([x + 4.0, h, z + 4.0]));
        }
    }
    for k in 0..12 {
        let x = 150.0 + 29.0 * k as f32;
        let z = 480.0 - 37.0 * k as f32;
        push_box(&mut scene, at([x, 0.0, z]), at([x + 8.0, 6.0, z + 8.0]));
    }
    scene
}

/// Checks the standard path's contract on `scene` and returns it.
fn check_standard_path(scene: &Scene, duration_s: f64) -> CameraPath {
    let path = standard_path(scene, duration_s).expect("standard path");
    assert!(
        (path.duration_s() - duration_s).abs() <= 0.05 * duration_s,
        "duration {} for {duration_s}",
        path.duration_s()
    );
    let pauses = path.pauses();
    assert_eq!(pauses.len(), STANDARD_PAUSES);
    assert!(pauses.iter().all(|p| p.duration_s == STANDARD_PAUSE_S), "{pauses:?}");
    let jumps = path.jumps();
    assert_eq!(jumps.len(), STANDARD_JUMPS);
    assert!(jumps.iter().all(|&j| j > 0.0 && j < path.duration_s()), "{jumps:?}");

    let bounds: Aabb = scene.bounds;
    let tolerance = 1e-4 * (1.0 + bounds.min.iter().chain(&bounds.max).fold(0.0f32, |a, v| a.max(v.abs())));
    let dt = 0.02;
    let bound = step_bound(&path, dt);
    let mut previous: Option<(f64, CameraPose)> = None;
    for i in 0..=((path.duration_s() / dt).ceil() as usize) {
        let t = i as f64 * dt;
        let pose = path.sample_between(previous.map(|p| p.0), t);
        assert!(finite(pose.position) && finite(pose.look_at), "t = {t}: {pose:?}");
        assert_ne!(pose.position, pose.look_at, "t = {t}");
        assert!(
            pose.position[1] > bounds.max[1],
            "t = {t}: eye {:?} not above the roofs {:?}",
            pose.position,
            bounds
        );
        assert!(
            bounds.contains(pose.look_at, tolerance),
            "t = {t}: look_at {:?} outside {bounds:?}",
            pose.look_at
        );
        // Looking down: a bird's-eye view.
        assert!(unit_dir(&pose)[1] < -0.3, "t = {t}: {pose:?}");
        if let Some((_, before)) = previous {
            if !pose.jumped {
                let step = max_axis_step(&before, &pose);
                assert!(step <= bound, "t = {t}: moved {step} m (bound {bound})");
            }
        }
        previous = Some((t, pose));
    }
    // Every jump lands on a new view.
    for &j in &jumps {
        let before = path.sample_between(None, j - 1e-6);
        let after = path.sample_between(Some(j - 1e-6), j);
        assert!(after.jumped);
        let turn = angle_deg(unit_dir(&before), unit_dir(&after));
        assert!(turn > 30.0, "jump at {j} s turns the view by only {turn}°");
    }
    // Pauses hold still.
    for p in &pauses {
        let start = path.sample_between(None, p.start_s);
        let end = path.sample_between(None, p.start_s + p.duration_s);
        assert!(start.in_pause && path.sample_between(None, p.start_s + 1.0).in_pause);
        assert_eq!((start.position, start.look_at), (end.position, end.look_at));
    }
    // Outside the pauses the camera keeps moving: no unmarked stops.
    let step = 0.1;
    for i in 0..((path.duration_s() / step) as usize) {
        let (t0, t1) = (i as f64 * step, (i as f64 + 1.0) * step);
        if t1 > path.duration_s() || pauses.iter().any(|p| p.start_s < t1 && p.start_s + p.duration_s > t0) {
            continue;
        }
        let (a, b) = (path.sample_between(None, t0), path.sample_between(None, t1));
        assert_ne!(a.position, b.position, "the camera stands still from {t0} s to {t1} s");
    }
    path
}

#[test]
fn standard_path_flies_over_dense_and_sparse_areas() {
    let scene = synthetic_city([0.0; 3], [0.0; 3]);
    let path = check_standard_path(&scene, 60.0);
    check_standard_path(&scene, 45.0);
    check_standard_path(&scene, MIN_STANDARD_DURATION_S);

    // The first pause looks at the block of towers, where meshes are densest.
    let pause = path.sample_between(None, path.pauses()[0].start_s);
    let (x, z) = (pause.look_at[0], pause.look_at[2]);
    assert!((20.0..=84.0).contains(&x) && (20.0..=84.0).contains(&z), "{pause:?}");
    // The path starts over a sparse area, away from the block.
    let start = path.sample_between(None, 0.0);
    assert!(start.look_at[0] > 100.0 || start.look_at[2] > 100.0, "{start:?}");

    // Deterministic, and the file round-trips.
    assert_eq!(standard_path(&scene, 60.0).expect("again"), path);
    let back = CameraPath::from_json(&path.to_json().expect("json")).expect("parse");
    assert_eq!(back, path);
}

#[test]
fn standard_path_works_for_a_single_one_metre_box() {
    let mut scene = Scene::new([0.0; 3]);
    push_box(&mut scene, [0.0; 3], [1.0; 3]);
    check_standard_path(&scene, 60.0);
}

#[test]
fn standard_path_works_far_from_the_origin() {
    // A large world origin, and scene-local coordinates far from zero as well.
    let scene = synthetic_city([3.9e6, 35.0, 5.8e6], [-2.0e5, 120.0, 1.5e5]);
    let path = check_standard_path(&scene, 60.0);
    let pause = path.sample_between(None, path.pauses()[0].start_s);
    let (x, z) = (pause.look_at[0] + 2.0e5, pause.look_at[2] - 1.5e5);
    assert!((20.0..=84.0).contains(&x) && (20.0..=84.0).contains(&z), "{pause:?}");
}

#[test]
fn standard_path_rejects_bad_requests() {
    let scene = synthetic_city([0.0; 3], [0.0; 3]);
    for d in [
        MIN_STANDARD_DURATION_S - 0.1,
        0.0,
        -60.0,
        f64::NAN,
        f64::INFINITY,
        1e300,
        86_401.0,
    ] {
        let e = standard_path(&scene, d).expect_err("bad duration");
        assert!(matches!(e, PathError::InvalidDuration { .. }), "{d}: {e}");
    }
    let e = standard_path(&Scene::new([0.0; 3]), 60.0).expect_err("empty scene");
    assert!(matches!(e, PathError::EmptyScene), "{e}");
}

#[test]
fn camera_path_can_be_shared_between_threads() {
    fn assert_send_sync<T: Send + Sync>() {}
    assert_send_sync::<CameraPath>();
}
