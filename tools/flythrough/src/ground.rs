//! `flythrough --ground PATCHES`: a patch set (`citystream patches`) draped under the city
//! through the engine's ground layer (a flexible clipmap), each patch inserted when its
//! arrival time comes; tile uploads share the controller's load size with the facades.
//! With PSNR measurements on, a second ground layer with every arrived patch resident is
//! the reference the streamed ground is measured against (both drawn alone, behind the
//! city's depth).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use citystream_bench::image_error::{ErrorSeries, FrameError};
use citystream_dataset::{Dataset, Scene};
use citystream_engine::city::{Camera, CityRenderer};
use citystream_engine::commands::CommandContext;
use citystream_engine::ground::{GroundAllowance, GroundConfig, GroundFrame, GroundLayer, GroundView};
use citystream_engine::stream::{Frame, TextureStreamer};
use citystream_engine::target::RenderTarget;
use citystream_engine::Device;
use citystream_gen::patches::PatchSet;
use citystream_streaming::clipmap::Patch;
use citystream_streaming::ground::PatchImage;
use citystream_streaming::source::MipSource;

/// One patch to insert when its time comes: where, and the PNG it is decoded from then.
struct Arrival {
    patch: Patch,
    file: PathBuf,
    arrival_s: f64,
}

/// Patch images decoded so far, each file once: shared by every patch that lists it and by
/// the streamed layer and the reference (inserting clones no texels).
#[derive(Default)]
struct DecodedImages(HashMap<PathBuf, Arc<PatchImage>>);

impl DecodedImages {
    fn get(&mut self, arrival: &Arrival) -> Result<Arc<PatchImage>> {
        if let Some(image) = self.0.get(&arrival.file) {
            return Ok(Arc::clone(image));
        }
        let (id, path) = (arrival.patch.id, arrival.file.display());
        let decoded = image::open(&arrival.file)
            .with_context(|| format!("decoding patch {id} ({path})"))?
            .to_rgba8();
        let image = PatchImage::from_rgba8(decoded.width(), decoded.height(), decoded.as_raw())
            .map_err(|e| anyhow::anyhow!("patch {id} ({path}): {e}"))?;
        let image = Arc::new(image);
        self.0.insert(arrival.file.clone(), Arc::clone(&image));
        Ok(image)
    }
}

/// Host memory a decoded `width` × `height` patch takes: RGBA8 texels and their mip chain.
fn decoded_bytes(width: u32, height: u32) -> u64 {
    u64::from(width) * u64::from(height) * 4 * 4 / 3
}

/// The ground of one flythrough.
pub struct GroundRun {
    arrivals: Vec<Arrival>,
    images: DecodedImages,
    /// Patches inserted into the streamed layer so far (arrivals are sorted).
    arrived: usize,
    /// Patches inserted into the reference so far.
    reference_arrived: usize,
    pub layer: GroundLayer,
    reference: Option<GroundLayer>,
    /// The streamed ground's error at every measured frame.
    pub errors: ErrorSeries,
}

/// Summary keys of the ground (`summary.json`).
#[derive(Debug, serde::Serialize)]
pub struct GroundSummary {
    pub patches: String,
    pub patches_arrived: usize,
    pub patches_total: usize,
    pub levels: u32,
    pub tiles_invalidated: u64,
    /// CPU wall time composing the streamed layer's tiles (rayon workers), ms in all and per tile.
    pub compose_ms: f64,
    pub compose_ms_per_tile: Option<f64>,
    pub memory_bytes: u64,
    pub tile_texels: u32,
    pub cache_side: u32,
    /// Levels the tile array holds (derived from the view, the imagery and the budget).
    pub level_slots: u32,
}

/// A patch set opened for the flown dataset: in its CRS (or both in local frames), with
/// the shift that moves the set's corners from the origin it was cut for to the dataset's.
pub struct GroundSet {
    dir: PathBuf,
    set: PatchSet,
    shift: [f64; 2],
}

impl GroundSet {
    /// Opens and checks the patch set in `dir` for `dataset`.
    pub fn open(dir: &Path, dataset: &Dataset) -> Result<Self> {
        let scene = &dataset.scene;
        let set = PatchSet::open(dir)?;
        if set.patches.is_empty() {
            bail!("{}: the patch set has no patches", dir.display());
        }
        set.check_frame(dir, dataset.dir(), scene)?;
        // The set's corners are relative to the origin of the dataset it was cut for; the
        // flown dataset's origin may differ (another write of the same city, say).
        let shift = [set.origin[0] - scene.origin[0], set.origin[2] - scene.origin[2]];
        if !shift.iter().all(|s| s.is_finite()) {
            bail!("{}: origin {:?} is not finite", dir.display(), set.origin);
        }
        Ok(Self {
            dir: dir.to_path_buf(),
            set,
            shift,
        })
    }

