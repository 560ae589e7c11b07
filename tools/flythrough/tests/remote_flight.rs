//! Datasets flown from an HTTP server: nginx from Debian, started by each test on
//! loopback with a configuration the test writes (range requests are nginx's default for
//! static files); S3 from an emulator the setup script installs. Where nginx or the
//! emulator is missing and the setup script (`make setup`) has not run, the tests that need
//! it compile as ignored (`tools/build.rs`), so they are reported as skipped; after it, a
//! missing tool fails them.

mod flight_support;

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use citystream_testing::fault_proxy::{FaultOptions, FaultProxy};
use citystream_testing::nginx::Nginx;
use citystream_testing::s3_emulator::S3Emulator;
use citystream_testing::tool_tests::{self, env_refs, start_nginx, S3_CITY};
use flight_support::{citystream_ok, fresh_dir, stderr};

/// A tiny city in the test's own directory, served by nginx (its parent as the root).
fn served_city(name: &str) -> (PathBuf, PathBuf, Nginx) {
    let dir = fresh_dir("remote_dataset", name);
    let city = tiny_city(&dir);
    let nginx = start_nginx(&dir, &dir.join("www"));
    (dir, city, nginx)
}

fn tiny_city(dir: &Path) -> PathBuf {
    let city = dir.join("www").join("city");
    citystream_ok(&["gen", "--preset", "tiny", "--out", city.to_str().expect("utf-8")]);
    city
}

/// 90 frames, every 30th written and measured against the fully resident reference.
const FRAMES_AND_ERROR: [&str; 6] = ["--frames", "90", "--frame-interval", "30", "--psnr-interval", "30"];

#[test]
#[cfg_attr(
    citystream_skip_nginx,
    ignore = "nginx is not installed and `make setup` has not run"
)]
fn a_city_streamed_from_http_renders_what_it_renders_from_disk() {
    let (dir, city, nginx) = served_city("http_frames");
    let url = nginx.url("city/");

    let local_out = run_ok(&dir, "local", city.to_str().expect("utf-8"), &FRAMES_AND_ERROR, &[]);
    let remote_out = run_ok(&dir, "remote", &url, &FRAMES_AND_ERROR, &[]);

    let local_csv = assert_same_frames(&local_out, &remote_out);

    // With room for only a few mips held ahead (the tiny city's are about 330 bytes), most
    // hints wait for reads to free room: still the same frames.
    let tight_out = dir.join("tight");
    let tight: Vec<&str> = FRAMES_AND_ERROR
        .iter()
        .copied()
        .chain(["--remote-prefetch-mb", "0.002", "--remote-in-flight", "2"])
        .collect();
    let out = fixed_run(&url, &tight_out, &tight, &[])
        .output()
        .expect("run flythrough");
    assert!(out.status.success(), "remote run, 2 KB ahead: {}", stderr(&out));
    let tight_csv = std::fs::read_to_string(tight_out.join("frames.csv")).expect("frames.csv");
    assert_eq!(tight_csv, local_csv, "frames.csv differs with 2 KB held ahead");
}

