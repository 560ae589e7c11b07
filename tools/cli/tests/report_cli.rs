//! `citystream report` and `citystream bench` end to end: synthetic
//! flythrough runs written here, the numbers in table.md checked against
//! statistics computed here, the charts decoded, bad inputs rejected with
//! the file and line, and `bench` driven through a fake flythrough script.

use std::path::{Path, PathBuf};

mod cli_support;
use cli_support::citystream;

type TestResult = Result<(), Box<dyn std::error::Error>>;

const HEADER: &str = "frame,time_s,dt_ms,tw_ms,tm_ms,tb_ms,tbl_ms,tbu_ms,load_size_mb,mip_bias,mips,bytes,blocks_bound,resident_bytes,mip_deficit,psnr_db";

/// Fresh, empty scratch directory for one test.
fn scratch(name: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("report_cli").join(name);
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("creating the scratch directory");
    dir
}

/// Median (mean of the middle two for an even count), mean, max, min.
fn stats(values: &[f64]) -> [f64; 4] {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let n = v.len();
    let median = if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    };
    let mean = v.iter().sum::<f64>() / n as f64;
    [median, mean, v[n - 1], v[0]]
}

fn stats_json(s: [f64; 4]) -> String {
    format!(
        "{{\"median\": {}, \"mean\": {}, \"max\": {}, \"min\": {}}}",
        s[0], s[1], s[2], s[3]
    )
}

/// One synthetic frame; every value is a multiple of 1/4 so sums are exact
/// and the expected two-decimal figures cannot differ by rounding order.
struct Frame {
    dt_ms: f64,
    tw_ms: f64,
    psnr_db: Option<f64>,
    mip_deficit: Option<f64>,
}

fn frames(n: usize, slow: f64, psnr_every: usize, deficit_every: usize) -> Vec<Frame> {
    (0..n)
        .map(|i| Frame {
            dt_ms: 4.0 + ((i * 7) % 13) as f64 * 0.25 * slow,
            tw_ms: 9.0 + ((i * 5) % 11) as f64 * 0.5 * slow,
            psnr_db: (psnr_every > 0 && i % psnr_every == 0).then_some(30.0 + (i % 9) as f64 * 0.75),
            mip_deficit: (deficit_every > 0 && i % deficit_every == 0).then_some((n - i) as f64 * 0.25),
        })
        .collect()
}

fn csv(frames: &[Frame]) -> String {
    let mut out = format!("{HEADER}\n");
    let opt = |v: Option<f64>| v.map(|x| x.to_string()).unwrap_or_default();
    for (i, f) in frames.iter().enumerate() {
        let mips = (i % 6) as u64;
        out.push_str(&format!(
            "{i},{},{},{},12,{},{},{},{},{},{mips},{},{mips},{},{},{}\n",
            i as f64 * 0.05,
            f.dt_ms,
            f.tw_ms,
            f.tw_ms - 1.0,
            f.tw_ms - 3.0,
            f.tw_ms + 2.0,
            0.5 + (i % 5) as f64 * 0.25,
            (i % 4) as f64 * 0.5,
            mips * 65_536,
            1_000_000 + i * 1000,
            opt(f.mip_deficit),
            opt(f.psnr_db),
        ));
    }
    out
}

/// Keys of summary.json besides the statistics.
fn summary(frames: &[Frame], policy: &str, psnr: Option<[f64; 4]>, deficit: Option<[f64; 4]>) -> String {
    let dt: Vec<f64> = frames.iter().map(|f| f.dt_ms).collect();
    let tw: Vec<f64> = frames.iter().map(|f| f.tw_ms).collect();
    let optional = |key: &str, s: Option<[f64; 4]>| match s {
        Some(s) => format!("\"{key}\": {},", stats_json(s)),
        None => format!("\"{key}\": null,"),
    };
    format!(
        "{{\"frame_ms\": {}, \"tw_ms\": {}, \"mips_per_s\": {}, \"mb_per_s\": {},
          \"load_size_mb\": {}, \"mip_bias\": {}, {} {}
          \"frames\": {}, \"duration_s\": 12.5, \"policy\": \"{policy}\",
          \"bytes_streamed\": 10485760, \"mips_streamed\": 321, \"blocks_bound\": 77,
          \"peak_resident_bytes\": 52428800, \"device\": \"test\", \"clock\": \"fixed\"}}",
        stats_json(stats(&dt)),
        stats_json(stats(&tw)),
        stats_json([8000.0, 9000.5, 20000.0, 0.0]),
        stats_json([41.75, 42.25, 93.5, 0.0]),
        stats_json([0.75, 0.5, 1.75, 0.25]),
        stats_json([0.5, 1.25, 8.0, 0.0]),
        optional("psnr_db", psnr),
        // An absent key must work like null.
        deficit
            .map(|d| format!("\"mip_deficit\": {},", stats_json(d)))
            .unwrap_or_default(),
        frames.len(),
    )
}

/// `summary_text` with the headline error keys a flythrough writes.
fn with_error(summary_text: &str, psnr_of_mean_mse_db: f64, identical: u32, measured: u32) -> String {
    summary_text.replacen(
        "\"frames\":",
        &format!(
            "\"psnr_of_mean_mse_db\": {psnr_of_mean_mse_db}, \
             \"error_frames\": {{\"measured\": {measured}, \"identical\": {identical}}}, \"frames\":"
        ),
        1,
    )
}

/// The part of `table` from the line `heading` on.
fn section<'a>(table: &'a str, heading: &str) -> &'a str {
    let start = table
        .find(&format!("\n{heading}\n"))
        .unwrap_or_else(|| panic!("table.md has no `{heading}`:\n{table}"));
    &table[start..]
}

fn write_run(dir: &Path, csv_text: &str, summary_text: &str) {
    std::fs::create_dir_all(dir).expect("creating a run directory");
    std::fs::write(dir.join("frames.csv"), csv_text).expect("writing frames.csv");
    std::fs::write(dir.join("summary.json"), summary_text).expect("writing summary.json");
}

/// The cells after the label of the table row starting with `label`.
fn row(table: &str, label: &str) -> Vec<String> {
    let line = table
        .lines()
        .find(|l| l.starts_with(&format!("| {label} |")))
        .unwrap_or_else(|| panic!("table.md has no row `{label}`:\n{table}"));
    line.trim_matches('|')
        .split('|')
        .skip(1)
        .map(|c| c.trim().to_string())
        .collect()
}

