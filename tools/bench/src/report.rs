//! `citystream report`: compare flythrough runs the way the paper's §4 does.
//!
//! Inputs, per run directory written by the engine's `flythrough --out DIR`:
//! - `DIR/summary.json`: objects `{"median","mean","max","min"}` under
//!   `frame_ms`, `tw_ms`, `mips_per_s`, `mb_per_s`, `load_size_mb`,
//!   `mip_bias`, and optionally (absent or `null` when not measured)
//!   `mip_deficit` and `psnr_db`, with `error_frames` (`measured`, `identical`) and
//!   `psnr_of_mean_mse_db` when present; plus `frames`, `duration_s`, `policy`,
//!   `bytes_streamed`, `mips_streamed`, `blocks_bound`,
//!   `peak_resident_bytes`, and when present `unique_bytes_streamed`,
//!   `memory_budget_bytes` (null: unlimited), `eviction` and
//!   `frames_over_budget`. Other keys are ignored.
//! - `DIR/frames.csv`: a header naming at least the columns
//!   [`FRAME_COLUMNS`](crate::report_runs::FRAME_COLUMNS) (any order) and optionally `mse`, then one row per frame;
//!   `mip_deficit`, `psnr_db` and `mse` cells are empty on frames where they were not
//!   measured.
//!
//! Outputs, in the report directory:
//! - `table.md`: the rows of the paper's Table 3 (frame latency, `t_w`,
//!   Mip/s, MB/s, `s`, `b`) plus PSNR and mip deficit, with median, average
//!   and max columns per run side by side, and a table of run totals. A
//!   statistic the summary leaves out (PSNR, mip deficit) is taken from the
//!   measured cells of `frames.csv`, or shown as "n/a" when there are none. An image-error
//!   table gives per run the headline error, the PSNR of the mean MSE over every measured
//!   frame (from the summary, or from the CSV's `mse` column), and how many of the measured
//!   frames were identical to their reference.
//! - `<run>_fig6.png` per run: the four panels of the paper's Fig. 6
//!   (t_w and t_m; t_b with its edges t_bl and t_bu; s and b; MB/s and
//!   Mip/s over time, rates counted per 0.10423 s window).
//! - `speed_vs_error.png`: one labelled point per run at (mean frame
//!   latency, PSNR of the mean MSE), with a line out to its max frame latency.
//!
//! Charts are drawn with `plotters` into an RGB buffer and encoded with the
//! `image` crate; the text uses the embedded DejaVu Sans font (licence in
//! `tools/bench/assets/fonts/`), so no system font is needed at run time.

use std::collections::HashSet;
use std::fmt::Write as _;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use anyhow::{anyhow, bail, Context, Result};
use citystream_streaming::bench::stats::{Stats, RATE_WINDOW_S};
use citystream_streaming::controller::BYTES_PER_MB;

use crate::image_error::{PhaseError, STARTUP_S};
use crate::report_runs::{load_run, read_frames_csv, FrameRow, Run, SummaryJson};
use plotters::coord::Shift;
use plotters::prelude::*;

/// Options of `citystream report`.
#[derive(Debug, clap::Args)]
pub struct ReportArgs {
    /// A flythrough output directory (holding summary.json and frames.csv);
    /// repeat for each run to compare.
    #[arg(long = "run", required = true)]
    runs: Vec<PathBuf>,
    /// Display name of each run, in the order of --run (default: the
    /// directory's name).
    #[arg(long = "name")]
    names: Vec<String>,
    /// Directory for table.md and the PNG charts (created if missing).
    #[arg(long, value_parser = citystream_gen::files::local_out)]
    out: PathBuf,
}

/// One run to report: where its files are and what to call it.
#[derive(Debug, Clone)]
pub struct RunInput {
    /// The flythrough output directory.
    pub dir: PathBuf,
    /// Name shown in the table and the chart titles.
    pub name: String,
}

/// What [`write_report`] wrote.
#[derive(Debug, Clone)]
pub struct ReportOutputs {
    /// The Markdown comparison table.
    pub table: PathBuf,
    /// One Fig. 6 chart per run, in input order.
    pub run_charts: Vec<PathBuf>,
    /// The speed-against-error chart.
    pub speed_vs_error: PathBuf,
}

