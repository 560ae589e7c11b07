//! Datasets by location, a directory or a URL, with the remote settings of the command
//! line over the environment's: what every tool that reads a dataset opens it with.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::Context;
use citystream_dataset::remote::{self, open_dataset as open_location, MipCacheOptions, RemoteOptions};
use citystream_dataset::Dataset;

/// Opens the dataset at `location`: a directory, or a URL (`http(s)://host/path/`,
/// `s3://bucket/prefix/`; see `citystream_dataset::remote`), with the remote settings of
/// the environment ([`RemoteOptions::from_env`]).
pub fn open_dataset(location: &Path) -> anyhow::Result<Dataset> {
    open_dataset_with(location, &RemoteOptions::from_env()?)
}

/// [`open_dataset`] with explicit remote settings (ignored for a directory).
pub fn open_dataset_with(location: &Path, options: &RemoteOptions) -> anyhow::Result<Dataset> {
    open_location(&location.to_string_lossy(), options)
        .with_context(|| format!("opening dataset {}", location.display()))
}

/// How a remote dataset is read: command-line settings over the environment's.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct RemoteArgs {
    /// Remote datasets: range requests in flight at most while prefetching
    /// (default 64, or CITYSTREAM_REMOTE_IN_FLIGHT).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=remote::MAX_IN_FLIGHT as i64))]
    pub remote_in_flight: Option<u32>,
    /// Remote datasets: retries of a failed request, with exponential backoff
    /// (default 5, or CITYSTREAM_REMOTE_RETRIES).
    #[arg(long, value_parser = clap::value_parser!(u32).range(0..=remote::MAX_RETRIES as i64))]
    pub remote_retries: Option<u32>,
    /// Remote datasets: seconds before a request is abandoned and retried
    /// (default 30, or CITYSTREAM_REMOTE_TIMEOUT_S).
    #[arg(long, value_parser = parse_timeout_s)]
    pub remote_timeout_s: Option<f64>,
    /// Remote datasets: MB fetched ahead of their reads held at most; hints
    /// past it wait for reads to make room (default 256, or
    /// CITYSTREAM_REMOTE_PREFETCH_MB).
    #[arg(long, value_parser = parse_megabytes_arg)]
    pub remote_prefetch_mb: Option<u64>,
    /// Remote datasets: follow redirects to another origin (scheme, host, port) than the
    /// dataset URL's; refused by default, so the data of the URL named never silently comes
    /// from elsewhere (or CITYSTREAM_REMOTE_FOLLOW_REDIRECTS=1).
    #[arg(long)]
    pub remote_follow_redirects: bool,
}

/// The on-disk mip cache of a remote dataset, from the command line or the environment.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct MipCacheArgs {
    /// Remote datasets: keep the mips read in this directory (created if
    /// missing; processes may share it), so a second run over the same area
    /// reads them locally; each checked against its CRC-32 (default:
    /// CITYSTREAM_MIP_CACHE, else none).
    #[arg(long)]
    pub mip_cache: Option<PathBuf>,
    /// With --mip-cache: MB it holds at most (fractions allowed), least
    /// recently used mips going first (default: CITYSTREAM_MIP_CACHE_MB, else
    /// a quarter of the space free on its filesystem).
    #[arg(long, value_parser = parse_megabytes_arg)]
    pub mip_cache_mb: Option<u64>,
}

/// MB (fractions allowed) as bytes.
fn parse_megabytes_arg(text: &str) -> Result<u64, String> {
    remote::parse_megabytes(text).ok_or_else(|| format!("`{text}`: {}", remote::MEGABYTES))
}

fn parse_timeout_s(text: &str) -> Result<f64, String> {
    remote::parse_timeout_seconds(text).ok_or_else(|| format!("`{text}`: {}", remote::TIMEOUT_SECONDS))
}

impl RemoteArgs {
    /// The environment's settings ([`RemoteOptions::from_env`]) with these applied.
    pub fn options(&self) -> anyhow::Result<RemoteOptions> {
        let mut options = RemoteOptions::from_env()?;
        if let Some(n) = self.remote_in_flight {
            options.requests_in_flight = n as usize;
        }
        if let Some(n) = self.remote_retries {
            options.retries = n as usize;
        }
        if let Some(s) = self.remote_timeout_s {
            options.timeout = Duration::from_secs_f64(s);
        }
        if let Some(bytes) = self.remote_prefetch_mb {
            options.prefetch_limit_bytes = bytes;
        }
        options.follow_redirects |= self.remote_follow_redirects;
        Ok(options)
    }

    /// [`RemoteArgs::options`] with the mip cache `cache` names (over the environment's).
    pub fn options_with_cache(&self, cache: &MipCacheArgs) -> anyhow::Result<RemoteOptions> {
        let mut options = self.options()?;
        if let Some(dir) = &cache.mip_cache {
            options.mip_cache = Some(MipCacheOptions {
                dir: dir.clone(),
                capacity_bytes: options.mip_cache_capacity_bytes,
            });
        }
        if let Some(bytes) = cache.mip_cache_mb {
            let Some(cache) = options.mip_cache.as_mut() else {
                anyhow::bail!("--mip-cache-mb needs --mip-cache (or CITYSTREAM_MIP_CACHE)");
            };
            cache.capacity_bytes = Some(bytes);
        }
        Ok(options)
    }
}
