//! The texture-atlas tree against the engine: with every texture resident, a tiny city
//! drawn with each leaf's atlas looks like the same city drawn with its original textures,
//! within a stated PSNR, from anywhere at least the leaves' distance away.

use std::path::Path;
use std::sync::Arc;

use anyhow::{ensure, Context, Result};
use citystream_bench::image_error::psnr_db;
use citystream_cache::geometry::cacheable_mip_count;
use citystream_dataset::Dataset;
use citystream_engine::atlas_tree::AtlasTreeRenderer;
use citystream_engine::city::Camera;
use citystream_engine::commands::CommandContext;
use citystream_engine::pipeline::Filtering;
use citystream_engine::target::RenderTarget;
use citystream_engine::texture_cache::{GpuCacheConfig, GpuTextureCache};
use citystream_engine::Device;
use citystream_gen::atlas_tree::{build, AtlasTreeArgs, LeafDistances};
use citystream_streaming::atlas_tree::{distance_to, AtlasTree, DrawWith, Selection};
use citystream_streaming::source::texel_format;
use citystream_tests::{
    assert_no_validation_errors, camera_on_centre, tiny_rgba8_city, validated_device, visible_city_renderer,
    whole_city_cache_config,
};
use glam::Vec3;

const WIDTH: u32 = 320;
const HEIGHT: u32 = 240;

/// The least PSNR (dB, RGB) of the leaf-atlas render against the originals' render. The
/// atlases resample the originals (bilinear, from the mip nearest above the area's size)
/// and the hardware then samples the atlas at its own level of detail, so the images are
/// close but not equal; measured 41.5 to 42.8 dB on these views (drawing every leaf with
/// the root's atlas instead gives 25.5 dB on the first).
const MIN_PSNR_DB: f64 = 38.0;

/// Renders the tree's dataset from `cameras` with every texture resident (every level):
/// once with the original textures, once with each leaf drawn with its own atlas.
fn render_both(
    device: &Arc<Device>,
    dir: &Path,
    cameras: &[Camera],
) -> Result<Vec<(image::RgbaImage, image::RgbaImage)>> {
    let dataset = Dataset::open(dir).with_context(|| format!("opening {}", dir.display()))?;
    let tree = AtlasTree::open(&dataset)?;
    let scene = &dataset.scene;
    let mut commands = CommandContext::new(device, "atlas tree render")?;
    let mut cache = GpuTextureCache::new(
        device,
        &mut commands,
        &GpuCacheConfig {
            filtering: Filtering::BilinearNearestLevel,
            ..whole_city_cache_config(dataset.textures.len(), 64)
        },
        dataset.colormap.colours(),
    )?;
    let mut bytes = Vec::new();
    for texture in 0..dataset.textures.len() {
        let info = *dataset.textures.info(texture)?;
        // The cache holds no level smaller than a texel block of its image.
        let levels = cacheable_mip_count(&texel_format(info.format()), info.width(), info.height());
        for level in 0..info.mip_count().min(levels) {
            dataset.textures.read_mip(texture, level, &mut bytes)?;
            cache.stage(texture, info.format(), info.width(), info.height(), level, &bytes)?;
        }
        // Whole chains stay within the staging ring.
        cache.finish_cycle(&mut commands)?;
    }
    let (renderer, _compactor) = visible_city_renderer(device, &mut commands, &dataset, &cache)?;
    let mut tree_renderer = AtlasTreeRenderer::new(device, &mut commands, &renderer, &scene.indices, &tree, &cache, 1)?;
    // Every leaf with its own atlas: the finest cut of the tree.
    let leaves = Selection {
        draws: (0..tree.nodes.len() as u32)
            .filter(|&n| tree.nodes[n as usize].is_leaf())
            .map(|n| (n, DrawWith::Atlas(n)))
            .collect(),
        fallbacks: 0,
    };
    let drawn = tree_renderer.write_selection(0, &leaves)?;
    ensure!(drawn.atlas_draws >= 4, "{drawn:?}: the tree must have several leaves");
    let target = RenderTarget::new(device, WIDTH, HEIGHT)?;
    let mut images = Vec::new();
    for camera in cameras {
        let cmd = commands.begin()?;
        renderer.record_visible(cmd, &target, camera, 1.0, false)?;
        commands.submit_and_wait(&[])?;
        let originals = target.read_pixels()?;
        let cmd = commands.begin()?;
        tree_renderer.record_visible(cmd, 0, &renderer, &target, camera, false, None)?;
        commands.submit_and_wait(&[])?;
        images.push((originals, target.read_pixels()?));
    }
    Ok(images)
}

