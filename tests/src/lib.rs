//! Shared helpers for the lavapipe integration tests: a device with the
//! validation layer forced on, a check that no validation error was
//! reported, a small cache's configuration, and image comparison that writes
//! actual/expected/difference PNGs on failure.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use citystream_dataset::{Aabb, Dataset, TextureFormat};
use citystream_engine::city::{city_geometry, Camera, CityMesh, CityRenderer};
use citystream_engine::commands::CommandContext;
use citystream_engine::device::{SparseMode, TextureBacking};
use citystream_engine::feedback::FeedbackCompactor;
use citystream_engine::gpu_types::Vertex;
use citystream_engine::instance::InstanceOptions;
use citystream_engine::pipeline::Filtering;
use citystream_engine::texture_cache::{CacheLayers, Eviction, GpuCacheConfig, GpuTextureCache};
use citystream_engine::{Device, DeviceOptions};
use citystream_gen::city::{FormatArg, GenArgs, Preset};
use glam::Vec3;

/// The tests' cache: `texture_count` textures of `formats` in two layers of 256² per image,
/// ring eviction, nearest filtering, 16 MB of budget and of staging. Tests that need
/// another shape change fields with `..test_cache_config(..)`.
pub fn test_cache_config(formats: &[TextureFormat], texture_count: u32) -> GpuCacheConfig {
    GpuCacheConfig {
        layer_size: 256,
        layers: CacheLayers::Fixed(2),
        formats: formats.to_vec(),
        eviction: Eviction::Ring,
        memory_budget_bytes: 16 << 20,
        virtual_budget_bytes: None,
        blocks_per_chunk: 16,
        texture_count,
        filtering: Filtering::Nearest,
        staging_bytes: 16 << 20,
    }
}

/// Quads, each its own mesh, in the layout `CityRenderer::new` takes: the scenes of the
/// tests that build their geometry by hand.
#[derive(Debug, Default)]
pub struct QuadMeshes {
    pub vertices: Vec<Vertex>,
    pub indices: Vec<u32>,
    pub meshes: Vec<CityMesh>,
}

impl QuadMeshes {
    /// Adds a quad with corners counter-clockwise from its lower left (texture v from 1 at
    /// the first edge to 0 at the last), one mesh of `texture` with `extent` texels.
    pub fn push(&mut self, corners: [Vec3; 4], normal: Vec3, texture: u32, extent: (u32, u32)) {
        let first_vertex = self.vertices.len() as u32;
        for (corner, uv) in corners.iter().zip([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]]) {
            self.vertices.push(Vertex {
                position: corner.to_array(),
                normal: normal.to_array(),
                uv,
            });
        }
        self.meshes.push(CityMesh {
            first_index: self.indices.len() as u32,
            index_count: 6,
            vertex_offset: first_vertex,
            texture,
            texture_width: extent.0,
            texture_height: extent.1,
            origin: glam::DVec3::ZERO,
        });
        self.indices.extend([0, 1, 2, 0, 2, 3]);
    }
}

/// Creates a device with `VK_LAYER_KHRONOS_validation` on, whatever the build.
pub fn validated_device() -> Result<Arc<Device>> {
    device_with_validation(false)
}

/// As [`validated_device`], with synchronization validation on too: for
/// code that overlaps frames.
pub fn sync_validated_device() -> Result<Arc<Device>> {
    device_with_validation(true)
}

/// As [`validated_device`], set up for the texture-array cache
/// ([`SparseMode::Off`]): no sparse feature enabled, even where the device
/// has them.
pub fn validated_array_device() -> Result<Arc<Device>> {
    let device = device_with_mode(false, SparseMode::Off)?;
    if device.texture_backing() != TextureBacking::Arrays {
        bail!("asked for texture arrays, got {:?}", device.texture_backing());
    }
    Ok(device)
}

/// The sparse cache's tests ask for it: on a device without sparse residency
/// they fail at once, naming the feature, rather than on the first sparse image.
fn device_with_validation(synchronization: bool) -> Result<Arc<Device>> {
    device_with_mode(synchronization, SparseMode::On)
}

fn device_with_mode(synchronization: bool, sparse: SparseMode) -> Result<Arc<Device>> {
    let options = DeviceOptions {
        instance: InstanceOptions {
            validation: true,
            synchronization,
            app_name: "citystream tests".to_owned(),
            extensions: Vec::new(),
        },
        device_name: None,
        presentation: false,
        sparse,
        ..Default::default()
    };
    Ok(Arc::new(
        Device::new(&options).context("creating a validated Vulkan device")?,
    ))
}

