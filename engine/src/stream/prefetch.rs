//! Where the camera will be, for the prefetch pass
//! ([`TextureStreamer::record_prefetch_resolve`](super::TextureStreamer::record_prefetch_resolve)).
//!
//! A host that knows its camera's path (a replay, a benchmark) passes the path's pose a
//! lead time ahead. A host flown by hand passes [`MotionPredictor::predict`]: the latest
//! frames' velocity and turn rate carried forward. Either way the host renders the
//! prefetch pass from that camera.

use std::collections::VecDeque;

use glam::DVec3;

use crate::city::Camera;

/// Frames whose motion the prediction follows: about a tenth of a second at 60 Hz, long
/// enough that one uneven frame does not steer it, short enough to follow a turn.
pub const MOTION_FRAMES: usize = 6;

/// A step this many times longer than the mean of the frames before it is a cut (a
/// teleport, a new view): the motion before it says nothing of the motion after.
pub const CUT_FACTOR: f32 = 8.0;

/// The most a prediction turns, radians: a turn rate carried far ahead wraps around.
pub const MAX_TURN: f32 = std::f32::consts::FRAC_PI_2;

/// Share of the lead time between two motion passes. The levels a pass requests stay
/// resident once loaded, and between passes spaced a quarter of the lead apart the
/// predicted view moves a quarter of the way the lead carries it, so each pass overlaps the
/// last by three quarters; a pass on every frame paid for the same requests again each
/// frame (docs/CONTROLLER.md, "Prefetch").
pub const MOTION_PASS_SPACING: f64 = 0.25;

/// Whether a prefetch pass looking ahead by motion (or along a known path, between its
/// cuts) is due at `now_s` (path seconds) with lead time `lead_s`, the last one at
/// `last_s`: at most one per [`MOTION_PASS_SPACING`] of the lead.
pub fn motion_pass_due(last_s: Option<f64>, now_s: f64, lead_s: f64) -> bool {
    last_s.is_none_or(|last| now_s - last >= MOTION_PASS_SPACING * lead_s)
}

/// One observed frame: when, where the eye was, where it looked.
#[derive(Clone, Copy, Debug)]
struct Sample {
    time_s: f64,
    eye: DVec3,
    /// Unit view direction.
    forward: DVec3,
    /// Distance to the target.
    reach: f64,
}

/// Extrapolates a camera's motion: velocity and turn rate over the latest
/// [`MOTION_FRAMES`] frames.
#[derive(Clone, Debug, Default)]
pub struct MotionPredictor {
    samples: VecDeque<Sample>,
}

impl MotionPredictor {
    /// A predictor with no history.
    pub fn new() -> Self {
        Self::default()
    }

    /// Records the camera of the frame at `time_s` (seconds, increasing). A camera with a
    /// non-finite or degenerate view, or a time not after the last one, is ignored; a cut
    /// ([`CUT_FACTOR`]) forgets the frames before it.
    pub fn observe(&mut self, time_s: f64, camera: &Camera) {
        let look = camera.target - camera.eye;
        let reach = look.length();
        if !(time_s.is_finite() && camera.eye.is_finite() && reach.is_finite() && reach > 0.0) {
            return;
        }
        let sample = Sample {
            time_s,
            eye: camera.eye,
            forward: look / reach,
            reach,
        };
        if let Some(last) = self.samples.back() {
            if time_s <= last.time_s {
                return;
            }
            let step = last.eye.distance(sample.eye);
            let steps = self.samples.len().saturating_sub(1);
            if steps > 0 {
                let mean = self
                    .samples
                    .iter()
                    .zip(self.samples.iter().skip(1))
                    .map(|(a, b)| a.eye.distance(b.eye))
                    .sum::<f64>()
                    / steps as f64;
                if step > f64::from(CUT_FACTOR) * mean && step > f64::from(f32::EPSILON) * reach.max(1.0) {
                    self.samples.clear();
                }
            }
        }
        self.samples.push_back(sample);
        while self.samples.len() > MOTION_FRAMES {
            self.samples.pop_front();
        }
    }

    /// Forgets every frame (a host that teleports its camera says so).
    pub fn reset(&mut self) {
        self.samples.clear();
    }

