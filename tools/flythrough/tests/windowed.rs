//! `flythrough --window` on lavapipe under Xvfb (a virtual X server each test
//! starts on a free display): presented frames against headless ones (also with the
//! atlas-tree strategy over aerial imagery), a recorded path replayed headless, resizing and minimising, wall-clock
//! replay. Synchronization validation is on; the window exits non-zero on any
//! validation message. Where Xvfb is missing and the setup script (`make setup`)
//! has not run, the tests that need it compile as ignored (`tools/build.rs`), so
//! they are reported as skipped; after it, a missing Xvfb fails them.

mod flight_support;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

use citystream_streaming::bench::path::CameraPath;
use citystream_testing::server_process::KilledOnDrop;
use flight_support::{citystream_ok, fresh_dir, setup_ran, stderr, tiny_city};

/// A running Xvfb, killed on drop.
struct Xvfb {
    _child: KilledOnDrop,
    display: String,
}

/// Starts Xvfb on a display it picks itself (`-displayfd`), so tests running
/// at once never collide.
fn start_xvfb() -> Xvfb {
    let spawned = Command::new("Xvfb")
        // `-noreset`: by default the server resets when its last client leaves, and a
        // test's next flythrough connecting during that reset is refused.
        .args([
            "-displayfd",
            "1",
            "-screen",
            "0",
            "1280x1024x24",
            "-nolisten",
            "tcp",
            "-noreset",
        ])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn();
    let mut child = match spawned {
        Ok(child) => child,
        Err(e) if setup_ran() => {
            panic!("Xvfb cannot run ({e}) although the setup script ran: it should have installed xvfb")
        }
        Err(e) => panic!("Xvfb cannot run ({e}); `make setup` installs it (this build found it: rebuild to skip)"),
    };
    // Xvfb writes the display number once it accepts connections.
    let mut line = String::new();
    let stdout = child.stdout.take().expect("Xvfb stdout");
    BufReader::new(stdout)
        .read_line(&mut line)
        .expect("read Xvfb's display number");
    let number: u32 = line
        .trim()
        .parse()
        .unwrap_or_else(|_| panic!("Xvfb did not report a display number: {line:?}"));
    Xvfb {
        _child: KilledOnDrop(child),
        display: format!(":{number}"),
    }
}

/// A fresh Xvfb, and a tiny city generated in the windowed test `name`'s own directory:
/// the server, the directory and the city.
fn xvfb_and_tiny_city(name: &str) -> (Xvfb, PathBuf, PathBuf) {
    let x = start_xvfb();
    let dir = fresh_dir("windowed", name);
    let city = tiny_city(&dir);
    (x, dir, city)
}

/// Runs the flythrough with `args`, on `display` when given; synchronization
/// validation on either way.
fn flythrough(display: Option<&Xvfb>, args: &[&str], paths: &[(&str, &Path)]) -> Output {
    let mut command = Command::new(env!("CARGO_BIN_EXE_flythrough"));
    command.env("CITYSTREAM_VALIDATION", "sync").args(args);
    for (option, path) in paths {
        command.arg(option).arg(path);
    }
    match display {
        Some(x) => command.env("DISPLAY", &x.display),
        None => command.env_remove("DISPLAY"),
    };
    command.output().expect("run flythrough")
}

fn assert_ok(out: &Output, what: &str) {
    let text = stderr(out);
    assert!(out.status.success(), "{what} failed: {text}");
    assert!(
        !text.contains("[vulkan validation error]"),
        "{what}: validation messages: {text}"
    );
}

