//! Writing into S3-compatible object storage: what a sharded build's shards and its merge
//! need (`docs/SHARDS.md`). Objects are put whole or in parts, listed, read and deleted,
//! and [`ObjectBucket::compose`] makes one object of byte ranges of others **inside the
//! store**, by a multipart upload whose parts are `UploadPartCopy` requests, so the bytes
//! copied never pass through this process.
//!
//! S3's rules shape the parts: every part but the last holds at least [`MIN_PART_BYTES`]
//! (5 MiB) and at most [`MAX_PART_BYTES`] (5 GiB), at most [`MAX_PARTS`] parts. A piece
//! of bytes this process makes (a header) cannot be a part of its own unless it is the
//! last, so it is topped up to 5 MiB with the start of the range that follows, read and
//! uploaded; likewise a copied range shorter than 5 MiB that is not last. What passed
//! through is counted ([`ComposeReport`]).
//!
//! `UploadPartCopy` with a range is not in `object_store`'s API: it is sent as a request
//! presigned by `object_store`'s SigV4 signer (query and the two `x-amz-copy-source`
//! headers under the signature). The rest goes through `object_store`.
//!
//! Threading: the calls block on the bucket's own small tokio runtime; use it from any one
//! thread at a time (`&self`, but not meant for concurrent use).

use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use object_store::aws::AmazonS3;
use object_store::multipart::{MultipartStore, PartId};
use object_store::path::Path as ObjectPath;
use object_store::signer::{HeaderName, HeaderValue, Method, SignedUrlOptions, Signer};
use object_store::{
    BackoffConfig, ClientOptions, ObjectStore, ObjectStoreExt, PutMode, PutPayload, RetryConfig, UpdateVersion,
};

use super::{guarded, s3_builder, RemoteOptions};
use crate::error::DatasetError;

/// S3's smallest part other than the last.
pub const MIN_PART_BYTES: u64 = 5 << 20;
/// S3's largest part.
pub const MAX_PART_BYTES: u64 = 5 << 30;
/// S3's most parts in one upload.
pub const MAX_PARTS: usize = 10_000;
/// Parts of a file uploaded by [`ObjectBucket::upload_file`].
const UPLOAD_PART_BYTES: u64 = 16 << 20;

/// One piece of an object [`ObjectBucket::compose`] makes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Segment {
    /// Bytes this process supplies.
    Bytes(Vec<u8>),
    /// A byte range of another object of the bucket (key relative to the bucket's prefix).
    Copy {
        /// The object.
        key: String,
        /// Its bytes.
        range: Range<u64>,
    },
}

/// What a composition did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ComposeReport {
    /// Parts of the multipart upload.
    pub parts: usize,
    /// Of them, copied inside the store.
    pub copied_parts: usize,
    /// Bytes copied inside the store.
    pub copied_bytes: u64,
    /// Bytes this process uploaded (its own, and those it read to fill parts).
    pub uploaded_bytes: u64,
    /// Bytes of other objects this process read to fill parts.
    pub read_bytes: u64,
}

/// An object's size and entity tag.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ObjectInfo {
    /// Bytes.
    pub size: u64,
    /// The store's entity tag (S3: an MD5 of the bytes, or of the parts' MD5s), changed by
    /// any change of the bytes.
    pub e_tag: Option<String>,
}

/// A piece of an upload part.
#[derive(Clone, Debug, PartialEq, Eq)]
enum Piece {
    Bytes(Vec<u8>),
    /// Read from the store and uploaded.
    Read {
        key: String,
        range: Range<u64>,
    },
}

/// One part of a composition.
#[derive(Clone, Debug, PartialEq, Eq)]
enum Part {
    Upload(Vec<Piece>),
    Copy { key: String, range: Range<u64> },
}

fn len(range: &Range<u64>) -> u64 {
    range.end - range.start
}

