//! What a run writes and shows: `frames.csv` rows, `summary.json` fields, the status line.

use std::io::Write;

use anyhow::Result;

use citystream_bench::image_error::{CauseFigures, ErrorCauses, FrameError, PrefixedErrorFigures};
use citystream_engine::city::Camera;
use citystream_gen::files::write_png;
use citystream_streaming::bench::stats::Stats;

use super::args::{frames_dir_path, Args};
use super::ground;
use super::passes::GpuPassMs;
use super::tree::TreeSummary;

#[derive(Debug, serde::Serialize)]
pub(crate) struct Run<'a> {
    pub(crate) device: String,
    pub(crate) scene: String,
    /// `feedback` or `atlas-tree`.
    pub(crate) strategy: &'a str,
    /// `--culling`: `on` or `off`.
    pub(crate) culling: &'a str,
    /// How the cache held textures: `sparse` or `texture-arrays` (`--sparse`, and the
    /// device's features).
    pub(crate) texture_backing: &'a str,
    /// `--strategy texture-arrays` with the city within the budget: what was loaded
    /// before the first frame (`mips`, `bytes`, `seconds`); null otherwise.
    pub(crate) preloaded: Option<super::preload::Preload>,
    /// Per frame: meshes the visible pass drew (with culling off, every mesh with geometry).
    pub(crate) meshes_drawn: Stats,
    /// Per frame: meshes of the city the visible pass skipped.
    pub(crate) meshes_culled: Stats,
    /// Per frame: meshes the feedback pass drew after its depth pre-pass (culling on).
    pub(crate) feedback_meshes_drawn: Option<Stats>,
    /// Per frame: meshes that passed the visible view's frustum and occlusion tests
    /// (culling on).
    pub(crate) meshes_passed: Option<Stats>,
    /// Frames whose visible pass listed more indices than a culled list holds, and so
    /// drew every mesh (culling on).
    pub(crate) cull_overflow_frames: Option<usize>,
    /// Per feedback read-back: meshes it listed (weight at least τ; τ = 0 on frames whose
    /// error is measured).
    pub(crate) meshes_seen_by_feedback: Stats,
    /// Per frame: draws of a renderer binding one texture per draw (meshes in view, a
    /// mesh having one texture; for the tree, atlases drawn plus the meshes in view of the
    /// leaves drawn with their originals); for texture arrays, Trapp and Döllner's
    /// Alg. 2 (one draw per batch of up to 8 arrays in view, the arrays the engine binds
    /// at once).
    /// citystream itself draws every mesh in one draw whatever the strategy.
    pub(crate) draw_calls: Stats,
    /// Per frame: nodes drawn (the atlas tree only).
    pub(crate) nodes_drawn: Option<Stats>,
    /// The atlas tree and its paging (the atlas-tree strategy only).
    pub(crate) atlas_tree: Option<TreeSummary>,
    pub(crate) policy: &'a str,
    pub(crate) alpha_ms: f64,
    /// `--clock modelled`: the display period a frame lasts at the least (0: uncapped),
    /// and what the controller was fed (`work` or `period`); absent with other clocks.
    pub(crate) display_period_ms: Option<f64>,
    pub(crate) controller_latency: Option<&'static str>,
    /// `--clock fixed` or `modelled`: a frame's modelled render cost (`--render-ms`);
    /// absent with the real clock.
    pub(crate) render_ms: Option<f64>,
    /// `--disk-model`: the disk the reads took modelled time on (null: none).
    pub(crate) disk_model: Option<crate::disk::DiskSummary>,
    /// Loading cycles started (with a disk model a cycle spans the frames its reads take).
    pub(crate) loading_cycles: u64,
    /// Path times (s) of the path's cuts (jumps to a new view) within the run: where the
    /// time to reach an error level after a cut is measured from.
    pub(crate) path_cuts_s: Vec<f64>,
    /// The order cycles took their mips in (`weight` or `error-per-byte`).
    pub(crate) priority: &'static str,
    /// `--prefetch` (`none`, `path`, `motion`), its lead time (s), the frames that recorded
    /// the prefetch pass, the mips it planned, and what the pass cost each modelled frame
    /// (ms; absent with the real clock).
    pub(crate) prefetch: &'static str,
    pub(crate) prefetch_lead_s: Option<f64>,
    pub(crate) prefetch_frames: u64,
    pub(crate) prefetched_mips: u64,
    pub(crate) prefetch_cost_ms: Option<f64>,
    pub(crate) mip_deficit: Option<Stats>,
    /// The facades' error against the fully resident reference: `psnr_db`,
    /// `psnr_ceiling_db`, `error_frames`, `mse`, `psnr_of_mean_mse_db` (every measured
    /// frame counts, identical ones at the ceiling; `citystream_bench::image_error`).
    #[serde(flatten)]
    pub(crate) error: PrefixedErrorFigures,
    /// The facades' mean MSE split by why each pixel was coarser than the reference's
    /// (lag, load size, bias, budget), start-up and streaming apart; each phase's parts
    /// sum to its mean MSE. `null` without measured frames.
    pub(crate) error_causes: Option<CauseFigures>,
    /// With --ground: tiles of ground imagery composed and uploaded, their MB, and the
    /// ground's error against a reference with every arrived patch resident (both drawn
    /// alone behind the city), under the same keys prefixed `ground_`.
    pub(crate) ground_tiles_uploaded: Option<u64>,
    pub(crate) ground_mb_streamed: Option<f64>,
    #[serde(flatten)]
    pub(crate) ground_error: PrefixedErrorFigures,
    pub(crate) ground: Option<ground::GroundSummary>,
    pub(crate) clock: &'a str,
    pub(crate) bind_latency: &'a str,
    pub(crate) width: u32,
    pub(crate) height: u32,
    pub(crate) duration_s: f64,
    pub(crate) wall_s: f64,
    /// Wall time per frame (ms): compare runs with 1 and 2 frames in flight.
    pub(crate) wall_ms_per_frame: f64,
    pub(crate) frames_in_flight: u32,
    /// Frames whose render thread blocked on the GPU to reuse a frame slot.
    pub(crate) cpu_wait_frames: u32,
    pub(crate) cpu_wait_ms: f64,
    /// Frames whose image was read back (PNG, PSNR): waits outside the steady state.
    pub(crate) readback_wait_frames: u32,
    pub(crate) mips_streamed: u64,
    /// Bytes of the distinct (texture, level) pairs the run uploaded, each once.
    pub(crate) unique_bytes_streamed: u64,
    pub(crate) blocks_bound: u64,
    pub(crate) peak_resident_bytes: u64,
    /// Most device memory the allocator held (geometry, cache blocks, table,
    /// targets, staging), sampled every 30 frames and at the end.
    pub(crate) peak_device_memory_bytes: u64,
    /// The budget in bytes; null when unlimited.
    pub(crate) memory_budget_bytes: Option<u64>,
    pub(crate) eviction: &'a str,
    /// Layers of each cache image, by format (BC1, RGBA8, BC3, BC7) of those the dataset has.
    pub(crate) cache_layers: Vec<u32>,
    /// Per cache format (BC1, RGBA8, BC3, BC7 of those the dataset has), its mip tail:
    /// `first_level` (null without one), `bytes_per_tail` (a layer's, or the image's when
    /// `single`), `single`, `synthetic` (forced by CITYSTREAM_FORCE_MIP_TAIL) and the
    /// tail bytes `held_bytes` at the end of the run (within `peak_resident_bytes`).
    pub(crate) cache_tails: Vec<TailSummary>,
    /// Frames in which the view needed more than the budget holds.
    pub(crate) frames_over_budget: u64,
    /// Per pause of the path: mips uploaded in its second half (a settled
    /// streamer uploads none while the camera holds still).
    pub(crate) pause_uploads_second_half: Vec<u64>,
    /// Failed reads and header errors, and the textures the loader gave up on.
    pub(crate) load_failures: u64,
    /// Failed reads that a retry then completed.
    pub(crate) read_retries: u64,
    /// Reads a cycle did not start because its load time had run out (the wall clock's, or
    /// the disk model's): 0 for the fixed and modelled clocks without a disk model, which
    /// are deterministic.
    pub(crate) deferred_by_time: u64,
    pub(crate) textures_failed: usize,
    /// Textures the error reference could not load (the same failure lifecycle: its frames
    /// show them at the levels it has); `None` without a reference.
    pub(crate) reference_textures_failed: Option<usize>,
    /// Levels dropped, layers evicted, loads refused and declined for room.
    pub(crate) dropped_levels: u64,
    pub(crate) evicted_layers: u64,
    pub(crate) refused_for_room: u64,
    pub(crate) declined_loads: u64,
    /// Side of the cache's array layers in texels.
    pub(crate) cache_layer_size: u32,
    /// GPU time of each pass per frame, from timestamps (null where the
    /// queue has none).
    pub(crate) gpu_pass_ms: Option<GpuPassMs>,
    pub(crate) validation_errors: usize,
    /// `--depth-slabs`: what the probe's pixels showed.
    pub(crate) depth_slabs: Option<super::depth_slabs::SlabCounts>,
    pub(crate) frames_written: Vec<String>,
    /// The on-disk mip cache of a remote dataset read through one (`--mip-cache`).
    pub(crate) mip_cache: Option<MipCacheSummary>,
}