fn fmt3(s: [f64; 4]) -> Vec<String> {
    vec![format!("{:.2}", s[0]), format!("{:.2}", s[1]), format!("{:.2}", s[2])]
}

/// The image-error table: the PSNR of the mean MSE and identical / measured frames, of the
/// streaming after the start-up fill (the headline), of the start-up fill and of every
/// frame, from the summary's keys, or recomputed from the CSV's `time_s` and `mse` columns
/// of a summary without them, or n/a.
#[test]
fn image_error_table_compares_runs_by_the_psnr_of_the_mean_mse() -> TestResult {
    let dir = scratch("image_error");
    // Run A: the keys in summary.json.
    let a = frames(20, 1.0, 5, 0);
    let a_summary = with_error(
        &summary(&a, "adaptive", Some([40.0, 45.0, 100.0, 20.0]), None),
        33.25,
        1,
        4,
    )
    .replacen(
        "\"frames\":",
        "\"startup_psnr_of_mean_mse_db\": 21.5, \"startup_error_frames\": {\"measured\": 1, \"identical\": 0}, \
         \"streaming_psnr_of_mean_mse_db\": 44.75, \"streaming_error_frames\": {\"measured\": 3, \"identical\": 1}, \
         \"frames\":",
        1,
    );
    write_run(&dir.join("a"), &csv(&a), &a_summary);
    // Run B: an older summary, with an `mse` column in the CSV (0 on an identical frame);
    // its frames 20 s of path apart, so the first alone is the start-up fill.
    let b = frames(12, 1.0, 4, 0);
    let mses = [
        Some(26.0),
        None,
        None,
        None,
        Some(0.0),
        None,
        None,
        None,
        Some(1.0),
        None,
        None,
        None,
    ];
    let mut b_csv = String::new();
    for (i, line) in csv(&b).lines().enumerate() {
        let mse = match i {
            0 => "mse".to_string(),
            _ => mses[i - 1].map(|m: f64| m.to_string()).unwrap_or_default(),
        };
        // time_s is the second column: frame i at 20·i s.
        let mut cells: Vec<String> = line.split(',').map(str::to_owned).collect();
        if i > 0 {
            cells[1] = ((i - 1) * 20).to_string();
        }
        b_csv.push_str(&format!("{},{mse}\n", cells.join(",")));
    }
    write_run(&dir.join("b"), &b_csv, &summary(&b, "baseline", None, None));
    // Run C: no error measured.
    let c = frames(10, 1.0, 0, 0);
    write_run(&dir.join("c"), &csv(&c), &summary(&c, "fixed", None, None));

    let out = dir.join("report");
    let run = |d: &str| dir.join(d).display().to_string();
    let (ra, rb, rc, ro) = (run("a"), run("b"), run("c"), out.display().to_string());
    let result = citystream(&["report", "--run", &ra, "--run", &rb, "--run", &rc, "--out", &ro]);
    assert!(
        result.status.success(),
        "report failed: {}",
        String::from_utf8_lossy(&result.stderr)
    );
    let table = std::fs::read_to_string(out.join("table.md"))?;
    let table = section(&table, "## Image error");
    assert!(
        table.contains(
            "| Run | Streaming PSNR of mean MSE (dB) | Identical / measured | Start-up PSNR of mean MSE (dB) | \
             Identical / measured | All frames PSNR of mean MSE (dB) | Identical / measured |"
        ),
        "{table}"
    );
    assert_eq!(row(table, "a"), ["44.75", "1 / 3", "21.50", "0 / 1", "33.25", "1 / 4"]);
    // MSEs 26 (start-up), 0 and 1 (after it): the mean MSE 9 over three frames is
    // 10·log10(65025 / 9) = 38.588..., the start-up's 10·log10(65025 / 26), the streaming's
    // 10·log10(65025 / 0.5).
    let db = |mse: f64| format!("{:.2}", 10.0 * (65025.0f64 / mse).log10());
    assert_eq!(
        row(table, "b"),
        [
            db(0.5),
            "1 / 2".into(),
            db(26.0),
            "0 / 1".into(),
            db(9.0),
            "1 / 3".into()
        ]
    );
    assert_eq!(row(table, "c"), ["n/a"; 6]);
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(stderr.contains("run `c` has no MSE measurement"), "{stderr}");
    Ok(())
}

