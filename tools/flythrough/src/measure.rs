//! Measurements against the fully resident reference: the reference's own loading, the
//! error split by cause, and the draws a renderer binding one texture per draw would issue.

use anyhow::Result;
use citystream_dataset::Aabb;

use citystream_bench::image_error::ErrorCauses;
use citystream_engine::city::{texture_of_id_pixel, Camera, CityMesh, FeedbackView};
use citystream_engine::commands::CommandContext;
use citystream_engine::gpu_types::{FeedbackEntry, FEEDBACK_MIP_ONE};
use citystream_engine::stream::TextureStreamer;
use citystream_engine::target::RenderTarget;
use citystream_streaming::atlas_tree::{frustum_planes, intersects_frustum};
use citystream_streaming::shortfall::ShortfallCause;
use citystream_streaming::source::MipSource;

use super::args::FIXED_STEP_MS;
use super::city_gpu::{CityGpu, CityTargets};
use super::passes::{self, Compaction};

/// Loads, into the reference streamer, every level from the one each seen
/// mesh needs up to its coarsest, with no budget or load size; returns how
/// many textures the reference cache had to evict (0 for a faithful reference).
/// Where `shown` (the streamed run's streamer) shows a seen texture finer than its
/// meshes ask for (a level loaded for an earlier view, or prefetched), the reference
/// holds that level too: a streamed frame is never sharper than its reference, so the
/// error counts only what streaming leaves coarser.
pub(crate) fn load_reference<S: MipSource + 'static>(
    reference: &mut CityGpu,
    commands: &mut CommandContext,
    entries: &[FeedbackEntry],
    meshes: &[CityMesh],
    shown: Option<&TextureStreamer<S>>,
) -> Result<u32> {
    let shown_level = |texture: u32| shown.and_then(|s| s.shown_level(texture));
    let needed = reference_levels(entries, meshes, shown_level);
    let evicted = reference.streamer.load_now(&needed, commands)?;
    Ok(evicted.len() as u32)
}

/// Per texture of the seen meshes (`entries`), the finest level the reference loads: the
/// finest any of its meshes asks for, or the finest `shown` says the streamed frame shows
/// if that is finer. In texture order.
fn reference_levels(
    entries: &[FeedbackEntry],
    meshes: &[CityMesh],
    shown: impl Fn(u32) -> Option<u32>,
) -> Vec<(u32, u32)> {
    let mut needed: Vec<(u32, u32)> = entries
        .iter()
        .filter_map(|e| {
            meshes.get(e.mesh_id as usize).map(|m| {
                let asked = e.mip / FEEDBACK_MIP_ONE as u32;
                (m.texture, shown(m.texture).map_or(asked, |level| asked.min(level)))
            })
        })
        .collect();
    needed.sort_unstable();
    needed.dedup_by_key(|(t, _)| *t);
    needed
}

/// Draws of the feedback strategy's frame as a renderer binding one texture per draw
/// issues them: one per mesh in view. Counted every frame on the host, so meshes are
/// grouped into runs of consecutive ones (neighbours in a city's mesh order) whose boxes
/// are tested first: a frame tests the runs plus the meshes of the runs in view, not
/// every mesh (7.7 M on the Berlin-sized city).
pub(crate) struct MeshesInView {
    /// Per run of [`MeshesInView::RUN`] meshes: the union of its drawable meshes' boxes
    /// (`None`: none is drawable).
    runs: Vec<Option<Aabb>>,
}

impl MeshesInView {
    const RUN: usize = 64;

    pub(crate) fn new(scene: &citystream_dataset::Scene) -> Self {
        let runs = scene
            .meshes
            .chunks(Self::RUN)
            .map(|run| {
                run.iter()
                    .filter(|m| m.index_count > 0)
                    .fold(None, |union: Option<Aabb>, m| {
                        let mut b = union.unwrap_or(m.bounds);
                        b.union(&m.bounds);
                        Some(b)
                    })
            })
            .collect();
        Self { runs }
    }

    /// The meshes of `scene` (the one given to `new`) whose boxes meet the frustum.
    pub(crate) fn count(&self, scene: &citystream_dataset::Scene, camera: &Camera, width: u32, height: u32) -> u32 {
        let mut count = 0;
        self.for_each(scene, camera, width, height, |_| count += 1);
        count
    }