fn phase_cell(phase: Option<PhaseError>) -> (String, String) {
    phase.map_or(("n/a".to_string(), "n/a".to_string()), |p| {
        (
            number(p.psnr_of_mean_mse_db),
            format!("{} / {}", p.error_frames.identical, p.error_frames.measured),
        )
    })
}

/// `citystream report`.
pub fn run(args: &ReportArgs) -> Result<()> {
    if !args.names.is_empty() && args.names.len() != args.runs.len() {
        bail!(
            "{} --name given for {} --run; give one name per run or none",
            args.names.len(),
            args.runs.len()
        );
    }
    let inputs: Vec<RunInput> = args
        .runs
        .iter()
        .enumerate()
        .map(|(i, dir)| RunInput {
            dir: dir.clone(),
            name: args.names.get(i).cloned().unwrap_or_else(|| default_name(dir)),
        })
        .collect();
    let outputs = write_report(&inputs, &args.out)?;
    print_outputs(&outputs);
    Ok(())
}

/// Print where the report went (shared with `citystream bench`).
pub fn print_outputs(outputs: &ReportOutputs) {
    println!("table:          {}", outputs.table.display());
    for chart in &outputs.run_charts {
        println!("run chart:      {}", chart.display());
    }
    println!("speed vs error: {}", outputs.speed_vs_error.display());
}

/// The name of a run directory, for runs given without `--name`.
pub fn default_name(dir: &Path) -> String {
    dir.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .filter(|n| !n.is_empty() && n != "." && n != "..")
        .unwrap_or_else(|| dir.display().to_string())
}

/// Read every run and write `table.md`, one Fig. 6 chart per run and
/// `speed_vs_error.png` into `out` (created if missing). Fails, naming the
/// file (and line for CSV), on a missing or malformed input, and on two
/// runs whose names map to the same chart file.
pub fn write_report(inputs: &[RunInput], out: &Path) -> Result<ReportOutputs> {
    let runs = load_runs(inputs)?;
    let mut slugs = HashSet::new();
    for run in &runs {
        if !slugs.insert(file_slug(&run.name)) {
            bail!(
                "two runs are named `{}` (after making the names file-safe); give distinct --name values",
                run.name
            );
        }
    }
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;

    let table = out.join("table.md");
    citystream_gen::files::write_atomically(&table, markdown_table(&runs).as_bytes())?;

    let mut run_charts = Vec::with_capacity(runs.len());
    for run in &runs {
        let path = out.join(format!("{}_fig6.png", file_slug(&run.name)));
        draw_fig6(run, &path).with_context(|| format!("drawing {}", path.display()))?;
        run_charts.push(path);
    }
    let speed_vs_error = out.join("speed_vs_error.png");
    draw_speed_vs_error(&runs, &speed_vs_error).with_context(|| format!("drawing {}", speed_vs_error.display()))?;
    Ok(ReportOutputs {
        table,
        run_charts,
        speed_vs_error,
    })
}

/// One speed-against-error chart of runs from several reports, at `path`.
pub fn write_speed_vs_error(inputs: &[RunInput], path: &Path) -> Result<()> {
    let runs = load_runs(inputs)?;
    draw_speed_vs_error(&runs, path).with_context(|| format!("drawing {}", path.display()))
}

/// Frames of the run in `dir` slower than `limit_ms` once `after_s` seconds of its path
/// have passed, from its frames.csv.
pub fn frames_over(dir: &Path, after_s: f64, limit_ms: f64) -> Result<u64> {
    let frames = read_frames_csv(&dir.join("frames.csv"))?;
    Ok(frames
        .iter()
        .filter(|f| f.time_s > after_s && f.dt_ms > limit_ms)
        .count() as u64)
}

/// What a run's cycles loaded and bound, from its frames.csv: the demand side of its
/// frame latency.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LoadProfile {
    pub frames: u64,
    /// MB (2^20 bytes) loaded per frame: mean and max.
    pub mb_per_frame: [f64; 2],
    /// Frames whose load reached 90 % of their load size `s` (the cycle was cut by `s`).
    pub frames_at_load_size: u64,
    /// Sparse blocks bound per frame: mean and max.
    pub blocks_per_frame: [f64; 2],
    /// Frames longer than twice the median frame, and the share of the path's time they
    /// take.
    pub frames_over_twice_median: u64,
    pub time_share_over_twice_median: f64,
    /// Loading cycles started (None for older CSVs).
    pub cycles: Option<u64>,
    /// With a disk model, MB each cycle read (mean and max) and the cycles whose reads
    /// reached 90 % of their load size `s`.
    pub mb_per_cycle: Option<[f64; 2]>,
    pub cycles_at_load_size: Option<u64>,
}

