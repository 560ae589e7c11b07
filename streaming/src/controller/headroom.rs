//! The headroom controller ([`HeadroomPolicy`]): a load size that spends the
//! room left under α and nothing more, and a bias only while frames are over α.

use super::estimator::{smoothstep, Estimator, Ring, TB_SAMPLES};
use super::{Decision, LoadPolicy, PolicyError, PolicyKind, PolicyOptions, Telemetry, BYTES_PER_MB};

/// Frames whose latency bounds the headroom: the batches of the frames in flight have not
/// shown their cost yet, so growth waits for the slowest of the latest few.
pub const HEADROOM_FRAMES: usize = 4;
/// Frames whose fastest latency stands for the frame without streaming work.
pub const BASE_FRAMES: usize = 64;
/// Frames whose largest applied load bounds the load size's growth.
pub const DEMAND_FRAMES: usize = 16;
/// Growth of the load size per frame at full headroom: `s ← s · (1 + g · (α − peak) / α)`.
pub const HEADROOM_GAIN: f64 = 1.0;
/// Growth per frame at full headroom beyond the size the latest cut left: the batches of
/// the frames in flight show their cost only frames later, so probing past a known limit
/// goes slowly.
pub const PROBE_GAIN: f64 = 0.25;
/// The most one frame grows the size past the size the latest cut left: with the cost of
/// a batch seen up to four frames late and growing with its square, 3 % a frame shows as
/// at most 1.03⁸ ≈ 1.27 times the cost that was measured (5 % saw-toothed over α on a
/// square-law plant).
pub const MAX_PROBE_STEP: f64 = 0.03;
/// The share of the room left under α that a frame over α aims its next batches at.
pub const OVERSHOOT_TARGET: f64 = 0.8;
/// The share of that room at which growth stops: below the cut's aim, so that what the
/// frames in flight still carry (up to 1.27 times the cost measured, see
/// [`MAX_PROBE_STEP`]) lands under α.
pub const GROWTH_TARGET: f64 = 0.7;
/// The most one frame over α shrinks the load size by (a 1/64 step reaches `s_min` from
/// `s_max` in under three frames).
pub const MAX_SHRINK: f64 = 1.0 / 64.0;
/// The share of α above the fastest recent frame from which the streaming work counts as
/// visible in the latency.
pub const VISIBLE_COST: f64 = 0.05;
/// Load sizes up to this multiple of `s_min` grow without applied loads to back them.
pub const DEMAND_FLOOR_BLOCKS: f64 = 16.0;
/// Bias begins where the mean of the latest frames reaches α and is full at this multiple.
pub const BIAS_FULL_AT: f64 = 1.5;

/// A controller that spends the room left under α and nothing more: the load size grows
/// with the headroom `α −` (the slowest of the latest [`HEADROOM_FRAMES`] frames), is cut
/// after a frame over α in proportion to how far over it went, and never runs far ahead
/// of what cycles actually load (at most twice the largest load of the latest
/// [`DEMAND_FRAMES`] frames, so a quiet stretch does not leave a full-size batch ready for
/// the next burst); the mip bias engages only while the latest frames' mean is over α.
/// docs/CONTROLLER.md sets it beside the paper's (Eq. 4–7) with the measurements.
///
/// The paper's controller ([`AdaptivePolicy`](super::AdaptivePolicy)) reacts to the relative swing of the
/// latency between its recent edges, so it raises the bias and holds the load size low
/// while every frame is far below α; this one leaves both alone until the frame nears α.
/// It shares the paper's bad-input rules and its stall rule: a frame far over the target
/// (see [the paper's controller](super::paper)) shrinks the load size but enters none of the histories.
#[derive(Clone, Debug)]
pub struct HeadroomPolicy {
    estimator: Estimator,
    alpha_ms: f64,
    beta: f64,
    s_max_bytes: f64,
    s_min_bytes: f64,
    load_bytes: f64,
    /// What the latest cut left (`s_max` before the first).
    safe_bytes: f64,
    /// Frames since the latest cut, and the latency that caused it: the frames in flight
    /// after a cut still carry batches sized before it, and cutting for each of them again
    /// would cut several times for one excess.
    frames_since_cut: usize,
    cut_for_ms: f64,
    /// Accepted frame latencies (ms), stalls left out.
    latencies: Ring<BASE_FRAMES>,
    /// Bytes applied per frame, once any load was observed.
    loads: Ring<DEMAND_FRAMES>,
    loads_observed: bool,
    decision: Decision,
    telemetry: Telemetry,
}

