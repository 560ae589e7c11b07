//! The streaming module driven as a host drives it: frames in flight, the
//! camera panning over more textures than the memory budget holds, so
//! blocks are evicted and unbound while earlier frames may still sample
//! them. Runs with synchronization validation; any message fails.

use std::sync::Arc;
use std::time::Duration;

use anyhow::{ensure, Context, Result};
use citystream_engine::city::{Camera, CityMesh, CityRenderer, FeedbackView};
use citystream_engine::commands::CommandContext;
use citystream_engine::device::Device;
use citystream_engine::gpu_types::{Vertex, TEXTURE_SAMPLEABLE};
use citystream_engine::image::memory_barrier;
use citystream_engine::stream::{StreamConfig, TextureStreamer};
use citystream_engine::target::RenderTarget;
use citystream_engine::texture_cache::{Eviction, ResidentCache};
use citystream_engine::vk;
use citystream_streaming::controller::{PolicyKind, PolicyOptions};
use citystream_streaming::loader::LoaderOptions;
use citystream_streaming::records::MeshMetaData;
use citystream_streaming::source::{bc1_mip_len, MemorySource};
use citystream_tests::{
    assert_clean_after_dropping, assert_no_validation_errors, sync_validated_device, tail_allowance,
};
use glam::Vec3;

const QUADS: u32 = 24;
const TEXTURE: u32 = 512;
const SPACING: f32 = 12.0;
const WIDTH: u32 = 192;
const HEIGHT: u32 = 108;

/// A row of textured quads facing +z, one texture each.
fn quad_row() -> (Vec<Vertex>, Vec<u32>, Vec<CityMesh>) {
    let mut vertices = Vec::new();
    let mut indices = Vec::new();
    let mut meshes = Vec::new();
    for q in 0..QUADS {
        let x = q as f32 * SPACING;
        let first_vertex = vertices.len() as u32;
        for (dx, dy) in [(0.0, 0.0), (10.0, 0.0), (10.0, 10.0), (0.0, 10.0)] {
            vertices.push(Vertex {
                position: [x + dx, dy, 0.0],
                normal: [0.0, 0.0, 1.0],
                uv: [dx / 10.0, 1.0 - dy / 10.0],
            });
        }
        meshes.push(CityMesh {
            first_index: indices.len() as u32,
            index_count: 6,
            vertex_offset: first_vertex,
            texture: q,
            texture_width: TEXTURE,
            texture_height: TEXTURE,
            origin: glam::DVec3::ZERO,
        });
        indices.extend([0, 1, 2, 0, 2, 3]);
    }
    (vertices, indices, meshes)
}

/// One `TEXTURE`² BC1 texture per quad of [`quad_row`].
fn row_source() -> MemorySource {
    let mut source = MemorySource::new();
    for _ in 0..QUADS {
        source.push_bc1(TEXTURE, TEXTURE);
    }
    source
}

/// What one frame of [`run`] did.
#[derive(Debug)]
struct FrameRecord {
    uploaded: u32,
    staged: Vec<(u32, u32)>,
    dropped: Vec<(u32, u32)>,
    over_budget: bool,
    /// The run's memory budget in bytes.
    budget: u64,
    bound_bytes: u64,
}