#[test]
fn table_has_the_statistics_of_each_run() -> TestResult {
    let dir = scratch("table");
    // Run A: PSNR and mip deficit in summary.json (its CSV has no deficit).
    let a = frames(41, 1.0, 3, 0);
    let a_psnr = [31.5, 32.25, 36.0, 30.0];
    let a_deficit = [0.5, 1.75, 6.0, 0.0];
    write_run(
        &dir.join("a"),
        &csv(&a),
        &summary(&a, "adaptive", Some(a_psnr), Some(a_deficit)),
    );
    // Run B: psnr_db null and mip_deficit absent: both come from the CSV.
    let b = frames(30, 6.0, 4, 5);
    write_run(&dir.join("b"), &csv(&b), &summary(&b, "baseline", None, None));
    // Run C: nothing measured anywhere: n/a.
    let c = frames(10, 2.0, 0, 0);
    write_run(&dir.join("c"), &csv(&c), &summary(&c, "fixed", None, None));

    let out = dir.join("report");
    let run = |d: &str| dir.join(d).display().to_string();
    let (ra, rb, rc, ro) = (run("a"), run("b"), run("c"), out.display().to_string());
    let result = citystream(&[
        "report",
        "--run",
        &ra,
        "--run",
        &rb,
        "--run",
        &rc,
        "--name",
        "adaptive α=12",
        "--name",
        "baseline",
        "--name",
        "fixed",
        "--out",
        &ro,
    ]);
    assert!(
        result.status.success(),
        "report failed: {}",
        String::from_utf8_lossy(&result.stderr)
    );
    let table = std::fs::read_to_string(out.join("table.md"))?;

    let header = table.lines().find(|l| l.starts_with("| |")).expect("header row");
    assert!(header.contains("adaptive α=12 median | adaptive α=12 average | adaptive α=12 max"));
    let position = |name: &str| header.find(name).expect("run name in the header");
    assert!(position("adaptive α=12") < position("baseline"));

    let col = |rs: &[&[Frame]], pick: fn(&Frame) -> f64| -> Vec<String> {
        rs.iter()
            .flat_map(|r| fmt3(stats(&r.iter().map(pick).collect::<Vec<_>>())))
            .collect()
    };
    let all: [&[Frame]; 3] = [&a, &b, &c];
    assert_eq!(row(&table, "Frame latency (ms)"), col(&all, |f| f.dt_ms));
    assert_eq!(row(&table, "t_w latency (ms)"), col(&all, |f| f.tw_ms));
    let repeated = |v: [&str; 3]| -> Vec<String> { (0..3).flat_map(|_| v.map(String::from)).collect() };
    assert_eq!(
        row(&table, "Transfer rate (Mip/s)"),
        repeated(["8000.00", "9000.50", "20000.00"])
    );
    assert_eq!(
        row(&table, "Transfer rate (MB/s)"),
        repeated(["41.75", "42.25", "93.50"])
    );
    assert_eq!(row(&table, "Load size s (MB)"), repeated(["0.75", "0.50", "1.75"]));
    assert_eq!(row(&table, "Mipmap bias b"), repeated(["0.50", "1.25", "8.00"]));

    let measured = |r: &[Frame], pick: fn(&Frame) -> Option<f64>| stats(&r.iter().filter_map(pick).collect::<Vec<_>>());
    let na = ["n/a", "n/a", "n/a"].map(String::from).to_vec();
    let psnr = [fmt3(a_psnr), fmt3(measured(&b, |f| f.psnr_db)), na.clone()].concat();
    assert_eq!(row(&table, "PSNR per frame (dB)"), psnr);
    let deficit = [fmt3(a_deficit), fmt3(measured(&b, |f| f.mip_deficit)), na].concat();
    assert_eq!(row(&table, "Mip deficit"), deficit);

    // The stacked layout of the paper: a heading row per run, then its rows.
    let stacked: Vec<&str> = table
        .lines()
        .skip_while(|l| !l.starts_with("| **baseline** |"))
        .take(3)
        .collect();
    let expect_row = |label: &str, s: [f64; 4]| format!("| {label} | {} |", fmt3(s).join(" | "));
    assert_eq!(
        stacked[1],
        expect_row(
            "Frame latency (ms)",
            stats(&b.iter().map(|f| f.dt_ms).collect::<Vec<_>>())
        )
    );
    assert_eq!(
        stacked[2],
        expect_row(
            "t_w latency (ms)",
            stats(&b.iter().map(|f| f.tw_ms).collect::<Vec<_>>())
        )
    );

    // Run totals.
    let totals = row(&table, "baseline");
    // A summary without the budget keys (an older run) shows them as n/a.
    assert_eq!(
        totals[..12],
        ["baseline", "30", "12.50", "10.00", "n/a", "n/a", "321", "77", "50.00", "n/a", "n/a", "n/a"]
    );
    Ok(())
}

fn decode(path: &Path) -> image::RgbImage {
    image::open(path)
        .unwrap_or_else(|e| panic!("decoding {}: {e}", path.display()))
        .to_rgb8()
}

/// Pixels of exactly this colour.
fn count_of(img: &image::RgbImage, rgb: [u8; 3]) -> usize {
    img.pixels().filter(|p| p.0 == rgb).count()
}

#[test]
fn charts_decode_with_their_size_and_are_drawn() -> TestResult {
    let dir = scratch("charts");
    let a = frames(200, 1.0, 10, 20);
    write_run(
        &dir.join("fast run"),
        &csv(&a),
        &with_error(
            &summary(&a, "adaptive", Some([31.0, 32.0, 35.0, 30.0]), None),
            31.5,
            0,
            20,
        ),
    );
    let b = frames(200, 8.0, 10, 20);
    write_run(
        &dir.join("slow"),
        &csv(&b),
        &with_error(
            &summary(&b, "baseline", Some([28.0, 27.5, 33.0, 20.0]), None),
            25.0,
            0,
            20,
        ),
    );
    let out = dir.join("report");
    let result = citystream(&[
        "report",
        "--run",
        &dir.join("fast run").display().to_string(),
        "--run",
        &dir.join("slow").display().to_string(),
        "--out",
        &out.display().to_string(),
    ]);
    assert!(
        result.status.success(),
        "report failed: {}",
        String::from_utf8_lossy(&result.stderr)
    );

    for name in ["fast_run_fig6.png", "slow_fig6.png"] {
        let img = decode(&out.join(name));
        assert_eq!(img.dimensions(), (1600, 1000), "{name}");
        // The series in red (t_w, t_b, Mip/s) and blue (t_m, t_bu, s) are
        // drawn: far more pixels than their three 40-pixel legend samples.
        let (red, blue) = (count_of(&img, [214, 39, 40]), count_of(&img, [31, 119, 180]));
        assert!(red > 400, "{name}: {red} red pixels");
        assert!(blue > 400, "{name}: {blue} blue pixels");
        let white = count_of(&img, [255, 255, 255]) as f64 / (1600.0 * 1000.0);
        assert!(white < 0.98, "{name}: almost blank");
    }
    let img = decode(&out.join("speed_vs_error.png"));
    assert_eq!(img.dimensions(), (900, 600));
    // One filled dot (about 110 pixels) per run, in the first two palette
    // colours.
    assert!(count_of(&img, [214, 39, 40]) > 80);
    assert!(count_of(&img, [31, 119, 180]) > 80);
    Ok(())
}

fn report_error(dir: &Path) -> String {
    let result = citystream(&[
        "report",
        "--run",
        &dir.display().to_string(),
        "--out",
        &dir.join("report").display().to_string(),
    ]);
    assert!(
        !result.status.success(),
        "report accepted a bad run in {}",
        dir.display()
    );
    String::from_utf8_lossy(&result.stderr).into_owned()
}

