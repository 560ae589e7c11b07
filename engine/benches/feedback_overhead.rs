//! Cost of the feedback pass and compaction on the device the engine picks
//! (lavapipe here): frame time of the visible pass alone versus with the
//! feedback depth pre-pass, feedback pass and compaction, and the compaction
//! of 5.7 M meshes (the paper's Berlin texture count).
//!
//! Run: `cargo bench -p citystream-engine --bench feedback_overhead`.
//! Prints a table; nothing is asserted (speed lives in benchmarks, not tests).

use citystream_dataset::TextureFormat;
use std::sync::Arc;
use std::time::Instant;

use anyhow::Result;
use citystream_engine::city::{Camera, CityMesh, CityRenderer, FeedbackView};
use citystream_engine::commands::CommandContext;
use citystream_engine::feedback::FeedbackCompactor;
use citystream_engine::gpu_types::{MeshFeedback, FEEDBACK_UNSEEN};
use citystream_engine::instance::InstanceOptions;
use citystream_engine::pipeline::Filtering;
use citystream_engine::placeholder::{self, SplitMix64};
use citystream_engine::target::RenderTarget;
use citystream_engine::texture_cache::{CacheLayers, Eviction, GpuCacheConfig, GpuTextureCache};
use citystream_engine::timing::GpuTimer;
use citystream_engine::{Device, DeviceOptions};
use glam::Vec3;

