//! The latency measurements shared by every policy, in seconds: `t_w`
//! (Eq. 5), `t_wa` and `t_m` (Eq. 6), `t_b` and the edges of Eq. 7, with the
//! bad-input rules and the stall rule (described with the paper's
//! controller, whose Eq. 6 the stall rule departs from).

use super::{Decision, Telemetry, BYTES_PER_MB};

/// Frame latencies above this (ms) are clamped to it: one minute.
pub const MAX_FRAME_LATENCY_MS: f64 = 60_000.0;

/// A frame latency above this multiple of max(α, `t_wa`) is a stall and
/// stays out of the histories (see [the paper's controller](super::paper)).
pub const STALL_FACTOR: f64 = 4.0;

/// Consecutive stalls kept out of the histories; from the next one on, slow
/// frames are the new normal and enter them (a render that became slow).
pub const STALL_RUN_FRAMES: u32 = 8;

/// Samples of `t_w` averaged into `t_wa` (Eq. 6).
pub const TWA_SAMPLES: usize = 200;
/// Samples of `t_bl` / `t_bu` averaged into the edges (Eq. 7).
pub const EDGE_SAMPLES: usize = 40;
/// Samples of `t_w` averaged into `t_b` (Eq. 7).
pub const TB_SAMPLES: usize = 5;

/// Fixed-capacity ring of the most recent samples.
#[derive(Clone, Debug)]
pub(super) struct Ring<const N: usize> {
    buf: [f64; N],
    len: usize,
    next: usize,
}

impl<const N: usize> Ring<N> {
    pub(super) fn new() -> Self {
        Ring {
            buf: [0.0; N],
            len: 0,
            next: 0,
        }
    }

    pub(super) fn push(&mut self, v: f64) {
        self.buf[self.next] = v;
        self.next = (self.next + 1) % N;
        self.len = (self.len + 1).min(N);
    }

    /// The stored samples, in no particular order.
    pub(super) fn samples(&self) -> &[f64] {
        &self.buf[..self.len]
    }

    /// The newest `k` samples (fewer if fewer exist).
    pub(super) fn newest(&self, k: usize) -> impl Iterator<Item = f64> + '_ {
        let k = k.min(self.len);
        (1..=k).map(move |j| self.buf[(self.next + N - j) % N])
    }
}

/// Mean of an iterator, summed fresh every time so that 10⁶ frames cannot
/// accumulate rounding drift.
fn mean(values: impl Iterator<Item = f64>) -> Option<f64> {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    (n > 0).then(|| sum / n as f64)
}

/// Eq. 5: weighted maximum frame latency, seconds in and out.
pub fn weighted_max_latency(tw_prev: f64, dt: f64) -> f64 {
    let d = (tw_prev - dt).max(0.0);
    (tw_prev - (30.0 * d).powi(2) * dt).max(dt)
}

/// Eq. 6: maximum frame latency threshold from `t_wa` and α (same units).
pub fn latency_threshold(twa: f64, alpha: f64) -> f64 {
    if twa > alpha {
        twa * (1.0 - 0.85) + alpha * 0.85
    } else {
        twa * (1.0 - 0.5) + alpha * 0.5
    }
}