/// The [`LoadProfile`] of the run in `dir`.
pub fn load_profile(dir: &Path) -> Result<LoadProfile> {
    let frames = read_frames_csv(&dir.join("frames.csv"))?;
    let n = frames.len() as f64;
    let mb: Vec<f64> = frames.iter().map(|f| f.bytes as f64 / BYTES_PER_MB).collect();
    let blocks: Vec<f64> = frames.iter().map(|f| f.blocks_bound as f64).collect();
    let mut dt: Vec<f64> = frames.iter().map(|f| f.dt_ms).collect();
    dt.sort_by(f64::total_cmp);
    let median = dt[dt.len() / 2];
    let slow: Vec<f64> = dt.iter().copied().filter(|&d| d > 2.0 * median).collect();
    let mean_max = |v: &[f64]| [v.iter().sum::<f64>() / n, v.iter().copied().fold(0.0, f64::max)];
    let cycles = frames
        .iter()
        .map(|f| f.cycle_started)
        .collect::<Option<Vec<bool>>>()
        .map(|started| started.iter().filter(|s| **s).count() as u64);
    // A cycle reads all it loads in its first frame, on a modelled disk.
    let cycle_reads: Option<Vec<(f64, f64)>> = frames
        .iter()
        .filter(|f| f.cycle_started == Some(true))
        .map(|f| {
            f.reads_in_flight_bytes
                .map(|b| (b as f64 / BYTES_PER_MB, f.load_size_mb))
        })
        .collect();
    let cycle_reads = cycle_reads.filter(|reads| !reads.is_empty());
    Ok(LoadProfile {
        cycles,
        mb_per_cycle: cycle_reads.as_ref().map(|reads| {
            [
                reads.iter().map(|r| r.0).sum::<f64>() / reads.len() as f64,
                reads.iter().map(|r| r.0).fold(0.0, f64::max),
            ]
        }),
        cycles_at_load_size: cycle_reads
            .as_ref()
            .map(|reads| reads.iter().filter(|(mb, s)| *s > 0.0 && *mb >= 0.9 * s).count() as u64),
        frames: frames.len() as u64,
        mb_per_frame: mean_max(&mb),
        frames_at_load_size: frames
            .iter()
            .filter(|f| f.load_size_mb > 0.0 && f.bytes as f64 / BYTES_PER_MB >= 0.9 * f.load_size_mb)
            .count() as u64,
        blocks_per_frame: mean_max(&blocks),
        frames_over_twice_median: slow.len() as u64,
        time_share_over_twice_median: slow.iter().fold(0.0, |a, b| a + b)
            / dt.iter().sum::<f64>().max(f64::MIN_POSITIVE),
    })
}

/// Every run of `inputs`, read; an error for none.
fn load_runs(inputs: &[RunInput]) -> Result<Vec<Run>> {
    if inputs.is_empty() {
        bail!("no runs to report");
    }
    inputs.iter().map(|input| load_run(&input.dir, &input.name)).collect()
}

/// A name reduced to characters safe in a file name.
fn file_slug(name: &str) -> String {
    // Each run of other characters becomes one `_`.
    let mut slug = String::with_capacity(name.len());
    for c in name.chars() {
        if c.is_ascii_alphanumeric() || c == '-' || c == '_' || c == '.' {
            slug.push(c);
        } else if !slug.ends_with('_') {
            slug.push('_');
        }
    }
    if slug.trim_matches(['_', '.']).is_empty() {
        "run".to_string()
    } else {
        slug
    }
}

