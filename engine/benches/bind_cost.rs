//! What `vkQueueBindSparse` costs on the device the engine picks, from the
//! submission until the GPU has carried it out: batches of 1 to 4,096 blocks
//! of 64 KiB (a BC1 cache image of 2048² layers, as the cache makes them),
//! bound and then unbound, contiguous (adjacent blocks on adjacent memory:
//! the binder merges them into one entry) and scattered (every other block,
//! memory in reverse: one entry per block).
//!
//! This is what the `desktop` bind-latency model (`streaming::bind_latency`)
//! stands in for: its cost is `5 µs + 0.5 µs·n + 0.448 µs·n²` per batch of
//! n contiguous blocks (470 ms for 1,024), charged alike for unbinds. The
//! table prints that model's figure beside each measured one.
//!
//! Run: `cargo bench -p citystream-engine --bench bind_cost` (the device as
//! `CITYSTREAM_DEVICE` names it, or the best one). `CITYSTREAM_BENCH_OUT=FILE`
//! also writes the rows as CSV. Nothing is asserted (speed lives in
//! benchmarks, not tests).

use std::io::Write;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{ensure, Context, Result};
use citystream_cache::{BindOp, BlockKey, MemorySlot};
use citystream_engine::binder::VulkanBinder;
use citystream_engine::instance::InstanceOptions;
use citystream_engine::sparse::{SparseImage, SparseImageDesc, SparseMemoryChunk};
use citystream_engine::vk;
use citystream_engine::{Device, DeviceOptions};
use citystream_streaming::bind_latency::{BatchShape, BindLatencyModel, BindLatencyPreset};

/// Batch sizes in blocks.
const SIZES: [u32; 8] = [1, 4, 16, 64, 256, 1024, 2048, 4096];
/// Timed repetitions of each batch (the median is reported).
const REPEATS: usize = 7;
const LAYER_SIZE: u32 = 2048;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

struct Setup {
    device: Arc<Device>,
    binder: VulkanBinder,
    /// Level-0 blocks of every layer, in (layer, row, column) order.
    blocks: Vec<BlockKey>,
    block_bytes: u64,
}

fn setup() -> Result<Setup> {
    let device = Arc::new(Device::new(&DeviceOptions {
        instance: InstanceOptions {
            validation: false,
            synchronization: false,
            app_name: "bind cost bench".into(),
            extensions: Vec::new(),
        },
        device_name: None,
        presentation: false,
        // Binds are what it measures.
        sparse: citystream_engine::device::SparseMode::On,
        ..Default::default()
    })?);
    println!("device: {}", citystream_engine::device::describe(&device));
    print_sparse_shapes(&device)?;
    let probe = SparseImage::new(
        &device,
        SparseImageDesc {
            width: LAYER_SIZE,
            height: LAYER_SIZE,
            layers: 1,
            mips: 1,
            format: vk::Format::BC1_RGB_UNORM_BLOCK,
        },
        "bind cost probe image",
    )?;
    let (across, down) = probe.level_blocks(0);
    let per_layer = across * down;
    let needed = *SIZES.iter().max().unwrap_or(&1) * 2;
    let layers = needed.div_ceil(per_layer.max(1));
    ensure!(
        layers <= device.properties().limits.max_image_array_layers,
        "{layers} layers of {LAYER_SIZE}² needed, the device allows {}",
        device.properties().limits.max_image_array_layers
    );
    drop(probe);
    let image = Arc::new(SparseImage::new(
        &device,
        SparseImageDesc {
            width: LAYER_SIZE,
            height: LAYER_SIZE,
            layers,
            mips: LAYER_SIZE.ilog2() + 1,
            format: vk::Format::BC1_RGB_UNORM_BLOCK,
        },
        "bind cost image",
    )?);
    let block_bytes = image.block_size();
    println!(
        "image: BC1 {LAYER_SIZE}² x {layers} layers, {across}x{down} blocks of {} KiB per layer at level 0",
        block_bytes / 1024
    );
    let mut binder = VulkanBinder::with_checks(&device, vec![Arc::clone(&image)], false)?;
    let memory_blocks = u64::from(*SIZES.iter().max().unwrap_or(&1));
    binder.add_chunk(SparseMemoryChunk::new(
        &device,
        &image,
        memory_blocks,
        "bind cost memory",
    )?)?;
    let blocks = (0..layers)
        .flat_map(|layer| {
            (0..down).flat_map(move |y| {
                (0..across).map(move |x| BlockKey {
                    image: 0,
                    layer,
                    mip: 0,
                    x,
                    y,
                })
            })
        })
        .collect();
    Ok(Setup {
        device,
        binder,
        blocks,
        block_bytes,
    })
}

