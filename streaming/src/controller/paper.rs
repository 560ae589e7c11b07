//! The adaptive controller of paper §3.4 (Eq. 4–7): [`AdaptivePolicy`] and
//! Eq. 4, which only it uses; Eq. 5–7's measurements it shares with the
//! headroom controller and they are re-exported from [`controller`](super).
//!
//! # Units
//!
//! Options and [`Telemetry`] speak milliseconds and MB. Inside
//! Eq. 4–7, **latencies are in seconds**. The constants of the polynomial
//! `P = |x| + (10|x|)² + (30|x|)³ + (50|x|)⁴` and of the `(30d)²` decay only
//! give the behaviour the paper describes in seconds:
//!
//! * Fig. 4 (left) plots the change of `l` against `x` "assuming Δt = 1 ms".
//!   In seconds, `x = −4 ms` gives `P = 0.0089` and a step of `9·10⁻⁶` per
//!   1 ms frame: the load factor creeps up while below the threshold, and a
//!   spike of `x = +100 ms` gives `P ≈ 620`, collapsing `l` in one frame. In
//!   milliseconds `P(1 ms)` would be `1 + 100 + 27 000 + 6 250 000` and `l`
//!   would saturate at 0 or 1 every frame, which no figure shows.
//! * Table 3 (α = 16 ms) reports a median load size near 1 MB of the 64 MB
//!   maximum and `t_w` well above the median frame latency (12 vs 4.5 ms): the
//!   `(30d)²` decay in seconds lets `t_w` fall from 100 ms to 59 ms in one
//!   5 ms frame and then ever more slowly, "widening the narrow spikes", while
//!   in milliseconds `t_w` would drop to `Δt` immediately.
//!
//! # Choices where the paper is ambiguous
//!
//! * **Start state.** `l` starts at 0 (the load size starts at `s_min` and
//!   creeps up), `t_w` starts at 0 (so the first `t_w` is the first `Δt`).
//!   Starting at `l = 1` would submit an `s_max` batch in the first cycle,
//!   exactly the stutter the controller exists to avoid.
//! * **"Previous" samples.** `t_wa` (200 samples) and `t_b` (5 samples) are
//!   means of the *previous* `t_w` values, `j = 1..N` as written, excluding
//!   the current one. Before any history exists the current `t_w` stands in.
//!   While fewer than N samples exist, the mean is over those that do.
//! * **Sums of Eq. 7.** `t_bl` and `t_bu` are recursive: the sums range over
//!   the 40 previous values of `t_bl` (respectively `t_bu`) itself, each
//!   clamped by `min` (respectively `max`) against the current `t_w`, then
//!   blended 0.2 : 0.8 with `t_w`. With no history both equal `t_w`.
//!   Because of the `min`/`max`, `t_bl ≤ t_w ≤ t_bu` holds on every frame.
//! * **sign(0) = 0.** When `t_w = t_m` exactly, `l` does not move.
//! * **Degenerate smoothstep.** If both edges are equal (only when all
//!   latencies so far were 0) the step is a hard step: `b = 0` when
//!   `t_b ≤ edge`, else `β`.
//!
//! # Stalls: where the controller departs from the paper
//!
//! Eq. 6 averages the previous 200 `t_w` into `t_wa`. One stalled frame
//! (a slow first frame from pipeline creation and page faults, a window
//! move, a breakpoint: nothing the streamer caused) would sit in that mean
//! for 200 frames: `t_m` rises far above the `t_w` of the normal frames
//! after it, `x = t_w − t_m` is strongly negative, `P(x)` is large and `l`
//! saturates, so the stall opens the throttle to `s_max` and the next cycle
//! binds a full-size batch, the stutter the controller exists to prevent.
//! A frame latency above [`STALL_FACTOR`](super::STALL_FACTOR) × max(α, `t_wa`) is therefore a
//! *stall*: it still drives Eq. 4–7 for its own frame (its `t_w` exceeds
//! `t_m`, so `l` falls, and Eq. 5 decays `t_w` from it as the paper does),
//! but it enters none of the histories (`t_wa`, `t_b`, the edges of Eq. 7),
//! and is counted in [`Telemetry::stall_samples`]. Latencies within 4× of
//! the target or of the running average, which is all a working controller
//! sees, follow Eq. 4–7 exactly as the paper gives them. A render that
//! turns slow for good is not a stall: after [`STALL_RUN_FRAMES`](super::STALL_RUN_FRAMES)
//! consecutive stalls the slow frames enter the histories again.