/// Pans the camera along the row and back over `frames` frames, or, with
/// `pause_at`, pans until then and holds still.
fn run(
    frames_in_flight: u32,
    deterministic: bool,
    eviction: Eviction,
    frames: u32,
    pause_at: Option<u32>,
) -> Result<Vec<FrameRecord>> {
    let device = sync_validated_device()?;
    let source = row_source();
    let (vertices, indices, meshes) = quad_row();
    let colormap: Vec<[u8; 4]> = (0..QUADS)
        .map(|q| [q as u8 * 10, 128, 255 - q as u8 * 10, 255])
        .collect();
    let view = FeedbackView::default();
    let target = RenderTarget::new(&device, WIDTH, HEIGHT)?;
    let feedback_target = RenderTarget::new(&device, WIDTH / 4, HEIGHT / 4)?;
    // About four 512² BC1 chains fit: far less than the row needs (and, on
    // a device with mip tails, four layers' tails or the single tail).
    let budget = (768 << 10) + tail_allowance(&device, vk::Format::BC1_RGB_UNORM_BLOCK, TEXTURE, QUADS, 4)?;
    let mut streamer = TextureStreamer::new(
        &device,
        source,
        meshes.iter().map(|m| m.texture).collect(),
        &colormap,
        PolicyKind::Baseline.build(&PolicyOptions::default())?,
        &StreamConfig {
            frames_in_flight,
            layer_size: TEXTURE,
            layer_count: Some(QUADS),
            eviction,
            memory_budget_bytes: budget,
            staging_bytes: 1 << 20,
            fragment_area: view.fragment_area(HEIGHT, feedback_target.height()),
            weight_cutoff: 1,
            deterministic,
            ..StreamConfig::default()
        },
    )?;
    let mut setup = CommandContext::new(&device, "stream test setup")?;
    let renderer = CityRenderer::new(
        &device,
        &mut setup,
        &vertices,
        &indices,
        meshes.clone(),
        streamer.cache(),
        streamer.compactor(),
    )?;
    let mut frame_commands = (0..frames_in_flight)
        .map(|i| CommandContext::new(&device, &format!("stream test frame {i}")))
        .collect::<std::result::Result<Vec<_>, _>>()?;

    let (mut unbound, mut uploaded, mut invalidated) = (0u32, 0u32, 0u32);
    let mut records = Vec::new();
    for frame in 0..frames {
        // Pan along the row and back: textures leave the view and return.
        let t = pause_at.map_or(frame, |p| frame.min(p)) as f32 / frames as f32;
        let x = (QUADS as f32 * SPACING - 10.0) * (1.0 - (2.0 * t - 1.0).abs());
        let camera = Camera {
            eye: Vec3::new(x + 5.0, 5.0, 9.0).as_dvec3(),
            target: Vec3::new(x + 5.0, 5.0, 0.0).as_dvec3(),
            fov_y: 60f32.to_radians(),
            near: 0.1,
        };
        let mut begun = streamer.begin_frame()?;
        let over_budget = begun.over_budget();
        let commands = &mut frame_commands[begun.slot() as usize];
        let rec = commands.begin_completed()?;
        let cycle = streamer.record_uploads(&mut begun, rec)?;
        renderer.record_feedback(rec, &feedback_target, &camera, &view, HEIGHT)?;
        streamer.record_feedback_resolve(&mut begun, rec)?;
        renderer.record_visible(rec, &target, &camera, 1.0, true)?;
        let submit = streamer.end_frame(begun, 16.0)?;
        commands.submit_frame(&submit.waits, &[submit.signal])?;
        if !deterministic {
            // The stream does not wait for its loads; the test does, after the frame is
            // submitted, so what a frame has loaded (and so what the budget must evict)
            // does not depend on how fast this machine reads while the frames overlap.
            ensure!(
                streamer.finish_loading(std::time::Duration::from_secs(60)),
                "frame {frame}: the loading task did not finish in 60 s"
            );
        }
        unbound += cycle.blocks_unbound;
        uploaded += cycle.mips_uploaded;
        invalidated += cycle.textures_invalidated;
        records.push(FrameRecord {
            uploaded: cycle.mips_uploaded,
            staged: streamer.last_cycle().staged.clone(),
            dropped: streamer.last_cycle().dropped.clone(),
            over_budget,
            budget,
            bound_bytes: streamer.cache().utilisation().held_bytes(),
        });

        // Every level the table lets shaders sample has all its blocks bound.
        for texture in 0..QUADS {
            let Some(data) = streamer.cache().texture_data(texture) else {
                continue;
            };
            if data.state != TEXTURE_SAMPLEABLE {
                continue;
            }
            let resident = streamer.cache().resident_levels(texture);
            for level in data.lowest_mip..data.mip_count {
                ensure!(
                    resident & (1 << level) != 0,
                    "frame {frame}: texture {texture} samples level {level}, which is not resident"
                );
            }
        }
    }
    device.wait_idle()?;
    ensure!(uploaded > QUADS, "only {uploaded} mips were uploaded");
    let dropped: usize = records.iter().map(|r| r.dropped.len()).sum();
    let evicted = match eviction {
        Eviction::Ring => invalidated,
        Eviction::View => dropped as u32,
    };
    ensure!(
        evicted > 0 && unbound > 0,
        "the budget never evicted ({evicted} textures or levels, {unbound} blocks unbound)"
    );
    let totals = streamer.totals();
    ensure!(totals.loaded_mips > 0, "the loader loaded nothing");
    assert_no_validation_errors(&device)
        .with_context(|| format!("{frames_in_flight} frames in flight, deterministic {deterministic}"))?;
    drop(renderer);
    drop(streamer);
    assert_no_validation_errors(&device)?;
    Ok(records)
}

