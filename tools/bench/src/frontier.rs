//! `--scenario frontier`: speed against error over every policy family on the pressure
//! benchmark (docs/CONTROLLER.md, docs/MEASURED.md).
//!
//! The runs: the baseline; fixed load sizes of 1 to 32 MB without bias; the paper's and the
//! headroom controller at α = 8, 12, 16 and 20 ms; the predictive controller at the same
//! α without prefetch and with `--prefetch path`, and at 12 ms with `--prefetch motion` and
//! with `--prefetch path` in the error-per-byte order (`--priority error-per-byte`).
//! Every run measures its image error every 12 frames (`FRONTIER_PSNR_INTERVAL`; about 145
//! measured frames after the start-up second of a 30 s path). `frontier.md` tabulates,
//! per run, the worst and 99th-percentile frame, the frames over α and 2α after the first
//! second, MB per second of path time, the start-up and after-start-up PSNR of the mean MSE
//! and the time to 40 dB after the start and after each cut of the path, then checks the
//! issue's targets; `frontier.png` plots error against worst frame with the Pareto front;
//! `frontier.json` holds the figures; `frontier-causes.png` stacks each run's error after
//! start-up by cause (lag, load size, bias, budget), which `frontier.md` tabulates too.

use std::path::Path;

use anyhow::{Context, Result};
use plotters::prelude::*;

use citystream_streaming::shortfall::ShortfallCause;

use crate::image_error::{psnr_of_mse_db, ErrorCauses};
use crate::report::{self, plot_error, render_png};
use crate::report_runs::{read_frames_csv, FrameRow};
use crate::runs::BenchRun;
use crate::tables::{checks_table, count, summary_of, Check, ERROR_NOTE};

/// Frames between error measurements of a frontier run.
pub(crate) const FRONTIER_PSNR_INTERVAL: u32 = 12;
/// The target latency the checks and the constant policies' columns use.
pub(crate) const FRONTIER_ALPHA_MS: f64 = 12.0;
/// The error level whose time to reach is measured.
pub(crate) const TARGET_PSNR_DB: f64 = 40.0;
/// Path time (s) after which frames count against α (the start-up fill before it).
const SETTLED_S: f64 = 1.0;

/// The families of policies the chart draws as lines.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Family {
    Baseline,
    Fixed,
    Paper,
    Headroom,
    Predictive,
    PredictivePath,
    PredictiveMotion,
    PredictivePathEpb,
    PredictivePathLead,
}

impl Family {
    fn label(self) -> &'static str {
        match self {
            Family::Baseline => "baseline (s = 64 MB)",
            Family::Fixed => "fixed s, b = 0",
            Family::Paper => "paper (Eq. 4-7)",
            Family::Headroom => "headroom",
            Family::Predictive => "predictive",
            Family::PredictivePath => "predictive + path prefetch",
            Family::PredictiveMotion => "predictive + motion prefetch",
            Family::PredictivePathEpb => "predictive + path prefetch, error-per-byte order",
            Family::PredictivePathLead => "predictive + path prefetch, lead 0.5 / 2 s",
        }
    }

    fn color(self) -> RGBColor {
        match self {
            Family::Baseline => BLACK,
            Family::Fixed => RGBColor(127, 127, 127),
            Family::Paper => RED,
            Family::Headroom => RGBColor(255, 127, 14),
            Family::Predictive => BLUE,
            Family::PredictivePath => RGBColor(44, 160, 44),
            Family::PredictiveMotion => RGBColor(148, 103, 189),
            Family::PredictivePathEpb => RGBColor(23, 190, 207),
            Family::PredictivePathLead => RGBColor(140, 86, 75),
        }
    }

    const ALL: [Family; 9] = [
        Family::Baseline,
        Family::Fixed,
        Family::Paper,
        Family::Headroom,
        Family::Predictive,
        Family::PredictivePath,
        Family::PredictiveMotion,
        Family::PredictivePathEpb,
        Family::PredictivePathLead,
    ];
}

/// One run of the frontier: the flythrough run, its family and its α (the constant
/// policies have none).
#[derive(Debug, Clone)]
pub(crate) struct FrontierRun {
    pub(crate) run: BenchRun,
    pub(crate) family: Family,
    pub(crate) alpha_ms: Option<f64>,
}

/// The α of the controllers' runs.
pub(crate) const FRONTIER_ALPHAS: [u32; 4] = [8, 12, 16, 20];
/// The fixed policies' load sizes, MB.
pub(crate) const FRONTIER_FIXED_MB: [u32; 6] = [1, 2, 4, 8, 16, 32];