fn png(path: &Path) -> image::RgbaImage {
    image::open(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .to_rgba8()
}

/// `frames.csv` rows as (frame, time_s, eye and look-at).
fn poses(csv: &Path) -> Vec<(u32, f64, [f64; 6])> {
    let text = std::fs::read_to_string(csv).unwrap_or_else(|e| panic!("{}: {e}", csv.display()));
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().expect("header").split(',').collect();
    let column = |name: &str| header.iter().position(|h| *h == name).expect(name);
    let pose_columns = ["eye_x", "eye_y", "eye_z", "look_x", "look_y", "look_z"].map(column);
    let (frame, time) = (column("frame"), column("time_s"));
    lines
        .map(|line| {
            let cells: Vec<&str> = line.split(',').collect();
            let pose = pose_columns.map(|c| cells[c].parse::<f64>().expect("pose number"));
            (
                cells[frame].parse().expect("frame"),
                cells[time].parse().expect("time"),
                pose,
            )
        })
        .collect()
}

fn write_script(dir: &Path, json: &str) -> PathBuf {
    let path = dir.join("script.json");
    std::fs::write(&path, json).expect("write script");
    path
}

/// Flies the first 1.5 s of the standard path of `dataset` in the window (presented, the
/// swapchain image read back at three frames) and headless, both with `extra` options, and
/// checks that the window flew the same poses and presented the headless renders pixel
/// for pixel (the fixed clock streams deterministically; the blit copies UNORM to UNORM).
fn assert_window_presents_the_headless_frames(
    x: &Xvfb,
    dir: &Path,
    dataset: &Path,
    extra: &[(&str, &Path)],
    flags: &[&str],
) {
    let script = write_script(
        dir,
        r#"{"events": [{"frame": 30, "screenshot": true}, {"frame": 60, "screenshot": true},
                       {"frame": 89, "screenshot": true}]}"#,
    );
    let mut common = vec![
        "--clock", "fixed", "--path", "standard", "--frames", "90", "--width", "320", "--height", "180",
    ];
    common.extend(flags);
    let mut paths = vec![("--dataset", dataset)];
    paths.extend(extra);
    let window_out = dir.join("window");
    let mut args = vec!["--window"];
    args.extend(&common);
    let mut window_paths = paths.clone();
    window_paths.extend([("--out", window_out.as_path()), ("--input-script", script.as_path())]);
    let out = flythrough(Some(x), &args, &window_paths);
    assert_ok(&out, "the window");
    assert!(stderr(&out).contains("validation: 0 message(s)"), "{}", stderr(&out));
    let headless_out = dir.join("headless");
    let mut args = vec!["--frame-interval", "1", "--psnr-interval", "0"];
    args.extend(&common);
    let mut headless_paths = paths;
    headless_paths.push(("--out", headless_out.as_path()));
    let out = flythrough(None, &args, &headless_paths);
    assert_ok(&out, "the headless run");

    // Same poses frame by frame ...
    let (window_poses, headless_poses) = (
        poses(&window_out.join("frames.csv")),
        poses(&headless_out.join("frames.csv")),
    );
    assert_eq!(window_poses.len(), 90);
    assert_eq!(window_poses, headless_poses);
    // ... and the presented images are the headless renders, pixel for pixel.
    for frame in [30, 60, 89] {
        let name = format!("frame_{frame:05}.png");
        let presented = png(&window_out.join("frames").join(&name));
        let headless = png(&headless_out.join("frames").join(&name));
        assert_eq!(presented.dimensions(), (320, 180));
        let first = presented.get_pixel(0, 0);
        assert!(presented.pixels().any(|p| p != first), "{name}: a flat image");
        let differing = presented
            .pixels()
            .zip(headless.pixels())
            .filter(|(a, b)| a != b)
            .count();
        assert_eq!(
            differing, 0,
            "{name}: {differing} pixels differ from the headless frame"
        );
    }
}

#[test]
#[cfg_attr(citystream_skip_xvfb, ignore = "Xvfb is not installed and `make setup` has not run")]
fn windowed_frames_are_the_headless_frames_of_the_same_camera_pose() {
    let (x, dir, city) = xvfb_and_tiny_city("frames");
    assert_window_presents_the_headless_frames(&x, &dir, &city, &[], &[]);
}