#[test]
fn two_frames_in_flight_drop_levels_under_a_small_budget_without_hazards() -> Result<()> {
    run(2, false, Eviction::View, 160, None).map(|_| ())
}

#[test]
fn three_frames_in_flight_deterministic_ring_eviction_without_hazards() -> Result<()> {
    run(3, true, Eviction::Ring, 160, None).map(|_| ())
}

/// Under a budget smaller than the view needs, the view-serving eviction
/// never drops a level in the cycle that loads that texture, keeps the
/// bound memory within the budget, reports the frames as over budget, and
/// settles once the camera stops: no uploads in the second half of the pause.
#[test]
fn a_view_larger_than_the_budget_settles_without_reloading() -> Result<()> {
    let (frames, pause_at) = (200, 60);
    let records = run(2, true, Eviction::View, frames, Some(pause_at))?;
    for (frame, record) in records.iter().enumerate() {
        for &(texture, level) in &record.dropped {
            ensure!(
                !record.staged.iter().any(|&(t, _)| t == texture),
                "frame {frame}: texture {texture} level {level} was dropped in the cycle that loads it"
            );
        }
        ensure!(
            record.bound_bytes <= record.budget,
            "frame {frame}: {} bytes bound over a {} byte budget",
            record.bound_bytes,
            record.budget
        );
    }
    ensure!(
        records.iter().any(|r| r.over_budget),
        "a view needing more than the budget was never reported over budget"
    );
    let paused = &records[pause_at as usize..];
    eprintln!(
        "pause: {} uploads, {} drops, {} frames over budget; whole run: {} drops",
        paused.iter().map(|r| r.uploaded).sum::<u32>(),
        paused.iter().map(|r| r.dropped.len()).sum::<usize>(),
        paused.iter().filter(|r| r.over_budget).count(),
        records.iter().map(|r| r.dropped.len()).sum::<usize>(),
    );
    let settled = &records[(pause_at + (frames - pause_at) / 2) as usize..];
    let late_uploads: u32 = settled.iter().map(|r| r.uploaded).sum();
    let late_drops: usize = settled.iter().map(|r| r.dropped.len()).sum();
    ensure!(
        late_uploads == 0 && late_drops == 0,
        "{late_uploads} uploads and {late_drops} drops in the second half of the pause"
    );
    Ok(())
}

/// The check above can fail: a copy that overwrites a buffer another copy
/// just wrote, with no barrier between, is reported as a hazard.
#[test]
fn synchronization_validation_reports_a_missing_barrier() -> Result<()> {
    let device = sync_validated_device()?;
    let buffer = citystream_engine::buffer::Buffer::new(
        &device,
        citystream_engine::buffer::BufferDesc {
            size: 256,
            usage: vk::BufferUsageFlags::TRANSFER_DST,
            location: citystream_engine::gpu_allocator::MemoryLocation::GpuOnly,
        },
        "hazard canary",
    )?;
    let mut commands = CommandContext::new(&device, "hazard canary")?;
    let rec = commands.begin()?;
    // Two writes of one range, with only a barrier that does not cover transfers.
    citystream_engine::commands::record_fill(&device, rec, &buffer, 0);
    memory_barrier(
        &device,
        rec,
        (vk::PipelineStageFlags2::FRAGMENT_SHADER, vk::AccessFlags2::SHADER_READ),
        (vk::PipelineStageFlags2::FRAGMENT_SHADER, vk::AccessFlags2::SHADER_READ),
    );
    citystream_engine::commands::record_fill(&device, rec, &buffer, 1);
    commands.submit_and_wait(&[])?;
    ensure!(
        device
            .validation_log()
            .errors()
            .iter()
            .any(|e| e.id.contains("SYNC-HAZARD")),
        "synchronization validation is not active"
    );
    // Note: the Debian 12 layer (1.3.239) checks hazards within a command
    // buffer only, not between submissions; frames in flight are ordered by
    // the barriers each frame records, which it does check (docs/EMBEDDING.md).
    Ok(())
}