#[test]
fn bad_inputs_are_named_with_file_and_line() -> TestResult {
    let dir = scratch("errors");
    let f = frames(5, 1.0, 0, 0);
    let good_csv = csv(&f);
    let good_summary = summary(&f, "adaptive", None, None);

    // Truncated last row (line 6: header + 5 rows).
    let truncated = &good_csv[..good_csv.len() - 20];
    write_run(&dir.join("truncated"), truncated, &good_summary);
    let err = report_error(&dir.join("truncated"));
    assert!(err.contains("frames.csv: line 6:"), "{err}");
    assert!(err.contains("fields"), "{err}");

    // A cell that is not a number, on line 3.
    let bad: String = good_csv
        .lines()
        .enumerate()
        .map(|(i, l)| {
            if i == 2 {
                let mut cells: Vec<&str> = l.split(',').collect();
                cells[3] = "fast";
                cells.join(",") + "\n"
            } else {
                format!("{l}\n")
            }
        })
        .collect();
    write_run(&dir.join("not_a_number"), &bad, &good_summary);
    let err = report_error(&dir.join("not_a_number"));
    assert!(err.contains("frames.csv: line 3: column `tw_ms` = \"fast\""), "{err}");

    // The optional columns (`mse`, `reads_in_flight_bytes`) with a bad cell on line 3.
    let with_optional = |mse: &str, in_flight: &str| -> String {
        good_csv
            .lines()
            .enumerate()
            .map(|(i, l)| match i {
                0 => format!("{l},mse,reads_in_flight_bytes\n"),
                2 => format!("{l},{mse},{in_flight}\n"),
                _ => format!("{l},,\n"),
            })
            .collect()
    };
    write_run(&dir.join("bad_mse"), &with_optional("fast", "0"), &good_summary);
    let err = report_error(&dir.join("bad_mse"));
    assert!(
        err.contains("frames.csv: line 3: column `mse` = \"fast\": not a number"),
        "{err}"
    );
    write_run(&dir.join("bad_in_flight"), &with_optional("", "-1"), &good_summary);
    let err = report_error(&dir.join("bad_in_flight"));
    assert!(
        err.contains("frames.csv: line 3: column `reads_in_flight_bytes` = \"-1\": not a non-negative integer"),
        "{err}"
    );

    // A header without a required column.
    write_run(
        &dir.join("header"),
        &good_csv.replacen("psnr_db", "psnr", 1),
        &good_summary,
    );
    let err = report_error(&dir.join("header"));
    assert!(
        err.contains("frames.csv: line 1: header lacks the column `psnr_db`"),
        "{err}"
    );

    // Header only.
    write_run(&dir.join("empty"), &format!("{HEADER}\n"), &good_summary);
    let err = report_error(&dir.join("empty"));
    assert!(err.contains("frames.csv: no frame rows"), "{err}");

    // summary.json missing a key, cut short, or missing altogether.
    write_run(
        &dir.join("no_key"),
        &good_csv,
        &good_summary.replacen("\"tw_ms\"", "\"tw\"", 1),
    );
    let err = report_error(&dir.join("no_key"));
    assert!(err.contains("summary.json") && err.contains("tw_ms"), "{err}");
    write_run(&dir.join("cut"), &good_csv, &good_summary[..good_summary.len() / 2]);
    let err = report_error(&dir.join("cut"));
    assert!(err.contains("summary.json") && err.contains("line"), "{err}");
    std::fs::create_dir_all(dir.join("missing"))?;
    let err = report_error(&dir.join("missing"));
    assert!(err.contains("summary.json"), "{err}");

    // --name count must match --run count.
    write_run(&dir.join("ok"), &good_csv, &good_summary);
    let ok = dir.join("ok").display().to_string();
    let result = citystream(&["report", "--run", &ok, "--run", &ok, "--name", "x", "--out", &ok]);
    assert!(!result.status.success());
    assert!(String::from_utf8_lossy(&result.stderr).contains("one name per run"));
    // Two runs whose names would share chart files.
    let report = dir.join("dup").display().to_string();
    let result = citystream(&["report", "--run", &ok, "--run", &ok, "--out", &report]);
    assert!(!result.status.success());
    assert!(String::from_utf8_lossy(&result.stderr).contains("two runs are named `ok`"));
    Ok(())
}

/// A stand-in flythrough: logs its arguments, one line per run, and writes
/// a summary and frames whose latency depends on the policy and α.
#[cfg(unix)]
fn fake_flythrough(dir: &Path, fail_policy: &str) -> (PathBuf, PathBuf) {
    use std::os::unix::fs::PermissionsExt;
    let log = dir.join("args.log");
    let script = dir.join("fake-flythrough.sh");
    let text = format!(
        r#"#!/bin/sh
echo "$*" >> '{log}'
out=""; policy=""; alpha=16; frames=20
while [ $# -gt 0 ]; do
  case "$1" in
    --out) out="$2"; shift ;;
    --policy) policy="$2"; shift ;;
    --alpha) alpha="$2"; shift ;;
    --frames) frames="$2"; shift ;;
  esac
  shift
done
[ "$policy" = "{fail_policy}" ] && {{ echo "simulated failure" >&2; exit 3; }}
case "$policy" in
  baseline) ms=40 ;;
  adaptive) ms=$alpha ;;
  *) ms=20 ;;
esac
mkdir -p "$out"
st() {{ echo "{{\"median\": $1, \"mean\": $1, \"max\": $1, \"min\": $1}}"; }}
cat > "$out/summary.json" <<EOF
{{"frame_ms": $(st $ms), "tw_ms": $(st $((ms + 1))), "mips_per_s": $(st 100),
 "mb_per_s": $(st 5), "load_size_mb": $(st 1), "mip_bias": $(st 0), "psnr_db": $(st $((60 - ms))),
 "psnr_of_mean_mse_db": $((60 - ms)), "error_frames": {{"measured": $frames, "identical": 0}},
 "startup_psnr_of_mean_mse_db": 20, "startup_error_frames": {{"measured": 1, "identical": 0}},
 "streaming_psnr_of_mean_mse_db": $((60 - ms)), "streaming_error_frames": {{"measured": $((frames - 1)), "identical": 0}},
 "mip_deficit": null, "frames": $frames, "duration_s": 1, "policy": "$policy",
 "bytes_streamed": 1048576, "mips_streamed": 10, "blocks_bound": 16, "peak_resident_bytes": 2097152}}