/// `base` emptied, and in `base/city` the tiny preset generated as RGBA8 from seed 5 (the
/// city the atlas tests render); the city's directory.
pub fn tiny_rgba8_city(base: &Path) -> Result<PathBuf> {
    let city = base.join("city");
    let _ = std::fs::remove_dir_all(base);
    citystream_gen::command::run(&GenArgs {
        preset: Preset::Tiny,
        seed: 5,
        out: city.clone(),
        format: FormatArg::Rgba8,
        max_extent: 512,
        textures_from: None,
        dry_run: false,
        quiet: true,
        shard: Default::default(),
    })?;
    Ok(city)
}

/// A camera looking at the centre of `bounds` from `offset(size)` away from it (`size` the
/// bounds' extent), with a 60° field of view (and, as every camera, no far plane).
pub fn camera_on_centre(bounds: &Aabb, offset: impl FnOnce(Vec3) -> Vec3) -> Camera {
    let size = Vec3::from(bounds.max) - Vec3::from(bounds.min);
    let centre = Vec3::from(bounds.center());
    Camera {
        eye: (centre + offset(size)).as_dvec3(),
        target: centre.as_dvec3(),
        fov_y: 60f32.to_radians(),
        near: 0.5,
    }
}

/// A camera at the origin looking down −z with the vertical field of view `fov_y` and near
/// plane 0.1: the view of the tests that place quads in front of it.
pub fn camera_down_negative_z(fov_y: f32) -> Camera {
    Camera {
        eye: glam::DVec3::ZERO,
        target: glam::DVec3::new(0.0, 0.0, -1.0),
        fov_y,
        near: 0.1,
    }
}

/// A renderer of `dataset`'s city sampling `cache`, with the feedback compactor it was made
/// with (for one entry per mesh: these tests draw the visible pass), to keep alive beside it.
pub fn visible_city_renderer(
    device: &Arc<Device>,
    commands: &mut CommandContext,
    dataset: &Dataset,
    cache: &GpuTextureCache,
) -> Result<(CityRenderer, FeedbackCompactor)> {
    let (vertices, meshes) = city_geometry(dataset)?;
    let compactor = FeedbackCompactor::new(device, commands, meshes.len() as u32, 1)?;
    let renderer = CityRenderer::new(
        device,
        commands,
        &vertices,
        &dataset.scene.indices,
        meshes,
        cache,
        &compactor,
    )?;
    Ok((renderer, compactor))
}

/// A cache for a whole city at once: `layers` layers of 2048² for BC1 and RGBA8 textures,
/// a 1 GiB budget and 32 MiB of staging.
pub fn whole_city_cache_config(texture_count: u32, layers: u32) -> GpuCacheConfig {
    GpuCacheConfig {
        layer_size: 2048,
        layers: CacheLayers::Fixed(layers),
        memory_budget_bytes: 1 << 30,
        blocks_per_chunk: 64,
        staging_bytes: 32 << 20,
        ..test_cache_config(&[TextureFormat::Bc1, TextureFormat::Rgba8], texture_count)
    }
}

/// A cache for `dataset`'s whole city ([`whole_city_cache_config`], 32 layers) with every
/// texture resident at `level`, or at its coarsest level the cache holds (both sides whole
/// texels) where it has fewer: a view that needs finer shows exactly that level.
pub fn city_cache_resident_at(
    device: &Arc<Device>,
    commands: &mut CommandContext,
    dataset: &Dataset,
    level: u32,
) -> Result<GpuTextureCache> {
    let mut cache = GpuTextureCache::new(
        device,
        commands,
        &whole_city_cache_config(dataset.textures.len(), 32),
        dataset.colormap.colours(),
    )?;
    let mut bytes = Vec::new();
    for texture in 0..dataset.textures.len() {
        let info = *dataset.textures.info(texture)?;
        let coarsest = (info.mip_count() - 1).min(info.width().min(info.height()).ilog2());
        let mip = level.min(coarsest);
        dataset.textures.read_mip(texture, mip, &mut bytes)?;
        cache.stage(texture, info.format(), info.width(), info.height(), mip, &bytes)?;
    }
    cache.finish_cycle(commands)?;
    Ok(cache)
}

/// Fails when the validation layer reported any error on `device`.
pub fn assert_no_validation_errors(device: &Device) -> Result<()> {
    let errors = device.validation_log().errors();
    if !errors.is_empty() {
        let listing: Vec<String> = errors.iter().map(|e| format!("  {}: {}", e.id, e.text)).collect();
        bail!("{} validation error(s):\n{}", errors.len(), listing.join("\n"));
    }
    Ok(())
}

/// Drops what a test held, in the order given (a tuple drops its fields first to last: what
/// records into or reads from a resource before the resource, the resource before its
/// memory), then fails when the validation layer reported any error on `device`: how most
/// tests here end.
pub fn assert_clean_after_dropping<T>(device: &Device, held: T) -> Result<()> {
    drop(held);
    assert_no_validation_errors(device)
}

