//! Far from the origin: a square 4 m across, turned in its plane so that its edges slant
//! across the pixel grid, 10 m ahead of a camera 1,000 km from the scene's origin (and, for
//! comparison, at the origin), the camera sliding sideways 5 mm a frame. On every
//! frame each pixel whose centre lies more than a tenth of a pixel (plus the rasteriser's
//! 1/256 snap) inside or outside the square's outline, as `f64` arithmetic projects the
//! vertices the GPU holds, is covered or not as that says: no vertex is a tenth of a pixel
//! from where `f64` puts it. Validation on; any message fails. (The city passes subtract
//! the eye before the rotation; with the eye's translation carried in an `f32` matrix the
//! same vertices land more than half a pixel off at 1,000 km:
//! `engine/src/city.rs`'s `relative_positions_keep_a_tenth_of_a_pixel_a_thousand_kilometres_out`.)

use anyhow::{ensure, Result};
use citystream_dataset::TextureFormat;
use citystream_engine::city::{Camera, CityRenderer};
use citystream_engine::commands::CommandContext;
use citystream_engine::feedback::FeedbackCompactor;
use citystream_engine::target::RenderTarget;
use citystream_engine::texture_cache::GpuTextureCache;
use citystream_tests::{assert_no_validation_errors, test_cache_config, validated_device, QuadMeshes};
use glam::{DVec3, DVec4, Vec3};

const SIZE: u32 = 512;
/// The square's colour: nothing is resident, so it shows its colormap colour.
const COLOUR: [u8; 4] = [255, 0, 0, 255];
/// How far inside or outside the outline a pixel centre must lie to be judged: the bound
/// on a vertex's error, and the rasteriser's sub-pixel snap (8 bits on lavapipe).
const TOLERANCE_PX: f64 = 0.1 + 1.0 / 256.0;
const FRAMES: u32 = 24;
const STEP_M: f64 = 5e-3;
const DISTANCE_M: f64 = 10.0;

/// The square's corners around `centre`, in the plane facing +z, turned 17° in it.
fn square(centre: DVec3) -> [Vec3; 4] {
    let (sin, cos) = 17f64.to_radians().sin_cos();
    [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)].map(|(x, y)| {
        let (x, y) = (x * 2.0, y * 2.0);
        (centre + DVec3::new(x * cos - y * sin, x * sin + y * cos, 0.0)).as_vec3()
    })
}

/// Pixel coordinates of `point` through `camera`.
fn project(camera: &Camera, point: DVec3) -> [f64; 2] {
    let clip = camera.view_projection_f64(1.0, 0.0) * DVec4::new(point.x, point.y, point.z, 1.0);
    let size = f64::from(SIZE);
    [
        (clip.x / clip.w * 0.5 + 0.5) * size,
        (clip.y / clip.w * 0.5 + 0.5) * size,
    ]
}

/// Signed distance in pixels of `point` inside the convex `outline` (negative outside):
/// the least over its edges, each taken positive on the side the polygon's winding puts
/// its inside.
fn inside_by(outline: &[[f64; 2]; 4], point: [f64; 2]) -> f64 {
    let area: f64 = (0..4)
        .map(|i| {
            let (a, b) = (outline[i], outline[(i + 1) % 4]);
            a[0] * b[1] - b[0] * a[1]
        })
        .sum();
    let winding = area.signum();
    (0..4)
        .map(|i| {
            let (a, b) = (outline[i], outline[(i + 1) % 4]);
            let edge = [b[0] - a[0], b[1] - a[1]];
            winding * (edge[0] * (point[1] - a[1]) - edge[1] * (point[0] - a[0])) / edge[0].hypot(edge[1])
        })
        .fold(f64::INFINITY, f64::min)
}

