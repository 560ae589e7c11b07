//! Datasets behind an HTTP server or in S3-compatible object storage (feature `remote`).
//!
//! [`open_dataset`] takes a directory or a URL: `http://host/path/city/`,
//! `https://…`, or `s3://bucket/prefix/`. A remote dataset is opened by fetching its small
//! files once (manifest, scene, texture table, checksums, colormap) and the pack's header;
//! every mip is then one HTTP range request (S3 `GetObject` with `Range`), checked against
//! its stored CRC-32 like a local read ([`crate::dataset::DatasetStore`]).
//!
//! The client is `object_store` (one API for HTTP and S3; timeouts, and retries with
//! exponential backoff of timeouts, 5xx answers and broken connections, built in). Its
//! requests run on a small tokio runtime owned by the [`RemoteStore`]; callers block on them
//! from their own threads (the loader's), never from the render thread.
//!
//! S3 settings come from the usual environment variables (`AWS_ACCESS_KEY_ID`,
//! `AWS_SECRET_ACCESS_KEY`, `AWS_SESSION_TOKEN`, `AWS_REGION` / `AWS_DEFAULT_REGION`,
//! `AWS_ENDPOINT_URL` / `AWS_ENDPOINT` for S3-compatible servers) or [`RemoteOptions`];
//! without credentials, requests go unsigned (public buckets).

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use object_store::aws::AmazonS3Builder;
use object_store::http::HttpBuilder;
use object_store::path::Path as ObjectPath;
use object_store::{BackoffConfig, ClientOptions, ObjectStore, ObjectStoreExt, RetryConfig};

use crate::dataset::{Dataset, DatasetError, DatasetStore};

/// How a remote dataset is reached.
#[derive(Clone, Debug)]
pub struct RemoteOptions {
    /// A request that has not completed after this long is abandoned (and retried).
    pub timeout: Duration,
    /// Connecting gives up after this long (and is retried).
    pub connect_timeout: Duration,
    /// Retries of a failed request (timeouts, 5xx, broken connections, short bodies),
    /// with exponential backoff from `initial_backoff`.
    pub retries: usize,
    /// The first retry's wait; each further one doubles it, up to 8 s.
    pub initial_backoff: Duration,
    /// S3 endpoint of an S3-compatible server (default: `AWS_ENDPOINT_URL`, then AWS).
    pub s3_endpoint: Option<String>,
    /// S3 region (default: `AWS_REGION`, `AWS_DEFAULT_REGION`, then `us-east-1`).
    pub s3_region: Option<String>,
}

impl Default for RemoteOptions {
    fn default() -> Self {
        Self {
            timeout: Duration::from_secs(30),
            connect_timeout: Duration::from_secs(5),
            retries: 5,
            initial_backoff: Duration::from_millis(100),
            s3_endpoint: None,
            s3_region: None,
        }
    }
}

impl RemoteOptions {
    /// The defaults, with `CITYSTREAM_REMOTE_RETRIES` (retries per request) and
    /// `CITYSTREAM_REMOTE_TIMEOUT_S` (request timeout, seconds) applied where set; a value
    /// that does not parse is an error naming the variable.
    pub fn from_env() -> Result<Self, DatasetError> {
        let mut options = Self::default();
        if let Ok(text) = std::env::var("CITYSTREAM_REMOTE_RETRIES") {
            options.retries =
                text.trim().parse().ok().filter(|r| *r <= 100).ok_or_else(|| {
                    DatasetError::InvalidInput(format!("CITYSTREAM_REMOTE_RETRIES={text}: not 0..=100"))
                })?;
        }
        if let Ok(text) = std::env::var("CITYSTREAM_REMOTE_TIMEOUT_S") {
            let seconds: f64 = text
                .trim()
                .parse()
                .ok()
                .filter(|s: &f64| s.is_finite() && *s > 0.0 && *s <= 3600.0)
                .ok_or_else(|| {
                    DatasetError::InvalidInput(format!(
                        "CITYSTREAM_REMOTE_TIMEOUT_S={text}: not a number of seconds in (0, 3600]"
                    ))
                })?;
            options.timeout = Duration::from_secs_f64(seconds);
        }
        Ok(options)
    }
}

