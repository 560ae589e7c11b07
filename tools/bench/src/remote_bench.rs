//! `citystream bench --scenario remote`: the loader's throughput from local disk against
//! the same dataset from nginx on loopback, directly and through a proxy adding 20 ms and
//! 80 ms per request, at 1, 8 and 32 requests in flight.
//!
//! Each pass is the loader benchmark's pass ([`crate::loader_bench`]): the unthrottled
//! loader over every texture, cycle after cycle (one mip per texture per cycle), until
//! nothing is left, every mip checked against its CRC-32. Two local references: the pack in
//! the page cache (after a full pass: the most the loader gets here) and read from the disk
//! (its pages dropped first). nginx serves the same files from the page cache. Then the
//! on-disk mip cache at 80 ms: a pass that fills it and one that reads it.

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use citystream_dataset::remote::{open_dataset, RemoteOptions};
use citystream_dataset::Dataset;

use citystream_dataset::remote::MipCacheOptions;

use crate::disk_probe::drop_page_cache;
use crate::loader_bench::loader_pass;
use citystream_testing::fault_proxy::{FaultOptions, FaultProxy};
use citystream_testing::nginx::Nginx;

/// One measured pass.
#[derive(Debug, Clone, serde::Serialize)]
pub struct RemotePass {
    /// `local (page cache)`, `local (disk)`, `nginx`, `nginx + 20 ms`, `nginx + 80 ms`, or
    /// `nginx + 80 ms, mip cache filling` / `… warm`.
    pub source: String,
    /// Prefetch requests in flight (none for local reads).
    pub in_flight: Option<usize>,
    pub mips: u64,
    pub bytes: u64,
    pub seconds: f64,
    pub mb_per_s: f64,
    pub mips_per_s: f64,
}

fn measure(source: &str, in_flight: Option<usize>, dataset: &Arc<Dataset>) -> Result<RemotePass> {
    let run = loader_pass(dataset)?;
    let seconds = run.elapsed.as_secs_f64().max(1e-9);
    let pass = RemotePass {
        source: source.to_owned(),
        in_flight,
        mips: run.loaded.len() as u64,
        bytes: run.bytes,
        seconds,
        mb_per_s: run.bytes as f64 / f64::from(1 << 20) / seconds,
        mips_per_s: run.loaded.len() as f64 / seconds,
    };
    eprintln!(
        "{:>14} {:>9}: {} mips, {:.1} MB in {:.2} s: {:.1} MB/s, {:.0} mips/s",
        pass.source,
        in_flight.map_or_else(|| "-".to_owned(), |n| format!("{n} in fl.")),
        pass.mips,
        pass.bytes as f64 / f64::from(1 << 20),
        pass.seconds,
        pass.mb_per_s,
        pass.mips_per_s
    );
    Ok(pass)
}

