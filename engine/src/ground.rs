//! The ground layer: the GPU half of the flexible clipmap (Feldmann et al.) that drapes
//! growing aerial imagery under a city. The bookkeeping (patches in an R*-tree, scale-keyed
//! levels, toroidal windows, the tile map's answer, invalidation) lives in
//! [`citystream_streaming::clipmap`]; tile composition in [`citystream_streaming::ground`].
//!
//! Here: one tile array (a 2D array image, one layer per tile slot: `level slots × side²`
//! layers, a scale's level slot is `scale mod level_slots`, a tile's slot within it
//! `(z mod side, x mod side)`, so a window move overwrites exactly the layers of the tiles
//! that left); per frame slot a host-visible tile map (which tile each layer holds and
//! whether it is resident) and a staging buffer; and the ground pass, one quad over the
//! imagery's area whose fragment stage picks the level its footprint needs, or the finest
//! coarser one resident there, and blends toward the next coarser level
//! (`shaders/ground.frag`).
//!
//! Per frame, after [`crate::stream::TextureStreamer::begin_frame`] returned the frame:
//! [`GroundLayer::insert`] patches that arrived, [`GroundLayer::update_streamed`] with the
//! streamer and the eye (its tiles share the controller's load size with the facades; a
//! host without a streamer calls [`GroundLayer::update`] with an allowance of its own),
//! [`GroundLayer::record_uploads`] before the passes, and [`GroundLayer::record_draw`]
//! inside the visible pass's rendering.

use std::collections::{HashMap, HashSet};
use std::sync::Arc;

use ash::vk;
use citystream_streaming::clipmap::{ClipmapOptions, Patch, TileKey};
use citystream_streaming::ground::{GroundImagery, PatchImage};
use citystream_streaming::source::MipSource;
use glam::Mat4;
use gpu_allocator::MemoryLocation;

use crate::buffer::{Buffer, BufferDesc};
use crate::commands::Recording;
use crate::device::Device;
use crate::error::{EngineError, Result};
use crate::gpu_types::{GroundPush, GroundTileEntry, BINDING_GROUND_TILES, BINDING_GROUND_TILE_MAP};
use crate::image::{transition, Image, ImageDesc};
use crate::pipeline::{
    BindingSpec, DepthMode, DescriptorPool, DescriptorResource, Filtering, GraphicsDesc, Pipeline, Sampler,
};
use crate::shaders;
use crate::stream::{Frame, TextureStreamer};
use crate::target::{COLOR_FORMAT, DEPTH_FORMAT};

/// How a [`GroundLayer`] is built.
#[derive(Clone, Debug, PartialEq)]
pub struct GroundConfig {
    /// Texels per tile side (a power of two, 16 to 4096).
    pub tile_texels: u32,
    /// Tiles per side of each level's window around the viewer (2 to 64).
    pub cache_side: u32,
    /// Levels the tile array holds; a clipmap with more draws its coarsest this many.
    pub level_slots: u32,
    /// Tiles one update may compose and upload (each frame slot's staging buffer).
    pub staging_tiles: u32,
    /// Frames the host may have in flight (one tile map and staging buffer each).
    pub frames_in_flight: u32,
    /// Height (y) of the ground plane in the dataset's frame, metres.
    pub ground_height: f32,
    /// Depth bias toward the viewer as a fraction of the depth (reversed depth: the
    /// imagery's depth times `1 + depth_bias`, as if `distance × depth_bias` nearer), so the
    /// imagery covers the city's own ground surfaces at the same height at every distance.
    pub depth_bias: f32,
    /// Colour where no patch covers the ground (RGB, 0 to 1).
    pub fallback: [f32; 3],
}

impl Default for GroundConfig {
    fn default() -> Self {
        Self {
            tile_texels: 256,
            cache_side: 4,
            level_slots: 12,
            staging_tiles: 16,
            frames_in_flight: 2,
            ground_height: 0.0,
            depth_bias: 2e-6,
            fallback: [0.42, 0.42, 0.4],
        }
    }
}

impl GroundConfig {
    /// Bytes of one tile (RGBA8).
    pub fn tile_bytes(&self) -> u64 {
        u64::from(self.tile_texels) * u64::from(self.tile_texels) * 4
    }

    /// Layers of the tile array.
    pub fn layers(&self) -> u64 {
        u64::from(self.level_slots) * u64::from(self.cache_side) * u64::from(self.cache_side)
    }

