//! `citystream bench --scenario loader`: the streaming loader's throughput
//! against raw positioned reads of the same mips.
//!
//! The loader runs unthrottled (no load-size or load-time limit, no mip
//! bias) over a record for every texture asking for its base level, cycle
//! after cycle until nothing is left to load: Algorithm 1's one mip per
//! texture per cycle, from the smallest useful level to the base. Its sink
//! keeps only the (texture, level) pairs and drops the bytes. The raw
//! reader then reads exactly those mips with `pread` on the same rayon
//! threads, into buffers it reuses: the most the disk and page cache give.
//!
//! Each is measured with the pack in the page cache (warm: after a full
//! read) and, on Linux, out of it (cold: `posix_fadvise(DONTNEED)` on the
//! pack before the pass; pages another process keeps mapped may stay). The
//! loader checks every mip against its stored CRC-32 (dataset format 2), so
//! it is compared with raw reads that do the same ("CRC on") and, for the
//! cost of that check, with raw reads that do not ("CRC off").

use std::collections::HashSet;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use citystream_dataset::Dataset;
use citystream_streaming::controller::Decision;
use citystream_streaming::loader::{Loader, LoaderOptions};
use citystream_streaming::records::MeshMetaData;
use citystream_streaming::source::{DatasetSource, MipSink, SinkError, StagedMip};
use rayon::prelude::*;

use crate::disk_probe::drop_page_cache;

/// Keeps which mips arrived, drops the bytes.
#[derive(Debug, Default)]
struct CountingSink {
    /// Shared with the pass, which reads it once the loader is done.
    loaded: Arc<Mutex<Vec<(u32, u32)>>>,
}

impl MipSink for CountingSink {
    fn stage(&self, mip: StagedMip) -> std::result::Result<(), SinkError> {
        self.loaded
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .push((mip.texture, mip.level));
        Ok(())
    }

    fn unload(&self, _texture: u32) {}
}

/// One measured pass.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct Pass {
    /// `loader` or `raw`.
    pub reader: &'static str,
    /// Page cache state: `warm` or `cold`.
    pub cache: &'static str,
    /// A CRC-32 of every mip was computed after its read.
    pub crc: bool,
    /// Mips read.
    pub mips: u64,
    /// Bytes read.
    pub bytes: u64,
    /// Seconds.
    pub seconds: f64,
    /// MB/s (MB = 2^20 bytes).
    pub mb_per_s: f64,
}

/// What one loader pass loaded.
pub(crate) struct LoaderRun {
    /// `(texture, level)` in the order the sink got them.
    pub(crate) loaded: Vec<(u32, u32)>,
    pub(crate) bytes: u64,
    pub(crate) elapsed: Duration,
}

/// The unthrottled loader over every texture until it loads nothing more.
pub(crate) fn loader_pass(dataset: &Arc<Dataset>) -> Result<LoaderRun> {
    let count = dataset.textures.len();
    let loaded = Arc::new(Mutex::new(Vec::new()));
    let sink = CountingSink {
        loaded: Arc::clone(&loaded),
    };
    let loader = Loader::new(
        DatasetSource::new(Arc::clone(dataset)),
        sink,
        (0..count).collect(),
        count as usize,
        LoaderOptions {
            load_time: Duration::from_secs(24 * 3600),
            ..LoaderOptions::default()
        },
    )
    .context("building the loader")?;
    let records: Vec<MeshMetaData> = (0..count)
        .map(|texture| MeshMetaData {
            mip_level: 0,
            weight: 1000,
            mesh_id: texture,
        })
        .collect();
    let decision = Decision::new(u64::MAX, 0.0);
    let started = Instant::now();
    loop {
        let report = loader.run_cycle(&records, decision).context("the loader was busy")?;
        if report.failed > 0 {
            bail!("{} mips failed to load: {:?}", report.failed, loader.failures().first());
        }
        if report.loaded_mips == 0 {
            break;
        }
    }
    let elapsed = started.elapsed();
    let bytes = loader.totals().loaded_bytes;
    let loaded = std::mem::take(&mut *loaded.lock().unwrap_or_else(std::sync::PoisonError::into_inner));
    Ok(LoaderRun { loaded, bytes, elapsed })
}

/// `pread` of each `(offset, len)` on the rayon pool into reused buffers.
fn raw_pass(pack: &File, mips: &[(u64, u64)], crc: bool) -> Result<(u64, Duration)> {
    let started = Instant::now();
    let fold = std::sync::atomic::AtomicU32::new(0);
    mips.par_iter()
        .try_for_each_init(Vec::new, |buf: &mut Vec<u8>, &(offset, len)| {
            buf.resize(len as usize, 0);
            pack.read_exact_at(buf, offset)?;
            if crc {
                fold.fetch_xor(crc32fast::hash(buf), std::sync::atomic::Ordering::Relaxed);
            }
            std::io::Result::Ok(())
        })?;
    Ok((mips.iter().map(|m| m.1).sum(), started.elapsed()))
}

fn pass(reader: &'static str, cache: &'static str, crc: bool, mips: u64, bytes: u64, time: Duration) -> Pass {
    let seconds = time.as_secs_f64();
    Pass {
        reader,
        cache,
        crc,
        mips,
        bytes,
        seconds,
        mb_per_s: bytes as f64 / f64::from(1 << 20) / seconds.max(1e-9),
    }
}