/// Every run of the frontier, in the order they fly, under `budget_mb`.
pub(crate) fn frontier_runs(budget_mb: u64) -> Vec<FrontierRun> {
    let shared: Vec<String> = [
        "--psnr-interval".to_string(),
        FRONTIER_PSNR_INTERVAL.to_string(),
        "--frame-interval".into(),
        "0".into(),
        "--memory-budget-mb".into(),
        budget_mb.to_string(),
    ]
    .into();
    let run = |dir: String, name: String, args: Vec<String>, family: Family, alpha_ms: Option<f64>| FrontierRun {
        run: BenchRun {
            dir,
            name,
            args: args.into_iter().chain(shared.iter().cloned()).collect(),
        },
        family,
        alpha_ms,
    };
    let strings = |args: &[&str]| args.iter().map(|a| a.to_string()).collect::<Vec<_>>();
    let mut runs = vec![run(
        "baseline".into(),
        "baseline".into(),
        strings(&["--policy", "baseline"]),
        Family::Baseline,
        None,
    )];
    for mb in FRONTIER_FIXED_MB {
        let size = mb.to_string();
        runs.push(run(
            format!("fixed-s{mb}"),
            format!("fixed s={mb} MB"),
            strings(&["--policy", "fixed", "--load-size-mb", &size, "--mip-bias", "0"]),
            Family::Fixed,
            None,
        ));
    }
    let controllers = [
        ("paper", Family::Paper, &[][..]),
        ("headroom", Family::Headroom, &[][..]),
        ("predictive", Family::Predictive, &[][..]),
        ("predictive", Family::PredictivePath, &["--prefetch", "path"][..]),
    ];
    for (controller, family, extra) in controllers {
        for alpha in FRONTIER_ALPHAS {
            let a = alpha.to_string();
            let suffix = if family == Family::PredictivePath { "-path" } else { "" };
            let mut args = strings(&["--policy", "adaptive", "--controller", controller, "--alpha", &a]);
            args.extend(strings(extra));
            runs.push(run(
                format!("{controller}-a{alpha}{suffix}"),
                format!(
                    "{controller} α={alpha} ms{}",
                    if suffix.is_empty() { "" } else { ", path prefetch" }
                ),
                args,
                family,
                Some(f64::from(alpha)),
            ));
        }
    }
    // The predictive controller at α = 12 ms, `extra` after: the runs beside the families.
    let predictive_a12 = |extra: &[&str]| {
        let mut args = strings(&["--policy", "adaptive", "--controller", "predictive", "--alpha", "12"]);
        args.extend(strings(extra));
        args
    };
    runs.push(run(
        "predictive-a12-motion".into(),
        "predictive α=12 ms, motion prefetch".into(),
        predictive_a12(&["--prefetch", "motion"]),
        Family::PredictiveMotion,
        Some(12.0),
    ));
    // Error per byte in place of the paper's order (weight, the default): which order
    // buys the most image under the predictive controller's block budget is measured.
    runs.push(run(
        "predictive-a12-path-epb".into(),
        "predictive α=12 ms, path prefetch, error-per-byte order".into(),
        predictive_a12(&["--prefetch", "path", "--priority", "error-per-byte"]),
        Family::PredictivePathEpb,
        Some(12.0),
    ));
    // The lead time of path prefetch, which its default is chosen from (the α = 12 ms run
    // above flies the default).
    for lead in FRONTIER_LEADS_S {
        runs.push(run(
            format!("predictive-a12-path-lead{lead}"),
            format!("predictive α=12 ms, path prefetch, lead {lead} s"),
            predictive_a12(&["--prefetch", "path", "--prefetch-lead-s", &lead.to_string()]),
            Family::PredictivePathLead,
            Some(12.0),
        ));
    }
    runs
}

/// Lead times (s) of path prefetch flown beside the default's run.
pub(crate) const FRONTIER_LEADS_S: [f64; 2] = [0.5, 2.0];

/// What the frontier reports of one run.
#[derive(Debug, Clone, serde::Serialize)]
pub(crate) struct FrontierFigures {
    pub(crate) dir: String,
    pub(crate) name: String,
    pub(crate) family: &'static str,
    pub(crate) alpha_ms: Option<f64>,
    pub(crate) frames: usize,
    pub(crate) worst_frame_ms: f64,
    pub(crate) p99_frame_ms: f64,
    /// Frames over α (the run's, or [`FRONTIER_ALPHA_MS`]) and over 2α from the first
    /// second of path time on.
    pub(crate) frames_over_alpha: usize,
    pub(crate) frames_over_2alpha: usize,
    /// MB (2^20 bytes) streamed per second of path time.
    pub(crate) mb_per_path_s: f64,
    pub(crate) startup_psnr_db: Option<f64>,
    pub(crate) streaming_psnr_db: Option<f64>,
    pub(crate) streaming_measured_frames: Option<u64>,
    /// Seconds of path time from the start to the first measured frame at 40 dB or
    /// better (`None`: none reached it).
    pub(crate) time_to_40db_start_s: Option<f64>,
    /// The same from each cut of the path (`None` where none reached it before the next
    /// cut or the end).
    pub(crate) time_to_40db_after_cuts_s: Vec<Option<f64>>,
    /// The mean MSE after start-up split by cause, in [`ShortfallCause::ALL`] order
    /// (`summary.json`'s `error_causes.streaming`); `None` for a run flown without it.
    pub(crate) streaming_error_causes: Option<ErrorCauses>,
}

/// The `q`-quantile (nearest rank) of `values`; 0 when empty.
fn quantile(values: &[f64], q: f64) -> f64 {
    let mut sorted: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
    if sorted.is_empty() {
        return 0.0;
    }
    sorted.sort_by(f64::total_cmp);
    let rank = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
    sorted[rank - 1]
}

/// Seconds from `from_s` to the first measured frame in `[from_s, until_s)` whose PSNR is
/// at least `level_db`.
pub(crate) fn time_to_level(frames: &[FrameRow], from_s: f64, until_s: f64, level_db: f64) -> Option<f64> {
    frames
        .iter()
        .filter(|f| f.time_s >= from_s && f.time_s < until_s)
        .find(|f| f.psnr_db.is_some_and(|p| p >= level_db))
        .map(|f| f.time_s - from_s)
}

