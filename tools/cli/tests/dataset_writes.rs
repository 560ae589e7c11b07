//! Writes never lose or mix datasets: `gen`, `import` and `atlas` killed at many moments
//! leave the old or the new dataset, concurrent writers are refused, failed writes leave the
//! old dataset, files that are not the tool's own are never touched, and version-1 and
//! version-2 datasets are named for `citystream upgrade`, which keeps their content and gives
//! them a CRS when asked.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Instant;

use citystream_dataset::{
    verify, Dataset, DatasetFiles, GEOMETRY_CRC_FILE, GEOMETRY_PACK_FILE, MANIFEST_FILE, SCENE_FILE, TILES_FILE,
};
use citystream_testing::fuzz::quad_buffer;

mod cli_support;
use cli_support::{citystream, copy_tree, stderr};

/// Kill moments per tool, spread evenly over an uninterrupted run.
const KILL_MOMENTS: u32 = 20;

fn fresh_dir(name: &str) -> PathBuf {
    cli_support::fresh_path("dataset-writes", name)
}

fn utf8(path: &Path) -> &str {
    path.to_str().expect("utf-8 temp path")
}

fn succeed(args: &[&str]) {
    let out = citystream(args);
    assert!(out.status.success(), "{args:?} failed: {}", stderr(&out));
}

fn write_id(dir: &Path) -> u64 {
    DatasetFiles::resolve(dir).expect("manifest").write_id()
}

/// The write subdirectories in `dir`.
fn write_dirs(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .expect("read dir")
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("write-"))
        .collect()
}

/// What identifies a dataset's content: scene, texture table, colours and every mip's
/// checksum (which `verify` checks every mip against).
fn fingerprint(dir: &Path) -> Fingerprint {
    fingerprint_of(Dataset::open(dir).expect("open"))
}

/// Scene, textures and colours as text, and every mip's checksum.
type Fingerprint = (String, Vec<u32>);
/// A scene's origin and CRS.
type Frame = ([f64; 3], Option<String>);

/// [`fingerprint`] apart from the scene's frame (origin and CRS), which generated cities
/// changed in format version 3; returns the frame beside it.
fn fingerprint_and_frame(dir: &Path) -> (Fingerprint, Frame) {
    let mut dataset = Dataset::open(dir).expect("open");
    let frame = (
        dataset.scene.origin,
        dataset.scene.crs.take().map(|crs| crs.to_string()),
    );
    dataset.scene.origin = [0.0; 3];
    (fingerprint_of(dataset), frame)
}

fn fingerprint_of(dataset: Dataset) -> Fingerprint {
    let checksums = dataset
        .textures
        .textures()
        .iter()
        .enumerate()
        .flat_map(|(id, info)| (0..info.mip_count()).map(move |level| (id as u32, level)))
        .map(|(id, level)| dataset.textures.mip_checksum(id, level).expect("checksum"))
        .collect();
    (
        format!(
            "{:?} {:?} {:?}",
            dataset.scene,
            dataset.textures.textures(),
            dataset.colormap.colours()
        ),
        checksums,
    )
}

