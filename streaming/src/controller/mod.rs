//! Streaming workload per cycle: the adaptive controller of paper §3.4
//! (Eq. 4–7) and the other load policies behind one trait.
//!
//! Every policy is fed one frame latency per rendered frame through
//! [`LoadPolicy::update`] and answers with a [`Decision`]: the adaptive load
//! size `s` (bytes a streaming cycle may load) and the mipmap bias `b`.
//!
//! - [`paper`]: the paper's controller ([`AdaptivePolicy`]): the units of
//!   Eq. 4–7, the choices where the paper is ambiguous, and the stall rule
//!   where it departs from the paper.
//! - [`headroom`]: [`HeadroomPolicy`], adaptive too, engaging only when the
//!   frame nears α.
//! - The latency measurements both share (Eq. 5, 6 and the edges of Eq. 7)
//!   with the bad-input and stall rules: a private module whose public items
//!   are re-exported here.
//! - This module: the trait, its options and errors, and the constant
//!   policies ([`ConstantPolicy::baseline`], [`ConstantPolicy::fixed`]).
//!
//! # Units
//!
//! Options and [`Telemetry`] speak milliseconds and MB (1 MB = 2^20 bytes, so
//! that `s_max` = 64 MB is exactly 1024 sparse blocks of 64 KiB). Inside
//! Eq. 4–7, **latencies are in seconds** ([`paper`] says why).
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

mod estimator;
pub mod headroom;
pub mod paper;
pub mod predictive;

use estimator::Estimator;
// Every item keeps its path `controller::X`.
pub use estimator::{
    latency_threshold, smoothstep, weighted_max_latency, EDGE_SAMPLES, MAX_FRAME_LATENCY_MS, STALL_FACTOR,
    STALL_RUN_FRAMES, TB_SAMPLES, TWA_SAMPLES,
};
pub use headroom::{
    headroom_load_size, HeadroomPolicy, BASE_FRAMES, BIAS_FULL_AT, DEMAND_FLOOR_BLOCKS, DEMAND_FRAMES, GROWTH_TARGET,
    HEADROOM_FRAMES, HEADROOM_GAIN, MAX_PROBE_STEP, MAX_SHRINK, OVERSHOOT_TARGET, PROBE_GAIN, VISIBLE_COST,
};
pub use paper::{load_polynomial, next_load_factor, AdaptivePolicy};
pub use predictive::{BindCostFit, OnlineFit, PredictivePolicy};

use crate::bind_latency::{BatchShape, BindLatencyPreset};

/// Bytes per MB in options and telemetry (MiB, so 64 MB = 1024 × 64 KiB).
pub const BYTES_PER_MB: f64 = 1_048_576.0;

/// Largest target frame latency α accepted (ms): one second.
pub const MAX_ALPHA_MS: f64 = 1000.0;

/// Largest mipmap bias β accepted: levels beyond the finest-to-coarsest
/// span of a 32 768² texture have no effect.
pub const MAX_BETA: f64 = 16.0;

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
    #[error("unknown load policy `{0}` (expected adaptive, headroom, predictive, baseline or fixed)")]
    UnknownPolicy(String),
}

/// What a streaming cycle may do: load at most `load_size_bytes` (the batch
/// stops once it exceeds this, Algorithm 1) and skip refinements with
/// `sampled mip + mip_bias >= loaded mip`; with a block budget, also stop before the
/// sparse blocks the cycle binds pass it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Decision {
    /// Adaptive load size `s` in bytes.
    pub load_size_bytes: u64,
    /// Mipmap bias `b`, in mip levels, within `[0, β]`.
    pub mip_bias: f64,
    /// The most sparse blocks the cycle may bind ([`PredictivePolicy`]); `None`: the
    /// load size alone bounds the cycle (the paper's Algorithm 1).
    pub block_budget: Option<BlockBudget>,
}

impl Decision {
    /// A load size and a bias, with no block budget.
    pub fn new(load_size_bytes: u64, mip_bias: f64) -> Self {
        Decision {
            load_size_bytes,
            mip_bias,
            block_budget: None,
        }
    }
}

