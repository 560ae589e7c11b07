//! Sharded builds (`gen`/`import` `--shard I/N`, `merge`, `merge --status`): shards written
//! by concurrent processes merge into the dataset one process writes, byte for byte (write
//! ids aside), locally and in the S3 emulator; a killed shard resumes; a missing shard, a
//! shard of another job and a damaged shard are refused by name with nothing written.

mod cli_support;
mod tileset_support;

use std::path::Path;
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use citystream_dataset::remote::{open_dataset, RemoteOptions};
use citystream_dataset::Dataset;
use citystream_testing::tool_tests::env_refs;
use cli_support::{assert_same_content, citystream, emulator_with_bucket, fresh_dir, stderr};
use tileset_support::{row_of_walls, wall_glb};

fn spawn(args: &[&str], env: &[(&str, &str)]) -> Child {
    Command::new(env!("CARGO_BIN_EXE_citystream"))
        .args(args)
        .envs(env.iter().copied())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start citystream")
}

fn ok(out: Output, what: &str) -> Output {
    assert!(out.status.success(), "{what}: {}", stderr(&out));
    out
}

fn run_env(args: &[&str], env: &[(&str, &str)]) -> Output {
    spawn(args, env).wait_with_output().expect("citystream")
}

/// The files of the write `dataset` names, header fields that hold the write id (and the
/// CRCs over it) left out: what must be identical between two writes of the same content.
fn content_of(dataset: &Dataset) -> Vec<(String, Vec<u8>)> {
    let skip = |name: &str| match name {
        "textures.meta" | "colormap.bin" | "textures.crc" | "geometry.crc" => 40,
        "textures.pack" => 64,
        // Its CRC at 44..48 covers the write id.
        "tiles.bin" => 48,
        _ => unreachable!("{name} is not a dataset file with a header"),
    };
    let geometry = std::fs::read(dataset.files().path("geometry.pack")).expect("read geometry.pack");
    std::iter::once(("geometry.pack".to_string(), geometry))
        .chain(
            [
                "tiles.bin",
                "geometry.crc",
                "textures.meta",
                "colormap.bin",
                "textures.crc",
                "textures.pack",
            ]
            .iter()
            .map(|name| {
                let bytes = std::fs::read(dataset.files().path(name)).expect("read file");
                let mut kept = bytes[24..32.min(bytes.len())].to_vec();
                kept.extend_from_slice(&bytes[skip(name)..]);
                (name.to_string(), kept)
            }),
        )
        .collect()
}

fn assert_same_dataset(merged: &Path, single: &Path) {
    let (a, b) = (
        Dataset::open(merged).expect("merged"),
        Dataset::open(single).expect("single"),
    );
    for ((name, x), (_, y)) in content_of(&a).into_iter().zip(content_of(&b)) {
        assert!(
            x == y,
            "{name} of {} differs from {}'s",
            merged.display(),
            single.display()
        );
    }
    assert!(!a.textures.is_empty() && !a.scene.meshes.is_empty());
}

fn manifest(dir: &Path) -> Option<Vec<u8>> {
    std::fs::read(dir.join("dataset.manifest")).ok()
}

