//! The atlas tool (paper §3.1) against the engine: a generated city and its
//! atlas version render identically at full resolution. Only level 0 is made
//! resident, so both renders sample exactly level 0 (the table's coarsest
//! resident level bounds sampling), with nearest filtering.

use std::path::Path;
use std::sync::Arc;

use anyhow::{ensure, Context, Result};
use citystream_dataset::Dataset;
use citystream_engine::city::Camera;
use citystream_engine::commands::CommandContext;
use citystream_engine::target::RenderTarget;
use citystream_engine::texture_cache::GpuTextureCache;
use citystream_engine::Device;
use citystream_gen::atlas::{self, AtlasArgs};
use citystream_tests::{
    assert_no_validation_errors, camera_on_centre, tiny_rgba8_city, validated_device, visible_city_renderer,
    whole_city_cache_config,
};
use glam::Vec3;

const WIDTH: u32 = 320;
const HEIGHT: u32 = 240;

fn render_level0(device: &Arc<Device>, dir: &Path, camera: &Camera) -> Result<image::RgbaImage> {
    let dataset = Dataset::open(dir).with_context(|| format!("opening {}", dir.display()))?;
    let mut commands = CommandContext::new(device, "atlas render")?;
    let mut cache = GpuTextureCache::new(
        device,
        &mut commands,
        &whole_city_cache_config(dataset.textures.len(), 32),
        dataset.colormap.colours(),
    )?;
    let mut bytes = Vec::new();
    for texture in 0..dataset.textures.len() {
        let info = *dataset.textures.info(texture)?;
        dataset.textures.read_mip(texture, 0, &mut bytes)?;
        cache.stage(texture, info.format(), info.width(), info.height(), 0, &bytes)?;
    }
    cache.finish_cycle(&mut commands)?;
    let (renderer, _compactor) = visible_city_renderer(device, &mut commands, &dataset, &cache)?;
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
    let original = tiny_rgba8_city(&base)?;
    let atlased = base.join("atlas");
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
    let camera = camera_on_centre(&before.scene.bounds, |size| {
        Vec3::new(size.x * 0.2, size.y * 0.5 + 5.0, size.z * 0.2)
    });
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