/// Whether `location` names a remote dataset (a URL this module opens).
pub fn is_remote(location: &str) -> bool {
    ["http://", "https://", "s3://"]
        .iter()
        .any(|scheme| location.len() > scheme.len() && location[..scheme.len()].eq_ignore_ascii_case(scheme))
}

/// Opens the dataset at `location`: a directory ([`Dataset::open`]) or a URL (above).
pub fn open_dataset(location: &str, options: &RemoteOptions) -> Result<Dataset, DatasetError> {
    if !is_remote(location) {
        return Dataset::open(location);
    }
    let store = RemoteStore::new(location, options)?;
    let root = store.root.clone();
    Dataset::open_store(Arc::new(store), &root)
}

/// A dataset's files on an HTTP server or in an S3 bucket.
pub struct RemoteStore {
    /// The dataset's URL without a trailing slash: the prefix of every path asked for.
    root: PathBuf,
    /// The objects' key prefix inside `store` (the URL's path, or the bucket prefix).
    prefix: String,
    store: Arc<dyn ObjectStore>,
    runtime: tokio::runtime::Runtime,
}

impl std::fmt::Debug for RemoteStore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RemoteStore").field("root", &self.root).finish()
    }
}

impl RemoteStore {
    /// A store for the dataset at `url` (`http(s)://host/path/` or `s3://bucket/prefix/`).
    pub fn new(url: &str, options: &RemoteOptions) -> Result<Self, DatasetError> {
        let bad = |why: String| DatasetError::InvalidInput(format!("dataset URL {url}: {why}"));
        // reqwest is built without a TLS provider of its own: ring's, once per process.
        let _ = rustls::crypto::ring::default_provider().install_default();
        let trimmed = url.trim_end_matches('/');
        let (scheme, rest) = trimmed.split_once("://").ok_or_else(|| bad("no scheme".into()))?;
        let (authority, prefix) = rest.split_once('/').unwrap_or((rest, ""));
        if authority.is_empty() {
            return Err(bad("no host or bucket".into()));
        }
        let client = ClientOptions::new()
            .with_timeout(options.timeout)
            .with_connect_timeout(options.connect_timeout)
            .with_allow_http(true);
        let retry = RetryConfig {
            backoff: BackoffConfig {
                init_backoff: options.initial_backoff,
                max_backoff: Duration::from_secs(8),
                base: 2.0,
            },
            max_retries: options.retries,
            retry_timeout: options.timeout.saturating_mul(options.retries as u32 + 1),
        };
        let store: Arc<dyn ObjectStore> = match scheme.to_ascii_lowercase().as_str() {
            "http" | "https" => Arc::new(
                HttpBuilder::new()
                    .with_url(format!("{scheme}://{authority}"))
                    .with_client_options(client)
                    .with_retry(retry)
                    .build()
                    .map_err(|e| bad(e.to_string()))?,
            ),
            "s3" => {
                let mut builder = AmazonS3Builder::from_env()
                    .with_bucket_name(authority)
                    .with_client_options(client)
                    .with_retry(retry);
                let endpoint = options
                    .s3_endpoint
                    .clone()
                    .or_else(|| std::env::var("AWS_ENDPOINT_URL").ok())
                    .or_else(|| std::env::var("AWS_ENDPOINT").ok());
                if let Some(endpoint) = endpoint {
                    builder = builder
                        .with_endpoint(endpoint.trim_end_matches('/'))
                        .with_virtual_hosted_style_request(false);
                }
                let region = options
                    .s3_region
                    .clone()
                    .or_else(|| std::env::var("AWS_REGION").ok())
                    .or_else(|| std::env::var("AWS_DEFAULT_REGION").ok())
                    .unwrap_or_else(|| "us-east-1".to_owned());
                builder = builder.with_region(region);
                if std::env::var_os("AWS_ACCESS_KEY_ID").is_none() {
                    builder = builder.with_skip_signature(true);
                }
                Arc::new(builder.build().map_err(|e| bad(e.to_string()))?)
            }
            other => return Err(bad(format!("scheme {other}:// is not http, https or s3"))),
        };
        // Two workers serve every request in flight; callers block on their own threads.
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("citystream-remote")
            .enable_all()
            .build()
            .map_err(|e| DatasetError::io(trimmed, e))?;
        Ok(Self {
            root: PathBuf::from(format!("{scheme}://{authority}/{prefix}").trim_end_matches('/')),
            prefix: prefix.to_owned(),
            store,
            runtime,
        })
    }