/// The figures of the run in `dir`.
pub(crate) fn figures_of(dir: &Path, run: &FrontierRun) -> Result<FrontierFigures> {
    let summary = summary_of(dir)?;
    let frames = read_frames_csv(&dir.join("frames.csv"))?;
    let alpha = run.alpha_ms.unwrap_or(FRONTIER_ALPHA_MS);
    let dts: Vec<f64> = frames.iter().map(|f| f.dt_ms).collect();
    let settled: Vec<f64> = frames
        .iter()
        .filter(|f| f.time_s >= SETTLED_S)
        .map(|f| f.dt_ms)
        .collect();
    let path_s = count(&summary, "duration_s").unwrap_or(0.0);
    let bytes: u64 = frames.iter().map(|f| f.bytes).sum();
    let cuts: Vec<f64> = summary
        .get("path_cuts_s")
        .and_then(|v| v.as_array())
        .map(|a| a.iter().filter_map(|v| v.as_f64()).collect())
        .unwrap_or_default();
    let end = frames.last().map_or(0.0, |f| f.time_s) + 1.0;
    let after_cuts = cuts
        .iter()
        .enumerate()
        .map(|(i, &cut)| {
            let until = cuts.get(i + 1).copied().unwrap_or(end);
            time_to_level(&frames, cut, until, TARGET_PSNR_DB)
        })
        .collect();
    let first_cut = cuts.first().copied().unwrap_or(end);
    Ok(FrontierFigures {
        dir: run.run.dir.clone(),
        name: run.run.name.clone(),
        family: run.family.label(),
        alpha_ms: run.alpha_ms,
        frames: frames.len(),
        worst_frame_ms: dts.iter().copied().fold(0.0, f64::max),
        p99_frame_ms: quantile(&dts, 0.99),
        frames_over_alpha: settled.iter().filter(|&&dt| dt > alpha).count(),
        frames_over_2alpha: settled.iter().filter(|&&dt| dt > 2.0 * alpha).count(),
        mb_per_path_s: if path_s > 0.0 {
            bytes as f64 / f64::from(1 << 20) / path_s
        } else {
            0.0
        },
        startup_psnr_db: count(&summary, "startup_psnr_of_mean_mse_db"),
        streaming_psnr_db: count(&summary, "streaming_psnr_of_mean_mse_db"),
        streaming_measured_frames: summary
            .get("streaming_error_frames")
            .and_then(|f| f.get("measured"))
            .and_then(|v| v.as_u64()),
        time_to_40db_start_s: time_to_level(&frames, 0.0, first_cut, TARGET_PSNR_DB),
        time_to_40db_after_cuts_s: after_cuts,
        streaming_error_causes: summary
            .get("error_causes")
            .and_then(|c| c.get("streaming"))
            .and_then(|c| serde_json::from_value(c.clone()).ok()),
    })
}

/// The runs on the Pareto front: none other has a worst frame as low or lower and a
/// higher PSNR after start-up (nor the same PSNR with a lower worst frame).
pub(crate) fn pareto_front(points: &[(f64, f64)]) -> Vec<usize> {
    let mut front: Vec<usize> = (0..points.len())
        .filter(|&i| {
            let (wi, pi) = points[i];
            !points.iter().any(|&(w, p)| (w <= wi && p > pi) || (w < wi && p >= pi))
        })
        .collect();
    front.sort_by(|&a, &b| points[a].0.total_cmp(&points[b].0));
    front
}

fn cell(v: Option<f64>, digits: usize) -> String {
    v.map_or("—".to_string(), |v| format!("{v:.digits$}"))
}

/// `frontier.md`, `frontier.json` and `frontier.png` from the finished runs in `out`
/// (runs not flown are listed as such); the markdown.
pub(crate) fn write_frontier(
    out: &Path,
    runs: &[FrontierRun],
    city: &Path,
    size: (u32, u32),
    budget_mb: u64,
) -> Result<String> {
    let mut figures = Vec::new();
    let mut missing = Vec::new();
    for run in runs {
        let dir = out.join(&run.run.dir);
        if dir.join("summary.json").is_file() {
            figures.push((run.family, figures_of(&dir, run)?));
        } else {
            missing.push(run.run.name.clone());
        }
    }
    let mut text = format!(
        "# The frontier: speed against error ({}, {}×{}, {budget_mb} MB)\n\n\
         Error measured every {FRONTIER_PSNR_INTERVAL} frames; frames over α count from the first second of \
         path time on (α = {FRONTIER_ALPHA_MS} ms for the baseline and the fixed sizes); MB = 2^20 bytes per \
         second of path time; time to {TARGET_PSNR_DB} dB: path seconds from the start, or from each cut, to \
         the first measured frame at {TARGET_PSNR_DB} dB or better (— : not reached).\n\n\
         | run | worst frame ms | p99 frame ms | frames > α / > 2α | MB per path s | start-up PSNR dB | \
         after start-up PSNR dB (measured) | to {TARGET_PSNR_DB} dB after start s | after each cut s |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---|\n",
        city.display(),
        size.0,
        size.1
    );
    for (_, f) in &figures {
        let cuts: Vec<String> = f.time_to_40db_after_cuts_s.iter().map(|t| cell(*t, 2)).collect();
        text.push_str(&format!(
            "| {} | {:.2} | {:.2} | {} / {} | {:.2} | {} | {} ({}) | {} | {} |\n",
            f.name,
            f.worst_frame_ms,
            f.p99_frame_ms,
            f.frames_over_alpha,
            f.frames_over_2alpha,
            f.mb_per_path_s,
            cell(f.startup_psnr_db, 2),
            cell(f.streaming_psnr_db, 2),
            f.streaming_measured_frames.map_or("—".into(), |m| m.to_string()),
            cell(f.time_to_40db_start_s, 2),
            if cuts.is_empty() { "—".into() } else { cuts.join(", ") },
        ));
    }
    if !missing.is_empty() {
        text.push_str(&format!("\nNot flown: {}.\n", missing.join(", ")));
    }
    let points: Vec<(f64, f64)> = figures
        .iter()
        .map(|(_, f)| (f.worst_frame_ms, f.streaming_psnr_db.unwrap_or(f64::NAN)))
        .collect();
    let front: Vec<String> = pareto_front(&points)
        .into_iter()
        .filter(|&i| points[i].1.is_finite())
        .map(|i| figures[i].1.name.clone())
        .collect();
    text.push_str(&format!(
        "\nOn the Pareto front (worst frame, after-start-up PSNR): {}.\n\n",
        front.join(", ")
    ));
    text.push_str(&checks(&figures));
    text.push_str(&causes_table(&figures));
    text.push_str(&format!("\n{ERROR_NOTE}\n"));
    citystream_gen::files::write_atomically(&out.join("frontier.md"), text.as_bytes())?;
    let json = serde_json::to_string_pretty(&figures.iter().map(|(_, f)| f).collect::<Vec<_>>())?;
    citystream_gen::files::write_atomically(&out.join("frontier.json"), json.as_bytes())?;
    draw_frontier(&figures, &out.join("frontier.png")).context("drawing frontier.png")?;
    draw_causes(&figures, &out.join("frontier-causes.png")).context("drawing frontier-causes.png")?;
    Ok(text)
}

