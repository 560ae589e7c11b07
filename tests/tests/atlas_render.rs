//! The atlas tool (paper §3.1) against the engine: a generated city and its
//! atlas version render identically at full resolution. Only level 0 is made
//! resident, so both renders sample exactly level 0 (the table's coarsest
//! resident level bounds sampling), with nearest filtering.

use citystream_dataset::TextureFormat;
use std::path::Path;
use std::sync::Arc;

use anyhow::{ensure, Context, Result};
use citystream_dataset::Dataset;
use citystream_engine::city::{city_geometry, Camera, CityRenderer};
use citystream_engine::commands::CommandContext;
use citystream_engine::feedback::FeedbackCompactor;
use citystream_engine::target::RenderTarget;
use citystream_engine::texture_cache::{CacheLayers, GpuCacheConfig, GpuTextureCache};
use citystream_engine::Device;
use citystream_gen::atlas::{self, AtlasArgs};
use citystream_gen::city::{FormatArg, GenArgs, Preset};
use citystream_gen::command as gen;
use citystream_tests::{assert_no_validation_errors, test_cache_config, validated_device};
use glam::Vec3;

const WIDTH: u32 = 320;
const HEIGHT: u32 = 240;

fn render_level0(device: &Arc<Device>, dir: &Path, camera: &Camera) -> Result<image::RgbaImage> {
    let dataset = Dataset::open(dir).with_context(|| format!("opening {}", dir.display()))?;
    let scene = &dataset.scene;
    let (vertices, meshes) = city_geometry(&dataset)?;
    let mut commands = CommandContext::new(device, "atlas render")?;
    let mut cache = GpuTextureCache::new(
        device,
        &mut commands,
        &GpuCacheConfig {
            layer_size: 2048,
            layers: CacheLayers::Fixed(32),
            memory_budget_bytes: 1 << 30,
            blocks_per_chunk: 64,
            staging_bytes: 32 << 20,
            ..test_cache_config(&[TextureFormat::Bc1, TextureFormat::Rgba8], dataset.textures.len())
        },
        dataset.colormap.colours(),
    )?;
    let mut bytes = Vec::new();
    for texture in 0..dataset.textures.len() {
        let info = *dataset.textures.info(texture)?;
        dataset.textures.read_mip(texture, 0, &mut bytes)?;
        cache.stage(texture, info.format(), info.width(), info.height(), 0, &bytes)?;
    }
    cache.finish_cycle(&mut commands)?;
    let compactor = FeedbackCompactor::new(device, &mut commands, meshes.len() as u32, 1)?;
    let renderer = CityRenderer::new(
        device,
        &mut commands,
        &vertices,
        &scene.indices,
        meshes,
        &cache,
        &compactor,
    )?;
    let target = RenderTarget::new(device, WIDTH, HEIGHT)?;
    let cmd = commands.begin()?;
    // Unlit, and without the colormap blend: the sampled texels as they are.
    renderer.record_visible(cmd, &target, camera, 0.0, false)?;
    commands.submit_and_wait(&[])?;
    Ok(target.read_pixels()?)
}

#[test]
fn atlas_city_renders_like_the_original_at_full_resolution() -> Result<()> {
    let base = Path::new(env!("CARGO_TARGET_TMPDIR")).join("atlas_render");
    let original = base.join("city");
    let atlased = base.join("atlas");
    let _ = std::fs::remove_dir_all(&base);
    gen::run(&GenArgs {
        preset: Preset::Tiny,
        seed: 5,
        out: original.clone(),
        format: FormatArg::Rgba8,
        max_extent: 512,
        textures_from: None,
        dry_run: false,
        quiet: true,
    })?;
    atlas::run(&AtlasArgs {
        input: original.clone(),
        out: atlased.clone(),
        region: 512.0,
        atlas_extent: 512,
        packing: atlas::Packing::Shelves,
        // Small enough that the atlases are composed in several batches.
        buffer_mb: 2,
        quiet: true,
    })?;
    let before = Dataset::open(&original)?;
    let after = Dataset::open(&atlased)?;
    ensure!(
        after.textures.len() * 4 <= before.textures.len(),
        "the atlas must merge textures: {} -> {}",
        before.textures.len(),
        after.textures.len()
    );

    // A close oblique view into the city: facades and roofs fill the frame.
    let bounds = before.scene.bounds;
    let size = Vec3::from(bounds.max) - Vec3::from(bounds.min);
    let centre = Vec3::from(bounds.center());
    let camera = Camera {
        eye: centre + Vec3::new(size.x * 0.2, size.y * 0.5 + 5.0, size.z * 0.2),
        target: centre,
        fov_y: 60f32.to_radians(),
        near: 0.5,
        far: size.length() * 4.0,
    };
    let device = validated_device()?;
    let a = render_level0(&device, &original, &camera)?;
    let b = render_level0(&device, &atlased, &camera)?;
    let differing = a
        .pixels()
        .zip(b.pixels())
        .filter(|(p, q)| p.0.iter().zip(q.0.iter()).any(|(x, y)| x.abs_diff(*y) > 2))
        .count();
    eprintln!("{differing} of {} pixels differ", WIDTH * HEIGHT);
    let sky = a.pixels().filter(|p| p.0 == a.get_pixel(0, 0).0).count();
    ensure!(
        sky < (WIDTH * HEIGHT / 2) as usize,
        "the view must show the city, not sky"
    );
    if differing > 0 {
        let out = base.join("diff");
        std::fs::create_dir_all(&out)?;
        a.save(out.join("original.png"))?;
        b.save(out.join("atlas.png"))?;
    }
    ensure!(
        differing * 1000 <= (WIDTH * HEIGHT) as usize,
        "{differing} of {} pixels differ between the original and the atlas city (see {})",
        WIDTH * HEIGHT,
        base.join("diff").display()
    );
    assert_no_validation_errors(&device)
}