    /// Draws of Trapp and Döllner's Alg. 2 for the view: every array is bound once and
    /// each output batch of Alg. 1 drawn, a batch holding the meshes of up to
    /// `arrays_per_batch` arrays (their a_max; the batch's primitives uncapped). So one
    /// draw per `arrays_per_batch` arrays holding a texture of a mesh in view, at least
    /// one when a mesh is in view; `image_of` tells a texture's array (`None`: not
    /// resident, drawn with its colormap colour in any batch).
    pub(crate) fn array_batches(
        &self,
        scene: &citystream_dataset::Scene,
        camera: &Camera,
        (width, height): (u32, u32),
        arrays_per_batch: u32,
        image_of: impl Fn(u32) -> Option<u32>,
    ) -> u32 {
        let mut arrays = 0u64;
        let mut any = false;
        self.for_each(scene, camera, width, height, |mesh| {
            any = true;
            if let Some(image) = image_of(mesh.texture) {
                arrays |= 1 << image.min(63);
            }
        });
        arrays
            .count_ones()
            .div_ceil(arrays_per_batch.max(1))
            .max(u32::from(any))
    }

    /// Calls `visit` with each drawable mesh whose box meets the frustum.
    fn for_each(
        &self,
        scene: &citystream_dataset::Scene,
        camera: &Camera,
        width: u32,
        height: u32,
        mut visit: impl FnMut(&citystream_dataset::Mesh),
    ) {
        let planes = frustum_planes(
            camera
                .view_projection(width as f32 / height as f32, 0.0)
                .to_cols_array_2d(),
        );
        // A box inside another meets the frustum only if the outer one does.
        let runs = self
            .runs
            .iter()
            .zip(scene.meshes.chunks(Self::RUN))
            .filter(|(union, _)| union.is_some_and(|b| intersects_frustum(&b, &planes)));
        for (_, run) in runs {
            for mesh in run {
                if mesh.index_count > 0 && intersects_frustum(&mesh.bounds, &planes) {
                    visit(mesh);
                }
            }
        }
    }
}

/// A measured frame's MSE (`image` against `reference_image`, the reference's view just
/// drawn into `target`) split by cause: the reference draws which texture each pixel shows,
/// and each texture's state in `streamer` names the cause its pixels carry
/// ([`ShortfallCause`]). Pixels no city mesh covers carry the lag (they differ only where
/// the two views' culling did).
pub(crate) fn error_causes<S: MipSource + 'static>(
    commands: &mut CommandContext,
    reference: &CityGpu,
    streamer: &TextureStreamer<S>,
    (target, camera): (&RenderTarget, &Camera),
    (image, reference_image): (&image::RgbaImage, &image::RgbaImage),
) -> Result<ErrorCauses> {
    let rec = commands.begin()?;
    reference.renderer.record_texture_ids(rec, target, camera)?;
    commands.submit_and_wait(&[])?;
    let ids = target.read_pixels()?;
    let mut known: std::collections::HashMap<u32, ShortfallCause> = std::collections::HashMap::new();
    Ok(ErrorCauses::of_images(image, reference_image, |x, y| {
        let Some(texture) = texture_of_id_pixel(ids.get_pixel(x, y).0) else {
            return ShortfallCause::Lag;
        };
        *known.entry(texture).or_insert_with(|| {
            streamer
                .shortfall(texture)
                .map_or(ShortfallCause::Lag, |state| state.cause())
        })
    }))
}

/// The feedback entries of the fully resident reference's own feedback pass for `camera`,
/// every seen mesh's: what the reference must load where the run has no feedback of its
/// own (the atlas-tree strategy). Its loader is handed no records, so only `load_now` fills it.
pub(crate) fn reference_feedback(
    reference: &mut CityGpu,
    commands: &mut CommandContext,
    targets: &CityTargets,
    camera: &Camera,
    visible_height: u32,
) -> Result<Vec<FeedbackEntry>> {
    reference.streamer.set_host_records(Vec::new())?;
    let index = feedback_frame_now(
        reference,
        commands,
        (&targets.feedback_target, &targets.view),
        camera,
        visible_height,
        Compaction::Tau(0),
    )?;
    feedback_reaching(&reference.streamer, index, 0)
}

