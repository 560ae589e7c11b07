//! The atlas tool (paper §3.1) against the engine: a generated city and its
//! atlas version render identically at full resolution, and at each coarser level
//! the atlas adds error only where textures run out of levels of their own. One
//! level is made resident at a time, so both renders sample exactly that level
//! (the table's coarsest resident level bounds sampling), with nearest filtering.

use std::path::Path;
use std::sync::Arc;

use anyhow::{ensure, Context, Result};
use citystream_dataset::Dataset;
use citystream_engine::city::Camera;
use citystream_engine::commands::CommandContext;
use citystream_engine::target::RenderTarget;
use citystream_engine::Device;
use citystream_gen::atlas::{self, AtlasArgs};
use citystream_tests::{
    assert_no_validation_errors, camera_on_centre, city_cache_resident_at, tiny_rgba8_city, validated_device,
    visible_city_renderer,
};
use glam::Vec3;

const WIDTH: u32 = 320;
const HEIGHT: u32 = 240;

fn render_level0(device: &Arc<Device>, dir: &Path, camera: &Camera) -> Result<image::RgbaImage> {
    render_from_level(device, dir, camera, 0)
}

/// The city in `dir` with every texture resident from `level` (or its coarsest level, if
/// it has fewer) to its coarsest: a view that needs finer shows exactly that level.
fn render_from_level(device: &Arc<Device>, dir: &Path, camera: &Camera, level: u32) -> Result<image::RgbaImage> {
    let dataset = Dataset::open(dir).with_context(|| format!("opening {}", dir.display()))?;
    let mut commands = CommandContext::new(device, "atlas render")?;
    // The cache holds levels while both sides are whole texels (RGBA8 blocks).
    let cache = city_cache_resident_at(device, &mut commands, &dataset, level)?;
    let (renderer, _compactor) = visible_city_renderer(device, &mut commands, &dataset, &cache)?;
    let target = RenderTarget::new(device, WIDTH, HEIGHT)?;
    let cmd = commands.begin()?;
    // Unlit, and without the colormap blend: the sampled texels as they are.
    renderer.record_visible(cmd, &target, camera, 0.0, false)?;
    commands.submit_and_wait(&[])?;
    Ok(target.read_pixels()?)
}

/// The tiny RGBA8 city under `base` and its version in 512² shelf-packed atlases.
fn tiny_city_and_atlas(base: &Path) -> Result<(std::path::PathBuf, std::path::PathBuf)> {
    let original = tiny_rgba8_city(base)?;
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
    Ok((original, atlased))
}

#[test]
fn atlas_city_renders_like_the_original_at_full_resolution() -> Result<()> {
    let base = Path::new(env!("CARGO_TARGET_TMPDIR")).join("atlas_render");
    let (original, atlased) = tiny_city_and_atlas(&base)?;
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

/// Mean squared error over the RGB channels of two renders, per pixel, and how many pixels
/// differ by more than 2 in some channel.
fn mse(a: &image::RgbaImage, b: &image::RgbaImage) -> (f64, usize) {
    let (mut squared, mut differing) = (0.0f64, 0usize);
    for (p, q) in a.pixels().zip(b.pixels()) {
        let d = [0, 1, 2].map(|i| f64::from(p.0[i]) - f64::from(q.0[i]));
        squared += d.iter().map(|x| x * x).sum::<f64>() / 3.0;
        differing += usize::from(d.iter().any(|x| x.abs() > 2.0));
    }
    (squared / (a.width() * a.height()).max(1) as f64, differing)
}

/// The error the atlas adds at each level, against the same meshes drawn from their own
/// textures, both with only that level resident (a texture with fewer levels shows its
/// coarsest): docs/ARCHITECTURE.md, "Numerical choices", gives the table this prints.
/// Every texture sits at a multiple of its own size in the atlas, so while a texture still
/// has a level of its own the atlas's level is the same box filter of the same texels and
/// adds only UV rounding (at most 0.1 % of pixels differ, as at level 0). Past the least
/// texture's last level, atlas texels average neighbouring textures: that error is the
/// price of the paper's atlases, and stays below what the level itself costs against level 0.
#[test]
fn the_atlas_adds_nothing_while_textures_have_levels_and_less_than_the_level_after() -> Result<()> {
    let base = Path::new(env!("CARGO_TARGET_TMPDIR")).join("atlas_levels");
    let (original, atlased) = tiny_city_and_atlas(&base)?;
    let before = Dataset::open(&original)?;
    let after = Dataset::open(&atlased)?;
    ensure!(
        after.textures.len() < before.textures.len(),
        "the atlas must merge textures"
    );
    // The last level every texture still has: its least side is one texel there.
    let least_side = (0..before.textures.len())
        .map(|t| before.textures.info(t).map(|i| i.width().min(i.height())))
        .collect::<Result<Vec<_>, _>>()?
        .into_iter()
        .min()
        .unwrap_or(1);
    let exact_through = least_side.ilog2();
    let camera = camera_on_centre(&before.scene.bounds, |size| {
        Vec3::new(size.x * 0.2, size.y * 0.5 + 5.0, size.z * 0.2)
    });
    let device = validated_device()?;
    let full = render_from_level(&device, &original, &camera, 0)?;
    let pixels = (WIDTH * HEIGHT) as usize;
    let mut failures = Vec::new();
    let mut added_after = Vec::new();
    for level in 0..=exact_through + 4 {
        let own = render_from_level(&device, &original, &camera, level)?;
        let atlas = render_from_level(&device, &atlased, &camera, level)?;
        let (added, differing) = mse(&own, &atlas);
        let (level_error, _) = mse(&own, &full);
        eprintln!(
            "level {level}: the atlas adds MSE {added:.3} ({differing} of {pixels} pixels differ); \
             the level costs MSE {level_error:.3} against level 0"
        );
        if level <= exact_through {
            if differing * 1000 > pixels {
                failures.push(format!(
                    "level {level}: {differing} pixels differ, every texture has this level"
                ));
            }
        } else {
            added_after.push(added);
            if added > level_error {
                failures.push(format!(
                    "level {level}: the atlas adds MSE {added:.3}, the level costs {level_error:.3}"
                ));
            }
        }
    }
    ensure!(failures.is_empty(), "{}", failures.join("\n"));
    // The view must reach the levels where atlases cost something, or the bound is idle.
    ensure!(
        added_after.iter().any(|&added| added > 1.0),
        "past level {exact_through} the atlas added {added_after:?}: the view shows no texture's border"
    );
    assert_no_validation_errors(&device)
}