/// Runs `command`, killing it (and failing) if it has not ended after `limit`.
fn output_within(mut command: Command, limit: Duration) -> Output {
    let mut child = command
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn");
    let started = Instant::now();
    loop {
        if child.try_wait().expect("status").is_some() {
            return child.wait_with_output().expect("output");
        }
        if started.elapsed() > limit {
            let _ = child.kill();
            let out = child.wait_with_output().expect("output");
            panic!("still running after {limit:?}: a hang; stderr: {}", stderr(&out));
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Asserts that two runs of [`FRAMES_AND_ERROR`] streamed frame for frame the same (the
/// fixed clock waits for every load, wherever it comes from): the same per-frame uploads,
/// residency and error, the same pixels, and no failure; returns the local frames.csv.
fn assert_same_frames(local_out: &Path, remote_out: &Path) -> String {
    let local_csv = std::fs::read_to_string(local_out.join("frames.csv")).expect("local frames.csv");
    let remote_csv = std::fs::read_to_string(remote_out.join("frames.csv")).expect("remote frames.csv");
    assert_eq!(local_csv.lines().count(), 91);
    assert_eq!(
        remote_csv, local_csv,
        "frames.csv differs between the remote and the local run"
    );
    for frame in [0, 30, 60] {
        let name = format!("frame_{frame:05}.png");
        let local = image::open(local_out.join("frames").join(&name)).expect("local frame");
        let remote = image::open(remote_out.join("frames").join(&name)).expect("remote frame");
        assert!(local.to_rgba8() == remote.to_rgba8(), "{name} differs");
    }
    let remote = summary(remote_out);
    assert!(remote["mips_streamed"].as_u64().is_some_and(|m| m > 20), "{remote}");
    assert_eq!(remote["load_failures"], 0);
    local_csv
}

/// [`fixed_run`] into `dir/name`, failing the test unless it succeeds within 300 s; returns
/// the output directory.
fn run_ok(dir: &Path, name: &str, dataset: &str, args: &[&str], env: &[(&str, &str)]) -> PathBuf {
    let out_dir = dir.join(name);
    let out = output_within(fixed_run(dataset, &out_dir, args, env), Duration::from_secs(300));
    assert!(out.status.success(), "{name} run of {dataset}: {}", stderr(&out));
    out_dir
}

/// The flythrough on `dataset` with the fixed clock at 160×96 into `out`, with
/// synchronization validation (frames overlap), `extra` options and `env` variables.
fn fixed_run(dataset: &str, out: &Path, extra: &[&str], env: &[(&str, &str)]) -> Command {
    run_with_clock("fixed", dataset, out, extra, env)
}

/// A flythrough of `dataset` under `clock` (`fixed`, `real`, `modelled`), as [`fixed_run`].
fn run_with_clock(clock: &str, dataset: &str, out: &Path, extra: &[&str], env: &[(&str, &str)]) -> Command {
    let mut command = Command::new(env!("CARGO_BIN_EXE_flythrough"));
    command
        .args([
            "--clock",
            clock,
            "--width",
            "160",
            "--height",
            "96",
            "--dataset",
            dataset,
        ])
        .args(extra)
        .arg("--out")
        .arg(out)
        .env("CITYSTREAM_VALIDATION", "sync")
        .envs(env.iter().copied());
    command
}

/// A tiny city served by nginx behind a fault proxy with `options`.
fn city_behind_proxy(name: &str, options: FaultOptions) -> (PathBuf, PathBuf, Nginx, FaultProxy) {
    let (dir, city, nginx) = served_city(name);
    let proxy = FaultProxy::start(([127, 0, 0, 1], nginx.port()).into(), options).expect("proxy");
    (dir, city, nginx, proxy)
}

fn summary(out: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).expect("summary.json")).expect("json")
}

/// 60 frames, no images, no error reference: what the fault tests compare.
const SHORT_RUN: [&str; 6] = ["--frames", "60", "--frame-interval", "0", "--psnr-interval", "0"];

#[test]
#[cfg_attr(
    citystream_skip_nginx,
    ignore = "nginx is not installed and `make setup` has not run"
)]
fn dropped_connections_and_short_bodies_are_retried_and_change_nothing() {
    let options = FaultOptions {
        drop_every: 7,
        truncate_every: 5,
        ..FaultOptions::default()
    };
    let (dir, city, _nginx, proxy) = city_behind_proxy("faults_retried", options);
    let local_out = run_ok(&dir, "local", city.to_str().expect("utf-8"), &SHORT_RUN, &[]);
    let url = format!("http://{}/city", proxy.addr());
    let remote_out = run_ok(&dir, "remote", &url, &SHORT_RUN, &[]);
    assert_faults_retried(&proxy, &local_out, &remote_out);
}

/// Asserts that `proxy` injected faults and every one was retried to success: the same
/// frames as from disk, nothing failed.
fn assert_faults_retried(proxy: &FaultProxy, local_out: &Path, remote_out: &Path) {
    assert!(
        proxy.faults() >= 3,
        "{} faults injected in {} requests",
        proxy.faults(),
        proxy.requests()
    );
    let local_csv = std::fs::read_to_string(local_out.join("frames.csv")).expect("csv");
    let remote_csv = std::fs::read_to_string(remote_out.join("frames.csv")).expect("csv");
    assert_eq!(remote_csv, local_csv);
    let remote = summary(remote_out);
    assert_eq!(remote["load_failures"], 0, "{remote}");
}

#[test]
#[cfg_attr(
    citystream_skip_nginx,
    ignore = "nginx is not installed and `make setup` has not run"
)]
fn mips_a_server_keeps_refusing_fail_their_textures_without_a_hang() {
    let options = FaultOptions {
        fail_mips: true,
        ..FaultOptions::default()
    };
    let (dir, _city, _nginx, proxy) = city_behind_proxy("faults_failing", options);
    let out_dir = dir.join("remote");
    let url = format!("http://{}/city", proxy.addr());
    // One retry per request: the loader's own three attempts follow.
    let out = output_within(
        fixed_run(&url, &out_dir, &SHORT_RUN, &[("CITYSTREAM_REMOTE_RETRIES", "1")]),
        Duration::from_secs(300),
    );
    assert!(!out.status.success(), "a run whose every mip failed exited 0");
    let text = stderr(&out);
    assert!(text.contains("failed to load") && text.contains("503"), "{text}");
    let run = summary(&out_dir);
    let failed = run["textures_failed"].as_u64().expect("textures_failed");
    assert!(failed > 0, "{run}");
    assert_eq!(run["mips_streamed"], 0, "{run}");
}

