//! Datasets behind an HTTP server or in S3-compatible object storage (feature `remote`).
//!
//! [`open_dataset`] takes a directory or a URL: `http://host/path/city/`,
//! `https://…`, or `s3://bucket/prefix/`. A remote dataset is opened by fetching its small
//! files once (manifest, scene, texture table, checksums, colormap) and the pack's header;
//! every mip is then one HTTP range request (S3 `GetObject` with `Range`), checked against
//! its stored CRC-32 like a local read ([`crate::DatasetStore`]).
//!
//! The client is `object_store` (one API for HTTP and S3; timeouts, and retries with
//! exponential backoff of timeouts, 5xx answers and broken connections, built in). Its
//! requests run on a small tokio runtime owned by the [`RemoteStore`]; callers block on them
//! from their own threads (the loader's), never from the render thread.
//!
//! Latency hiding: the loader hints each cycle's mips in priority order
//! ([`DatasetStore::prefetch`]); the store merges ranges that lie back to back in the pack
//! into one request, issues the requests in priority order with at most
//! [`RemoteOptions::requests_in_flight`] at once, and [`DatasetStore::read_at`] takes a
//! prefetched range when it arrives (or reads it directly if it was never hinted, failed,
//! or took longer than a request may). What a cycle hinted and did not read is kept until
//! the next cycle's hint, which drops what it does not ask for again. Hinted ranges past
//! [`RemoteOptions::prefetch_limit_bytes`] wait, in priority order, and are requested as
//! reads free room.
//!
//! An optional on-disk mip cache ([`RemoteOptions::mip_cache`], [`MipCache`]) keeps the
//! mips read, so a second flight over the same area reads them locally; hints skip what it
//! holds.
//!
//! S3 settings come from the usual environment variables (`AWS_ACCESS_KEY_ID`,
//! `AWS_SECRET_ACCESS_KEY`, `AWS_SESSION_TOKEN`, `AWS_REGION` / `AWS_DEFAULT_REGION`,
//! `AWS_ENDPOINT_URL` / `AWS_ENDPOINT` for S3-compatible servers) or [`RemoteOptions`];
//! without credentials, requests go unsigned (public buckets).

use std::collections::{HashMap, HashSet, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use object_store::aws::AmazonS3Builder;
use object_store::http::HttpBuilder;
use object_store::path::Path as ObjectPath;
use object_store::{BackoffConfig, ClientOptions, ObjectStore, ObjectStoreExt, RetryConfig};

use crate::dataset::Dataset;
use crate::error::DatasetError;
use crate::mip_cache::MipCache;
use crate::store::DatasetStore;

mod guarded;
mod objects;

pub use objects::{
    lease_holder, ComposeReport, Lease, ObjectBucket, ObjectInfo, Segment, LEASE_RENEW, LEASE_STALE, MIN_PART_BYTES,
};

// Defined where the guarded client enforces it; public here beside the other limits.
pub use guarded::MAX_REDIRECTS;

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
    /// Prefetch requests in flight at most (each a mip, or back-to-back mips merged).
    pub requests_in_flight: usize,
    /// Bytes fetched ahead of their reads held at most (hints past it are not fetched).
    pub prefetch_limit_bytes: u64,
    /// S3 endpoint of an S3-compatible server (default: `AWS_ENDPOINT_URL`, then AWS).
    pub s3_endpoint: Option<String>,
    /// S3 region (default: `AWS_REGION`, `AWS_DEFAULT_REGION`, then `us-east-1`).
    pub s3_region: Option<String>,
    /// An on-disk mip cache to read through (none by default).
    pub mip_cache: Option<MipCacheOptions>,
    /// `CITYSTREAM_MIP_CACHE_MB` where set: the capacity a cache named later gets.
    pub mip_cache_capacity_bytes: Option<u64>,
    /// Follow redirects to another origin (scheme, host and port) than the dataset URL's.
    /// Off by default: the data of a URL the user named never silently comes from
    /// elsewhere (redirects within the origin are followed, up to [`MAX_REDIRECTS`]).
    pub follow_redirects: bool,
}