    /// Device memory the layer allocates: the tile array and every frame slot's staging
    /// buffer (tile maps are a few kB). A host deducts it from its texture budget.
    pub fn memory_bytes(&self) -> u64 {
        (self.layers() + u64::from(self.staging_tiles) * u64::from(self.frames_in_flight.max(1))) * self.tile_bytes()
    }

    /// This configuration with `cache_side` and `level_slots` derived from `view`, then fitted
    /// to `max_bytes` (`None`: no limit) and the device's `max_array_layers` by dropping the
    /// finest levels (the layer draws the coarsest `level_slots` of the clipmap's levels, so
    /// detail goes first, coverage never).
    ///
    /// - A level of texel size `t` is the one a pixel needs out to `t · focal_px` metres from
    ///   the viewer (its footprint is `distance / focal_px` or more), and a window of
    ///   `2g + 1` tiles reaches `g` tiles beyond the viewer's own tile wherever the viewer
    ///   stands in it; so `g = ⌈focal_px / tile_texels⌉`, the side `2g + 1`.
    /// - The clipmap's coarsest level is one above the finest that groups the extent in 2 × 2
    ///   tiles (§3.4), so its tile is under 4 × the extent however the grid is aligned, or
    ///   one above the first patch's level (texels `2 · coarsest_imagery`) if coarser; the
    ///   finest any pixel needs has the footprint `f` straight below the lowest eye
    ///   (`min_eye_height / focal_px`), or the finest imagery if that is coarser, and the level
    ///   drawn there has texels between `f / 2` and `f`. Levels are powers of two apart, so
    ///   `⌈log2(2 · coarsest / f)⌉` slots hold every level from the coarsest down.
    pub fn sized_for(mut self, view: &GroundView, max_bytes: Option<u64>, max_array_layers: u32) -> Result<Self> {
        let invalid = |what: String| EngineError::InvalidRequest(format!("ground layer: {what}"));
        let finite_positive = |v: f64| v.is_finite() && v > 0.0;
        if !(finite_positive(view.focal_px)
            && finite_positive(view.min_eye_height_m)
            && finite_positive(view.extent_m)
            && finite_positive(view.finest_imagery_m)
            && finite_positive(view.coarsest_imagery_m))
        {
            return Err(invalid(format!("{view:?} needs finite, positive values")));
        }
        let tile = f64::from(self.tile_texels.max(1));
        let reach_tiles = (view.focal_px / tile).ceil().clamp(1.0, 31.0) as u32;
        self.cache_side = 2 * reach_tiles + 1;
        let coarsest_texel_bound = (4.0 * view.extent_m / tile).max(2.0 * view.coarsest_imagery_m);
        let footprint = (view.min_eye_height_m / view.focal_px).max(view.finest_imagery_m);
        let slots = (2.0 * coarsest_texel_bound / footprint).log2().ceil().clamp(1.0, 64.0);
        self.level_slots = slots as u32;
        let side_squared = self.cache_side * self.cache_side;
        let level_bytes = u64::from(side_squared) * self.tile_bytes();
        let staging_bytes = self.memory_bytes() - self.layers() * self.tile_bytes();
        let by_memory = max_bytes.map_or(u64::MAX, |max| max.saturating_sub(staging_bytes) / level_bytes);
        let by_layers = u64::from(max_array_layers / side_squared);
        let fitted = u64::from(self.level_slots).min(by_memory).min(by_layers);
        if fitted == 0 {
            return Err(invalid(format!(
                "not one level of {}² tiles of {} texels fits: {} MB allowed ({:.1} MB per level plus {:.1} MB of staging), {max_array_layers} array layers",
                self.cache_side,
                self.tile_texels,
                max_bytes.map_or(u64::MAX, |m| m >> 20),
                level_bytes as f64 / f64::from(1 << 20),
                staging_bytes as f64 / f64::from(1 << 20)
            )));
        }
        self.level_slots = fitted as u32;
        Ok(self)
    }
}

/// What a ground layer's capacities are derived from ([`GroundConfig::sized_for`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GroundView {
    /// Focal length in pixels: viewport height / (2 · tan(fov_y / 2)).
    pub focal_px: f64,
    /// The lowest the eye comes above the ground plane, metres.
    pub min_eye_height_m: f64,
    /// The larger side of the ground the imagery covers, metres.
    pub extent_m: f64,
    /// Ground size of the finest imagery's texels, metres.
    pub finest_imagery_m: f64,
    /// Ground size of the coarsest imagery's texels, metres (the first patch to arrive sets
    /// the clipmap's grid, whose coarsest level is at least one above it).
    pub coarsest_imagery_m: f64,
}

