//! Streaming workload per cycle: the adaptive controller of paper §3.4
//! (Eq. 4–7) and the other load policies behind one trait.
//!
//! Every policy is fed one frame latency per rendered frame through
//! [`LoadPolicy::update`] and answers with a [`Decision`]: the adaptive load
//! size `s` (bytes a streaming cycle may load) and the mipmap bias `b`.
//!
//! # Units
//!
//! Options and [`Telemetry`] speak milliseconds and MB (1 MB = 2^20 bytes, so
//! that `s_max` = 64 MB is exactly 1024 sparse blocks of 64 KiB). Inside
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
//! A frame latency above [`STALL_FACTOR`] × max(α, `t_wa`) is therefore a
//! *stall*: it still drives Eq. 4–7 for its own frame (its `t_w` exceeds
//! `t_m`, so `l` falls, and Eq. 5 decays `t_w` from it as the paper does),
//! but it enters none of the histories (`t_wa`, `t_b`, the edges of Eq. 7),
//! and is counted in [`Telemetry::stall_samples`]. Latencies within 4× of
//! the target or of the running average, which is all a working controller
//! sees, follow Eq. 4–7 exactly as the paper gives them. A render that
//! turns slow for good is not a stall: after [`STALL_RUN_FRAMES`]
//! consecutive stalls the slow frames enter the histories again.
//!
//! # Bad input
//!
//! A frame latency that is NaN, infinite or negative is rejected: the policy
//! keeps its state, returns its previous decision and counts the sample in
//! [`Telemetry::rejected_samples`]. A finite latency above
//! [`MAX_FRAME_LATENCY_MS`] is clamped to it. α must lie in (0,
//! [`MAX_ALPHA_MS`]] and β in [0, [`MAX_BETA`]]. With these rules every
//! output is finite, `l ∈ [0, 1]`, `s ∈ [s_min, s_max]` and `b ∈ [0, β]`.
//!
//! # Threading
//!
//! Policies are plain single-owner state machines (`Send`, not shared): the
//! render loop owns one and calls `update` once per frame.

use std::fmt;
use std::str::FromStr;

/// Bytes per MB in options and telemetry (MiB, so 64 MB = 1024 × 64 KiB).
pub const BYTES_PER_MB: f64 = 1_048_576.0;

/// Frame latencies above this (ms) are clamped to it: one minute.
pub const MAX_FRAME_LATENCY_MS: f64 = 60_000.0;

/// A frame latency above this multiple of max(α, `t_wa`) is a stall and
/// stays out of the histories (see the module docs).
pub const STALL_FACTOR: f64 = 4.0;

/// Consecutive stalls kept out of the histories; from the next one on, slow
/// frames are the new normal and enter them (a render that became slow).
pub const STALL_RUN_FRAMES: u32 = 8;

/// Largest target frame latency α accepted (ms): one second.
pub const MAX_ALPHA_MS: f64 = 1000.0;

/// Largest mipmap bias β accepted: levels beyond the finest-to-coarsest
/// span of a 32 768² texture have no effect.
pub const MAX_BETA: f64 = 16.0;

/// Samples of `t_w` averaged into `t_wa` (Eq. 6).
pub const TWA_SAMPLES: usize = 200;
/// Samples of `t_bl` / `t_bu` averaged into the edges (Eq. 7).
pub const EDGE_SAMPLES: usize = 40;
/// Samples of `t_w` averaged into `t_b` (Eq. 7).
pub const TB_SAMPLES: usize = 5;

/// Error building a policy from options or a name.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PolicyError {
    /// An option is out of its valid range.
    #[error("policy option `{name}` = {value:?} is invalid: expected {expected}")]
    InvalidOption {
        /// Option name as the command line spells it.
        name: &'static str,
        /// The rejected value.
        value: f64,
        /// What would be accepted.
        expected: &'static str,
    },
    /// No policy of that name.
    #[error("unknown load policy `{0}` (expected adaptive, headroom, baseline or fixed)")]
    UnknownPolicy(String),
}

/// What a streaming cycle may do: load at most `load_size_bytes` (the batch
/// stops once it exceeds this, Algorithm 1) and skip refinements with
/// `sampled mip + mip_bias >= loaded mip`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Decision {
    /// Adaptive load size `s` in bytes.
    pub load_size_bytes: u64,
    /// Mipmap bias `b`, in mip levels, within `[0, β]`.
    pub mip_bias: f64,
}