    /// The dataset's URL.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// The object key of `path` (a path under [`RemoteStore::root`]).
    fn key(&self, path: &Path) -> Result<ObjectPath, DatasetError> {
        let relative = path.strip_prefix(&self.root).map_err(|_| {
            DatasetError::InvalidInput(format!(
                "{} is not inside the remote dataset {}",
                path.display(),
                self.root.display()
            ))
        })?;
        let relative = relative.to_string_lossy();
        let key = if self.prefix.is_empty() {
            relative.into_owned()
        } else {
            format!("{}/{relative}", self.prefix)
        };
        ObjectPath::parse(&key).map_err(|e| DatasetError::InvalidInput(format!("{}: {e}", path.display())))
    }

    fn error(path: &Path, error: object_store::Error) -> DatasetError {
        match error {
            object_store::Error::NotFound { .. } => DatasetError::Missing {
                path: path.to_path_buf(),
            },
            other => DatasetError::io(path, std::io::Error::other(other.to_string())),
        }
    }
}

impl DatasetStore for RemoteStore {
    fn read_all(&self, path: &Path) -> Result<Vec<u8>, DatasetError> {
        let key = self.key(path)?;
        self.runtime
            .block_on(async {
                let result = self.store.get(&key).await?;
                result.bytes().await
            })
            .map(|bytes| bytes.to_vec())
            .map_err(|e| Self::error(path, e))
    }

    fn len(&self, path: &Path) -> Result<u64, DatasetError> {
        let key = self.key(path)?;
        self.runtime
            .block_on(self.store.head(&key))
            .map(|meta| meta.size)
            .map_err(|e| Self::error(path, e))
    }

    fn read_at(&self, path: &Path, offset: u64, dst: &mut [u8]) -> Result<(), DatasetError> {
        let key = self.key(path)?;
        let end = offset.saturating_add(dst.len() as u64);
        let bytes = self
            .runtime
            .block_on(self.store.get_range(&key, offset..end))
            .map_err(|e| Self::error(path, e))?;
        if bytes.len() != dst.len() {
            return Err(DatasetError::Truncated {
                path: path.to_path_buf(),
                what: format!("a range request answered with {} bytes", bytes.len()),
                offset,
                end,
                file_len: offset + bytes.len() as u64,
            });
        }
        dst.copy_from_slice(&bytes);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_are_told_from_directories() {
        assert!(is_remote("http://127.0.0.1:8080/city/"));
        assert!(is_remote("HTTPS://example.invalid/city"));
        assert!(is_remote("s3://bucket/prefix"));
        assert!(!is_remote("data/city"));
        assert!(!is_remote("/srv/http://x"));
        assert!(!is_remote("s3://"));
    }

    #[test]
    fn keys_are_the_paths_under_the_url() {
        let store = RemoteStore::new("http://127.0.0.1:9/some/city/", &RemoteOptions::default()).expect("store");
        assert_eq!(store.root(), Path::new("http://127.0.0.1:9/some/city"));
        let key = store
            .key(&store.root().join("write-0000000000000001").join("scene.bin"))
            .expect("key");
        assert_eq!(key.as_ref(), "some/city/write-0000000000000001/scene.bin");
        assert!(store.key(Path::new("http://127.0.0.1:9/other/x")).is_err());
        for bad in ["ftp://host/x", "http:///x", "http//host"] {
            assert!(RemoteStore::new(bad, &RemoteOptions::default()).is_err(), "{bad}");
        }
    }
}