#[test]
fn gen_in_shards_merges_to_the_one_process_city_and_faulty_shards_are_refused() {
    let dir = fresh_dir("shards", "gen_local");
    let (single, out) = (dir.join("single"), dir.join("sharded"));
    let (single_s, out_s) = (single.to_str().expect("utf-8"), out.to_str().expect("utf-8"));
    let gen = |out: &str, extra: &[&str]| -> Vec<String> {
        let mut args: Vec<String> = ["gen", "--preset", "small", "--seed", "1", "--quiet", "--out", out]
            .iter()
            .map(|s| s.to_string())
            .collect();
        args.extend(extra.iter().map(|s| s.to_string()));
        args
    };
    let refs = |args: &[String]| -> Vec<String> { args.to_vec() };
    let run = |args: Vec<String>| {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        citystream(&args)
    };
    ok(run(gen(single_s, &[])), "one-process gen");

    // Shard 0 of 2 only: shard 1 is missing, and nothing is written.
    ok(run(refs(&gen(out_s, &["--shard", "0/2"]))), "shard 0");
    let refused = citystream(&["merge", out_s]);
    assert!(!refused.status.success());
    assert!(
        stderr(&refused).contains("shard 1 of 2 is missing"),
        "{}",
        stderr(&refused)
    );
    assert_eq!(manifest(&out), None, "a refused merge wrote a dataset");

    // Shard 1 of another job (other options): refused by name.
    ok(
        run(gen(out_s, &["--shard", "1/2", "--max-extent", "256"])),
        "foreign shard 1",
    );
    let refused = citystream(&["merge", out_s]);
    assert!(
        stderr(&refused).contains("shard 1") && stderr(&refused).contains("another job"),
        "{}",
        stderr(&refused)
    );
    assert_eq!(manifest(&out), None);

    // Shard 1 killed once its first checkpoint is durable: running, refused, then resumed.
    let args = gen(out_s, &["--shard", "1/2"]);
    let arg_refs: Vec<&str> = args.iter().map(String::as_str).collect();
    let mut child = spawn(&arg_refs, &[]);
    let started = Instant::now();
    let journal_has_a_record = || {
        std::fs::read_dir(out.join("shards/1"))
            .into_iter()
            .flatten()
            .flatten()
            .any(|e| std::fs::metadata(e.path().join("resume.journal")).is_ok_and(|m| m.len() > 200))
    };
    while !journal_has_a_record() {
        assert!(
            started.elapsed() < Duration::from_secs(120),
            "no checkpoint within 2 min"
        );
        assert!(
            child.try_wait().expect("wait").is_none(),
            "the shard ended before its kill"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    child.kill().expect("kill");
    child.wait().expect("reap");
    let status = ok(citystream(&["merge", "--status", out_s]), "status");
    let text = String::from_utf8_lossy(&status.stdout);
    // The foreign shard is still there, its replacement running beside it.
    assert!(
        text.contains("shard 0/2: done") && text.contains("a rerun is running"),
        "{text}"
    );
    let refused = citystream(&["merge", out_s]);
    assert!(stderr(&refused).contains("shard 1 ("), "{}", stderr(&refused));
    assert_eq!(manifest(&out), None);
    let rerun = ok(
        run(gen(out_s, &["--shard", "1/2"])
            .into_iter()
            .filter(|a| a != "--quiet")
            .collect()),
        "rerun",
    );
    assert!(stderr(&rerun).contains("resuming shard 1/2"), "{}", stderr(&rerun));

    // A flipped byte in shard 0's mips: refused naming the shard and the mip.
    let shard0 = Dataset::open(out.join("shards/0")).expect("shard 0");
    let pack = shard0.files().path("textures.pack");
    let mut bytes = std::fs::read(&pack).expect("pack");
    let at = bytes.len() / 2;
    bytes[at] ^= 0x10;
    std::fs::write(&pack, &bytes).expect("damage");
    let refused = citystream(&["merge", out_s]);
    let text = stderr(&refused);
    assert!(
        text.contains("shard 0 of 2") && text.contains("damaged") && text.contains("checksum"),
        "{text}"
    );
    assert_eq!(manifest(&out), None);
    bytes[at] ^= 0x10;
    std::fs::write(&pack, &bytes).expect("repair");

    let merged = ok(citystream(&["merge", out_s]), "merge");
    assert!(String::from_utf8_lossy(&merged.stdout).contains("merged 2 shards"));
    ok(citystream(&["verify", out_s]), "verify");
    assert_same_dataset(&out, &single);
}

/// A tileset of `n` walls in a row, each its own content and texture, under one root.
#[test]
fn a_tileset_imported_in_three_shards_merges_to_the_one_process_import() {
    let dir = fresh_dir("shards", "import");
    let tileset = row_of_walls(&dir, 8);
    let (single, out) = (dir.join("single"), dir.join("sharded"));
    let t = tileset.to_str().expect("utf-8");
    ok(
        citystream(&["import", t, "--out", single.to_str().expect("utf-8")]),
        "import",
    );
    let children: Vec<Child> = (0..3)
        .map(|i| {
            let shard = format!("{i}/3");
            spawn(
                &["import", t, "--out", out.to_str().expect("utf-8"), "--shard", &shard],
                &[],
            )
        })
        .collect();
    for child in children {
        ok(child.wait_with_output().expect("import shard"), "import shard");
    }
    ok(citystream(&["merge", out.to_str().expect("utf-8")]), "merge");
    assert_same_dataset(&out, &single);
    let merged = Dataset::open(&out).expect("merged");
    assert_eq!(merged.textures.len(), 8);

    // The tileset changes between two shards (one .glb's texture, same size): the shards
    // are of two jobs, refused by name with nothing written.
    let changed = dir.join("changed");
    let out_c = changed.to_str().expect("utf-8");
    ok(citystream(&["import", t, "--out", out_c, "--shard", "0/2"]), "shard 0");
    std::fs::write(dir.join("wall0.glb"), wall_glb(99)).expect("rewrite a content");
    ok(citystream(&["import", t, "--out", out_c, "--shard", "1/2"]), "shard 1");
    let refused = citystream(&["merge", out_c]);
    assert!(
        !refused.status.success(),
        "shards of two versions of the tileset merged"
    );
    assert!(stderr(&refused).contains("another job"), "{}", stderr(&refused));
    assert_eq!(manifest(&changed), None, "a refused merge wrote a dataset");

    // A glTF file is one content: nothing to divide.
    let glb = dir.join("wall0.glb");
    let refused = citystream(&["import", glb.to_str().expect("utf-8"), "--out", "x", "--shard", "0/2"]);
    assert!(
        stderr(&refused).contains("--shard divides a 3D Tiles tileset"),
        "{}",
        stderr(&refused)
    );
}

#[test]
#[cfg_attr(
    citystream_skip_s3,
    ignore = "the S3 emulator is not installed and `make setup` has not run"
)]
fn gen_in_four_concurrent_shards_into_s3_merges_there_to_the_one_process_city() {
    let preset = std::env::var("CITYSTREAM_SHARD_TEST_PRESET").unwrap_or_else(|_| "small".into());
    let dir = fresh_dir("shards", "gen_s3");
    let single = dir.join("single");
    ok(
        citystream(&[
            "gen",
            "--preset",
            &preset,
            "--seed",
            "1",
            "--quiet",
            "--out",
            single.to_str().expect("utf-8"),
        ]),
        "one-process gen",
    );
    let (_s3, env) = emulator_with_bucket(&dir);
    let env = env_refs(&env);
    let url = format!("s3://cities/{preset}");
    let children: Vec<Child> = (0..4)
        .map(|i| {
            let index = i.to_string();
            let mut env = env.clone();
            env.push(("AWS_BATCH_JOB_ARRAY_INDEX", &index));
            let args = [
                "gen",
                "--preset",
                &preset,
                "--seed",
                "1",
                "--quiet",
                "--out",
                &url,
                "--shard-index-env",
                "AWS_BATCH_JOB_ARRAY_INDEX",
                "--shards",
                "4",
            ];
            spawn(&args, &env)
        })
        .collect();
    for child in children {
        ok(child.wait_with_output().expect("gen shard"), "gen shard");
    }
    let status = ok(run_env(&["merge", "--status", &url], &env), "status");
    assert!(String::from_utf8_lossy(&status.stdout).contains("4 done, 0 running, 0 missing"));
    let merged = ok(run_env(&["merge", &url], &env), "merge");
    let summary = String::from_utf8_lossy(&merged.stdout).into_owned();
    assert!(summary.contains("merged 4 shards"), "{summary}");
    ok(run_env(&["verify", &url], &env), "verify");

    // Tables, colours, every mip's CRC and the scene, as read back from the store.
    for (k, v) in &env {
        std::env::set_var(k, v);
    }
    let remote = open_dataset(&url, &RemoteOptions::default()).expect("open merged");
    let local = Dataset::open(&single).expect("single");
    assert_same_content(&remote, &local);
    // `verify` above read every mip against these CRCs: the mips are the single build's.
    assert!(summary.contains("copied in the store"), "{summary}");
}