    /// The larger side of the ground its patches cover, metres.
    fn extent_m(&self) -> f64 {
        let patches = &self.set.patches;
        let side = |d: usize| {
            let lo = patches.iter().map(|p| p.min[d]).fold(f64::INFINITY, f64::min);
            let hi = patches.iter().map(|p| p.max[d]).fold(f64::NEG_INFINITY, f64::max);
            hi - lo
        };
        side(0).max(side(1))
    }

    /// Ground size of its finest and coarsest texels, metres.
    fn texel_range_m(&self) -> (f64, f64) {
        let texels = self.set.patches.iter().map(|p| p.metres_per_texel);
        (
            texels.clone().fold(f64::INFINITY, f64::min),
            texels.fold(f64::NEG_INFINITY, f64::max),
        )
    }
}

/// The ground layer's configuration for a flythrough over `scene` with `set`: tiles of 256
/// texels at the scene's lowest point; the window's side from the view's focal length
/// (`focal_px`), the levels from the set's extent down to the footprint below the path's
/// lowest eye (`min_eye_height_m` above the ground) or the set's finest imagery, fitted in
/// half the memory budget (`budget`; the facades keep the other half, as the ground earns at
/// most half the load size) and the device's array layers.
///
/// Also returns the reference's configuration: every level of the imagery down to its
/// finest texels and no budget, so that the ground's error counts what the derived levels
/// and the budget leave out, not only what is still streaming.
pub fn ground_config(
    set: &GroundSet,
    scene: &Scene,
    frames_in_flight: u32,
    focal_px: f64,
    min_eye_height_m: f64,
    budget: Option<u64>,
    device: &Device,
) -> Result<(GroundConfig, GroundConfig)> {
    let (finest_imagery_m, coarsest_imagery_m) = set.texel_range_m();
    let view = GroundView {
        focal_px,
        min_eye_height_m,
        extent_m: set.extent_m(),
        finest_imagery_m,
        coarsest_imagery_m,
    };
    let layers = device.properties().limits.max_image_array_layers;
    let base = GroundConfig {
        frames_in_flight,
        ground_height: scene.bounds.min[1],
        ..GroundConfig::default()
    };
    let every_level = GroundView {
        min_eye_height_m: f64::MIN_POSITIVE,
        ..view
    };
    let reference = GroundConfig {
        frames_in_flight: 1,
        staging_tiles: 64,
        ..base.clone()
    }
    .sized_for(&every_level, None, layers)
    .context("sizing the ground's reference layer")?;
    let config = base
        .sized_for(&view, budget.map(|b| b / 2), layers)
        .with_context(|| match budget {
            Some(b) => format!(
                "sizing the ground layer for {} in half the {} MB memory budget",
                set.dir.display(),
                b >> 20
            ),
            None => format!("sizing the ground layer for {}", set.dir.display()),
        })?;
    eprintln!(
        "ground: {} level slots of {}² tiles ({:.1} MB) for a {:.0} px focal length, eye down to {:.1} m, {:.0} m of imagery down to {:.3} m/texel",
        config.level_slots,
        config.cache_side,
        config.memory_bytes() as f64 / f64::from(1 << 20),
        focal_px,
        min_eye_height_m,
        view.extent_m,
        view.finest_imagery_m
    );
    Ok((config, reference))
}

impl GroundRun {
    /// Builds the streamed layer for `set`, and a reference layer of `reference` (the second
    /// of [`ground_config`]) where given; patches are moved from the set's origin into the
    /// dataset's. Patches are decoded when they arrive, each image file once; the images of
    /// the whole set must fit `memory_bytes` of host memory (the run's memory budget), or the
    /// set is refused before the flight, naming what it would take.
    pub fn new(
        device: &Arc<Device>,
        ground: GroundSet,
        config: GroundConfig,
        reference: Option<GroundConfig>,
        memory_bytes: Option<u64>,
    ) -> Result<Self> {
        let GroundSet { dir, set, shift } = ground;
        let dir = dir.as_path();
        let mut files: HashMap<&str, u64> = HashMap::new();
        for record in &set.patches {
            files.insert(&record.file, decoded_bytes(record.width, record.height));
        }
        let imagery_bytes: u64 = files.values().sum();
        if let Some(limit) = memory_bytes.filter(|&limit| imagery_bytes > limit) {
            bail!(
                "{}: its {} patches ({} image files) decode to {:.0} MB of imagery, more than the {:.0} MB memory \
                 budget (--memory-budget-mb): use fewer or smaller patches, or a larger budget",
                dir.display(),
                set.patches.len(),
                files.len(),
                imagery_bytes as f64 / f64::from(1 << 20),
                limit as f64 / f64::from(1 << 20)
            );
        }
        eprintln!(
            "ground: {} patches from {} ({} image files, {:.0} MB decoded as they arrive)",
            set.patches.len(),
            dir.display(),
            files.len(),
            imagery_bytes as f64 / f64::from(1 << 20)
        );
        let mut arrivals = Vec::with_capacity(set.patches.len());
        for record in &set.patches {
            arrivals.push(Arrival {
                patch: Patch {
                    id: record.id,
                    min: [record.min[0] + shift[0], record.min[1] + shift[1]],
                    max: [record.max[0] + shift[0], record.max[1] + shift[1]],
                    metres_per_texel: record.metres_per_texel,
                    captured_s: record.arrival_s,
                },
                file: dir.join(&record.file),
                arrival_s: record.arrival_s,
            });
        }
        arrivals.sort_by(|a, b| a.arrival_s.total_cmp(&b.arrival_s).then(a.patch.id.cmp(&b.patch.id)));
        let reference = reference.map(|config| GroundLayer::new(device, config)).transpose()?;
        Ok(Self {
            arrivals,
            images: DecodedImages::default(),
            arrived: 0,
            reference_arrived: 0,
            layer: GroundLayer::new(device, config)?,
            reference,
            errors: ErrorSeries::new(),
        })
    }