/// Flies the slide with the square at `centre`; the pixels that disagree with `f64` and
/// how many pixels within half a pixel of the outline were judged.
fn slide(centre: DVec3) -> Result<(Vec<String>, u64)> {
    let device = validated_device()?;
    let mut commands = CommandContext::new(&device, "far from the origin")?;
    let cache = GpuTextureCache::new(
        &device,
        &mut commands,
        &test_cache_config(&[TextureFormat::Rgba8], 1),
        &[COLOUR],
    )?;
    let corners = square(centre);
    let mut quads = QuadMeshes::default();
    quads.push(corners, Vec3::Z, 0, (64, 64));
    let compactor = FeedbackCompactor::new(&device, &mut commands, 1, 1)?;
    let renderer = CityRenderer::new(
        &device,
        &mut commands,
        &quads.vertices,
        &quads.indices,
        quads.meshes,
        &cache,
        &compactor,
    )?;
    let target = RenderTarget::new(&device, SIZE, SIZE)?;
    let mut wrong = Vec::new();
    let mut near_edges = 0;
    for frame in 0..FRAMES {
        let eye = centre + DVec3::new(STEP_M * f64::from(frame), 0.0, DISTANCE_M);
        let camera = Camera {
            eye,
            target: eye - DVec3::Z,
            fov_y: 60f32.to_radians(),
            near: 0.5,
        };
        let cmd = commands.begin()?;
        renderer.record_visible(cmd, &target, &camera, 0.0, true)?;
        commands.submit_and_wait(&[])?;
        let image = target.read_pixels()?;
        // The vertices as the GPU holds them (f32), projected in f64.
        let outline = corners.map(|c| project(&camera, c.as_dvec3()));
        for y in 0..SIZE {
            for x in 0..SIZE {
                let inside = inside_by(&outline, [f64::from(x) + 0.5, f64::from(y) + 0.5]);
                if inside.abs() < 0.5 {
                    near_edges += 1;
                }
                if inside.abs() <= TOLERANCE_PX {
                    continue;
                }
                let covered = image.get_pixel(x, y).0 == COLOUR;
                if covered != (inside > 0.0) {
                    wrong.push(format!(
                        "frame {frame}: pixel ({x}, {y}) {:.3} px {} the outline is {}",
                        inside.abs(),
                        if inside > 0.0 { "inside" } else { "outside" },
                        if covered { "covered" } else { "not covered" }
                    ));
                }
            }
        }
    }
    drop(renderer);
    assert_no_validation_errors(&device)?;
    Ok((wrong, near_edges))
}

#[test]
fn a_thousand_kilometres_out_no_vertex_strays_a_tenth_of_a_pixel_from_f64() -> Result<()> {
    for (name, centre) in [
        ("at the origin", DVec3::new(0.0, 30.0, 0.0)),
        ("1,000 km out", DVec3::new(1.0e6, 30.0, -1.0e6)),
    ] {
        let (wrong, near_edges) = slide(centre)?;
        eprintln!(
            "{name}: {} pixels disagree with f64, {near_edges} pixels within half a pixel of the outline",
            wrong.len()
        );
        // The check means something only where many pixel centres lie near the edges.
        ensure!(near_edges > 10_000, "{name}: {near_edges} pixels near the outline");
        ensure!(
            wrong.is_empty(),
            "{name}:\n{}",
            wrong.iter().take(10).cloned().collect::<Vec<_>>().join("\n")
        );
    }
    Ok(())
}

/// Where the small city is placed for the far run: about 1,000 km east and north of the
/// scene's origin, at no multiple of a power of two, so the origin's split has a low part.
const FAR_ORIGIN: DVec3 = DVec3::new(1_000_003.718_281_828, 41.141_592_653, -999_997.302_585_093);

/// Eye offsets from the city's centre, in units of its extent: an oblique orbit around it
/// sliding slowly sideways, as a flythrough's frames would.
fn relative_path(size: Vec3) -> Vec<(DVec3, DVec3)> {
    (0..6)
        .map(|frame| {
            let angle = 0.4 + 0.25 * f64::from(frame);
            let radius = f64::from(size.x.max(size.z)) * 0.45;
            let eye = DVec3::new(
                angle.cos() * radius,
                f64::from(size.y) * 0.6 + 8.0,
                angle.sin() * radius,
            );
            // Looking a little to the side of the centre, so edges cross the frame at
            // every slant.
            (eye, DVec3::new(3.0 * f64::from(frame), 0.0, -2.0))
        })
        .collect()
}

/// How the small city is drawn.
#[derive(Clone, Copy)]
enum Placement {
    /// Its meshes' local origins at the point (their vertices as the dataset holds them).
    Local(DVec3),
    /// Its vertices moved to the point in `f32` and the origins zero: positions relative to
    /// one scene origin, as the engine drew every city before local origins.
    Flattened(DVec3),
    /// The whole scene moved to the point, cut into dataset format 4's leaf tiles (each with
    /// its own origin; `tiles.bin` encoded and decoded, each tile's geometry read back from
    /// the pack) and drawn from them (`tiled_city_geometry`).
    Tiles(DVec3),
}