EOF
echo "{HEADER}" > "$out/frames.csv"
i=0
while [ $i -lt $frames ]; do
  echo "$i,$i,$ms,$((ms + 1)),$ms,$ms,$ms,$ms,1,0,1,65536,1,1048576,,$((60 - ms))" >> "$out/frames.csv"
  i=$((i + 1))
done
echo "fake flythrough $policy done"
"#,
        log = log.display()
    );
    std::fs::write(&script, text).expect("writing the fake flythrough");
    std::fs::set_permissions(&script, std::fs::Permissions::from_mode(0o755))
        .expect("making the fake flythrough executable");
    (script, log)
}

#[cfg(unix)]
#[test]
fn bench_runs_every_policy_and_reports() -> TestResult {
    let dir = scratch("bench");
    let (script, log) = fake_flythrough(&dir, "none");
    let dataset = dir.join("city");
    std::fs::create_dir_all(&dataset)?;
    let out = dir.join("out");
    let (d, o, s) = (
        dataset.display().to_string(),
        out.display().to_string(),
        script.display().to_string(),
    );
    let result = citystream(&[
        "bench",
        "--dataset",
        &d,
        "--out",
        &o,
        "--frames",
        "7",
        "--flythrough",
        &s,
        "--",
        "--path",
        "standard",
    ]);
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(result.status.success(), "bench failed: {stderr}");
    assert!(
        stderr.contains("[1/4] baseline") && stderr.contains("[4/4] fixed s=4 MB b=0"),
        "{stderr}"
    );
    assert!(
        stderr.contains(
            "7 frames, frame latency mean 12.00 / max 12.00 ms, 5.00 MB/s mean, PSNR of mean MSE 48.00 dB \
             (0 of 7 measured frames identical)"
        ),
        "{stderr}"
    );

    let logged = std::fs::read_to_string(&log)?;
    let lines: Vec<&str> = logged.lines().collect();
    let tail = |name: &str| format!("--clock fixed --bind-latency desktop --frames 7 --out {o}/{name} --path standard");
    let expected = [
        format!("--dataset {d} --policy baseline {}", tail("baseline")),
        format!("--dataset {d} --policy adaptive --alpha 12 {}", tail("adaptive-a12")),
        format!("--dataset {d} --policy adaptive --alpha 16 {}", tail("adaptive-a16")),
        format!(
            "--dataset {d} --policy fixed --load-size-mb 4 --mip-bias 0 {}",
            tail("fixed-s4-b0")
        ),
    ];
    assert_eq!(lines, expected);

    let table = std::fs::read_to_string(out.join("table.md"))?;
    // Frame latency per run as the fake wrote it: 40, 12, 16, 20 ms.
    let latency: Vec<String> = [40.0, 12.0, 16.0, 20.0]
        .iter()
        .flat_map(|&ms: &f64| fmt3([ms; 4]))
        .collect();
    assert_eq!(row(&table, "Frame latency (ms)"), latency);
    let psnr: Vec<String> = [20.0, 48.0, 44.0, 40.0]
        .iter()
        .flat_map(|&p: &f64| fmt3([p; 4]))
        .collect();
    assert_eq!(row(&table, "PSNR per frame (dB)"), psnr);
    assert_eq!(row(&table, "fixed s=4 MB b=0")[..3], ["fixed", "7", "1.00"]);
    for chart in [
        "baseline_fig6.png",
        "adaptive_12_ms_fig6.png",
        "adaptive_16_ms_fig6.png",
        "fixed_s_4_MB_b_0_fig6.png",
        "speed_vs_error.png",
    ] {
        assert!(out.join(chart).is_file(), "missing {chart}");
    }
    Ok(())
}

#[cfg(unix)]
#[test]
fn bench_stops_at_a_failing_run() -> TestResult {
    let dir = scratch("bench_fail");
    let (script, log) = fake_flythrough(&dir, "adaptive");
    let out = dir.join("out");
    let result = citystream(&[
        "bench",
        "--dataset",
        &dir.display().to_string(),
        "--out",
        &out.display().to_string(),
        "--flythrough",
        &script.display().to_string(),
    ]);
    assert!(!result.status.success());
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(stderr.contains("flythrough run `adaptive α=12 ms` failed"), "{stderr}");
    // Baseline ran, the first adaptive run failed, nothing after it ran.
    assert_eq!(std::fs::read_to_string(&log)?.lines().count(), 2);
    assert!(!out.join("table.md").exists());

    let missing = citystream(&[
        "bench",
        "--dataset",
        &dir.display().to_string(),
        "--out",
        &out.display().to_string(),
        "--flythrough",
        &dir.join("no-such-binary").display().to_string(),
    ]);
    assert!(!missing.status.success());
    assert!(String::from_utf8_lossy(&missing.stderr).contains("flythrough binary not found"));
    Ok(())
}

/// A bench re-run into an earlier `--out` that fails leaves the earlier results as they
/// were: every run's directory (summary, frames, command) and the report, which still
/// reads them.
#[cfg(unix)]
#[test]
fn a_failed_bench_rerun_leaves_the_earlier_results_intact() -> TestResult {
    let dir = scratch("bench_rerun_fails");
    let out = dir.join("out");
    let bench = |script: &Path, frames: &str| {
        citystream(&[
            "bench",
            "--dataset",
            &dir.display().to_string(),
            "--out",
            &out.display().to_string(),
            "--frames",
            frames,
            "--flythrough",
            &script.display().to_string(),
        ])
    };
    let (good, _) = fake_flythrough(&dir, "none");
    let first = bench(&good, "7");
    assert!(first.status.success(), "{}", String::from_utf8_lossy(&first.stderr));
    let files = [
        "table.md",
        "baseline/summary.json",
        "baseline/bench-command.txt",
        "baseline/frames.csv",
    ];
    let before: Vec<Vec<u8>> = files
        .iter()
        .map(|f| std::fs::read(out.join(f)))
        .collect::<Result<_, _>>()?;
    // Another bench (more frames) whose second run fails: its first run has finished by then.
    let failing_dir = dir.join("failing");
    std::fs::create_dir_all(&failing_dir)?;
    let (failing, _) = fake_flythrough(&failing_dir, "adaptive");
    let second = bench(&failing, "9");
    assert!(!second.status.success(), "the re-run should fail");
    let after: Vec<Vec<u8>> = files
        .iter()
        .map(|f| std::fs::read(out.join(f)))
        .collect::<Result<_, _>>()?;
    for ((file, b), a) in files.iter().zip(&before).zip(&after) {
        assert!(b == a, "{file} changed by the failed re-run");
    }
    assert!(!out.join(".bench-previous").exists());
    let report = citystream(&[
        "report",
        "--run",
        &out.join("baseline").display().to_string(),
        "--out",
        &dir.join("report").display().to_string(),
    ]);
    assert!(report.status.success(), "{}", String::from_utf8_lossy(&report.stderr));
    Ok(())
}