/// What each cause would be worth removed: `frontier.md`'s "Where the error comes from".
fn causes_table(figures: &[(Family, FrontierFigures)]) -> String {
    let with: Vec<(&FrontierFigures, ErrorCauses)> = figures
        .iter()
        .filter_map(|(_, f)| f.streaming_error_causes.map(|c| (f, c)))
        .collect();
    if with.is_empty() {
        return String::new();
    }
    let mut text = String::from(
        "\n## Where the error comes from\n\n\
         The mean MSE after start-up split by why each pixel's texture showed coarser than the \
         reference's (docs/CONTROLLER.md): not requested yet (lag), requested and waiting (load size), \
         held back by the mip bias (bias), dropped, evicted or refused for room (budget); each share of \
         the run's squared error, and the after-start-up PSNR the run would read with that part gone \
         (`frontier-causes.png` stacks the parts).\n\n\
         | run | mean MSE | lag | load size | bias | budget | PSNR without lag / load / bias / budget dB |\n\
         |---|---:|---:|---:|---:|---:|---|\n",
    );
    for (f, causes) in with {
        let total = causes.total();
        let share = |c: ShortfallCause| {
            if total > 0.0 {
                format!("{:.0} %", 100.0 * causes.part(c) / total)
            } else {
                "—".into()
            }
        };
        let without: Vec<String> = ShortfallCause::ALL
            .iter()
            .map(|&c| format!("{:.2}", psnr_of_mse_db(total - causes.part(c))))
            .collect();
        text.push_str(&format!(
            "| {} | {:.3} | {} | {} | {} | {} | {} |\n",
            f.name,
            total,
            share(ShortfallCause::Lag),
            share(ShortfallCause::LoadSize),
            share(ShortfallCause::Bias),
            share(ShortfallCause::Budget),
            without.join(" / "),
        ));
    }
    text
}

/// The colour of a cause's part in `frontier-causes.png`.
fn cause_color(cause: ShortfallCause) -> RGBColor {
    match cause {
        ShortfallCause::Lag => RGBColor(0x44, 0x77, 0xAA),
        ShortfallCause::LoadSize => RGBColor(0xEE, 0x66, 0x77),
        ShortfallCause::Bias => RGBColor(0xCC, 0xBB, 0x44),
        ShortfallCause::Budget => RGBColor(0x22, 0x88, 0x33),
    }
}

/// `frontier-causes.png`: per run, its mean MSE after start-up as a bar stacked by cause.
fn draw_causes(figures: &[(Family, FrontierFigures)], path: &Path) -> Result<()> {
    let runs: Vec<(&str, ErrorCauses)> = figures
        .iter()
        .filter_map(|(_, f)| f.streaming_error_causes.map(|c| (f.dir.as_str(), c)))
        .collect();
    if runs.is_empty() {
        eprintln!("frontier: no run split its error by cause; frontier-causes.png not drawn");
        return Ok(());
    }
    // A quarter of the axis past the longest bar: room for the legend beside every bar.
    let top = runs.iter().map(|(_, c)| c.total()).fold(0.0f64, f64::max).max(1e-6) * 1.3;
    let count = runs.len();
    let height = (120 + 34 * count as u32).max(300);
    render_png(path, (1000, height), |root| {
        let mut chart = ChartBuilder::on(root)
            .caption(
                "Where the error comes from: mean MSE after start-up, by cause",
                ("sans-serif", 22),
            )
            .margin(16)
            .x_label_area_size(46)
            .y_label_area_size(190)
            .build_cartesian_2d(0.0..top, (0..count).into_segmented())
            .map_err(plot_error)?;
        chart
            .configure_mesh()
            .disable_y_mesh()
            .y_label_formatter(&|v| match v {
                SegmentValue::CenterOf(i) => runs.get(*i).map_or(String::new(), |(dir, _)| dir.to_string()),
                _ => String::new(),
            })
            .y_labels(count)
            .x_desc("mean MSE after start-up (8-bit RGB)")
            .label_style(("sans-serif", 13))
            .axis_desc_style(("sans-serif", 15))
            .draw()
            .map_err(plot_error)?;
        for (k, cause) in ShortfallCause::ALL.iter().enumerate() {
            let color = cause_color(*cause);
            chart
                .draw_series(runs.iter().enumerate().map(|(i, (_, c))| {
                    let parts = c.parts();
                    let from: f64 = parts[..k].iter().sum();
                    let to = from + parts[k];
                    let mut bar = Rectangle::new(
                        [(from, SegmentValue::Exact(i)), (to, SegmentValue::Exact(i + 1))],
                        color.filled(),
                    );
                    bar.set_margin(5, 5, 0, 0);
                    bar
                }))
                .map_err(plot_error)?
                .label(cause.name())
                .legend(move |(x, y)| Rectangle::new([(x, y - 6), (x + 14, y + 6)], color.filled()));
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::LowerRight)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 14))
            .draw()
            .map_err(plot_error)?;
        Ok(())
    })
}

