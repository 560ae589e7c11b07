//! Dataset benchmark: generation throughput, open time and host bytes per texture.
//!
//! `cargo bench -p citystream-cli --bench dataset` (set `CITYSTREAM_BENCH_PRESET=small`
//! for a quick run). Prints:
//! 1. `citystream gen --preset large` (about 100 000 textures): textures/s and MB/s;
//! 2. the time to open that dataset (median of 5) and its host metadata per texture;
//! 3. the time to open a Berlin-sized texture table (5 712 309 textures of one 4×4 BC1 mip
//!    each, so the pack stays small) — the cost bounded by "opens in seconds".

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{ensure, Context, Result};
use citystream_dataset::{Dataset, DatasetWriter, Scene, TextureFormat};

const BERLIN_TEXTURES: u32 = 5_712_309;

fn median_open(dir: &Path, runs: usize) -> Result<(Duration, Dataset)> {
    let mut times = Vec::new();
    let mut last = None;
    for _ in 0..runs {
        let start = Instant::now();
        let dataset = Dataset::open(dir)?;
        times.push(start.elapsed());
        last = Some(dataset);
    }
    times.sort();
    Ok((times[times.len() / 2], last.context("no runs")?))
}

fn main() -> Result<()> {
    let preset = std::env::var("CITYSTREAM_BENCH_PRESET").unwrap_or_else(|_| "large".into());
    let root = Path::new(env!("CARGO_TARGET_TMPDIR")).join("dataset-bench");
    let dir = root.join(&preset);

    let start = Instant::now();
    let out = Command::new(env!("CARGO_BIN_EXE_citystream"))
        .args(["gen", "--preset", &preset, "--seed", "1", "--quiet", "--out"])
        .arg(&dir)
        .output()?;
    ensure!(
        out.status.success(),
        "gen failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let wall = start.elapsed().as_secs_f64();
    println!("== citystream gen --preset {preset} --seed 1 (wall {wall:.1} s, including process start)");
    print!("{}", String::from_utf8_lossy(&out.stdout));

    let (open, dataset) = median_open(&dir, 5)?;
    let textures = dataset.textures.len();
    println!(
        "== open {preset}: {:.1} ms median of 5 ({} textures, {} meshes; includes reading and validating the {:.1} MB of tiles and their geometry)",
        open.as_secs_f64() * 1e3,
        textures,
        dataset.scene.meshes.len(),
        dataset.scene_file_len() as f64 / 1e6
    );
    println!(
        "   host metadata: {:.1} bytes per texture ({} per texture + {} per mip checksum, {:.2} mips per texture); on disk {} bytes per texture + {} per mip",
        host_metadata_bytes(&dataset) as f64 / f64::from(textures),
        Dataset::metadata_bytes_per_texture(),
        Dataset::metadata_bytes_per_mip(),
        mip_count(&dataset) as f64 / f64::from(textures),
        10 + 4,
        4
    );
    drop(dataset);
    std::fs::remove_dir_all(&dir)?;

    let berlin = root.join("berlin-table");
    let mut writer = DatasetWriter::create(&berlin)?;
    let block = [0u8; 8];
    for _ in 0..BERLIN_TEXTURES {
        writer.add_texture(TextureFormat::Bc1, 4, 4, 1, &block, [128, 128, 128, 255])?;
    }
    writer.finish(&Scene::new([0.0; 3]))?;
    let (open, dataset) = median_open(&berlin, 3)?;
    println!(
        "== open a {} -texture table: {:.0} ms median of 3, {:.1} MB host metadata",
        dataset.textures.len(),
        open.as_secs_f64() * 1e3,
        host_metadata_bytes(&dataset) as f64 / 1e6
    );
    drop(dataset);
    std::fs::remove_dir_all(&berlin)?;
    Ok(())
}

fn mip_count(dataset: &Dataset) -> u64 {
    dataset
        .textures
        .textures()
        .iter()
        .map(|t| u64::from(t.mip_count()))
        .sum()
}

/// What the opened texture metadata holds in host memory: records, checksum indices and
/// mip checksums (`TexturePack::metadata_bytes`) plus the colormap.
fn host_metadata_bytes(dataset: &Dataset) -> u64 {
    dataset.textures.metadata_bytes() as u64 + 4 * u64::from(dataset.textures.len())
}