use super::estimator::{smoothstep, Estimator};
use super::{Decision, LoadPolicy, PolicyError, PolicyKind, PolicyOptions, Telemetry, BYTES_PER_MB};

/// Eq. 4: the polynomial `P(x)`, `x` in seconds.
pub fn load_polynomial(x: f64) -> f64 {
    let a = x.abs();
    a + (10.0 * a).powi(2) + (30.0 * a).powi(3) + (50.0 * a).powi(4)
}

/// Eq. 4: next load factor from the previous one, `x = t_w − t_m` and Δt
/// (seconds), clamped to `[0, 1]`; `sign(0) = 0`.
pub fn next_load_factor(l_prev: f64, x: f64, dt: f64) -> f64 {
    let step = load_polynomial(x) * dt;
    let l = if x > 0.0 {
        l_prev - step
    } else if x < 0.0 {
        l_prev + step
    } else {
        l_prev
    };
    // `clamp` keeps NaN; the inputs are finite by construction, but a NaN
    // must never escape, so map it to the safe end.
    if l.is_nan() {
        0.0
    } else {
        l.clamp(0.0, 1.0)
    }
}

/// Paper §3.4: adaptive load size (Eq. 4–6) and mipmap bias (Eq. 7).
#[derive(Clone, Debug)]
pub struct AdaptivePolicy {
    estimator: Estimator,
    beta: f64,
    s_max_bytes: f64,
    s_min_bytes: f64,
    load_factor: f64,
    decision: Decision,
    telemetry: Telemetry,
}

impl AdaptivePolicy {
    /// A fresh controller (`l = 0`, `t_w = 0`, no history).
    pub fn new(options: &PolicyOptions) -> Result<Self, PolicyError> {
        options.validate()?;
        let decision = Decision::new(options.s_min_bytes, 0.0);
        Ok(AdaptivePolicy {
            estimator: Estimator::new(options.alpha_ms),
            beta: options.beta,
            s_max_bytes: options.s_max_bytes(),
            s_min_bytes: options.s_min_bytes as f64,
            load_factor: 0.0,
            decision,
            telemetry: Telemetry {
                load_size_mb: options.s_min_bytes as f64 / BYTES_PER_MB,
                ..Telemetry::default()
            },
        })
    }
}

impl LoadPolicy for AdaptivePolicy {
    fn update(&mut self, frame_latency_ms: f64) -> Decision {
        let Some(e) = self.estimator.step(frame_latency_ms) else {
            self.telemetry.rejected_samples = self.estimator.rejected;
            return self.decision;
        };
        // Eq. 4.
        self.load_factor = next_load_factor(self.load_factor, e.tw - e.tm, e.dt);
        let s = (self.load_factor * self.s_max_bytes)
            .max(self.s_min_bytes)
            .min(self.s_max_bytes);
        // Eq. 7.
        let b = self.beta * smoothstep(0.96 * e.tbl, 1.2 * e.tbu, e.tb);
        self.decision = Decision::new(s.round() as u64, b.clamp(0.0, self.beta));
        self.telemetry = self.estimator.telemetry(&e, self.load_factor, self.decision);
        self.decision
    }

    fn decision(&self) -> Decision {
        self.decision
    }

    fn telemetry(&self) -> Telemetry {
        self.telemetry
    }

