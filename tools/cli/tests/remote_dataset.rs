//! Datasets read by `info` and `verify` from an HTTP server (the flythrough's tests fly
//! them): nginx from Debian, started by each test on loopback with a configuration the test
//! writes (range requests are nginx's default for static files); S3 from an emulator the
//! setup script installs. Where nginx or the emulator is missing and the setup script
//! (`make setup`) has not run, the tests that need it compile as ignored (`tools/build.rs`),
//! so they are reported as skipped; after it, a missing tool fails them.

mod cli_support;

use std::path::{Path, PathBuf};
use std::process::Command;

use citystream_testing::nginx::Nginx;
use citystream_testing::s3_emulator::S3Emulator;
use citystream_testing::tool_tests::{self, env_refs, start_nginx, S3_CITY};
use cli_support::{citystream, citystream_into, fresh_dir, stderr, tiny_city_at};

/// A tiny city in the test's own directory, served by nginx (its parent as the root).
fn served_city(name: &str) -> (PathBuf, PathBuf, Nginx) {
    let dir = fresh_dir("remote_dataset", name);
    let city = tiny_city(&dir);
    let nginx = start_nginx(&dir, &dir.join("www"));
    (dir, city, nginx)
}

fn tiny_city(dir: &Path) -> PathBuf {
    tiny_city_at(dir.join("www").join("city"))
}

#[test]
#[cfg_attr(
    citystream_skip_nginx,
    ignore = "nginx is not installed and `make setup` has not run"
)]
fn info_and_verify_read_a_remote_dataset() {
    let (_dir, city, nginx) = served_city("info_verify");
    let url = nginx.url("city");

    let info = |location: &str| -> serde_json::Value {
        let out = citystream(&["info", location, "--json"]);
        assert!(out.status.success(), "info {location}: {}", stderr(&out));
        let mut json: serde_json::Value = serde_json::from_slice(&out.stdout).expect("info JSON");
        let object = json.as_object_mut().expect("object");
        object.remove("dir");
        object.remove("open_seconds");
        json
    };
    assert_eq!(info(&url), info(city.to_str().expect("utf-8")));

    let out = citystream(&["verify", &url]);
    assert!(out.status.success(), "verify: {}", stderr(&out));
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.starts_with("ok: ") && text.contains(&url), "{text}");

    // A damaged mip on the server is found, named by URL and offset.
    let pack = std::fs::read_dir(&city)
        .expect("city")
        .map(|e| e.expect("entry").path())
        .find(|p| p.is_dir())
        .expect("write directory")
        .join("textures.pack");
    let mut bytes = std::fs::read(&pack).expect("pack");
    let last = bytes.len() - 1;
    bytes[last] ^= 0xff;
    std::fs::write(&pack, bytes).expect("damage");
    let out = citystream(&["verify", &url]);
    assert!(!out.status.success(), "a damaged pack verified");
    let text = stderr(&out);
    assert!(
        text.contains("textures.pack") && text.contains("http://127.0.0.1"),
        "{text}"
    );
}

#[test]
#[cfg_attr(
    citystream_skip_nginx,
    ignore = "nginx is not installed and `make setup` has not run"
)]
fn a_missing_remote_dataset_is_a_clear_error() {
    let dir = fresh_dir("remote_dataset", "missing");
    std::fs::create_dir_all(dir.join("www")).expect("www");
    let nginx = start_nginx(&dir, &dir.join("www"));
    let url = nginx.url("nowhere/");
    let out = citystream(&["info", &url]);
    assert!(!out.status.success());
    let text = stderr(&out);
    assert!(text.contains("dataset.manifest") && text.contains("missing"), "{text}");
    assert!(!text.contains("panicked"), "{text}");
    for bad in ["ftp://host/city", "http://"] {
        let out = citystream(&["info", bad]);
        assert!(!out.status.success(), "{bad} accepted");
        assert!(!stderr(&out).contains("panicked"), "{}", stderr(&out));
    }
}

/// A tiny city uploaded to [`S3_CITY`] of a fresh emulator.
fn city_in_s3(name: &str) -> (PathBuf, PathBuf, S3Emulator) {
    let dir = fresh_dir("remote_dataset", name);
    let city = tiny_city(&dir);
    let s3 = tool_tests::city_in_s3(&dir, &city);
    (dir, city, s3)
}

#[test]
#[cfg_attr(
    citystream_skip_s3,
    ignore = "the S3 emulator is not installed and `make setup` has not run"
)]
fn info_and_verify_read_a_dataset_in_s3() {
    let (_dir, city, s3) = city_in_s3("s3_info_verify");
    let env = s3.client_env();
    let env = env_refs(&env);

    // info and verify read the bucket; a missing prefix is a clear error naming it.
    let with_env = |args: &[&str]| {
        let mut command = Command::new(env!("CARGO_BIN_EXE_citystream"));
        command.args(args).envs(env.iter().copied());
        command.output().expect("run citystream")
    };
    let out = with_env(&["verify", S3_CITY]);
    assert!(out.status.success(), "verify: {}", stderr(&out));
    assert!(String::from_utf8_lossy(&out.stdout).starts_with("ok: s3://citystream/cities/tiny"));
    let out = with_env(&["info", S3_CITY, "--json"]);
    assert!(out.status.success(), "info: {}", stderr(&out));
    let info: serde_json::Value = serde_json::from_slice(&out.stdout).expect("info JSON");
    assert_eq!(info["textures"], summary_of_local_info(&city)["textures"]);
    let out = with_env(&["info", "s3://citystream/nowhere/"]);
    assert!(!out.status.success());
    let text = stderr(&out);
    assert!(
        text.contains("s3://citystream/nowhere") && text.contains("missing"),
        "{text}"
    );
    assert!(!text.contains("panicked"), "{text}");
}

fn summary_of_local_info(city: &Path) -> serde_json::Value {
    let out = citystream(&["info", city.to_str().expect("utf-8"), "--json"]);
    assert!(out.status.success(), "info: {}", stderr(&out));
    serde_json::from_slice(&out.stdout).expect("info JSON")
}

#[test]
#[cfg_attr(
    citystream_skip_nginx,
    ignore = "nginx is not installed and `make setup` has not run"
)]
fn a_texture_atlas_tree_is_read_and_checked_over_http() {
    let (dir, city, nginx) = served_city("atlas_tree");
    let tree = dir.join("www").join("tree");
    let out = citystream_into("atlas-tree", &city, &tree, &["--atlas-extent", "128", "--quiet"]);
    assert!(out.status.success(), "atlas-tree: {}", stderr(&out));
    let info = |location: &str| -> serde_json::Value {
        let out = citystream(&["info", location, "--json"]);
        assert!(out.status.success(), "info {location}: {}", stderr(&out));
        let json: serde_json::Value = serde_json::from_slice(&out.stdout).expect("info JSON");
        json["atlas_tree"].clone()
    };
    let url = nginx.url("tree/");
    let local = info(tree.to_str().expect("utf-8"));
    assert!(local["nodes"].as_u64().is_some_and(|n| n > 1), "{local}");
    assert_eq!(info(&url), local);
    let out = citystream(&["verify", &url]);
    assert!(out.status.success(), "verify: {}", stderr(&out));
    assert!(String::from_utf8_lossy(&out.stdout).contains("atlas tree of"));
}