/// The sparse blocks a cycle may bind: what its predicted bind cost fits.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BlockBudget {
    /// Blocks the cycle's mips may take.
    pub blocks: u64,
    /// Bytes of one sparse block: a mip of a block or more takes `⌈bytes / block_bytes⌉`;
    /// smaller ones share blocks ([`BlockBudget::blocks_of_cycle`]).
    pub block_bytes: u64,
}

impl BlockBudget {
    /// Whether a mip of `bytes` binds whole blocks of its own (otherwise it shares blocks
    /// with the neighbouring textures' levels of the same layer).
    pub fn owns_blocks(&self, bytes: u64) -> bool {
        bytes >= self.block_bytes.max(1)
    }

    /// The blocks a cycle binds for mips of a block or more totalling `own` blocks and
    /// smaller mips totalling `shared_bytes`: the small ones counted by their bytes, as
    /// the levels of a layer's textures share its blocks (a block of one level holds many
    /// textures' regions). Charging each small mip a whole block (as before) held a cycle
    /// of the Berlin-sized city, whose mips average 12 KB against 64 KB blocks, to 50 mips
    /// and 0.65 MB when its budget allowed 3.2 MB.
    pub fn blocks_of_cycle(&self, own: u64, shared_bytes: u64) -> u64 {
        own.saturating_add(self.whole_blocks(shared_bytes))
    }

    /// The whole blocks `bytes` fill: a mip's own where it [owns blocks](Self::owns_blocks).
    pub fn whole_blocks(&self, bytes: u64) -> u64 {
        bytes.div_ceil(self.block_bytes.max(1))
    }

    /// The blocks a mip of `bytes` costs alone, for ranking mips by error per byte: its
    /// whole blocks, or its bytes' share of one.
    pub fn blocks_of(&self, bytes: u64) -> f64 {
        if self.owns_blocks(bytes) {
            self.whole_blocks(bytes) as f64
        } else {
            bytes as f64 / self.block_bytes.max(1) as f64
        }
    }
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
    /// The shape of the bind submission the latest frame carried (blocks bound and
    /// unbound, their runs) and the bytes it applied; the streamer calls it once per frame
    /// in place of [`observe_load`](Self::observe_load), which it calls by default.
    fn observe_batch(&mut self, _shape: BatchShape, bytes_loaded: u64) {
        self.observe_load(bytes_loaded);
    }
}