/// The targets for this streaming (predictive α = 12 ms with path, and with
/// motion, prefetch), as far as the runs flown allow.
fn checks(figures: &[(Family, FrontierFigures)]) -> String {
    let get = |dir: &str| figures.iter().map(|(_, f)| f).find(|f| f.dir == dir);
    let baseline = get("baseline");
    let path = get("predictive-a12-path");
    let motion = get("predictive-a12-motion");
    let paper = get("paper-a12");
    let psnr = |f: Option<&FrontierFigures>| f.and_then(|f| f.streaming_psnr_db);
    // Runs whose worst frame is no lower than ours that show at least our error: the
    // comparison the issue asks ours to win.
    let unbeaten = |ours: &FrontierFigures| -> Vec<String> {
        figures
            .iter()
            .filter(|(family, _)| matches!(family, Family::Fixed | Family::Paper | Family::Headroom))
            .map(|(_, f)| f)
            .filter(|f| f.worst_frame_ms >= ours.worst_frame_ms)
            .filter(|f| f.streaming_psnr_db.unwrap_or(f64::NEG_INFINITY) >= ours.streaming_psnr_db.unwrap_or(f64::NAN))
            .map(|f| f.name.clone())
            .collect()
    };
    // A stronger reading than the issue's, over every α flown (reported, not a target):
    // each run of the other families matched by some predictive + path run with no higher
    // worst frame and no more error.
    let path_family: Vec<&FrontierFigures> = figures
        .iter()
        .filter(|(family, _)| *family == Family::PredictivePath)
        .map(|(_, f)| f)
        .collect();
    let undominated: Vec<String> = figures
        .iter()
        .filter(|(family, _)| matches!(family, Family::Fixed | Family::Paper | Family::Headroom))
        .map(|(_, f)| f)
        .filter(|f| !path_family.iter().any(|p| matched_on_both(p, f)))
        .map(|f| f.name.clone())
        .collect();
    let mut notes = String::new();
    if !path_family.is_empty() {
        notes.push_str(&format!(
            "\nBeyond the targets: runs of the fixed, paper and headroom families that no predictive + path run \
             (α = {} ms) matches with a worst frame no higher and no more error: {}.\n",
            path_family
                .iter()
                .filter_map(|f| f.alpha_ms)
                .map(|a| format!("{a}"))
                .collect::<Vec<_>>()
                .join(", "),
            if undominated.is_empty() {
                "none".to_string()
            } else {
                undominated.join(", ")
            }
        ));
    }
    if let Some(ours) = path {
        let left = unbeaten(ours);
        notes.push_str(&format!(
            "\nRuns of the fixed, paper and headroom families with a worst frame at or above the path-prefetch run's \
             ({:.2} ms) and no more error (at least its PSNR after start-up): {}.\n",
            ours.worst_frame_ms,
            if left.is_empty() {
                "none".to_string()
            } else {
                left.join(", ")
            }
        ));
    }
    let [worst, over_2alpha, psnr_gain, flood] = path_prefetch_checks(path, baseline);
    let checks: Vec<Check> = vec![
        worst,
        over_2alpha,
        psnr_gain,
        (
            "predictive α=12 + motion: after-start-up PSNR − baseline's (dB)".into(),
            psnr(motion).zip(psnr(baseline)).map(|(a, b)| a - b),
            "≥ −1",
            |v| v >= -1.0,
        ),
        (
            "predictive α=12 + motion: worst frame (ms)".into(),
            motion.map(|f| f.worst_frame_ms),
            "≤ 24",
            |v| v <= 24.0,
        ),
        (
            "predictive α=12 + path: fixed, paper and headroom runs at or above its worst frame with no more error"
                .into(),
            path.map(|ours| unbeaten(ours).len() as f64),
            "0",
            |v| v == 0.0,
        ),
        flood,
        (
            "time to 40 dB after the start: paper α=12 / predictive α=12 + path".into(),
            paper
                .and_then(|p| p.time_to_40db_start_s)
                .zip(path.and_then(|f| f.time_to_40db_start_s))
                .map(|(p, ours)| p / ours.max(1e-9)),
            "≥ 2",
            |v| v >= 2.0,
        ),
    ];
    let mut text = checks_table("## The issue's targets", checks);
    text.push_str(&notes);
    text
}

/// Whether `ours` has a worst frame no higher than `theirs` and an after-start-up PSNR no
/// lower (a run without one matches nothing and is matched by nothing).
fn matched_on_both(ours: &FrontierFigures, theirs: &FrontierFigures) -> bool {
    match (ours.streaming_psnr_db, theirs.streaming_psnr_db) {
        (Some(a), Some(b)) => ours.worst_frame_ms <= theirs.worst_frame_ms && a >= b,
        _ => false,
    }
}

/// The targets of the predictive α = 12 ms run with path prefetch against the baseline, on
/// any city: worst frame at most 2α, no frame over 2α after the first second, at least the
/// baseline's PSNR after start-up, at most 1.2× its MB per path second.
pub(crate) fn path_prefetch_checks(path: Option<&FrontierFigures>, baseline: Option<&FrontierFigures>) -> [Check; 4] {
    let psnr = |f: Option<&FrontierFigures>| f.and_then(|f| f.streaming_psnr_db);
    [
        (
            "predictive α=12 + path: worst frame (ms)".into(),
            path.map(|f| f.worst_frame_ms),
            "≤ 24",
            |v| v <= 24.0,
        ),
        (
            "predictive α=12 + path: frames over 2α after the first second".into(),
            path.map(|f| f.frames_over_2alpha as f64),
            "0",
            |v| v == 0.0,
        ),
        (
            "predictive α=12 + path: after-start-up PSNR − baseline's (dB)".into(),
            psnr(path).zip(psnr(baseline)).map(|(a, b)| a - b),
            "≥ 0",
            |v| v >= 0.0,
        ),
        (
            "predictive α=12 + path: MB per path s / baseline's".into(),
            path.zip(baseline).map(|(a, b)| a.mb_per_path_s / b.mb_per_path_s),
            "≤ 1.2",
            |v| v <= 1.2,
        ),
    ]
}