/// GLSL `smoothstep`, with a hard step when the edges coincide or cross.
pub fn smoothstep(edge0: f64, edge1: f64, x: f64) -> f64 {
    if edge1 <= edge0 {
        return if x <= edge0 { 0.0 } else { 1.0 };
    }
    let t = ((x - edge0) / (edge1 - edge0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// The latency measurements shared by every policy (Eq. 5, 6 and the
/// edges of Eq. 7), in seconds.
#[derive(Clone, Debug)]
pub(super) struct Estimator {
    alpha_s: f64,
    tw: f64,
    tw_history: Ring<TWA_SAMPLES>,
    tbl_history: Ring<EDGE_SAMPLES>,
    tbu_history: Ring<EDGE_SAMPLES>,
    frames: u64,
    pub(super) rejected: u64,
    stalls: u64,
    /// Stalls in a row up to the latest sample.
    stall_run: u32,
}

/// One frame's measurements, seconds.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct Estimate {
    pub(super) dt: f64,
    /// The frame was taken as a stall and kept out of the histories.
    pub(super) stall: bool,
    pub(super) tw: f64,
    twa: f64,
    pub(super) tm: f64,
    pub(super) tb: f64,
    pub(super) tbl: f64,
    pub(super) tbu: f64,
}

impl Estimator {
    pub(super) fn new(alpha_ms: f64) -> Self {
        Estimator {
            alpha_s: alpha_ms / 1000.0,
            tw: 0.0,
            tw_history: Ring::new(),
            tbl_history: Ring::new(),
            tbu_history: Ring::new(),
            frames: 0,
            rejected: 0,
            stalls: 0,
            stall_run: 0,
        }
    }

    /// Accept one frame latency (ms); `None` when the sample is rejected.
    pub(super) fn step(&mut self, frame_latency_ms: f64) -> Option<Estimate> {
        if !frame_latency_ms.is_finite() || frame_latency_ms < 0.0 {
            self.rejected += 1;
            return None;
        }
        let dt = frame_latency_ms.min(MAX_FRAME_LATENCY_MS) / 1000.0;
        let tw = weighted_max_latency(self.tw, dt);
        let history_twa = mean(self.tw_history.samples().iter().copied());
        let far_above = dt > STALL_FACTOR * history_twa.unwrap_or(0.0).max(self.alpha_s);
        self.stall_run = if far_above { self.stall_run.saturating_add(1) } else { 0 };
        let stall = far_above && self.stall_run <= STALL_RUN_FRAMES;
        let twa = history_twa.unwrap_or(tw);
        let tm = latency_threshold(twa, self.alpha_s);
        let tb = mean(self.tw_history.newest(TB_SAMPLES)).unwrap_or(tw);
        let tbl =
            mean(self.tbl_history.samples().iter().map(|&v| v.min(tw))).map_or(tw, |m| tw * (1.0 - 0.8) + m * 0.8);
        let tbu =
            mean(self.tbu_history.samples().iter().map(|&v| v.max(tw))).map_or(tw, |m| tw * (1.0 - 0.8) + m * 0.8);
        self.tw = tw;
        if stall {
            self.stalls += 1;
        } else {
            self.tw_history.push(tw);
            self.tbl_history.push(tbl);
            self.tbu_history.push(tbu);
        }
        self.frames += 1;
        Some(Estimate {
            dt,
            stall,
            tw,
            twa,
            tm,
            tb,
            tbl,
            tbu,
        })
    }

    pub(super) fn telemetry(&self, e: &Estimate, load_factor: f64, d: Decision) -> Telemetry {
        Telemetry {
            frame_ms: e.dt * 1000.0,
            tw_ms: e.tw * 1000.0,
            tm_ms: e.tm * 1000.0,
            twa_ms: e.twa * 1000.0,
            tb_ms: e.tb * 1000.0,
            tbl_ms: e.tbl * 1000.0,
            tbu_ms: e.tbu * 1000.0,
            load_factor,
            load_size_mb: d.load_size_bytes as f64 / BYTES_PER_MB,
            mip_bias: d.mip_bias,
            frames: self.frames,
            rejected_samples: self.rejected,
            stall_samples: self.stalls,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::controller::tests::close;

    #[test]
    fn eq5_weighted_max_latency_by_hand() {
        // t_w,i-1 = 50 ms, Δt = 10 ms: d = 0.04 s, (30·0.04)² = 1.44,
        // 1.44 · 0.01 = 0.0144, t_w = max(0.05 − 0.0144, 0.01) = 0.0356 s.
        assert!(close(weighted_max_latency(0.050, 0.010), 0.0356, 1e-12));
        // A frame slower than t_w,i-1 is taken immediately: d = 0.
        assert_eq!(weighted_max_latency(0.010, 0.040), 0.040);
        // Large d: t_w = 0.1 s, Δt = 5 ms: d = 0.095, (2.85)² · 0.005
        // = 0.0406125, t_w = 0.0593875 s ("widens the spike").
        assert!(close(weighted_max_latency(0.1, 0.005), 0.0593875, 1e-12));
        // Decay can never undershoot Δt.
        assert_eq!(weighted_max_latency(10.0, 0.005), 0.005);
    }

    #[test]
    fn eq6_threshold_both_branches_by_hand() {
        // t_wa = 20 ms > α = 16 ms: 0.15 · 20 + 0.85 · 16 = 3 + 13.6 = 16.6 ms.
        assert!(close(latency_threshold(0.020, 0.016), 0.0166, 1e-12));
        // t_wa = 10 ms ≤ α: 0.5 · 10 + 0.5 · 16 = 13 ms.
        assert!(close(latency_threshold(0.010, 0.016), 0.013, 1e-12));
        // The boundary t_wa = α takes the second branch and returns α.
        assert!(close(latency_threshold(0.016, 0.016), 0.016, 1e-15));
    }

    #[test]
    fn smoothstep_matches_glsl() {
        // t = (1 − 0)/(4 − 0) = 0.25: 0.0625 · (3 − 0.5) = 0.15625.
        assert!(close(smoothstep(0.0, 4.0, 1.0), 0.15625, 1e-15));
        assert_eq!(smoothstep(0.0, 4.0, -1.0), 0.0);
        assert_eq!(smoothstep(0.0, 4.0, 5.0), 1.0);
        // Fig. 4 right: β = 4, t_bl = 0, t_bu = 16.67 ms, t_b = 10 ms:
        // t = 10/(1.2·16.67) = 0.49990, s = 0.24990 · 2.00020 = 0.49985, b ≈ 1.9994.
        let b = 4.0 * smoothstep(0.0, 1.2 * 0.01667, 0.010);
        assert!(close(b, 1.9994, 1e-3));
        // Degenerate edges: hard step.
        assert_eq!(smoothstep(0.0, 0.0, 0.0), 0.0);
        assert_eq!(smoothstep(0.0, 0.0, 1e-9), 1.0);
    }
}