/// `citystream bench --scenario SCENARIO --budget-mb 8` on an empty dataset directory in
/// scratch `name`, with the fake flythrough: the dataset, the output directory, what the
/// bench printed on standard error (it must succeed) and the flythrough lines it ran.
#[cfg(unix)]
fn fake_bench(name: &str, scenario: &str) -> (String, String, String, Vec<String>) {
    let dir = scratch(name);
    let (script, log) = fake_flythrough(&dir, "none");
    let dataset = dir.join("city");
    std::fs::create_dir_all(&dataset).expect("creating the dataset directory");
    let out = dir.join("out");
    let (d, o) = (dataset.display().to_string(), out.display().to_string());
    let result = citystream(&[
        "bench",
        "--scenario",
        scenario,
        "--dataset",
        &d,
        "--out",
        &o,
        "--budget-mb",
        "8",
        "--flythrough",
        &script.display().to_string(),
    ]);
    let stderr = String::from_utf8_lossy(&result.stderr).into_owned();
    assert!(result.status.success(), "bench failed: {stderr}");
    let logged = std::fs::read_to_string(&log).expect("the fake flythrough's log");
    (d, o, stderr, logged.lines().map(str::to_owned).collect())
}

#[cfg(unix)]
#[test]
fn pressure_bench_runs_the_policies_under_the_budget_then_ring_and_unbudgeted() -> TestResult {
    let (d, o, _, lines) = fake_bench("bench-pressure", "pressure");
    let out = Path::new(&o);
    let shared = "--psnr-interval 60 --frame-interval 0";
    // 30 s of the path at 1080p, the camera moving with the modelled latency.
    let tail = |name: &str| {
        format!("--clock modelled --bind-latency desktop --duration-s 30 --width 1920 --height 1080 --out {o}/{name}")
    };
    let expected = [
        format!(
            "--dataset {d} --policy baseline {shared} --memory-budget-mb 8 {}",
            tail("baseline")
        ),
        format!(
            "--dataset {d} --policy adaptive --alpha 12 {shared} --memory-budget-mb 8 {}",
            tail("adaptive-a12")
        ),
        format!(
            "--dataset {d} --policy adaptive --alpha 16 {shared} --memory-budget-mb 8 {}",
            tail("adaptive-a16")
        ),
        format!(
            "--dataset {d} --policy fixed --load-size-mb 4 --mip-bias 0 {shared} --memory-budget-mb 8 {}",
            tail("fixed-s4-b0")
        ),
        format!(
            "--dataset {d} --policy adaptive --alpha 12 {shared} --memory-budget-mb 8 --eviction ring {}",
            tail("adaptive-a12-ring")
        ),
        format!(
            "--dataset {d} --policy adaptive --alpha 12 {shared} --memory-budget-mb unlimited {}",
            tail("unbudgeted-a12")
        ),
    ];
    assert_eq!(lines, expected);
    let checks = std::fs::read_to_string(out.join("pressure.md"))?;
    // The fake's adaptive α=12 frame latency is 12 ms against the baseline's 40.
    assert!(
        checks.contains("| Max frame latency, adaptive / baseline | 0.300 | ≤ 0.05 | no |"),
        "{checks}"
    );
    // Both streamed at PSNR 60 − ms: 48 against 48 for the unbudgeted α=12 run.
    assert!(
        checks.contains("| PSNR of mean MSE after start-up: unbudgeted − adaptive α=12 (dB) | 0.000 | ≤ 3 | yes |"),
        "{checks}"
    );
    // The fake writes no unique bytes: not measured, not a pass.
    assert!(
        checks.contains("| Bytes streamed / unique bytes, adaptive α=12 | n/a | ≤ 2 | n/a |"),
        "{checks}"
    );
    Ok(())
}

