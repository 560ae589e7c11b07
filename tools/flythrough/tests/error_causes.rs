//! The error split by cause in a flight: each cause shows up where the run's settings make
//! it the reason texels are coarse, and the parts partition every measured frame's MSE.

mod flight_support;
use flight_support::{default_city, fly_flythrough, optional_column};

/// 240 modelled frames of the default city at 160×120 with validation, error every 8
/// frames, `extra` after; summary.json and frames.csv.
fn fly(name: &str, extra: &[&str]) -> (serde_json::Value, String) {
    let out = std::path::Path::new(env!("CARGO_TARGET_TMPDIR"))
        .join("error_causes")
        .join(name);
    let mut args = vec!["--width", "160", "--height", "120", "--frames", "240"];
    args.extend(["--clock", "modelled", "--bind-latency", "desktop"]);
    args.extend(["--frame-interval", "0", "--psnr-interval", "8", "--validation=true"]);
    args.extend(extra);
    let (output, summary, csv) = fly_flythrough(&args, &default_city(), &out);
    assert!(
        output.status.success(),
        "{name}: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert_eq!(summary["validation_errors"], 0, "{name}: {summary}");
    (summary, csv)
}

/// Every measured frame's `(mse, [lag, load, bias, budget])`.
fn measured(csv: &str) -> Vec<(f64, [f64; 4])> {
    let mse = optional_column(csv, "mse");
    let parts = ["mse_lag", "mse_load", "mse_bias", "mse_budget"].map(|name| optional_column(csv, name));
    mse.iter()
        .enumerate()
        .filter_map(|(i, m)| m.map(|m| (m, parts.each_ref().map(|p| p[i].expect("a part on a measured frame")))))
        .collect()
}

/// The after-start-up parts of `summary.json`, in lag, load, bias, budget order.
fn streaming_parts(summary: &serde_json::Value) -> [f64; 4] {
    let streaming = &summary["error_causes"]["streaming"];
    ["lag_mse", "load_mse", "bias_mse", "budget_mse"].map(|k| streaming[k].as_f64().expect("part"))
}

#[test]
fn each_cause_appears_where_the_settings_make_it() {
    // A trickle of loads, no bias, room for everything: texels wait for the load size.
    let (summary, csv) = fly(
        "trickle",
        &[
            "--policy",
            "fixed",
            "--load-size-mb",
            "0.25",
            "--mip-bias",
            "0",
            "--memory-budget-mb",
            "512",
        ],
    );
    let frames = measured(&csv);
    assert!(frames.len() >= 20, "{} measured frames", frames.len());
    for (mse, parts) in &frames {
        let sum: f64 = parts.iter().sum();
        assert!(
            (sum - mse).abs() <= 1e-6 * mse.max(1e-12),
            "parts {parts:?} vs mse {mse}"
        );
    }
    let [lag, load, bias, budget] = streaming_parts(&summary);
    assert!(load > 0.0, "{summary}");
    assert!(
        load > lag,
        "a trickle of loads waits on the load size: {load} vs lag {lag}"
    );
    assert_eq!((bias, budget), (0.0, 0.0), "no bias and no budget pressure");

    // Everything loads at once, but a bias of 4 levels holds every texture back.
    let (summary, _) = fly(
        "biased",
        &[
            "--policy",
            "fixed",
            "--load-size-mb",
            "64",
            "--mip-bias",
            "4",
            "--memory-budget-mb",
            "512",
        ],
    );
    let [lag, load, bias, budget] = streaming_parts(&summary);
    assert!(bias > lag + load + budget, "the bias dominates: {summary}");

    // The same loads into a budget far below what the view needs: levels are dropped.
    let (summary, _) = fly(
        "tight",
        &[
            "--policy",
            "fixed",
            "--load-size-mb",
            "64",
            "--mip-bias",
            "0",
            "--memory-budget-mb",
            "8",
        ],
    );
    let [_, _, bias, budget] = streaming_parts(&summary);
    assert!(budget > 0.0, "a tight budget shows as budget: {summary}");
    assert_eq!(bias, 0.0);
}
