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
//! Reads are direct (`O_DIRECT`, in aligned 4 KiB blocks), so neither a warm page cache nor
//! the kernel's readahead answers them. Where the file system refuses direct reads they are
//! buffered with the page cache dropped first, and where that fails too the figures are the
//! cache's; the file's `source` says which.

use std::fs::File;
use std::io::Read;
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

/// The most bytes a disk model file may hold (the probe writes a few hundred).
pub const MAX_FILE_BYTES: u64 = 64 * 1024;

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

    /// Reads and checks `path`: a regular file of at most [`MAX_FILE_BYTES`] (a device, a
    /// FIFO or a huge file is refused before it is read).
    pub fn read(path: &Path) -> Result<Self> {
        let file = File::open(path).with_context(|| format!("opening the disk model {}", path.display()))?;
        let meta = file
            .metadata()
            .with_context(|| format!("reading the disk model {}", path.display()))?;
        if !meta.is_file() {
            bail!(
                "the disk model {} is not a regular file (a device, FIFO or directory cannot hold one)",
                path.display()
            );
        }
        let mut text = String::new();
        // The limit holds even for a file that grows while it is read.
        file.take(MAX_FILE_BYTES + 1)
            .read_to_string(&mut text)
            .with_context(|| format!("reading the disk model {}", path.display()))?;
        if text.len() as u64 > MAX_FILE_BYTES {
            bail!(
                "the disk model {} is larger than {MAX_FILE_BYTES} bytes: not a file `--disk-model measured` wrote",
                path.display()
            );
        }
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

    // Buffered reads of a small pack hit the page cache (readahead fills it after the
    // first read), so the probe reads around it where the file system allows.
    let mut buf = Vec::new();
    let (reader, direct) = match open_direct(&pack_path) {
        Some(file)
            if small
                .first()
                .is_none_or(|&(offset, len)| read_span(&file, true, &mut buf, offset, len).is_ok()) =>
        {
            (file, true)
        }
        _ => (pack, false),
    };
    let cold = drop_page_cache(&pack_path)?;
    let started = Instant::now();
    for &(offset, len) in &small {
        read_span(&reader, direct, &mut buf, offset, len)
            .with_context(|| format!("reading {} at {offset}", pack_path.display()))?;
    }
    let latency = started.elapsed() / small.len() as u32;

    drop_page_cache(&pack_path)?;
    let started = Instant::now();
    large
        .par_iter()
        .try_for_each_init(Vec::new, |buf: &mut Vec<u8>, &(offset, len)| {
            read_span(&reader, direct, buf, offset, len).map(drop)
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
             {}",
            pack_path.display(),
            dataset_dir.display(),
            small.len(),
            large_bytes as f64 / 1e6,
            match (direct, cold) {
                (true, _) => "direct reads (O_DIRECT, around the page cache)",
                (false, true) => {
                    "buffered reads (the file system refuses direct reads), the page cache dropped first: \
                     readahead's page-cache hits are in these figures"
                }
                (false, false) =>
                    "buffered reads from a warm page cache (neither direct reads nor dropping it work here)",
            }
        ),
    };
    file.model()?;
    Ok(file)
}

/// Offsets, lengths and buffers of direct reads are multiples of this (the largest logical
/// block size of common disks).
const DIRECT_ALIGN: usize = 4096;

/// `path` opened for direct reads (around the page cache), where the file system allows it.
#[cfg(target_os = "linux")]
fn open_direct(path: &Path) -> Option<File> {
    use rustix::fs::{Mode, OFlags};
    rustix::fs::open(path, OFlags::RDONLY | OFlags::DIRECT | OFlags::CLOEXEC, Mode::empty())
        .ok()
        .map(File::from)
}

#[cfg(not(target_os = "linux"))]
fn open_direct(_path: &Path) -> Option<File> {
    None
}

/// Reads `len` bytes of `file` at `offset` into `buf`; a `direct` file is read in aligned
/// blocks around the span, into an aligned window of `buf`. Returns where in `buf` the
/// bytes are.
fn read_span(
    file: &File,
    direct: bool,
    buf: &mut Vec<u8>,
    offset: u64,
    len: u64,
) -> std::io::Result<std::ops::Range<usize>> {
    if !direct {
        buf.resize(len as usize, 0);
        file.read_exact_at(buf, offset)?;
        return Ok(0..len as usize);
    }
    let align = DIRECT_ALIGN as u64;
    let start = offset / align * align;
    let end = (offset + len).div_ceil(align) * align;
    let span = (end - start) as usize;
    buf.resize(span + DIRECT_ALIGN, 0);
    let shift = buf.as_ptr().align_offset(DIRECT_ALIGN);
    let window = &mut buf[shift..shift + span];
    let wanted = (offset + len - start) as usize;
    let mut done = 0;
    while done < wanted {
        // Whole blocks until the end of the file, where a direct read returns short.
        match file.read_at(&mut window[done..], start + done as u64)? {
            0 => return Err(std::io::ErrorKind::UnexpectedEof.into()),
            n => done += n,
        }
    }
    let first = shift + (offset - start) as usize;
    Ok(first..first + len as usize)
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

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("citystream-disk-probe-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("scratch directory");
        dir
    }

    #[test]
    fn a_disk_model_that_is_not_a_small_regular_file_is_refused_unread() {
        let err = DiskModelFile::read(Path::new("/dev/zero")).expect_err("/dev/zero");
        assert!(format!("{err:#}").contains("not a regular file"), "{err:#}");
        let dir = scratch("kinds");
        let fifo = dir.join("fifo");
        let made = std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .expect("mkfifo runs");
        assert!(made.success());
        // Opening a FIFO for reading with no writer would block: refused from its metadata
        // only after the open, so it is opened where a writer exists.
        let writer = std::thread::spawn({
            let fifo = fifo.clone();
            move || std::fs::OpenOptions::new().write(true).open(fifo).map(drop)
        });
        let err = DiskModelFile::read(&fifo).expect_err("a FIFO");
        assert!(format!("{err:#}").contains("not a regular file"), "{err:#}");
        writer.join().expect("writer").expect("FIFO opened for writing");
        let err = DiskModelFile::read(&dir).expect_err("a directory");
        assert!(format!("{err:#}").contains("not a regular file"), "{err:#}");
        let huge = dir.join("huge.json");
        std::fs::write(&huge, vec![b' '; MAX_FILE_BYTES as usize + 1]).expect("written");
        let err = DiskModelFile::read(&huge).expect_err("a huge file");
        assert!(format!("{err:#}").contains("larger than 65536 bytes"), "{err:#}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_direct_read_returns_the_span_asked_for_at_any_offset() {
        let dir = scratch("span");
        let path = dir.join("data");
        let bytes: Vec<u8> = (0..20_000u32).map(|i| (i * 7 % 251) as u8).collect();
        std::fs::write(&path, &bytes).expect("written");
        let direct = open_direct(&path);
        for (file, is_direct) in [(File::open(&path).ok(), false), (direct, true)] {
            let Some(file) = file else { continue };
            let mut buf = Vec::new();
            for (offset, len) in [(0u64, 8u64), (4095, 2), (5000, 15_000), (19_999, 1)] {
                let at = read_span(&file, is_direct, &mut buf, offset, len).expect("read");
                assert_eq!(
                    buf[at],
                    bytes[offset as usize..][..len as usize],
                    "{offset}+{len}, direct {is_direct}"
                );
            }
            assert!(
                read_span(&file, is_direct, &mut buf, 19_990, 20).is_err(),
                "past the end"
            );
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}