/// `frontier.png`: after-start-up PSNR against worst frame (log axis), each family a line
/// through its runs by worst frame, the Pareto front dashed; the legend beside the chart, so
/// that no run hides under it.
fn draw_frontier(figures: &[(Family, FrontierFigures)], path: &Path) -> Result<()> {
    let points: Vec<(Family, f64, f64, String)> = figures
        .iter()
        .filter_map(|(family, f)| {
            f.streaming_psnr_db
                .filter(|p| p.is_finite())
                .map(|p| (*family, f.worst_frame_ms.max(1e-3), p, point_label(*family, f)))
        })
        .collect();
    if points.is_empty() {
        eprintln!("frontier: no run has an error after start-up; frontier.png not drawn");
        return Ok(());
    }
    let (x_lo, x_hi) = points
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(lo, hi), p| (lo.min(p.1), hi.max(p.1)));
    let (y_lo, y_hi) = points.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
        (lo.min(p.2), hi.max(p.2))
    });
    // The runs' own span (not whole decades, which left most runs within one decade's
    // first fifth), labelled at round values chosen for that span.
    let x_range = (x_lo / 1.08)..(x_hi * 1.08);
    let x_keys = log_axis_keys(x_range.start, x_range.end);
    let pad = ((y_hi - y_lo) * 0.08).max(0.25);
    let y_range = (y_lo - pad)..(y_hi + pad);
    let size = (FRONTIER_CHART_WIDTH + FRONTIER_LEGEND_WIDTH, report::SPEED_ERROR_SIZE.1);
    let families: Vec<Family> = Family::ALL
        .into_iter()
        .filter(|family| points.iter().any(|p| p.0 == *family))
        .collect();
    render_png(path, size, |root| {
        let (chart_area, legend_area) = root.split_horizontally(FRONTIER_CHART_WIDTH);
        let mut chart = ChartBuilder::on(&chart_area)
            .caption(
                "The frontier: error after start-up against worst frame",
                ("sans-serif", 24),
            )
            .margin(16)
            .x_label_area_size(50)
            .y_label_area_size(70)
            .build_cartesian_2d(x_range.log_scale().with_key_points(x_keys), y_range)
            .map_err(plot_error)?;
        chart
            .configure_mesh()
            .x_label_formatter(&|x| {
                if *x >= 10.0 {
                    format!("{x:.0}")
                } else {
                    format!("{x:.1}")
                }
            })
            .x_desc("worst frame (ms, log scale)")
            .y_desc("PSNR of the mean MSE after start-up (dB)")
            .label_style(("sans-serif", 14))
            .axis_desc_style(("sans-serif", 16))
            .draw()
            .map_err(plot_error)?;
        // The front first, under the families.
        let xy: Vec<(f64, f64)> = points.iter().map(|p| (p.1, p.2)).collect();
        let front: Vec<(f64, f64)> = pareto_front(&xy).into_iter().map(|i| xy[i]).collect();
        let mut steps = Vec::new();
        for (i, &(x, y)) in front.iter().enumerate() {
            if i > 0 {
                steps.push((x, front[i - 1].1));
            }
            steps.push((x, y));
        }
        chart
            .draw_series(DashedLineSeries::new(steps, 6, 4, BLACK.mix(0.5).stroke_width(2)))
            .map_err(plot_error)?;
        for family in &families {
            let mut line: Vec<(f64, f64)> = points.iter().filter(|p| p.0 == *family).map(|p| (p.1, p.2)).collect();
            line.sort_by(|a, b| a.0.total_cmp(&b.0));
            let color = family.color();
            chart
                .draw_series(LineSeries::new(line.clone(), color.stroke_width(2)))
                .map_err(plot_error)?;
            chart
                .draw_series(line.iter().map(|&p| Circle::new(p, 4, color.filled())))
                .map_err(plot_error)?;
        }
        // Each run's setting beside its point (its family is its colour).
        chart
            .draw_series(points.iter().map(|(family, x, y, label)| {
                EmptyElement::at((*x, *y))
                    + Text::new(
                        label.clone(),
                        (6, -14),
                        ("sans-serif", 12).into_font().color(&family.color()),
                    )
            }))
            .map_err(plot_error)?;
        // The legend: the front, then each family flown.
        let row = |i: usize| 60 + 26 * i as i32;
        let entries = std::iter::once(("Pareto front (dashed)", BLACK.mix(0.5)))
            .chain(families.iter().map(|f| (f.label(), f.color().mix(1.0))));
        for (i, (text, color)) in entries.enumerate() {
            let y = row(i);
            legend_area
                .draw(&PathElement::new([(8, y), (36, y)], color.stroke_width(3)))
                .map_err(plot_error)?;
            legend_area
                .draw(&Text::new(text, (44, y - 8), ("sans-serif", 14)))
                .map_err(plot_error)?;
        }
        let notes = row(families.len() + 1) + 10;
        for (i, text) in ["point labels: α (ms), load size (MB)", "or lead time of the run"]
            .into_iter()
            .enumerate()
        {
            legend_area
                .draw(&Text::new(text, (8, notes + 20 * i as i32), ("sans-serif", 13)))
                .map_err(plot_error)?;
        }
        Ok(())
    })
}