/// The selectable policies, by name: `adaptive`, `headroom`, `baseline`, `fixed`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum PolicyKind {
    /// Paper §3.4: adaptive load size and mipmap bias.
    Adaptive,
    /// Adaptive too, engaging only when the frame nears α ([`HeadroomPolicy`]).
    Headroom,
    /// Loads what the predicted bind cost fits under α ([`PredictivePolicy`]).
    Predictive,
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
            PolicyKind::Predictive => "predictive",
            PolicyKind::Baseline => "baseline",
            PolicyKind::Fixed => "fixed",
        }
    }

    /// Build this policy from options (validated).
    pub fn build(self, options: &PolicyOptions) -> Result<Box<dyn LoadPolicy>, PolicyError> {
        Ok(match self {
            PolicyKind::Adaptive => Box::new(AdaptivePolicy::new(options)?),
            PolicyKind::Headroom => Box::new(HeadroomPolicy::new(options)?),
            PolicyKind::Predictive => Box::new(PredictivePolicy::new(options)?),
            PolicyKind::Baseline => Box::new(ConstantPolicy::baseline(options)?),
            PolicyKind::Fixed => Box::new(ConstantPolicy::fixed(options)?),
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
            "predictive" => Ok(PolicyKind::Predictive),
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
    /// The bind-latency preset that describes the device, for the predictive
    /// controller's cost fit; `None`: it learns the device's cost from the frames.
    pub bind_cost: Option<BindLatencyPreset>,
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
            bind_cost: None,
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

/// A policy with a constant decision; still measures `t_w` and the other
/// latencies so that its telemetry compares with the adaptive one. Two of them:
/// [`ConstantPolicy::baseline`] and [`ConstantPolicy::fixed`].
#[derive(Clone, Debug)]
pub struct ConstantPolicy {
    kind: PolicyKind,
    estimator: Estimator,
    load_factor: f64,
    decision: Decision,
    telemetry: Telemetry,
}

impl ConstantPolicy {
    /// No adaptive algorithms: `s = s_max`, `b = 0`, streaming as fast as the
    /// load-time limit allows (the paper's "No adaptive algorithms" rows).
    /// Only `s_max` of the options matters for the decision.
    pub fn baseline(options: &PolicyOptions) -> Result<Self, PolicyError> {
        options.validate()?;
        let decision = Decision::new(options.s_max_bytes().round() as u64, 0.0);
        Ok(Self::new(PolicyKind::Baseline, options, decision))
    }

    /// The user's `s` (`fixed_load_size_mb`) and `b` (`fixed_mip_bias`); the
    /// fixed size must lie in `[s_min, s_max]`.
    pub fn fixed(options: &PolicyOptions) -> Result<Self, PolicyError> {
        options.validate_fixed()?;
        let decision = Decision::new(
            (options.fixed_load_size_mb * BYTES_PER_MB).round() as u64,
            options.fixed_mip_bias,
        );
        Ok(Self::new(PolicyKind::Fixed, options, decision))
    }

    fn new(kind: PolicyKind, options: &PolicyOptions, decision: Decision) -> Self {
        let load_factor = decision.load_size_bytes as f64 / options.s_max_bytes();
        ConstantPolicy {
            kind,
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
}

impl LoadPolicy for ConstantPolicy {
    fn update(&mut self, frame_latency_ms: f64) -> Decision {
        match self.estimator.step(frame_latency_ms) {
            Some(e) => self.telemetry = self.estimator.telemetry(&e, self.load_factor, self.decision),
            None => self.telemetry.rejected_samples = self.estimator.rejected,
        }
        self.decision
    }
    fn decision(&self) -> Decision {
        self.decision
    }
    fn telemetry(&self) -> Telemetry {
        self.telemetry
    }
    fn kind(&self) -> PolicyKind {
        self.kind
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Shared by the tests of every controller module.
    pub(super) fn close(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol
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
        // Each option out of range, named as the command line spells it.
        type Edit = fn(&mut PolicyOptions);
        let cases: [(&str, Edit); 9] = [
            ("alpha", |o| o.alpha_ms = f64::NAN),
            ("beta", |o| o.beta = -1.0),
            ("alpha", |o| o.alpha_ms = 1000.5),
            ("alpha", |o| o.alpha_ms = f64::INFINITY),
            ("beta", |o| o.beta = 16.5),
            ("s-min-bytes", |o| o.s_min_bytes = 0),
            ("load-size-mb", |o| o.fixed_load_size_mb = 65.0),
            ("mip-bias", |o| o.fixed_mip_bias = 1e300),
            ("mip-bias", |o| o.fixed_mip_bias = 16.5),
        ];
        for (name, edit) in cases {
            let mut o = PolicyOptions::default();
            edit(&mut o);
            match ConstantPolicy::fixed(&o) {
                Err(PolicyError::InvalidOption { name: n, .. }) => assert_eq!(n, name),
                other => panic!("expected error for {name}, got {other:?}"),
            }
        }
    }

    #[test]
    fn small_mips_share_blocks_and_large_ones_take_their_own() {
        let budget = BlockBudget {
            blocks: 50,
            block_bytes: 65_536,
        };
        // A cycle of the Berlin-sized city: 200 mips of 12 KB fill 38 blocks together, so
        // all of them fit 50; charged a block each, 50 would.
        assert_eq!(budget.blocks_of_cycle(0, 200 * 12_288), 38);
        assert!(!budget.owns_blocks(12_288) && budget.owns_blocks(65_536));
        // A 2-block mip and a 100-byte one: 2 + 1.
        assert_eq!(budget.blocks_of_cycle(2, 100), 3);
        assert_eq!(budget.blocks_of(131_073), 3.0);
        assert_eq!(budget.blocks_of(16_384), 0.25);
    }
}
