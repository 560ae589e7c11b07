//! The predictive controller, the error-per-byte order and the prefetch pass in a flight:
//! reproducible, validated, charged in the modelled frame, and refused where they do not
//! apply.

use std::process::{Command, Output};

/// The default city, created once for the tests that fly it (concurrent creators are safe:
/// each builds privately and renames into place).
fn default_city() -> std::path::PathBuf {
    let city = std::path::Path::new(env!("CARGO_TARGET_TMPDIR"))
        .join("default_city")
        .join("city");
    citystream_gen::default_city::ensure_default_city(&city, true).expect("default city created");
    city
}

/// 150 modelled frames of the default city at 160×120 with validation, `extra` after; its
/// output, summary.json and frames.csv.
fn fly(name: &str, extra: &[&str]) -> (Output, serde_json::Value, String) {
    let out = std::path::Path::new(env!("CARGO_TARGET_TMPDIR"))
        .join("prefetch")
        .join(name);
    let output = Command::new(env!("CARGO_BIN_EXE_flythrough"))
        .args(["--width", "160", "--height", "120", "--frames", "150"])
        .args([
            "--clock",
            "modelled",
            "--bind-latency",
            "desktop",
            "--memory-budget-mb",
            "32",
        ])
        .args(["--frame-interval", "0", "--psnr-interval", "30", "--validation=true"])
        .args(extra)
        .arg("--dataset")
        .arg(default_city())
        .arg("--out")
        .arg(&out)
        .output()
        .expect("flythrough runs");
    let summary = serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap_or_default())
        .unwrap_or(serde_json::Value::Null);
    let csv = std::fs::read_to_string(out.join("frames.csv")).unwrap_or_default();
    (output, summary, csv)
}

fn column(csv: &str, name: &str) -> Vec<f64> {
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().expect("header").split(',').collect();
    let at = header.iter().position(|h| *h == name).expect("column");
    lines
        .map(|l| l.split(',').nth(at).expect("cell").parse().expect("number"))
        .collect()
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
    assert_eq!(summary["priority"], "error-per-byte");
    assert_eq!(summary["prefetch"], "path");
    assert_eq!(summary["prefetch_lead_s"], 0.5);
    assert_eq!(summary["prefetch_cost_ms"], 3.0);
    // The pass is recorded where the camera half a second ahead sees beyond the view's
    // margin: some frames, not all.
    let passes = column(&first, "prefetch_pass");
    let recorded = passes.iter().filter(|&&p| p == 1.0).count();
    assert_eq!(summary["prefetch_frames"].as_u64(), Some(recorded as u64), "{summary}");
    assert!(
        (1..150).contains(&recorded),
        "{recorded} frames recorded the prefetch pass"
    );
    assert!(summary["prefetched_mips"].as_u64().is_some_and(|m| m > 0), "{summary}");
    // Two runs of the same options: the same frames, byte for byte.
    let (output, _, second) = fly("path-b", &args);
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    assert_eq!(
        first, second,
        "two runs of the same options must give the same frames.csv"
    );
    // A frame with the pass pays for it: one that uploads nothing costs the render and the
    // pass (8 + 3 ms), without the pass the render alone.
    let (dts, bytes) = (column(&first, "dt_ms"), column(&first, "bytes"));
    for pass in [1.0, 0.0] {
        let quiet: Vec<f64> = (0..dts.len())
            .filter(|&i| passes[i] == pass && bytes[i] == 0.0)
            .map(|i| dts[i])
            .collect();
        assert!(!quiet.is_empty(), "no frame without uploads and with pass = {pass}");
        let expected = 8.0 + 3.0 * pass;
        assert!(
            quiet.iter().all(|&dt| (dt - expected).abs() < 1e-9),
            "frames without uploads, pass = {pass}: {quiet:?}"
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
    assert!((1..=148).contains(&frames), "{frames} frames prefetched");
    // The paper's order by default for the paper's controller.
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