#[test]
#[cfg_attr(citystream_skip_xvfb, ignore = "Xvfb is not installed and `make setup` has not run")]
fn windowed_atlas_tree_over_aerial_imagery_presents_the_headless_frames() {
    let (x, dir, city) = xvfb_and_tiny_city("tree_ground");
    let tree = dir.join("tree");
    let s = |p: &Path| p.to_str().expect("utf-8 path").to_owned();
    citystream_ok(&[
        "atlas-tree",
        &s(&city),
        "--out",
        &s(&tree),
        "--atlas-extent",
        "256",
        "--quiet",
    ]);
    let image = dir.join("survey.png");
    image::RgbaImage::from_fn(300, 200, |x, y| {
        image::Rgba([(x % 256) as u8, (y % 256) as u8, 128, 255])
    })
    .save(&image)
    .expect("write the survey image");
    let patches = dir.join("patches");
    citystream_ok(&[
        "patches",
        &s(&image),
        "--dataset",
        &s(&tree),
        "--out",
        &s(&patches),
        "--count",
        "6",
        "--max-texels",
        "256",
        "--quiet",
    ]);
    assert_window_presents_the_headless_frames(
        &x,
        &dir,
        &tree,
        &[("--ground", &patches)],
        &["--strategy", "atlas-tree"],
    );
}

#[test]
#[cfg_attr(citystream_skip_xvfb, ignore = "Xvfb is not installed and `make setup` has not run")]
fn windowed_recording_replays_headless_at_the_recorded_poses() {
    let (x, dir, city) = xvfb_and_tiny_city("record");
    // Fly forward while looking around, hold still, jump to the overview,
    // strafe faster; recorded from the first frame.
    let script = write_script(
        &dir,
        r#"{"events": [{"frame": 5, "press": "forward"}, {"frame": 20, "look": [60, 25]},
                       {"frame": 40, "release": "forward"}, {"frame": 60, "press": "overview"},
                       {"frame": 65, "press": "right"}, {"frame": 66, "scroll": 2},
                       {"frame": 80, "release": "right"}]}"#,
    );
    let recorded = dir.join("recorded.json");
    std::fs::write(&recorded, "an older file, replaced whole").expect("write");
    let window_out = dir.join("window");
    let out = flythrough(
        Some(&x),
        &[
            "--window", "--clock", "fixed", "--frames", "90", "--width", "160", "--height", "96",
        ],
        &[
            ("--dataset", &city),
            ("--out", &window_out),
            ("--input-script", &script),
            ("--record", &recorded),
        ],
    );
    assert_ok(&out, "the window");

    let path = CameraPath::load(&recorded).expect("the recording is a valid path file");
    let keyframes = path.keyframes();
    assert!(!keyframes[0].jump);
    let holds: Vec<f64> = keyframes.iter().filter(|k| k.hold_s > 0.0).map(|k| k.t).collect();
    let jumps: Vec<f64> = keyframes.iter().filter(|k| k.jump).map(|k| k.t).collect();
    // Still before the first press and from the release to the jump; one jump, at frame 60.
    assert!(holds.len() >= 2, "holds at {holds:?}");
    assert_eq!(jumps.len(), 1, "jumps at {jumps:?}");
    assert!((jumps[0] - 1.0).abs() < 1e-9, "jump at {} s", jumps[0]);
    let hold_before_jump = keyframes
        .iter()
        .rfind(|k| k.t < jumps[0])
        .expect("a keyframe before the jump");
    assert!(
        hold_before_jump.hold_s > 0.3,
        "held {} s after the release",
        hold_before_jump.hold_s
    );

    let replay_out = dir.join("replay");
    let out = flythrough(
        None,
        &[
            "--clock",
            "fixed",
            "--frames",
            "90",
            "--width",
            "160",
            "--height",
            "96",
            "--psnr-interval",
            "0",
            "--frame-interval",
            "0",
        ],
        &[("--dataset", &city), ("--out", &replay_out), ("--path", &recorded)],
    );
    assert_ok(&out, "the headless replay");
    let flown = poses(&window_out.join("frames.csv"));
    let replayed = poses(&replay_out.join("frames.csv"));
    assert_eq!(flown.len(), 90);
    assert_eq!(replayed.len(), 90);
    let moved = flown.windows(2).filter(|w| w[0].2 != w[1].2).count();
    assert!(moved > 30, "the camera moved in only {moved} frames");
    for ((frame, t, a), (_, u, b)) in flown.iter().zip(&replayed) {
        assert!((t - u).abs() < 1e-9, "frame {frame}: {t} s flown, {u} s replayed");
        let worst = a.iter().zip(b).map(|(p, q)| (p - q).abs()).fold(0.0, f64::max);
        assert!(
            worst < 1e-3,
            "frame {frame}: replayed pose {b:?} is {worst} m from the flown {a:?}"
        );
    }
}