/// Every quantity of Eq. 4–7 after the latest update, in ms and MB.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "bench", derive(serde::Serialize))]
pub struct Telemetry {
    /// Frame latency Δt of the latest accepted sample (after clamping).
    pub frame_ms: f64,
    /// Weighted maximum frame latency `t_w` (Eq. 5).
    pub tw_ms: f64,
    /// Maximum frame latency threshold `t_m` (Eq. 6).
    pub tm_ms: f64,
    /// Mean of the previous 200 `t_w`, `t_wa` (Eq. 6).
    pub twa_ms: f64,
    /// Mean of the previous 5 `t_w`, `t_b` (Eq. 7).
    pub tb_ms: f64,
    /// Lower smoothstep edge `t_bl` before the 0.96 factor (Eq. 7).
    pub tbl_ms: f64,
    /// Upper smoothstep edge `t_bu` before the 1.2 factor (Eq. 7).
    pub tbu_ms: f64,
    /// Load factor `l` (Eq. 4), in `[0, 1]`.
    pub load_factor: f64,
    /// Load size `s` in MB.
    pub load_size_mb: f64,
    /// Mipmap bias `b`.
    pub mip_bias: f64,
    /// Frames accepted so far.
    pub frames: u64,
    /// Samples rejected as NaN, infinite or negative.
    pub rejected_samples: u64,
    /// Samples taken as stalls and kept out of the histories.
    pub stall_samples: u64,
}

/// A streaming workload policy, fed once per frame.
pub trait LoadPolicy: Send + fmt::Debug {
    /// Feed the latest frame latency in milliseconds and get the workload of
    /// the next streaming cycle. Never panics; see the module docs for how
    /// NaN, negative and huge values are handled.
    fn update(&mut self, frame_latency_ms: f64) -> Decision;
    /// The current decision without feeding a sample.
    fn decision(&self) -> Decision;
    /// Every quantity of Eq. 4–7 after the latest update.
    fn telemetry(&self) -> Telemetry;
    /// Which policy this is.
    fn kind(&self) -> PolicyKind;
    /// The bytes the streaming cycle applied in the latest frame (0 when none finished):
    /// what the load size actually carried, for policies that keep it near the demand.
    /// The paper's controller ignores it.
    fn observe_load(&mut self, _bytes_loaded: u64) {}
}

/// The selectable policies, by name: `adaptive`, `headroom`, `baseline`, `fixed`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum PolicyKind {
    /// Paper §3.4: adaptive load size and mipmap bias.
    Adaptive,
    /// Adaptive too, engaging only when the frame nears α ([`HeadroomPolicy`]).
    Headroom,
    /// No adaptive algorithms: `s = s_max`, `b = 0` (the paper's baseline rows).
    Baseline,
    /// User-given `s` and `b`.
    Fixed,
}

impl PolicyKind {
    /// The name `FromStr` accepts.
    pub fn name(self) -> &'static str {
        match self {
            PolicyKind::Adaptive => "adaptive",
            PolicyKind::Headroom => "headroom",
            PolicyKind::Baseline => "baseline",
            PolicyKind::Fixed => "fixed",
        }
    }

    /// Build this policy from options (validated).
    pub fn build(self, options: &PolicyOptions) -> Result<Box<dyn LoadPolicy>, PolicyError> {
        Ok(match self {
            PolicyKind::Adaptive => Box::new(AdaptivePolicy::new(options)?),
            PolicyKind::Headroom => Box::new(HeadroomPolicy::new(options)?),
            PolicyKind::Baseline => Box::new(BaselinePolicy::new(options)?),
            PolicyKind::Fixed => Box::new(FixedPolicy::new(options)?),
        })
    }
}

impl fmt::Display for PolicyKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for PolicyKind {
    type Err = PolicyError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "adaptive" => Ok(PolicyKind::Adaptive),
            "headroom" => Ok(PolicyKind::Headroom),
            "baseline" => Ok(PolicyKind::Baseline),
            "fixed" => Ok(PolicyKind::Fixed),
            _ => Err(PolicyError::UnknownPolicy(s.to_owned())),
        }
    }
}

/// Policy parameters; defaults are the paper's Table 2.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PolicyOptions {
    /// Target maximum frame latency α in ms (Table 2: 16).
    pub alpha_ms: f64,
    /// Maximum mipmap bias β (Table 2: 8).
    pub beta: f64,
    /// Maximum load size `s_max` in MB (Table 2: 64).
    pub s_max_mb: f64,
    /// Minimum load size `s_min` in bytes: one sparse block of the device
    /// (64 KiB on lavapipe; Table 2: 0.065 MB).
    pub s_min_bytes: u64,
    /// Load size of the `fixed` policy in MB.
    pub fixed_load_size_mb: f64,
    /// Mipmap bias of the `fixed` policy.
    pub fixed_mip_bias: f64,
}

