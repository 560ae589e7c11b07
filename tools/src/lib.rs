//! The `citystream` tool's commands as a library: the binary parses the
//! command line, and cross-crate tests drive the same commands directly
//! (for example, rendering a generated city and its atlas version).

pub mod atlas;
pub mod bench;
pub mod cache_report;
pub mod default_city;
pub mod fault_proxy;
pub mod fuzz;
pub mod gen;
pub mod import;
pub mod info;
pub mod loader_bench;
pub mod nginx;
pub mod path;
pub mod remote_bench;
pub mod report;
pub mod simulate;
pub mod upgrade;
pub mod verify;

use std::path::Path;

use anyhow::Context;
use citystream_streaming::dataset::Dataset;
use citystream_streaming::remote::{open_dataset as open_location, RemoteOptions};

/// Opens the dataset at `location`: a directory, or a URL (`http(s)://host/path/`,
/// `s3://bucket/prefix/`; see `citystream_streaming::remote`).
pub fn open_dataset(location: &Path) -> anyhow::Result<Dataset> {
    let options = RemoteOptions::from_env()?;
    open_location(&location.to_string_lossy(), &options)
        .with_context(|| format!("opening dataset {}", location.display()))
}
