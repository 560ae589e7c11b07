//! The flythrough binary end to end on lavapipe: frames and report written,
//! no validation errors, bad arguments refused with a clear message.

use std::process::Command;

#[test]
fn flythrough_writes_frames_and_report() {
    let out = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("flythrough_cli");
    let _ = std::fs::remove_dir_all(&out);
    let status = Command::new(env!("CARGO_BIN_EXE_flythrough"))
        .args(["--frames", "4", "--frame-interval", "2", "--width", "96", "--height", "64", "--blocks", "3"])
        .arg("--validation=true")
        .arg("--out")
        .arg(&out)
        .status()
        .expect("flythrough runs");
    assert!(status.success(), "flythrough failed: {status}");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).expect("report.json written"))
            .expect("report.json is JSON");
    assert_eq!(report["frames"], 4);
    assert_eq!(report["validation_errors"], 0);
    assert!(report["frame_ms"]["max"].as_f64().is_some_and(|v| v > 0.0));
    for frame in ["frame_00000.png", "frame_00002.png"] {
        let image = image::open(out.join("frames").join(frame)).expect("frame PNG readable");
        assert_eq!((image.width(), image.height()), (96, 64));
        // A real render has more than one colour (sky, ground, facades).
        let rgba = image.to_rgba8();
        let first = rgba.get_pixel(0, 0);
        assert!(rgba.pixels().any(|p| p != first), "{frame} is a flat image");
    }
}

#[test]
fn bad_arguments_are_refused_clearly() {
    let output = Command::new(env!("CARGO_BIN_EXE_flythrough"))
        .args(["--width", "0"])
        .output()
        .expect("flythrough runs");
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("--width"), "error does not name the option: {stderr}");
}
