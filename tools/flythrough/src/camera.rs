//! The camera of a flight: the path it follows, the engine's camera at a pose, and what
//! the ground layer is sized by (its focal length, the lowest eye).

use anyhow::{Context, Result};
use glam::Vec3;

use citystream_engine::city::{near_plane, Camera, NEAR_PLANE_MIN};
use citystream_streaming::bench::path::{standard_path, CameraPath, CameraPose, DEFAULT_STANDARD_DURATION_S};

use super::args::FIXED_STEP_MS;

/// The camera path the run follows: the standard path of the dataset or a file.
pub(crate) fn camera_path(name: &str, scene: &citystream_dataset::Scene) -> Result<CameraPath> {
    if name == "standard" {
        standard_path(scene, DEFAULT_STANDARD_DURATION_S).context("deriving the standard path of the dataset")
    } else {
        CameraPath::load(name).with_context(|| format!("reading the camera path {name}"))
    }
}

/// `camera`'s focal length in pixels for a view `height_px` tall.
pub(crate) fn focal_px(height_px: u32, camera: &Camera) -> f64 {
    f64::from(height_px) / (2.0 * f64::from(camera.fov_y * 0.5).tan())
}

/// The lowest the eye of `path` comes above the ground plane at `ground_y` within
/// `duration_s` (sampled at the fixed clock's step), never below the least near plane:
/// nothing nearer is drawn.
pub(crate) fn lowest_eye_height(path: &CameraPath, duration_s: f64, ground_y: f32) -> f64 {
    let steps = (duration_s * 1000.0 / FIXED_STEP_MS).ceil().max(0.0) as u64;
    let lowest = (0..=steps)
        .map(|i| path.sample_between(None, i as f64 * FIXED_STEP_MS / 1000.0).position[1] - ground_y)
        .fold(f32::INFINITY, f32::min);
    f64::from(lowest.max(NEAR_PLANE_MIN))
}

/// The scene's bounds, which a camera's near plane is chosen from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct SceneBox {
    pub(crate) low: Vec3,
    pub(crate) high: Vec3,
}

impl SceneBox {
    pub(crate) fn of(scene: &citystream_dataset::Scene) -> Self {
        Self {
            low: Vec3::from(scene.bounds.min),
            high: Vec3::from(scene.bounds.max),
        }
    }
}

/// A camera at `pose` over `scene`, its near plane chosen from both ([`near_plane`]).
pub(crate) fn pose_camera(pose: &CameraPose, scene: SceneBox) -> Camera {
    let eye = Vec3::from(pose.position).as_dvec3();
    Camera {
        eye,
        target: Vec3::from(pose.look_at).as_dvec3(),
        fov_y: 60f32.to_radians(),
        near: near_plane(eye, scene.low, scene.high),
    }
}