#[test]
#[cfg_attr(
    citystream_skip_nginx,
    ignore = "nginx is not installed and `make setup` has not run"
)]
fn mips_a_server_never_answers_fail_their_textures_within_their_timeouts_in_every_clock_mode() {
    let options = FaultOptions {
        silent_mips: true,
        ..FaultOptions::default()
    };
    let (dir, _city, _nginx, proxy) = city_behind_proxy("faults_silent", options);
    let url = format!("http://{}/city", proxy.addr());
    for clock in ["fixed", "real"] {
        let out_dir = dir.join(clock);
        // Requests time out after 2 s and are retried once: the first mip goes unanswered for
        // about 4 s, and every read after it fails at once until a later one is answered.
        let started = Instant::now();
        let out = output_within(
            run_with_clock(
                clock,
                &url,
                &out_dir,
                &SHORT_RUN,
                &[("CITYSTREAM_REMOTE_RETRIES", "1"), ("CITYSTREAM_REMOTE_TIMEOUT_S", "2")],
            ),
            Duration::from_secs(120),
        );
        assert!(!out.status.success(), "{clock}: a run that streamed nothing exited 0");
        let text = stderr(&out);
        assert!(
            text.contains("failed to load") && text.contains("no answer from"),
            "{clock}: {text}"
        );
        let run = summary(&out_dir);
        assert!(
            run["textures_failed"].as_u64().expect("textures_failed") > 0,
            "{clock}: {run}"
        );
        assert_eq!(run["mips_streamed"], 0, "{clock}: {run}");
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "{clock}: took {:?}",
            started.elapsed()
        );
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
fn a_city_streamed_from_s3_renders_what_it_renders_from_disk() {
    let (dir, city, s3) = city_in_s3("s3_frames");
    let env = s3.client_env();
    let env = env_refs(&env);

    let local_out = run_ok(&dir, "local", city.to_str().expect("utf-8"), &FRAMES_AND_ERROR, &[]);
    let remote_out = run_ok(&dir, "s3", S3_CITY, &FRAMES_AND_ERROR, &env);
    assert_same_frames(&local_out, &remote_out);
}

#[test]
#[cfg_attr(
    citystream_skip_s3,
    ignore = "the S3 emulator is not installed and `make setup` has not run"
)]
fn s3_requests_dropped_and_cut_short_are_retried_and_change_nothing() {
    let (dir, city, s3) = city_in_s3("s3_faults");
    let options = FaultOptions {
        drop_every: 7,
        truncate_every: 5,
        ..FaultOptions::default()
    };
    let proxy = FaultProxy::start(([127, 0, 0, 1], s3.port()).into(), options).expect("proxy");
    let mut env: Vec<(&str, String)> = s3.client_env();
    env[0].1 = format!("http://{}", proxy.addr());
    let env = env_refs(&env);

    let local_out = run_ok(&dir, "local", city.to_str().expect("utf-8"), &SHORT_RUN, &[]);
    let remote_out = run_ok(&dir, "s3", S3_CITY, &SHORT_RUN, &env);
    assert_faults_retried(&proxy, &local_out, &remote_out);
}

/// Bytes in the files under `dir` whose name `counts` accepts.
fn tree_bytes_where(dir: &Path, counts: &dyn Fn(&std::ffi::OsStr) -> bool) -> u64 {
    std::fs::read_dir(dir).map_or(0, |entries| {
        entries
            .map(|e| e.expect("entry"))
            .map(|e| {
                let meta = e.metadata().expect("metadata");
                if meta.is_dir() {
                    tree_bytes_where(&e.path(), counts)
                } else if counts(&e.file_name()) {
                    meta.len()
                } else {
                    0
                }
            })
            .sum()
    })
}

/// Bytes in the files under `dir`.
fn tree_bytes(dir: &Path) -> u64 {
    tree_bytes_where(dir, &|_| true)
}

/// Bytes in the files under `dir` with one of `names`.
fn tree_bytes_named(dir: &Path, names: &[&str]) -> u64 {
    tree_bytes_where(dir, &|name| names.iter().any(|n| name == *n))
}