/// Where the on-disk mip cache lies and how much it holds.
#[derive(Clone, Debug)]
pub struct MipCacheOptions {
    /// Its directory (created if missing; processes may share it).
    pub dir: PathBuf,
    /// Bytes it holds at most; `None`: a quarter of the space free on its filesystem when
    /// it is opened ([`default_mip_cache_bytes`]).
    pub capacity_bytes: Option<u64>,
}

/// The mip cache's default capacity in `dir` (which must exist): a quarter of the space
/// free there plus what the cache already holds (so reopening does not shrink it), so the
/// cache never crowds out the rest of the disk; at least [`MIN_DEFAULT_MIP_CACHE_BYTES`].
pub fn default_mip_cache_bytes(dir: &Path) -> Result<u64, DatasetError> {
    let stat = rustix::fs::statvfs(dir).map_err(|e| DatasetError::io(dir, e.into()))?;
    let free = stat.f_bavail.saturating_mul(stat.f_frsize);
    Ok((free.saturating_add(MipCache::bytes_in(dir)) / 4).max(MIN_DEFAULT_MIP_CACHE_BYTES))
}

/// The least a default mip cache capacity is (a full disk still gets a small cache; its
/// writes then fail and are counted, and loads go on).
pub const MIN_DEFAULT_MIP_CACHE_BYTES: u64 = 64 << 20;

impl Default for RemoteOptions {
    fn default() -> Self {
        Self {
            timeout: Duration::from_secs(30),
            connect_timeout: Duration::from_secs(5),
            retries: 5,
            initial_backoff: Duration::from_millis(100),
            requests_in_flight: 64,
            prefetch_limit_bytes: 256 << 20,
            s3_endpoint: None,
            s3_region: None,
            mip_cache: None,
            mip_cache_capacity_bytes: None,
            follow_redirects: false,
        }
    }
}

impl RemoteOptions {
    /// The defaults, with `CITYSTREAM_REMOTE_RETRIES` (retries per request),
    /// `CITYSTREAM_REMOTE_IN_FLIGHT` (prefetch requests in flight) and
    /// `CITYSTREAM_REMOTE_TIMEOUT_S` (request timeout, seconds),
    /// `CITYSTREAM_REMOTE_PREFETCH_MB` (bytes held ahead, MB), `CITYSTREAM_MIP_CACHE`
    /// (the mip cache's directory), `CITYSTREAM_MIP_CACHE_MB` (its capacity) and
    /// `CITYSTREAM_REMOTE_FOLLOW_REDIRECTS` (`1` or `0`: redirects to another origin) applied
    /// where set; a value that does not parse is an error naming the variable.
    pub fn from_env() -> Result<Self, DatasetError> {
        let mut options = Self::default();
        if let Ok(text) = std::env::var("CITYSTREAM_REMOTE_RETRIES") {
            options.retries = text.trim().parse().ok().filter(|r| *r <= MAX_RETRIES).ok_or_else(|| {
                DatasetError::InvalidInput(format!("CITYSTREAM_REMOTE_RETRIES={text}: not 0..={MAX_RETRIES}"))
            })?;
        }
        if let Ok(text) = std::env::var("CITYSTREAM_REMOTE_IN_FLIGHT") {
            options.requests_in_flight = text
                .trim()
                .parse()
                .ok()
                .filter(|n| (1..=MAX_IN_FLIGHT).contains(n))
                .ok_or_else(|| {
                    DatasetError::InvalidInput(format!("CITYSTREAM_REMOTE_IN_FLIGHT={text}: not 1..={MAX_IN_FLIGHT}"))
                })?;
        }
        if let Ok(text) = std::env::var("CITYSTREAM_REMOTE_TIMEOUT_S") {
            let seconds = parse_timeout_seconds(&text).ok_or_else(|| {
                DatasetError::InvalidInput(format!("CITYSTREAM_REMOTE_TIMEOUT_S={text}: {TIMEOUT_SECONDS}"))
            })?;
            options.timeout = Duration::from_secs_f64(seconds);
        }
        if let Ok(text) = std::env::var("CITYSTREAM_REMOTE_PREFETCH_MB") {
            options.prefetch_limit_bytes = parse_megabytes(&text).ok_or_else(|| {
                DatasetError::InvalidInput(format!("CITYSTREAM_REMOTE_PREFETCH_MB={text}: {MEGABYTES}"))
            })?;
        }
        if let Some(dir) = std::env::var_os("CITYSTREAM_MIP_CACHE").filter(|d| !d.is_empty()) {
            options.mip_cache = Some(MipCacheOptions {
                dir: PathBuf::from(dir),
                capacity_bytes: None,
            });
        }
        if let Ok(text) = std::env::var("CITYSTREAM_MIP_CACHE_MB") {
            let bytes = parse_megabytes(&text)
                .ok_or_else(|| DatasetError::InvalidInput(format!("CITYSTREAM_MIP_CACHE_MB={text}: {MEGABYTES}")))?;
            // Without a directory there is no cache to size (a `--mip-cache DIR` given later
            // takes this capacity).
            options.mip_cache_capacity_bytes = Some(bytes);
            if let Some(cache) = options.mip_cache.as_mut() {
                cache.capacity_bytes = Some(bytes);
            }
        }
        if let Ok(text) = std::env::var("CITYSTREAM_REMOTE_FOLLOW_REDIRECTS") {
            options.follow_redirects = match text.trim() {
                "1" => true,
                "0" => false,
                _ => {
                    return Err(DatasetError::InvalidInput(format!(
                        "CITYSTREAM_REMOTE_FOLLOW_REDIRECTS={text}: not 1 or 0"
                    )))
                }
            };
        }
        Ok(options)
    }
}