/// How many tiles one [`GroundLayer::update`] may compose and upload.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GroundAllowance {
    /// The controller's load size `s` (bytes per streaming cycle), shared with the facades:
    /// the ground earns half of it per frame, saved up to `max(s / 2, one tile)`, and spends
    /// it a tile at a time; the host charges what it spent to the streamer
    /// ([`crate::stream::TextureStreamer::charge_host_uploads`]).
    LoadSize(u64),
    /// Every pending tile the staging buffer holds: for references and tests.
    Everything,
}

/// Running counts of a ground layer.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct GroundTotals {
    /// Tiles composed and uploaded.
    pub tiles_uploaded: u64,
    /// Their bytes.
    pub bytes_uploaded: u64,
    /// Patches inserted.
    pub patches: u64,
    /// Resident tiles patches invalidated (composed again when their turn comes).
    pub tiles_invalidated: u64,
    /// Wall time spent composing tiles on the CPU, microseconds (not part of any modelled
    /// frame latency: a host measures it with its real clock).
    pub compose_micros: u64,
}

/// What one update did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct GroundFrame {
    /// Tiles staged for upload this frame.
    pub tiles: u32,
    /// Their bytes.
    pub bytes: u64,
    /// Tiles still waiting (entered, or invalidated, and adding detail).
    pub pending: usize,
}

struct GroundSlot {
    set: vk::DescriptorSet,
    tile_map: Buffer,
    staging: Buffer,
    /// Layers this slot's staging fills, in staging order.
    staged: Vec<u32>,
}

/// The ground layer: imagery, tile array, tile maps and the ground pass.
pub struct GroundLayer {
    device: Arc<Device>,
    imagery: GroundImagery,
    config: GroundConfig,
    tiles: Image,
    _sampler: Sampler,
    pipeline: Pipeline,
    _pool: DescriptorPool,
    slots: Vec<GroundSlot>,
    /// In-window tiles to compose: entered their window, or a patch arrived over them.
    pending: HashSet<TileKey>,
    credit: u64,
    totals: GroundTotals,
    /// The tile array has left `UNDEFINED`.
    initialised: bool,
    entries: Vec<GroundTileEntry>,
}

debug_fields!(GroundLayer { imagery, config, pending = |s| s.pending.len(), totals });

impl Drop for GroundLayer {
    fn drop(&mut self) {
        // The array, tile maps and staging may still be read by submitted frames; the
        // host's frame loop does not tell this layer when they completed.
        let _ = self.device.wait_idle();
    }
}

/// `a mod n` for `n > 0`, whatever the sign of `a` (as `ground.frag`'s `floor_mod`).
fn floor_mod(a: i64, n: u32) -> u32 {
    a.rem_euclid(i64::from(n)) as u32
}

const NO_TILE: GroundTileEntry = GroundTileEntry {
    x: 0,
    z: 0,
    scale: i32::MIN,
    resident: 0,
};