/// Width of `frontier.png`'s chart and of the legend beside it, pixels.
const FRONTIER_CHART_WIDTH: u32 = 900;
const FRONTIER_LEGEND_WIDTH: u32 = 360;

/// What tells a run from the others of its family on the chart: its α, load size or lead.
fn point_label(family: Family, f: &FrontierFigures) -> String {
    match family {
        Family::Baseline => "baseline".into(),
        Family::Fixed => format!("{} MB", f.dir.trim_start_matches("fixed-s")),
        Family::PredictivePathLead => format!("lead {} s", f.dir.rsplit("lead").next().unwrap_or("?")),
        _ => f.alpha_ms.map_or_else(|| f.dir.clone(), |a| format!("α {a}")),
    }
}

/// Round values for a log axis over `lo..hi`: 1, 2, 3 and 5 times each power of ten where
/// the span covers more than a decade, finer steps (1, 1.2, 1.5, 2, 2.5, 3, 4, 5, 6, 7, 8)
/// where it covers less, so that a narrow span still has several labels.
fn log_axis_keys(lo: f64, hi: f64) -> Vec<f64> {
    if !(lo > 0.0 && hi > lo && hi.is_finite()) {
        return Vec::new();
    }
    let mantissas: &[f64] = if hi / lo > 10.0 {
        &[1.0, 2.0, 3.0, 5.0]
    } else {
        &[1.0, 1.2, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0]
    };
    let first = lo.log10().floor() as i32;
    let last = hi.log10().ceil() as i32;
    (first..=last)
        .flat_map(|e| mantissas.iter().map(move |m| m * 10f64.powi(e)))
        .filter(|k| (lo..=hi).contains(k))
        .collect()
}

#[cfg(test)]
mod tests {

    #[test]
    fn log_axis_keys_are_round_values_inside_the_span() {
        // A span within a decade gets the fine steps; a wider one 1, 2, 3, 5 per decade.
        assert_eq!(log_axis_keys(18.5, 32.2), vec![20.0, 25.0, 30.0]);
        assert_eq!(
            log_axis_keys(18.0, 580.0),
            vec![20.0, 30.0, 50.0, 100.0, 200.0, 300.0, 500.0]
        );
        assert!(log_axis_keys(0.0, 10.0).is_empty() && log_axis_keys(5.0, 5.0).is_empty());
    }
    use super::*;

    fn row(time_s: f64, dt_ms: f64, psnr_db: Option<f64>) -> FrameRow {
        FrameRow {
            time_s,
            dt_ms,
            tw_ms: dt_ms,
            tm_ms: 0.0,
            tb_ms: 0.0,
            tbl_ms: 0.0,
            tbu_ms: 0.0,
            load_size_mb: 0.0,
            mip_bias: 0.0,
            mips: 0,
            bytes: 0,
            blocks_bound: 0,
            mip_deficit: None,
            psnr_db,
            mse: None,
            cycle_started: None,
            reads_in_flight_bytes: None,
        }
    }

    #[test]
    fn time_to_a_level_counts_from_the_event_to_the_first_measured_frame_reaching_it() {
        let frames = [
            row(0.0, 8.0, Some(12.0)),
            row(0.2, 8.0, None),
            row(0.4, 8.0, Some(39.9)),
            row(0.6, 8.0, Some(41.0)),
            row(1.0, 8.0, Some(25.0)),
            row(1.2, 8.0, Some(45.0)),
        ];
        assert_eq!(time_to_level(&frames, 0.0, 1.0, 40.0), Some(0.6));
        // From a cut at 0.9 s: the frame at 1.0 s is under, 1.2 s reaches it.
        let t = time_to_level(&frames, 0.9, 2.0, 40.0).expect("reached");
        assert!((t - 0.3).abs() < 1e-12);
        // Not before the next event: none.
        assert_eq!(time_to_level(&frames, 0.9, 1.1, 40.0), None);
    }

    #[test]
    fn the_pareto_front_keeps_the_runs_no_other_beats_on_both() {
        // (worst frame, PSNR): the second is beaten by the first (lower worst, higher
        // PSNR); the fourth ties the third's PSNR at a higher worst frame.
        let points = [(20.0, 45.0), (25.0, 44.0), (500.0, 48.0), (600.0, 48.0), (10.0, 30.0)];
        assert_eq!(pareto_front(&points), vec![4, 0, 2]);
        assert_eq!(quantile(&[5.0, 1.0, 3.0, 2.0, 4.0], 0.99), 5.0);
        assert_eq!(quantile(&[5.0, 1.0, 3.0, 2.0, 4.0], 0.5), 3.0);
    }

