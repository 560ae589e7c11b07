//! Depth precision over a city-sized extent: two parallel textured slabs 0.5 m apart, seen
//! from 10 km and from 100 m, head-on and obliquely, over a ground 40 km across. The nearer
//! slab wins every pixel in the visible pass, unculled and culled (Hi-Z), and the culled
//! and unculled images and depths are identical. Synchronization validation on; any message
//! fails. (With the standard projection and the near plane of a 40 km extent, 4 m, the far
//! slab showed through on 34 and 40 pixels of the views from 10 km.)

use anyhow::{ensure, Result};
use citystream_dataset::TextureFormat;
use citystream_engine::city::{near_plane, Camera, CityMesh, CityRenderer, FeedbackView};
use citystream_engine::commands::CommandContext;
use citystream_engine::feedback::FeedbackCompactor;
use citystream_engine::gpu_types::Vertex;
use citystream_engine::target::RenderTarget;
use citystream_engine::texture_cache::GpuTextureCache;
use citystream_tests::{assert_no_validation_errors, sync_validated_device, test_cache_config, QuadMeshes};
use glam::Vec3;

const WIDTH: u32 = 256;
const HEIGHT: u32 = 144;
/// The ground's side: the scene's extent, as a Berlin-sized city's.
const EXTENT: f32 = 40_000.0;
/// The gap between the slabs, metres.
const GAP: f32 = 0.5;
/// Colormap colours: nothing is resident, so each mesh shows its texture's.
const NEAR: [u8; 4] = [255, 0, 0, 255];
const FAR: [u8; 4] = [0, 0, 255, 255];
const GROUND: [u8; 4] = [0, 255, 0, 255];

/// The near slab (texture 0, 3 km square, in the plane z = 0, facing −z), the far slab
/// (texture 1, 0.5 m behind it and 100 m smaller each way, so that from these views it
/// could show only through the near one) and the ground (texture 2).
fn scene() -> (Vec<Vertex>, Vec<u32>, Vec<CityMesh>) {
    let mut quads = QuadMeshes::default();
    let mut quad = |corners: [Vec3; 4], normal: Vec3, texture: u32| quads.push(corners, normal, texture, (256, 256));
    let slab = |half: f32, low: f32, high: f32, z: f32| {
        [
            Vec3::new(-half, low, z),
            Vec3::new(half, low, z),
            Vec3::new(half, high, z),
            Vec3::new(-half, high, z),
        ]
    };
    quad(slab(1_500.0, 0.0, 3_000.0, 0.0), -Vec3::Z, 0);
    quad(slab(1_400.0, 100.0, 2_900.0, GAP), -Vec3::Z, 1);
    let h = EXTENT * 0.5;
    quad(
        [
            Vec3::new(-h, 0.0, h),
            Vec3::new(h, 0.0, h),
            Vec3::new(h, 0.0, -h),
            Vec3::new(-h, 0.0, -h),
        ],
        Vec3::Y,
        2,
    );
    (quads.vertices, quads.indices, quads.meshes)
}

/// From `distance` in front of the slab's centre line, turned `yaw_deg` about the vertical,
/// looking at a point on the near slab.
fn view(distance: f32, yaw_deg: f32) -> Camera {
    let yaw = yaw_deg.to_radians();
    let target = Vec3::new(0.0, 1_000.0_f32.min(distance), 0.0);
    let eye = target + Vec3::new(-yaw.sin(), 0.1, -yaw.cos()) * distance;
    // The near plane the flythrough chooses over this scene's bounds.
    let h = EXTENT * 0.5;
    Camera {
        eye: eye.as_dvec3(),
        target: target.as_dvec3(),
        fov_y: 60f32.to_radians(),
        near: near_plane(eye.as_dvec3(), Vec3::new(-h, 0.0, -h), Vec3::new(h, 3_000.0, h)),
    }
}

#[test]
fn the_nearer_of_two_slabs_half_a_metre_apart_wins_every_pixel_from_10_km_and_100_m() -> Result<()> {
    let (vertices, indices, meshes) = scene();
    let device = sync_validated_device()?;
    let mut commands = CommandContext::new(&device, "depth precision test")?;
    let cache = GpuTextureCache::new(
        &device,
        &mut commands,
        &test_cache_config(&[TextureFormat::Bc1], 3),
        &[NEAR, FAR, GROUND],
    )?;
    let mesh_count = meshes.len() as u32;
    let compactor = FeedbackCompactor::new(&device, &mut commands, mesh_count, mesh_count)?;
    let mut renderer = CityRenderer::new(&device, &mut commands, &vertices, &indices, meshes, &cache, &compactor)?;
    renderer.enable_culling(&mut commands, &vertices, &indices, 1)?;
    let target = RenderTarget::new(&device, WIDTH, HEIGHT)?;
    let feedback_target = RenderTarget::new(&device, WIDTH / 4, HEIGHT / 4)?;
    let feedback = FeedbackView::default();
    let mut render = |renderer: &CityRenderer, camera: &Camera| -> Result<(image::RgbaImage, Vec<f32>)> {
        let cmd = commands.begin()?;
        // The feedback first: culling's early phase draws what the last frame's listed.
        renderer.record_feedback(cmd, &feedback_target, camera, &feedback, HEIGHT)?;
        renderer.record_visible(cmd, &target, camera, 0.0, true)?;
        commands.submit_and_wait(&[])?;
        Ok((target.read_pixels()?, target.read_depth(&device, &mut commands)?))
    };
    let mut failures = Vec::new();
    for distance in [10_000.0, 100.0] {
        for yaw in [0.0, 30.0, 60.0] {
            let camera = view(distance, yaw);
            renderer.set_culling(false)?;
            let (unculled, unculled_depth) = render(&renderer, &camera)?;
            renderer.set_culling(true)?;
            // Twice: the second culled frame's early phase draws what the first listed.
            render(&renderer, &camera)?;
            let (culled, culled_depth) = render(&renderer, &camera)?;
            for (name, pixels) in [("unculled", &unculled), ("culled", &culled)] {
                let shows = |colour: [u8; 4]| pixels.pixels().filter(|p| p.0 == colour).count();
                let (near, far) = (shows(NEAR), shows(FAR));
                let total = (WIDTH * HEIGHT) as usize;
                // The slab must be in view for the test to mean anything.
                ensure!(
                    near * 100 > total,
                    "{distance} m, {yaw}°: the near slab covers {near} of {total} pixels"
                );
                if far > 0 {
                    failures.push(format!(
                        "{distance} m, yaw {yaw}°, {name}: the far slab shows through on {far} of {near} + {far} pixels"
                    ));
                }
            }
            if unculled != culled {
                let differ = unculled.pixels().zip(culled.pixels()).filter(|(a, b)| a != b).count();
                failures.push(format!(
                    "{distance} m, yaw {yaw}°: {differ} pixels differ culled and unculled"
                ));
            }
            let depth_differs = unculled_depth
                .iter()
                .zip(&culled_depth)
                .filter(|(a, b)| a.to_bits() != b.to_bits())
                .count();
            if depth_differs > 0 {
                failures.push(format!(
                    "{distance} m, yaw {yaw}°: {depth_differs} depths differ culled and unculled"
                ));
            }
        }
    }
    ensure!(failures.is_empty(), "{}", failures.join("\n"));
    drop(renderer);
    assert_no_validation_errors(&device)
}