impl GroundLayer {
    /// An empty ground layer (levels appear with the first patch); the tile array's
    /// layers must fit the device.
    pub fn new(device: &Arc<Device>, config: GroundConfig) -> Result<Self> {
        let invalid = |what: String| EngineError::InvalidRequest(format!("ground layer: {what}"));
        let imagery = GroundImagery::new(ClipmapOptions {
            origin: [0.0, 0.0],
            tile_texels: config.tile_texels,
            cache_side: config.cache_side,
        })
        .map_err(|e| invalid(e.to_string()))?;
        if !(1..=64).contains(&config.level_slots) || config.staging_tiles == 0 || config.frames_in_flight == 0 {
            return Err(invalid(format!(
                "{} level slots (1 to 64), {} staging tiles and {} frames in flight (at least 1)",
                config.level_slots, config.staging_tiles, config.frames_in_flight
            )));
        }
        if !(config.ground_height.is_finite() && config.depth_bias.is_finite()) {
            return Err(invalid("ground height and depth bias must be finite".into()));
        }
        let limit = device.properties().limits.max_image_array_layers;
        if config.layers() > u64::from(limit) {
            return Err(invalid(format!(
                "{} level slots of {}² tiles need {} array layers; the device allows {limit}",
                config.level_slots,
                config.cache_side,
                config.layers()
            )));
        }
        if config.tile_texels > device.properties().limits.max_image_dimension2_d {
            return Err(invalid(format!(
                "tiles of {} texels exceed the device's {}",
                config.tile_texels,
                device.properties().limits.max_image_dimension2_d
            )));
        }
        let tiles = Image::new(
            device,
            ImageDesc {
                width: config.tile_texels,
                height: config.tile_texels,
                layers: config.layers() as u32,
                mips: 1,
                format: vk::Format::R8G8B8A8_UNORM,
                usage: vk::ImageUsageFlags::SAMPLED | vk::ImageUsageFlags::TRANSFER_DST,
                view_type: vk::ImageViewType::TYPE_2D_ARRAY,
            },
            "ground tiles",
        )?;
        let sampler = Sampler::new(device, Filtering::BilinearNearestLevel, "ground tile sampler")?;
        let fragment = vk::ShaderStageFlags::FRAGMENT;
        let bindings: Vec<BindingSpec> = vec![
            (
                BINDING_GROUND_TILES,
                vk::DescriptorType::COMBINED_IMAGE_SAMPLER,
                1,
                fragment,
            ),
            (BINDING_GROUND_TILE_MAP, vk::DescriptorType::STORAGE_BUFFER, 1, fragment),
        ];
        let pipeline = Pipeline::graphics(
            device,
            &GraphicsDesc {
                vertex: shaders::GROUND_VERT,
                fragment: shaders::GROUND_FRAG,
                vertex_stride: 0,
                attributes: Vec::new(),
                color_format: COLOR_FORMAT,
                depth_format: DEPTH_FORMAT,
                cull_mode: vk::CullModeFlags::NONE,
                bindings,
                push_constant_size: std::mem::size_of::<GroundPush>() as u32,
                depth: DepthMode::TestAndWrite,
                color_write: true,
            },
            "ground pipeline",
        )?;
        let pool = DescriptorPool::new(device, &pipeline, config.frames_in_flight, "ground descriptors")?;
        let host = |size: u64, usage: vk::BufferUsageFlags, name: String| {
            Buffer::new(
                device,
                BufferDesc {
                    size,
                    usage,
                    location: MemoryLocation::CpuToGpu,
                },
                &name,
            )
        };
        let mut slots = Vec::with_capacity(config.frames_in_flight as usize);
        for slot in 0..config.frames_in_flight {
            let tile_map = host(
                config.layers() * std::mem::size_of::<GroundTileEntry>() as u64,
                vk::BufferUsageFlags::STORAGE_BUFFER,
                format!("ground tile map (slot {slot})"),
            )?;
            let staging = host(
                u64::from(config.staging_tiles) * config.tile_bytes(),
                vk::BufferUsageFlags::TRANSFER_SRC,
                format!("ground staging (slot {slot})"),
            )?;
            let set = pool.allocate(
                &pipeline,
                &[
                    (
                        BINDING_GROUND_TILES,
                        DescriptorResource::SampledImage(tiles.view(), sampler.raw()),
                    ),
                    (
                        BINDING_GROUND_TILE_MAP,
                        DescriptorResource::StorageBuffer(tile_map.raw()),
                    ),
                ],
            )?;
            slots.push(GroundSlot {
                set,
                tile_map,
                staging,
                staged: Vec::new(),
            });
        }
        let mut layer = Self {
            device: Arc::clone(device),
            imagery,
            entries: vec![NO_TILE; config.layers() as usize],
            config,
            tiles,
            _sampler: sampler,
            pipeline,
            _pool: pool,
            slots,
            pending: HashSet::new(),
            credit: 0,
            totals: GroundTotals::default(),
            initialised: false,
        };
        // Every slot's tile map starts empty: nothing is drawn before a tile is resident.
        for slot in 0..layer.slots.len() {
            layer.slots[slot].tile_map.write(0, &layer.entries)?;
        }
        Ok(layer)
    }

    /// The imagery and the clipmap's bookkeeping.
    pub fn imagery(&self) -> &GroundImagery {
        &self.imagery
    }

    /// The configuration.
    pub fn config(&self) -> &GroundConfig {
        &self.config
    }

    /// Running counts.
    pub fn totals(&self) -> GroundTotals {
        self.totals
    }

    /// Tiles waiting to be composed.
    pub fn pending_tiles(&self) -> usize {
        self.pending.len()
    }

