//! `--depth-slabs METRES`: a depth-precision probe placed in the city being flown. Two
//! parallel square slabs 0.5 m apart face the first pose's eye from METRES away, in the
//! heading it looks along and 20° above the horizon (over the city, where nothing else
//! stands), the nearer drawn with the dataset's first texture and the farther with its
//! second. On every measured frame the error reference draws the view from that frame's eye
//! towards the slabs (the culled view, when culling is on) and its texture-id pass says
//! which texture each pixel shows: a pixel of the farther slab inside the nearer's outline
//! means depth did not resolve the half metre there, and the run fails
//! (docs/ARCHITECTURE.md, "Numerical choices").

use anyhow::{bail, ensure, Result};
use glam::{Vec3, Vec4Swizzles};
use serde::Serialize;

use citystream_dataset::{Dataset, Scene};
use citystream_engine::city::{texture_of_id_pixel, Camera};
use citystream_streaming::bench::path::CameraPath;

/// How far behind the nearer slab the farther one lies, metres.
pub(crate) const SLAB_GAP_M: f32 = 0.5;
/// The slabs' centre lies this far above the horizon seen from the first eye: above any
/// city's roofs at the distances the probe is for, so nothing stands in front.
const ELEVATION_DEG: f32 = 20.0;
/// A slab's side as a fraction of its distance: about 190 pixels of a 2160-pixel-high
/// view with a 60° field of view, 30 of a 360-pixel one.
const SIDE_PER_DISTANCE: f32 = 0.1;
/// Pixels this close to the nearer slab's outline are not judged: the rasteriser may give
/// an edge pixel to either slab.
const EDGE_MARGIN_PX: f32 = 2.0;

/// The slabs placed in a scene.
#[derive(Clone, Debug)]
pub(crate) struct DepthSlabs {
    pub(crate) distance_m: f64,
    /// The path the slabs were placed from, derived before they were added (the standard
    /// path follows the meshes' bounds, which the slabs would widen).
    pub(crate) path: CameraPath,
    /// The nearer slab's corners, in order around it.
    near_corners: [Vec3; 4],
    /// The farther slab's centre: which side of the nearer one it lies on.
    far_centre: Vec3,
    near_texture: u32,
    far_texture: u32,
}

/// What the probe saw over a run: `summary.json`'s `depth_slabs`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub(crate) struct SlabCounts {
    pub(crate) distance_m: f64,
    pub(crate) frames_checked: u32,
    /// Pixels inside the nearer slab's outline showing it.
    pub(crate) near_pixels: u64,
    /// Showing the farther slab: depth lost the half metre there.
    pub(crate) far_pixels: u64,
    /// Showing anything else (a mesh in front of both).
    pub(crate) other_pixels: u64,
}

impl DepthSlabs {
    /// Adds the slabs to `dataset`'s scene, placed from the first pose of `path` (derived
    /// from the city alone, and flown as it is): two meshes after the city's. The scene's
    /// bounds stay the city's: the near plane and the ground are sized by the city, not by
    /// the probe.
    pub(crate) fn add(dataset: &mut Dataset, path: CameraPath, distance_m: f64) -> Result<Self> {
        let pose = path.sample_between(None, 0.0);
        ensure!(
            dataset.textures.len() >= 2,
            "--depth-slabs draws the slabs with the dataset's first two textures; {} has {}",
            dataset.dir().display(),
            dataset.textures.len()
        );
        let eye = Vec3::from(pose.position);
        let view = (Vec3::from(pose.look_at) - eye).normalize_or_zero();
        if view == Vec3::ZERO {
            bail!("--depth-slabs: the path's first pose looks nowhere");
        }
        // The heading the eye looks along (north, −z, when it looks straight down or up).
        let heading = Vec3::new(view.x, 0.0, view.z).try_normalize().unwrap_or(Vec3::NEG_Z);
        let elevation = ELEVATION_DEG.to_radians();
        let towards = heading * elevation.cos() + Vec3::Y * elevation.sin();
        let right = towards.cross(Vec3::Y).normalize();
        let distance = distance_m as f32;
        let half = 0.5 * SIDE_PER_DISTANCE * distance;
        let (across, along) = (right * half, right.cross(towards).normalize() * half);
        let corners_at = |centre: Vec3| {
            [
                centre - across - along,
                centre + across - along,
                centre + across + along,
                centre - across + along,
            ]
        };
        let near_centre = eye + towards * distance;
        let near_corners = corners_at(near_centre);
        let far_corners = corners_at(near_centre + towards * SLAB_GAP_M);
        let scene = &mut dataset.scene;
        let bounds = scene.bounds;
        let (near_texture, far_texture) = (0, 1);
        for (corners, texture) in [(near_corners, near_texture), (far_corners, far_texture)] {
            push_quad(scene, corners, -towards, texture)?;
        }
        scene.bounds = bounds;
        Ok(Self {
            distance_m,
            path,
            far_centre: near_centre + towards * SLAB_GAP_M,
            near_corners,
            near_texture,
            far_texture,
        })
    }