impl Default for PolicyOptions {
    fn default() -> Self {
        PolicyOptions {
            alpha_ms: 16.0,
            beta: 8.0,
            s_max_mb: 64.0,
            s_min_bytes: 65_536,
            fixed_load_size_mb: 1.0,
            fixed_mip_bias: 0.0,
        }
    }
}

impl PolicyOptions {
    /// Check the options every policy uses (not the `fixed_*` ones); the
    /// error names the first bad one.
    pub fn validate(&self) -> Result<(), PolicyError> {
        let bad = |name, value, expected| PolicyError::InvalidOption { name, value, expected };
        if !(self.alpha_ms.is_finite() && self.alpha_ms > 0.0 && self.alpha_ms <= MAX_ALPHA_MS) {
            return Err(bad("alpha", self.alpha_ms, "a latency in (0, 1000] ms"));
        }
        if !(self.beta.is_finite() && (0.0..=MAX_BETA).contains(&self.beta)) {
            return Err(bad("beta", self.beta, "a bias in [0, 16] levels"));
        }
        if !(self.s_max_mb.is_finite() && self.s_max_mb > 0.0 && self.s_max_mb <= 1.0e6) {
            return Err(bad("s-max-mb", self.s_max_mb, "a size in (0, 1e6] MB"));
        }
        let s_min = self.s_min_bytes as f64;
        if self.s_min_bytes == 0 || s_min > self.s_max_bytes() {
            return Err(bad("s-min-bytes", s_min, "a size in [1 byte, s_max]"));
        }
        Ok(())
    }

    /// Check the options of the `fixed` policy as well (its size must lie
    /// in `[s_min, s_max]`, its bias in `[0, 16]` levels as `beta`'s).
    pub fn validate_fixed(&self) -> Result<(), PolicyError> {
        self.validate()?;
        let bad = |name, value, expected| PolicyError::InvalidOption { name, value, expected };
        let s_min = self.s_min_bytes as f64;
        let fixed = self.fixed_load_size_mb * BYTES_PER_MB;
        if !(fixed.is_finite() && fixed >= s_min && fixed <= self.s_max_bytes()) {
            return Err(bad("load-size-mb", self.fixed_load_size_mb, "a size in [s_min, s_max]"));
        }
        // Bounded as the adaptive policy's bias is (`beta`): a bias beyond every level of
        // any texture means the same as the largest.
        if !(self.fixed_mip_bias.is_finite() && (0.0..=MAX_BETA).contains(&self.fixed_mip_bias)) {
            return Err(bad("mip-bias", self.fixed_mip_bias, "a bias in [0, 16] levels"));
        }
        Ok(())
    }

    fn s_max_bytes(&self) -> f64 {
        self.s_max_mb * BYTES_PER_MB
    }
}

/// Fixed-capacity ring of the most recent samples.
#[derive(Clone, Debug)]
struct Ring<const N: usize> {
    buf: [f64; N],
    len: usize,
    next: usize,
}

impl<const N: usize> Ring<N> {
    fn new() -> Self {
        Ring {
            buf: [0.0; N],
            len: 0,
            next: 0,
        }
    }

    fn push(&mut self, v: f64) {
        self.buf[self.next] = v;
        self.next = (self.next + 1) % N;
        self.len = (self.len + 1).min(N);
    }

    /// The stored samples, in no particular order.
    fn samples(&self) -> &[f64] {
        &self.buf[..self.len]
    }