fn markdown_table(runs: &[Run]) -> String {
    let mut out = String::new();
    let _ = writeln!(out, "# Streaming performance comparison\n");
    let _ = writeln!(
        out,
        "Rows as in the paper's Table 3, plus PSNR against the fully resident reference \
         (every measured frame, identical ones at the summary's ceiling, 100 dB) and the mip \
         deficit; median, average and max per run. The image-error table at the end compares \
         runs by the PSNR of the mean MSE.\n"
    );
    let _ = write!(out, "| |");
    for run in runs {
        let name = escape_cell(&run.name);
        let _ = write!(out, " {name} median | {name} average | {name} max |");
    }
    let _ = write!(out, "\n|---|");
    for _ in runs {
        let _ = write!(out, "---:|---:|---:|");
    }
    out.push('\n');
    type Pick = fn(&Run) -> Option<Stats>;
    let rows: [(&str, Pick); 8] = [
        ("Frame latency (ms)", |r| Some(r.summary.frame_ms.into())),
        ("t_w latency (ms)", |r| Some(r.summary.tw_ms.into())),
        ("Transfer rate (Mip/s)", |r| Some(r.summary.mips_per_s.into())),
        ("Transfer rate (MB/s)", |r| Some(r.summary.mb_per_s.into())),
        ("Load size s (MB)", |r| Some(r.summary.load_size_mb.into())),
        ("Mipmap bias b", |r| Some(r.summary.mip_bias.into())),
        ("PSNR per frame (dB)", |r| r.psnr_db),
        ("Mip deficit", |r| r.mip_deficit),
    ];
    for (label, pick) in rows {
        let _ = write!(out, "| {label} |");
        for run in runs {
            match pick(run) {
                Some(s) => {
                    let _ = write!(out, " {} | {} | {} |", number(s.median), number(s.mean), number(s.max));
                }
                None => out.push_str(" n/a | n/a | n/a |"),
            }
        }
        out.push('\n');
    }
    let _ = writeln!(
        out,
        "\n## Per run, as the paper's Table 3\n\n| | Median | Average | Max |\n|---|---:|---:|---:|"
    );
    for run in runs {
        let _ = writeln!(out, "| **{}** | | | |", escape_cell(&run.name));
        for (label, pick) in rows {
            match pick(run) {
                Some(s) => {
                    let _ = writeln!(
                        out,
                        "| {label} | {} | {} | {} |",
                        number(s.median),
                        number(s.mean),
                        number(s.max)
                    );
                }
                None => {
                    let _ = writeln!(out, "| {label} | n/a | n/a | n/a |");
                }
            }
        }
    }
    let _ = writeln!(
        out,
        "\n## Runs\n\n| Run | Policy | Frames | Duration (s) | MB streamed | Unique MB | Streamed / unique | Mips streamed | Blocks bound | Peak resident (MB) | Budget (MB) | Peak / budget | Frames over budget | Directory |\n|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"
    );
    let optional = |value: Option<f64>| value.map_or_else(|| "n/a".to_string(), number);
    for run in runs {
        let s = &run.summary;
        let unique = s.unique_bytes_streamed.map(|u| u as f64);
        let budget = s.memory_budget_bytes.map(|b| b as f64);
        let _ = writeln!(
            out,
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
            escape_cell(&run.name),
            escape_cell(&s.policy),
            s.frames,
            number(s.duration_s),
            number(s.bytes_streamed as f64 / BYTES_PER_MB),
            optional(unique.map(|u| u / BYTES_PER_MB)),
            optional(unique.filter(|&u| u > 0.0).map(|u| s.bytes_streamed as f64 / u)),
            s.mips_streamed,
            s.blocks_bound,
            number(s.peak_resident_bytes as f64 / BYTES_PER_MB),
            match (&s.eviction, budget) {
                (None, _) => "n/a".to_string(),
                (Some(_), None) => "unlimited".to_string(),
                (Some(_), Some(b)) => number(b / BYTES_PER_MB),
            },
            optional(budget.filter(|&b| b > 0.0).map(|b| s.peak_resident_bytes as f64 / b)),
            s.frames_over_budget
                .map_or_else(|| "n/a".to_string(), |f| f.to_string()),
            escape_cell(&run.dir.display().to_string())
        );
    }
    let _ = writeln!(
        out,
        "\n## Image error\n\nThe PSNR of the mean squared error of the streaming after the start-up fill \
         (frames from {STARTUP_S} s of path time on: the headline), of the start-up fill, and over every \
         measured frame, with how many measured frames were identical to their reference.\n\n\
         | Run | Streaming PSNR of mean MSE (dB) | Identical / measured | Start-up PSNR of mean MSE (dB) | \
         Identical / measured | All frames PSNR of mean MSE (dB) | Identical / measured |\n\
         |---|---:|---:|---:|---:|---:|---:|"
    );
    for run in runs {
        let (streaming, startup, all) = match run.error {
            Some(e) => (
                phase_cell(e.streaming),
                phase_cell(e.startup),
                (number(e.psnr_of_mean_mse_db), e.frames_cell()),
            ),
            None => {
                let na = || ("n/a".to_string(), "n/a".to_string());
                (na(), na(), na())
            }
        };
        let _ = writeln!(
            out,
            "| {} | {} | {} | {} | {} | {} | {} |",
            escape_cell(&run.name),
            streaming.0,
            streaming.1,
            startup.0,
            startup.1,
            all.0,
            all.1
        );
    }
    let _ = writeln!(out, "\nMB = 2^20 bytes. Transfer rates per {RATE_WINDOW_S} s window.");
    out
}