/// Runs `args` (which write into `dir`) once uninterrupted into a scratch copy to learn its
/// duration and result, then `KILL_MOMENTS` times over the old dataset in `dir`, killing it
/// with SIGKILL at evenly spaced moments. After each kill `dir` must verify and hold the old
/// or the new dataset. Returns how many kills left the old and how many the new one.
fn kill_at_moments(name: &str, old: &Path, args: impl Fn(&Path) -> Vec<String>) -> (u32, u32) {
    let reference = fresh_dir(&format!("{name}-reference"));
    copy_tree(old, &reference);
    let started = Instant::now();
    let reference_args = args(&reference);
    let out = Command::new(env!("CARGO_BIN_EXE_citystream"))
        .args(&reference_args)
        .output()
        .expect("run");
    let duration = started.elapsed();
    assert!(out.status.success(), "{reference_args:?}: {}", stderr(&out));
    let new_content = fingerprint(&reference);
    let old_content = fingerprint(old);
    assert_ne!(new_content, old_content, "the write must change the dataset");
    let old_id = write_id(old);

    let dir = fresh_dir(name);
    let (mut kept_old, mut got_new) = (0, 0);
    for moment in 0..KILL_MOMENTS {
        if dir.exists() && write_id(&dir) != old_id {
            std::fs::remove_dir_all(&dir).expect("reset");
        }
        if !dir.exists() {
            copy_tree(old, &dir);
        }
        let mut child = Command::new(env!("CARGO_BIN_EXE_citystream"))
            .args(args(&dir))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("spawn");
        std::thread::sleep(duration.mul_f64((f64::from(moment) + 0.5) / f64::from(KILL_MOMENTS)));
        let _ = child.kill();
        child.wait().expect("reap");
        let report = verify(&dir).unwrap_or_else(|e| panic!("{name}: kill {moment} left a broken dataset: {e}"));
        assert!(report.textures > 0);
        if write_id(&dir) == old_id {
            assert!(
                fingerprint(&dir) == old_content,
                "{name}: kill {moment}: old write id, other content"
            );
            kept_old += 1;
        } else {
            assert!(
                fingerprint(&dir) == new_content,
                "{name}: kill {moment} left a dataset that is neither the old nor the new one"
            );
            got_new += 1;
        }
    }
    // What a killed writer left behind goes with the next write.
    let out = Command::new(env!("CARGO_BIN_EXE_citystream"))
        .args(args(&dir))
        .output()
        .expect("run");
    assert!(out.status.success(), "{}", stderr(&out));
    assert_eq!(write_dirs(&dir).len(), 1, "stale writes left: {:?}", write_dirs(&dir));
    assert!(fingerprint(&dir) == new_content);
    eprintln!("{name}: {kept_old} kills kept the old dataset, {got_new} left the new one ({duration:?} per run)");
    (kept_old, got_new)
}

fn gen_tiny(name: &str, seed: &str) -> PathBuf {
    let dir = fresh_dir(name);
    succeed(&["gen", "--preset", "tiny", "--seed", seed, "--out", utf8(&dir)]);
    dir
}

fn strings(args: &[&str]) -> Vec<String> {
    args.iter().map(|s| s.to_string()).collect()
}

#[test]
fn killed_gen_leaves_the_old_or_the_new_dataset() {
    let old = gen_tiny("gen-old", "1");
    let (kept_old, _) = kill_at_moments("gen-kill", &old, |dir| {
        strings(&["gen", "--preset", "small", "--seed", "2", "--out", utf8(dir)])
    });
    assert!(kept_old > 0, "no kill landed before the switch");
}

#[test]
fn killed_atlas_leaves_the_old_or_the_new_dataset() {
    let source = fresh_dir("atlas-source");
    succeed(&["gen", "--preset", "small", "--seed", "3", "--out", utf8(&source)]);
    let old = gen_tiny("atlas-old", "1");
    let source_str = utf8(&source).to_string();
    let (kept_old, _) = kill_at_moments("atlas-kill", &old, move |dir| {
        strings(&["atlas", &source_str, "--out", utf8(dir), "--atlas-extent", "2048"])
    });
    assert!(kept_old > 0, "no kill landed before the switch");
}

/// A glTF of one quad textured with a `side`² PNG, so that import spends its time decoding,
/// resampling and encoding.
fn write_big_texture_gltf(dir: &Path, side: u32) -> PathBuf {
    std::fs::create_dir_all(dir).expect("dir");
    let quad = quad_buffer(10.0, 1.0);
    std::fs::write(dir.join("quad.bin"), &quad.bytes).expect("bin");
    image::RgbaImage::from_fn(side, side, |x, y| {
        image::Rgba([(x % 251) as u8, (y % 241) as u8, ((x ^ y) % 256) as u8, 255])
    })
    .save(dir.join("big.png"))
    .expect("png");
    let gltf = serde_json::json!({
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2, "material": 0}]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
        "textures": [{"source": 0}],
        "images": [{"uri": "big.png"}],
        "buffers": [{"uri": "quad.bin", "byteLength": quad.bytes.len()}],
        "bufferViews": quad.buffer_views,
        "accessors": quad.accessors
    });
    let path = dir.join("quad.gltf");
    std::fs::write(&path, serde_json::to_vec(&gltf).expect("json")).expect("gltf");
    path
}

#[test]
fn killed_import_leaves_the_old_or_the_new_dataset() {
    let gltf = write_big_texture_gltf(&fresh_dir("import-source"), 4096);
    let old = gen_tiny("import-old", "1");
    let gltf_str = utf8(&gltf).to_string();
    let (kept_old, _) = kill_at_moments("import-kill", &old, move |dir| {
        strings(&["import", &gltf_str, "--out", utf8(dir), "--max-extent", "4096"])
    });
    assert!(kept_old > 0, "no kill landed before the switch");
}

