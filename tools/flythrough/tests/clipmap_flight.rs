//! `flythrough --ground`: a simulated survey cut over a generated city is draped under it
//! as its patches arrive, and decoded as they arrive within the memory budget.

mod flight_support;

use std::path::{Path, PathBuf};

use citystream_gen::patches::PatchSet;
use citystream_testing::tool_tests::{gradient_in, patches_args};
use flight_support::{citystream, fresh_dir, stderr, tiny_city};

/// A tiny generated city and a survey over it, cut from a gradient image with `seed`
/// (`citystream patches`), in `name`'s own directory: the directory, the city and the
/// patches.
fn city_and_survey(name: &str, seed: &str) -> (PathBuf, PathBuf, PathBuf) {
    let dir = fresh_dir("clipmap_patches", name);
    let city = tiny_city(&dir);
    let patches = dir.join("patches");
    citystream(&patches_args(&city, &gradient_in(&dir), &patches, seed)).expect("patches");
    (dir, city, patches)
}

#[test]
fn clipmap_flythrough_drapes_arriving_patches_under_the_city() {
    let (dir, city, patches) = city_and_survey("flythrough", "3");
    let set = PatchSet::open(&patches).expect("set");
    let fly = |frames: &str, extra: &[&str], out: &Path| {
        // Two frames in flight by default: synchronization validation too.
        std::process::Command::new(env!("CARGO_BIN_EXE_flythrough"))
            .env("CITYSTREAM_VALIDATION", "sync")
            .arg("--dataset")
            .arg(&city)
            .args([
                "--clock", "fixed", "--frames", frames, "--width", "160", "--height", "96",
            ])
            .args(["--psnr-interval", "60", "--frame-interval", "0", "--validation=true"])
            .args(extra)
            .arg("--out")
            .arg(out)
            .output()
            .expect("flythrough runs")
    };
    let out = dir.join("flight");
    let run = fly("600", &["--ground", patches.to_str().expect("utf-8")], &out);
    assert!(run.status.success(), "{}", stderr(&run));
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).expect("summary")).expect("JSON");
    assert_eq!(summary["validation_errors"], 0, "{summary}");
    // 600 frames at 60 per camera second: the patches arriving within 10 s are inserted.
    let arrived = set.patches.iter().filter(|p| p.arrival_s <= 599.0 / 60.0).count();
    assert_eq!(summary["ground"]["patches_arrived"], arrived as u64, "{summary}");
    let tiles = summary["ground_tiles_uploaded"]
        .as_u64()
        .expect("ground_tiles_uploaded");
    assert!(tiles > 0, "{summary}");
    // The window follows the view: 96 px tall at 60° is an 83 px focal length, one tile of
    // 256 texels beyond the viewer's own each way.
    assert_eq!(summary["ground"]["cache_side"], 3, "{summary}");
    assert!(
        summary["ground"]["level_slots"].as_u64().is_some_and(|s| s >= 1),
        "{summary}"
    );
    let mb = summary["ground_mb_streamed"].as_f64().expect("ground_mb_streamed");
    let tile_mb = (256.0 * 256.0 * 4.0) / f64::from(1 << 20);
    assert!((mb - tiles as f64 * tile_mb).abs() < 1e-9, "{mb} MB for {tiles} tiles");
    // Against the reference with every arrived patch resident, measured every 60 frames.
    let psnr = &summary["ground_psnr_db"];
    for key in ["median", "mean", "max", "min"] {
        assert!(psnr[key].as_f64().is_some_and(|p| p > 0.0), "{key}: {summary}");
    }
    // The facades' error is measured on the same streamed ground: their streaming still
    // reaches the reference once the view settles.
    assert!(
        summary["psnr_db"]["max"].as_f64().is_some_and(|p| p > 30.0),
        "{summary}"
    );

    // Without --ground the keys are null and nothing else changes shape.
    let plain = dir.join("plain");
    let run = fly("30", &[], &plain);
    assert!(run.status.success(), "{}", stderr(&run));
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(plain.join("summary.json")).expect("summary")).expect("JSON");
    assert!(summary["ground_tiles_uploaded"].is_null() && summary["ground_psnr_db"].is_null());

    // A budget half of which holds not one level of the ground, and a directory that is no
    // patch set.
    let run = fly(
        "30",
        &["--ground", patches.to_str().expect("utf-8"), "--memory-budget-mb", "8"],
        &dir.join("small"),
    );
    assert!(!run.status.success());
    let text = stderr(&run);
    assert!(
        text.contains("half the 8 MB memory budget") && text.contains("not one level"),
        "{text}"
    );
    let run = fly(
        "30",
        &["--ground", city.to_str().expect("utf-8")],
        &dir.join("not-a-set"),
    );
    assert!(!run.status.success());
    assert!(stderr(&run).contains("patches.json"), "{}", stderr(&run));

    // A set in another CRS, or cut for a city in a local frame, is refused: its corners
    // would land somewhere else.
    let json = std::fs::read_to_string(patches.join("patches.json")).expect("json");
    let mut value: serde_json::Value = serde_json::from_str(&json).expect("json");
    let elsewhere = dir.join("elsewhere");
    std::fs::create_dir_all(&elsewhere).expect("dir");
    for p in &set.patches {
        std::fs::copy(patches.join(&p.file), elsewhere.join(&p.file)).expect("copy patch");
    }
    for (crs, version, expected) in [
        (serde_json::json!("EPSG:32633"), 2, "georeferenced in EPSG:32633"),
        (serde_json::Value::Null, 1, "cut for a dataset in a local frame"),
    ] {
        value["crs"] = crs;
        value["version"] = serde_json::json!(version);
        std::fs::write(elsewhere.join("patches.json"), value.to_string()).expect("write");
        let run = fly(
            "30",
            &["--ground", elsewhere.to_str().expect("utf-8")],
            &dir.join("elsewhere-out"),
        );
        assert!(!run.status.success());
        let text = stderr(&run);
        assert!(text.contains(expected) && text.contains("EPSG:25833"), "{text}");
    }
}