/// The tiny city's views along [`relative_path`] placed as `placement` says, each frame's
/// feedback pass before its visible pass, with GPU culling when `culled`.
/// Also returns how many meshes the culling left undrawn over the frames (0 unculled).
fn fly_small_city(dir: &std::path::Path, placement: Placement, culled: bool) -> Result<(Vec<image::RgbaImage>, u64)> {
    use citystream_dataset::Dataset;
    use citystream_engine::city::FeedbackView;
    use citystream_engine::city::{city_geometry, tiled_city_geometry};
    let dataset = Dataset::open(dir)?;
    let device = validated_device()?;
    let mut commands = CommandContext::new(&device, "small city far from the origin")?;
    let cache = citystream_tests::city_cache_resident_at(&device, &mut commands, &dataset, 0)?;
    let (mut vertices, mut meshes) = city_geometry(&dataset)?;
    let mut indices = dataset.scene.indices.clone();
    let origin = match placement {
        Placement::Local(origin) => {
            for mesh in &mut meshes {
                mesh.origin = origin;
            }
            origin
        }
        Placement::Flattened(origin) => {
            for vertex in &mut vertices {
                vertex.position = (origin + Vec3::from(vertex.position).as_dvec3()).as_vec3().to_array();
            }
            origin
        }
        Placement::Tiles(origin) => {
            use citystream_dataset::tiled::{read_tile_geometry, TiledScene};
            use citystream_dataset::tiles::TileTree;
            let mut moved = dataset.scene.clone();
            moved.origin = (DVec3::from(moved.origin) + origin).to_array();
            let tiled = TiledScene::of(&moved, 1)?;
            let limits = tiled.limits(dataset.textures.len());
            let path = std::path::Path::new("tiles.bin");
            let tree = TileTree::decode(path, &tiled.tree.encode(path, limits)?, limits)?;
            ensure!(tree.tiles.len() > 1, "the tiny city is one tile");
            eprintln!("the tiny city in {} tiles", tree.tiles.len());
            let tiles = read_tile_geometry(std::path::Path::new("geometry.pack"), &tree, &tiled.pack)?;
            // The frame the other placements' cameras are given in: the scene's own origin.
            (vertices, indices, meshes) =
                tiled_city_geometry(&tree, &tiles, &dataset.textures, DVec3::from(dataset.scene.origin))?;
            origin
        }
    };
    let compactor = FeedbackCompactor::new(&device, &mut commands, meshes.len() as u32, 1)?;
    let mut renderer = CityRenderer::new(&device, &mut commands, &vertices, &indices, meshes, &cache, &compactor)?;
    let bounds = &dataset.scene.bounds;
    let size = Vec3::from(bounds.max) - Vec3::from(bounds.min);
    let centre = Vec3::from(bounds.center()).as_dvec3();
    if culled {
        renderer.enable_culling(&mut commands, &vertices, &indices, 1)?;
    }
    let target = RenderTarget::new(&device, SIZE, SIZE)?;
    let feedback_target = RenderTarget::new(&device, SIZE / 4, SIZE / 4)?;
    let view = FeedbackView {
        margin: 0.25,
        foreground_distance: 50.0,
    };
    let mut images = Vec::new();
    let mut meshes_culled = 0;
    for (eye, aside) in relative_path(size) {
        let camera = Camera {
            eye: origin + centre + eye,
            target: origin + centre + aside,
            fov_y: 60f32.to_radians(),
            near: 0.5,
        };
        let cmd = commands.begin()?;
        // The feedback pass builds the depth pyramid the culling tests boxes against.
        renderer.record_feedback(cmd, &feedback_target, &camera, &view, SIZE)?;
        // Unlit, and without the colormap blend: the sampled texels as they are.
        renderer.record_visible(cmd, &target, &camera, 0.0, false)?;
        commands.submit_and_wait(&[])?;
        images.push(target.read_pixels()?);
        if let Some(stats) = renderer.cull_stats(0)? {
            meshes_culled += u64::from(stats.meshes_culled);
        }
        // Reset the feedback array for the next frame: a compaction that keeps nothing.
        let cmd = commands.begin()?;
        compactor.record_compact(cmd, u32::MAX, 0)?;
        commands.submit_and_wait(&[])?;
    }
    drop(renderer);
    assert_no_validation_errors(&device)?;
    Ok((images, meshes_culled))
}

/// Pixels of `a` and `b` whose channels differ by more than one 8-bit step, and the
/// largest difference.
fn differing_pixels(a: &image::RgbaImage, b: &image::RgbaImage) -> (usize, u8) {
    let comparison = citystream_tests::count_differences(a, b, 1);
    (comparison.mismatched, comparison.max_difference)
}