/// One line on a finished run for progress output: frame latency, transfer
/// rate and image error from its `summary.json`.
pub fn run_headline(dir: &Path) -> Result<String> {
    let path = dir.join("summary.json");
    let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let s: SummaryJson =
        serde_json::from_str(&text).with_context(|| format!("{}: not a valid flythrough summary", path.display()))?;
    let error = match (s.psnr_of_mean_mse_db, s.error_frames) {
        (Some(psnr), Some(frames)) => format!(
            "{} dB ({} of {} measured frames identical){}",
            number(psnr),
            frames.identical,
            frames.measured,
            s.streaming_psnr_of_mean_mse_db
                .map(|streaming| format!(", after start-up {} dB", number(streaming)))
                .unwrap_or_default()
        ),
        _ => "n/a".to_string(),
    };
    Ok(format!(
        "{} frames, frame latency mean {} / max {} ms, {} MB/s mean, PSNR of mean MSE {error}",
        s.frames,
        number(s.frame_ms.mean),
        number(s.frame_ms.max),
        number(s.mb_per_s.mean),
    ))
}

/// Two decimals, as the paper's tables.
fn number(x: f64) -> String {
    if x.is_finite() {
        format!("{x:.2}")
    } else {
        "n/a".to_string()
    }
}

fn escape_cell(s: &str) -> String {
    s.replace('|', "\\|").replace('\n', " ")
}

/// Size of one Fig. 6 panel in pixels; the per-run chart is 2 × 2 panels.
pub const PANEL_SIZE: (u32, u32) = (800, 500);
/// Size of `speed_vs_error.png` in pixels.
pub const SPEED_ERROR_SIZE: (u32, u32) = (900, 600);

fn ensure_font() -> Result<()> {
    static FONT: &[u8] = include_bytes!("../assets/fonts/DejaVuSans.ttf");
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED.get_or_init(|| plotters::style::register_font("sans-serif", FontStyle::Normal, FONT).is_ok());
    if ok {
        Ok(())
    } else {
        bail!("the embedded chart font could not be loaded")
    }
}

/// Draw into an RGB buffer of `size` and save it as PNG.
pub(crate) fn render_png(
    path: &Path,
    size: (u32, u32),
    draw: impl FnOnce(&DrawingArea<BitMapBackend<'_>, Shift>) -> Result<()>,
) -> Result<()> {
    ensure_font()?;
    let mut buffer = vec![0u8; size.0 as usize * size.1 as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buffer, size).into_drawing_area();
        root.fill(&WHITE).map_err(plot_error)?;
        draw(&root)?;
        root.present().map_err(plot_error)?;
    }
    let image =
        image::RgbImage::from_raw(size.0, size.1, buffer).ok_or_else(|| anyhow!("chart buffer has the wrong size"))?;
    image
        .save_with_format(path, image::ImageFormat::Png)
        .with_context(|| format!("writing {}", path.display()))
}

pub(crate) fn plot_error<E: std::fmt::Display>(e: E) -> anyhow::Error {
    anyhow!("plotting: {e}")
}