#[test]
#[cfg_attr(citystream_skip_xvfb, ignore = "Xvfb is not installed and `make setup` has not run")]
fn windowed_resize_and_minimise_recreate_the_swapchain_cleanly() {
    let (x, dir, city) = xvfb_and_tiny_city("resize");
    let script = write_script(
        &dir,
        r#"{"events": [{"frame": 5, "screenshot": true}, {"frame": 10, "resize": [240, 136]},
                       {"frame": 15, "screenshot": true}, {"frame": 20, "minimise_s": 0.4},
                       {"frame": 25, "resize": [352, 200]}, {"frame": 26, "minimise_s": 0.2},
                       {"frame": 26, "screenshot": true}, {"frame": 40, "screenshot": true}]}"#,
    );
    let out_dir = dir.join("window");
    let out = flythrough(
        Some(&x),
        &["--window", "--clock", "fixed", "--path", "standard", "--frames", "50"],
        &[("--dataset", &city), ("--out", &out_dir), ("--input-script", &script)],
    );
    assert_ok(&out, "the window");
    assert!(stderr(&out).contains("validation: 0 message(s)"), "{}", stderr(&out));
    // Every frame rendered (none lost to the minimised spells), each presented
    // image at the window's size of its moment.
    assert_eq!(poses(&out_dir.join("frames.csv")).len(), 50);
    // Events after a minimise in the same frame wait for the window to show.
    for (frame, size) in [(5, (640, 360)), (15, (240, 136)), (26, (352, 200)), (40, (352, 200))] {
        let image = png(&out_dir.join("frames").join(format!("frame_{frame:05}.png")));
        assert_eq!(image.dimensions(), size, "frame {frame}");
        let first = image.get_pixel(0, 0);
        assert!(image.pixels().any(|p| p != first), "frame {frame}: a flat image");
    }
}