    /// `camera` as it will be `lead_s` seconds after the latest frame: its eye moved on by
    /// the recent velocity, its view turned by the recent turn rate (at most [`MAX_TURN`]),
    /// its target as far ahead as now. `None` before two frames since the last cut.
    pub fn predict(&self, camera: &Camera, lead_s: f64) -> Option<Camera> {
        let (first, last) = (self.samples.front()?, self.samples.back()?);
        let span = last.time_s - first.time_s;
        if span <= 0.0 || !lead_s.is_finite() || lead_s < 0.0 {
            return None;
        }
        let ahead = lead_s / span;
        let eye = last.eye + (last.eye - first.eye) * ahead;
        // The turn from the first frame's direction to the latest one's, carried on at the
        // same rate about the same axis.
        let axis = first.forward.cross(last.forward);
        let angle = first.forward.dot(last.forward).clamp(-1.0, 1.0).acos();
        let forward = if axis.length_squared() > 1e-12 && angle.is_finite() {
            let turn = (angle * ahead).min(f64::from(MAX_TURN));
            glam::DQuat::from_axis_angle(axis.normalize(), turn) * last.forward
        } else {
            last.forward
        };
        let predicted = Camera {
            eye,
            target: eye + forward * last.reach,
            ..*camera
        };
        (predicted.eye.is_finite() && predicted.target.is_finite()).then_some(predicted)
    }
}

/// The most the eye may come nearer to (or go further from) what it looks at, as a share
/// of the distance, before a view ahead needs a pass of its own: a quarter nearer needs
/// textures under half a level finer (log2(4/3) = 0.42), and a quarter further shows what
/// the view's feedback already covers with its 25 % margin.
pub const PREFETCH_MAX_DEPTH_SHARE: f32 = 0.25;