#[test]
fn concurrent_writers_never_mix() {
    for round in 0..3 {
        let dir = fresh_dir(&format!("concurrent-{round}"));
        let spawn = |seed: &str| {
            Command::new(env!("CARGO_BIN_EXE_citystream"))
                .args(["gen", "--preset", "small", "--seed", seed, "--out", utf8(&dir)])
                .stdout(Stdio::null())
                .stderr(Stdio::piped())
                .spawn()
                .expect("spawn")
        };
        let (a, b) = (spawn("1"), spawn("2"));
        let (a, b) = (a.wait_with_output().expect("a"), b.wait_with_output().expect("b"));
        assert!(
            a.status.success() || b.status.success(),
            "neither writer finished: {} / {}",
            stderr(&a),
            stderr(&b)
        );
        for out in [&a, &b] {
            if !out.status.success() {
                assert!(stderr(out).contains("another process is writing"), "{}", stderr(out));
            }
        }
        verify(&dir).expect("the dataset verifies");
        let got = fingerprint(&dir);
        let expected: Vec<_> = [("1", &a), ("2", &b)]
            .into_iter()
            .filter(|(_, out)| out.status.success())
            .map(|(seed, _)| {
                let reference = fresh_dir(&format!("concurrent-{round}-seed-{seed}"));
                succeed(&["gen", "--preset", "small", "--seed", seed, "--out", utf8(&reference)]);
                fingerprint(&reference)
            })
            .collect();
        assert!(expected.contains(&got), "round {round}: a mixed dataset");
        assert_eq!(write_dirs(&dir).len(), 1);
    }
}

#[test]
fn failed_writes_leave_the_old_dataset_untouched() {
    let dir = gen_tiny("failed-writes", "4");
    let before = (write_id(&dir), fingerprint(&dir));
    let no_images = fresh_dir("failed-writes-no-images");
    std::fs::create_dir_all(&no_images).expect("dir");
    std::fs::write(no_images.join("readme.txt"), b"not an image").expect("file");
    // A glTF whose image does not decode.
    let broken = write_big_texture_gltf(&fresh_dir("failed-writes-gltf"), 64);
    std::fs::write(broken.with_file_name("big.png"), b"\x89PNG but not really").expect("png");
    let failures: [Vec<&str>; 2] = [
        vec![
            "gen",
            "--preset",
            "tiny",
            "--textures-from",
            utf8(&no_images),
            "--out",
            utf8(&dir),
        ],
        vec!["import", utf8(&broken), "--out", utf8(&dir)],
    ];
    for args in failures {
        let out = citystream(&args);
        assert!(!out.status.success(), "{args:?} succeeded");
        verify(&dir).unwrap_or_else(|e| panic!("{args:?} broke the dataset: {e}"));
        assert_eq!(
            (write_id(&dir), fingerprint(&dir)),
            before,
            "{args:?} changed the dataset"
        );
        assert_eq!(write_dirs(&dir).len(), 1, "{args:?} left its partial write");
    }
    // A successful atlas of a dataset into itself replaces it.
    succeed(&["atlas", utf8(&dir), "--out", utf8(&dir), "--atlas-extent", "512"]);
    verify(&dir).expect("atlas into itself");
    assert_ne!(write_id(&dir), before.0);
}

#[test]
fn files_that_are_not_the_tools_own_are_never_touched() {
    let dir = fresh_dir("user-files");
    std::fs::create_dir_all(&dir).expect("dir");
    // The user's own files, one named like a dataset file.
    std::fs::write(dir.join("notes.txt"), b"survey notes").expect("notes");
    std::fs::write(dir.join(SCENE_FILE), b"my scene, not a dataset").expect("scene");
    std::fs::create_dir_all(dir.join("write-photos")).expect("photos");
    succeed(&["gen", "--preset", "tiny", "--out", utf8(&dir)]);
    succeed(&["gen", "--preset", "tiny", "--seed", "2", "--out", utf8(&dir)]);
    verify(&dir).expect("dataset");
    assert_eq!(std::fs::read(dir.join("notes.txt")).expect("notes"), b"survey notes");
    assert_eq!(
        std::fs::read(dir.join(SCENE_FILE)).expect("scene"),
        b"my scene, not a dataset"
    );
    assert!(dir.join("write-photos").is_dir());

    // A file named like the manifest that is not one is refused, not replaced.
    let dir = fresh_dir("user-manifest");
    std::fs::create_dir_all(&dir).expect("dir");
    std::fs::write(dir.join(MANIFEST_FILE), b"my own manifest of photos").expect("manifest");
    let out = citystream(&["gen", "--preset", "tiny", "--out", utf8(&dir)]);
    assert!(!out.status.success());
    assert!(stderr(&out).contains(MANIFEST_FILE), "{}", stderr(&out));
    assert_eq!(
        std::fs::read(dir.join(MANIFEST_FILE)).expect("kept"),
        b"my own manifest of photos"
    );
    assert!(write_dirs(&dir).is_empty());
}