#[test]
#[cfg_attr(citystream_skip_xvfb, ignore = "Xvfb is not installed and `make setup` has not run")]
fn windowed_replay_follows_the_wall_clock() {
    let (x, dir, city) = xvfb_and_tiny_city("wall_clock");
    let path_file = dir.join("standard.json");
    citystream_ok(&[
        "path",
        "--dataset",
        city.to_str().expect("utf-8"),
        "--out",
        path_file.to_str().expect("utf-8"),
    ]);
    let out_dir = dir.join("window");
    // Hidden for 1.5 s after frame 10: camera time stands still meanwhile.
    let script = write_script(&dir, r#"{"events": [{"frame": 10, "minimise_s": 1.5}]}"#);
    let started = std::time::Instant::now();
    let out = flythrough(
        Some(&x),
        &["--window", "--duration-s", "1.5", "--width", "160", "--height", "96"],
        &[
            ("--dataset", &city),
            ("--out", &out_dir),
            ("--path", &path_file),
            ("--input-script", &script),
        ],
    );
    let wall_s = started.elapsed().as_secs_f64();
    assert_ok(&out, "the window");
    let rows = poses(&out_dir.join("frames.csv"));
    let last = rows.last().expect("frames");
    // Camera time is wall time: the run lasts at least as long as the 1.5 s it
    // shows, and each frame shows the path where it is at that frame's time.
    assert!(last.1 >= 1.4 && last.1 <= 1.5 + 1e-6, "last frame at {} s", last.1);
    assert!(
        wall_s >= last.1 + 1.5,
        "{wall_s} s of wall time for {} s of path",
        last.1
    );
    let largest_step = rows.windows(2).map(|w| w[1].1 - w[0].1).fold(0.0, f64::max);
    assert!(largest_step < 0.9, "camera time jumped {largest_step} s between frames");
    let csv = std::fs::read_to_string(out_dir.join("frames.csv")).expect("frames.csv");
    let worst_latency = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').nth(2).expect("dt_ms").parse::<f64>().expect("number"))
        .fold(0.0, f64::max);
    assert!(
        worst_latency < 900.0,
        "the hidden spell counted as a {worst_latency} ms frame"
    );
    let path = CameraPath::load(&path_file).expect("path");
    for (frame, t, pose) in &rows {
        let expected = path.sample(*t);
        let want = [expected.position, expected.look_at].concat();
        // time_s is written to 0.1 ms; the camera moves a few m/s at most.
        let worst = pose
            .iter()
            .zip(&want)
            .map(|(p, q)| (p - f64::from(*q)).abs())
            .fold(0.0, f64::max);
        assert!(worst < 0.05, "frame {frame} at {t} s: {worst} m off the path");
    }
}

#[test]
fn windowed_vsync_feeds_the_controller_the_frame_or_the_interval_as_asked() {
    let (x, dir, city) = xvfb_and_tiny_city("controller_latency");
    for latency in ["work", "period"] {
        let out_dir = dir.join(latency);
        let out = flythrough(
            Some(&x),
            &[
                "--window",
                "--present-mode",
                "vsync",
                "--frames",
                "40",
                "--width",
                "160",
                "--height",
                "96",
                "--controller",
                "headroom",
                "--controller-latency",
                latency,
            ],
            &[("--dataset", &city), ("--out", &out_dir)],
        );
        assert_ok(&out, latency);
        let csv = std::fs::read_to_string(out_dir.join("frames.csv")).expect("frames.csv");
        let fed: Vec<f64> = csv
            .lines()
            .skip(1)
            .map(|l| l.split(',').nth(2).expect("dt_ms").parse::<f64>().expect("number"))
            .collect();
        assert_eq!(fed.len(), 40, "{latency}");
        assert!(fed.iter().all(|ms| ms.is_finite() && *ms >= 0.0), "{latency}: {fed:?}");
    }
    // Xvfb does not pace lavapipe's FIFO presentation (docs/CONTROLLER.md, "Under vsync"),
    // so the waits left out are too short here to compare the two runs by.
}

#[test]
fn windowed_mode_refuses_bad_input_clearly() {
    let dir = fresh_dir("windowed", "bad_input");
    // Scripts are checked before anything opens, each error naming the event.
    for (script, expected) in [
        (
            r#"{"events": [{"frame": 1, "press": "forward"}, {"frame": 2, "press": "up", "look": [1, 1]}]}"#,
            "event 1",
        ),
        (r#"{"events": [{"frame": 1, "press": "warp"}]}"#, "warp"),
        (r#"{"events": [{"frame": 1, "resize": [0, 100]}]}"#, "resize 0x100"),
        (
            r#"{"events": [{"frame": 1, "screenshot": true, "colour": 1}]}"#,
            "colour",
        ),
        (r#"{"events": [{"frame": 1, "minimise_s": -1}]}"#, "minimise_s"),
        ("[1, 2", "parsing the input script"),
    ] {
        let file = write_script(&dir, script);
        let out = flythrough(
            None,
            &["--window"],
            &[("--input-script", &file), ("--out", &dir.join("out"))],
        );
        assert!(!out.status.success(), "{script} was accepted");
        let text = stderr(&out);
        assert!(
            text.contains(expected) && text.contains("script.json"),
            "{script}: {text}"
        );
        assert!(!text.contains("panicked"), "{text}");
    }
    let out = flythrough(None, &["--window", "--clock", "modelled"], &[]);
    assert!(!out.status.success());
    assert!(stderr(&out).contains("modelled"), "{}", stderr(&out));
    let out = flythrough(None, &["--window", "--present-mode", "sometimes"], &[]);
    assert!(!out.status.success());
    assert!(stderr(&out).contains("--present-mode"), "{}", stderr(&out));

    // Without a display: a clear error, before any dataset is opened or created.
    let out = flythrough(None, &["--window", "--frames", "2"], &[("--out", &dir.join("out"))]);
    assert!(!out.status.success());
    let text = stderr(&out);
    assert!(text.contains("DISPLAY") && text.contains("headless"), "{text}");
    assert!(!text.contains("panicked"), "{text}");
    // Window-only options need --window.
    let out = flythrough(None, &["--record", "x.json"], &[]);
    assert!(!out.status.success());
    assert!(stderr(&out).contains("--window"), "{}", stderr(&out));
}