/// Retries per request at most ([`RemoteOptions::retries`]).
pub const MAX_RETRIES: usize = 100;
/// Requests in flight at most ([`RemoteOptions::requests_in_flight`]).
pub const MAX_IN_FLIGHT: usize = 1024;
/// What [`parse_timeout_seconds`] accepts.
pub const TIMEOUT_SECONDS: &str = "not a number of seconds in (0, 3600]";

/// A request timeout in seconds, from just above 0 to an hour.
pub fn parse_timeout_seconds(text: &str) -> Option<f64> {
    text.trim()
        .parse()
        .ok()
        .filter(|s: &f64| s.is_finite() && *s > 0.0 && *s <= 3600.0)
}

/// What [`parse_megabytes`] accepts.
pub const MEGABYTES: &str = "not a number of MB from 1 byte to 2^30 MB (fractions allowed)";

/// Bytes of a size given in MB (2^20 bytes; fractions allowed), from 1 byte to 2^30 MB.
pub fn parse_megabytes(text: &str) -> Option<u64> {
    let megabytes: f64 = text.trim().parse().ok()?;
    let bytes = megabytes * f64::from(1 << 20);
    (megabytes.is_finite() && bytes >= 1.0 && megabytes <= f64::from(1 << 30)).then_some(bytes as u64)
}

/// The S3 client of `bucket` with the endpoint and region of `options` or the environment
/// (`AWS_ENDPOINT_URL`, `AWS_ENDPOINT`, `AWS_REGION`, `AWS_DEFAULT_REGION`; path-style
/// requests to an endpoint given), credentials from the environment.
fn s3_builder(
    bucket: &str,
    options: &RemoteOptions,
    client: ClientOptions,
    connector: guarded::GuardedConnector,
    retry: RetryConfig,
) -> AmazonS3Builder {
    let mut builder = AmazonS3Builder::from_env()
        .with_bucket_name(bucket)
        .with_client_options(client)
        .with_http_connector(connector)
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
    builder.with_region(region)
}