/// `summary.json`'s `mip_cache`: where it lies, how big it may grow, what it did.
#[derive(Debug, serde::Serialize)]
pub(crate) struct MipCacheSummary {
    pub(crate) dir: String,
    pub(crate) capacity_bytes: u64,
    #[serde(flatten)]
    pub(crate) stats: citystream_dataset::MipCacheStats,
}

/// Writes `image` as frame `frame`'s PNG in OUT/frames/ and lists its path in `written`.
pub(crate) fn write_frame_png(
    args: &Args,
    frame: u32,
    image: &image::RgbaImage,
    written: &mut Vec<String>,
) -> Result<()> {
    let path = frames_dir_path(args).join(format!("frame_{frame:05}.png"));
    write_png(image, &path)?;
    written.push(path.display().to_string());
    Ok(())
}

/// The live one-line status: rewritten in place on a terminal, a line every
/// 30 frames otherwise (logs, CI).
pub(crate) fn status(frame: u32, frames: u32, dt: f64, s_mb: f64, b: f64, mb_s: f64, resident_mb: f64) {
    use std::io::IsTerminal;
    let line = format!(
        "frame {:>6}/{frames}  dt {dt:7.2} ms  s {s_mb:7.2} MB  b {b:4.2}  {mb_s:7.2} MB/s  resident {resident_mb:8.1} MB",
        frame + 1
    );
    if std::io::stderr().is_terminal() {
        // The path's length is known, so a bar shows how far the run is.
        const BAR: usize = 20;
        let done = (f64::from(frame + 1) / f64::from(frames.max(1)) * BAR as f64).round() as usize;
        let bar = format!("{}{}", "#".repeat(done.min(BAR)), "-".repeat(BAR - done.min(BAR)));
        eprint!("\r[{bar}] {line}");
        let _ = std::io::stderr().flush();
    } else if frame.is_multiple_of(30) || frame + 1 == frames {
        eprintln!("{line}");
    }
}