impl HeadroomPolicy {
    /// A fresh controller: `s = s_min`, `b = 0`, no history.
    pub fn new(options: &PolicyOptions) -> Result<Self, PolicyError> {
        options.validate()?;
        let s_min = options.s_min_bytes as f64;
        Ok(HeadroomPolicy {
            estimator: Estimator::new(options.alpha_ms),
            alpha_ms: options.alpha_ms,
            beta: options.beta,
            s_max_bytes: options.s_max_bytes(),
            s_min_bytes: s_min,
            load_bytes: s_min,
            safe_bytes: options.s_max_bytes(),
            frames_since_cut: usize::MAX,
            cut_for_ms: 0.0,
            latencies: Ring::new(),
            loads: Ring::new(),
            loads_observed: false,
            decision: Decision::new(options.s_min_bytes, 0.0),
            telemetry: Telemetry {
                load_size_mb: s_min / BYTES_PER_MB,
                load_factor: s_min / options.s_max_bytes(),
                ..Telemetry::default()
            },
        })
    }

    /// The largest load size the applied loads justify.
    fn demand_cap(&self) -> f64 {
        let floor = self.s_min_bytes * DEMAND_FLOOR_BLOCKS;
        if !self.loads_observed {
            return self.s_max_bytes;
        }
        let largest = self.loads.samples().iter().copied().fold(0.0, f64::max);
        (2.0 * largest).max(floor)
    }
}

/// The next load size after a frame of `frame_ms` whose slowest recent frame took
/// `peak_ms`, the fastest `base_ms` (all ms, finite, non-negative), for target `alpha_ms`;
/// `safe_bytes` is the size the latest cut left (the frames after it were under α), up to
/// which the size grows fast, and beyond which it probes slowly.
pub fn headroom_load_size(
    load_bytes: f64,
    safe_bytes: f64,
    frame_ms: f64,
    peak_ms: f64,
    base_ms: f64,
    alpha_ms: f64,
) -> f64 {
    let aim = ((alpha_ms - base_ms) * OVERSHOOT_TARGET).max(0.0);
    if frame_ms > alpha_ms {
        // Bind cost grows with the batch at least linearly (the `desktop` model: with its
        // square), so the square root of the ratio of the aim to the excess is the cut
        // that brings a square-law batch back under α; a linear one is cut again next frame.
        let excess = (frame_ms - base_ms).max(f64::MIN_POSITIVE);
        let ratio = (aim / excess).clamp(MAX_SHRINK * MAX_SHRINK, 1.0);
        return load_bytes * ratio.sqrt();
    }
    let work_ms = frame_ms - base_ms;
    if work_ms > aim && aim > 0.0 {
        // Under α but past the aim (the batches in flight overshot it): ease back to it
        // (by at most √0.8 a frame) before a frame crosses α.
        return load_bytes * (aim / work_ms).sqrt();
    }
    let headroom = ((alpha_ms - peak_ms) / alpha_ms).clamp(0.0, 1.0);
    let mut growth = if load_bytes < safe_bytes {
        1.0 + HEADROOM_GAIN * headroom
    } else {
        1.0 + (PROBE_GAIN * headroom).min(MAX_PROBE_STEP)
    };
    let bind_ms = peak_ms - base_ms;
    if bind_ms > VISIBLE_COST * alpha_ms {
        // The streaming work shows in the frame: grow no further than a square-law cost
        // would allow.
        let room = ((alpha_ms - base_ms) * GROWTH_TARGET).max(0.0);
        growth = growth.min((room / bind_ms).sqrt().max(1.0));
    }
    let grown = load_bytes * growth;
    if load_bytes < safe_bytes {
        // Fast growth ends at the size known to be safe; the probing goes on from there.
        grown.min(safe_bytes)
    } else {
        grown
    }
}

