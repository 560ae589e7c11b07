//! The tables and checks of a scenario's runs, read back from their summaries.

use std::path::Path;

use anyhow::{Context, Result};

use crate::report;
use crate::runs::{BenchRun, StrategyArg};

/// The controllers scenario's comparisons (the acceptance targets), as a markdown table.
pub(crate) fn controller_checks(out: &Path) -> Result<String> {
    const ALPHA_MS: f64 = 12.0;
    let pressure = out.join("pressure");
    let default = out.join("default");
    let [p_base, p_paper, p_head, d_paper, d_head] = [
        pressure.join("baseline"),
        pressure.join("paper-a12"),
        pressure.join("headroom-a12"),
        default.join("paper-a12"),
        default.join("headroom-a12"),
    ]
    .map(|dir| summary_of(&dir));
    let (p_base, p_paper, p_head, d_paper, d_head) = (p_base?, p_paper?, p_head?, d_paper?, d_head?);
    let worst = |s: &serde_json::Value| stat(s, "frame_ms", "max");
    let psnr = |s: &serde_json::Value| stat(s, "psnr_db", "mean");
    let streaming = |s: &serde_json::Value| count(s, "streaming_psnr_of_mean_mse_db");
    let over_2a = |run: &str| report::frames_over(&pressure.join(run), 1.0, 2.0 * ALPHA_MS).map(|n| n as f64);
    let (paper_over_2a, headroom_over_2a) = (over_2a("paper-a12")?, over_2a("headroom-a12")?);
    let checks: Vec<Check> = vec![
        (
            "pressure: worst frame, headroom / baseline".into(),
            worst(&p_head).zip(worst(&p_base)).map(|(h, b)| h / b),
            "≤ 0.05",
            |v| v <= 0.05,
        ),
        (
            format!("pressure: frames over 2α after the first second, headroom − paper (paper: {paper_over_2a})"),
            Some(headroom_over_2a - paper_over_2a),
            "≤ 0",
            |v| v <= 0.0,
        ),
        (
            "pressure: mean PSNR, baseline − headroom (dB)".into(),
            psnr(&p_base).zip(psnr(&p_head)).map(|(b, h)| b - h),
            "≤ 1.5",
            |v| v <= 1.5,
        ),
        (
            "pressure: mean PSNR, baseline − paper (dB), for comparison".into(),
            psnr(&p_base).zip(psnr(&p_paper)).map(|(b, p)| b - p),
            "—",
            |_| true,
        ),
        (
            "pressure: PSNR of mean MSE after start-up, baseline − headroom (dB)".into(),
            streaming(&p_base).zip(streaming(&p_head)).map(|(b, h)| b - h),
            "—",
            |_| true,
        ),
        (
            "pressure: PSNR of mean MSE after start-up, baseline − paper (dB)".into(),
            streaming(&p_base).zip(streaming(&p_paper)).map(|(b, p)| b - p),
            "—",
            |_| true,
        ),
        (
            "pressure: MB/s mean, headroom / baseline".into(),
            stat(&p_head, "mb_per_s", "mean")
                .zip(stat(&p_base, "mb_per_s", "mean"))
                .map(|(h, b)| h / b),
            "≥ 0.5",
            |v| v >= 0.5,
        ),
        (
            "default city: worst frame, headroom − paper (ms)".into(),
            worst(&d_head).zip(worst(&d_paper)).map(|(h, p)| h - p),
            "≤ 0",
            |v| v <= 0.0,
        ),
        (
            "default city: mean PSNR, headroom − paper (dB)".into(),
            psnr(&d_head).zip(psnr(&d_paper)).map(|(h, p)| h - p),
            "≥ 0",
            |v| v >= 0.0,
        ),
    ];
    let mut text = checks_table("# Controllers: headroom against the paper's and the baseline", checks);
    text.push_str(&format!("\n{ERROR_NOTE}\n"));
    Ok(text)
}

/// Writes a comparison's `OUT/NAME.md` and `OUT/NAME.json` and shows the table.
pub(crate) fn write_table(out: &Path, name: &str, (text, json): (String, serde_json::Value)) -> Result<()> {
    let path = out.join(format!("{name}.md"));
    citystream_gen::files::write_atomically(&path, text.as_bytes())?;
    let json_path = out.join(format!("{name}.json"));
    citystream_gen::files::write_atomically(&json_path, serde_json::to_string_pretty(&json)?.as_bytes())?;
    eprint!("{text}");
    eprintln!("wrote {} and {}", path.display(), json_path.display());
    Ok(())
}

