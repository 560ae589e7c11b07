//! End-to-end checks of `citystream path` on the tiny city.

use std::path::PathBuf;

use citystream_dataset::Dataset;
use citystream_streaming::bench::path::{standard_path, CameraPath, STANDARD_JUMPS, STANDARD_PAUSES};

mod cli_support;
use cli_support::citystream;

fn fresh_dir(name: &str) -> PathBuf {
    cli_support::fresh_dir("path-cli", name)
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

#[test]
fn path_writes_the_standard_path_of_a_generated_city() {
    let root = fresh_dir("tiny");
    let dataset = root.join("city");
    let dataset_str = dataset.to_str().expect("utf-8 temp path");
    let out = citystream(&["gen", "--preset", "tiny", "--quiet", "--out", dataset_str]);
    assert!(out.status.success(), "gen failed: {}", text(&out.stderr));

    let file = root.join("standard.json");
    let file_str = file.to_str().expect("utf-8 temp path");
    let out = citystream(&["path", "--dataset", dataset_str, "--out", file_str, "--duration", "45"]);
    assert!(out.status.success(), "path failed: {}", text(&out.stderr));
    let stdout = text(&out.stdout);
    assert!(stdout.contains("duration 45.00 s"), "{stdout}");
    assert!(stdout.contains(&format!("{STANDARD_PAUSES} pauses")), "{stdout}");
    assert!(stdout.contains(&format!("{STANDARD_JUMPS} jumps")), "{stdout}");

    // The file is the library's standard path for the dataset's scene.
    let written = CameraPath::load(&file).expect("load the written path");
    let scene = Dataset::open(&dataset).expect("open dataset").scene;
    assert_eq!(written, standard_path(&scene, 45.0).expect("standard path"));
    assert!(
        stdout.contains(&format!("{} keyframes", written.keyframes().len())),
        "{stdout}"
    );

    // Default duration: a minute.
    let out = citystream(&["path", "--dataset", dataset_str, "--out", file_str]);
    assert!(out.status.success(), "path failed: {}", text(&out.stderr));
    assert_eq!(CameraPath::load(&file).expect("load").duration_s().round(), 60.0);
}

#[test]
fn path_rejects_bad_arguments_clearly() {
    let root = fresh_dir("bad");
    let out_file = root.join("p.json");
    let out_str = out_file.to_str().expect("utf-8");

    let missing = root.join("no-dataset");
    let out = citystream(&["path", "--dataset", missing.to_str().expect("utf-8"), "--out", out_str]);
    assert!(!out.status.success());
    let stderr = text(&out.stderr);
    assert!(
        stderr.contains("no-dataset") && stderr.contains("dataset.manifest") && stderr.contains("missing"),
        "{stderr}"
    );
    assert!(!out_file.exists());

    let out = citystream(&["path", "--out", out_str]);
    assert!(!out.status.success());
    assert!(text(&out.stderr).contains("--dataset"), "{}", text(&out.stderr));

    let dataset = root.join("city");
    let dataset_str = dataset.to_str().expect("utf-8");
    let gen = citystream(&["gen", "--preset", "tiny", "--quiet", "--out", dataset_str]);
    assert!(gen.status.success(), "gen failed: {}", text(&gen.stderr));
    for duration in ["5", "nan", "-60"] {
        let out = citystream(&[
            "path",
            "--dataset",
            dataset_str,
            "--out",
            out_str,
            &format!("--duration={duration}"),
        ]);
        assert!(!out.status.success(), "--duration {duration} accepted");
        let stderr = text(&out.stderr);
        assert!(stderr.contains("duration"), "--duration {duration}: {stderr}");
    }
    let out = citystream(&["path", "--dataset", dataset_str, "--out", out_str, "--duration", "abc"]);
    assert!(!out.status.success());
    assert!(text(&out.stderr).contains("--duration"), "{}", text(&out.stderr));
    assert!(!out_file.exists());

    // An unwritable output names the file.
    let unwritable = root.join("no-such-dir").join("p.json");
    let out = citystream(&[
        "path",
        "--dataset",
        dataset_str,
        "--out",
        unwritable.to_str().expect("utf-8"),
    ]);
    assert!(!out.status.success());
    assert!(text(&out.stderr).contains("no-such-dir"), "{}", text(&out.stderr));
}