/// What the device reports for the cache's formats and layer sizes: block
/// bytes, granularity and the mip tail (what binding a tail would need).
fn print_sparse_shapes(device: &Arc<Device>) -> Result<()> {
    let support = device.sparse_support();
    println!(
        "sparseAddressSpaceSize {} bytes, residencyNonResidentStrict {}",
        support.address_space_size, support.non_resident_strict
    );
    for format in [
        vk::Format::BC1_RGB_UNORM_BLOCK,
        vk::Format::BC3_UNORM_BLOCK,
        vk::Format::BC7_UNORM_BLOCK,
        vk::Format::R8G8B8A8_UNORM,
    ] {
        for size in [512u32, 2048] {
            let image = SparseImage::new(
                device,
                SparseImageDesc {
                    width: size,
                    height: size,
                    layers: 4,
                    mips: size.ilog2() + 1,
                    format,
                },
                "sparse shape probe",
            )?;
            let (gw, gh) = image.granularity();
            println!(
                "{format:?} {size}² x4 layers: block {} B, granularity {gw}x{gh} texels, {:?}",
                image.block_size(),
                image.mip_tail()
            );
        }
    }
    Ok(())
}

/// The batch binding `n` blocks: adjacent ones on adjacent memory, or every
/// other one on memory in reverse order.
fn bind_batch(setup: &Setup, n: u32, scattered: bool) -> Vec<BindOp> {
    (0..n as usize)
        .map(|i| {
            let (block, slot) = if scattered {
                (setup.blocks[2 * i], n as usize - 1 - i)
            } else {
                (setup.blocks[i], i)
            };
            BindOp::Bind {
                block,
                memory: MemorySlot {
                    chunk: 0,
                    offset: slot as u64 * setup.block_bytes,
                },
            }
        })
        .collect()
}

/// Seconds from submitting `batch` until the device is idle again.
fn timed_submit(setup: &mut Setup, batch: &[BindOp]) -> Result<(f64, u32)> {
    let started = Instant::now();
    let report = setup.binder.submit_after(batch, None)?;
    setup.device.wait_idle()?;
    Ok((started.elapsed().as_secs_f64(), report.entries))
}

fn main() -> Result<()> {
    let mut setup = setup()?;
    let model = BindLatencyModel::preset(BindLatencyPreset::Desktop);
    let mut csv = String::from("blocks,pattern,entries,bind_ms,unbind_ms,desktop_model_ms\n");
    println!(
        "{:>6} {:>10} {:>8} {:>12} {:>12} {:>12} {:>14}",
        "blocks", "pattern", "entries", "bind ms", "unbind ms", "µs/block", "desktop model"
    );
    // One untimed round first: the driver's first binds set up page tables.
    let warm = bind_batch(&setup, 64, false);
    timed_submit(&mut setup, &warm)?;
    let unbind: Vec<BindOp> = warm.iter().map(|op| BindOp::Unbind { block: op.block() }).collect();
    timed_submit(&mut setup, &unbind)?;
    for scattered in [false, true] {
        for &n in &SIZES {
            let batch = bind_batch(&setup, n, scattered);
            let unbind: Vec<BindOp> = batch.iter().map(|op| BindOp::Unbind { block: op.block() }).collect();
            let (mut binds, mut unbinds, mut entries) = (Vec::new(), Vec::new(), 0);
            for _ in 0..REPEATS {
                let (seconds, e) = timed_submit(&mut setup, &batch)?;
                binds.push(seconds * 1e3);
                entries = e;
                unbinds.push(timed_submit(&mut setup, &unbind)?.0 * 1e3);
            }
            let (bind_ms, unbind_ms) = (median(binds), median(unbinds));
            let model_ms = model.expected_cost_s(BatchShape::of(&batch)) * 1e3;
            let pattern = if scattered { "scattered" } else { "contiguous" };
            println!(
                "{n:>6} {pattern:>10} {entries:>8} {bind_ms:>12.3} {unbind_ms:>12.3} {:>12.2} {model_ms:>14.3}",
                bind_ms * 1e3 / f64::from(n)
            );
            csv.push_str(&format!(
                "{n},{pattern},{entries},{bind_ms:.4},{unbind_ms:.4},{model_ms:.4}\n"
            ));
        }
    }
    if let Some(path) = std::env::var_os("CITYSTREAM_BENCH_OUT") {
        let mut file = std::fs::File::create(&path).with_context(|| format!("creating {path:?}"))?;
        file.write_all(csv.as_bytes())?;
    }
    Ok(())
}