/// `ground.md` and `ground.json`: latency without and with the ground, their ratio, and
/// what streaming the ground did.
pub(crate) fn ground_table(out: &Path, dataset: &Path) -> Result<(String, serde_json::Value)> {
    let without = summary_of(&out.join("no-ground"))?;
    let with = summary_of(&out.join("ground"))?;
    let shown = |v: Option<f64>, digits: usize| v.map_or("n/a".to_string(), |v| format!("{v:.digits$}"));
    let mut text = format!(
        "# Ground imagery on {}: the standard path without and with it\n\n\
         | | frames | latency median / mean / max (ms, modelled) | facade MB streamed | PSNR of mean MSE after start-up (dB) | identical / measured after start-up | start-up PSNR of mean MSE (dB) | ground tiles | ground MB | CPU ms per tile composed (measured) | ground PSNR of mean MSE after start-up (dB) | ground identical / measured after start-up | ground PSNR median / min (dB) | patches arrived |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
        dataset.display()
    );
    for (name, summary) in [("without ground", &without), ("with ground", &with)] {
        let ground_psnr = match stat(summary, "ground_psnr_db", "median") {
            Some(median) => format!("{median:.2} / {}", shown(stat(summary, "ground_psnr_db", "min"), 2)),
            None => "n/a".into(),
        };
        text.push_str(&format!(
            "| {name} | {} | {} / {} / {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {ground_psnr} | {} |\n",
            shown(count(summary, "frames"), 0),
            shown(stat(summary, "frame_ms", "median"), 1),
            shown(stat(summary, "frame_ms", "mean"), 1),
            shown(stat(summary, "frame_ms", "max"), 1),
            shown(count(summary, "bytes_streamed").map(|b| b / f64::from(1 << 20)), 1),
            shown(count(summary, "streaming_psnr_of_mean_mse_db"), 2),
            error_frames(summary, "streaming_"),
            shown(count(summary, "startup_psnr_of_mean_mse_db"), 2),
            shown(count(summary, "ground_tiles_uploaded"), 0),
            shown(count(summary, "ground_mb_streamed"), 1),
            shown(stat(summary, "ground", "compose_ms_per_tile"), 2),
            shown(count(summary, "ground_streaming_psnr_of_mean_mse_db"), 2),
            error_frames(summary, "ground_streaming_"),
            shown(stat(summary, "ground", "patches_arrived"), 0),
        ));
    }
    let max_without = stat(&without, "frame_ms", "max");
    let max_with = stat(&with, "frame_ms", "max");
    let ratio = match (max_with, max_without) {
        (Some(a), Some(b)) if b > 0.0 => Some(a / b),
        _ => None,
    };
    text.push_str(&format!(
        "\nMaximum frame latency with the ground / without it: **{}** ({} ms / {} ms).\n\n\
         Latency is the `modelled` clock's (a fixed 8 ms render, the desktop bind-latency model, every \
         copy at 12 GB/s, ground tiles included); ground tiles are plain copies into the tile array (no \
         sparse binding) and take their bytes from the controller's load size; composing a tile \
         is CPU work on rayon's workers, measured with the real clock and not in the modelled latency. Ground error is the ground \
         drawn alone behind the city's depth against the same with every arrived patch resident, measured \
         once patches have arrived. {ERROR_NOTE}\n",
        shown(ratio, 3),
        shown(max_with, 2),
        shown(max_without, 2),
    ));
    let budget = count(&with, "memory_budget_bytes").map_or("an unlimited".to_string(), |b| {
        format!("the {:.0} MB", b / f64::from(1 << 20))
    });
    text.push_str(&format!(
        "\nThe ground layer (sized from the view, the imagery and the budget): {} level slots of {}² \
         tiles of the clipmap's {} levels, {} MB of {budget} memory budget.\n",
        shown(stat(&with, "ground", "level_slots"), 0),
        shown(stat(&with, "ground", "cache_side"), 0),
        shown(stat(&with, "ground", "levels"), 0),
        shown(stat(&with, "ground", "memory_bytes").map(|b| b / f64::from(1 << 20)), 1),
    ));
    let json = serde_json::json!({
        "dataset": dataset.display().to_string(),
        "max_latency_ratio": ratio,
        "runs": [
            {"run": "no-ground", "summary": without},
            {"run": "ground", "summary": with},
        ],
    });
    Ok((text, json))
}