/// The parts that make `segments` under S3's rules (module docs), copying all it can.
fn plan_parts(segments: &[Segment], min_part: u64, max_part: u64) -> Vec<Part> {
    let mut parts = Vec::new();
    let mut pending: Vec<Piece> = Vec::new();
    let mut pending_len = 0u64;
    let last = segments.len().saturating_sub(1);
    for (s, segment) in segments.iter().enumerate() {
        let (key, mut range) = match segment {
            Segment::Bytes(bytes) if bytes.is_empty() => continue,
            Segment::Bytes(bytes) => {
                pending_len += bytes.len() as u64;
                pending.push(Piece::Bytes(bytes.clone()));
                continue;
            }
            Segment::Copy { range, .. } if range.is_empty() => continue,
            Segment::Copy { key, range } => (key, range.clone()),
        };
        let is_last = s == last;
        if pending_len > 0 {
            let need = min_part.saturating_sub(pending_len).min(len(&range));
            let rest = len(&range) - need;
            if rest >= min_part || (is_last && rest > 0) || (rest == 0 && !is_last && need == 0) {
                // Top the pending bytes up to a whole part; copy what remains.
                if need > 0 {
                    pending.push(Piece::Read {
                        key: key.clone(),
                        range: range.start..range.start + need,
                    });
                    range.start += need;
                }
                parts.push(Part::Upload(std::mem::take(&mut pending)));
                pending_len = 0;
            } else {
                // Too little would remain to copy as a part of its own: read it all.
                pending_len += len(&range);
                pending.push(Piece::Read {
                    key: key.clone(),
                    range,
                });
                if pending_len >= min_part {
                    parts.push(Part::Upload(std::mem::take(&mut pending)));
                    pending_len = 0;
                }
                continue;
            }
        }
        if range.is_empty() {
            continue;
        }
        if len(&range) < min_part && !is_last {
            pending_len += len(&range);
            pending.push(Piece::Read {
                key: key.clone(),
                range,
            });
            continue;
        }
        // Equal copy parts of at most `max_part`: each at least `min_part` when the range is.
        let count = len(&range).div_ceil(max_part);
        let (base, extra) = (len(&range) / count, len(&range) % count);
        let mut start = range.start;
        for p in 0..count {
            let end = start + base + u64::from(p < extra);
            parts.push(Part::Copy {
                key: key.clone(),
                range: start..end,
            });
            start = end;
        }
    }
    if !pending.is_empty() {
        parts.push(Part::Upload(pending));
    }
    parts
}

/// Seconds without renewal after which a lease may be taken over: long enough for a busy
/// machine's renewal (every [`LEASE_RENEW`]) to arrive, short enough that a rerun after a
/// killed writer waits little.
pub const LEASE_STALE: Duration = Duration::from_secs(60);
/// How often a held lease is renewed.
pub const LEASE_RENEW: Duration = Duration::from_secs(10);
const LEASE_FIRST_LINE: &str = "citystream lease 1";

/// A lease on one object of a bucket: a lock that lapses when its holder stops renewing it
/// ([`ObjectBucket::acquire_lease`]). A task on the bucket's runtime renews it every
/// [`LEASE_RENEW`] (each renewal conditional on the version it last wrote) until it is
/// released or dropped; [`Lease::check`] says whether it is still held.
#[derive(Debug)]
pub struct Lease {
    key: String,
    url: PathBuf,
    holder: String,
    lost: Arc<std::sync::atomic::AtomicBool>,
    renewer: tokio::task::JoinHandle<()>,
}

impl Lease {
    /// Who holds it.
    pub fn holder(&self) -> &str {
        &self.holder
    }

    /// An error when another writer has taken the lease over (this holder's renewals
    /// stopped for longer than [`LEASE_STALE`]): what this holder writes next would
    /// interleave with it.
    pub fn check(&self) -> Result<(), DatasetError> {
        if self.lost.load(Ordering::SeqCst) {
            return Err(DatasetError::io(
                &self.url,
                std::io::Error::other(
                    "this writer's lease was taken over by another writer (its renewals stopped for too long); \
                     stopping before it would remove or replace that writer's files",
                ),
            ));
        }
        Ok(())
    }
}

impl Drop for Lease {
    fn drop(&mut self) {
        self.renewer.abort();
    }
}

/// The body of a lease: its holder and when it was written.
fn lease_body(holder: &str, note: &str) -> Vec<u8> {
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis());
    format!(
        "{LEASE_FIRST_LINE}\nholder {holder}\nrenewed_unix_ms {now}\nnote {}\n",
        note.replace(['\n', '\r'], " ")
    )
    .into_bytes()
}