    #[test]
    fn the_causes_table_gives_each_share_and_the_psnr_without_it() {
        let causes = ErrorCauses {
            lag_mse: 1.0,
            load_mse: 3.0,
            bias_mse: 0.0,
            budget_mse: 0.0,
        };
        let figures = FrontierFigures {
            dir: "predictive-a12".into(),
            name: "predictive α=12 ms".into(),
            family: Family::Predictive.label(),
            alpha_ms: Some(12.0),
            frames: 10,
            worst_frame_ms: 20.0,
            p99_frame_ms: 15.0,
            frames_over_alpha: 0,
            frames_over_2alpha: 0,
            mb_per_path_s: 1.0,
            startup_psnr_db: None,
            streaming_psnr_db: Some(psnr_of_mse_db(4.0)),
            streaming_measured_frames: Some(10),
            time_to_40db_start_s: None,
            time_to_40db_after_cuts_s: Vec::new(),
            streaming_error_causes: Some(causes),
        };
        let without_causes = FrontierFigures {
            streaming_error_causes: None,
            ..figures.clone()
        };
        assert_eq!(causes_table(&[(Family::Predictive, without_causes)]), "");
        let table = causes_table(&[(Family::Predictive, figures.clone())]);
        let row = format!(
            "| predictive α=12 ms | 4.000 | 25 % | 75 % | 0 % | 0 % | {:.2} / {:.2} / {:.2} / {:.2} |",
            psnr_of_mse_db(3.0),
            psnr_of_mse_db(1.0),
            psnr_of_mse_db(4.0),
            psnr_of_mse_db(4.0)
        );
        assert!(table.contains(&row), "{table}");
        let dir = std::env::temp_dir().join(format!("citystream-frontier-causes-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temporary directory");
        let png = dir.join("frontier-causes.png");
        draw_causes(&[(Family::Predictive, figures)], &png).expect("drawn");
        assert!(std::fs::metadata(&png).expect("written").len() > 1000);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_run_of_another_family_is_left_only_when_no_path_run_matches_it_on_both() {
        let run = |dir: &str, family: Family, worst_frame_ms: f64, psnr_db: f64| {
            let figures = FrontierFigures {
                dir: dir.into(),
                name: dir.into(),
                family: family.label(),
                alpha_ms: Some(12.0),
                frames: 10,
                worst_frame_ms,
                p99_frame_ms: worst_frame_ms,
                frames_over_alpha: 0,
                frames_over_2alpha: 0,
                mb_per_path_s: 1.0,
                startup_psnr_db: None,
                streaming_psnr_db: Some(psnr_db),
                streaming_measured_frames: Some(10),
                time_to_40db_start_s: None,
                time_to_40db_after_cuts_s: Vec::new(),
                streaming_error_causes: None,
            };
            (family, figures)
        };
        let mut figures = vec![
            run("predictive-a8-path", Family::PredictivePath, 15.0, 48.0),
            run("predictive-a12-path", Family::PredictivePath, 20.0, 50.0),
            // Matched: the α = 12 run is as fast and better; the α = 8 run is faster and as good.
            run("fixed-s4", Family::Fixed, 20.0, 49.0),
            run("fixed-s2", Family::Fixed, 16.0, 48.0),
            // Better than either on error at a frame no path run undercuts with that error.
            run("headroom-a16", Family::Headroom, 25.0, 51.0),
            // Faster than every path run: nothing matches it on the worst frame.
            run("fixed-s1", Family::Fixed, 14.0, 40.0),
        ];
        let text = checks(&figures);
        assert!(
            text.contains("matches with a worst frame no higher and no more error: headroom-a16, fixed-s1."),
            "{text}"
        );
        // The chart of the same runs, its legend beside the chart: pixels drawn there.
        let dir = std::env::temp_dir().join(format!("citystream-frontier-chart-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temporary directory");
        let png = dir.join("frontier.png");
        draw_frontier(&figures, &png).expect("drawn");
        let image = image::open(&png).expect("a PNG").to_rgb8();
        assert_eq!(image.width(), FRONTIER_CHART_WIDTH + FRONTIER_LEGEND_WIDTH);
        let legend_ink = (FRONTIER_CHART_WIDTH..image.width())
            .flat_map(|x| (0..image.height()).map(move |y| (x, y)))
            .filter(|&(x, y)| image.get_pixel(x, y).0 != [255, 255, 255])
            .count();
        assert!(legend_ink > 500, "legend pixels: {legend_ink}");
        let _ = std::fs::remove_dir_all(&dir);
        figures.truncate(4);
        assert!(
            checks(&figures).contains("matches with a worst frame no higher and no more error: none."),
            "{}",
            checks(&figures)
        );
        // The α = 12 run's own check counts the headroom run only when it is not faster.
        figures.push(run("headroom-a20", Family::Headroom, 22.0, 50.5));
        assert!(checks(&figures).contains("and no more error (at least its PSNR after start-up): headroom-a20."));
    }

    #[test]
    fn each_point_is_labelled_with_what_sets_it_apart_in_its_family() {
        let figures = |dir: &str, alpha_ms: Option<f64>| FrontierFigures {
            dir: dir.into(),
            name: dir.into(),
            family: "",
            alpha_ms,
            frames: 0,
            worst_frame_ms: 0.0,
            p99_frame_ms: 0.0,
            frames_over_alpha: 0,
            frames_over_2alpha: 0,
            mb_per_path_s: 0.0,
            startup_psnr_db: None,
            streaming_psnr_db: None,
            streaming_measured_frames: None,
            time_to_40db_start_s: None,
            time_to_40db_after_cuts_s: Vec::new(),
            streaming_error_causes: None,
        };
        assert_eq!(point_label(Family::Fixed, &figures("fixed-s16", None)), "16 MB");
        assert_eq!(point_label(Family::Paper, &figures("paper-a8", Some(8.0))), "α 8");
        assert_eq!(
            point_label(
                Family::PredictivePathLead,
                &figures("predictive-a12-path-lead0.5", Some(12.0))
            ),
            "lead 0.5 s"
        );
        assert_eq!(point_label(Family::Baseline, &figures("baseline", None)), "baseline");
    }

    #[test]
    fn the_runs_cover_every_family_once_per_setting() {
        let runs = frontier_runs(256);
        assert_eq!(runs.len(), 1 + 6 + 4 * 4 + 2 + FRONTIER_LEADS_S.len());
        let mut dirs: Vec<&str> = runs.iter().map(|r| r.run.dir.as_str()).collect();
        dirs.sort_unstable();
        dirs.dedup();
        assert_eq!(dirs.len(), runs.len(), "directory names are unique");
        let path = runs.iter().find(|r| r.run.dir == "predictive-a12-path").expect("flown");
        assert_eq!(path.family, Family::PredictivePath);
        assert!(path.run.args.windows(2).any(|w| w == ["--prefetch", "path"]));
        assert!(path.run.args.windows(2).any(|w| w == ["--psnr-interval", "12"]));
    }
}