    /// Inserts a patch and its image: the clipmap grows where it must, and every tile in a
    /// window that the patch overlaps waits to be composed again (resident ones keep their
    /// old texels on screen meanwhile). Returns how many resident tiles it invalidated.
    pub fn insert(&mut self, patch: Patch, image: impl Into<Arc<PatchImage>>) -> Result<usize> {
        let insertion = self
            .imagery
            .insert(patch, image)
            .map_err(|e| EngineError::InvalidRequest(format!("ground layer: {e}")))?;
        let clipmap = self.imagery.clipmap();
        for (key, _) in clipmap.cached_tiles() {
            let (min, max) = clipmap.tile_bounds(key);
            let overlaps = (0..2).all(|d| min[d] < patch.max[d] && patch.min[d] < max[d]);
            if overlaps {
                self.pending.insert(key);
            }
        }
        self.totals.patches += 1;
        self.totals.tiles_invalidated += insertion.invalidated.len() as u64;
        Ok(insertion.invalidated.len())
    }

    /// The scales drawn: the coarsest `level_slots` of the clipmap's.
    pub fn drawn_scales(&self) -> Option<(i32, i32)> {
        let (finest, coarsest) = self.imagery.clipmap().scales()?;
        Some((finest.max(coarsest - self.config.level_slots as i32 + 1), coarsest))
    }

    fn layer_of(&self, key: TileKey) -> u32 {
        let side = self.config.cache_side;
        (floor_mod(i64::from(key.scale), self.config.level_slots) * side + floor_mod(key.z, side)) * side
            + floor_mod(key.x, side)
    }

    /// Recentres every level's window on `eye` (ground x, z), composes the most urgent
    /// pending tiles the allowance pays for into frame slot `slot`'s staging buffer
    /// (coarsest level first, so every place has imagery soon; then nearest to the eye),
    /// and writes that slot's tile map. Tiles that add no detail to their parent are not
    /// uploaded: the tile map sends fragments there to the parent. The slot's previous
    /// frame must have completed.
    pub fn update(&mut self, slot: u32, eye: [f64; 2], allowance: GroundAllowance) -> Result<GroundFrame> {
        let index = slot as usize;
        if index >= self.slots.len() {
            return Err(EngineError::InvalidRequest(format!(
                "ground layer: frame slot {slot} of {}",
                self.slots.len()
            )));
        }
        if !eye.iter().all(|c| c.is_finite()) {
            return Err(EngineError::InvalidRequest(format!(
                "ground layer: eye at {eye:?} is not finite"
            )));
        }
        self.slots[index].staged.clear();
        let entered = self.imagery.clipmap_mut().recentre(eye);
        self.pending.extend(entered);
        let tile_bytes = self.config.tile_bytes();
        let mut chosen = Vec::new();
        if let Some((finest, _)) = self.drawn_scales() {
            let window: HashMap<TileKey, bool> = self.imagery.clipmap().cached_tiles().into_iter().collect();
            self.pending
                .retain(|key| key.scale >= finest && window.contains_key(key));
            let clipmap = self.imagery.clipmap();
            let distance = |key: &TileKey| {
                let (min, max) = clipmap.tile_bounds(*key);
                (0..2).map(|d| (eye[d] - (min[d] + max[d]) / 2.0).powi(2)).sum::<f64>()
            };
            let mut order: Vec<TileKey> = self.pending.iter().copied().collect();
            order.sort_by(|a, b| {
                b.scale
                    .cmp(&a.scale)
                    .then(distance(a).total_cmp(&distance(b)))
                    .then(a.cmp(b))
            });
            if let GroundAllowance::LoadSize(load) = allowance {
                self.credit = (self.credit + load / 2).min((load / 2).max(tile_bytes));
            }
            let mut empty = Vec::new();
            for key in order {
                if !self.imagery.tile_adds_detail(key) {
                    empty.push(key);
                    continue;
                }
                if chosen.len() >= self.config.staging_tiles as usize {
                    break;
                }
                if let GroundAllowance::LoadSize(_) = allowance {
                    if self.credit < tile_bytes {
                        break;
                    }
                    self.credit -= tile_bytes;
                }
                chosen.push(key);
            }
            for key in empty {
                self.pending.remove(&key);
                self.imagery.clipmap_mut().set_resident(key, false);
            }
        }
        let staging = self.slots[index]
            .staging
            .mapped_mut()
            .ok_or_else(|| EngineError::InvalidRequest("ground staging is not host visible".into()))?;
        let started = std::time::Instant::now();
        self.imagery
            .compose_tiles(&chosen, staging)
            .map_err(|e| EngineError::InvalidRequest(format!("ground layer: {e}")))?;
        if !chosen.is_empty() {
            self.totals.compose_micros += started.elapsed().as_micros() as u64;
        }
        for &key in &chosen {
            self.pending.remove(&key);
            self.imagery.clipmap_mut().set_resident(key, true);
            let layer = self.layer_of(key);
            self.slots[index].staged.push(layer);
        }
        let bytes = chosen.len() as u64 * tile_bytes;
        self.totals.tiles_uploaded += chosen.len() as u64;
        self.totals.bytes_uploaded += bytes;
        self.write_tile_map(index)?;
        Ok(GroundFrame {
            tiles: chosen.len() as u32,
            bytes,
            pending: self.pending.len(),
        })
    }

