//! A 3D Tiles tileset imported (`citystream import`) flies with its error measured.

mod flight_support;
#[path = "../../cli/tests/tileset_support/mod.rs"]
mod tileset_support;

use serde_json::Value;

use flight_support::{citystream_ok, fresh_dir};
use tileset_support::write_tileset;

#[test]
fn the_imported_tileset_flies_with_its_error_measured() {
    let src = fresh_dir("import-tiles", "fly-src");
    let (tileset, _) = write_tileset(&src);
    let dataset = fresh_dir("import-tiles", "fly");
    let (input, out_dir) = (tileset.to_str().expect("utf-8"), dataset.to_str().expect("utf-8"));
    citystream_ok(&["import", input, "--out", out_dir, "--lod", "all"]);
    citystream_ok(&["verify", out_dir]);
    fly_and_check(&dataset, &fresh_dir("import-tiles", "fly-out"), 90, "the tileset");
}

/// Flies `dataset` for `frames` fixed-clock frames (160×90, PSNR every 30 frames, the
/// validation layer on) into `out`: it must exit 0 with every frame run, 0 validation
/// messages, 0 load failures and a PSNR of the mean MSE above 20 dB.
fn fly_and_check(dataset: &std::path::Path, out: &std::path::Path, frames: u32, what: &str) {
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_flythrough"))
        .arg("--dataset")
        .arg(dataset)
        .args(["--frames", &frames.to_string(), "--clock", "fixed"])
        .args(["--psnr-interval", "30", "--frame-interval", "0"])
        .args(["--width", "160", "--height", "90", "--validation=true"])
        .arg("--out")
        .arg(out)
        .status()
        .expect("flythrough runs");
    assert!(status.success(), "{what}: flythrough failed: {status}");
    let summary: Value =
        serde_json::from_slice(&std::fs::read(out.join("summary.json")).expect("summary.json")).expect("JSON");
    assert_eq!(summary["frames"], frames, "{what}");
    assert_eq!(summary["validation_errors"], 0, "{what}");
    assert_eq!(summary["load_failures"], 0, "{what}");
    // Every 30th frame measured against the fully resident reference.
    let psnr = summary["psnr_of_mean_mse_db"].as_f64().expect("PSNR measured");
    assert!(psnr > 20.0, "{what}: PSNR of the mean MSE {psnr} dB");
}

/// The same four buildings in each encoding real tilesets ship (Draco, meshopt with
/// quantization, UASTC and ETC1S KTX2 textures; tools/test-data/encoded-tilesets) import,
/// verify and fly under the validation layer without a message.
#[test]
fn tilesets_in_every_encoding_import_verify_and_fly() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../test-data/encoded-tilesets");
    for encoding in ["plain", "draco", "meshopt", "ktx2-uastc-zstd", "ktx2-etc1s"] {
        let tileset = root.join(encoding).join("tileset.json");
        let dataset = fresh_dir("fly-encodings", encoding);
        let out_dir = dataset.to_str().expect("utf-8");
        citystream_ok(&[
            "import",
            tileset.to_str().expect("utf-8"),
            "--out",
            out_dir,
            "--format",
            "bc7",
        ]);
        citystream_ok(&["verify", out_dir]);
        fly_and_check(
            &dataset,
            &fresh_dir("fly-encodings", &format!("{encoding}-fly")),
            60,
            encoding,
        );
    }
}