/// Runs one streamer frame of feedback for `camera` (uploads, feedback pass, compaction
/// with `compaction`) and waits for it; returns the frame's index, whose feedback is then
/// readable.
///
/// Not a [`super::flight::Flight`] frame: a flight is the run's streamer (its policy, budget,
/// frames in flight, ground and strategy) and never waits for its frames, where this is a
/// streamer of references that load explicitly, waited for. Its passes are recorded by the
/// functions the flight records them with ([`passes::record_feedback`]).
pub(crate) fn feedback_frame_now(
    gpu: &mut CityGpu,
    commands: &mut CommandContext,
    feedback_view: (&RenderTarget, &FeedbackView),
    camera: &Camera,
    visible_height: u32,
    compaction: Compaction,
) -> Result<u64> {
    let mut frame = gpu.streamer.begin_frame()?;
    let index = frame.index();
    let rec = commands.begin()?;
    gpu.streamer.record_uploads(&mut frame, rec)?;
    passes::record_feedback(
        gpu,
        &mut frame,
        rec,
        feedback_view,
        camera,
        visible_height,
        Some(compaction),
        None,
    )?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    #[test]
    fn the_reference_holds_what_the_view_asks_and_what_the_stream_shows() {
        let mesh = |texture| CityMesh {
            first_index: 0,
            index_count: 3,
            vertex_offset: 0,
            texture,
            texture_width: 256,
            texture_height: 256,
            origin: glam::DVec3::ZERO,
        };
        let meshes = [mesh(0), mesh(0), mesh(1), mesh(2)];
        let entry = |mesh_id, level: u32| FeedbackEntry {
            mip: level * FEEDBACK_MIP_ONE as u32 + FEEDBACK_MIP_ONE as u32 / 2,
            weight: 1,
            mesh_id,
        };
        // Texture 0: its meshes ask for 3 and 5; the stream shows 4: the finest asked, 3.
        // Texture 1: asks for 6, the stream shows 2 (an earlier view's, or prefetched): 2.
        // Texture 2: asks for 1, nothing shown: 1. A mesh outside the city is skipped.
        let entries = [entry(1, 5), entry(0, 3), entry(2, 6), entry(3, 1), entry(9, 0)];
        let shown = |texture: u32| match texture {
            0 => Some(4),
            1 => Some(2),
            _ => None,
        };
        assert_eq!(reference_levels(&entries, &meshes, shown), vec![(0, 3), (1, 2), (2, 1)]);
    }

    /// The run-first count equals testing every mesh, over views that see all, part and
    /// none of a grid of buildings (and a mesh without triangles, never counted).
    #[test]
    fn meshes_in_view_counts_what_testing_every_mesh_counts() {
        let mut scene = citystream_dataset::Scene::new([391_250.0, 34.0, -5_819_500.0]);
        for i in 0..1000u32 {
            let (x, z) = ((i % 40) as f32 * 12.0, (i / 40) as f32 * 12.0);
            let h = 5.0 + (i % 7) as f32 * 6.0;
            let indices: &[u32] = if i == 500 { &[] } else { &[0, 1, 2, 0, 2, 3] };
            scene
                .push_mesh(
                    i,
                    &[[x, 0.0, z], [x + 8.0, 0.0, z], [x + 8.0, h, z], [x, h, z]],
                    &[[0.0, 0.0, 1.0]; 4],
                    &[[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]],
                    indices,
                )
                .expect("mesh");
        }
        let counter = MeshesInView::new(&scene);
        let views = [
            (Vec3::new(240.0, 400.0, -200.0), Vec3::new(240.0, 0.0, 150.0)),
            (Vec3::new(10.0, 2.0, 100.0), Vec3::new(200.0, 2.0, 110.0)),
            (Vec3::new(-50.0, 30.0, -50.0), Vec3::new(-200.0, 30.0, -200.0)),
            (Vec3::new(100.0, 60.0, 300.0), Vec3::new(300.0, 0.0, 0.0)),
        ];
        let mut counts = Vec::new();
        for (eye, target) in views {
            let camera = Camera {
                eye: eye.as_dvec3(),
                target: target.as_dvec3(),
                fov_y: 1.0,
                near: 0.5,
            };
            let planes = frustum_planes(camera.view_projection(16.0 / 9.0, 0.0).to_cols_array_2d());
            let every = scene
                .meshes
                .iter()
                .filter(|m| m.index_count > 0 && intersects_frustum(&m.bounds, &planes))
                .count() as u32;
            assert_eq!(counter.count(&scene, &camera, 1600, 900), every);
            counts.push(every);
        }
        // The views see everything, part of the city, nothing.
        assert_eq!(counts[0], 999, "{counts:?}");
        assert!(counts[1] > 0 && counts[1] < 999, "{counts:?}");
        assert_eq!(counts[2], 0, "{counts:?}");
    }
}
