//! Measurements against the fully resident reference: the reference's own loading, and the
//! draws a renderer binding one texture per draw would issue.

use anyhow::Result;

use citystream_engine::city::{Camera, CityMesh, FeedbackView};
use citystream_engine::commands::CommandContext;
use citystream_engine::gpu_types::{FeedbackEntry, FEEDBACK_MIP_ONE};
use citystream_engine::stream::TextureStreamer;
use citystream_engine::target::RenderTarget;
use citystream_streaming::atlas_tree::{frustum_planes, intersects_frustum};
use citystream_streaming::source::MipSource;

use super::args::FIXED_STEP_MS;
use super::flight::{CityGpu, CityTargets};

/// Loads, into the reference streamer, every level from the one each seen
/// mesh needs up to its coarsest, with no budget or load size; returns how
/// many textures the reference cache had to evict (0 for a faithful reference).
pub(crate) fn load_reference(
    reference: &mut CityGpu,
    commands: &mut CommandContext,
    entries: &[FeedbackEntry],
    meshes: &[CityMesh],
) -> Result<u32> {
    let mut needed: Vec<(u32, u32)> = entries
        .iter()
        .filter_map(|e| {
            meshes
                .get(e.mesh_id as usize)
                .map(|m| (m.texture, e.mip / FEEDBACK_MIP_ONE as u32))
        })
        .collect();
    needed.sort_unstable();
    needed.dedup_by_key(|(t, _)| *t);
    let evicted = reference.streamer.load_now(&needed, commands)?;
    Ok(evicted.len() as u32)
}

/// Draws of the feedback strategy's frame as a renderer binding one texture per draw
/// issues them: one per mesh in view.
pub(crate) fn meshes_in_view(scene: &citystream_dataset::Scene, camera: &Camera, width: u32, height: u32) -> u32 {
    let planes = frustum_planes(
        camera
            .view_projection(width as f32 / height as f32, 0.0)
            .to_cols_array_2d(),
    );
    scene
        .meshes
        .iter()
        .filter(|mesh| mesh.index_count > 0 && intersects_frustum(&mesh.bounds, &planes))
        .count() as u32
}

/// The feedback entries (reaching `tau`) of the fully resident reference's own feedback
/// pass for `camera`: what the reference must load where the run has no feedback of its
/// own (the atlas-tree strategy). Its loader is handed no records, so only `load_now` fills it.
pub(crate) fn reference_feedback(
    reference: &mut CityGpu,
    commands: &mut CommandContext,
    targets: &CityTargets,
    camera: &Camera,
    visible_height: u32,
) -> Result<Vec<FeedbackEntry>> {
    let tau = reference.streamer.gpu_tau();
    reference.streamer.set_host_records(Vec::new())?;
    let index = feedback_frame_now(
        reference,
        commands,
        (&targets.feedback_target, &targets.view),
        camera,
        visible_height,
        Some(0),
    )?;
    feedback_reaching(&reference.streamer, index, tau)
}

/// Runs one streamer frame of feedback for `camera` (uploads, feedback pass, compaction
/// with `compact_tau` or the streamer's own threshold) and waits for it; returns the
/// frame's index, whose feedback is then readable.
pub(crate) fn feedback_frame_now(
    gpu: &mut CityGpu,
    commands: &mut CommandContext,
    (feedback_target, view): (&RenderTarget, &FeedbackView),
    camera: &Camera,
    visible_height: u32,
    compact_tau: Option<u32>,
) -> Result<u64> {
    let mut frame = gpu.streamer.begin_frame()?;
    let index = frame.index();
    let rec = commands.begin()?;
    gpu.streamer.record_uploads(&mut frame, rec)?;
    gpu.renderer
        .record_feedback(rec, feedback_target, camera, view, visible_height)?;
    match compact_tau {
        Some(tau) => gpu.streamer.record_feedback_resolve_with_tau(&mut frame, rec, tau)?,
        None => gpu.streamer.record_feedback_resolve(&mut frame, rec)?,
    }
    let submit = gpu.streamer.end_frame(frame, FIXED_STEP_MS)?;
    commands.submit(&submit.waits, &[submit.signal])?;
    // The frame timeline says when the feedback is readable (a fence may
    // signal before the timeline value is visible).
    gpu.streamer.wait_for_frame(index)?;
    commands.wait()?;
    Ok(index)
}

/// The compacted feedback entries of completed frame `index` whose weight reaches `tau`.
pub(crate) fn feedback_reaching<S: MipSource + 'static>(
    streamer: &TextureStreamer<S>,
    index: u64,
    tau: u32,
) -> Result<Vec<FeedbackEntry>> {
    Ok(streamer
        .feedback_of(index)?
        .map(|f| f.entries)
        .unwrap_or_default()
        .into_iter()
        .filter(|e| e.weight >= tau)
        .collect())
}