/// Outcome of comparing two images.
#[derive(Debug)]
pub struct Comparison {
    /// Pixels compared (not masked out).
    pub compared: usize,
    /// Compared pixels whose channels differ by more than the tolerance.
    pub mismatched: usize,
    /// Largest channel difference among compared pixels.
    pub max_difference: u8,
}

/// The largest difference between two pixels' channels.
pub fn channel_difference(a: &image::Rgba<u8>, b: &image::Rgba<u8>) -> u8 {
    a.0.iter()
        .zip(b.0.iter())
        .map(|(p, q)| p.abs_diff(*q))
        .max()
        .unwrap_or(0)
}

/// How two images of one size differ, every pixel compared: those whose channels differ by
/// more than `tolerance`, and the largest difference (no files written, no error: for tests
/// that bound the count rather than require none).
pub fn count_differences(actual: &image::RgbaImage, expected: &image::RgbaImage, tolerance: u8) -> Comparison {
    actual.pixels().zip(expected.pixels()).fold(
        Comparison {
            compared: 0,
            mismatched: 0,
            max_difference: 0,
        },
        |mut result, (a, e)| {
            let worst = channel_difference(a, e);
            result.compared += 1;
            result.mismatched += usize::from(worst > tolerance);
            result.max_difference = result.max_difference.max(worst);
            result
        },
    )
}