/// The holder of a lease body and how long ago it was written (`None`: not a lease).
fn parse_lease(bytes: &[u8]) -> Option<(String, Duration)> {
    let text = std::str::from_utf8(bytes).ok()?;
    let mut lines = text.lines();
    if lines.next()? != LEASE_FIRST_LINE {
        return None;
    }
    let holder = lines.next()?.strip_prefix("holder ")?.to_owned();
    let renewed: u128 = lines.next()?.strip_prefix("renewed_unix_ms ")?.parse().ok()?;
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .ok()?
        .as_millis();
    Some((holder, Duration::from_millis(now.saturating_sub(renewed) as u64)))
}

/// Who this process is, for leases: the scheduler's task where there is one, then host,
/// process id and a random tag.
pub fn lease_holder() -> String {
    let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|h| h.trim().to_owned())
        .unwrap_or_else(|_| "a host".into());
    let task = scheduler_task().map(|task| format!("{task} on ")).unwrap_or_default();
    format!(
        "{task}{host} pid {} tag {:016x}",
        std::process::id(),
        crate::fresh_write_id()
    )
}

/// The name of the task this process runs as, for a scheduler that reruns a task under
/// the same name only once its earlier run is dead (Slurm's requeue: it kills the task,
/// then starts it again): `slurm job 12_3` for task 3 of array job 12.
fn scheduler_task() -> Option<String> {
    let var = |name: &str| std::env::var(name).ok().filter(|v| !v.is_empty());
    let job = match (var("SLURM_ARRAY_JOB_ID"), var("SLURM_ARRAY_TASK_ID")) {
        (Some(job), Some(task)) => format!("{job}_{task}"),
        _ => var("SLURM_JOB_ID")?,
    };
    Some(format!("slurm job {job}"))
}

/// Whether the lease holder `other` is an earlier run of the task this process runs as
/// (see [`scheduler_task`]), whose lease it may take over at once.
fn earlier_run_of_this_task(other: &str) -> bool {
    scheduler_task().is_some_and(|task| other.starts_with(&format!("{task} on ")))
}

/// A prefix of an S3 bucket written object by object (see the module docs).
pub struct ObjectBucket {
    /// `s3://bucket/prefix` without a trailing slash, for messages.
    url: String,
    bucket: String,
    prefix: String,
    store: Arc<AmazonS3>,
    http: reqwest::Client,
    runtime: tokio::runtime::Runtime,
    request_timeout: Duration,
    sent: AtomicU64,
    received: AtomicU64,
}

impl std::fmt::Debug for ObjectBucket {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ObjectBucket").field("url", &self.url).finish()
    }
}