#[test]
#[cfg_attr(
    citystream_skip_nginx,
    ignore = "nginx is not installed and `make setup` has not run"
)]
fn a_second_flight_reads_its_mips_from_the_mip_cache() {
    let (dir, city, nginx) = served_city("mip_cache");
    let cache = dir.join("mip-cache");
    let cache_arg = cache.to_str().expect("utf-8");
    let url = nginx.url("city/");
    let with_cache: Vec<&str> = SHORT_RUN.iter().copied().chain(["--mip-cache", cache_arg]).collect();

    // First flight: every mip comes from the server and goes into the cache.
    let first_out = dir.join("first");
    let out = output_within(fixed_run(&url, &first_out, &with_cache, &[]), Duration::from_secs(300));
    assert!(out.status.success(), "first flight: {}", stderr(&out));
    let first = summary(&first_out);
    let mips = first["mips_streamed"].as_u64().expect("mips_streamed");
    assert!(mips > 20, "{first}");
    assert_eq!(first["mip_cache"]["hits"], 0, "{first}");
    assert!(first["mip_cache"]["written"].as_u64() >= Some(mips), "{first}");

    // Second flight through a server that refuses every mip: it renders the same, all from
    // the cache.
    let refusing = FaultProxy::start(
        ([127, 0, 0, 1], nginx.port()).into(),
        FaultOptions {
            fail_mips: true,
            ..FaultOptions::default()
        },
    )
    .expect("proxy");
    let second_out = dir.join("second");
    let refusing_url = format!("http://{}/city/", refusing.addr());
    let out = output_within(
        fixed_run(
            &refusing_url,
            &second_out,
            &SHORT_RUN,
            &[("CITYSTREAM_MIP_CACHE", cache_arg)],
        ),
        Duration::from_secs(300),
    );
    assert!(out.status.success(), "second flight from the cache: {}", stderr(&out));
    let second = summary(&second_out);
    assert_eq!(second["mip_cache"]["misses"], 0, "{second}");
    assert!(second["mip_cache"]["hits"].as_u64() >= Some(mips), "{second}");
    assert_eq!(second["load_failures"], 0);
    let csv = |out: &Path| std::fs::read_to_string(out.join("frames.csv")).expect("frames.csv");
    assert_eq!(csv(&second_out), csv(&first_out));
    let local_out = run_ok(&dir, "local", city.to_str().expect("utf-8"), &SHORT_RUN, &[]);
    assert_eq!(csv(&first_out), csv(&local_out));

    // A damaged entry is found by its CRC, dropped and read from the server again.
    let entry = std::fs::read_dir(cache.join("v1"))
        .expect("cache")
        .map(|e| e.expect("entry").path())
        .find(|p| p.is_dir())
        .and_then(|ns| {
            std::fs::read_dir(ns)
                .expect("namespace")
                .map(|e| e.expect("entry").path())
                .find(|p| p.file_name().is_some_and(|n| n != "SOURCE"))
        })
        .expect("a cached mip");
    let mut bytes = std::fs::read(&entry).expect("entry");
    bytes[0] ^= 0xff;
    std::fs::write(&entry, bytes).expect("damage");
    let third_out = dir.join("third");
    let out = output_within(fixed_run(&url, &third_out, &with_cache, &[]), Duration::from_secs(300));
    assert!(out.status.success(), "third flight: {}", stderr(&out));
    let third = summary(&third_out);
    assert!(third["mip_cache"]["damaged"].as_u64() >= Some(1), "{third}");
    assert_eq!(csv(&third_out), csv(&first_out));

    // A cache smaller than the mips read (25 KB here) stays within its capacity.
    let small = dir.join("small-cache");
    let small_out = dir.join("small");
    let small_args: Vec<&str> = SHORT_RUN
        .iter()
        .copied()
        .chain(["--mip-cache", small.to_str().expect("utf-8"), "--mip-cache-mb", "0.005"])
        .collect();
    let out = output_within(fixed_run(&url, &small_out, &small_args, &[]), Duration::from_secs(300));
    assert!(out.status.success(), "small cache: {}", stderr(&out));
    let run = summary(&small_out);
    assert!(run["mip_cache"]["evicted"].as_u64() > Some(0), "{run}");
    // Its SOURCE note and lock file aside.
    let held = tree_bytes(&small.join("v1")) - tree_bytes_named(&small.join("v1"), &["SOURCE", "lock"]);
    assert!(held <= 5242, "a 0.005 MB cache holds {held} bytes");
    assert!(held > 0);
    assert_eq!(csv(&small_out), csv(&first_out));
}