#[test]
fn shard_counts_are_bounded_and_many_missing_shards_are_counted_in_runs() {
    let dir = fresh_dir("shards", "bounded");
    let out = dir.join("out");
    let out_s = out.to_str().expect("utf-8");
    let gen = |extra: &[&str]| {
        let mut args = vec!["gen", "--preset", "tiny", "--seed", "1", "--quiet", "--out", out_s];
        args.extend_from_slice(extra);
        citystream(&args)
    };
    // The tiny city has 254 textures.
    for (shard, expected) in [
        ("0/1000000000", "at most 65536 shards"),
        ("0/4294967296", "at most 65536 shards"),
        ("0/0", "the shard count must be at least 1"),
        ("0/300", "300 shards of 254 textures: at most one shard per texture"),
    ] {
        let refused = gen(&["--shard", shard]);
        assert!(!refused.status.success(), "--shard {shard} ran");
        assert!(stderr(&refused).contains(expected), "{shard}: {}", stderr(&refused));
        assert!(!out.join("shards").exists(), "--shard {shard} wrote a shard");
    }
    // A dry run of a shard gives the shard's own part.
    let dry = ok(gen(&["--shard", "1/16", "--dry-run"]), "dry run");
    let text = String::from_utf8_lossy(&dry.stdout);
    assert!(
        text.contains("shard 1 of 16: textures 15 to 30 (16 textures)")
            && text.contains("this shard's part of the pack"),
        "{text}"
    );
    // One shard of 200 written, one of another job: the 198 others are counted in runs.
    ok(gen(&["--shard", "0/200"]), "shard 0");
    ok(
        gen(&["--shard", "7/200", "--max-extent", "256"]),
        "shard 7 of another job",
    );
    let status = ok(citystream(&["merge", "--status", out_s]), "status");
    let text = String::from_utf8_lossy(&status.stdout);
    assert!(text.contains("  shards 1 to 6 of 200: missing (6 shards)"), "{text}");
    assert!(text.contains("  shard 7/200: of another job"), "{text}");
    assert!(
        text.contains("  shards 8 to 199 of 200: missing (192 shards)"),
        "{text}"
    );
    assert!(
        text.ends_with("1 done, 0 running, 198 missing, 1 of another job\n"),
        "{text}"
    );
    assert!(text.lines().count() < 10, "{text}");
    let refused = citystream(&["merge", out_s]);
    assert!(!refused.status.success());
    let why = stderr(&refused);
    assert!(why.contains("shards 1 to 6 of 200 are missing (6 shards)"), "{why}");
    assert!(why.contains("shards 8 to 199 of 200 are missing (192 shards)"), "{why}");
    assert!(why.contains("shard 7") && why.contains("another job"), "{why}");
    assert_eq!(manifest(&out), None, "a refused merge wrote a dataset");
}