/// Whether `location` names a remote dataset (a URL this module opens).
/// The key prefix of an `s3://bucket/PREFIX` URL as every reader and writer uses it: empty
/// segments dropped (`s3://b//x/` is `x`, as the object store itself keys it); `.` and `..`
/// segments refused, as no store resolves them.
pub(crate) fn normalized_s3_prefix(prefix: &str) -> Result<String, String> {
    let segments: Vec<&str> = prefix.split('/').filter(|s| !s.is_empty()).collect();
    if let Some(dots) = segments.iter().find(|s| matches!(**s, "." | "..")) {
        return Err(format!(
            "the prefix {prefix:?} has a {dots:?} segment, which S3 keys do not resolve"
        ));
    }
    Ok(segments.join("/"))
}

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
    prefetched: Arc<Prefetched>,
    in_flight: Arc<tokio::sync::Semaphore>,
    prefetch_limit_bytes: u64,
    mip_cache: Option<Arc<MipCache>>,
    /// Whether the server still answers.
    liveness: Arc<Liveness>,
}

/// Whether the server still answers: a request that failed after waiting at least the
/// request timeout means it did not, and until one succeeds again, reads fail at once
/// instead of each waiting out its own timeouts and retries. One read tries again after
/// `stall_limit`, the next after twice that, and so on (up to [`MAX_STALL_PROBE`]), so a
/// server that stops answering fails the loads within about one retry chain, through the
/// loader's failure lifecycle, in every clock mode, and one that comes back is used again.
#[derive(Debug)]
struct Liveness {
    /// `scheme://authority` of the server, for messages.
    origin: String,
    state: Mutex<Silence>,
    request_timeout: Duration,
    /// One request's whole retry chain.
    stall_limit: Duration,
    retries: usize,
}

/// Since when nothing was answered, and how many reads tried again in vain since.
#[derive(Debug, Default)]
struct Silence {
    since: Option<Instant>,
    last_try: Option<Instant>,
    failed_tries: u32,
}

/// The longest a silent server goes without a read trying it again.
const MAX_STALL_PROBE: Duration = Duration::from_secs(600);

impl Liveness {
    fn new(options: &RemoteOptions, origin: String) -> Self {
        Self {
            origin,
            state: Mutex::default(),
            request_timeout: options.timeout,
            stall_limit: options.timeout.saturating_mul(options.retries as u32 + 1),
            retries: options.retries,
        }
    }

    fn lock(&self) -> MutexGuard<'_, Silence> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Records how a request that took `waited` ended.
    fn record(&self, answered: bool, waited: Duration) {
        let mut silence = self.lock();
        if answered {
            *silence = Silence::default();
        } else if waited >= self.request_timeout && silence.since.is_none() {
            let now = Instant::now();
            *silence = Silence {
                since: Some(now),
                last_try: Some(now),
                failed_tries: 0,
            };
        }
    }

    fn is_silent(&self) -> bool {
        self.lock().since.is_some()
    }

    /// `Err` with what to report while the server is silent, unless this read is the one
    /// that tries it again.
    fn check(&self) -> Result<(), String> {
        let mut silence = self.lock();
        let (Some(since), Some(last_try)) = (silence.since, silence.last_try) else {
            return Ok(());
        };
        let wait = self
            .stall_limit
            .saturating_mul(1 << silence.failed_tries.min(16))
            .min(MAX_STALL_PROBE);
        if last_try.elapsed() >= wait {
            silence.last_try = Some(Instant::now());
            silence.failed_tries += 1;
            return Ok(());
        }
        Err(format!(
            "no answer from {}: a request went unanswered for its timeout of {:.1} s through {} retries, \
             and nothing has been answered in the {:.1} s since",
            self.origin,
            self.request_timeout.as_secs_f64(),
            self.retries,
            since.elapsed().as_secs_f64()
        ))
    }
}

/// Ranges fetched ahead of their reads.
#[derive(Default)]
struct Prefetched {
    state: Mutex<PrefetchState>,
    changed: Condvar,
}

/// A range by (file, offset, length).
type RangeKey = (PathBuf, u64, u64);

#[derive(Default)]
struct PrefetchState {
    /// Ranges requested or fetched, not yet read.
    slots: HashMap<RangeKey, Slot>,
    /// Ranges the last hint asked for that did not fit the bytes held ahead, in priority
    /// order: requested as reads make room.
    deferred: VecDeque<RangeKey>,
}

impl PrefetchState {
    fn held_bytes(&self) -> u64 {
        self.slots.keys().map(|(_, _, len)| len).sum()
    }
}

