//! `flythrough --disk-model`: under the deterministic clocks a loading cycle's reads take
//! modelled time on the loader's threads while frames go on, so a cycle spans the frames
//! its reads take, and the same run repeats byte for byte.

mod flight_support;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use flight_support::{fresh_dir, stderr, tiny_city};

/// A fixed-clock flight of `city` into `out` (160×96, no PSNR, 240 frames) with `extra`.
fn fly(city: &Path, out: &Path, extra: &[&str]) -> Output {
    fly_on(city, out, "fixed", extra)
}

/// [`fly`] with the clock `clock`.
fn fly_on(city: &Path, out: &Path, clock: &str, extra: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_flythrough"))
        .arg("--dataset")
        .arg(city)
        .args(["--clock", clock, "--frames", "240", "--width", "160", "--height", "96"])
        .args([
            "--psnr-interval",
            "0",
            "--frame-interval",
            "0",
            "--bind-latency",
            "desktop",
        ])
        .args(extra)
        .arg("--out")
        .arg(out)
        .output()
        .expect("flythrough runs")
}

fn summary(out: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).expect("summary.json")).expect("JSON")
}

/// frames.csv's `cycle_started`, `reads_in_flight_bytes` and `bytes` per frame.
fn cycles(out: &Path) -> Vec<(bool, u64, u64)> {
    let csv = std::fs::read_to_string(out.join("frames.csv")).expect("frames.csv");
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().expect("a header").split(',').collect();
    let column = |name: &str| header.iter().position(|c| *c == name).expect(name);
    let (started, in_flight, bytes) = (
        column("cycle_started"),
        column("reads_in_flight_bytes"),
        column("bytes"),
    );
    lines
        .map(|line| {
            let cells: Vec<&str> = line.split(',').collect();
            (
                cells[started] == "1",
                cells[in_flight].parse().expect("reads_in_flight_bytes"),
                cells[bytes].parse().expect("bytes"),
            )
        })
        .collect()
}

/// A disk model file for `measured:FILE`.
fn disk_file(dir: &Path, bytes_per_s: u64, latency_ns: u64, queue_depth: u32) -> PathBuf {
    let path = dir.join(format!("disk-{bytes_per_s}.json"));
    let json = serde_json::json!({
        "bytes_per_s": bytes_per_s,
        "request_latency_ns": latency_ns,
        "queue_depth": queue_depth,
        "source": "a slow disk for a test",
    });
    std::fs::write(&path, json.to_string()).expect("disk model file");
    path
}

#[test]
fn the_paper_s_disk_repeats_exactly_and_a_slow_disk_spans_frames() {
    let dir = fresh_dir("read_model", "spans");
    let city = tiny_city(&dir);

    // The same path twice under the paper's SSD: identical frames.csv.
    let (a, b) = (dir.join("evo-a"), dir.join("evo-b"));
    for out in [&a, &b] {
        let run = fly(&city, out, &["--disk-model", "970evo"]);
        assert!(run.status.success(), "{}", stderr(&run));
    }
    let csv = |out: &Path| std::fs::read(out.join("frames.csv")).expect("frames.csv");
    assert_eq!(
        csv(&a),
        csv(&b),
        "two 970evo runs of the same path must match byte for byte"
    );
    let evo = summary(&a);
    assert_eq!(evo["disk_model"]["name"], "970evo");
    assert_eq!(evo["disk_model"]["bytes_per_s"], 3_400_000_000u64);
    assert_eq!(evo["disk_model"]["queue_depth"], 12);
    assert_eq!(evo["validation_errors"], 0);

    // 200 KB/s with 2 ms a request on one lane: reads of the tiny city's mips take
    // frames, and the next cycle waits for them.
    let slow = disk_file(&dir, 200_000, 2_000_000, 1);
    let out = dir.join("slow");
    let run = fly(&city, &out, &["--disk-model", &format!("measured:{}", slow.display())]);
    assert!(run.status.success(), "{}", stderr(&run));
    let rows = cycles(&out);
    assert_eq!(rows.len(), 240);
    let starts: Vec<usize> = rows.iter().enumerate().filter(|(_, r)| r.0).map(|(f, _)| f).collect();
    assert_eq!(summary(&out)["loading_cycles"], starts.len());
    assert!(starts.len() > 3, "{starts:?}");
    let mut spanned = 0;
    for pair in starts.windows(2) {
        let (from, next) = (pair[0], pair[1]);
        let held = rows[from].1;
        // Every byte of a cycle's reads passes the 200 KB/s pipe after at least one 2 ms
        // request: the next cycle starts no sooner than that on the 60 Hz path, and it
        // starts in the first frame after the reads are done (one 2 ms request a mip, and
        // no mip is under 4 bytes).
        let at_least = held as f64 / 200_000.0 + if held > 0 { 0.002 } else { 0.0 };
        let at_most = held as f64 / 200_000.0 + held as f64 / 4.0 * 0.002;
        let took = (next - from) as f64 / 60.0;
        assert!(
            took + 1e-9 >= at_least && took <= at_most + 1.0 / 60.0 + 1e-9,
            "cycle at frame {from} held {held} bytes and the next started at frame {next}"
        );
        if next - from > 1 {
            spanned += 1;
            // The frames between see the reads in flight and no new cycle.
            assert!(rows[from + 1..next].iter().all(|r| !r.0 && r.1 > 0));
        }
        // Its bytes reach the cache as its reads complete, the last of them in the frame
        // the next cycle starts.
        let arrived: u64 = rows[from + 1..=next].iter().map(|r| r.2).sum();
        assert_eq!(arrived, held, "cycle at frame {from}");
    }
    assert!(spanned > 0, "no cycle spanned frames on the slow disk: {starts:?}");
}