impl LoadPolicy for HeadroomPolicy {
    fn update(&mut self, frame_latency_ms: f64) -> Decision {
        let Some(e) = self.estimator.step(frame_latency_ms) else {
            self.telemetry.rejected_samples = self.estimator.rejected;
            return self.decision;
        };
        let frame_ms = e.dt * 1000.0;
        if !e.stall {
            self.latencies.push(frame_ms);
        }
        let peak_ms = self
            .latencies
            .newest(HEADROOM_FRAMES)
            .fold(if e.stall { frame_ms } else { 0.0 }, f64::max);
        let base_ms = self.latencies.samples().iter().copied().fold(frame_ms, f64::min);
        let over = frame_ms > self.alpha_ms;
        let cut_pending = self.frames_since_cut < HEADROOM_FRAMES && frame_ms <= self.cut_for_ms;
        let grown = if over && cut_pending {
            // The latest cut has not shown yet, and this frame is no worse than the one
            // that caused it: hold.
            self.load_bytes
        } else {
            headroom_load_size(
                self.load_bytes,
                self.safe_bytes,
                frame_ms,
                peak_ms,
                base_ms,
                self.alpha_ms,
            )
        };
        self.frames_since_cut = self.frames_since_cut.saturating_add(1);
        if over && !cut_pending {
            self.frames_since_cut = 0;
            self.cut_for_ms = frame_ms;
        }
        // Growth stops at what the loads justify; a cut is never undone by the cap.
        let capped = if grown > self.load_bytes {
            grown.min(self.demand_cap().max(self.load_bytes))
        } else {
            grown
        };
        let next = capped.clamp(self.s_min_bytes, self.s_max_bytes);
        // A frame over α while the size was already the smallest says nothing of what
        // size is safe (the loads did not cause it).
        if over && !cut_pending && self.load_bytes > self.s_min_bytes {
            self.safe_bytes = next;
        }
        self.load_bytes = next;
        // Sustained frames over α, not the first few: missing samples count as 0 ms.
        let recent_ms = self.latencies.newest(TB_SAMPLES).sum::<f64>() / TB_SAMPLES as f64;
        let bias = self.beta * smoothstep(self.alpha_ms, BIAS_FULL_AT * self.alpha_ms, recent_ms);
        self.decision = Decision::new(self.load_bytes.round() as u64, bias.clamp(0.0, self.beta));
        self.telemetry = self
            .estimator
            .telemetry(&e, self.load_bytes / self.s_max_bytes, self.decision);
        self.decision
    }

    fn observe_load(&mut self, bytes_loaded: u64) {
        self.loads_observed = true;
        self.loads.push(bytes_loaded as f64);
    }

    fn decision(&self) -> Decision {
        self.decision
    }

    fn telemetry(&self) -> Telemetry {
        self.telemetry
    }

