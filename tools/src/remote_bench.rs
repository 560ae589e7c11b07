//! `citystream bench --scenario remote`: the loader's throughput from local disk against
//! the same dataset from nginx on loopback, directly and through a proxy adding 20 ms and
//! 80 ms per request, at 1, 8 and 32 requests in flight.
//!
//! Each pass is the loader benchmark's pass ([`crate::loader_bench`]): the unthrottled
//! loader over every texture, cycle after cycle (one mip per texture per cycle), until
//! nothing is left, every mip checked against its CRC-32. The local pass runs with the pack
//! in the page cache (after a full pass), so it is the most the loader gets here; nginx
//! serves the same files, also from the page cache.

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use citystream_streaming::dataset::Dataset;
use citystream_streaming::remote::{open_dataset, RemoteOptions};

use crate::fault_proxy::{FaultOptions, FaultProxy};
use crate::loader_bench::loader_pass;
use crate::nginx::Nginx;

/// One measured pass.
#[derive(Debug, Clone, serde::Serialize)]
pub struct RemotePass {
    /// `local`, `nginx`, `nginx + 20 ms` or `nginx + 80 ms`.
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
    // Warm the page cache, then the local reference.
    loader_pass(&local)?;
    let mut passes = vec![measure("local", None, &local)?];
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
        for in_flight in [1usize, 8, 32] {
            let options = RemoteOptions {
                requests_in_flight: in_flight,
                ..RemoteOptions::default()
            };
            let remote = Arc::new(open_dataset(&url, &options).with_context(|| format!("opening {url}"))?);
            passes.push(measure(&source, Some(in_flight), &remote)?);
        }
    }

    let local_mb_s = passes[0].mb_per_s;
    let mut md = format!(
        "# Loader from local disk and over HTTP\n\n`{}`: {} mips, {:.1} MB, {} loader threads; \
         nginx on loopback, directly and through a proxy adding a delay per request.\n\n\
         | source | requests in flight | MB/s | mips/s | of local MB/s |\n|---|---:|---:|---:|---:|\n",
        dataset_dir.display(),
        passes[0].mips,
        passes[0].bytes as f64 / f64::from(1 << 20),
        rayon::current_num_threads()
    );
    for pass in &passes {
        md.push_str(&format!(
            "| {} | {} | {:.1} | {:.0} | {:.1} % |\n",
            pass.source,
            pass.in_flight.map_or_else(|| "-".to_owned(), |n| n.to_string()),
            pass.mb_per_s,
            pass.mips_per_s,
            100.0 * pass.mb_per_s / local_mb_s.max(1e-9)
        ));
    }
    md.push_str(
        "\nMB = 2^20 bytes. Every pass loads the same mips (every level of every texture, one per \
         texture per cycle) and checks each against its CRC-32; the local pass has the pack in the page cache.\n",
    );
    std::fs::write(out.join("remote.json"), serde_json::to_string_pretty(&passes)?)?;
    std::fs::write(out.join("remote.md"), &md)?;
    Ok(md)
}