    /// The view from `frame`'s eye towards the nearer slab's centre, with `frame`'s field of
    /// view and near plane: what the probe is checked through.
    pub(crate) fn probe_camera(&self, frame: &Camera) -> Camera {
        let centre = self.near_corners.iter().copied().sum::<Vec3>() * 0.25;
        Camera {
            target: centre.as_dvec3(),
            ..*frame
        }
    }

    /// Counts what the pixels inside the nearer slab's outline show in `ids` (a texture-id
    /// image, [`texture_of_id_pixel`]) drawn for `camera`, into `counts`.
    pub(crate) fn check(&self, ids: &image::RgbaImage, camera: &Camera, counts: &mut SlabCounts) {
        counts.distance_m = self.distance_m;
        // An eye at or past the nearer slab's plane sees the farther one first (or edge on):
        // the probe says nothing about depth from there.
        let centre = self.near_corners.iter().copied().sum::<Vec3>().as_dvec3() * 0.25;
        let normal = (self.near_corners[1] - self.near_corners[0])
            .cross(self.near_corners[3] - self.near_corners[0])
            .as_dvec3();
        let far_side = (self.far_centre.as_dvec3() - centre).dot(normal).signum();
        if (camera.eye - centre).dot(normal) * far_side >= 0.0 {
            return;
        }
        let (width, height) = (ids.width() as f32, ids.height() as f32);
        // In f64: the outline is judged to a fraction of a pixel, however far out.
        let view_proj = camera.view_projection_f64(width / height, 0.0);
        let mut outline = [[0.0f32; 2]; 4];
        for (corner, pixel) in self.near_corners.iter().zip(&mut outline) {
            let clip = view_proj * corner.as_dvec3().extend(1.0);
            if clip.w <= 0.0 {
                // Behind the eye: this frame cannot see the probe.
                return;
            }
            let ndc = clip.xy() / clip.w;
            *pixel = [
                ((ndc.x * 0.5 + 0.5) * f64::from(width)) as f32,
                ((ndc.y * 0.5 + 0.5) * f64::from(height)) as f32,
            ];
        }
        counts.frames_checked += 1;
        for y in 0..ids.height() {
            for x in 0..ids.width() {
                let centre = [x as f32 + 0.5, y as f32 + 0.5];
                if !inside_by(&outline, centre, EDGE_MARGIN_PX) {
                    continue;
                }
                match texture_of_id_pixel(ids.get_pixel(x, y).0) {
                    Some(t) if t == self.near_texture => counts.near_pixels += 1,
                    Some(t) if t == self.far_texture => counts.far_pixels += 1,
                    _ => counts.other_pixels += 1,
                }
            }
        }
    }
}

/// A two-triangle square of `texture` with `corners` in order around it, facing `normal`.
fn push_quad(scene: &mut Scene, corners: [Vec3; 4], normal: Vec3, texture: u32) -> Result<()> {
    let positions = corners.map(|c| c.to_array());
    let normals = [normal.to_array(); 4];
    let uvs = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
    scene.push_mesh(texture, &positions, &normals, &uvs, &[0, 1, 2, 0, 2, 3])?;
    Ok(())
}

/// Whether `point` lies inside the convex polygon `outline` by at least `margin` from
/// every edge, on the side the polygon's winding (either) puts its inside.
fn inside_by(outline: &[[f32; 2]; 4], point: [f32; 2], margin: f32) -> bool {
    let area: f32 = (0..4)
        .map(|i| {
            let (a, b) = (outline[i], outline[(i + 1) % 4]);
            a[0] * b[1] - b[0] * a[1]
        })
        .sum();
    if area == 0.0 || !area.is_finite() {
        return false;
    }
    (0..4).all(|i| {
        let (a, b) = (outline[i], outline[(i + 1) % 4]);
        let edge = [b[0] - a[0], b[1] - a[1]];
        let length = edge[0].hypot(edge[1]);
        let distance = area.signum() * (edge[0] * (point[1] - a[1]) - edge[1] * (point[0] - a[0])) / length;
        length > 0.0 && distance >= margin
    })
}