/// Writes with this build what the fixtures' `gen` command wrote with theirs.
fn gen_like_the_fixtures(dir: &Path) {
    succeed(&[
        "gen",
        "--preset",
        "tiny",
        "--seed",
        "3",
        "--max-extent",
        "16",
        "--out",
        utf8(dir),
    ]);
}

/// A copy, in `name`'s own directory, of the fixture dataset `tools/test-data/FIXTURE`.
fn fixture(fixture: &str, name: &str) -> PathBuf {
    let dir = fresh_dir(name);
    copy_tree(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("../test-data").join(fixture),
        &dir,
    );
    dir
}

/// The names of the files and directories in `dir` other than its writes, sorted.
fn names_beside_the_writes(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .expect("dir")
        .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
        .filter(|n| !n.starts_with("write-"))
        .collect();
    names.sort();
    names
}

/// `info` and `verify` refuse the dataset in `dir`, of format `version`, naming its
/// version and the upgrade that would make it readable.
fn assert_info_and_verify_name_the_upgrade(dir: &Path, version: u32) {
    for command in ["info", "verify"] {
        let out = citystream(&[command, utf8(dir)]);
        assert!(!out.status.success(), "{command} accepted a version-{version} dataset");
        let message = stderr(&out);
        assert!(
            message.contains(&format!("format version {version}"))
                && message.contains(&format!("citystream upgrade {}", utf8(dir))),
            "{command}: {message}"
        );
    }
}

/// A version-1 dataset written by the version-1 `gen --preset tiny --seed 3 --max-extent 16`.
fn v1_fixture(name: &str) -> PathBuf {
    fixture("v1-tiny", name)
}

#[test]
fn version_1_datasets_name_the_upgrade_and_the_upgrade_keeps_their_content() {
    let dir = v1_fixture("v1");
    std::fs::write(dir.join("notes.txt"), b"mine").expect("notes");
    assert_info_and_verify_name_the_upgrade(&dir, 1);
    let out = citystream(&["upgrade", utf8(&dir)]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(String::from_utf8_lossy(&out.stdout).contains("from format version 1 to 4"));
    verify(&dir).expect("upgraded dataset verifies");
    // The version-1 files are gone, the user's file stays.
    assert_eq!(names_beside_the_writes(&dir), [MANIFEST_FILE, "notes.txt"]);
    // The same command with this build writes the same content.
    let regenerated = fresh_dir("v1-regenerated");
    gen_like_the_fixtures(&regenerated);
    // Generated cities now sit at Berlin's UTM coordinates with +z south (northing −z) and
    // say so; the upgrade keeps the old frame as it was, without a CRS.
    let (upgraded, upgraded_frame) = fingerprint_and_frame(&dir);
    let (fresh, fresh_frame) = fingerprint_and_frame(&regenerated);
    assert!(upgraded == fresh, "the upgrade changed the content");
    assert_eq!(upgraded_frame, ([391_250.0, 34.0, 5_819_500.0], None));
    assert_eq!(
        fresh_frame,
        ([391_250.0, 34.0, -5_819_500.0], Some("EPSG:25833".to_string()))
    );
    // Upgrading again does nothing.
    let id = write_id(&dir);
    let out = citystream(&["upgrade", utf8(&dir)]);
    assert!(out.status.success());
    assert!(String::from_utf8_lossy(&out.stdout).contains("nothing to do"));
    assert_eq!(write_id(&dir), id);

    // An upgrade killed after its manifest rename, before its clean-up, leaves the version-1
    // files beside the new write: the next upgrade removes them, and nothing else.
    let fixture = v1_fixture("v1-leftovers-source");
    let mut leftovers = Vec::new();
    for entry in std::fs::read_dir(&fixture).expect("fixture") {
        let entry = entry.expect("entry");
        if entry.file_type().expect("type").is_file() {
            std::fs::copy(entry.path(), dir.join(entry.file_name())).expect("copy");
            leftovers.push(entry.file_name().to_string_lossy().into_owned());
        }
    }
    assert!(leftovers.len() >= 5, "{leftovers:?}");
    verify(&dir).expect("the current write is what a reader sees");
    let out = citystream(&["upgrade", utf8(&dir)]);
    assert!(out.status.success(), "{}", stderr(&out));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains("nothing to do") && stdout.contains(&format!("removed {} version-1 files", leftovers.len())),
        "{stdout}"
    );
    assert_eq!(names_beside_the_writes(&dir), [MANIFEST_FILE, "notes.txt"]);
    assert_eq!(write_id(&dir), id);
}