/// Calls the frame token's types cannot order are refused with an error naming the call
/// (those they can order do not compile: see the `compile_fail` examples of
/// `citystream_engine::stream::Frame` and `citystream_engine::commands::Recording`).
/// A streamer of one `side`² BC1 texture (a red placeholder) under the baseline policy.
fn one_texture_streamer(
    device: &Arc<Device>,
    side: u32,
    config: &StreamConfig,
) -> citystream_engine::Result<TextureStreamer<MemorySource>> {
    let mut source = MemorySource::new();
    source.push_bc1(side, side);
    TextureStreamer::new(
        device,
        source,
        vec![0],
        &[[255, 0, 0, 255]],
        PolicyKind::Baseline.build(&PolicyOptions::default())?,
        config,
    )
}

#[test]
fn calls_out_of_order_are_refused() -> Result<()> {
    let device = sync_validated_device()?;
    let new_streamer = || -> Result<TextureStreamer<MemorySource>> {
        let config = StreamConfig {
            layer_size: 256,
            layer_count: Some(2),
            memory_budget_bytes: 1 << 20,
            staging_bytes: 1 << 16,
            ..StreamConfig::default()
        };
        Ok(one_texture_streamer(&device, 64, &config)?)
    };
    let mut streamer = new_streamer()?;
    let mut other = new_streamer()?;
    let mut commands = CommandContext::new(&device, "order test")?;
    let refused = |result: citystream_engine::Result<()>, call: &str| -> Result<()> {
        match result {
            Err(citystream_engine::EngineError::InvalidRequest(message)) if message.contains(call) => Ok(()),
            other => anyhow::bail!("{call} out of order gave {other:?}"),
        }
    };
    refused(commands.recording().map(|_| ()), "not recording")?;
    refused(commands.submit(&[], &[]), "not begun")?;
    let mut frame = streamer.begin_frame()?;
    refused(streamer.begin_frame().map(|_| ()), "begin_frame")?;
    let mut others = other.begin_frame()?;
    let rec = commands.begin()?;
    refused(
        streamer.record_uploads(&mut others, rec).map(|_| ()),
        "another streamer",
    )?;
    refused(streamer.record_feedback_resolve(&mut others, rec), "another streamer")?;
    streamer.record_uploads(&mut frame, rec)?;
    refused(streamer.record_uploads(&mut frame, rec).map(|_| ()), "record_uploads")?;
    refused(streamer.end_frame(others, 16.0).map(|_| ()), "another streamer")?;
    refused(streamer.wait_for_frame(0).map(|_| ()), "frame 0")?;
    let submit = streamer.end_frame(frame, 16.0)?;
    commands.submit(&submit.waits, &[submit.signal])?;
    streamer.wait_for_frame(0)?;
    refused(streamer.wait_for_frame(1).map(|_| ()), "frame 1")?;
    // A frame ended without its uploads is refused (its bound cycle would never be copied).
    let frame = other.begin_frame().err();
    ensure!(frame.is_some(), "the other streamer's frame 0 was never ended");
    let mut third = new_streamer()?;
    let frame = third.begin_frame()?;
    refused(third.end_frame(frame, 16.0).map(|_| ()), "record_uploads")?;
    commands.wait()?;
    assert_clean_after_dropping(&device, (streamer, other, third))
}

/// [`stream_fixed_view`] of the row of quads, one texture each ([`row_source`]).
fn stream_row_fixed_view(
    device: &Arc<Device>,
    config: StreamConfig,
    frames: u32,
    host_records: Option<Vec<MeshMetaData>>,
) -> Result<TextureStreamer<MemorySource>> {
    let (_, _, meshes) = quad_row();
    stream_fixed_view(device, row_source(), meshes, config, frames, host_records)
}