impl ObjectBucket {
    /// The bucket and prefix of `url` (`s3://bucket/prefix`), with the credentials, endpoint
    /// and region of the environment (as remote datasets are read) or of `options`.
    pub fn new(url: &str, options: &RemoteOptions) -> Result<Self, DatasetError> {
        let bad = |why: String| DatasetError::InvalidInput(format!("{url}: {why}"));
        let _ = rustls::crypto::ring::default_provider().install_default();
        let rest = url
            .get(..5)
            .filter(|scheme| scheme.eq_ignore_ascii_case("s3://"))
            .map(|_| &url[5..])
            .ok_or_else(|| bad("writing needs an s3://bucket/prefix URL".into()))?;
        let rest = rest.trim_end_matches('/');
        let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
        if bucket.is_empty() || rest.contains(['?', '#']) {
            return Err(bad("no bucket, or a query string".into()));
        }
        // One form for writers and readers (`RemoteStore`): `s3://b//x` is `s3://b/x`.
        let prefix = super::normalized_s3_prefix(prefix).map_err(bad)?;
        let rest = if prefix.is_empty() {
            bucket.to_owned()
        } else {
            format!("{bucket}/{prefix}")
        };
        if std::env::var_os("AWS_ACCESS_KEY_ID").is_none() {
            return Err(bad(
                "writing to S3 needs credentials: set AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY".into(),
            ));
        }
        let client = ClientOptions::new()
            .with_timeout(options.timeout)
            .with_connect_timeout(options.connect_timeout)
            .with_allow_http(true);
        let connector = guarded::GuardedConnector {
            timeout: options.timeout,
            connect_timeout: options.connect_timeout,
            follow_redirects: options.follow_redirects,
            query: None,
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
        let store = s3_builder(bucket, options, client, connector, retry)
            .build()
            .map_err(|e| bad(e.to_string()))?;
        let http = reqwest::Client::builder()
            .timeout(options.timeout)
            .connect_timeout(options.connect_timeout)
            .build()
            .map_err(|e| bad(e.to_string()))?;
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("citystream-objects")
            .enable_all()
            .build()
            .map_err(|e| DatasetError::io(url, e))?;
        Ok(Self {
            url: format!("s3://{rest}"),
            bucket: bucket.to_owned(),
            prefix,
            store: Arc::new(store),
            http,
            runtime,
            request_timeout: options.timeout,
            sent: AtomicU64::new(0),
            received: AtomicU64::new(0),
        })
    }

    /// `s3://bucket/prefix/key`: how messages name an object.
    pub fn url_of(&self, key: &str) -> PathBuf {
        PathBuf::from(if key.is_empty() {
            self.url.clone()
        } else {
            format!("{}/{key}", self.url)
        })
    }

    /// The bucket's URL with its prefix (`s3://bucket/prefix`).
    pub fn url(&self) -> &str {
        &self.url
    }

    fn path(&self, key: &str) -> Result<ObjectPath, DatasetError> {
        let full = if self.prefix.is_empty() {
            key.to_owned()
        } else if key.is_empty() {
            self.prefix.clone()
        } else {
            format!("{}/{key}", self.prefix)
        };
        ObjectPath::parse(&full).map_err(|e| DatasetError::InvalidInput(format!("{}: {e}", self.url_of(key).display())))
    }

    fn error(&self, key: &str, error: impl std::fmt::Display) -> DatasetError {
        DatasetError::io(self.url_of(key), std::io::Error::other(error.to_string()))
    }

    /// Bytes this process sent as object data (puts and parts).
    pub fn bytes_sent(&self) -> u64 {
        self.sent.load(Ordering::Relaxed)
    }

    /// Bytes of object data this process received (gets).
    pub fn bytes_received(&self) -> u64 {
        self.received.load(Ordering::Relaxed)
    }

    /// The object `key`, whole; `None` where there is none.
    pub fn get(&self, key: &str) -> Result<Option<Vec<u8>>, DatasetError> {
        let path = self.path(key)?;
        let result = self.runtime.block_on(async {
            let got = self.store.get(&path).await?;
            got.bytes().await
        });
        match result {
            Ok(bytes) => {
                self.received.fetch_add(bytes.len() as u64, Ordering::Relaxed);
                Ok(Some(bytes.to_vec()))
            }
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(self.error(key, e)),
        }
    }

    fn get_range(&self, key: &str, range: Range<u64>) -> Result<Vec<u8>, DatasetError> {
        let path = self.path(key)?;
        let wanted = len(&range);
        let bytes = self
            .runtime
            .block_on(self.store.get_range(&path, range.clone()))
            .map_err(|e| self.error(key, e))?;
        self.received.fetch_add(bytes.len() as u64, Ordering::Relaxed);
        if bytes.len() as u64 != wanted {
            return Err(DatasetError::truncated(
                self.url_of(key),
                format!("a range request answered with {} bytes", bytes.len()),
                range.start,
                range.end,
                range.start + bytes.len() as u64,
            ));
        }
        Ok(bytes.to_vec())
    }

    /// The size and entity tag of `key`; `None` where there is no such object.
    pub fn head(&self, key: &str) -> Result<Option<ObjectInfo>, DatasetError> {
        let path = self.path(key)?;
        match self.runtime.block_on(self.store.head(&path)) {
            Ok(meta) => Ok(Some(ObjectInfo {
                size: meta.size,
                e_tag: meta.e_tag,
            })),
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(self.error(key, e)),
        }
    }

    /// Takes the lease `key` for `holder` (`note` says what for): created where there is
    /// none (`If-None-Match: *`), taken over where its holder has not renewed it for
    /// [`LEASE_STALE`] or is an earlier run of this scheduler task (a Slurm requeue: see
    /// [`lease_holder`]), with `If-Match` on the version read, so two takers cannot both
    /// have it; otherwise refused with [`DatasetError::Leased`]. Renewed in the background until
    /// released ([`ObjectBucket::release_lease`]) or dropped.
    pub fn acquire_lease(&self, key: &str, holder: &str, note: &str) -> Result<Lease, DatasetError> {
        let path = self.path(key)?;
        let put = |mode: PutMode| {
            self.runtime.block_on(
                self.store
                    .put_opts(&path, PutPayload::from(lease_body(holder, note)), mode.into()),
            )
        };
        // A lease released between the failed create and the read is created again.
        for _ in 0..3 {
            let created = match put(PutMode::Create) {
                Ok(done) => Some(done.e_tag),
                Err(object_store::Error::AlreadyExists { .. }) => None,
                Err(e) => return Err(self.error(key, e)),
            };
            if let Some(e_tag) = created {
                return Ok(self.lease(key, holder, note, e_tag));
            }
            let read = self.runtime.block_on(async {
                let got = self.store.get(&path).await?;
                let e_tag = got.meta.e_tag.clone();
                Ok::<_, object_store::Error>((e_tag, got.bytes().await?))
            });
            let (e_tag, bytes) = match read {
                Ok(read) => read,
                Err(object_store::Error::NotFound { .. }) => continue,
                Err(e) => return Err(self.error(key, e)),
            };
            let (other, age) = parse_lease(&bytes).unwrap_or_else(|| ("an unreadable lease".into(), Duration::MAX));
            // A requeued task takes its own killed run's lease without waiting for it to lapse.
            if age < LEASE_STALE && !earlier_run_of_this_task(&other) {
                return Err(DatasetError::Leased {
                    url: self.url_of(key),
                    holder: other,
                    age_s: age.as_secs_f64(),
                    stale_s: LEASE_STALE.as_secs_f64(),
                });
            }
            match put(PutMode::Update(UpdateVersion { e_tag, version: None })) {
                Ok(done) => return Ok(self.lease(key, holder, note, done.e_tag)),
                Err(object_store::Error::Precondition { .. } | object_store::Error::AlreadyExists { .. }) => continue,
                Err(e) => return Err(self.error(key, e)),
            }
        }
        Err(DatasetError::Leased {
            url: self.url_of(key),
            holder: "other writers taking it at the same moment".into(),
            age_s: 0.0,
            stale_s: LEASE_STALE.as_secs_f64(),
        })
    }

    /// A held lease whose renewals run on this bucket's runtime.
    fn lease(&self, key: &str, holder: &str, note: &str, e_tag: Option<String>) -> Lease {
        let e_tag = Arc::new(std::sync::Mutex::new(e_tag));
        let lost = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let renewer = {
            let (store, e_tag, lost) = (self.store.clone(), e_tag.clone(), lost.clone());
            let (path, holder, note) = (self.path(key), holder.to_owned(), note.to_owned());
            self.runtime.spawn(async move {
                let Ok(path) = path else { return };
                loop {
                    tokio::time::sleep(LEASE_RENEW).await;
                    let current = e_tag.lock().unwrap_or_else(std::sync::PoisonError::into_inner).clone();
                    let mode = PutMode::Update(UpdateVersion {
                        e_tag: current,
                        version: None,
                    });
                    match store
                        .put_opts(&path, PutPayload::from(lease_body(&holder, &note)), mode.into())
                        .await
                    {
                        Ok(done) => *e_tag.lock().unwrap_or_else(std::sync::PoisonError::into_inner) = done.e_tag,
                        Err(object_store::Error::Precondition { .. } | object_store::Error::NotFound { .. }) => {
                            lost.store(true, Ordering::SeqCst);
                            return;
                        }
                        // A failed request is tried again at the next renewal; the lease
                        // lapses only after LEASE_STALE without one.
                        Err(_) => {}
                    }
                }
            })
        };
        Lease {
            key: key.to_owned(),
            url: self.url_of(key),
            holder: holder.to_owned(),
            lost,
            renewer,
        }
    }

    /// Stops renewing `lease` and removes it where it is still this holder's (its body
    /// names this holder: a renewal cut off by the stop may have changed its version).
    pub fn release_lease(&self, lease: Lease) -> Result<(), DatasetError> {
        lease.renewer.abort();
        if lease.lost.load(Ordering::SeqCst) {
            return Ok(());
        }
        let Some(body) = self.get(&lease.key)? else {
            return Ok(());
        };
        match parse_lease(&body) {
            Some((holder, _)) if holder == lease.holder => self.delete(&lease.key),
            _ => Ok(()),
        }
    }

    /// Puts `bytes` as `key` (replacing any object there in one step).
    pub fn put(&self, key: &str, bytes: Vec<u8>) -> Result<(), DatasetError> {
        let path = self.path(key)?;
        let n = bytes.len() as u64;
        self.runtime
            .block_on(self.store.put(&path, PutPayload::from(bytes)))
            .map_err(|e| self.error(key, e))?;
        self.sent.fetch_add(n, Ordering::Relaxed);
        Ok(())
    }

    /// Uploads the file `file` as `key`: in parts of 16 MiB when larger, `progress` called
    /// with the bytes sent so far and the total after each.
    pub fn upload_file(&self, key: &str, file: &Path, progress: &mut dyn FnMut(u64, u64)) -> Result<(), DatasetError> {
        use std::io::Read;
        let io = |e| DatasetError::io(file, e);
        let mut source = std::fs::File::open(file).map_err(io)?;
        let total = source.metadata().map_err(io)?.len();
        if total <= UPLOAD_PART_BYTES {
            let mut bytes = Vec::with_capacity(total as usize);
            source.read_to_end(&mut bytes).map_err(io)?;
            self.put(key, bytes)?;
            progress(total, total);
            return Ok(());
        }
        let path = self.path(key)?;
        let id = self
            .runtime
            .block_on(self.store.create_multipart(&path))
            .map_err(|e| self.error(key, e))?;
        let result = (|| {
            let mut parts = Vec::new();
            let mut done = 0u64;
            while done < total {
                let n = UPLOAD_PART_BYTES.min(total - done);
                let mut chunk = vec![0u8; n as usize];
                source.read_exact(&mut chunk).map_err(io)?;
                let part = self
                    .runtime
                    .block_on(self.store.put_part(&path, &id, parts.len(), PutPayload::from(chunk)))
                    .map_err(|e| self.error(key, e))?;
                parts.push(part);
                done += n;
                self.sent.fetch_add(n, Ordering::Relaxed);
                progress(done, total);
            }
            self.runtime
                .block_on(self.store.complete_multipart(&path, &id, parts))
                .map_err(|e| self.error(key, e))
        })();
        if result.is_err() {
            let _ = self.runtime.block_on(self.store.abort_multipart(&path, &id));
        }
        result.map(|_| ())
    }

    /// Keys (relative to the bucket's prefix) of the objects under `under` (a key prefix
    /// ending in `/`, or empty for all), with their sizes.
    pub fn list(&self, under: &str) -> Result<Vec<(String, u64)>, DatasetError> {
        let path = self.path(under.trim_end_matches('/'))?;
        let listed = self
            .runtime
            .block_on(collect(self.store.list(Some(&path))))
            .map_err(|e| self.error(under, e))?;
        let strip = if self.prefix.is_empty() {
            String::new()
        } else {
            format!("{}/", self.prefix)
        };
        Ok(listed
            .into_iter()
            .filter_map(|meta| {
                let key = meta.location.as_ref().strip_prefix(&strip)?.to_owned();
                Some((key, meta.size))
            })
            .collect())
    }

    /// Deletes `key` (nothing there is no error).
    pub fn delete(&self, key: &str) -> Result<(), DatasetError> {
        let path = self.path(key)?;
        match self.runtime.block_on(self.store.delete(&path)) {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
            Err(e) => Err(self.error(key, e)),
        }
    }

    /// Makes `key` the concatenation of `segments` (module docs); `progress` gets the parts
    /// done and their count after each. Nothing is left behind when it fails (the upload is
    /// aborted); `key` appears whole or not at all.
    pub fn compose(
        &self,
        key: &str,
        segments: &[Segment],
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<ComposeReport, DatasetError> {
        let plan = plan_parts(segments, MIN_PART_BYTES, MAX_PART_BYTES);
        if plan.len() > MAX_PARTS {
            return Err(DatasetError::InvalidInput(format!(
                "{}: {} parts, more than S3's {MAX_PARTS}",
                self.url_of(key).display(),
                plan.len()
            )));
        }
        let path = self.path(key)?;
        let id = self
            .runtime
            .block_on(self.store.create_multipart(&path))
            .map_err(|e| self.error(key, e))?;
        let mut report = ComposeReport {
            parts: plan.len(),
            ..ComposeReport::default()
        };
        let result = (|| {
            let mut done = Vec::with_capacity(plan.len());
            for (p, part) in plan.iter().enumerate() {
                let id_part = match part {
                    Part::Upload(pieces) => {
                        let mut bytes = Vec::new();
                        for piece in pieces {
                            match piece {
                                Piece::Bytes(b) => bytes.extend_from_slice(b),
                                Piece::Read { key, range } => {
                                    bytes.extend(self.get_range(key, range.clone())?);
                                    report.read_bytes += len(range);
                                }
                            }
                        }
                        report.uploaded_bytes += bytes.len() as u64;
                        self.sent.fetch_add(bytes.len() as u64, Ordering::Relaxed);
                        self.runtime
                            .block_on(self.store.put_part(&path, &id, p, PutPayload::from(bytes)))
                            .map_err(|e| self.error(key, e))?
                    }
                    Part::Copy { key: source, range } => {
                        report.copied_parts += 1;
                        report.copied_bytes += len(range);
                        self.copy_part(&path, &id, p, source, range.clone())?
                    }
                };
                done.push(id_part);
                progress(p + 1, plan.len());
            }
            self.runtime
                .block_on(self.store.complete_multipart(&path, &id, done))
                .map_err(|e| self.error(key, e))
        })();
        if result.is_err() {
            let _ = self.runtime.block_on(self.store.abort_multipart(&path, &id));
        }
        result.map(|_| report)
    }

    /// `UploadPartCopy` of `range` of `source` as part `index` (from 0) of upload `id`.
    fn copy_part(
        &self,
        path: &ObjectPath,
        id: &str,
        index: usize,
        source: &str,
        range: Range<u64>,
    ) -> Result<PartId, DatasetError> {
        let source_path = self.path(source)?;
        let copy_source = format!("/{}/{}", self.bucket, encode_key(source_path.as_ref()));
        let copy_range = format!("bytes={}-{}", range.start, range.end - 1);
        let header = |name: &'static str, value: &str| -> Result<(HeaderName, HeaderValue), DatasetError> {
            Ok((
                HeaderName::from_static(name),
                HeaderValue::from_str(value).map_err(|e| self.error(source, e))?,
            ))
        };
        let (source_name, source_value) = header("x-amz-copy-source", &copy_source)?;
        let (range_name, range_value) = header("x-amz-copy-source-range", &copy_range)?;
        let options = SignedUrlOptions::new()
            .with_query([("partNumber", (index + 1).to_string()), ("uploadId", id.to_owned())])
            .with_signed_header(source_name, source_value)
            .with_signed_header(range_name, range_value);
        let target = self.url_of(path.as_ref().strip_prefix(&self.prefix).unwrap_or(path.as_ref()));
        let answer = self.runtime.block_on(async {
            let url = self
                .store
                .signed_url_opts(
                    Method::PUT,
                    path,
                    self.request_timeout.max(Duration::from_secs(600)),
                    &options,
                )
                .await
                .map_err(|e| e.to_string())?;
            let response = self
                .http
                .put(url.as_str())
                .header("x-amz-copy-source", &copy_source)
                .header("x-amz-copy-source-range", &copy_range)
                .send()
                .await
                .map_err(|e| e.to_string())?;
            let status = response.status();
            let body = response.text().await.map_err(|e| e.to_string())?;
            Ok::<_, String>((status, body))
        });
        let (status, body) = answer.map_err(|e| self.error(&target.to_string_lossy(), e))?;
        // S3 may answer 200 and report a failed copy in the body.
        let e_tag = body
            .split_once("<ETag>")
            .and_then(|(_, rest)| rest.split_once("</ETag>"))
            .map(|(tag, _)| tag.replace("&quot;", "\""));
        match e_tag {
            Some(tag) if status.is_success() && !body.contains("<Error>") => Ok(PartId { content_id: tag }),
            _ => Err(DatasetError::io(
                self.url_of(source),
                std::io::Error::other(format!(
                    "copying bytes {}..{} into part {} of {}: {status}: {}",
                    range.start,
                    range.end,
                    index + 1,
                    target.display(),
                    body.chars().take(300).collect::<String>()
                )),
            )),
        }
    }
}

/// A key as the `x-amz-copy-source` header takes it: URL-encoded, `/` kept.
fn encode_key(key: &str) -> String {
    let mut out = String::with_capacity(key.len());
    for b in key.bytes() {
        if b.is_ascii_alphanumeric() || b"-_.~/".contains(&b) {
            out.push(b as char);
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

/// A listing's stream collected (poll by poll: `futures-core` has the trait only).
async fn collect(
    mut stream: std::pin::Pin<
        Box<dyn futures_core::Stream<Item = object_store::Result<object_store::ObjectMeta>> + Send>,
    >,
) -> object_store::Result<Vec<object_store::ObjectMeta>> {
    let mut out = Vec::new();
    while let Some(item) = std::future::poll_fn(|cx| stream.as_mut().poll_next(cx)).await {
        out.push(item?);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn copy(key: &str, range: Range<u64>) -> Segment {
        Segment::Copy { key: key.into(), range }
    }

    /// Every part but the last within S3's sizes, and the parts together the segments.
    fn check(segments: &[Segment], parts: &[Part], min: u64, max: u64) {
        let mut joined: Vec<(String, u64)> = Vec::new();
        let expand = |key: &str, range: &Range<u64>, out: &mut Vec<(String, u64)>| {
            out.extend(range.clone().map(|b| (key.to_owned(), b)));
        };
        let mut expected = Vec::new();
        for s in segments {
            match s {
                Segment::Bytes(b) => expected.extend(b.iter().map(|&v| ("".to_owned(), u64::from(v)))),
                Segment::Copy { key, range } => expand(key, range, &mut expected),
            }
        }
        for (p, part) in parts.iter().enumerate() {
            let size = match part {
                Part::Upload(pieces) => {
                    let mut n = 0;
                    for piece in pieces {
                        match piece {
                            Piece::Bytes(b) => {
                                joined.extend(b.iter().map(|&v| ("".to_owned(), u64::from(v))));
                                n += b.len() as u64;
                            }
                            Piece::Read { key, range } => {
                                expand(key, range, &mut joined);
                                n += len(range);
                            }
                        }
                    }
                    n
                }
                Part::Copy { key, range } => {
                    expand(key, range, &mut joined);
                    len(range)
                }
            };
            assert!(size <= max, "part {p} of {size} bytes");
            assert!(
                p + 1 == parts.len() || size >= min,
                "part {p} of {size} bytes: {parts:?}"
            );
        }
        assert_eq!(joined, expected);
    }

    #[test]
    fn a_header_is_topped_up_and_the_rest_copied() {
        let segments = [Segment::Bytes(vec![1, 2]), copy("a", 2..40), copy("b", 2..30)];
        let parts = plan_parts(&segments, 8, 16);
        check(&segments, &parts, 8, 16);
        assert_eq!(
            parts[0],
            Part::Upload(vec![
                Piece::Bytes(vec![1, 2]),
                Piece::Read {
                    key: "a".into(),
                    range: 2..8
                }
            ])
        );
        let read: u64 = parts
            .iter()
            .map(|p| match p {
                Part::Upload(pieces) => pieces
                    .iter()
                    .map(|piece| match piece {
                        Piece::Read { range, .. } => len(range),
                        Piece::Bytes(_) => 0,
                    })
                    .sum(),
                Part::Copy { .. } => 0,
            })
            .sum();
        assert_eq!(read, 6, "only the header's top-up passes through: {parts:?}");
    }

    #[test]
    fn small_ranges_in_the_middle_are_read_and_sizes_hold_everywhere() {
        for sizes in [
            [3u64, 5, 9, 40],
            [20, 1, 1, 1],
            [7, 8, 9, 1],
            [100, 3, 100, 3],
            [1, 1, 1, 1],
        ] {
            for header in [0usize, 2, 9] {
                let mut segments = vec![Segment::Bytes(vec![7; header])];
                for (i, n) in sizes.iter().enumerate() {
                    segments.push(copy(&i.to_string(), 10..10 + n));
                }
                let parts = plan_parts(&segments, 8, 16);
                check(&segments, &parts, 8, 16);
            }
        }
    }
}
