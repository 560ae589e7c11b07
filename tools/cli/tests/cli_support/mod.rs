//! Helpers the tools' command-line tests share (each test file is its own
//! crate and includes this module with `mod cli_support;`).

#![allow(dead_code, unused_imports)] // reason: each test binary uses a different subset

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use citystream_testing::tool_tests;
pub use citystream_testing::tool_tests::{setup_ran, stderr};

/// Runs the `citystream` binary built with these tests.
pub fn citystream(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_citystream"))
        .args(args)
        .output()
        .expect("run citystream")
}

/// Runs `citystream COMMAND INPUT --out OUT EXTRA…`.
pub fn citystream_into(command: &str, input: &Path, out: &Path, extra: &[&str]) -> Output {
    let mut args = vec![
        command,
        input.to_str().expect("utf-8"),
        "--out",
        out.to_str().expect("utf-8"),
    ];
    args.extend_from_slice(extra);
    citystream(&args)
}

/// Runs `citystream import INPUT --out OUT EXTRA…`.
pub fn import(input: &Path, out: &Path, extra: &[&str]) -> Output {
    citystream_into("import", input, out, extra)
}

/// `citystream gen --preset tiny --out CITY`, which must succeed; the city's directory.
pub fn tiny_city_at(city: PathBuf) -> PathBuf {
    let out = citystream(&["gen", "--preset", "tiny", "--out", city.to_str().expect("utf-8")]);
    assert!(out.status.success(), "gen: {}", stderr(&out));
    city
}

/// [`import`] into `out_dir`, which must succeed and pass `citystream verify`; the dataset
/// written and the import's output.
pub fn import_verified(input: &Path, out_dir: &Path, extra: &[&str]) -> (citystream_dataset::Dataset, Output) {
    let out = import(input, out_dir, extra);
    assert!(
        out.status.success(),
        "import of {} failed: {}",
        input.display(),
        stderr(&out)
    );
    let verify = citystream(&["verify", out_dir.to_str().expect("utf-8")]);
    assert!(verify.status.success(), "verify failed: {}", stderr(&verify));
    let dataset = citystream_dataset::Dataset::open(out_dir).expect("open imported dataset");
    (dataset, out)
}

/// `CARGO_TARGET_TMPDIR/group/name`, removed if it exists; its parent exists,
/// it does not (for commands that must create their output themselves).
pub fn fresh_path(group: &str, name: &str) -> PathBuf {
    tool_tests::fresh_path(Path::new(env!("CARGO_TARGET_TMPDIR")), group, name)
}

/// [`fresh_path`], created empty.
pub fn fresh_dir(group: &str, name: &str) -> PathBuf {
    tool_tests::fresh_dir(Path::new(env!("CARGO_TARGET_TMPDIR")), group, name)
}

/// Copies the directory tree `from` to `to`.
pub fn copy_tree(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).expect("create copy");
    for entry in std::fs::read_dir(from).expect("read dir") {
        let entry = entry.expect("entry");
        if entry.file_type().expect("type").is_dir() {
            copy_tree(&entry.path(), &to.join(entry.file_name()));
        } else {
            std::fs::copy(entry.path(), to.join(entry.file_name())).expect("copy");
        }
    }
}

/// The S3 emulator started under `dir`, with the bucket `cities` (made by uploading a small
/// file tree), and its client environment.
pub fn emulator_with_bucket(dir: &Path) -> (citystream_testing::s3_emulator::S3Emulator, Vec<(&'static str, String)>) {
    let seed_dir = dir.join("seed");
    std::fs::create_dir_all(&seed_dir).expect("seed dir");
    std::fs::write(seed_dir.join("README"), "a bucket for the tests").expect("seed file");
    let s3 = citystream_testing::s3_emulator::S3Emulator::start(dir)
        .expect("start the S3 emulator (`make setup` installs it)");
    s3.upload_dir("cities", "readme", &seed_dir).expect("make the bucket");
    let env = s3.client_env();
    (s3, env)
}

/// Tables, colours, scene and every mip's CRC of `remote` are those of `local` (with
/// `verify`, which reads every mip against its CRC, the mips are the same).
pub fn assert_same_content(remote: &citystream_dataset::Dataset, local: &citystream_dataset::Dataset) {
    assert_eq!(remote.textures.textures(), local.textures.textures(), "texture tables");
    assert_eq!(remote.colormap, local.colormap, "colormaps");
    assert_eq!(remote.scene, local.scene, "scenes");
    for t in 0..local.textures.len() {
        for level in 0..local.textures.textures()[t as usize].mip_count() {
            assert_eq!(
                remote.textures.mip_checksum(t, level).expect("remote crc"),
                local.textures.mip_checksum(t, level).expect("local crc"),
                "texture {t} level {level}"
            );
        }
    }
}