#[cfg(unix)]
#[test]
fn berlin_bench_flies_table_3s_policies_on_a_68_6_s_path_beside_the_papers_rows() -> TestResult {
    let dir = scratch("bench-berlin");
    let (script, log) = fake_flythrough(&dir, "none");
    // Any dataset in DATA/berlin is taken as it is (the real one takes 40 minutes to build).
    let data = dir.join("data");
    let city = data.join("berlin");
    let generated = citystream(&["gen", "--preset", "tiny", "--out", &city.display().to_string()]);
    assert!(
        generated.status.success(),
        "{}",
        String::from_utf8_lossy(&generated.stderr)
    );
    let out = dir.join("out");
    let (c, o) = (city.display().to_string(), out.display().to_string());
    let (data_dir, fake) = (data.display().to_string(), script.display().to_string());
    let bench = |runs: &[&str]| {
        let mut command = vec![
            "bench",
            "--scenario",
            "berlin",
            "--data-dir",
            &data_dir,
            "--out",
            &o,
            "--flythrough",
            &fake,
        ];
        command.extend_from_slice(runs);
        let result = citystream(&command);
        let stderr = String::from_utf8_lossy(&result.stderr).to_string();
        assert!(result.status.success(), "bench failed: {stderr}");
        stderr
    };
    // Two runs first: the table has the others as not run.
    bench(&["--runs", "baseline,adaptive-a12"]);
    let table = std::fs::read_to_string(out.join("berlin.md"))?;
    assert!(table.contains("| adaptive α=16 ms | desktop | not run |"), "{table}");
    assert!(
        table.contains("| baseline, h200-linux | h200-linux | not run |"),
        "{table}"
    );
    assert!(
        table.contains("| Mean frame latency, adaptive α=12 / baseline (paper 0.125) | 0.300 | ≤ 0.35 | yes |"),
        "{table}"
    );
    // The frontier's targets wait for the predictive run.
    assert!(
        table.contains("| predictive α=12 + path: worst frame (ms) | n/a |"),
        "{table}"
    );
    // Then all of them: the two that finished with the same command are kept.
    let stderr = bench(&[]);
    assert!(
        stderr.contains("baseline: kept, finished earlier with the same command"),
        "{stderr}"
    );
    let unknown = citystream(&[
        "bench",
        "--scenario",
        "berlin",
        "--data-dir",
        &data_dir,
        "--out",
        &o,
        "--runs",
        "adaptive-a13",
    ]);
    assert!(!unknown.status.success());
    assert!(
        String::from_utf8_lossy(&unknown.stderr).contains("no run `adaptive-a13`"),
        "{}",
        String::from_utf8_lossy(&unknown.stderr)
    );
    let logged = std::fs::read_to_string(&log)?;
    let lines: Vec<&str> = logged.lines().collect();
    // Every run reads on the paper's SSD and renders the paper's frame; the bind model is
    // the paper's driver unless the run names another.
    let shared = format!(
        "--memory-budget-mb 1024 --path {o}/path.json --psnr-interval 60 --frame-interval 0 \
         --disk-model 970evo --render-ms 4.5"
    );
    let size = "--width 3840 --height 2160";
    let desktop = |args: &str, name: &str| {
        format!("--dataset {c} {args} {shared} --clock modelled --bind-latency desktop {size} --out {o}/{name}")
    };
    let h200 = |args: &str, name: &str| {
        format!("--dataset {c} {args} --bind-latency h200-linux {shared} --clock modelled {size} --out {o}/{name}")
    };
    let expected = [
        desktop("--policy baseline", "baseline"),
        desktop("--policy adaptive --alpha 12 --beta 8", "adaptive-a12"),
        desktop("--policy fixed --load-size-mb 64 --mip-bias 0", "fixed-s64"),
        desktop("--policy fixed --load-size-mb 4 --mip-bias 0", "fixed-s4"),
        desktop("--policy adaptive --alpha 16 --beta 8", "adaptive-a16"),
        desktop(
            "--policy adaptive --controller headroom --alpha 12 --beta 8",
            "headroom-a12",
        ),
        desktop(
            "--policy adaptive --controller predictive --alpha 12 --beta 8 --prefetch path",
            "predictive-a12-path",
        ),
        h200("--policy baseline", "h200-baseline"),
        h200("--policy adaptive --alpha 12 --beta 8", "h200-adaptive-a12"),
    ];
    assert_eq!(lines, expected);
    // The path: the city's standard path, as long as the paper's Berlin benchmark.
    let path: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("path.json"))?)?;
    let last = path["keyframes"]
        .as_array()
        .and_then(|k| k.last())
        .and_then(|k| k["t"].as_f64())
        .expect("keyframe times");
    assert!((last - 68.6).abs() < 1e-9, "path ends at {last} s");
    let table = std::fs::read_to_string(out.join("berlin.md"))?;
    // Each run beside the paper's row; the fake's baseline runs at 40 ms, α at α ms.
    assert!(
        table.contains("| baseline | desktop | 20 | 40.00 | 40.00 | 40.00 | 1.00 |"),
        "{table}"
    );
    assert!(table.contains("| 6.8 / 42.5 / 471.16 | 79.95 | 9628 |"), "{table}");
    assert!(table.contains("| adaptive α=16 ms | desktop | 20 | 16.00 |"), "{table}");
    assert!(table.contains("| headroom α=12 ms | desktop | 20 | 12.00 |"), "{table}");
    assert!(
        table.contains("| baseline, h200-linux | h200-linux | 20 | 40.00 |"),
        "{table}"
    );
    assert!(
        table.contains("| Mean frame latency, headroom α=12 / baseline | 0.300 | ≤ 0.35 | yes |"),
        "{table}"
    );
    assert!(
        table.contains(
            "| Baseline: mean / median frame latency (it stalls throughout; paper 6.25) | 1.000 | ≥ 2 | no |"
        ),
        "{table}"
    );
    assert!(
        table.contains("| Mean frame latency, adaptive α=12 / baseline (paper 0.125) | 0.300 | ≤ 0.35 | yes |"),
        "{table}"
    );
    // The fake loads 64 KiB a frame in one block, under its 1 MB load size; its frames.csv
    // has no cycle columns.
    assert!(
        table.contains("| baseline | n/a | n/a | n/a | n/a | 0.06 / 0.06 | 1.0 / 1 | 0 | 0.0 % |"),
        "{table}"
    );
    // The frontier's targets: the fake's predictive run (12 ms, 48 dB) against its baseline
    // (40 ms, 20 dB), fixed 4 MB (20 ms, 40 dB) and paper's α = 12 (12 ms, 48 dB): the paper's
    // run is as fast and as good, so the last target is not met.
    for row in [
        "| predictive α=12 + path: worst frame (ms) | 12.000 | ≤ 24 | yes |",
        "| predictive α=12 + path: frames over 2α after the first second | 0.000 | 0 | yes |",
        "| predictive α=12 + path: after-start-up PSNR − baseline's (dB) | 28.000 | ≥ 0 | yes |",
        "| predictive α=12 + path: MB per path s / baseline's | 1.000 | ≤ 1.2 | yes |",
        "(2 of 2 flown) | 1.000 | 0 | no |",
    ] {
        assert!(table.contains(row), "{row} in {table}");
    }
    assert!(out.join("table.md").is_file(), "the report of every run");
    // Another scenario into the same folder would replace table.md and the charts.
    let table_before = std::fs::read(out.join("table.md"))?;
    let other = citystream(&[
        "bench",
        "--scenario",
        "strategies",
        "--dataset",
        &c,
        "--out",
        &o,
        "--flythrough",
        &fake,
    ]);
    assert!(
        !other.status.success(),
        "a strategies bench ran into a Berlin bench's folder"
    );
    assert!(
        String::from_utf8_lossy(&other.stderr).contains("holds the results of `bench --scenario berlin`"),
        "{}",
        String::from_utf8_lossy(&other.stderr)
    );
    assert_eq!(std::fs::read(out.join("table.md"))?, table_before, "table.md replaced");
    Ok(())
}