/// Streams `frames` frames of a fixed view of the row's first quads
/// (texture 0 among them; the rest of the row is off screen) with the
/// baseline policy, then waits for the device and returns the streamer.
/// With `host_records`, every frame hands the loader those instead of
/// feedback, and no feedback pass runs.
fn stream_fixed_view(
    device: &Arc<Device>,
    source: MemorySource,
    meshes: Vec<CityMesh>,
    config: StreamConfig,
    frames: u32,
    host_records: Option<Vec<MeshMetaData>>,
) -> Result<TextureStreamer<MemorySource>> {
    let (vertices, indices, _) = quad_row();
    let view = FeedbackView::default();
    let target = RenderTarget::new(device, WIDTH, HEIGHT)?;
    let feedback_target = RenderTarget::new(device, WIDTH / 4, HEIGHT / 4)?;
    let mut streamer = TextureStreamer::new(
        device,
        source,
        meshes.iter().map(|m| m.texture).collect(),
        &vec![[90, 90, 90, 255]; QUADS as usize],
        PolicyKind::Baseline.build(&PolicyOptions::default())?,
        &StreamConfig {
            layer_size: TEXTURE,
            staging_bytes: 1 << 20,
            fragment_area: view.fragment_area(HEIGHT, feedback_target.height()),
            deterministic: true,
            ..config
        },
    )?;
    let mut setup = CommandContext::new(device, "fixed view setup")?;
    let renderer = CityRenderer::new(
        device,
        &mut setup,
        &vertices,
        &indices,
        meshes,
        streamer.cache(),
        streamer.compactor(),
    )?;
    let mut frame_commands = (0..2)
        .map(|i| CommandContext::new(device, &format!("fixed view frame {i}")))
        .collect::<std::result::Result<Vec<_>, _>>()?;
    let camera = Camera {
        eye: glam::DVec3::new(15.0, 5.0, 14.0),
        target: glam::DVec3::new(15.0, 5.0, 0.0),
        fov_y: 60f32.to_radians(),
        near: 0.1,
    };
    for _ in 0..frames {
        if let Some(records) = &host_records {
            streamer.set_host_records(records.clone())?;
        }
        let mut begun = streamer.begin_frame()?;
        let commands = &mut frame_commands[begun.slot() as usize];
        let rec = commands.begin_completed()?;
        streamer.record_uploads(&mut begun, rec)?;
        if host_records.is_none() {
            renderer.record_feedback(rec, &feedback_target, &camera, &view, HEIGHT)?;
            streamer.record_feedback_resolve(&mut begun, rec)?;
        }
        renderer.record_visible(rec, &target, &camera, 1.0, true)?;
        let submit = streamer.end_frame(begun, 16.0)?;
        commands.submit_frame(&submit.waits, &[submit.signal])?;
    }
    device.wait_idle()?;
    Ok(streamer)
}

#[test]
fn a_texture_the_cache_cannot_hold_fails_once_instead_of_reloading() -> Result<()> {
    let device = sync_validated_device()?;
    // Texture 0 is twice the layer size; the others fit.
    let mut source = MemorySource::new();
    source.push_bc1(2 * TEXTURE, 2 * TEXTURE);
    for _ in 1..QUADS {
        source.push_bc1(TEXTURE, TEXTURE);
    }
    let (_, _, mut meshes) = quad_row();
    meshes[0].texture_width = 2 * TEXTURE;
    meshes[0].texture_height = 2 * TEXTURE;
    let config = StreamConfig {
        memory_budget_bytes: 64 << 20,
        weight_cutoff: 1,
        ..StreamConfig::default()
    };
    let streamer = stream_fixed_view(&device, source, meshes, config, 30, None)?;
    let failures = streamer.load_failures();
    ensure!(
        streamer.failed_textures() == 1 && streamer.totals().failed == 1,
        "{} textures failed, {} failures: {failures:?}",
        streamer.failed_textures(),
        streamer.totals().failed
    );
    ensure!(
        failures[0].texture == 0 && failures[0].reason.contains("larger than the layer size"),
        "{failures:?}"
    );
    // The others streamed as usual.
    let resident: Vec<u32> = (0..4).map(|t| streamer.cache().resident_levels(t)).collect();
    ensure!(
        resident[0] == 0 && resident[1] != 0 && resident[2] != 0,
        "the textures beside it were not streamed: resident levels {resident:?}, totals {:?}",
        streamer.totals()
    );
    assert_clean_after_dropping(&device, streamer)
}

/// Texture arrays spend the memory budget on whole layers when the streamer is made
/// (`StreamConfig::memory_budget_bytes`, docs/EMBEDDING.md "Memory budget"): a budget
/// below one layer's full mip chain is refused naming it, one that holds a layer is not.
#[test]
fn texture_arrays_refuse_a_budget_below_one_layer_s_full_chain() -> Result<()> {
    let device = citystream_tests::validated_array_device()?;
    // A 2048² BC1 layer with its levels down to 1×1, before the device's alignment.
    let chain: u64 = (0..12).map(|level| bc1_mip_len(2048 >> level, 2048 >> level)).sum();
    let new_streamer = |budget: u64| {
        let config = StreamConfig {
            layer_size: 2048,
            memory_budget_bytes: budget,
            staging_bytes: 1 << 16,
            ..StreamConfig::default()
        };
        one_texture_streamer(&device, 256, &config)
    };
    match new_streamer(chain - 1) {
        Err(citystream_engine::EngineError::InvalidRequest(message)) if message.contains("full mip chain") => {}
        other => anyhow::bail!("a budget one byte below a layer's chain gave {other:?}"),
    }
    // A layer and room for the device's rounding.
    drop(new_streamer(chain + (1 << 20)).context("a budget holding one layer")?);
    assert_no_validation_errors(&device)
}