const FRAMES: u32 = 60;
const WIDTH: u32 = 640;
const HEIGHT: u32 = 360;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> Result<()> {
    let device = Arc::new(Device::new(&DeviceOptions {
        instance: InstanceOptions {
            validation: false,
            synchronization: false,
            app_name: "feedback overhead bench".into(),
            extensions: Vec::new(),
        },
        device_name: None,
        presentation: false,
        ..Default::default()
    })?);
    println!("device: {}", citystream_engine::device::describe(&device));
    let mut commands = CommandContext::new(&device, "bench")?;

    // A placeholder city of 20x20 blocks; every mesh gets its own 512x512 texture id.
    let geometry = placeholder::city(7, 20);
    let meshes: Vec<CityMesh> = geometry
        .meshes
        .iter()
        .enumerate()
        .map(|(i, m)| CityMesh {
            first_index: m.first_index,
            index_count: m.index_count,
            vertex_offset: m.vertex_offset,
            texture: i as u32,
            texture_width: 512,
            texture_height: 512,
            origin: glam::DVec3::ZERO,
        })
        .collect();
    let count = meshes.len() as u32;
    let cache = GpuTextureCache::new(
        &device,
        &mut commands,
        &GpuCacheConfig {
            layer_size: 512,
            layers: CacheLayers::Fixed(4),
            formats: vec![TextureFormat::Bc1, TextureFormat::Rgba8],
            eviction: Eviction::Ring,
            memory_budget_bytes: 64 << 20,
            virtual_budget_bytes: None,
            blocks_per_chunk: 64,
            texture_count: count,
            filtering: Filtering::BilinearNearestLevel,
            staging_bytes: 16 << 20,
        },
        &vec![[128, 128, 128, 255]; count as usize],
    )?;
    let compactor = FeedbackCompactor::new(&device, &mut commands, count, count)?;
    let renderer = CityRenderer::new(
        &device,
        &mut commands,
        &geometry.vertices,
        &geometry.indices,
        meshes,
        &cache,
        &compactor,
    )?;
    let target = RenderTarget::new(&device, WIDTH, HEIGHT)?;
    let feedback_target = RenderTarget::new(&device, WIDTH / 4, HEIGHT / 4)?;
    // Slots: 0 the whole frame, 1 depth pre-pass + feedback, 2 compaction.
    let timer = GpuTimer::new(&device, 3)?;
    let view = FeedbackView::default();

    // One frame, timed on the CPU (submit to read-back) and the GPU.
    let mut frame = |camera: &Camera, with_feedback: bool| -> Result<[f64; 4]> {
        let start = Instant::now();
        let cmd = commands.begin()?;
        timer.begin(cmd, 0);
        if with_feedback {
            timer.begin(cmd, 1);
            renderer.record_feedback(cmd, &feedback_target, camera, &view, HEIGHT)?;
            timer.end(cmd, 1);
            timer.begin(cmd, 2);
            compactor.record_compact(cmd, 1200, 0)?;
            timer.end(cmd, 2);
        }
        renderer.record_visible(cmd, &target, camera, 1.0, true)?;
        timer.end(cmd, 0);
        commands.submit_and_wait(&[])?;
        if with_feedback {
            compactor.read_back(0)?;
        }
        let cpu = start.elapsed().as_secs_f64() * 1000.0;
        let gpu = timer.read_ms(0)?.unwrap_or(f64::NAN);
        let (feedback, compaction) = if with_feedback {
            (
                timer.read_ms(1)?.unwrap_or(f64::NAN),
                timer.read_ms(2)?.unwrap_or(f64::NAN),
            )
        } else {
            (0.0, 0.0)
        };
        Ok([cpu, gpu, feedback, compaction])
    };
    // The two variants alternate frame by frame, so both see the same
    // machine state (on a shared 2-core machine, back-to-back runs drift by
    // tens of percent); the first frames warm pipelines up.
    let mut plain: [Vec<f64>; 4] = Default::default();
    let mut with: [Vec<f64>; 4] = Default::default();
    for index in 0..FRAMES + 5 {
        let angle = index as f32 * 0.05;
        let camera = Camera {
            eye: Vec3::new(angle.cos() * 250.0, 120.0, angle.sin() * 250.0).as_dvec3(),
            target: glam::DVec3::new(0.0, 10.0, 0.0),
            fov_y: 60f32.to_radians(),
            near: 1.0,
        };
        let a = frame(&camera, false)?;
        let b = frame(&camera, true)?;
        if index >= 5 {
            for k in 0..4 {
                plain[k].push(a[k]);
                with[k].push(b[k]);
            }
        }
    }
    let [plain_cpu, plain_gpu, _, _] = plain.map(median);
    let [fb_cpu, fb_gpu, fb_pass, fb_compact] = with.map(median);
    println!(
        "city: {count} meshes, {} triangles, {WIDTH}x{HEIGHT}, feedback {}x{}",
        geometry.indices.len() / 3,
        WIDTH / 4,
        HEIGHT / 4
    );
    println!("| frame (median of {FRAMES}, variants interleaved) | CPU wall ms | GPU ms |");
    println!("| --- | ---: | ---: |");
    println!("| visible pass only | {plain_cpu:.2} | {plain_gpu:.2} |");
    println!("| + depth pre-pass, feedback, compaction, read-back | {fb_cpu:.2} | {fb_gpu:.2} |");
    println!(
        "| overhead | {:+.1} % | {:+.1} % |",
        (fb_cpu / plain_cpu - 1.0) * 100.0,
        (fb_gpu / plain_gpu - 1.0) * 100.0
    );
    println!("of which on the GPU: depth pre-pass + feedback {fb_pass:.2} ms, compaction {fb_compact:.2} ms");

    // Compaction of 5.7 M meshes, 2 % of them seen.
    let big = 5_700_000u32;
    let compactor = FeedbackCompactor::new(&device, &mut commands, big, 1 << 20)?;
    let mut rng = SplitMix64::new(3);
    let values: Vec<MeshFeedback> = (0..big)
        .map(|_| {
            if rng.next_f32() < 0.02 {
                MeshFeedback {
                    min_mip: (rng.next_u64() % 3072) as u32,
                    weight: (rng.next_u64() % 4000) as u32,
                }
            } else {
                MeshFeedback {
                    min_mip: FEEDBACK_UNSEEN,
                    weight: 0,
                }
            }
        })
        .collect();
    let mut gpu = Vec::new();
    let mut readback = Vec::new();
    for _ in 0..7 {
        compactor.upload_mesh_feedback(&mut commands, &values)?;
        let cmd = commands.begin()?;
        timer.begin(cmd, 0);
        compactor.record_compact(cmd, 1200, 0)?;
        timer.end(cmd, 0);
        commands.submit_and_wait(&[])?;
        gpu.push(timer.read_ms(0)?.unwrap_or(f64::NAN));
        let start = Instant::now();
        let entries = compactor.read_back(0)?;
        readback.push(start.elapsed().as_secs_f64() * 1000.0);
        std::hint::black_box(entries);
    }
    println!(
        "compaction of {big} meshes: GPU {:.2} ms (median of 7), read-back of the dense entries {:.2} ms",
        median(gpu),
        median(readback)
    );
    device.wait_idle()?;
    Ok(())
}