    /// [`update`](Self::update) for a ground streamed beside a city: a second client of
    /// `streamer`'s load size. Its allowance is the controller's current load size (the
    /// layer earns half of it per frame, [`GroundAllowance::LoadSize`]) and what it stages
    /// is charged to the streamer's next loading cycles
    /// ([`TextureStreamer::charge_host_uploads`]), so that over a run everything streamed
    /// stays within the adaptive load size; the slot is `frame`'s.
    pub fn update_streamed<S: MipSource + 'static>(
        &mut self,
        streamer: &mut TextureStreamer<S>,
        frame: &Frame,
        eye: [f64; 2],
    ) -> Result<GroundFrame> {
        let load_size = streamer.decision().load_size_bytes;
        let staged = self.update(frame.slot(), eye, GroundAllowance::LoadSize(load_size))?;
        streamer.charge_host_uploads(staged.bytes);
        Ok(staged)
    }

    fn write_tile_map(&mut self, index: usize) -> Result<()> {
        self.entries.fill(NO_TILE);
        if let Some((finest, coarsest)) = self.drawn_scales() {
            for (key, resident) in self.imagery.clipmap().cached_tiles() {
                // Tile indices beyond i32 (a place ~2^31 tiles from the origin) are never
                // drawn: the shader's indices are 32-bit.
                let (Ok(x), Ok(z)) = (i32::try_from(key.x), i32::try_from(key.z)) else {
                    continue;
                };
                if resident && (finest..=coarsest).contains(&key.scale) {
                    let layer = self.layer_of(key) as usize;
                    self.entries[layer] = GroundTileEntry {
                        x,
                        z,
                        scale: key.scale,
                        resident: 1,
                    };
                }
            }
        }
        let entries = std::mem::take(&mut self.entries);
        let written = self.slots[index].tile_map.write(0, &entries);
        self.entries = entries;
        written
    }

    /// Records the copies of slot `slot`'s staged tiles into the tile array, outside any
    /// rendering and before the ground pass. Earlier frames still in flight may sample
    /// the array: the barrier before the copies orders them after those reads (same queue).
    pub fn record_uploads(&mut self, rec: Recording<'_>, slot: u32) -> Result<()> {
        let cmd = rec.raw();
        let index = slot as usize;
        let Some(ground_slot) = self.slots.get(index) else {
            return Err(EngineError::InvalidRequest(format!(
                "ground layer: frame slot {slot} of {}",
                self.slots.len()
            )));
        };
        if self.initialised && ground_slot.staged.is_empty() {
            return Ok(());
        }
        let range = self.tiles.desc().full_range();
        let sampled = (
            vk::PipelineStageFlags2::FRAGMENT_SHADER,
            vk::AccessFlags2::SHADER_SAMPLED_READ,
        );
        let copy = (vk::PipelineStageFlags2::COPY, vk::AccessFlags2::TRANSFER_WRITE);
        let from = if self.initialised {
            vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL
        } else {
            vk::ImageLayout::UNDEFINED
        };
        transition(
            &self.device,
            rec,
            self.tiles.raw(),
            range,
            from,
            vk::ImageLayout::TRANSFER_DST_OPTIMAL,
            sampled,
            copy,
        );
        let texels = self.config.tile_texels;
        let regions: Vec<vk::BufferImageCopy> = ground_slot
            .staged
            .iter()
            .enumerate()
            .map(|(i, &layer)| vk::BufferImageCopy {
                buffer_offset: i as u64 * self.config.tile_bytes(),
                buffer_row_length: 0,
                buffer_image_height: 0,
                image_subresource: vk::ImageSubresourceLayers {
                    aspect_mask: vk::ImageAspectFlags::COLOR,
                    mip_level: 0,
                    base_array_layer: layer,
                    layer_count: 1,
                },
                image_offset: vk::Offset3D::default(),
                image_extent: vk::Extent3D {
                    width: texels,
                    height: texels,
                    depth: 1,
                },
            })
            .collect();
        if !regions.is_empty() {
            // SAFETY: cmd is recording outside rendering; the staging buffer holds a tile
            // per region (written by `update`, its slot's previous frame complete) and every
            // layer lies within the array, which is in TRANSFER_DST_OPTIMAL here.
            unsafe {
                self.device.raw().cmd_copy_buffer_to_image(
                    cmd,
                    ground_slot.staging.raw(),
                    self.tiles.raw(),
                    vk::ImageLayout::TRANSFER_DST_OPTIMAL,
                    &regions,
                );
            }
        }
        transition(
            &self.device,
            rec,
            self.tiles.raw(),
            range,
            vk::ImageLayout::TRANSFER_DST_OPTIMAL,
            vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
            copy,
            sampled,
        );
        self.initialised = true;
        Ok(())
    }

    /// Records the ground pass of frame slot `slot` inside the caller's rendering (colour
    /// [`COLOR_FORMAT`], depth [`DEPTH_FORMAT`]), with `view_proj` (Vulkan clip space).
    /// Draws nothing before the first patch or before the first [`record_uploads`](Self::record_uploads).
    pub fn record_draw(&self, rec: Recording<'_>, slot: u32, view_proj: Mat4) -> Result<()> {
        let cmd = rec.raw();
        let ground_slot = self.slots.get(slot as usize).ok_or_else(|| {
            EngineError::InvalidRequest(format!("ground layer: frame slot {slot} of {}", self.slots.len()))
        })?;
        let (Some((finest, coarsest)), Some((min, max)), true) =
            (self.drawn_scales(), self.imagery.clipmap().area(), self.initialised)
        else {
            return Ok(());
        };
        let [r, g, b] = self.config.fallback;
        let push = GroundPush {
            view_proj: view_proj.to_cols_array_2d(),
            area: [min[0] as f32, min[1] as f32, max[0] as f32, max[1] as f32],
            params: [
                self.config.ground_height,
                self.imagery.clipmap().cell_metres() as f32,
                self.config.depth_bias,
                self.config.tile_texels as f32,
            ],
            levels: [
                finest,
                coarsest - finest + 1,
                self.config.cache_side as i32,
                self.config.level_slots as i32,
            ],
            fallback: [r, g, b, 1.0],
        };
        self.pipeline.bind(rec, ground_slot.set);
        self.pipeline.push(rec, &push);
        // SAFETY: cmd is recording inside rendering with this pipeline's formats; the
        // vertex stage makes its six vertices from gl_VertexIndex.
        unsafe { self.device.raw().cmd_draw(cmd, 6, 1, 0, 0) };
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MB: u64 = 1 << 20;

    fn view(focal_px: f64) -> GroundView {
        GroundView {
            focal_px,
            min_eye_height_m: 20.0,
            extent_m: 1350.0,
            finest_imagery_m: 0.01,
            coarsest_imagery_m: 2.6,
        }
    }

    #[test]
    fn clipmap_capacities_follow_the_view_resolution() {
        // 640 × 360 at 60°: focal 312 px needs two tiles of 256 beyond the viewer's; 1080p
        // (935 px) four.
        let focal = |height: f64| height / (2.0 * (30f64).to_radians().tan());
        let small = GroundConfig::default()
            .sized_for(&view(focal(360.0)), None, 2048)
            .expect("fits");
        assert_eq!(small.cache_side, 5);
        let large = GroundConfig::default()
            .sized_for(&view(focal(1080.0)), None, 2048)
            .expect("fits");
        assert_eq!(large.cache_side, 9);
        // 8 · 1350 / 256 = 42.2 m over the footprint 20 m / focal: 0.064 m at 360p (2^9.4,
        // 10 slots), 0.021 m at 1080p (2^10.9, 11 slots).
        assert_eq!((small.level_slots, large.level_slots), (10, 11));
        // Imagery no finer than 0.5 m needs no slot below it.
        let coarse = GroundConfig::default()
            .sized_for(
                &GroundView {
                    finest_imagery_m: 0.5,
                    ..view(focal(1080.0))
                },
                None,
                2048,
            )
            .expect("fits");
        assert_eq!(coarse.level_slots, 7);
        // Exactly one tile of reach where the focal length equals the tile.
        assert_eq!(
            GroundConfig::default()
                .sized_for(&view(256.0), None, 2048)
                .expect("fits")
                .cache_side,
            3
        );
    }

    /// Scales `(coarsest, wanted)` of a clipmap holding a base patch over `[lo, lo + extent]²`
    /// and a finer one inside it: the coarsest level, and the one the ground pass samples
    /// where a pixel's footprint is `footprint` metres (texels no larger, or the finest).
    fn clipmap_scales(origin: f64, lo: f64, extent: f64, base_m: f64, fine_m: f64, footprint: f64) -> (i32, i32) {
        let mut clipmap = citystream_streaming::clipmap::Clipmap::new(ClipmapOptions {
            origin: [origin, -origin],
            tile_texels: 256,
            cache_side: 5,
        })
        .expect("options");
        let patch =
            |id, min: f64, max: f64, metres_per_texel| Patch::new(id, [min, min], [max, max], metres_per_texel, 0.0);
        clipmap.insert(patch(0, lo, lo + extent, base_m)).expect("base");
        clipmap
            .insert(patch(1, lo + extent * 0.4, lo + extent * 0.5, fine_m))
            .expect("fine");
        let (finest, coarsest) = clipmap.scales().expect("levels");
        let texel = |scale| clipmap.tile_metres(scale) / 256.0;
        let wanted = (finest..=coarsest)
            .rev()
            .find(|&s| texel(s) <= footprint)
            .unwrap_or(finest);
        (coarsest, wanted)
    }

    #[test]
    fn clipmap_capacities_hold_every_level_from_the_coarsest_to_the_one_a_pixel_needs() {
        // Grids aligned anyhow, far from the origin too; eyes low and high; imagery finer and
        // coarser than the footprint.
        for origin in [0.0, 137.5, 391_250.0] {
            for (lo, extent) in [(-672.0, 1344.0), (-4032.0, 8064.0), (13.0, 700.0), (-50.0, 5000.0)] {
                for (base_m, fine_m) in [(2.625, 0.091), (15.75, 0.547), (1.0, 0.5)] {
                    for eye in [5.0, 290.0, 447.0, 3000.0] {
                        let view = GroundView {
                            focal_px: 312.0,
                            min_eye_height_m: eye,
                            extent_m: extent,
                            finest_imagery_m: fine_m,
                            coarsest_imagery_m: base_m,
                        };
                        let config = GroundConfig::default().sized_for(&view, None, 1 << 16).expect("fits");
                        let footprint = (eye / view.focal_px).max(fine_m);
                        let (coarsest, wanted) = clipmap_scales(origin, lo, extent, base_m, fine_m, footprint);
                        let needed = (coarsest - wanted + 1) as u32;
                        assert!(
                            config.level_slots >= needed,
                            "{view:?} at origin {origin}: {} slots, {needed} levels needed",
                            config.level_slots
                        );
                        // The bound spares at most the grid's worst alignment (two octaves) and
                        // the footprint's rounding (one).
                        assert!(
                            config.level_slots <= needed + 3,
                            "{view:?}: {} slots for {needed}",
                            config.level_slots
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn clipmap_capacities_fit_the_budget_and_the_device_by_dropping_fine_levels() {
        let config = GroundConfig::default();
        let unlimited = config.clone().sized_for(&view(935.0), None, 2048).expect("fits");
        assert_eq!(unlimited.level_slots, 11);
        // 81 tiles of 256 KB = 20.25 MB a level, 8 MB of staging (16 tiles, 2 frames).
        let fitted = config
            .clone()
            .sized_for(&view(935.0), Some(100 * MB), 2048)
            .expect("fits");
        assert_eq!(fitted.level_slots, 4);
        assert!(fitted.memory_bytes() <= 100 * MB, "{}", fitted.memory_bytes());
        assert_eq!(fitted.cache_side, unlimited.cache_side, "coverage is kept");
        // The device's array layers: 256 / 81 = 3 levels.
        assert_eq!(
            config
                .clone()
                .sized_for(&view(935.0), None, 256)
                .expect("fits")
                .level_slots,
            3
        );
        // Not one level: a clear error.
        let error = config
            .clone()
            .sized_for(&view(935.0), Some(20 * MB), 2048)
            .expect_err("too small");
        assert!(error.to_string().contains("not one level"), "{error}");
        for bad in [f64::NAN, 0.0, -1.0, f64::INFINITY] {
            let error = config.clone().sized_for(&view(bad), None, 2048).expect_err("refused");
            assert!(error.to_string().contains("finite, positive"), "{error}");
        }
    }
}