/// `strategies.md` and `strategies.json`: the runs that just ran, in one table, the paper's
/// figures beside.
pub(crate) fn strategies_table(
    out: &Path,
    dataset: &Path,
    budget_mb: u64,
    runs: &[BenchRun],
) -> Result<(String, serde_json::Value)> {
    let mut text = format!(
        "# Streaming strategies on {}: budget {budget_mb} MB\n\n\
         | | frames | latency median / mean / max (ms, modelled) | GPU ms per frame, measured (feedback + compaction + visible) | wall ms per frame | MB streamed | peak resident MB | PSNR of mean MSE after start-up (dB) | identical / measured after start-up | start-up PSNR of mean MSE (dB) | draw calls mean / max | nodes drawn mean / max | tree depth |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
        dataset.display()
    );
    let mut rows = Vec::new();
    for run in runs {
        let name = run.dir.as_str();
        let summary = summary_of(&out.join(name))?;
        let shown = |v: Option<f64>, digits: usize| v.map_or("n/a".to_string(), |v| format!("{v:.digits$}"));
        let pair = |key: &str| {
            format!(
                "{} / {}",
                shown(stat(&summary, key, "mean"), 1),
                shown(stat(&summary, key, "max"), 0)
            )
        };
        let mb = |key: &str| count(&summary, key).map(|b| b / f64::from(1 << 20));
        let depth = summary
            .get("atlas_tree")
            .and_then(|t| t.get("depth"))
            .and_then(|d| d.as_f64());
        let pass_ms = |pass: &str| {
            stat(
                summary.get("gpu_pass_ms").unwrap_or(&serde_json::Value::Null),
                pass,
                "mean",
            )
        };
        let gpu_ms = match (pass_ms("feedback"), pass_ms("compaction"), pass_ms("visible")) {
            (Some(f), Some(c), Some(v)) => format!("{:.1} ({f:.1} + {c:.1} + {v:.1})", f + c + v),
            _ => "n/a".into(),
        };
        let nodes = if name == StrategyArg::AtlasTree.name() {
            pair("nodes_drawn")
        } else {
            "n/a".into()
        };
        let preloaded = summary
            .get("preloaded")
            .and_then(|p| p.get("bytes"))
            .and_then(|b| b.as_f64())
            .map_or(String::new(), |b| {
                format!(" (+{:.1} before the first frame)", b / f64::from(1 << 20))
            });
        text.push_str(&format!(
            "| {} | {} | {} / {} / {} | {gpu_ms} | {} | {}{preloaded} | {} | {} | {} | {} | {} | {nodes} | {} |\n",
            name,
            shown(count(&summary, "frames"), 0),
            shown(stat(&summary, "frame_ms", "median"), 1),
            shown(stat(&summary, "frame_ms", "mean"), 1),
            shown(stat(&summary, "frame_ms", "max"), 1),
            shown(count(&summary, "wall_ms_per_frame"), 1),
            shown(mb("bytes_streamed"), 1),
            shown(mb("peak_resident_bytes"), 1),
            shown(count(&summary, "streaming_psnr_of_mean_mse_db"), 2),
            error_frames(&summary, "streaming_"),
            shown(count(&summary, "startup_psnr_of_mean_mse_db"), 2),
            pair("draw_calls"),
            shown(depth, 0),
        ));
        rows.push(serde_json::json!({"strategy": name, "summary": summary}));
    }
    text.push_str(
        "| paper: atlas tree, Berlin | | 14.5 ms mean (69 fps average, real) | | | | 160 blocks in memory (at most 350 MB in all) | | | | | mostly < 20, never > 40 | 6 |\n\n\
         Latency is the `modelled` clock's (a fixed 8 ms render, the desktop bind-latency model, the copies at \
         12 GB/s), the same for a strategy whatever this machine's speed; GPU ms are the strategy's passes timed \
         with timestamps on this device (the atlas tree has no feedback pass); wall ms include the PSNR \
         measurements every 30th frame (for the tree also the reference's own feedback pass). Draw calls are those of a renderer \
         binding one texture per draw, for texture arrays Trapp and Döllner's Alg. 2 (every array bound once, one draw \
         per batch of up to 8 arrays in view; citystream draws every mesh in one draw under every strategy). `texture-arrays` runs without a budget: the whole city is loaded \
         into fully bound arrays before the first frame where the device holds it (its MB in parentheses), and its \
         resident MB are every layer's full mip chain; `texture-arrays-streamed` streams into arrays under the budget \
         at whole-mip granularity (no sparse residency). The error is against the same view with every texture the \
         view needs resident (the originals).\n",
    );
    text.push_str(ERROR_NOTE);
    text.push('\n');
    let json = serde_json::json!({
        "dataset": dataset.display().to_string(),
        "budget_mb": budget_mb,
        "runs": rows,
    });
    Ok((text, json))
}

/// One run's summary.json.
pub(crate) fn summary_of(dir: &Path) -> Result<serde_json::Value> {
    let path = dir.join("summary.json");
    let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))
}

pub(crate) fn stat(summary: &serde_json::Value, key: &str, field: &str) -> Option<f64> {
    summary.get(key)?.get(field)?.as_f64()
}

pub(crate) fn count(summary: &serde_json::Value, key: &str) -> Option<f64> {
    summary.get(key)?.as_f64()
}

