//! Where the camera will be, for the prefetch pass
//! ([`TextureStreamer::record_prefetch_resolve`](super::TextureStreamer::record_prefetch_resolve)).
//!
//! A host that knows its camera's path (a replay, a benchmark) passes the path's pose a
//! lead time ahead. A host flown by hand passes [`MotionPredictor::predict`]: the latest
//! frames' velocity and turn rate carried forward. Either way the host renders the
//! prefetch pass from that camera.

use std::collections::VecDeque;

use glam::Vec3;

use crate::city::Camera;

/// Frames whose motion the prediction follows: about a tenth of a second at 60 Hz, long
/// enough that one uneven frame does not steer it, short enough to follow a turn.
pub const MOTION_FRAMES: usize = 6;

/// A step this many times longer than the mean of the frames before it is a cut (a
/// teleport, a new view): the motion before it says nothing of the motion after.
pub const CUT_FACTOR: f32 = 8.0;

/// The most a prediction turns, radians: a turn rate carried far ahead wraps around.
pub const MAX_TURN: f32 = std::f32::consts::FRAC_PI_2;

/// One observed frame: when, where the eye was, where it looked.
#[derive(Clone, Copy, Debug)]
struct Sample {
    time_s: f64,
    eye: Vec3,
    /// Unit view direction.
    forward: Vec3,
    /// Distance to the target.
    reach: f32,
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
                    .sum::<f32>()
                    / steps as f32;
                if step > CUT_FACTOR * mean && step > f32::EPSILON * reach.max(1.0) {
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
        let ahead = (lead_s / span) as f32;
        let eye = last.eye + (last.eye - first.eye) * ahead;
        // The turn from the first frame's direction to the latest one's, carried on at the
        // same rate about the same axis.
        let axis = first.forward.cross(last.forward);
        let angle = first.forward.dot(last.forward).clamp(-1.0, 1.0).acos();
        let forward = if axis.length_squared() > 1e-12 && angle.is_finite() {
            let turn = (angle * ahead).min(MAX_TURN);
            glam::Quat::from_axis_angle(axis.normalize(), turn) * last.forward
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

#[cfg(test)]
mod tests {
    use super::*;

    fn camera(eye: Vec3, target: Vec3) -> Camera {
        Camera {
            eye,
            target,
            fov_y: 1.0,
            near: 0.1,
            far: 1000.0,
        }
    }

    #[test]
    fn a_straight_flight_is_carried_on() {
        let mut motion = MotionPredictor::new();
        assert!(motion.predict(&camera(Vec3::ZERO, Vec3::X), 0.5).is_none());
        // 10 m/s along x, looking along x, 60 frames a second.
        for frame in 0..10 {
            let t = frame as f64 / 60.0;
            let eye = Vec3::new(10.0 * t as f32, 5.0, 0.0);
            motion.observe(t, &camera(eye, eye + Vec3::X * 20.0));
        }
        let now = camera(Vec3::new(1.5, 5.0, 0.0), Vec3::new(21.5, 5.0, 0.0));
        let ahead = motion.predict(&now, 0.5).expect("two frames seen");
        assert!(
            ahead.eye.distance(Vec3::new(10.0 * 9.0 / 60.0 + 5.0, 5.0, 0.0)) < 1e-3,
            "{:?}",
            ahead.eye
        );
        assert!((ahead.target - ahead.eye).normalize().distance(Vec3::X) < 1e-5);
        assert_eq!(ahead.fov_y, now.fov_y);
    }

    #[test]
    fn a_turn_is_carried_on_at_its_rate_and_a_cut_forgets_the_motion() {
        let mut motion = MotionPredictor::new();
        // Standing still, turning about y at 1 rad/s.
        for frame in 0..6 {
            let t = frame as f64 / 60.0;
            let a = t as f32;
            motion.observe(t, &camera(Vec3::ZERO, Vec3::new(a.cos(), 0.0, -a.sin()) * 10.0));
        }
        let now = camera(Vec3::ZERO, Vec3::X);
        let ahead = motion.predict(&now, 0.25).expect("seen");
        let expected = 5.0f32 / 60.0 + 0.25;
        let forward = (ahead.target - ahead.eye).normalize();
        assert!(
            forward.distance(Vec3::new(expected.cos(), 0.0, -expected.sin())) < 1e-4,
            "{forward:?}"
        );
        assert!(ahead.eye.length() < 1e-6);
        // Moving slowly, then a teleport: the jump is not taken for a velocity.
        let mut motion = MotionPredictor::new();
        for frame in 0..5 {
            let eye = Vec3::new(frame as f32 * 0.1, 0.0, 0.0);
            motion.observe(frame as f64 / 60.0, &camera(eye, eye + Vec3::Z));
        }
        let far = Vec3::new(5000.0, 0.0, 0.0);
        motion.observe(5.0 / 60.0, &camera(far, far + Vec3::Z));
        assert!(motion.predict(&camera(far, far + Vec3::Z), 1.0).is_none());
        motion.observe(6.0 / 60.0, &camera(far, far + Vec3::Z));
        let still = motion
            .predict(&camera(far, far + Vec3::Z), 1.0)
            .expect("two frames since the cut");
        assert!(still.eye.distance(far) < 1e-3);
    }
}