pub(crate) const CSV_HEADER: &str =
    "frame,time_s,dt_ms,tw_ms,tm_ms,tb_ms,tbl_ms,tbu_ms,load_size_mb,mip_bias,mips,bytes,\
                          blocks_bound,resident_bytes,mip_deficit,psnr_db,mse,ground_psnr_db,ground_mse,\
                          eye_x,eye_y,eye_z,look_x,look_y,look_z,cycle_started,reads_in_flight_bytes,prefetch_pass,\
                          mse_lag,mse_load,mse_bias,mse_budget";

/// One frame's line of frames.csv.
pub(crate) struct CsvRow<'a> {
    pub(crate) frame: u32,
    pub(crate) time_s: f64,
    pub(crate) frame_ms: f64,
    pub(crate) telemetry: &'a citystream_streaming::controller::Telemetry,
    pub(crate) applied: &'a citystream_engine::texture_cache::CycleReport,
    pub(crate) resident: u64,
    pub(crate) deficit: Option<f64>,
    /// The facades' and the ground's error, on measured frames.
    pub(crate) error: Option<FrameError>,
    pub(crate) ground_error: Option<FrameError>,
    pub(crate) camera: &'a Camera,
    /// A loading cycle started in this frame.
    pub(crate) cycle_started: bool,
    /// With `--disk-model`, bytes read by the cycle in flight and not yet in the cache
    /// after this frame's `begin_frame` (empty without one).
    pub(crate) reads_in_flight_bytes: Option<u64>,
    /// The frame recorded the prefetch pass (and a modelled frame paid for it).
    pub(crate) prefetch_pass: bool,
    /// The facades' MSE split by cause, on measured frames.
    pub(crate) causes: Option<ErrorCauses>,
}