/// Compares `actual` with `expected` channel by channel, skipping pixels
/// where `mask` is false. On any mismatch beyond `tolerance`, writes
/// `NAME-actual.png`, `NAME-expected.png` and `NAME-difference.png` into
/// `out_dir` and returns an error naming them.
pub fn compare_images(
    actual: &image::RgbaImage,
    expected: &image::RgbaImage,
    mask: impl Fn(u32, u32) -> bool,
    tolerance: u8,
    out_dir: &Path,
    name: &str,
) -> Result<Comparison> {
    if actual.dimensions() != expected.dimensions() {
        bail!(
            "{name}: actual image is {:?}, expected {:?}",
            actual.dimensions(),
            expected.dimensions()
        );
    }
    let mut difference = image::RgbaImage::new(actual.width(), actual.height());
    let mut result = Comparison {
        compared: 0,
        mismatched: 0,
        max_difference: 0,
    };
    for (x, y, a) in actual.enumerate_pixels() {
        if !mask(x, y) {
            difference.put_pixel(x, y, image::Rgba([0, 0, 64, 255]));
            continue;
        }
        let worst = channel_difference(a, expected.get_pixel(x, y));
        result.compared += 1;
        result.max_difference = result.max_difference.max(worst);
        if worst > tolerance {
            result.mismatched += 1;
            difference.put_pixel(x, y, image::Rgba([255, 0, 0, 255]));
        } else {
            difference.put_pixel(
                x,
                y,
                image::Rgba([
                    worst.saturating_mul(16),
                    worst.saturating_mul(16),
                    worst.saturating_mul(16),
                    255,
                ]),
            );
        }
    }
    if result.mismatched > 0 {
        std::fs::create_dir_all(out_dir)?;
        let paths: Vec<PathBuf> = ["actual", "expected", "difference"]
            .iter()
            .map(|kind| out_dir.join(format!("{name}-{kind}.png")))
            .collect();
        actual.save(&paths[0])?;
        expected.save(&paths[1])?;
        difference.save(&paths[2])?;
        bail!(
            "{name}: {} of {} pixels differ by more than {tolerance} (max {}); see {}",
            result.mismatched,
            result.compared,
            result.max_difference,
            paths
                .iter()
                .map(|p| p.display().to_string())
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    Ok(result)
}

/// [`compare_images`] of `actual` against `expected` within 2 per channel, where
/// `certain` (row-major, one per pixel) says the reference knows the pixel.
pub fn compare_where_certain(
    actual: &image::RgbaImage,
    expected: &image::RgbaImage,
    certain: &[bool],
    out_dir: &Path,
    name: &str,
) -> Result<Comparison> {
    let width = actual.width();
    compare_images(
        actual,
        expected,
        |x, y| certain[(y * width + x) as usize],
        2,
        out_dir,
        name,
    )
}

/// Decodes one BC1 block (opaque RGB mode) into 16 RGBA8 texels, row by row,
/// as the Vulkan spec defines it (RGB565 endpoints expanded by bit
/// replication; 4-colour mode when colour0 > colour1, else 3-colour with black).
pub fn decode_bc1_block(block: &[u8; 8]) -> [[u8; 4]; 16] {
    let c0 = u16::from_le_bytes([block[0], block[1]]);
    let c1 = u16::from_le_bytes([block[2], block[3]]);
    let expand = |c: u16| -> [f32; 3] {
        let r = u32::from((c >> 11) & 31);
        let g = u32::from((c >> 5) & 63);
        let b = u32::from(c & 31);
        [
            ((r << 3) | (r >> 2)) as f32,
            ((g << 2) | (g >> 4)) as f32,
            ((b << 3) | (b >> 2)) as f32,
        ]
    };
    let (e0, e1) = (expand(c0), expand(c1));
    let lerp = |t: f32| -> [f32; 3] { [0, 1, 2].map(|i| e0[i] + (e1[i] - e0[i]) * t) };
    let palette: [[f32; 3]; 4] = if c0 > c1 {
        [e0, e1, lerp(1.0 / 3.0), lerp(2.0 / 3.0)]
    } else {
        [e0, e1, lerp(0.5), [0.0; 3]]
    };
    let indices = u32::from_le_bytes([block[4], block[5], block[6], block[7]]);
    let mut texels = [[0u8; 4]; 16];
    for (i, texel) in texels.iter_mut().enumerate() {
        let c = palette[((indices >> (2 * i)) & 3) as usize];
        *texel = [c[0].round() as u8, c[1].round() as u8, c[2].round() as u8, 255];
    }
    texels
}

/// The RGBA8 texel at (x, y) of a BC1 level of `width` texels.
pub fn bc1_texel(level: &[u8], width: u32, x: u32, y: u32) -> [u8; 4] {
    let blocks_across = width.div_ceil(4);
    let block = ((y / 4) * blocks_across + x / 4) as usize * 8;
    let mut bytes = [0u8; 8];
    bytes.copy_from_slice(&level[block..block + 8]);
    decode_bc1_block(&bytes)[((y % 4) * 4 + x % 4) as usize]
}

/// Bytes of memory a sparse cache of `layers` layers of `layer_size`²
/// `format` texels binds for mip tails beyond what the same levels take
/// without a tail, when `live_layers` layers hold textures: where a level of
/// the tail alone (its coarsest) would take one block per live layer, a
/// per-layer tail takes all of its blocks per live layer, and a single tail
/// is bound once; zero
/// without a tail (lavapipe, unless `CITYSTREAM_FORCE_MIP_TAIL` forces one).
/// Tests whose budget holds "about N textures" add it, so the scenario stays
/// the one they describe on a device with tails.
pub fn tail_allowance(
    device: &Arc<Device>,
    format: citystream_engine::vk::Format,
    layer_size: u32,
    layers: u32,
    live_layers: u32,
) -> Result<u64> {
    use citystream_engine::sparse::{SparseImage, SparseImageDesc};
    let probe = SparseImage::new(
        device,
        SparseImageDesc {
            width: layer_size,
            height: layer_size,
            layers,
            mips: layer_size.max(1).ilog2() + 1,
            format,
        },
        "tail allowance probe",
    )?;
    let tail_bytes = u64::from(probe.tail_blocks()) * probe.block_size();
    // Without a tail, the coarsest level alone of a live layer takes a block.
    let coarsest_alone = probe.block_size() * u64::from(live_layers);
    Ok(if probe.tail_blocks() == 0 {
        0
    } else if probe.mip_tail().single {
        tail_bytes.saturating_sub(coarsest_alone)
    } else {
        (tail_bytes * u64::from(live_layers)).saturating_sub(coarsest_alone)
    })
}

/// Copies `bytes` into freshly created `image` (from `UNDEFINED`) as `uploads` say, leaving
/// it sampleable, in one submission on `commands` that waits on `waits` (the binds of the
/// blocks it writes), and waits for it.
pub fn copy_into_new_sparse_image(
    device: &Arc<Device>,
    commands: &mut citystream_engine::commands::CommandContext,
    image: &citystream_engine::sparse::SparseImage,
    uploads: &[citystream_engine::sparse::TexelUpload],
    bytes: &[u8],
    waits: &[citystream_engine::commands::SemaphoreWait],
) -> Result<()> {
    use citystream_engine::buffer::{Buffer, BufferDesc};
    use citystream_engine::vk;
    let mut staging = Buffer::new(
        device,
        BufferDesc {
            size: bytes.len() as u64,
            usage: vk::BufferUsageFlags::TRANSFER_SRC,
            location: citystream_engine::gpu_allocator::MemoryLocation::CpuToGpu,
        },
        "test upload staging",
    )?;
    staging.write(0, bytes)?;
    let cmd = commands.begin()?;
    image.record_layout(cmd, vk::ImageLayout::UNDEFINED, vk::ImageLayout::TRANSFER_DST_OPTIMAL);
    image.record_copies(cmd, staging.raw(), uploads)?;
    image.record_layout(
        cmd,
        vk::ImageLayout::TRANSFER_DST_OPTIMAL,
        vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
    );
    commands.submit_and_wait(waits)?;
    Ok(())
}