#[test]
fn an_s3_out_without_shard_is_refused_and_nothing_is_written_locally() {
    let dir = fresh_dir("shards", "s3_out_refused");
    let city = cli_support::tiny_city_at(dir.join("city"));
    let city_s = city.to_str().expect("utf-8");
    let url = "s3://cities/y";
    let run = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_citystream"))
            .args(args)
            .current_dir(&dir)
            .output()
            .expect("citystream runs")
    };
    for (args, expected) in [
        (vec!["gen", "--preset", "tiny", "--out", url], "is a URL"),
        (vec!["gen", "--preset", "tiny", "--dry-run", "--out", url], "is a URL"),
        (vec!["atlas", city_s, "--out", url], "is a URL"),
        (vec!["bench", "--out", url], "is a URL"),
        (vec!["path", "--dataset", city_s, "--out", url], "is a URL"),
    ] {
        let refused = run(&args);
        assert!(!refused.status.success(), "{args:?} ran");
        assert!(stderr(&refused).contains(expected), "{args:?}: {}", stderr(&refused));
    }
    let glb = dir.join("wall.glb");
    std::fs::write(&glb, tileset_support::wall_glb(1)).expect("glb written");
    let refused = run(&["import", glb.to_str().expect("utf-8"), "--out", url]);
    assert!(stderr(&refused).contains("is a URL"), "{}", stderr(&refused));
    assert!(!dir.join("s3:").exists(), "a local ./s3:/ folder was written");
}

#[test]
#[cfg_attr(
    citystream_skip_s3,
    ignore = "the S3 emulator is not installed and `make setup` has not run"
)]
fn an_s3_prefix_with_empty_segments_is_the_same_prefix_for_writers_and_readers() {
    let dir = fresh_dir("shards", "s3_prefix");
    let (_s3, env) = emulator_with_bucket(&dir);
    let env = env_refs(&env);
    let gen = [
        "gen",
        "--preset",
        "tiny",
        "--seed",
        "1",
        "--quiet",
        "--shard",
        "0/1",
        "--out",
        "s3://cities//x/",
    ];
    ok(run_env(&gen, &env), "gen into s3://cities//x/");
    let status = ok(run_env(&["merge", "--status", "s3://cities/x"], &env), "status");
    let text = String::from_utf8_lossy(&status.stdout);
    assert!(text.contains("1 done, 0 running, 0 missing"), "{text}");
    // The shard's lease (its journal) went with its write.
    assert!(!text.contains("a rerun is running"), "{text}");
    ok(run_env(&["merge", "s3://cities//x"], &env), "merge");
    ok(run_env(&["verify", "s3://cities/x/"], &env), "verify");
    let info = ok(run_env(&["info", "s3://cities///x"], &env), "info");
    assert!(
        String::from_utf8_lossy(&info.stdout).contains("254 textures"),
        "{}",
        String::from_utf8_lossy(&info.stdout)
    );
    let refused = run_env(&["merge", "--status", "s3://cities/x/../y"], &env);
    assert!(stderr(&refused).contains("\"..\" segment"), "{}", stderr(&refused));
}