    /// Inserts the patches whose arrival time is `time_s` or earlier; then recentres on the
    /// eye and stages what `streamer`'s load size pays for into `frame`'s slot (charged to
    /// the streamer's next loading cycles).
    pub fn update<S: MipSource + 'static>(
        &mut self,
        time_s: f64,
        streamer: &mut TextureStreamer<S>,
        frame: &Frame,
        camera: &Camera,
    ) -> Result<GroundFrame> {
        while let Some(next) = self.arrivals.get(self.arrived).filter(|a| a.arrival_s <= time_s) {
            let image = self.images.get(next)?;
            self.layer
                .insert(next.patch, image)
                .with_context(|| format!("inserting patch {}", next.patch.id))?;
            self.arrived += 1;
        }
        let eye = [camera.eye.x, camera.eye.z];
        Ok(self.layer.update_streamed(streamer, frame, eye)?)
    }

    /// Error of the streamed ground of frame slot `slot` (its frame complete, at `path_s`
    /// seconds of path time) against the reference with every arrived patch resident, both
    /// drawn alone behind the city.
    pub fn measure(
        &mut self,
        commands: &mut CommandContext,
        city: &CityRenderer,
        target: &RenderTarget,
        camera: &Camera,
        slot: u32,
        path_s: f64,
    ) -> Result<Option<FrameError>> {
        let Some(reference) = self.reference.as_mut() else {
            return Ok(None);
        };
        if self.arrived == 0 {
            return Ok(None);
        }
        let cmd = commands.begin()?;
        city.record_ground_only(cmd, target, camera, (&self.layer, slot))?;
        commands.submit_and_wait(&[])?;
        let streamed = target.read_pixels()?;
        while self.reference_arrived < self.arrived {
            let next = &self.arrivals[self.reference_arrived];
            reference.insert(next.patch, self.images.get(next)?)?;
            self.reference_arrived += 1;
        }
        let eye = [camera.eye.x, camera.eye.z];
        // Every tile of every window: a bounded number of batches of the staging's size.
        let batches = reference.config().layers() / u64::from(reference.config().staging_tiles) + 2;
        for _ in 0..batches {
            let frame = reference.update(0, eye, GroundAllowance::Everything)?;
            let cmd = commands.begin()?;
            reference.record_uploads(cmd, 0)?;
            commands.submit_and_wait(&[])?;
            if frame.pending == 0 {
                break;
            }
        }
        let cmd = commands.begin()?;
        city.record_ground_only(cmd, target, camera, (reference, 0))?;
        commands.submit_and_wait(&[])?;
        let error = FrameError::of_images(&streamed, &target.read_pixels()?);
        self.errors.push(path_s, error);
        Ok(Some(error))
    }

    /// What `summary.json` says of the ground besides the headline keys.
    pub fn summary(&self, dir: &Path) -> GroundSummary {
        let config = self.layer.config();
        let totals = self.layer.totals();
        GroundSummary {
            patches: dir.display().to_string(),
            patches_arrived: self.arrived,
            patches_total: self.arrivals.len(),
            levels: self.layer.imagery().clipmap().level_count(),
            tiles_invalidated: totals.tiles_invalidated,
            compose_ms: totals.compose_micros as f64 / 1000.0,
            compose_ms_per_tile: (totals.tiles_uploaded > 0)
                .then(|| totals.compose_micros as f64 / 1000.0 / totals.tiles_uploaded as f64),
            memory_bytes: config.memory_bytes(),
            tile_texels: config.tile_texels,
            cache_side: config.cache_side,
            level_slots: config.level_slots,
        }
    }
}