/// A version-2 dataset written by the version-2 `gen --preset tiny --seed 3 --max-extent 16`.
fn v2_fixture(name: &str) -> PathBuf {
    fixture("v2-tiny", name)
}

fn upgrade_stdout(args: &[&str]) -> String {
    let out = citystream(args);
    assert!(out.status.success(), "{args:?} failed: {}", stderr(&out));
    String::from_utf8_lossy(&out.stdout).into_owned()
}

#[test]
fn version_2_datasets_name_the_upgrade_which_keeps_their_content_and_can_give_them_a_crs() {
    let dir = v2_fixture("v2");
    assert_info_and_verify_name_the_upgrade(&dir, 2);
    let old_write = write_dirs(&dir);
    // A text that is no CRS is refused before anything is written.
    let out = citystream(&["upgrade", utf8(&dir), "--crs", "UTM 33N"]);
    assert!(!out.status.success());
    assert!(stderr(&out).contains("not a CRS"), "{}", stderr(&out));
    assert_eq!(write_dirs(&dir), old_write);

    let regenerated = fresh_dir("v2-regenerated");
    gen_like_the_fixtures(&regenerated);
    let (fresh, _) = fingerprint_and_frame(&regenerated);

    // Without --crs: the same content in a local frame.
    let plain = v2_fixture("v2-plain");
    assert!(upgrade_stdout(&["upgrade", utf8(&plain)]).contains("from format version 2 to 4:"));
    verify(&plain).expect("upgraded dataset verifies");
    assert_eq!(write_dirs(&plain).len(), 1, "the version-2 write is removed");
    let (content, frame) = fingerprint_and_frame(&plain);
    assert!(content == fresh, "the upgrade changed the content");
    assert_eq!(frame, ([391_250.0, 34.0, 5_819_500.0], None));

    // With --crs: the same content, georeferenced.
    let said = upgrade_stdout(&["upgrade", utf8(&dir), "--crs", "epsg:25833"]);
    assert!(said.contains("from format version 2 to 4 in CRS EPSG:25833"), "{said}");
    let (content, frame) = fingerprint_and_frame(&dir);
    assert!(content == fresh, "the upgrade changed the content");
    assert_eq!(frame.1.as_deref(), Some("EPSG:25833"));
    // The same CRS again (as WKT naming it) is nothing to do; another one is refused.
    let id = write_id(&dir);
    let wkt = r#"PROJCRS["ETRS89 / UTM zone 33N",BASEGEOGCRS["ETRS89",ID["EPSG",4258]],ID["EPSG",25833]]"#;
    assert!(upgrade_stdout(&["upgrade", utf8(&dir), "--crs", wkt]).contains("nothing to do"));
    let out = citystream(&["upgrade", utf8(&dir), "--crs", "EPSG:32633"]);
    assert!(!out.status.success());
    let message = stderr(&out);
    assert!(
        message.contains("already in CRS EPSG:25833") && message.contains("EPSG:32633"),
        "{message}"
    );
    assert_eq!(write_id(&dir), id, "a refused upgrade writes nothing");

    // A current dataset without a CRS gets one, and keeps its content.
    let said = upgrade_stdout(&["upgrade", utf8(&plain), "--crs", wkt]);
    assert!(said.contains("from format version 4 to 4"), "{said}");
    let (content, frame) = fingerprint_and_frame(&plain);
    assert!(content == fresh);
    assert_eq!(frame.1.as_deref(), Some(wkt));
}

