//! This machine's disk as the read model sees it (`--disk-model measured`): a probe of a
//! dataset's pack measures the service time of one small read and the bandwidth of many
//! reads in parallel, and the figures go to a file (`disk-model.json`) that later runs
//! name (`--disk-model measured:FILE`), so that they repeat exactly.
//!
//! * **Latency**: the smallest level of up to [`LATENCY_READS`] textures spread over the
//!   pack, read one after another on one thread with the pack out of the page cache.
//! * **Bandwidth**: level 0 of textures spread over the pack, up to [`BANDWIDTH_BYTES`],
//!   read on the loader's threads (rayon's pool) with the pack out of the page cache.
//! * **Queue depth**: those threads, as many reads as the loader has outstanding.
//!
//! Where the page cache cannot be dropped the figures are the cache's, and the file says
//! so.

use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use citystream_dataset::Dataset;
use citystream_streaming::disk_model::DiskModel;
use rayon::prelude::*;

/// Reads timed one at a time for the latency.
pub const LATENCY_READS: usize = 256;
/// Bytes read in parallel for the bandwidth.
pub const BANDWIDTH_BYTES: u64 = 256 << 20;

/// The file `--disk-model measured` writes and `measured:FILE` reads.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DiskModelFile {
    /// Bytes per second of parallel reads.
    pub bytes_per_s: u64,
    /// Service time of one small read, nanoseconds.
    pub request_latency_ns: u64,
    /// Reads outstanding at once.
    pub queue_depth: u32,
    /// What was measured, where and how.
    pub source: String,
}

impl DiskModelFile {
    /// The model these figures make, checked.
    pub fn model(&self) -> Result<DiskModel> {
        let model = DiskModel {
            bytes_per_s: self.bytes_per_s,
            request_latency: Duration::from_nanos(self.request_latency_ns),
            queue_depth: self.queue_depth,
        };
        model.validate()?;
        Ok(model)
    }

    /// Reads and checks `path`.
    pub fn read(path: &Path) -> Result<Self> {
        let text =
            std::fs::read_to_string(path).with_context(|| format!("reading the disk model {}", path.display()))?;
        let file: DiskModelFile = serde_json::from_str(&text).with_context(|| {
            format!(
                "{}: not a disk model (bytes_per_s, request_latency_ns, queue_depth, source)",
                path.display()
            )
        })?;
        file.model().with_context(|| format!("{}", path.display()))?;
        Ok(file)
    }

    /// Writes it to `path`, atomically.
    pub fn write(&self, path: &Path) -> Result<()> {
        let json = serde_json::to_string_pretty(self)?;
        citystream_gen::files::write_atomically(path, json.as_bytes())
    }
}

/// Measures the disk under `dataset_dir`'s pack (module docs).
pub fn measure(dataset: &Dataset, dataset_dir: &Path) -> Result<DiskModelFile> {
    let textures = &dataset.textures;
    let count = textures.len();
    if count == 0 {
        bail!("{}: no textures to measure the disk with", dataset_dir.display());
    }
    let pack_path = textures.pack_path().to_path_buf();
    let pack = File::open(&pack_path).with_context(|| {
        format!(
            "opening {} (--disk-model measured needs a local dataset)",
            pack_path.display()
        )
    })?;
    // Textures spread evenly over the pack, the same ones on every probe.
    let spread = |n: usize| -> Vec<u32> {
        let n = n.min(count as usize).max(1);
        (0..n)
            .map(|i| (i as u64 * u64::from(count) / n as u64) as u32)
            .collect()
    };
    let locate = |texture: u32, smallest: bool| -> Result<(u64, u64)> {
        let levels = textures
            .info(texture)
            .with_context(|| format!("texture {texture}"))?
            .mip_count();
        let level = if smallest { levels.saturating_sub(1) } else { 0 };
        let at = textures
            .mip_location(texture, level)
            .with_context(|| format!("locating texture {texture} level {level}"))?;
        Ok((at.offset, at.len))
    };
    let small: Vec<(u64, u64)> = spread(LATENCY_READS)
        .into_iter()
        .map(|t| locate(t, true))
        .collect::<Result<_>>()?;
    let mut large = Vec::new();
    let mut large_bytes = 0;
    for texture in spread(count as usize) {
        if large_bytes >= BANDWIDTH_BYTES {
            break;
        }
        let at = locate(texture, false)?;
        large_bytes += at.1;
        large.push(at);
    }

    let cold = drop_page_cache(&pack_path)?;
    let mut buf = Vec::new();
    let started = Instant::now();
    for &(offset, len) in &small {
        buf.resize(len as usize, 0);
        pack.read_exact_at(&mut buf, offset)
            .with_context(|| format!("reading {} at {offset}", pack_path.display()))?;
    }
    let latency = started.elapsed() / small.len() as u32;

    drop_page_cache(&pack_path)?;
    let started = Instant::now();
    large
        .par_iter()
        .try_for_each_init(Vec::new, |buf: &mut Vec<u8>, &(offset, len)| {
            buf.resize(len as usize, 0);
            pack.read_exact_at(buf, offset)
        })
        .with_context(|| format!("reading {}", pack_path.display()))?;
    let elapsed = started.elapsed().as_secs_f64().max(1e-9);
    let bytes_per_s = (large_bytes as f64 / elapsed).round() as u64;
    let threads = rayon::current_num_threads() as u32;
    let file = DiskModelFile {
        bytes_per_s,
        request_latency_ns: u64::try_from(latency.as_nanos()).unwrap_or(u64::MAX),
        queue_depth: threads,
        source: format!(
            "{} of {}: {} reads of the smallest level one at a time, {:.1} MB of level 0 on {threads} threads, \
             the page cache {}",
            pack_path.display(),
            dataset_dir.display(),
            small.len(),
            large_bytes as f64 / 1e6,
            if cold {
                "dropped first"
            } else {
                "warm (it could not be dropped here)"
            }
        ),
    };
    file.model()?;
    Ok(file)
}

/// Drops the pack's pages from the page cache where the OS allows it.
#[cfg(target_os = "linux")]
pub(crate) fn drop_page_cache(path: &Path) -> Result<bool> {
    let file = File::open(path).with_context(|| format!("opening {}", path.display()))?;
    Ok(rustix::fs::fadvise(&file, 0, None, rustix::fs::Advice::DontNeed).is_ok())
}

#[cfg(not(target_os = "linux"))]
pub(crate) fn drop_page_cache(_path: &Path) -> Result<bool> {
    Ok(false)
}