/// A value range covering the finite values (and 0 when `from_zero`), with
/// a margin so the lines do not sit on the frame.
fn value_range(values: impl Iterator<Item = f64>, from_zero: bool) -> Range<f64> {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in values.filter(|v| v.is_finite()) {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if !lo.is_finite() {
        return 0.0..1.0;
    }
    if from_zero {
        lo = lo.min(0.0);
        hi = hi.max(0.0);
    }
    let span = hi - lo;
    if span <= f64::EPSILON * hi.abs().max(1.0) {
        // A constant series: centre it in a unit range (from 0 if asked).
        return if from_zero && lo >= 0.0 {
            0.0..hi + 1.0
        } else {
            lo - 0.5..hi + 0.5
        };
    }
    let pad = span * 0.05;
    (if from_zero && lo >= 0.0 { lo } else { lo - pad })..hi + pad
}

/// One line of a chart: label, colour and (x, y) points.
struct Series {
    label: &'static str,
    color: RGBColor,
    points: Vec<(f64, f64)>,
}

impl Series {
    fn new(label: &'static str, color: RGBColor, points: Vec<(f64, f64)>) -> Series {
        let points = points
            .into_iter()
            .filter(|(x, y)| x.is_finite() && y.is_finite())
            .collect();
        Series { label, color, points }
    }
}

/// A time chart with series on the left axis and, optionally, on a right
/// axis of its own unit.
fn time_panel(
    area: &DrawingArea<BitMapBackend<'_>, Shift>,
    title: &str,
    time: Range<f64>,
    left: (&str, Vec<Series>),
    right: Option<(&str, Vec<Series>)>,
) -> Result<()> {
    let left_range = value_range(left.1.iter().flat_map(|s| s.points.iter().map(|p| p.1)), true);
    let right_range = right
        .as_ref()
        .map(|(_, series)| value_range(series.iter().flat_map(|s| s.points.iter().map(|p| p.1)), true));
    let mut builder = ChartBuilder::on(area);
    builder
        .caption(title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(70);
    if right.is_some() {
        builder.right_y_label_area_size(70);
    }
    let mut chart = builder
        .build_cartesian_2d(time.clone(), left_range)
        .map_err(plot_error)?
        .set_secondary_coord(time, right_range.unwrap_or(0.0..1.0));
    chart
        .configure_mesh()
        .x_desc("time (s)")
        .y_desc(left.0)
        .label_style(("sans-serif", 14))
        .axis_desc_style(("sans-serif", 16))
        .draw()
        .map_err(plot_error)?;
    // One-pixel lines: wider polylines get miter spikes at the sharp turns
    // of dense per-frame series.
    for series in left.1 {
        let color = series.color;
        chart
            .draw_series(LineSeries::new(series.points, color.stroke_width(1)))
            .map_err(plot_error)?
            .label(series.label)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
    }
    if let Some((unit, series_list)) = right {
        chart
            .configure_secondary_axes()
            .y_desc(unit)
            .label_style(("sans-serif", 14))
            .axis_desc_style(("sans-serif", 16))
            .draw()
            .map_err(plot_error)?;
        for series in series_list {
            let color = series.color;
            chart
                .draw_secondary_series(LineSeries::new(series.points, color.stroke_width(1)))
                .map_err(plot_error)?
                .label(series.label)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
        }
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .label_font(("sans-serif", 14))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(plot_error)?;
    Ok(())
}

/// Points (time in s, value) of a chart line.
type Points = Vec<(f64, f64)>;

/// MB and mips streamed per second (in that order), counted per
/// [`RATE_WINDOW_S`] window of the frames' `time_s` and plotted at the
/// window's centre.
fn rate_windows(frames: &[FrameRow]) -> (Points, Points) {
    let start = frames
        .iter()
        .map(|f| f.time_s)
        .filter(|t| t.is_finite())
        .fold(f64::INFINITY, f64::min);
    if !start.is_finite() {
        return (Vec::new(), Vec::new());
    }
    let mut mips: Vec<u64> = Vec::new();
    let mut bytes: Vec<u64> = Vec::new();
    for f in frames.iter().filter(|f| f.time_s.is_finite()) {
        let window = ((f.time_s - start) / RATE_WINDOW_S) as usize;
        if mips.len() <= window {
            mips.resize(window + 1, 0);
            bytes.resize(window + 1, 0);
        }
        mips[window] += f.mips;
        bytes[window] += f.bytes;
    }
    // As in the summary's rates, the last window is partial (the run ended
    // inside it), so it is left out unless it is the only one.
    if mips.len() > 1 {
        mips.pop();
        bytes.pop();
    }
    let centre = |i: usize| start + (i as f64 + 0.5) * RATE_WINDOW_S;
    let mb = bytes
        .iter()
        .enumerate()
        .map(|(i, &b)| (centre(i), b as f64 / BYTES_PER_MB / RATE_WINDOW_S))
        .collect();
    let mip = mips
        .iter()
        .enumerate()
        .map(|(i, &m)| (centre(i), m as f64 / RATE_WINDOW_S))
        .collect();
    (mb, mip)
}

const RED: RGBColor = RGBColor(214, 39, 40);
const BLUE: RGBColor = RGBColor(31, 119, 180);
const GREEN: RGBColor = RGBColor(44, 160, 44);
const ORANGE: RGBColor = RGBColor(255, 127, 14);

fn draw_fig6(run: &Run, path: &Path) -> Result<()> {
    let frames = &run.frames;
    let time = value_range(frames.iter().map(|f| f.time_s), false);
    let at = |pick: fn(&FrameRow) -> f64| -> Vec<(f64, f64)> { frames.iter().map(|f| (f.time_s, pick(f))).collect() };
    let size = (PANEL_SIZE.0 * 2, PANEL_SIZE.1 * 2);
    render_png(path, size, |root| {
        let root = root
            .margin(8, 0, 0, 0)
            .titled(
                &format!("{} ({}): streaming over time", run.name, run.summary.policy),
                ("sans-serif", 28),
            )
            .map_err(plot_error)?;
        let panels = root.split_evenly((2, 2));
        time_panel(
            &panels[0],
            "(a) weighted max frame latency t_w and threshold t_m",
            time.clone(),
            (
                "latency (ms)",
                vec![
                    Series::new("t_w", RED, at(|f| f.tw_ms)),
                    Series::new("t_m", BLUE, at(|f| f.tm_ms)),
                ],
            ),
            None,
        )?;
        time_panel(
            &panels[1],
            "(b) average latency t_b and its edges t_bl, t_bu",
            time.clone(),
            (
                "latency (ms)",
                // t_b last, so it is drawn over its edges.
                vec![
                    Series::new("t_bl", GREEN, at(|f| f.tbl_ms)),
                    Series::new("t_bu", BLUE, at(|f| f.tbu_ms)),
                    Series::new("t_b", RED, at(|f| f.tb_ms)),
                ],
            ),
            None,
        )?;
        time_panel(
            &panels[2],
            "(c) load size s and mipmap bias b",
            time.clone(),
            (
                "load size s (MB)",
                vec![Series::new("s (left)", BLUE, at(|f| f.load_size_mb))],
            ),
            Some((
                "mipmap bias b",
                vec![Series::new("b (right)", ORANGE, at(|f| f.mip_bias))],
            )),
        )?;
        let (mb, mip) = rate_windows(frames);
        time_panel(
            &panels[3],
            "(d) transfer rate per 0.10423 s window",
            time.clone(),
            ("MB/s", vec![Series::new("MB/s (left)", GREEN, mb)]),
            Some(("Mip/s", vec![Series::new("Mip/s (right)", RED, mip)])),
        )?;
        Ok(())
    })
}

fn draw_speed_vs_error(runs: &[Run], path: &Path) -> Result<()> {
    let measured: Vec<(&Run, f64)> = runs
        .iter()
        .filter_map(|r| r.error.map(|e| (r, e.headline_db())))
        .filter(|(_, p)| p.is_finite())
        .collect();
    let missing: Vec<&str> = runs
        .iter()
        .filter(|r| !measured.iter().any(|(m, _)| std::ptr::eq(*m, *r)))
        .map(|r| r.name.as_str())
        .collect();
    for name in &missing {
        eprintln!("speed vs error: run `{name}` has no MSE measurement; left out of the chart");
    }
    let x_range = value_range(
        measured
            .iter()
            .flat_map(|(r, _)| [r.summary.frame_ms.mean, r.summary.frame_ms.max]),
        true,
    );
    // Room on the right for the label of the slowest run.
    let x_range = x_range.start..x_range.end + 0.25 * (x_range.end - x_range.start);
    let y_range = value_range(measured.iter().map(|(_, p)| *p), false);
    render_png(path, SPEED_ERROR_SIZE, |root| {
        let mut chart = ChartBuilder::on(root)
            .caption(
                "Speed against error: frame latency vs PSNR of the mean MSE per run",
                ("sans-serif", 24),
            )
            .margin(16)
            .x_label_area_size(50)
            .y_label_area_size(70)
            .build_cartesian_2d(x_range, y_range)
            .map_err(plot_error)?;
        chart
            .configure_mesh()
            .x_desc("frame latency (ms): dot = mean, cross = max")
            .y_desc("PSNR of the mean MSE (dB)")
            .label_style(("sans-serif", 14))
            .axis_desc_style(("sans-serif", 16))
            .draw()
            .map_err(plot_error)?;
        let palette = [RED, BLUE, GREEN, ORANGE, RGBColor(148, 103, 189)];
        for (i, (run, psnr)) in measured.iter().enumerate() {
            let color = palette[i % palette.len()];
            let (mean, max) = (run.summary.frame_ms.mean, run.summary.frame_ms.max);
            chart
                .draw_series(LineSeries::new([(mean, *psnr), (max, *psnr)], color.stroke_width(1)))
                .map_err(plot_error)?;
            chart
                .draw_series([Cross::new((max, *psnr), 6, color.stroke_width(2))])
                .map_err(plot_error)?;
            // The label sits beside the dot, in pixels, so it never covers it.
            let marker = EmptyElement::at((mean, *psnr))
                + Circle::new((0, 0), 6, color.filled())
                + Text::new(
                    match run.error {
                        Some(e) => format!("{} ({} identical)", run.name, e.frames_cell()),
                        None => run.name.clone(),
                    },
                    (10, -20),
                    ("sans-serif", 16).into_font().color(&color),
                );
            chart.draw_series([marker]).map_err(plot_error)?;
        }
        if !missing.is_empty() {
            root.draw(&Text::new(
                format!("no MSE measured: {}", missing.join(", ")),
                (20, SPEED_ERROR_SIZE.1 as i32 - 22),
                ("sans-serif", 14),
            ))
            .map_err(plot_error)?;
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::report_runs::FRAME_COLUMNS;

    #[test]
    fn load_profile_counts_cycles_cut_by_the_load_size_and_slow_frames() -> Result<()> {
        let dir = std::env::temp_dir().join(format!("citystream-load-profile-{}", std::process::id()));
        std::fs::create_dir_all(&dir)?;
        let mut csv = format!("{}\n", FRAME_COLUMNS.join(","));
        // (dt ms, load size MB, MB loaded, blocks): two frames cut by s (64 of 64, 58 of 64
        // MB), two at half of theirs; two of the five slower than twice the 10 ms median.
        let frames = [
            (10.0, 64.0, 64.0, 1024),
            (30.0, 64.0, 58.0, 928),
            (10.0, 64.0, 32.0, 512),
            (8.0, 1.0, 0.0, 0),
            (25.0, 1.0, 0.5, 8),
        ];
        for (i, (dt, s, mb, blocks)) in frames.iter().enumerate() {
            let bytes = (mb * BYTES_PER_MB) as u64;
            csv.push_str(&format!("{i},{i},{dt},{dt},{dt},0,0,0,{s},0,1,{bytes},{blocks},0,,\n"));
        }
        std::fs::write(dir.join("frames.csv"), csv)?;
        let p = load_profile(&dir)?;
        assert_eq!(p.frames, 5);
        assert!(
            (p.mb_per_frame[0] - 154.5 / 5.0).abs() < 1e-9 && p.mb_per_frame[1] == 64.0,
            "{p:?}"
        );
        assert_eq!(p.frames_at_load_size, 2, "{p:?}");
        assert_eq!((p.blocks_per_frame[0], p.blocks_per_frame[1]), (2472.0 / 5.0, 1024.0));
        assert_eq!(p.frames_over_twice_median, 2);
        assert!((p.time_share_over_twice_median - 55.0 / 83.0).abs() < 1e-12, "{p:?}");
        std::fs::remove_dir_all(dir)?;
        Ok(())
    }
}