/// Whether the camera `ahead` sees enough that the view `now` does not (its feedback
/// taken with the field of view widened by `margin`, as `FeedbackView::margin`) to be worth
/// a prefetch pass: its view turned, plus its eye moved sideways, further than the margin
/// reaches beyond the visible view, or its eye moved along the view by more than
/// [`PREFETCH_MAX_DEPTH_SHARE`] of the distance to the target. Where the view's own
/// feedback covers the camera ahead, a pass would ask for nothing new, so the pass (and
/// its cost) comes where it pays: around cuts, fast turns and fast moves.
pub fn sees_beyond_margin(now: &Camera, ahead: &Camera, margin: f32) -> bool {
    let reach = (now.target - now.eye).length().max(f64::MIN_POSITIVE);
    let forward = |c: &Camera| (c.target - c.eye).normalize_or_zero();
    let (now_forward, moved) = (forward(now), ahead.eye - now.eye);
    let along = moved.dot(now_forward);
    let sideways = (moved - now_forward * along).length();
    let half = f64::from(now.fov_y * 0.5).clamp(0.0, 1.5);
    let beyond = ((1.0 + f64::from(margin.max(0.0))) * half.tan()).atan() - half;
    let turned = now_forward.dot(forward(ahead)).clamp(-1.0, 1.0).acos();
    let covered =
        turned + (sideways / reach).atan() <= beyond && along.abs() <= f64::from(PREFETCH_MAX_DEPTH_SHARE) * reach;
    !covered
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera(eye: DVec3, target: DVec3) -> Camera {
        Camera {
            eye,
            target,
            fov_y: 1.0,
            near: 0.1,
        }
    }

    #[test]
    fn only_a_view_beyond_the_margin_is_worth_a_pass() {
        let now = camera(DVec3::ZERO, DVec3::new(0.0, 0.0, -100.0));
        // A 60° view with a 25 % margin reaches 5.8° further each side.
        let turned = |deg: f64| {
            let a = deg.to_radians();
            camera(DVec3::ZERO, DVec3::new(a.sin(), 0.0, -a.cos()) * 100.0)
        };
        let wide = Camera {
            fov_y: 60f32.to_radians(),
            ..now
        };
        let with_fov = |c: Camera| Camera { fov_y: wide.fov_y, ..c };
        assert!(!sees_beyond_margin(&wide, &with_fov(turned(5.0)), 0.25));
        assert!(sees_beyond_margin(&wide, &with_fov(turned(7.0)), 0.25));
        // Sideways at 100 m from the target: 5 m (2.9°) is covered, 15 m (8.5°) is not; along
        // the view 20 m is, 30 m is not; a cut is not.
        let moved = |x: f64, z: f64| with_fov(camera(DVec3::new(x, 0.0, z), DVec3::new(x, 0.0, z - 100.0)));
        assert!(!sees_beyond_margin(&wide, &moved(5.0, 0.0), 0.25));
        assert!(sees_beyond_margin(&wide, &moved(15.0, 0.0), 0.25));
        assert!(!sees_beyond_margin(&wide, &moved(0.0, -20.0), 0.25));
        assert!(sees_beyond_margin(&wide, &moved(0.0, -30.0), 0.25));
        assert!(sees_beyond_margin(&wide, &moved(0.0, 30.0), 0.25));
        assert!(sees_beyond_margin(&wide, &moved(5000.0, 0.0), 0.25));
        assert!(!sees_beyond_margin(&wide, &wide, 0.25));
    }

    #[test]
    fn motion_passes_are_spaced_a_quarter_of_the_lead_apart() {
        assert!(motion_pass_due(None, 0.0, 0.5));
        assert!(!motion_pass_due(Some(1.0), 1.1, 0.5));
        assert!(motion_pass_due(Some(1.0), 1.125, 0.5));
        assert!(motion_pass_due(Some(1.0), 3.0, 0.5));
    }

    #[test]
    fn a_straight_flight_is_carried_on() {
        let mut motion = MotionPredictor::new();
        assert!(motion.predict(&camera(DVec3::ZERO, DVec3::X), 0.5).is_none());
        // 10 m/s along x, looking along x, 60 frames a second.
        for frame in 0..10 {
            let t = frame as f64 / 60.0;
            let eye = DVec3::new(10.0 * t, 5.0, 0.0);
            motion.observe(t, &camera(eye, eye + DVec3::X * 20.0));
        }
        let now = camera(DVec3::new(1.5, 5.0, 0.0), DVec3::new(21.5, 5.0, 0.0));
        let ahead = motion.predict(&now, 0.5).expect("two frames seen");
        assert!(
            ahead.eye.distance(DVec3::new(10.0 * 9.0 / 60.0 + 5.0, 5.0, 0.0)) < 1e-3,
            "{:?}",
            ahead.eye
        );
        assert!((ahead.target - ahead.eye).normalize().distance(DVec3::X) < 1e-5);
        assert_eq!(ahead.fov_y, now.fov_y);
    }

    #[test]
    fn a_turn_is_carried_on_at_its_rate_and_a_cut_forgets_the_motion() {
        let mut motion = MotionPredictor::new();
        // Standing still, turning about y at 1 rad/s.
        for frame in 0..6 {
            let t = frame as f64 / 60.0;
            let a = t;
            motion.observe(t, &camera(DVec3::ZERO, DVec3::new(a.cos(), 0.0, -a.sin()) * 10.0));
        }
        let now = camera(DVec3::ZERO, DVec3::X);
        let ahead = motion.predict(&now, 0.25).expect("seen");
        let expected = 5.0f64 / 60.0 + 0.25;
        let forward = (ahead.target - ahead.eye).normalize();
        assert!(
            forward.distance(DVec3::new(expected.cos(), 0.0, -expected.sin())) < 1e-4,
            "{forward:?}"
        );
        assert!(ahead.eye.length() < 1e-6);
        // Moving slowly, then a teleport: the jump is not taken for a velocity.
        let mut motion = MotionPredictor::new();
        for frame in 0..5 {
            let eye = DVec3::new(f64::from(frame) * 0.1, 0.0, 0.0);
            motion.observe(frame as f64 / 60.0, &camera(eye, eye + DVec3::Z));
        }
        let far = DVec3::new(5000.0, 0.0, 0.0);
        motion.observe(5.0 / 60.0, &camera(far, far + DVec3::Z));
        assert!(motion.predict(&camera(far, far + DVec3::Z), 1.0).is_none());
        motion.observe(6.0 / 60.0, &camera(far, far + DVec3::Z));
        let still = motion
            .predict(&camera(far, far + DVec3::Z), 1.0)
            .expect("two frames since the cut");
        assert!(still.eye.distance(far) < 1e-3);
    }
}