/// Runs the benchmark on `dataset_dir`, writing `loader.json`, `loader.md` and the read
/// model's `disk-model.json` ([`crate::disk_probe`]) to `out`; returns the markdown.
pub fn run(dataset_dir: &Path, out: &Path) -> Result<String> {
    let dataset = Arc::new(Dataset::open(dataset_dir).with_context(|| format!("opening {}", dataset_dir.display()))?);
    let pack_path = dataset.textures.pack_path().to_path_buf();
    let pack = File::open(&pack_path).with_context(|| format!("opening {}", pack_path.display()))?;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let threads = rayon::current_num_threads();
    eprintln!(
        "loader benchmark on {} ({} textures, {threads} threads)",
        dataset_dir.display(),
        dataset.textures.len()
    );

    // The mips the loader loads, found by one pass (which also warms the cache).
    let loaded = loader_pass(&dataset)?.loaded;
    let unique: HashSet<(u32, u32)> = loaded.iter().copied().collect();
    if unique.len() != loaded.len() {
        bail!("the loader loaded {} mips twice", loaded.len() - unique.len());
    }
    let mut mips: Vec<(u64, u64)> = loaded
        .iter()
        .map(|&(texture, level)| {
            dataset
                .textures
                .mip_location(texture, level)
                .map(|l| (l.offset, l.len))
                .with_context(|| format!("locating texture {texture} level {level}"))
        })
        .collect::<Result<_>>()?;
    // The loader reads in priority order; raw reads go in pack order, its best case.
    mips.sort_unstable();
    let count = mips.len() as u64;
    eprintln!(
        "{count} mips, {:.1} MB",
        mips.iter().map(|m| m.1).sum::<u64>() as f64 / f64::from(1 << 20)
    );

    let mut passes = Vec::new();
    let mut cold_supported = true;
    for cache in ["warm", "cold"] {
        if cache == "cold" && !cold_supported {
            break;
        }
        for crc in [false, true] {
            // Raw, loader, raw again: the two raw passes bracket the loader's.
            for reader in ["raw", "loader", "raw"] {
                if cache == "cold" {
                    cold_supported = drop_page_cache(&pack_path)?;
                    if !cold_supported {
                        eprintln!("the page cache cannot be dropped here: cold passes skipped");
                        break;
                    }
                } else {
                    raw_pass(&pack, &mips, false)?;
                }
                let measured = if reader == "raw" {
                    let (bytes, time) = raw_pass(&pack, &mips, crc)?;
                    pass("raw", cache, crc, count, bytes, time)
                } else {
                    let run = loader_pass(&dataset)?;
                    if run.loaded.len() as u64 != count {
                        bail!("the loader loaded {} mips this time, {count} before", run.loaded.len());
                    }
                    // The loader always checks: `crc` says which raw reads it is set against.
                    pass("loader", cache, crc, count, run.bytes, run.elapsed)
                };
                eprintln!(
                    "{:>6} {cache} crc {:>6}: {:.3} s, {:.1} MB/s",
                    measured.reader,
                    match (measured.reader, crc) {
                        ("loader", _) => "always",
                        (_, true) => "on",
                        _ => "off",
                    },
                    measured.seconds,
                    measured.mb_per_s
                );
                passes.push(measured);
            }
        }
    }

    let mut md = format!(
        "# Loader against raw positioned reads\n\n`{}`: {count} mips, {:.1} MB, {threads} threads.\n\n\
         | page cache | raw reads check CRC-32 | raw MB/s (before, after) | loader MB/s (checks every mip) | loader / raw |\n|---|---|---:|---:|---:|\n",
        dataset_dir.display(),
        mips.iter().map(|m| m.1).sum::<u64>() as f64 / f64::from(1 << 20)
    );
    for group in passes.chunks(3) {
        let [before, loader, after] = group else { continue };
        let raw = (before.mb_per_s + after.mb_per_s) / 2.0;
        md.push_str(&format!(
            "| {} | {} | {:.1}, {:.1} | {:.1} | {:.1} % |\n",
            loader.cache,
            if loader.crc { "on" } else { "off" },
            before.mb_per_s,
            after.mb_per_s,
            loader.mb_per_s,
            100.0 * loader.mb_per_s / raw.max(1e-9)
        ));
    }
    md.push_str("\nMB = 2^20 bytes. The loader's time includes its planning (state and header lookups).\n");
    // This machine's disk as the flythrough's read model takes it (`--disk-model
    // measured:OUT/disk-model.json`).
    let disk = crate::disk_probe::measure(&dataset, dataset_dir)?;
    disk.write(&out.join("disk-model.json"))?;
    md.push_str(&format!(
        "\nThe read model's figures (`disk-model.json`, for `flythrough --disk-model measured:FILE`): \
         {:.1} MB/s, {:.1} µs per request, {} reads in flight ({}).\n",
        disk.bytes_per_s as f64 / 1e6,
        disk.request_latency_ns as f64 / 1e3,
        disk.queue_depth,
        disk.source
    ));
    let json = serde_json::to_string_pretty(&passes)?;
    let json_path = out.join("loader.json");
    citystream_gen::files::write_atomically(&json_path, json.as_bytes())?;
    let md_path = out.join("loader.md");
    citystream_gen::files::write_atomically(&md_path, md.as_bytes())?;
    Ok(md)
}