enum Slot {
    Pending,
    Ready(bytes::Bytes),
    Failed,
}

impl Prefetched {
    fn lock(&self) -> MutexGuard<'_, PrefetchState> {
        // A poisoned lock only means a thread panicked while holding it; the map is intact.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// One prefetch request: back-to-back ranges merged, with the best priority among them.
struct RangeRequest {
    priority: usize,
    start: u64,
    end: u64,
    members: Vec<(u64, u64)>,
}

/// Merged requests stay below this, so one slow request holds back little.
const MAX_MERGED_BYTES: u64 = 8 << 20;

impl std::fmt::Debug for RemoteStore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RemoteStore").field("root", &self.root).finish()
    }
}

impl RemoteStore {
    /// A store for the dataset at `url` (`http(s)://host/path/` or `s3://bucket/prefix/`).
    ///
    /// An HTTP URL's query string (`…/?token=abc`, as hosted datasets and tilesets are
    /// served) is sent with every request; an S3 URL takes none.
    pub fn new(url: &str, options: &RemoteOptions) -> Result<Self, DatasetError> {
        let bad = |why: String| DatasetError::InvalidInput(format!("dataset URL {url}: {why}"));
        // reqwest is built without a TLS provider of its own: ring's, once per process.
        let _ = rustls::crypto::ring::default_provider().install_default();
        let (url_path, query) = match url.split_once('?') {
            Some((path, query)) => (path, Some(query.split('#').next().unwrap_or("").to_owned())),
            None => (url.split('#').next().unwrap_or(url), None),
        };
        let query = query.filter(|q| !q.is_empty());
        let trimmed = url_path.trim_end_matches('/');
        let (scheme, rest) = trimmed.split_once("://").ok_or_else(|| bad("no scheme".into()))?;
        let (authority, prefix) = rest.split_once('/').unwrap_or((rest, ""));
        if authority.is_empty() {
            return Err(bad("no host or bucket".into()));
        }
        let prefix = if scheme.eq_ignore_ascii_case("s3") {
            normalized_s3_prefix(prefix).map_err(bad)?
        } else {
            prefix.to_owned()
        };
        let prefix = prefix.as_str();
        let client = ClientOptions::new()
            .with_timeout(options.timeout)
            .with_connect_timeout(options.connect_timeout)
            .with_allow_http(true);
        if query.is_some() && scheme.eq_ignore_ascii_case("s3") {
            return Err(bad("an s3:// URL takes no query string".into()));
        }
        let connector = guarded::GuardedConnector {
            timeout: options.timeout,
            connect_timeout: options.connect_timeout,
            follow_redirects: options.follow_redirects,
            query,
        };
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
                    .with_http_connector(connector)
                    .with_retry(retry)
                    .build()
                    .map_err(|e| bad(e.to_string()))?,
            ),
            "s3" => {
                let mut builder = s3_builder(authority, options, client, connector, retry);
                if std::env::var_os("AWS_ACCESS_KEY_ID").is_none() {
                    builder = builder.with_skip_signature(true);
                }
                Arc::new(builder.build().map_err(|e| bad(e.to_string()))?)
            }
            other => return Err(bad(format!("scheme {other}:// is not http, https or s3"))),
        };
        let mip_cache = match &options.mip_cache {
            None => None,
            Some(cache) => {
                std::fs::create_dir_all(&cache.dir).map_err(|e| DatasetError::io(&cache.dir, e))?;
                let capacity = match cache.capacity_bytes {
                    Some(bytes) => bytes,
                    None => default_mip_cache_bytes(&cache.dir)?,
                };
                Some(Arc::new(MipCache::open(&cache.dir, capacity)?))
            }
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
            prefetched: Arc::default(),
            in_flight: Arc::new(tokio::sync::Semaphore::new(options.requests_in_flight.max(1))),
            prefetch_limit_bytes: options.prefetch_limit_bytes,
            mip_cache,
            liveness: Arc::new(Liveness::new(options, format!("{scheme}://{authority}"))),
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

    /// Requests the deferred ranges of `path` that fit in the room reads have freed.
    fn top_up(&self, path: &Path) {
        let mut fresh: Vec<(usize, u64, u64)> = Vec::new();
        {
            let mut state = self.prefetched.lock();
            let mut held = state.held_bytes();
            while let Some(range) = state.deferred.front() {
                // A range larger than the limit goes when nothing else is held, so it
                // never blocks the ranges behind it for good.
                if held > 0 && held.saturating_add(range.2) > self.prefetch_limit_bytes {
                    break;
                }
                let Some(range) = state.deferred.pop_front() else { break };
                held += range.2;
                if range.0 == path && !state.slots.contains_key(&range) {
                    fresh.push((fresh.len(), range.1, range.2));
                    state.slots.insert(range, Slot::Pending);
                }
            }
        }
        if !fresh.is_empty() {
            if let Ok(key) = self.key(path) {
                self.request(path, key, fresh);
            }
        }
    }

    /// Requests `(priority, offset, len)` ranges of `path` (already `Pending` slots):
    /// back-to-back ranges merged, in priority order, at most `in_flight` at once.
    fn request(&self, path: &Path, key: ObjectPath, mut fresh: Vec<(usize, u64, u64)>) {
        if fresh.is_empty() {
            return;
        }
        fresh.sort_by_key(|&(_, offset, _)| offset);
        let mut requests: Vec<RangeRequest> = Vec::new();
        for (priority, offset, len) in fresh {
            match requests.last_mut() {
                Some(last) if last.end == offset && last.end - last.start + len <= MAX_MERGED_BYTES => {
                    last.end += len;
                    last.priority = last.priority.min(priority);
                    last.members.push((offset, len));
                }
                _ => requests.push(RangeRequest {
                    priority,
                    start: offset,
                    end: offset + len,
                    members: vec![(offset, len)],
                }),
            }
        }
        requests.sort_by_key(|r| r.priority);
        let (store, semaphore, prefetched, path, liveness) = (
            Arc::clone(&self.store),
            Arc::clone(&self.in_flight),
            Arc::clone(&self.prefetched),
            path.to_path_buf(),
            Arc::clone(&self.liveness),
        );
        // One dispatcher per call: it starts the requests in priority order as permits free up.
        self.runtime.spawn(async move {
            for request in requests {
                let Ok(permit) = Arc::clone(&semaphore).acquire_owned().await else {
                    return;
                };
                let (store, prefetched, key, path, liveness) = (
                    Arc::clone(&store),
                    Arc::clone(&prefetched),
                    key.clone(),
                    path.clone(),
                    Arc::clone(&liveness),
                );
                tokio::spawn(async move {
                    let started = Instant::now();
                    let result = store.get_range(&key, request.start..request.end).await;
                    liveness.record(result.is_ok(), started.elapsed());
                    drop(permit);
                    let whole = matches!(&result, Ok(bytes) if bytes.len() as u64 == request.end - request.start);
                    let mut state = prefetched.lock();
                    for (offset, len) in request.members {
                        let slot = match &result {
                            Ok(bytes) if whole => {
                                let from = (offset - request.start) as usize;
                                Slot::Ready(bytes.slice(from..from + len as usize))
                            }
                            _ => Slot::Failed,
                        };
                        if let Some(entry) = state.slots.get_mut(&(path.clone(), offset, len)) {
                            *entry = slot;
                        }
                    }
                    drop(state);
                    prefetched.changed.notify_all();
                });
            }
        });
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
        // The length the server declares, then exactly that range: an answer longer than
        // it is refused as it arrives ([`guarded`]), never buffered whole.
        let len = self.len(path)?;
        let len =
            usize::try_from(len).map_err(|_| DatasetError::InvalidInput(format!("{}: {len} bytes", path.display())))?;
        let mut bytes = vec![0; len];
        if len > 0 {
            self.read_at(path, 0, &mut bytes)?;
        }
        Ok(bytes)
    }

    fn len(&self, path: &Path) -> Result<u64, DatasetError> {
        let key = self.key(path)?;
        self.runtime
            .block_on(self.store.head(&key))
            .map(|meta| meta.size)
            .map_err(|e| Self::error(path, e))
    }

    fn prefetch(&self, path: &Path, ranges: &[(u64, u64)]) {
        let Ok(key) = self.key(path) else {
            return;
        };
        let wanted: HashSet<(u64, u64)> = ranges.iter().copied().collect();
        let mut fresh: Vec<(usize, u64, u64)> = Vec::new();
        {
            let mut state = self.prefetched.lock();
            // Bounded memory: what this hint does not ask for again goes (requests still
            // in flight finish first).
            state
                .slots
                .retain(|(p, o, l), slot| matches!(slot, Slot::Pending) || (p == path && wanted.contains(&(*o, *l))));
            state.deferred.clear();
            let mut held = state.held_bytes();
            let mut deferred: HashSet<(u64, u64)> = HashSet::new();
            for (priority, &(offset, len)) in ranges.iter().enumerate() {
                let range = (path.to_path_buf(), offset, len);
                if len == 0 || state.slots.contains_key(&range) || deferred.contains(&(offset, len)) {
                    continue;
                }
                // Past the limit, in priority order: requested as reads free room. Once
                // one range waits, the lower-priority ones behind it wait too.
                if !deferred.is_empty() || (held > 0 && held.saturating_add(len) > self.prefetch_limit_bytes) {
                    deferred.insert((offset, len));
                    state.deferred.push_back(range);
                    continue;
                }
                state.slots.insert(range, Slot::Pending);
                held += len;
                fresh.push((priority, offset, len));
            }
        }
        self.request(path, key, fresh);
    }

    fn mip_cache(&self) -> Option<&Arc<MipCache>> {
        self.mip_cache.as_ref()
    }

    fn read_at(&self, path: &Path, offset: u64, dst: &mut [u8]) -> Result<(), DatasetError> {
        let slot_key = (path.to_path_buf(), offset, dst.len() as u64);
        {
            let mut state = self.prefetched.lock();
            // A prefetched range is waited for as long as one request's retry chain.
            let deadline = Instant::now() + self.liveness.stall_limit;
            loop {
                match state.slots.get(&slot_key) {
                    None => {
                        // Read now, so not requested again later.
                        if let Some(at) = state.deferred.iter().position(|range| *range == slot_key) {
                            state.deferred.remove(at);
                        }
                        break;
                    }
                    Some(Slot::Pending) => {
                        let now = Instant::now();
                        // A server that stopped answering will not answer this one either.
                        if self.liveness.is_silent() {
                            break;
                        }
                        if now >= deadline {
                            // A whole retry chain without the prefetch's answer: the server
                            // is silent, and a direct read would wait out another chain.
                            self.liveness.record(false, self.liveness.stall_limit);
                            break;
                        }
                        state = self
                            .prefetched
                            .changed
                            .wait_timeout(state, deadline - now)
                            .unwrap_or_else(|e| e.into_inner())
                            .0;
                    }
                    Some(Slot::Ready(_)) => {
                        if let Some(Slot::Ready(bytes)) = state.slots.remove(&slot_key) {
                            drop(state);
                            dst.copy_from_slice(&bytes);
                            self.top_up(path);
                            return Ok(());
                        }
                    }
                    // Read it directly, with the client's retries, and report that error.
                    Some(Slot::Failed) => {
                        state.slots.remove(&slot_key);
                        break;
                    }
                }
            }
        }
        self.top_up(path);
        let key = self.key(path)?;
        let end = offset.saturating_add(dst.len() as u64);
        self.liveness
            .check()
            .map_err(|why| DatasetError::io(path, std::io::Error::new(std::io::ErrorKind::TimedOut, why)))?;
        let started = Instant::now();
        let result = self.runtime.block_on(self.store.get_range(&key, offset..end));
        self.liveness.record(result.is_ok(), started.elapsed());
        let bytes = result.map_err(|e| Self::error(path, e))?;
        if bytes.len() != dst.len() {
            return Err(DatasetError::truncated(
                path,
                format!("a range request answered with {} bytes", bytes.len()),
                offset,
                end,
                offset + bytes.len() as u64,
            ));
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