/// `--depth-slabs`: finite metres from 10 m to 1,000 km.
pub(crate) fn parse_depth_slabs_m(text: &str) -> std::result::Result<f64, String> {
    match text.parse::<f64>() {
        Ok(m) if m.is_finite() && (10.0..=1e6).contains(&m) => Ok(m),
        Ok(m) => Err(format!("{m} m is not a distance from 10 m to 1,000 km")),
        Err(_) => Err(format!("`{text}` is not a number of metres")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn id_pixel(texture: Option<u32>) -> image::Rgba<u8> {
        let id = texture.map_or(0, |t| t + 1);
        image::Rgba([id as u8, (id >> 8) as u8, (id >> 16) as u8, 255])
    }

    fn camera() -> Camera {
        Camera {
            eye: glam::DVec3::ZERO,
            target: glam::DVec3::new(0.0, 0.0, -1.0),
            fov_y: 60f32.to_radians(),
            near: 1.0,
        }
    }

    /// Slabs facing the eye at the origin, straight ahead (no elevation), 100 m out.
    fn slabs_ahead() -> DepthSlabs {
        let half = 5.0;
        DepthSlabs {
            distance_m: 100.0,
            path: CameraPath::from_json(
                r#"{"version": 1, "keyframes": [{"t": 0, "position": [0, 0, 0], "look_at": [0, 0, -1]}]}"#,
            )
            .expect("a path"),
            near_corners: [
                Vec3::new(-half, -half, -100.0),
                Vec3::new(half, -half, -100.0),
                Vec3::new(half, half, -100.0),
                Vec3::new(-half, half, -100.0),
            ],
            far_centre: Vec3::new(0.0, 0.0, -100.5),
            near_texture: 0,
            far_texture: 1,
        }
    }

    #[test]
    fn pixels_inside_the_outline_are_counted_by_what_they_show() {
        // A 10 m square 100 m ahead in a 200-pixel view: 2 · 100 · tan 30° = 115.5 m high,
        // so the square spans 17.3 pixels each way around the centre.
        let slabs = slabs_ahead();
        let mut ids = image::RgbaImage::from_pixel(200, 200, id_pixel(Some(0)));
        let mut counts = SlabCounts::default();
        slabs.check(&ids, &camera(), &mut counts);
        let inside = counts.near_pixels;
        assert!((150..=200).contains(&inside), "{counts:?}");
        assert_eq!((counts.far_pixels, counts.other_pixels), (0, 0));
        // The farther slab at the centre and a mesh in front at one pixel; the sky outside
        // the outline counts for nothing.
        ids.put_pixel(100, 100, id_pixel(Some(1)));
        ids.put_pixel(101, 100, id_pixel(Some(7)));
        ids.put_pixel(0, 0, id_pixel(Some(1)));
        let mut counts = SlabCounts::default();
        slabs.check(&ids, &camera(), &mut counts);
        assert_eq!(
            (counts.near_pixels, counts.far_pixels, counts.other_pixels),
            (inside - 2, 1, 1)
        );
        assert_eq!(counts.frames_checked, 1);
    }

    #[test]
    fn a_frame_looking_away_checks_nothing() {
        let slabs = slabs_ahead();
        let ids = image::RgbaImage::from_pixel(64, 64, id_pixel(Some(1)));
        let mut away = camera();
        away.target = glam::DVec3::new(0.0, 0.0, 1.0);
        let mut counts = SlabCounts::default();
        slabs.check(&ids, &away, &mut counts);
        assert_eq!(
            counts,
            SlabCounts {
                distance_m: 100.0,
                ..SlabCounts::default()
            }
        );
    }

    #[test]
    fn an_eye_past_the_nearer_slab_checks_nothing() {
        // From behind the slabs the farther is in front: not a depth failure.
        let slabs = slabs_ahead();
        let ids = image::RgbaImage::from_pixel(64, 64, id_pixel(Some(1)));
        let behind = Camera {
            eye: glam::DVec3::new(0.0, 0.0, -150.0),
            target: glam::DVec3::new(0.0, 0.0, -100.0),
            ..camera()
        };
        let mut counts = SlabCounts::default();
        slabs.check(&ids, &behind, &mut counts);
        assert_eq!(counts.frames_checked, 0);
        assert_eq!(counts.far_pixels, 0);
    }

    #[test]
    fn the_distance_is_checked() {
        assert_eq!(parse_depth_slabs_m("10000"), Ok(10_000.0));
        for bad in ["5", "NaN", "inf", "2e6", "ten"] {
            assert!(parse_depth_slabs_m(bad).is_err(), "{bad}");
        }
    }
}