/// Meshes lighter than τ are not loaded (the paper's cutoff), but the view
/// still shows them: view-serving eviction must count their textures as in
/// view, not as out of view and first to drop.
#[test]
fn textures_seen_below_the_weight_cutoff_are_in_view_but_not_loaded() -> Result<()> {
    let device = sync_validated_device()?;
    let config = StreamConfig {
        eviction: Eviction::View,
        memory_budget_bytes: 64 << 20,
        // No mesh of this view weighs this much.
        weight_cutoff: 1 << 30,
        ..StreamConfig::default()
    };
    let streamer = stream_row_fixed_view(&device, config, 8, None)?;
    let in_view: Vec<u32> = (0..QUADS).filter(|&t| streamer.needs().in_view(t)).collect();
    ensure!(
        in_view.len() >= 2 && in_view.iter().all(|&t| t < 3),
        "textures counted in view: {in_view:?} (quads 0 to 2 are on screen)"
    );
    let entries = streamer.latest_feedback().map(|(_, e)| e.len()).unwrap_or(0);
    ensure!(
        streamer.totals().loaded_mips == 0,
        "{} mips loaded although no mesh reaches τ ({entries} entries read back)",
        streamer.totals().loaded_mips
    );
    assert_clean_after_dropping(&device, streamer)
}

/// Deterministic means it: a cycle's reads are not cut by the loader's wall-clock limit
/// (a limit of zero would defer every read on any machine), so what loads depends on the
/// inputs alone.
#[test]
fn a_deterministic_stream_ignores_the_wall_clock_load_time() -> Result<()> {
    let device = sync_validated_device()?;
    let config = StreamConfig {
        memory_budget_bytes: 64 << 20,
        loader: LoaderOptions {
            load_time: Duration::ZERO,
            ..LoaderOptions::default()
        },
        ..StreamConfig::default()
    };
    let streamer = stream_row_fixed_view(&device, config, 8, None)?;
    let totals = streamer.totals();
    ensure!(
        totals.loaded_mips > 0 && totals.deferred_by_time == 0,
        "{} mips loaded, {} deferred for time in a deterministic run",
        totals.loaded_mips,
        totals.deferred_by_time
    );
    assert_clean_after_dropping(&device, streamer)
}

/// A host that knows what the view needs another way (the texture-atlas tree's paging)
/// hands the loader its own records: they replace the feedback, whatever the view shows.
#[test]
fn host_records_replace_the_feedback() -> Result<()> {
    let device = sync_validated_device()?;
    let config = StreamConfig {
        memory_budget_bytes: 64 << 20,
        weight_cutoff: 1,
        ..StreamConfig::default()
    };
    // The last quad is far off screen; quads 0 to 2 are on it.
    let off_screen = QUADS - 1;
    let records = vec![MeshMetaData {
        mip_level: 0,
        weight: 1000,
        mesh_id: off_screen,
    }];
    let mut streamer = stream_row_fixed_view(&device, config, 30, Some(records))?;
    let full = (1u32 << (TEXTURE.trailing_zeros() + 1)) - 1;
    let resident: Vec<u32> = (0..QUADS).map(|t| streamer.cache().resident_levels(t)).collect();
    ensure!(
        resident[off_screen as usize] & 1 == 1,
        "the host's texture did not reach level 0: resident levels {:b}",
        resident[off_screen as usize]
    );
    ensure!(
        resident[..off_screen as usize].iter().all(|&r| r == 0),
        "textures the host did not ask for were loaded: {resident:?} (all levels: {full:b})"
    );
    let error = streamer
        .set_host_records(vec![MeshMetaData {
            mip_level: 0,
            weight: 1000,
            mesh_id: QUADS,
        }])
        .expect_err("a mesh id outside the table");
    ensure!(error.to_string().contains("mesh 24"), "{error}");
    assert_clean_after_dropping(&device, streamer)
}