/// Runs the benchmark on the dataset in `dataset_dir`; writes `remote.md` and
/// `remote.json` into `out` and returns the table.
pub fn run(dataset_dir: &Path, out: &Path) -> Result<String> {
    let local = Arc::new(Dataset::open(dataset_dir).with_context(|| format!("opening {}", dataset_dir.display()))?);
    let dataset_dir = std::path::absolute(dataset_dir)?;
    let (Some(root), Some(name)) = (dataset_dir.parent(), dataset_dir.file_name()) else {
        bail!("{} has no parent directory to serve", dataset_dir.display());
    };
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let work = out.join("nginx");
    std::fs::create_dir_all(&work)?;
    let nginx = Nginx::start(&work, root)?;
    eprintln!(
        "remote loader benchmark on {} ({} textures, {} loader threads), nginx on port {}",
        dataset_dir.display(),
        local.textures.len(),
        rayon::current_num_threads(),
        nginx.port()
    );
    // Warm the page cache, then the local references: warm, and from the disk.
    loader_pass(&local)?;
    let mut passes = vec![measure("local (page cache)", None, &local)?];
    if drop_page_cache(local.textures.pack_path())? {
        passes.push(measure("local (disk)", None, &local)?);
    } else {
        eprintln!("the OS keeps the pack in its page cache: no local disk pass");
    }
    loader_pass(&local)?;
    let mut delayed_80ms = None;
    for delay_ms in [0u64, 20, 80] {
        let proxy = if delay_ms > 0 {
            Some(FaultProxy::start(
                ([127, 0, 0, 1], nginx.port()).into(),
                FaultOptions {
                    delay: Duration::from_millis(delay_ms),
                    ..FaultOptions::default()
                },
            )?)
        } else {
            None
        };
        let base = match &proxy {
            Some(proxy) => format!("http://{}", proxy.addr()),
            None => format!("http://127.0.0.1:{}", nginx.port()),
        };
        let url = format!("{base}/{}", name.to_string_lossy());
        let source = if delay_ms > 0 {
            format!("nginx + {delay_ms} ms")
        } else {
            "nginx".to_owned()
        };
        for in_flight in [1usize, 8, 32, 64, 128] {
            let options = RemoteOptions {
                requests_in_flight: in_flight,
                ..RemoteOptions::default()
            };
            let remote = Arc::new(open_dataset(&url, &options).with_context(|| format!("opening {url}"))?);
            passes.push(measure(&source, Some(in_flight), &remote)?);
        }
        if delay_ms == 80 {
            delayed_80ms = Some((url, proxy));
        }
    }
    // The mip cache at 80 ms and 32 in flight: a first pass fills it, a second reads it.
    if let Some((url, _proxy)) = &delayed_80ms {
        let cache_dir = out.join("mip-cache");
        if cache_dir.exists() {
            std::fs::remove_dir_all(&cache_dir).with_context(|| format!("emptying {}", cache_dir.display()))?;
        }
        let options = RemoteOptions {
            requests_in_flight: 32,
            mip_cache: Some(MipCacheOptions {
                dir: cache_dir.clone(),
                capacity_bytes: None,
            }),
            ..RemoteOptions::default()
        };
        for phase in ["filling", "warm"] {
            let remote = Arc::new(open_dataset(url, &options).with_context(|| format!("opening {url}"))?);
            passes.push(measure(
                &format!("nginx + 80 ms, mip cache {phase}"),
                Some(32),
                &remote,
            )?);
        }
        std::fs::remove_dir_all(&cache_dir).with_context(|| format!("removing {}", cache_dir.display()))?;
    }

    let cached_mb_s = passes[0].mb_per_s;
    let disk_mb_s = passes.iter().find(|p| p.source == "local (disk)").map(|p| p.mb_per_s);
    let mut md = format!(
        "# Loader from local disk and over HTTP\n\n`{}`: {} mips, {:.1} MB, {} loader threads; \
         nginx on loopback, directly and through a proxy adding a delay per request.\n\n\
         | source | requests in flight | MB/s | mips/s | of local disk MB/s | of page-cache MB/s |\n\
         |---|---:|---:|---:|---:|---:|\n",
        dataset_dir.display(),
        passes[0].mips,
        passes[0].bytes as f64 / f64::from(1 << 20),
        rayon::current_num_threads()
    );
    for pass in &passes {
        md.push_str(&format!(
            "| {} | {} | {:.1} | {:.0} | {} | {:.1} % |\n",
            pass.source,
            pass.in_flight.map_or_else(|| "-".to_owned(), |n| n.to_string()),
            pass.mb_per_s,
            pass.mips_per_s,
            disk_mb_s.map_or_else(
                || "-".to_owned(),
                |disk| format!("{:.1} %", 100.0 * pass.mb_per_s / disk.max(1e-9))
            ),
            100.0 * pass.mb_per_s / cached_mb_s.max(1e-9)
        ));
    }
    md.push_str(
        "\nMB = 2^20 bytes. Every pass loads the same mips (every level of every texture, one per \
         texture per cycle) and checks each against its CRC-32. `local (page cache)` reads the pack from \
         memory, `local (disk)` after dropping its pages; nginx serves from the page cache. The mip cache \
         passes run behind the 80 ms proxy at 32 in flight: `filling` also writes every mip into an empty \
         cache, `warm` reads them back from it (its files still in the page cache).\n",
    );
    citystream_gen::files::write_atomically(
        &out.join("remote.json"),
        serde_json::to_string_pretty(&passes)?.as_bytes(),
    )?;
    citystream_gen::files::write_atomically(&out.join("remote.md"), md.as_bytes())?;
    Ok(md)
}