    fn kind(&self) -> PolicyKind {
        PolicyKind::Headroom
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::controller::tests::close;
    use crate::controller::MAX_FRAME_LATENCY_MS;

    fn headroom_at(alpha_ms: f64) -> HeadroomPolicy {
        HeadroomPolicy::new(&PolicyOptions {
            alpha_ms,
            ..PolicyOptions::default()
        })
        .expect("valid")
    }

    /// `frames` frames of a plant whose frame costs `base_ms` plus a square-law bind of
    /// what the load size carried `delay` frames before (the `desktop` model's 470 ms for
    /// 1,024 blocks), with unlimited demand; the latencies.
    fn square_law_run(p: &mut HeadroomPolicy, base_ms: f64, delay: usize, frames: usize) -> Vec<f64> {
        let mut batches = std::collections::VecDeque::from(vec![0u64; delay]);
        let mut latencies = Vec::with_capacity(frames);
        for _ in 0..frames {
            batches.push_back(p.decision().load_size_bytes);
            let bytes = batches.pop_front().unwrap_or(0);
            let blocks = bytes as f64 / 65_536.0;
            let ms = base_ms + 470.0 * (blocks / 1024.0).powi(2);
            p.observe_load(bytes);
            p.update(ms);
            latencies.push(ms);
        }
        latencies
    }

    #[test]
    fn headroom_cut_after_a_frame_over_alpha_by_hand() {
        // s = 1 MB, base 8 ms, α = 12 ms, a 20 ms frame: room (12 − 8) · 0.8 = 3.2 ms,
        // excess 12 ms, s · √(3.2 / 12) = 0.516 MB.
        let s = headroom_load_size(1_048_576.0, 1e9, 20.0, 20.0, 8.0, 12.0);
        assert!(close(s, 1_048_576.0 * (3.2f64 / 12.0).sqrt(), 1e-6), "{s}");
        // At the aim (8 + 3.2 ms) the size is held.
        assert_eq!(headroom_load_size(1000.0, 1e9, 11.2, 11.2, 8.0, 12.0), 1000.0);
        // (s, safe bytes, frame, peak, base, α) and the size expected.
        for (case, [load, safe, frame, peak, base, alpha], expected) in [
            // Below α the size grows with the headroom left by the slowest recent frame.
            ("peak 9 ms of 12: × 1.25", [1000.0, 1e9, 8.0, 9.0, 8.0, 12.0], 1250.0),
            // A frame at α is past the aim (8 + 3.2 ms): eased back by √(3.2 / 4).
            (
                "a frame at α",
                [1000.0, 1e9, 12.0, 12.0, 8.0, 12.0],
                1000.0 * 0.8f64.sqrt(),
            ),
            (
                "a frame far over α cuts by at most 1/64",
                [64_000.0, 1e9, 60_000.0, 60_000.0, 8.0, 12.0],
                1000.0,
            ),
            (
                "a base at or over α leaves no room: the largest cut",
                [64_000.0, 1e9, 13.0, 13.0, 13.0, 12.0],
                1000.0,
            ),
        ] {
            let s = headroom_load_size(load, safe, frame, peak, base, alpha);
            assert!(close(s, expected, 1e-9), "{case}: {s}, expected {expected}");
        }
    }

    #[test]
    fn headroom_settles_under_alpha_on_a_square_law_bind() {
        for (alpha, delay) in [(12.0, 1), (12.0, 3), (16.0, 2), (30.0, 3)] {
            let mut p = headroom_at(alpha);
            let latencies = square_law_run(&mut p, 8.0, delay, 600);
            let worst = latencies.iter().copied().fold(0.0, f64::max);
            assert!(
                worst <= 2.0 * alpha,
                "α = {alpha}, delay {delay}: worst frame {worst} ms"
            );
            let settled = &latencies[300..];
            let mean = settled.iter().sum::<f64>() / settled.len() as f64;
            // It spends most of the room (a square-law plant keeps a margin) and no more.
            assert!(
                mean <= alpha && mean >= 8.0 + 0.5 * (alpha - 8.0),
                "α = {alpha}, delay {delay}: mean {mean} ms"
            );
            // Probing touches α now and then; a bias of a few hundredths of a level at most.
            assert!(
                p.decision().mip_bias <= 0.05,
                "α = {alpha}, delay {delay}: bias {}",
                p.decision().mip_bias
            );
        }
    }

    #[test]
    fn headroom_load_size_follows_the_demand() {
        let mut p = headroom_at(16.0);
        for _ in 0..500 {
            p.observe_load(100_000);
            p.update(8.0);
        }
        // Twice the largest recent load, or 16 blocks when that is less.
        assert_eq!(p.decision().load_size_bytes, 16 * 65_536);
        for _ in 0..100 {
            p.observe_load(3_000_000);
            p.update(8.0);
        }
        assert_eq!(p.decision().load_size_bytes, 6_000_000);
        // Never fed loads (a host that does not report them): the size is free to grow.
        let mut free = headroom_at(16.0);
        for _ in 0..500 {
            free.update(8.0);
        }
        assert_eq!(free.decision().load_size_bytes, 64 << 20);
    }

    #[test]
    fn headroom_rejects_bad_samples_and_clamps_huge() {
        let mut p = headroom_at(16.0);
        let first = p.update(8.0);
        for bad in [f64::NAN, -1.0, -0.0 - 1e-300, f64::NEG_INFINITY, f64::INFINITY] {
            assert_eq!(p.update(bad), first, "{bad}");
        }
        assert_eq!(p.telemetry().rejected_samples, 5);
        assert_eq!(p.telemetry().frames, 1);
        p.update(1e300);
        let t = p.telemetry();
        assert_eq!(t.frame_ms, MAX_FRAME_LATENCY_MS);
        assert_eq!(t.stall_samples, 1);
        assert_eq!(p.decision().load_size_bytes, 65_536);
        for ms in [0.0, f64::MIN_POSITIVE, 5e-324, 1e-9, 1e4, 0.0, 16.0, 5.0] {
            let d = p.update(ms);
            let t = p.telemetry();
            assert!((65_536..=64 << 20).contains(&d.load_size_bytes), "{ms}: {d:?}");
            assert!((0.0..=8.0).contains(&d.mip_bias), "{ms}: {d:?}");
            for v in [t.frame_ms, t.tw_ms, t.tm_ms, t.twa_ms, t.tb_ms, t.load_factor] {
                assert!(v.is_finite() && v >= 0.0, "{ms}: {t:?}");
            }
        }
    }

    #[test]
    fn headroom_slow_frames_never_open_the_throttle() {
        // A stall mid-run (after 1,000 frames at half the target) and a slow first frame.
        for stall_ms in [500.0, 2_000.0, 60_000.0, 1e9] {
            let mut p = headroom_at(16.0);
            let before = (0..1000).map(|_| p.update(8.0).load_size_bytes).last().unwrap_or(0);
            p.update(stall_ms);
            let after: Vec<Decision> = (0..200).map(|_| p.update(8.0)).collect();
            assert!(
                after.iter().all(|d| d.load_size_bytes <= before),
                "after a {stall_ms} ms stall"
            );
            assert!(after.iter().all(|d| d.mip_bias == 0.0), "a stall is no reason to bias");
            let mut slow = headroom_at(16.0);
            let mut steady = headroom_at(16.0);
            slow.update(stall_ms);
            steady.update(8.0);
            for frame in 0..200 {
                let (s, undisturbed) = (slow.update(8.0), steady.update(8.0));
                assert!(
                    s.load_size_bytes <= undisturbed.load_size_bytes,
                    "frame {frame} after a {stall_ms} ms first frame"
                );
            }
        }
    }

    #[test]
    fn headroom_bias_engages_only_over_alpha() {
        let mut p = headroom_at(12.0);
        for ms in [8.0, 11.9, 12.0, 4.0] {
            for _ in 0..50 {
                assert_eq!(p.update(ms).mip_bias, 0.0, "{ms} ms frames");
            }
        }
        // Sustained frames at 1.25 α: half way up the smoothstep; at 1.5 α and over: β.
        for _ in 0..50 {
            p.update(15.0);
        }
        assert!(close(p.decision().mip_bias, 4.0, 1e-9), "{:?}", p.decision());
        for _ in 0..50 {
            p.update(40.0);
        }
        assert_eq!(p.decision().mip_bias, 8.0);
    }
}