    fn kind(&self) -> PolicyKind {
        PolicyKind::Adaptive
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::controller::tests::close;
    use crate::controller::{MAX_FRAME_LATENCY_MS, STALL_RUN_FRAMES};

    fn adaptive() -> AdaptivePolicy {
        AdaptivePolicy::new(&PolicyOptions::default()).expect("defaults are valid")
    }

    #[test]
    fn eq4_polynomial_and_load_factor_by_hand() {
        // x = −3 ms: 0.003 + 0.03² + 0.09³ + 0.15⁴
        //          = 0.003 + 0.0009 + 0.000729 + 0.00050625 = 0.00513525.
        assert!(close(load_polynomial(-0.003), 0.00513525, 1e-15));
        // Fig. 4 left, Δt = 1 ms: x = −4 ms raises l by
        // (0.004 + 0.0016 + 0.001728 + 0.0016) · 0.001 = 8.928e-6.
        assert!(close(next_load_factor(0.5, -0.004, 0.001), 0.5 + 8.928e-6, 1e-15));
        // x = +100 ms: 0.1 + 1 + 27 + 625 = 653.1; ·0.001 → l collapses to 0.
        assert!(close(load_polynomial(0.1), 653.1, 1e-9));
        assert_eq!(next_load_factor(0.5, 0.1, 0.001), 0.0);
        // Why seconds: read in ms, x = −1 "ms" would give
        // P = 1 + 100 + 27 000 + 6 250 000 = 6 277 101 and l would jump from
        // 0 to 1 in a single 1 "ms" frame (and back to 0 on any frame above
        // the threshold): the bang-bang behaviour Fig. 4 does not show.
        assert_eq!(load_polynomial(1.0), 6_277_101.0);
        assert_eq!(next_load_factor(0.0, -1.0, 1.0), 1.0);
        // sign(0) = 0: no change.
        assert_eq!(next_load_factor(0.25, 0.0, 0.016), 0.25);
        // Upper clamp.
        assert_eq!(next_load_factor(0.99, -1.0, 1.0), 1.0);
    }

    #[test]
    fn three_frames_by_hand() {
        let mut p = adaptive();
        // Frame 1, Δt = 10 ms. t_w = max(0 − 0, 0.01) = 0.01. No history:
        // t_wa = t_w = 0.01 ≤ α → t_m = 0.5·0.01 + 0.5·0.016 = 0.013.
        // x = −0.003, P = 0.00513525, l = 0 + P·0.01 = 5.13525e-5.
        // s = max(5.13525e-5 · 64 MiB = 3446 B, 65536 B) = 65536 B.
        // t_b = t_bl = t_bu = 0.01; edges 0.0096 and 0.012,
        // t = 0.0004/0.0024 = 1/6, smoothstep = (1/36)(3 − 1/3) = 0.0740741,
        // b = 8 · 0.0740741 = 0.5925926.
        let d = p.update(10.0);
        let t = p.telemetry();
        assert!(close(t.tw_ms, 10.0, 1e-12));
        assert!(close(t.tm_ms, 13.0, 1e-12));
        assert!(close(t.load_factor, 5.13525e-5, 1e-15));
        assert_eq!(d.load_size_bytes, 65_536);
        assert!(close(d.mip_bias, 8.0 * (1.0 / 36.0) * (3.0 - 1.0 / 3.0), 1e-12));
        assert!(close(d.mip_bias, 0.5925926, 1e-6));

        // Frame 2, Δt = 40 ms. d = max(0.01 − 0.04, 0) = 0 → t_w = 0.04.
        // t_wa = mean[0.01] = 0.01 → t_m = 0.013. x = 0.027,
        // P = 0.027 + 0.0729 + 0.531441 + 3.32150625 = 3.95284725,
        // l = clamp(5.135e-5 − 3.9528·0.04) = 0 → s = s_min.
        // t_b = mean[0.01] = 0.01; t_bl = 0.2·0.04 + 0.8·min(0.01, 0.04) = 0.016,
        // t_bu = 0.2·0.04 + 0.8·max(0.01, 0.04) = 0.04; t_b < 0.96·0.016 → b = 0.
        let d = p.update(40.0);
        let t = p.telemetry();
        assert!(close(t.tw_ms, 40.0, 1e-12));
        assert!(close(t.tm_ms, 13.0, 1e-12));
        assert_eq!(t.load_factor, 0.0);
        assert_eq!(d.load_size_bytes, 65_536);
        assert!(close(t.tbl_ms, 16.0, 1e-12));
        assert!(close(t.tbu_ms, 40.0, 1e-12));
        assert_eq!(d.mip_bias, 0.0);

        // Frame 3, Δt = 10 ms. d = 0.03, (0.9)²·0.01 = 0.0081 → t_w = 0.0319.
        // t_wa = mean[0.01, 0.04] = 0.025 > α → t_m = 0.15·0.025 + 0.85·0.016
        // = 0.01735. x > 0 → l stays 0.
        // t_b = mean[0.01, 0.04] = 0.025.
        // t_bl = 0.2·0.0319 + 0.8·mean[min(0.01, 0.0319), min(0.016, 0.0319)]
        //      = 0.00638 + 0.8·0.013 = 0.01678.
        // t_bu = 0.00638 + 0.8·mean[max(0.01, 0.0319), max(0.04, 0.0319)]
        //      = 0.00638 + 0.8·0.03595 = 0.03514.
        // edges 0.0161088 and 0.042168, t = 0.0088912/0.0260592 = 0.3411924,
        // smoothstep = 0.1164122·2.3176153 = 0.2697988, b = 2.158390.
        let d = p.update(10.0);
        let t = p.telemetry();
        assert!(close(t.tw_ms, 31.9, 1e-9));
        assert!(close(t.twa_ms, 25.0, 1e-9));
        assert!(close(t.tm_ms, 17.35, 1e-9));
        assert!(close(t.tb_ms, 25.0, 1e-9));
        assert!(close(t.tbl_ms, 16.78, 1e-9));
        assert!(close(t.tbu_ms, 35.14, 1e-9));
        let e0 = 0.96 * 0.01678;
        let e1 = 1.2 * 0.03514;
        let x = (0.025 - e0) / (e1 - e0);
        assert!(close(d.mip_bias, 8.0 * x * x * (3.0 - 2.0 * x), 1e-9));
        assert!(close(d.mip_bias, 2.158390, 1e-6));
        assert_eq!(t.load_factor, 0.0);
    }

    #[test]
    fn load_factor_creeps_up_below_threshold_and_collapses_after_spike() {
        let mut p = adaptive();
        for _ in 0..2000 {
            p.update(5.0);
        }
        let before = p.telemetry().load_factor;
        assert!(before > 0.0, "l must grow below the threshold");
        assert!(p.decision().load_size_bytes > 65_536);
        p.update(1000.0);
        let t = p.telemetry();
        assert_eq!(t.load_factor, 0.0);
        assert_eq!(p.decision().load_size_bytes, 65_536);
        // t_w took the spike immediately and decays over later frames.
        assert!(close(t.tw_ms, 1000.0, 1e-9));
        p.update(5.0);
        let tw = p.telemetry().tw_ms;
        assert!((5.0..1000.0).contains(&tw));
    }

    #[test]
    fn rejects_nan_infinity_and_negative_clamps_huge() {
        let mut p = adaptive();
        let first = p.update(8.0);
        assert_eq!(p.update(f64::NAN), first);
        assert_eq!(p.update(-1.0), first);
        assert_eq!(p.update(f64::NEG_INFINITY), first);
        assert_eq!(p.update(f64::INFINITY), first);
        assert_eq!(p.telemetry().rejected_samples, 4);
        assert_eq!(p.telemetry().frames, 1);
        p.update(1e300);
        let t = p.telemetry();
        assert_eq!(t.frame_ms, MAX_FRAME_LATENCY_MS);
        assert_eq!(t.tw_ms, MAX_FRAME_LATENCY_MS);
        assert_eq!(t.load_factor, 0.0);
        assert_eq!(t.stall_samples, 1);
        assert!(t.mip_bias.is_finite());
    }

    /// Load sizes of `frames` frames of `ms` each, after `before`.
    fn load_sizes(p: &mut AdaptivePolicy, ms: f64, frames: usize) -> Vec<u64> {
        (0..frames).map(|_| p.update(ms).load_size_bytes).collect()
    }

    #[test]
    fn a_stall_mid_run_does_not_open_the_throttle() {
        for stall_ms in [500.0, 2_000.0, 20_000.0, 60_000.0, 1e9] {
            let mut p = adaptive();
            // A long steady run at half the target: l has crept up.
            let before = *load_sizes(&mut p, 8.0, 1000).last().unwrap_or(&0);
            assert!(before > 4 * 65_536, "{before} bytes before the stall");
            p.update(stall_ms);
            assert_eq!(p.telemetry().stall_samples, 1);
            let after = load_sizes(&mut p, 8.0, 200);
            let largest = after.iter().copied().max().unwrap_or(0);
            assert!(
                largest <= before,
                "a {stall_ms} ms stall let s reach {largest} bytes, {before} before it"
            );
        }
    }

    #[test]
    fn a_slow_first_frame_does_not_open_the_throttle() {
        for first_ms in [500.0, 5_000.0, 60_000.0] {
            let mut slow = adaptive();
            let mut steady = adaptive();
            slow.update(first_ms);
            steady.update(8.0);
            let slow_sizes = load_sizes(&mut slow, 8.0, 200);
            let steady_sizes = load_sizes(&mut steady, 8.0, 200);
            for (frame, (s, undisturbed)) in slow_sizes.iter().zip(&steady_sizes).enumerate() {
                assert!(
                    s <= undisturbed,
                    "frame {frame} after a {first_ms} ms first frame: s = {s}, {undisturbed} without it"
                );
            }
        }
    }

    #[test]
    fn a_render_that_turns_slow_for_good_is_not_a_stall() {
        // Every frame 100 ms from frame 100 on: the first eight are held
        // back as stalls, the rest raise t_wa as Eq. 6 intends.
        let mut p = adaptive();
        load_sizes(&mut p, 8.0, 100);
        load_sizes(&mut p, 100.0, 300);
        let t = p.telemetry();
        assert_eq!(t.stall_samples, u64::from(STALL_RUN_FRAMES));
        assert!(t.twa_ms > 90.0, "t_wa = {} ms", t.twa_ms);
        // Overloaded: the bias coarsens streaming as the paper's Eq. 7 does.
        assert!(t.mip_bias > 0.0, "b = {}", t.mip_bias);
    }

    #[test]
    fn hard_cases_stay_in_range() {
        let o = PolicyOptions::default();
        let s_min = o.s_min_bytes;
        let s_max = 64 * 1_048_576;
        let mut p = adaptive();
        for ms in [0.0, 1e-9, 1e4, f64::NAN, f64::INFINITY, 0.0, 1000.0, 5.0] {
            let d = p.update(ms);
            let t = p.telemetry();
            assert!((s_min..=s_max).contains(&d.load_size_bytes));
            assert!((0.0..=8.0).contains(&d.mip_bias), "{ms}: {d:?}");
            assert!((0.0..=1.0).contains(&t.load_factor));
            for v in [t.tw_ms, t.tm_ms, t.twa_ms, t.tb_ms, t.tbl_ms, t.tbu_ms] {
                assert!(v.is_finite() && v >= 0.0, "{ms}: {t:?}");
            }
        }
        // Δt = 0 from a fresh start: every latency is 0, the edges
        // coincide, the hard step gives b = 0, and l does not move (P·0).
        let mut z = adaptive();
        for _ in 0..10 {
            let d = z.update(0.0);
            assert_eq!(d.mip_bias, 0.0);
            assert_eq!(d.load_size_bytes, s_min);
        }
        assert_eq!(z.telemetry().load_factor, 0.0);
    }

    #[test]
    fn alpha_below_base_frame_time_pins_s_min() {
        // α = 2 ms with 5 ms frames: t_wa = 5 > α → t_m = 0.75 + 1.7 = 2.45 ms
        // < t_w = 5 ms, so x > 0 every frame and l stays 0.
        let o = PolicyOptions {
            alpha_ms: 2.0,
            ..PolicyOptions::default()
        };
        let mut p = AdaptivePolicy::new(&o).expect("valid");
        for _ in 0..1000 {
            assert_eq!(p.update(5.0).load_size_bytes, o.s_min_bytes);
        }
        assert!(close(p.telemetry().tm_ms, 2.45, 1e-9));
    }

    #[test]
    fn beta_zero_gives_zero_bias() {
        let o = PolicyOptions {
            beta: 0.0,
            ..PolicyOptions::default()
        };
        let mut p = AdaptivePolicy::new(&o).expect("valid");
        for i in 0..500 {
            let ms = if i % 50 == 0 { 300.0 } else { 4.0 + (i % 7) as f64 };
            assert_eq!(p.update(ms).mip_bias, 0.0);
        }
    }

    #[test]
    fn constant_latency_bias_settles_at_closed_form() {
        // Constant t_w = Δt: t_bl = t_bu = t_b = Δt, t = (1 − 0.96)/(1.2 − 0.96)
        // = 1/6, b = 8 · (1/36) · (8/3) = 0.5925926 whatever Δt is.
        let mut p = adaptive();
        for _ in 0..300 {
            p.update(7.0);
        }
        assert!(close(p.decision().mip_bias, 0.5925926, 1e-6));
    }
}