/// The emulator with the bucket `cities`, and its client environment.
#[test]
#[cfg_attr(
    citystream_skip_s3,
    ignore = "the S3 emulator is not installed and `make setup` has not run"
)]
fn two_writers_of_one_s3_shard_at_once_one_is_refused_and_the_shard_stays_whole() {
    let dir = fresh_dir("shards", "s3_same_shard");
    let (_s3, env) = emulator_with_bucket(&dir);
    let env = env_refs(&env);
    let url = "s3://cities/twice";
    let mut refused_any = false;
    for round in 0..3 {
        // Two machines: two staging directories.
        let children: Vec<Child> = (0..2)
            .map(|machine| {
                let tmp = dir.join(format!("tmp-{round}-{machine}"));
                std::fs::create_dir_all(&tmp).expect("tmp");
                let mut env = env.clone();
                env.push(("TMPDIR", tmp.to_str().expect("utf-8")));
                spawn(
                    &[
                        "gen", "--preset", "tiny", "--seed", "1", "--quiet", "--shard", "0/2", "--out", url,
                    ],
                    &env,
                )
            })
            .collect();
        let outputs: Vec<Output> = children
            .into_iter()
            .map(|c| c.wait_with_output().expect("gen"))
            .collect();
        let refused: Vec<&Output> = outputs.iter().filter(|o| !o.status.success()).collect();
        assert!(refused.len() <= 1, "round {round}: both writers failed");
        for output in &refused {
            assert!(stderr(output).contains("held by another writer"), "{}", stderr(output));
        }
        refused_any |= !refused.is_empty();
        // The shard names only files that are there, every mip checked.
        ok(
            run_env(&["verify", &format!("{url}/shards/0")], &env),
            "verify the shard",
        );
    }
    assert!(refused_any, "the two writers never met: the test did not race them");
    ok(
        run_env(
            &[
                "gen", "--preset", "tiny", "--seed", "1", "--quiet", "--shard", "1/2", "--out", url,
            ],
            &env,
        ),
        "shard 1",
    );
    ok(run_env(&["merge", url], &env), "merge");
    ok(run_env(&["verify", url], &env), "verify");
}

#[test]
#[cfg_attr(
    citystream_skip_s3,
    ignore = "the S3 emulator is not installed and `make setup` has not run"
)]
fn concurrent_merges_into_one_s3_prefix_never_break_the_merged_dataset() {
    let dir = fresh_dir("shards", "s3_merges");
    let (_s3, env) = emulator_with_bucket(&dir);
    let env = env_refs(&env);
    let url = "s3://cities/merged";
    for i in 0..2 {
        let shard = format!("{i}/2");
        ok(
            run_env(
                &[
                    "gen", "--preset", "tiny", "--seed", "1", "--quiet", "--shard", &shard, "--out", url,
                ],
                &env,
            ),
            "shard",
        );
    }
    ok(run_env(&["merge", url], &env), "first merge");
    let mut refused_any = false;
    for round in 0..4 {
        let children: Vec<Child> = (0..3).map(|_| spawn(&["merge", "--quiet", url], &env)).collect();
        let outputs: Vec<Output> = children
            .into_iter()
            .map(|c| c.wait_with_output().expect("merge"))
            .collect();
        for output in outputs.iter().filter(|o| !o.status.success()) {
            refused_any = true;
            assert!(
                stderr(output).contains("held by another writer"),
                "round {round}: {}",
                stderr(output)
            );
        }
        // Whichever merges ran, the dataset the manifest names is whole.
        ok(run_env(&["verify", url], &env), "verify after concurrent merges");
    }
    assert!(refused_any, "no merge ever met another: the test did not race them");
    // The lease is gone once every merge has finished: another merge runs.
    ok(run_env(&["merge", "--quiet", url], &env), "a later merge");
}
