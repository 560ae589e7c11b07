//! The read model of a run (`--disk-model`): the disk the loader's reads take modelled
//! time on, and how `summary.json` records it.

use std::path::Path;

use anyhow::{Context, Result};
use citystream_bench::disk_probe::{self, DiskModelFile};
use citystream_dataset::Dataset;
use citystream_streaming::disk_model::{DiskModel, DiskModelChoice};

use super::args::Args;

/// The model in `summary.json`: its name and parameters.
#[derive(Clone, Debug, serde::Serialize)]
pub(crate) struct DiskSummary {
    pub(crate) name: String,
    pub(crate) bytes_per_s: u64,
    pub(crate) request_latency_us: f64,
    pub(crate) queue_depth: u32,
    /// Where the figures come from.
    pub(crate) source: String,
}

impl DiskSummary {
    fn of(name: String, model: DiskModel, source: String) -> Self {
        DiskSummary {
            name,
            bytes_per_s: model.bytes_per_s,
            request_latency_us: model.request_latency.as_secs_f64() * 1e6,
            queue_depth: model.queue_depth,
            source,
        }
    }
}

/// The disk model `--disk-model` names, `None` for `none`. `measured` probes the pack
/// of the dataset in `dir` and writes the figures to OUT/disk-model.json, so that the run
/// can be repeated exactly with `measured:OUT/disk-model.json`.
pub(crate) fn disk_model(args: &Args, dataset: &Dataset, dir: &Path) -> Result<Option<(DiskModel, DiskSummary)>> {
    let choice = &args.disk_model;
    let (model, source) = match choice {
        DiskModelChoice::None => return Ok(None),
        DiskModelChoice::Evo970 => (
            DiskModel::SAMSUNG_970_EVO_1TB,
            "Samsung 970 EVO 1 TB data sheet (the paper's SSD); the paper's i7-8700K's 12 threads".to_owned(),
        ),
        DiskModelChoice::Measured(Some(file)) => {
            let figures = DiskModelFile::read(file)?;
            (figures.model()?, figures.source)
        }
        DiskModelChoice::Measured(None) => {
            eprintln!("measuring the disk under {} for --disk-model measured", dir.display());
            let figures = disk_probe::measure(dataset, dir).context("--disk-model measured")?;
            let path = args.out.join("disk-model.json");
            figures.write(&path)?;
            eprintln!(
                "disk: {:.1} MB/s, {:.1} µs per request, {} reads in flight (written to {}; \
                 --disk-model measured:{} repeats this run)",
                figures.bytes_per_s as f64 / 1e6,
                figures.request_latency_ns as f64 / 1e3,
                figures.queue_depth,
                path.display(),
                path.display()
            );
            (figures.model()?, figures.source)
        }
    };
    Ok(Some((model, DiskSummary::of(choice.name(), model, source))))
}