/// What the error columns of the bench's tables mean.
pub(crate) const ERROR_NOTE: &str = "PSNR of mean MSE is the PSNR of the mean squared error over the measured frames: \
    after start-up (from the first second of path time on, `streaming_psnr_of_mean_mse_db`, the \
    headline) or in the start-up fill (the first second, `startup_psnr_of_mean_mse_db`, when nothing \
    is resident yet and every policy is about equally wrong); identical / measured counts the \
    measured frames equal to their reference (each counts at the summary's `psnr_ceiling_db` in the \
    per-frame PSNR statistics).";

/// `identical / measured` frames of the error figures under `prefix` (`""`, `"ground_"`).
pub(crate) fn error_frames(summary: &serde_json::Value, prefix: &str) -> String {
    let frames = summary.get(format!("{prefix}error_frames"));
    let field = |name: &str| frames.and_then(|f| f.get(name)).and_then(|v| v.as_u64());
    match (field("identical"), field("measured")) {
        (Some(identical), Some(measured)) => format!("{identical} / {measured}"),
        _ => "n/a".into(),
    }
}

/// The pressure scenario's acceptance ratios, as a markdown table.
pub(crate) fn pressure_checks(out: &Path, budget_mb: u64) -> Result<String> {
    let baseline = summary_of(&out.join("baseline"))?;
    let adaptive = summary_of(&out.join("adaptive-a12"))?;
    let unbudgeted = summary_of(&out.join("unbudgeted-a12"))?;
    let budget = (budget_mb << 20) as f64;
    let ratio = |a: Option<f64>, b: Option<f64>| match (a, b) {
        (Some(a), Some(b)) if b > 0.0 => Some(a / b),
        _ => None,
    };
    let checks: Vec<Check> = vec![
        (
            "PSNR of mean MSE after start-up: unbudgeted − adaptive α=12 (dB)".into(),
            count(&unbudgeted, "streaming_psnr_of_mean_mse_db")
                .zip(count(&adaptive, "streaming_psnr_of_mean_mse_db"))
                .map(|(u, a)| u - a),
            "≤ 3",
            |v| v <= 3.0,
        ),
        (
            "Mip deficit, adaptive α=12, mean (levels)".into(),
            stat(&adaptive, "mip_deficit", "mean"),
            "≤ 1",
            |v| v <= 1.0,
        ),
        (
            "Peak resident / budget, adaptive α=12".into(),
            count(&adaptive, "peak_resident_bytes").map(|p| p / budget),
            "≤ 1.1",
            |v| v <= 1.1,
        ),
        (
            "Bytes streamed / unique bytes, adaptive α=12".into(),
            ratio(
                count(&adaptive, "bytes_streamed"),
                count(&adaptive, "unique_bytes_streamed"),
            ),
            "≤ 2",
            |v| v <= 2.0,
        ),
        (
            "Max frame latency, adaptive / baseline".into(),
            ratio(stat(&adaptive, "frame_ms", "max"), stat(&baseline, "frame_ms", "max")),
            "≤ 0.05",
            |v| v <= 0.05,
        ),
        (
            "Mean frame latency, adaptive / baseline".into(),
            ratio(stat(&adaptive, "frame_ms", "mean"), stat(&baseline, "frame_ms", "mean")),
            "≤ 0.35",
            |v| v <= 0.35,
        ),
        (
            "MB/s mean, adaptive / baseline".into(),
            ratio(stat(&adaptive, "mb_per_s", "mean"), stat(&baseline, "mb_per_s", "mean")),
            "≥ 0.5",
            |v| v >= 0.5,
        ),
    ];
    Ok(checks_table(
        &format!("# Pressure benchmark: budget {budget_mb} MB"),
        checks,
    ))
}

/// One measured figure against its target: label, value, target as shown, and whether a
/// value meets it (a target shown as `—` is for comparison, not a check).
pub(crate) type Check = (String, Option<f64>, &'static str, fn(f64) -> bool);

/// `heading` and a markdown table of `checks`.
pub(crate) fn checks_table(heading: &str, checks: Vec<Check>) -> String {
    let mut text = format!("{heading}\n\n| Check | Measured | Target | Met |\n|---|---:|---:|---|\n");
    for (label, value, target, met) in checks {
        let (shown, verdict) = match value {
            Some(v) if v.is_finite() => (
                format!("{v:.3}"),
                if target == "—" {
                    "—"
                } else if met(v) {
                    "yes"
                } else {
                    "no"
                },
            ),
            _ => ("n/a".to_string(), "n/a"),
        };
        text.push_str(&format!("| {label} | {shown} | {target} | {verdict} |\n"));
    }
    text
}