#[test]
fn a_small_city_a_thousand_kilometres_out_looks_as_it_does_at_the_origin() -> Result<()> {
    // The tiny generated city, drawn with level 0 of every texture resident, along the same
    // path relative to it: at the scene's origin, and with its meshes' local origins 1,000
    // km out. The two images of every frame agree within one 8-bit step per channel but for
    // at most one pixel in 10,000: the f32 arithmetic of the two runs rounds differently by
    // micrometres, and where a pixel centre lies within the rasteriser's 1/256-pixel snap of
    // an edge (or a texel boundary) that flips it. The same city nudged by a micrometre at
    // home flips pixels alike (reported beside). With its vertices moved 1,000 km out in
    // f32 instead (one scene origin, as before local origins), where an f32 position is a
    // multiple of 6.25 cm, thousands of pixels a frame differ.
    const MOST_DIFFERING: usize = (SIZE * SIZE / 10_000) as usize;
    let base = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("far_from_origin_city");
    let dir = citystream_tests::tiny_rgba8_city(&base)?;
    let (home, _) = fly_small_city(&dir, Placement::Local(DVec3::ZERO), false)?;
    let (nudged, _) = fly_small_city(&dir, Placement::Local(DVec3::new(1e-6, 1e-6, -1e-6)), false)?;
    let (far, _) = fly_small_city(&dir, Placement::Local(FAR_ORIGIN), false)?;
    let (far_culled, meshes_culled) = fly_small_city(&dir, Placement::Local(FAR_ORIGIN), true)?;
    let (flattened, _) = fly_small_city(&dir, Placement::Flattened(FAR_ORIGIN), false)?;
    eprintln!("1,000 km out the culling left {meshes_culled} meshes undrawn over the frames");
    // Culled and unculled images compared below mean something only if culling culls.
    ensure!(meshes_culled > 0, "the culling drew every mesh of every frame");
    let mut failures = Vec::new();
    let mut flattened_differing = 0;
    for (frame, (((home, nudged), far), flattened)) in home.iter().zip(&nudged).zip(&far).zip(&flattened).enumerate() {
        let sky = home.pixels().filter(|p| p.0 == home.get_pixel(0, 0).0).count();
        ensure!(
            sky < (SIZE * SIZE / 2) as usize,
            "frame {frame}: the view must show the city, not sky ({sky} sky pixels)"
        );
        // Culling 1,000 km out hides nothing the view shows: its boxes are the vertices in
        // the scene's frame rounded outwards, so an f32 box is never smaller than the mesh.
        ensure!(
            far_culled[frame] == *far,
            "frame {frame}: 1,000 km out the culled image differs from the unculled one in {} pixels",
            differing_pixels(&far_culled[frame], far).0
        );
        let (differing, worst) = differing_pixels(home, far);
        let (jitter, _) = differing_pixels(home, nudged);
        let (moved, moved_worst) = differing_pixels(home, flattened);
        eprintln!(
            "frame {frame}: local origins 1,000 km out: {differing} pixels differ by more than one step \
             (largest difference {worst}); nudged a micrometre at home: {jitter}; one f32 frame 1,000 km \
             out: {moved} (largest {moved_worst})"
        );
        flattened_differing += moved;
        if differing > MOST_DIFFERING {
            failures.push(format!("frame {frame}: {differing} pixels, largest difference {worst}"));
            let out = base.join("diff");
            std::fs::create_dir_all(&out)?;
            home.save(out.join(format!("home-{frame}.png")))?;
            far.save(out.join(format!("far-{frame}.png")))?;
        }
    }
    // The comparison means something only if one f32 frame so far out shows.
    ensure!(
        flattened_differing > 100 * MOST_DIFFERING * home.len(),
        "the city flattened into one f32 frame 1,000 km out differs in only {flattened_differing} pixels"
    );
    ensure!(failures.is_empty(), "{}", failures.join("\n"));
    Ok(())
}

#[test]
fn a_small_city_drawn_from_its_tiles_a_thousand_kilometres_out_looks_as_it_does_at_home() -> Result<()> {
    // Dataset format 4's path for the same small city: its scene cut into leaf tiles, each
    // tile's positions relative to its own origin, drawn from the tiles read back. At home
    // and with the whole city 1,000 km out, every frame agrees with the scene drawn at home
    // within one 8-bit step but for at most one pixel in 10,000, as the meshes' own origins
    // do (the test above): the tiles' positions are rounded around their tiles' origins
    // instead of the scene's, by micrometres.
    const MOST_DIFFERING: usize = (SIZE * SIZE / 10_000) as usize;
    let base = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("far_from_origin_tiles");
    let dir = citystream_tests::tiny_rgba8_city(&base)?;
    let (home, _) = fly_small_city(&dir, Placement::Local(DVec3::ZERO), false)?;
    let mut failures = Vec::new();
    for (name, origin) in [("at home", DVec3::ZERO), ("1,000 km out", FAR_ORIGIN)] {
        let (tiled, _) = fly_small_city(&dir, Placement::Tiles(origin), false)?;
        for (frame, (home, tiled)) in home.iter().zip(&tiled).enumerate() {
            let (differing, worst) = differing_pixels(home, tiled);
            eprintln!(
                "{name}, frame {frame}: drawn from its tiles, {differing} pixels differ by more than one step \
                 (largest difference {worst})"
            );
            if differing > MOST_DIFFERING {
                failures.push(format!(
                    "{name}, frame {frame}: {differing} pixels, largest difference {worst}"
                ));
            }
        }
    }
    ensure!(failures.is_empty(), "{}", failures.join("\n"));
    Ok(())
}