#[test]
fn measured_probes_this_disk_and_the_file_repeats_the_run() {
    let dir = fresh_dir("read_model", "measured");
    let city = tiny_city(&dir);
    let first = dir.join("first");
    let run = fly(&city, &first, &["--disk-model", "measured"]);
    assert!(run.status.success(), "{}", stderr(&run));
    let figures = first.join("disk-model.json");
    let written: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&figures).expect("disk-model.json")).expect("JSON");
    assert!(written["bytes_per_s"].as_u64().is_some_and(|b| b > 0), "{written}");
    assert_eq!(summary(&first)["disk_model"]["name"], "measured");
    // The figures it wrote give the same run.
    let again = dir.join("again");
    let run = fly(
        &city,
        &again,
        &["--disk-model", &format!("measured:{}", figures.display())],
    );
    assert!(run.status.success(), "{}", stderr(&run));
    assert_eq!(
        std::fs::read(first.join("frames.csv")).expect("frames.csv"),
        std::fs::read(again.join("frames.csv")).expect("frames.csv")
    );
}

#[test]
fn disk_models_that_cannot_apply_are_refused_by_name() {
    let dir = fresh_dir("read_model", "refused");
    let city = tiny_city(&dir);
    let bad_depth = disk_file(&dir, 1_000_000, 1_000, 0);
    let bad_depth = format!("measured:{}", bad_depth.display());
    let cases: [(&str, &[&str], &str); 4] = [
        (
            "real",
            &["--disk-model", "970evo"],
            "--disk-model 970evo times reads on a modelled clock",
        ),
        ("fixed", &["--disk-model", "ssd"], "unknown disk model `ssd`"),
        (
            "fixed",
            &["--disk-model", "measured:/nonexistent/disk.json"],
            "/nonexistent/disk.json",
        ),
        ("modelled", &["--disk-model", &bad_depth], "queue_depth is 0"),
    ];
    for (i, (clock, args, expected)) in cases.iter().enumerate() {
        let out = dir.join(format!("case-{i}"));
        let run = fly_on(&city, &out, clock, args);
        assert!(!run.status.success(), "{args:?} ran");
        assert!(stderr(&run).contains(expected), "{args:?}: {}", stderr(&run));
    }
}

/// Bytes of `file` in the page cache (`fincore`, util-linux).
fn resident_bytes(file: &Path) -> u64 {
    let out = Command::new("fincore")
        .args(["--bytes", "--noheadings", "--output", "RES"])
        .arg(file)
        .output()
        .expect("fincore (util-linux) runs");
    assert!(
        out.status.success(),
        "fincore: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout)
        .trim()
        .parse()
        .expect("fincore's RES")
}

#[test]
fn the_disk_probe_reads_around_the_page_cache_or_says_it_did_not() {
    let dir = fresh_dir("read_model", "probe-cache");
    let city = tiny_city(&dir);
    let dataset = citystream_dataset::Dataset::open(&city).expect("the tiny city opens");
    let pack = dataset.textures.pack_path().to_path_buf();
    // Written pages are dirty until synced, and dirty pages cannot be dropped.
    std::fs::File::open(&pack)
        .and_then(|f| f.sync_all())
        .expect("pack synced");
    let figures = citystream_bench::disk_probe::measure(&dataset, &city).expect("the probe measures");
    let resident = resident_bytes(&pack);
    if figures.source.contains("direct reads (O_DIRECT") {
        // Buffered reads of a pack this small leave it in the page cache (readahead), and
        // the probe's figures would be the cache's.
        assert_eq!(
            resident, 0,
            "{}: {resident} bytes cached after the probe",
            figures.source
        );
    } else {
        assert!(
            figures.source.contains("page-cache hits") || figures.source.contains("warm page cache"),
            "{}",
            figures.source
        );
    }
}
