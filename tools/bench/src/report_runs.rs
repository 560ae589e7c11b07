//! Flythrough runs as `citystream report` reads them: `summary.json` and `frames.csv` of
//! each run directory.

use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use citystream_streaming::bench::stats::Stats;
use serde::Deserialize;

use crate::image_error::{ErrorFrames, FrameError, PhaseError, STARTUP_S};

/// The columns `frames.csv` must have, as the flythrough writes them.
pub const FRAME_COLUMNS: [&str; 16] = [
    "frame",
    "time_s",
    "dt_ms",
    "tw_ms",
    "tm_ms",
    "tb_ms",
    "tbl_ms",
    "tbu_ms",
    "load_size_mb",
    "mip_bias",
    "mips",
    "bytes",
    "blocks_bound",
    "resident_bytes",
    "mip_deficit",
    "psnr_db",
];
/// Median / mean / max / min as written in `summary.json`.
#[derive(Debug, Clone, Copy, Deserialize)]
pub(crate) struct StatsJson {
    pub(crate) median: f64,
    pub(crate) mean: f64,
    pub(crate) max: f64,
    pub(crate) min: f64,
}

impl From<StatsJson> for Stats {
    fn from(s: StatsJson) -> Stats {
        Stats {
            median: s.median,
            mean: s.mean,
            max: s.max,
            min: s.min,
        }
    }
}

/// The part of `summary.json` the report reads.
#[derive(Debug, Clone, Deserialize)]
pub(crate) struct SummaryJson {
    pub(crate) frame_ms: StatsJson,
    pub(crate) tw_ms: StatsJson,
    pub(crate) mips_per_s: StatsJson,
    pub(crate) mb_per_s: StatsJson,
    pub(crate) load_size_mb: StatsJson,
    pub(crate) mip_bias: StatsJson,
    #[serde(default)]
    pub(crate) mip_deficit: Option<StatsJson>,
    #[serde(default)]
    pub(crate) psnr_db: Option<StatsJson>,
    /// Absent in summaries of runs before every measured frame counted.
    #[serde(default)]
    pub(crate) error_frames: Option<ErrorFrames>,
    #[serde(default)]
    pub(crate) psnr_of_mean_mse_db: Option<f64>,
    /// The start-up fill's and the streaming's errors apart; absent in older summaries.
    #[serde(default)]
    pub(crate) startup_psnr_of_mean_mse_db: Option<f64>,
    #[serde(default)]
    pub(crate) startup_error_frames: Option<ErrorFrames>,
    #[serde(default)]
    pub(crate) streaming_psnr_of_mean_mse_db: Option<f64>,
    #[serde(default)]
    pub(crate) streaming_error_frames: Option<ErrorFrames>,
    pub(crate) frames: u64,
    pub(crate) duration_s: f64,
    pub(crate) policy: String,
    pub(crate) bytes_streamed: u64,
    pub(crate) mips_streamed: u64,
    pub(crate) blocks_bound: u64,
    pub(crate) peak_resident_bytes: u64,
    /// Absent in summaries of older runs.
    #[serde(default)]
    pub(crate) unique_bytes_streamed: Option<u64>,
    /// Absent or null: unlimited.
    #[serde(default)]
    pub(crate) memory_budget_bytes: Option<u64>,
    #[serde(default)]
    pub(crate) frames_over_budget: Option<u64>,
    /// Written by the runs that also write the budget; absent in older ones.
    #[serde(default)]
    pub(crate) eviction: Option<String>,
}

/// One row of `frames.csv`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct FrameRow {
    pub(crate) time_s: f64,
    pub(crate) dt_ms: f64,
    pub(crate) tw_ms: f64,
    pub(crate) tm_ms: f64,
    pub(crate) tb_ms: f64,
    pub(crate) tbl_ms: f64,
    pub(crate) tbu_ms: f64,
    pub(crate) load_size_mb: f64,
    pub(crate) mip_bias: f64,
    pub(crate) mips: u64,
    pub(crate) bytes: u64,
    pub(crate) blocks_bound: u64,
    pub(crate) mip_deficit: Option<f64>,
    pub(crate) psnr_db: Option<f64>,
    /// Absent from older CSVs.
    pub(crate) mse: Option<f64>,
    /// A loading cycle started in the frame (absent from older CSVs).
    pub(crate) cycle_started: Option<bool>,
    /// With a disk model, the bytes the cycle in flight had still to deliver after the
    /// frame began (at a cycle's first frame, all it read); absent otherwise.
    pub(crate) reads_in_flight_bytes: Option<u64>,
}