/// A version-3 dataset written by the version-3 `gen --preset tiny --seed 3 --max-extent 16`
/// (one `scene.bin`; the generator unchanged since).
fn v3_fixture(name: &str) -> PathBuf {
    fixture("v3-tiny", name)
}

#[test]
fn version_3_datasets_name_the_upgrade_which_cuts_their_scene_into_tiles_and_keeps_the_rest() {
    let dir = v3_fixture("v3");
    assert_info_and_verify_name_the_upgrade(&dir, 3);
    let regenerated = fresh_dir("v3-regenerated");
    gen_like_the_fixtures(&regenerated);
    let said = upgrade_stdout(&["upgrade", utf8(&dir)]);
    assert!(said.contains("from format version 3 to 4:"), "{said}");
    verify(&dir).expect("upgraded dataset verifies");
    assert_eq!(write_dirs(&dir).len(), 1, "the version-3 write is removed");
    // The same scene (frame and CRS included), textures and colours as this build's `gen`.
    assert!(
        fingerprint(&dir) == fingerprint(&regenerated),
        "the upgrade changed the content"
    );
    let files = DatasetFiles::resolve(&dir).expect("a version-4 manifest");
    for name in [TILES_FILE, GEOMETRY_PACK_FILE, GEOMETRY_CRC_FILE] {
        assert!(files.path(name).is_file(), "{name} is written");
    }
    assert!(!files.path(SCENE_FILE).exists(), "version 4 has no scene.bin");
    assert!(upgrade_stdout(&["upgrade", utf8(&dir)]).contains("nothing to do"));
}

#[test]
fn info_reports_the_crs_and_the_origin_in_its_axes() {
    let dir = fresh_dir("info-crs");
    gen_like_the_fixtures(&dir);
    let out = citystream(&["info", utf8(&dir), "--json"]);
    assert!(out.status.success(), "{}", stderr(&out));
    let info: serde_json::Value = serde_json::from_slice(&out.stdout).expect("json");
    assert_eq!(info["format_version"], 4);
    assert_eq!(info["crs"], "EPSG:25833");
    // Easting, northing, height of the scene origin (x east, y up, z south).
    assert_eq!(info["origin_crs"], serde_json::json!([391_250.0, 5_819_500.0, 34.0]));
    let text = upgrade_stdout(&["info", utf8(&dir)]);
    assert!(
        text.contains("crs        EPSG:25833; origin easting 391250.000 northing 5819500.000 height 34.000"),
        "{text}"
    );
}

#[test]
fn concurrent_upgrades_of_one_dataset_both_succeed() {
    // Two runs finding the same old city: the second waits for the first, then has nothing to do.
    for round in 0..3 {
        let dir = v1_fixture(&format!("v1-concurrent-{round}"));
        let spawn = || {
            Command::new(env!("CARGO_BIN_EXE_citystream"))
                .args(["upgrade", utf8(&dir)])
                .stdout(Stdio::piped())
                .stderr(Stdio::piped())
                .spawn()
                .expect("spawn")
        };
        let (a, b) = (spawn(), spawn());
        let (a, b) = (a.wait_with_output().expect("a"), b.wait_with_output().expect("b"));
        for out in [&a, &b] {
            assert!(out.status.success(), "round {round}: {}", stderr(out));
        }
        let said: Vec<String> = [&a, &b]
            .iter()
            .map(|o| String::from_utf8_lossy(&o.stdout).into_owned())
            .collect();
        assert_eq!(
            said.iter().filter(|s| s.contains("nothing to do")).count(),
            1,
            "round {round}: {said:?}"
        );
        verify(&dir).expect("upgraded dataset verifies");
        assert_eq!(write_dirs(&dir).len(), 1);
    }
}

#[test]
fn damaged_version_1_datasets_are_not_upgraded() {
    let dir = v1_fixture("v1-damaged");
    let pack = dir.join("textures.pack");
    let mut bytes = std::fs::read(&pack).expect("pack");
    let n = bytes.len();
    bytes[n - 5] ^= 0x55;
    std::fs::write(&pack, &bytes).expect("write");
    let out = citystream(&["upgrade", utf8(&dir)]);
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains("textures.pack") && stderr(&out).contains("checksum"),
        "{}",
        stderr(&out)
    );
    // Nothing was written: the version-1 files are all still there.
    assert!(!dir.join(MANIFEST_FILE).exists());
    assert!(write_dirs(&dir).is_empty());
    assert_eq!(std::fs::read(&pack).expect("pack"), bytes);
}