#[test]
fn atlas_tree_render_with_every_leaf_atlas_matches_the_originals() -> Result<()> {
    let base = Path::new(env!("CARGO_TARGET_TMPDIR")).join("atlas_tree_render");
    let city = tiny_rgba8_city(&base)?;
    let tree_dir = base.join("tree");
    let summary = build(&AtlasTreeArgs {
        dataset: city,
        out: tree_dir.clone(),
        atlas_extent: 512,
        texel_per_pixel: 1.0,
        screen_height: HEIGHT,
        min_distance: None,
        distances: LeafDistances::FullDensity,
        buffer_mb: 64,
        quiet: true,
    })?;
    let dataset = Dataset::open(&tree_dir)?;
    let tree = AtlasTree::open(&dataset)?;
    // Oblique views over the city and one from street level, all at least the leaves'
    // distance d_min from every triangle (nearer, the traversal draws the originals).
    let bounds = &dataset.scene.bounds;
    let cameras = [
        camera_on_centre(bounds, |size| {
            Vec3::new(size.x * 0.25, size.y * 0.3 + 10.0, size.z * 0.25)
        }),
        camera_on_centre(bounds, |size| {
            Vec3::new(-size.x * 0.4, size.y * 0.2 + 5.0, size.z * 0.1)
        }),
        camera_on_centre(bounds, |size| {
            Vec3::new(-size.x * 0.25, size.y * 0.3 + 10.0, -size.z * 0.25)
        }),
    ];
    let d_min = tree.params.leaf_min_distance;
    for (i, camera) in cameras.iter().enumerate() {
        let nearest = tree
            .nodes
            .iter()
            .filter(|n| n.is_leaf())
            .map(|n| distance_to(&n.bounds, camera.eye.as_vec3().to_array()))
            .fold(f32::INFINITY, f32::min);
        ensure!(
            nearest >= d_min,
            "view {i} is {nearest} m from a leaf, nearer than d_min = {d_min} m ({summary:?})"
        );
    }
    let device = validated_device()?;
    let out = base.join("images");
    for (i, (originals, leaves)) in render_both(&device, &tree_dir, &cameras)?.iter().enumerate() {
        let sky = originals
            .pixels()
            .filter(|p| p.0 == originals.get_pixel(0, 0).0)
            .count();
        if sky >= (WIDTH * HEIGHT / 2) as usize {
            std::fs::create_dir_all(&out)?;
            originals.save(out.join(format!("view{i}-originals.png")))?;
        }
        ensure!(
            sky < (WIDTH * HEIGHT / 2) as usize,
            "view {i} must show the city, not sky"
        );
        let psnr = psnr_db(leaves, originals);
        eprintln!("view {i}: leaf atlases against originals {psnr:.2} dB");
        if psnr < MIN_PSNR_DB {
            std::fs::create_dir_all(&out)?;
            originals.save(out.join(format!("view{i}-originals.png")))?;
            leaves.save(out.join(format!("view{i}-leaf-atlases.png")))?;
        }
        ensure!(
            psnr >= MIN_PSNR_DB,
            "view {i}: the leaf atlases render {psnr:.2} dB from the originals, below {MIN_PSNR_DB} dB (images in {})",
            out.display()
        );
    }
    assert_no_validation_errors(&device)
}