    /// The newest `k` samples (fewer if fewer exist).
    fn newest(&self, k: usize) -> impl Iterator<Item = f64> + '_ {
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
struct Estimator {
    alpha_s: f64,
    tw: f64,
    tw_history: Ring<TWA_SAMPLES>,
    tbl_history: Ring<EDGE_SAMPLES>,
    tbu_history: Ring<EDGE_SAMPLES>,
    frames: u64,
    rejected: u64,
    stalls: u64,
    /// Stalls in a row up to the latest sample.
    stall_run: u32,
}

/// One frame's measurements, seconds.
#[derive(Clone, Copy, Debug, Default)]
struct Estimate {
    dt: f64,
    /// The frame was taken as a stall and kept out of the histories.
    stall: bool,
    tw: f64,
    twa: f64,
    tm: f64,
    tb: f64,
    tbl: f64,
    tbu: f64,
}

impl Estimator {
    fn new(alpha_ms: f64) -> Self {
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
    fn step(&mut self, frame_latency_ms: f64) -> Option<Estimate> {
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

    fn telemetry(&self, e: &Estimate, load_factor: f64, d: Decision) -> Telemetry {
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
        let decision = Decision {
            load_size_bytes: options.s_min_bytes,
            mip_bias: 0.0,
        };
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
        self.decision = Decision {
            load_size_bytes: s.round() as u64,
            mip_bias: b.clamp(0.0, self.beta),
        };
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
/// The paper's controller ([`AdaptivePolicy`]) reacts to the relative swing of the
/// latency between its recent edges, so it raises the bias and holds the load size low
/// while every frame is far below α; this one leaves both alone until the frame nears α.
/// It shares the paper's bad-input rules and its stall rule: a frame far over the target
/// (see the module docs) shrinks the load size but enters none of the histories.
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
            decision: Decision {
                load_size_bytes: options.s_min_bytes,
                mip_bias: 0.0,
            },
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
        self.decision = Decision {
            load_size_bytes: self.load_bytes.round() as u64,
            mip_bias: bias.clamp(0.0, self.beta),
        };
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

/// A policy with a constant decision; still measures `t_w` and the other
/// latencies so that its telemetry compares with the adaptive one.
#[derive(Clone, Debug)]
struct ConstantPolicy {
    estimator: Estimator,
    load_factor: f64,
    decision: Decision,
    telemetry: Telemetry,
}

impl ConstantPolicy {
    fn new(options: &PolicyOptions, decision: Decision) -> Self {
        let load_factor = decision.load_size_bytes as f64 / options.s_max_bytes();
        ConstantPolicy {
            estimator: Estimator::new(options.alpha_ms),
            load_factor,
            decision,
            telemetry: Telemetry {
                load_factor,
                load_size_mb: decision.load_size_bytes as f64 / BYTES_PER_MB,
                mip_bias: decision.mip_bias,
                ..Telemetry::default()
            },
        }
    }

    fn update(&mut self, frame_latency_ms: f64) -> Decision {
        match self.estimator.step(frame_latency_ms) {
            Some(e) => self.telemetry = self.estimator.telemetry(&e, self.load_factor, self.decision),
            None => self.telemetry.rejected_samples = self.estimator.rejected,
        }
        self.decision
    }
}

/// No adaptive algorithms: `s = s_max`, `b = 0`, streaming as fast as the
/// load-time limit allows (the paper's "No adaptive algorithms" rows).
#[derive(Clone, Debug)]
pub struct BaselinePolicy(ConstantPolicy);

impl BaselinePolicy {
    /// Build from options (only `s_max` matters for the decision).
    pub fn new(options: &PolicyOptions) -> Result<Self, PolicyError> {
        options.validate()?;
        let decision = Decision {
            load_size_bytes: options.s_max_bytes().round() as u64,
            mip_bias: 0.0,
        };
        Ok(BaselinePolicy(ConstantPolicy::new(options, decision)))
    }
}

impl LoadPolicy for BaselinePolicy {
    fn update(&mut self, frame_latency_ms: f64) -> Decision {
        self.0.update(frame_latency_ms)
    }
    fn decision(&self) -> Decision {
        self.0.decision
    }
    fn telemetry(&self) -> Telemetry {
        self.0.telemetry
    }
    fn kind(&self) -> PolicyKind {
        PolicyKind::Baseline
    }
}

/// The user's `s` (`fixed_load_size_mb`) and `b` (`fixed_mip_bias`).
#[derive(Clone, Debug)]
pub struct FixedPolicy(ConstantPolicy);

impl FixedPolicy {
    /// Build from options; the fixed size must lie in `[s_min, s_max]`.
    pub fn new(options: &PolicyOptions) -> Result<Self, PolicyError> {
        options.validate_fixed()?;
        let decision = Decision {
            load_size_bytes: (options.fixed_load_size_mb * BYTES_PER_MB).round() as u64,
            mip_bias: options.fixed_mip_bias,
        };
        Ok(FixedPolicy(ConstantPolicy::new(options, decision)))
    }
}

impl LoadPolicy for FixedPolicy {
    fn update(&mut self, frame_latency_ms: f64) -> Decision {
        self.0.update(frame_latency_ms)
    }
    fn decision(&self) -> Decision {
        self.0.decision
    }
    fn telemetry(&self) -> Telemetry {
        self.0.telemetry
    }
    fn kind(&self) -> PolicyKind {
        PolicyKind::Fixed
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol
    }

    fn adaptive() -> AdaptivePolicy {
        AdaptivePolicy::new(&PolicyOptions::default()).expect("defaults are valid")
    }

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
    fn baseline_and_fixed_are_constant_but_measure() {
        let o = PolicyOptions {
            fixed_load_size_mb: 2.0,
            fixed_mip_bias: 1.5,
            ..PolicyOptions::default()
        };
        let mut base = PolicyKind::Baseline.build(&o).expect("valid");
        let mut fixed = PolicyKind::Fixed.build(&o).expect("valid");
        for ms in [5.0, 400.0, 5.0] {
            let d = base.update(ms);
            assert_eq!(d.load_size_bytes, 64 * 1_048_576);
            assert_eq!(d.mip_bias, 0.0);
            let d = fixed.update(ms);
            assert_eq!(d.load_size_bytes, 2 * 1_048_576);
            assert_eq!(d.mip_bias, 1.5);
        }
        // Same Eq. 5 measurement as the adaptive policy: 400 ms then a 5 ms
        // frame: d = 0.395, (11.85)²·0.005 = 0.7021 → t_w = max(−0.30, 0.005).
        assert!(close(base.telemetry().tw_ms, 5.0, 1e-12));
        assert_eq!(base.telemetry().load_factor, 1.0);
        assert!(close(fixed.telemetry().load_factor, 2.0 / 64.0, 1e-15));
    }

    #[test]
    fn names_parse_and_bad_options_are_named() {
        assert_eq!("adaptive".parse::<PolicyKind>(), Ok(PolicyKind::Adaptive));
        assert_eq!("Baseline".parse::<PolicyKind>(), Ok(PolicyKind::Baseline));
        assert_eq!("fixed".parse::<PolicyKind>(), Ok(PolicyKind::Fixed));
        assert!(matches!(
            "cw2020".parse::<PolicyKind>(),
            Err(PolicyError::UnknownPolicy(_))
        ));
        // Adaptive ignores the fixed policy's options.
        let fixed_too_big = PolicyOptions {
            fixed_load_size_mb: 65.0,
            ..PolicyOptions::default()
        };
        assert!(AdaptivePolicy::new(&fixed_too_big).is_ok());
        for (o, name) in [
            (
                PolicyOptions {
                    alpha_ms: f64::NAN,
                    ..PolicyOptions::default()
                },
                "alpha",
            ),
            (
                PolicyOptions {
                    beta: -1.0,
                    ..PolicyOptions::default()
                },
                "beta",
            ),
            (
                PolicyOptions {
                    alpha_ms: 1000.5,
                    ..PolicyOptions::default()
                },
                "alpha",
            ),
            (
                PolicyOptions {
                    alpha_ms: f64::INFINITY,
                    ..PolicyOptions::default()
                },
                "alpha",
            ),
            (
                PolicyOptions {
                    beta: 16.5,
                    ..PolicyOptions::default()
                },
                "beta",
            ),
            (
                PolicyOptions {
                    s_min_bytes: 0,
                    ..PolicyOptions::default()
                },
                "s-min-bytes",
            ),
            (
                PolicyOptions {
                    fixed_load_size_mb: 65.0,
                    ..PolicyOptions::default()
                },
                "load-size-mb",
            ),
            (
                PolicyOptions {
                    fixed_mip_bias: 1e300,
                    ..PolicyOptions::default()
                },
                "mip-bias",
            ),
            (
                PolicyOptions {
                    fixed_mip_bias: 16.5,
                    ..PolicyOptions::default()
                },
                "mip-bias",
            ),
        ] {
            match FixedPolicy::new(&o) {
                Err(PolicyError::InvalidOption { name: n, .. }) => assert_eq!(n, name),
                other => panic!("expected error for {name}, got {other:?}"),
            }
        }
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
        // Below α the size grows with the headroom left by the slowest recent frame:
        // peak 9 ms of 12 → × 1.25.
        assert!(close(
            headroom_load_size(1000.0, 1e9, 8.0, 9.0, 8.0, 12.0),
            1250.0,
            1e-9
        ));
        // A frame at α is past the aim (8 + 3.2 ms): eased back by √(3.2 / 4); at the aim,
        // held; a frame far over α cuts by at most 1/64.
        assert!(close(
            headroom_load_size(1000.0, 1e9, 12.0, 12.0, 8.0, 12.0),
            1000.0 * 0.8f64.sqrt(),
            1e-9
        ));
        assert_eq!(headroom_load_size(1000.0, 1e9, 11.2, 11.2, 8.0, 12.0), 1000.0);
        assert!(close(
            headroom_load_size(64_000.0, 1e9, 60_000.0, 60_000.0, 8.0, 12.0),
            1000.0,
            1e-9
        ));
        // A base at or over α leaves no room: the largest cut.
        assert!(close(
            headroom_load_size(64_000.0, 1e9, 13.0, 13.0, 13.0, 12.0),
            1000.0,
            1e-9
        ));
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