/// A run read from disk, with the statistics the table shows.
#[derive(Debug, Clone)]
pub(crate) struct Run {
    pub(crate) name: String,
    pub(crate) dir: PathBuf,
    pub(crate) summary: SummaryJson,
    pub(crate) frames: Vec<FrameRow>,
    pub(crate) mip_deficit: Option<Stats>,
    pub(crate) psnr_db: Option<Stats>,
    /// The headline error and what it counts.
    pub(crate) error: Option<RunError>,
}

/// A run's image error: over every measured frame, and apart for the start-up fill and
/// the streaming after it (the headline; `crate::image_error::STARTUP_S`).
#[derive(Debug, Clone, Copy)]
pub(crate) struct RunError {
    pub(crate) psnr_of_mean_mse_db: f64,
    pub(crate) frames: ErrorFrames,
    pub(crate) startup: Option<PhaseError>,
    pub(crate) streaming: Option<PhaseError>,
}

impl RunError {
    /// From the summary's keys, or recomputed from the CSV's `time_s` and `mse` cells.
    pub(crate) fn of(summary: &SummaryJson, frames: &[FrameRow]) -> Option<Self> {
        let from_csv = |startup: Option<bool>| {
            PhaseError::of(
                frames
                    .iter()
                    .filter(|f| startup.is_none_or(|s| (f.time_s < STARTUP_S) == s))
                    .filter_map(|f| f.mse.map(FrameError::of_mse)),
            )
        };
        let phase = |psnr: Option<f64>, counted: Option<ErrorFrames>, startup: bool| match (psnr, counted) {
            (Some(psnr_of_mean_mse_db), Some(error_frames)) => Some(PhaseError {
                psnr_of_mean_mse_db,
                error_frames,
            }),
            _ => from_csv(Some(startup)),
        };
        let all = match (summary.psnr_of_mean_mse_db, summary.error_frames) {
            (Some(psnr_of_mean_mse_db), Some(error_frames)) => PhaseError {
                psnr_of_mean_mse_db,
                error_frames,
            },
            _ => from_csv(None)?,
        };
        Some(RunError {
            psnr_of_mean_mse_db: all.psnr_of_mean_mse_db,
            frames: all.error_frames,
            startup: phase(summary.startup_psnr_of_mean_mse_db, summary.startup_error_frames, true),
            streaming: phase(
                summary.streaming_psnr_of_mean_mse_db,
                summary.streaming_error_frames,
                false,
            ),
        })
    }

    /// The figure runs are compared by: the streaming after the start-up fill, or every
    /// frame where none was measured after it.
    pub(crate) fn headline_db(&self) -> f64 {
        self.streaming
            .map_or(self.psnr_of_mean_mse_db, |p| p.psnr_of_mean_mse_db)
    }

    pub(crate) fn frames_cell(&self) -> String {
        format!("{} / {}", self.frames.identical, self.frames.measured)
    }
}

pub(crate) fn load_run(dir: &Path, name: &str) -> Result<Run> {
    let summary_path = dir.join("summary.json");
    let text = std::fs::read_to_string(&summary_path).with_context(|| format!("reading {}", summary_path.display()))?;
    // serde_json's messages carry the line and column of the fault.
    let summary: SummaryJson = serde_json::from_str(&text)
        .with_context(|| format!("{}: not a valid flythrough summary", summary_path.display()))?;
    let frames = read_frames_csv(&dir.join("frames.csv"))?;
    let measured = |pick: fn(&FrameRow) -> Option<f64>| -> Option<Stats> {
        let samples: Vec<f64> = frames.iter().filter_map(pick).filter(|x| x.is_finite()).collect();
        (!samples.is_empty()).then(|| Stats::from_samples(&samples))
    };
    let mip_deficit = summary
        .mip_deficit
        .map(Stats::from)
        .or_else(|| measured(|f| f.mip_deficit));
    let psnr_db = summary.psnr_db.map(Stats::from).or_else(|| measured(|f| f.psnr_db));
    let error = RunError::of(&summary, &frames);
    Ok(Run {
        name: name.to_string(),
        dir: dir.to_path_buf(),
        summary,
        frames,
        mip_deficit,
        psnr_db,
        error,
    })
}