#[test]
fn clipmap_patches_are_decoded_as_they_arrive_within_the_memory_budget() {
    let (dir, city, patches) = city_and_survey("memory", "5");
    let json = std::fs::read_to_string(patches.join("patches.json")).expect("json");
    let value: serde_json::Value = serde_json::from_str(&json).expect("json");
    let fly = |set: &Path, name: &str| {
        std::process::Command::new(env!("CARGO_BIN_EXE_flythrough"))
            .arg("--dataset")
            .arg(&city)
            .args(["--clock", "fixed", "--frames", "30", "--width", "160", "--height", "96"])
            .args([
                "--psnr-interval",
                "0",
                "--frame-interval",
                "0",
                "--memory-budget-mb",
                "64",
            ])
            .arg("--ground")
            .arg(set)
            .arg("--out")
            .arg(dir.join(name))
            .output()
            .expect("flythrough runs")
    };
    // One image listed 5,000 times is decoded once (it took 5,000 decodes before the flight).
    let many = dir.join("one-image-many-times");
    std::fs::create_dir_all(&many).expect("dir");
    let mut set = value.clone();
    let records = set["patches"].as_array().expect("patches").clone();
    for record in &records[..2] {
        let file = record["file"].as_str().expect("file");
        std::fs::copy(patches.join(file), many.join(file)).expect("copy");
    }
    let mut listed = vec![records[0].clone()];
    listed.extend((0..5000).map(|i| {
        let mut record = records[1].clone();
        record["id"] = serde_json::json!(i + 1);
        record
    }));
    set["patches"] = serde_json::Value::Array(listed);
    std::fs::write(many.join("patches.json"), set.to_string()).expect("write");
    let run = fly(&many, "many");
    assert!(run.status.success(), "{}", stderr(&run));
    assert!(
        stderr(&run).contains("5001 patches from") && stderr(&run).contains("(2 image files,"),
        "{}",
        stderr(&run)
    );

    // Twenty distinct 1024² images decode to 107 MB: more than the 64 MB budget holds.
    let big = dir.join("big-images");
    std::fs::create_dir_all(&big).expect("dir");
    let mut set = value;
    let listed: Vec<serde_json::Value> = (0..20)
        .map(|i| {
            let file = format!("big_{i:02}.png");
            image::RgbaImage::from_fn(1024, 1024, |x, y| {
                image::Rgba([(x % 256) as u8, (y % 256) as u8, i, 255])
            })
            .save(big.join(&file))
            .expect("write image");
            let mut record = records[i as usize % records.len()].clone();
            record["id"] = serde_json::json!(i);
            record["file"] = serde_json::json!(file);
            record["width"] = serde_json::json!(1024);
            record["height"] = serde_json::json!(1024);
            record
        })
        .collect();
    set["patches"] = serde_json::Value::Array(listed);
    std::fs::write(big.join("patches.json"), set.to_string()).expect("write");
    let run = fly(&big, "big");
    assert!(!run.status.success(), "a set beyond the budget was accepted");
    let text = stderr(&run);
    assert!(
        text.contains("20 patches (20 image files) decode to 107 MB") && text.contains("64 MB memory budget"),
        "{text}"
    );
}
