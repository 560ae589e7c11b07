//! The predictive controller, the error-per-byte order and the prefetch pass in a flight:
//! reproducible, validated, charged in the modelled frame, and refused where they do not
//! apply.

use std::process::Output;

mod flight_support;
use flight_support::{column, default_city, fly_flythrough};

/// The default city's standard path made 18 s long (the shortest), its first cut at
/// about 4 s; the file and the cut times.
fn short_path() -> (std::path::PathBuf, Vec<f64>) {
    let dataset = citystream_dataset::Dataset::open(default_city()).expect("default city opens");
    let path = citystream_streaming::bench::path::standard_path(&dataset.scene, 18.0).expect("standard path");
    let file = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("prefetch-path.json");
    path.save(&file).expect("path written");
    (file, path.jumps())
}

/// 300 modelled frames (5 s or more of the path) of the default city along [`short_path`]
/// at 160×120 with validation, `extra` after; its output, summary.json and frames.csv.
fn fly(name: &str, extra: &[&str]) -> (Output, serde_json::Value, String) {
    let out = std::path::Path::new(env!("CARGO_TARGET_TMPDIR"))
        .join("prefetch")
        .join(name);
    let (path, _) = short_path();
    let path = path.to_str().expect("utf-8 path");
    let mut args = vec!["--width", "160", "--height", "120", "--frames", "300", "--path", path];
    args.extend([
        "--clock",
        "modelled",
        "--bind-latency",
        "desktop",
        "--memory-budget-mb",
        "32",
    ]);
    args.extend(["--frame-interval", "0", "--psnr-interval", "30", "--validation=true"]);
    args.extend(extra);
    fly_flythrough(&args, &default_city(), &out)
}

#[test]
fn path_prefetch_flights_are_reproducible_validated_and_charged() {
    let args = [
        "--policy",
        "predictive",
        "--alpha",
        "12",
        "--prefetch",
        "path",
        "--prefetch-lead-s",
        "0.5",
        "--prefetch-cost-ms",
        "3",
    ];
    let (output, summary, first) = fly("path-a", &args);
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    assert_eq!(summary["validation_errors"], 0, "{summary}");
    assert_eq!(summary["policy"], "predictive");
    assert_eq!(summary["priority"], "weight");
    assert_eq!(summary["prefetch"], "path");
    assert_eq!(summary["prefetch_lead_s"], 0.5);
    assert_eq!(summary["prefetch_cost_ms"], 3.0);
    // The pass is recorded on every frame of the half second before each cut of the path,
    // from the view after it; between cuts, where the pose half a second ahead sees beyond
    // the view's margin, at most once per eighth of a second (a quarter of the lead).
    let (_, cuts) = short_path();
    let (passes, times) = (column(&first, "prefetch_pass"), column(&first, "time_s"));
    let recorded = passes.iter().filter(|&&p| p == 1.0).count();
    assert_eq!(summary["prefetch_frames"].as_u64(), Some(recorded as u64), "{summary}");
    assert!(recorded > 0, "no frame recorded the prefetch pass");
    let mut between_cuts = Vec::new();
    for (&pass, &t) in passes.iter().zip(&times) {
        // frames.csv has time_s to 0.1 ms.
        let before_a_cut = cuts.iter().any(|&cut| cut > t + 1e-4 && cut <= t + 0.5 - 1e-4);
        let near_a_cut = cuts
            .iter()
            .any(|&cut| (cut - t).abs() < 1e-4 || (cut - t - 0.5).abs() < 1e-4);
        if before_a_cut && !near_a_cut {
            assert_eq!(pass, 1.0, "frame at {t} s before a cut, cuts at {cuts:?}");
        } else if !near_a_cut && pass == 1.0 {
            between_cuts.push(t);
        }
    }
    assert!(!between_cuts.is_empty(), "the path's turns need no pass?");
    assert!(
        between_cuts.windows(2).all(|w| w[1] - w[0] >= 0.125 - 2e-4),
        "passes between cuts closer than a quarter of the lead: {between_cuts:?}"
    );
    assert!(summary["prefetched_mips"].as_u64().is_some_and(|m| m > 0), "{summary}");
    // Two runs of the same options: the same frames, byte for byte.
    let (output, _, second) = fly("path-b", &args);
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    assert_eq!(
        first, second,
        "two runs of the same options must give the same frames.csv"
    );
    // A frame with the pass pays for it: the cheapest one that uploads nothing costs the
    // render and the pass (8 + 3 ms), without the pass the render alone (a frame that
    // uploads nothing may still unbind).
    let (dts, bytes) = (column(&first, "dt_ms"), column(&first, "bytes"));
    for pass in [1.0, 0.0] {
        let cheapest = (0..dts.len())
            .filter(|&i| passes[i] == pass && bytes[i] == 0.0)
            .map(|i| dts[i])
            .fold(f64::INFINITY, f64::min);
        let expected = 8.0 + 3.0 * pass;
        assert!(
            (cheapest - expected).abs() < 1e-9,
            "pass = {pass}: the cheapest quiet frame took {cheapest} ms"
        );
        let all = (0..dts.len()).filter(|&i| passes[i] == pass).map(|i| dts[i]);
        assert!(
            all.clone().all(|dt| dt >= expected - 1e-9),
            "pass = {pass}: a frame under {expected} ms"
        );
    }
    let (output, summary, without) = fly("none", &args[..4]);
    assert!(column(&without, "prefetch_pass").iter().all(|&p| p == 0.0));
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    assert_eq!(
        (summary["prefetch"].as_str(), summary["prefetch_frames"].as_u64()),
        (Some("none"), Some(0))
    );
    assert_eq!(summary["prefetched_mips"], 0);
    let quiet = column(&without, "dt_ms").into_iter().fold(f64::INFINITY, f64::min);
    assert!((quiet - 8.0).abs() < 1e-9, "the cheapest frame took {quiet} ms");
}

#[test]
fn motion_prefetch_extrapolates_and_the_orders_are_options() {
    let (output, summary, _) = fly(
        "motion",
        &[
            "--policy",
            "adaptive",
            "--controller",
            "paper",
            "--prefetch",
            "motion",
            "--prefetch-lead-s",
            "2",
            "--priority",
            "error-per-byte",
        ],
    );
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    assert_eq!(summary["validation_errors"], 0, "{summary}");
    assert_eq!(
        (summary["policy"].as_str(), summary["priority"].as_str()),
        (Some("adaptive"), Some("error-per-byte"))
    );
    // The first two frames have no motion to extrapolate; the others may see beyond the
    // view's margin.
    let frames = summary["prefetch_frames"].as_u64().expect("prefetch_frames");
    assert!((1..=298).contains(&frames), "{frames} frames prefetched");
    // The paper's order by default.
    let (output, summary, _) = fly("paper-order", &["--policy", "adaptive"]);
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    assert_eq!(summary["priority"], "weight");
}

#[test]
fn prefetch_and_predictive_options_are_refused_clearly() {
    for (args, says) in [
        (&["--prefetch", "sideways"][..], "sideways"),
        (&["--prefetch", "path", "--prefetch-lead-s", "0"][..], "lead time"),
        (&["--prefetch", "path", "--prefetch-lead-s", "nan"][..], "lead time"),
        (&["--priority", "random"][..], "random"),
        (
            &["--policy", "fixed", "--controller", "predictive"][..],
            "--controller predictive",
        ),
    ] {
        let (output, _, _) = fly("refused", args);
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(!output.status.success(), "{args:?} was accepted");
        assert!(stderr.contains(says), "{args:?}: {stderr}");
    }
}
