//! `--depth-slabs`: the depth probe placed in the default city. Slabs 0.5 m apart 10 km
//! out resolve on every measured frame (the nearer shows on every pixel inside its outline,
//! the farther on none), the path flown is the one without the probe, and a run that
//! measures no frame is refused before it starts.

mod flight_support;
use flight_support::{column, default_city, fly_flythrough, fresh_dir};

const SIZE: [&str; 4] = ["--width", "320", "--height", "180"];

#[test]
fn slabs_half_a_metre_apart_ten_kilometres_out_resolve_and_leave_the_path_alone() {
    let city = default_city();
    let common = [
        "--frames",
        "61",
        "--clock",
        "fixed",
        "--frame-interval",
        "0",
        "--validation=true",
    ];
    let mut probed = common.to_vec();
    probed.extend(SIZE);
    probed.extend(["--psnr-interval", "30", "--depth-slabs", "10000"]);
    let (output, summary, csv) = fly_flythrough(&probed, &city, &fresh_dir("depth_slabs", "probed"));
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{stderr}");
    assert_eq!(summary["validation_errors"], 0, "{summary}");
    let slabs = &summary["depth_slabs"];
    assert_eq!(slabs["distance_m"], 10_000.0, "{slabs}");
    assert_eq!(slabs["frames_checked"], 3, "{slabs}");
    assert_eq!(slabs["far_pixels"], 0, "{slabs}");
    // A 1 km slab 10 km out spans about 16 pixels of a 180-pixel-high view; less its edges,
    // well over 100 pixels a frame.
    let near = slabs["near_pixels"].as_u64().expect("a count");
    assert!(near > 300, "{slabs}");
    assert!(stderr.contains("depth slabs at 10000 m"), "{stderr}");

    let mut plain = common.to_vec();
    plain.extend(SIZE);
    plain.extend(["--psnr-interval", "30"]);
    let (output, summary, plain_csv) = fly_flythrough(&plain, &city, &fresh_dir("depth_slabs", "plain"));
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    assert!(summary["depth_slabs"].is_null(), "{summary}");
    for axis in ["eye_x", "eye_y", "eye_z", "look_x", "look_y", "look_z"] {
        assert_eq!(column(&csv, axis), column(&plain_csv, axis), "{axis}");
    }
}

#[test]
fn a_probe_no_frame_would_check_is_refused() {
    let out = fresh_dir("depth_slabs", "unchecked");
    let (output, _, _) = fly_flythrough(
        &["--frames", "2", "--psnr-interval", "0", "--depth-slabs", "10000"],
        &default_city(),
        &out,
    );
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success(), "{stderr}");
    assert!(stderr.contains("--psnr-interval 0 measures none"), "{stderr}");
    let (output, _, _) = fly_flythrough(&["--frames", "2", "--depth-slabs", "3"], &default_city(), &out);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        !output.status.success() && stderr.contains("not a distance from 10 m"),
        "{stderr}"
    );
}