#[cfg(unix)]
#[test]
fn controllers_bench_flies_both_controllers_and_the_baseline_on_both_benchmarks() -> TestResult {
    let dir = scratch("bench-controllers");
    let (script, log) = fake_flythrough(&dir, "none");
    let city = dir.join("city");
    std::fs::create_dir_all(&city)?;
    // The pressure city: any dataset in DATA/large-atlas is taken as it is.
    let data = dir.join("data");
    let pressure_city = data.join("large-atlas");
    let generated = citystream(&["gen", "--preset", "tiny", "--out", &pressure_city.display().to_string()]);
    assert!(
        generated.status.success(),
        "{}",
        String::from_utf8_lossy(&generated.stderr)
    );
    let out = dir.join("out");
    let (c, p, o) = (
        city.display().to_string(),
        pressure_city.display().to_string(),
        out.display().to_string(),
    );
    let result = citystream(&[
        "bench",
        "--scenario",
        "controllers",
        "--dataset",
        &c,
        "--data-dir",
        &data.display().to_string(),
        "--out",
        &o,
        "--flythrough",
        &script.display().to_string(),
    ]);
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(result.status.success(), "bench failed: {stderr}");
    let logged = std::fs::read_to_string(&log)?;
    let lines: Vec<&str> = logged.lines().collect();
    let policies = [
        ("baseline", "--policy baseline"),
        ("paper-a12", "--policy adaptive --controller paper --alpha 12"),
        ("headroom-a12", "--policy adaptive --controller headroom --alpha 12"),
    ];
    let mut expected: Vec<String> = policies
        .iter()
        .map(|(name, args)| {
            format!("--dataset {c} {args} --clock fixed --bind-latency desktop --out {o}/default/{name}")
        })
        .collect();
    expected.extend(policies.iter().map(|(name, args)| {
        format!(
            "--dataset {p} {args} --psnr-interval 60 --frame-interval 0 --memory-budget-mb 256 --clock modelled \
             --bind-latency desktop --duration-s 30 --width 1920 --height 1080 --out {o}/pressure/{name}"
        )
    }));
    assert_eq!(lines, expected);
    for report in ["default/table.md", "pressure/table.md", "speed_vs_error.png"] {
        assert!(out.join(report).is_file(), "{report} not written");
    }
    let checks = std::fs::read_to_string(out.join("controllers.md"))?;
    // The fake renders both controllers at 12 ms (its α) and PSNR 48 dB, the baseline at
    // 40 ms and 20 dB, every frame.
    for row in [
        "| pressure: worst frame, headroom / baseline | 0.300 | ≤ 0.05 | no |",
        "| pressure: frames over 2α after the first second, headroom − paper (paper: 0) | 0.000 | ≤ 0 | yes |",
        "| pressure: mean PSNR, baseline − headroom (dB) | -28.000 | ≤ 1.5 | yes |",
        "| pressure: PSNR of mean MSE after start-up, baseline − headroom (dB) | -28.000 | — | — |",
        "| pressure: PSNR of mean MSE after start-up, baseline − paper (dB) | -28.000 | — | — |",
        "| pressure: MB/s mean, headroom / baseline | 1.000 | ≥ 0.5 | yes |",
        "| default city: worst frame, headroom − paper (ms) | 0.000 | ≤ 0 | yes |",
        "| default city: mean PSNR, headroom − paper (dB) | 0.000 | ≥ 0 | yes |",
    ] {
        assert!(checks.contains(row), "{row} missing from:\n{checks}");
    }
    Ok(())
}

#[test]
fn loader_bench_reads_the_same_mips_as_raw_reads() -> TestResult {
    let dir = scratch("bench-loader");
    let city = dir.join("city");
    let out = dir.join("out");
    let generated = citystream(&[
        "gen",
        "--preset",
        "tiny",
        "--out",
        &city.display().to_string(),
        "--quiet",
    ]);
    assert!(
        generated.status.success(),
        "{}",
        String::from_utf8_lossy(&generated.stderr)
    );
    let result = citystream(&[
        "bench",
        "--scenario",
        "loader",
        "--dataset",
        &city.display().to_string(),
        "--out",
        &out.display().to_string(),
    ]);
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(result.status.success(), "loader bench failed: {stderr}");
    let passes: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("loader.json"))?)?;
    let passes = passes.as_array().expect("an array of passes");
    assert!(passes.len() >= 6, "warm passes missing: {passes:?}");
    let first = &passes[0];
    for pass in passes {
        assert_eq!(pass["mips"], first["mips"], "every pass reads the same mips");
        assert_eq!(pass["bytes"], first["bytes"], "every pass reads the same bytes");
        assert!(pass["mb_per_s"].as_f64().is_some_and(|v| v.is_finite() && v > 0.0));
    }
    assert!(first["mips"].as_u64().is_some_and(|m| m > 0));
    let md = std::fs::read_to_string(out.join("loader.md"))?;
    assert!(md.contains("| warm | off |") && md.contains("| warm | on |"), "{md}");
    Ok(())
}

/// `--scenario strategies` on a dataset that is no atlas tree: the feedback run and both
/// texture-array runs (fully resident without a budget, streamed under it), no tree run,
/// and their rows in strategies.md.
#[cfg(unix)]
#[test]
fn strategies_bench_runs_texture_arrays_resident_and_streamed() -> TestResult {
    let (d, o, stderr, lines) = fake_bench("bench-strategies", "strategies");
    let out = Path::new(&o);
    assert!(stderr.contains("no atlas-tree run"), "{stderr}");
    let shared = format!("--dataset {d} --policy adaptive --alpha 16 --psnr-interval 30 --frame-interval 0");
    let tail = |name: &str| format!("--clock modelled --bind-latency desktop --out {o}/{name}");
    let expected = [
        format!("{shared} --memory-budget-mb 8 --strategy feedback {}", tail("feedback")),
        format!("{shared} --strategy texture-arrays {}", tail("texture-arrays")),
        format!(
            "{shared} --memory-budget-mb 8 --strategy texture-arrays {}",
            tail("texture-arrays-streamed")
        ),
    ];
    assert_eq!(lines, expected);
    let table = std::fs::read_to_string(out.join("strategies.md"))?;
    for row in ["| feedback |", "| texture-arrays |", "| texture-arrays-streamed |"] {
        assert!(table.contains(row), "{row} missing: {table}");
    }
    assert!(!table.contains("| atlas-tree |"), "{table}");
    Ok(())
}