pub(crate) fn write_csv_row(csv: &mut impl Write, row: &CsvRow) -> Result<()> {
    let t = row.telemetry;
    // Camera paths hold f32 poses: the f32 of the f64 eye is the pose itself.
    let (eye, look) = (row.camera.eye.as_vec3(), row.camera.target.as_vec3());
    // The pose exactly (shortest round-trip form): a replay is compared with it.
    writeln!(
        csv,
        "{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
        row.frame,
        row.time_s,
        row.frame_ms,
        t.tw_ms,
        t.tm_ms,
        t.tb_ms,
        t.tbl_ms,
        t.tbu_ms,
        t.load_size_mb,
        t.mip_bias,
        row.applied.mips_uploaded,
        row.applied.bytes_uploaded,
        row.applied.blocks_bound,
        row.resident,
        optional(row.deficit),
        // The error exactly (shortest round-trip form), so that figures recomputed from the
        // CSV equal the summary's.
        exact(row.error.map(|e| e.psnr_db)),
        exact(row.error.map(|e| e.mse)),
        exact(row.ground_error.map(|e| e.psnr_db)),
        exact(row.ground_error.map(|e| e.mse)),
        eye.x,
        eye.y,
        eye.z,
        look.x,
        look.y,
        look.z,
        u8::from(row.cycle_started),
        row.reads_in_flight_bytes.map(|b| b.to_string()).unwrap_or_default(),
        u8::from(row.prefetch_pass),
        exact(row.causes.map(|c| c.lag_mse)),
        exact(row.causes.map(|c| c.load_mse)),
        exact(row.causes.map(|c| c.bias_mse)),
        exact(row.causes.map(|c| c.budget_mse)),
    )?;
    Ok(())
}

pub(crate) fn optional(value: Option<f64>) -> String {
    value
        .filter(|v| v.is_finite())
        .map(|v| format!("{v:.4}"))
        .unwrap_or_default()
}

/// A measured value in shortest round-trip form; empty when not measured.
pub(crate) fn exact(value: Option<f64>) -> String {
    value.map(|v| v.to_string()).unwrap_or_default()
}

/// A cache format's mip tail in `summary.json`.
#[derive(Debug, serde::Serialize)]
pub(crate) struct TailSummary {
    pub(crate) format: &'static str,
    pub(crate) first_level: Option<u32>,
    pub(crate) bytes_per_tail: u64,
    pub(crate) single: bool,
    pub(crate) synthetic: bool,
    pub(crate) held_bytes: u64,
}

impl From<citystream_engine::texture_cache::FormatTail> for TailSummary {
    fn from(tail: citystream_engine::texture_cache::FormatTail) -> Self {
        TailSummary {
            format: tail.format,
            first_level: tail.first_level,
            bytes_per_tail: tail.bytes_per_tail,
            single: tail.single,
            synthetic: tail.synthetic,
            held_bytes: tail.held_bytes,
        }
    }
}