/// Parse `frames.csv`; every error names the file and the 1-based line.
/// The value of a column older `frames.csv` files lack (`column` is `None`), or a row left
/// empty: `None`; otherwise parsed, an error naming the row (`at`), the column and `what` it
/// should be.
fn optional_column<T>(
    cells: &[&str],
    column: Option<usize>,
    name: &str,
    what: &str,
    at: impl Fn() -> String,
) -> Result<Option<T>>
where
    T: std::str::FromStr,
    T::Err: std::fmt::Display,
{
    match column.map(|c| cells[c]) {
        None | Some("") => Ok(None),
        Some(text) => text
            .parse::<T>()
            .map(Some)
            .map_err(|e| anyhow!("{}: column `{name}` = {text:?}: {what} ({e})", at())),
    }
}

pub(crate) fn read_frames_csv(path: &Path) -> Result<Vec<FrameRow>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut lines = text.lines().enumerate();
    let header = loop {
        match lines.next() {
            Some((_, l)) if l.trim().is_empty() => continue,
            Some((_, l)) => break l,
            None => bail!("{}: empty file, expected a header line", path.display()),
        }
    };
    let names: Vec<&str> = header.trim_end_matches('\r').split(',').map(str::trim).collect();
    let mse_column = names.iter().position(|n| *n == "mse");
    let cycle_column = names.iter().position(|n| *n == "cycle_started");
    let in_flight_column = names.iter().position(|n| *n == "reads_in_flight_bytes");
    let mut index = [0usize; FRAME_COLUMNS.len()];
    for (slot, column) in index.iter_mut().zip(FRAME_COLUMNS) {
        *slot = names.iter().position(|n| *n == column).ok_or_else(|| {
            anyhow!(
                "{}: line 1: header lacks the column `{column}` (expected {})",
                path.display(),
                FRAME_COLUMNS.join(",")
            )
        })?;
    }
    let mut rows = Vec::new();
    for (i, line) in lines {
        let line_no = i + 1;
        let line = line.trim_end_matches('\r');
        if line.trim().is_empty() {
            continue;
        }
        let cells: Vec<&str> = line.split(',').map(str::trim).collect();
        if cells.len() != names.len() {
            bail!(
                "{}: line {line_no}: {} fields, the header has {} (truncated or malformed row)",
                path.display(),
                cells.len(),
                names.len()
            );
        }
        let cell = |c: usize| cells[index[c]];
        let context = |c: usize| {
            format!(
                "{}: line {line_no}: column `{}` = {:?}",
                path.display(),
                FRAME_COLUMNS[c],
                cell(c)
            )
        };
        let float = |c: usize| -> Result<f64> {
            cell(c)
                .parse::<f64>()
                .map_err(|e| anyhow!("{}: not a number ({e})", context(c)))
        };
        let count = |c: usize| -> Result<u64> {
            cell(c)
                .parse::<u64>()
                .map_err(|e| anyhow!("{}: not a non-negative integer ({e})", context(c)))
        };
        let optional = |c: usize| -> Result<Option<f64>> {
            if cell(c).is_empty() {
                Ok(None)
            } else {
                float(c).map(Some)
            }
        };
        // Indices into FRAME_COLUMNS; `frame` and `resident_bytes` are validated but not
        // charted.
        count(0)?;
        count(13)?;
        rows.push(FrameRow {
            time_s: float(1)?,
            dt_ms: float(2)?,
            tw_ms: float(3)?,
            tm_ms: float(4)?,
            tb_ms: float(5)?,
            tbl_ms: float(6)?,
            tbu_ms: float(7)?,
            load_size_mb: float(8)?,
            mip_bias: float(9)?,
            mips: count(10)?,
            blocks_bound: count(12)?,
            bytes: count(11)?,
            mip_deficit: optional(14)?,
            psnr_db: optional(15)?,
            mse: optional_column(&cells, mse_column, "mse", "not a number", || {
                format!("{}: line {line_no}", path.display())
            })?,
            cycle_started: match cycle_column.map(|c| cells[c]) {
                None => None,
                Some("0") => Some(false),
                Some("1") => Some(true),
                Some(text) => bail!(
                    "{}: line {line_no}: column `cycle_started` = {text:?}: expected 0 or 1",
                    path.display()
                ),
            },
            reads_in_flight_bytes: optional_column(
                &cells,
                in_flight_column,
                "reads_in_flight_bytes",
                "not a non-negative integer",
                || format!("{}: line {line_no}", path.display()),
            )?,
        });
    }
    if rows.is_empty() {
        bail!("{}: no frame rows after the header", path.display());
    }
    Ok(rows)
}
