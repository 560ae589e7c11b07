//! The predictive controller ([`PredictivePolicy`]): each cycle loads what its predicted
//! bind cost fits in the room a frame has under α, no more and no less.
//!
//! The paper's controller and the headroom one learn what a batch costs from the
//! latencies of the frames after it, two or three frames late; both therefore grow
//! slowly and cut hard, and after a jump in the view the load size is far below what the
//! frame could afford. This one predicts the cost of a batch from its blocks *before*
//! the cycle runs, with a per-device fit of the bind cost ([`BindCostFit`]):
//!
//! ```text
//! cost(n, bind runs, unbind runs) = k0 + k1·n + k2·n² + k3·bind runs + k4·unbind runs
//! ```
//!
//! over the blocks `n` a submission binds and unbinds, which holds every preset of
//! [`crate::bind_latency`] exactly (their expected cost; spikes are unpredictable by
//! definition). A device no preset describes is learned online ([`OnlineFit`]): the
//! frames' measured latencies, less the render's, regressed on the shapes of the batches
//! they carried.
//!
//! Each frame it estimates the render's own latency (`base`: the frame's latency less
//! the predicted cost of the batch it carried, median of the latest
//! [`BASE_FRAMES_PREDICTIVE`]), and gives the next cycle the most blocks `m` whose
//! predicted cost fits [`ROOM_SHARE`] of `α − base`, counting the unbinds and runs the
//! binds of recent batches brought with them. The loader stops a cycle before its blocks
//! pass `m` ([`Decision::block_budget`]). The mip bias stays 0 unless the render alone is
//! over α (then `b = β·smoothstep(α, 1.5α, base)`): the bias is the lever of last resort.

use super::estimator::{Estimator, Ring};
use super::{
    smoothstep, BlockBudget, Decision, LoadPolicy, PolicyError, PolicyKind, PolicyOptions, Telemetry, BIAS_FULL_AT,
    BYTES_PER_MB,
};
use crate::bind_latency::{BatchShape, BindLatencyModel, BindLatencyPreset};

/// Frames whose base estimates (latency less predicted bind cost) give the render's
/// latency by their median: odd, so the median is a sample; a third of a second at 60 Hz,
/// so a spike of one frame in ten never moves it.
pub const BASE_FRAMES_PREDICTIVE: usize = 21;
/// The share of the room under α the predicted cost of a cycle may take: the rest is
/// left for what no model predicts (the copies' time and a render that varies).
pub const ROOM_SHARE: f64 = 0.9;
/// Batches whose blocks and runs per bound block scale the planned blocks into a
/// submission's shape (how many blocks evictions unbind per block bound, how many runs).
pub const SHAPE_FRAMES: usize = 32;
/// Host frames between a batch's submission and the latency that carries it: a host
/// passes `end_frame` the latency of its previous frame, whose batch the streamer
/// observed one frame before the one it observed last.
pub const LATENCY_LAG: usize = 1;
/// Scale of the fit's block features: coefficients stay of similar size.
const BLOCK_SCALE: f64 = 64.0;
/// Features of the cost model.
const FEATURES: usize = 5;

/// The per-device fit of what a bind submission costs, in milliseconds:
/// `k0 + k1·n + k2·n² + k3·bind runs + k4·unbind runs` for `n` blocks bound and unbound,
/// an empty submission costing nothing.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BindCostFit {
    /// Coefficients over [`features`] (scaled block counts), ms.
    coefficients: [f64; FEATURES],
}

/// The fit's features of a batch: 1, n, n², bind runs, unbind runs, block counts divided
/// by [`BLOCK_SCALE`].
fn features(shape: BatchShape) -> [f64; FEATURES] {
    let n = shape.blocks() as f64 / BLOCK_SCALE;
    [
        1.0,
        n,
        n * n,
        shape.bind_runs as f64 / BLOCK_SCALE,
        shape.unbind_runs as f64 / BLOCK_SCALE,
    ]
}

/// The batches a per-device fit is made from, as a bind benchmark measures them: 1 to
/// 1,024 blocks, bound contiguous (4 blocks a run, a 2048² BC1 level's row) and scattered
/// (a run each), and the same unbound.
fn calibration_shapes() -> Vec<BatchShape> {
    let mut shapes = Vec::new();
    for blocks in [1u64, 2, 4, 8, 16, 32, 64, 128, 256, 512, 768, 1024] {
        let contiguous = blocks.div_ceil(4);
        shapes.push(BatchShape::binds(blocks, contiguous));
        shapes.push(BatchShape::binds(blocks, blocks));
        shapes.push(BatchShape {
            unbound: blocks,
            unbind_runs: contiguous,
            ..BatchShape::default()
        });
        shapes.push(BatchShape {
            bound: blocks / 2,
            bind_runs: blocks / 2,
            unbound: blocks - blocks / 2,
            unbind_runs: (blocks - blocks / 2).max(1),
        });
    }
    shapes
}

impl BindCostFit {
    /// Nothing costs anything.
    pub fn zero() -> Self {
        BindCostFit {
            coefficients: [0.0; FEATURES],
        }
    }

    /// The least-squares fit of `samples` (a batch's shape and its measured cost in ms),
    /// pulled toward `prior` with weight `ridge` (0: none). `None` when the samples
    /// cannot determine the fit (too few, or all the same shape) and `ridge` is 0.
    pub fn least_squares(samples: &[(BatchShape, f64)], prior: &BindCostFit, ridge: f64) -> Option<Self> {
        let mut normal = NormalEquations::new();
        for &(shape, ms) in samples {
            if shape.blocks() > 0 && ms.is_finite() {
                normal.add(&features(shape), ms, 1.0);
            }
        }
        normal
            .solve(prior, ridge)
            .map(|coefficients| BindCostFit { coefficients })
    }

    /// The fit of a bind-latency preset: its expected cost over calibration batches of 1 to
    /// 1,024 blocks, contiguous, scattered and unbound, as a bind benchmark measures them
    /// (for `h200-linux` the preset is itself the least-squares fit of the H200's measured
    /// table; for `desktop` the paper's calibration).
    pub fn for_preset(preset: BindLatencyPreset) -> Self {
        let model = BindLatencyModel::preset(preset);
        let samples: Vec<(BatchShape, f64)> = calibration_shapes()
            .into_iter()
            .map(|shape| (shape, model.expected_cost_s(shape) * 1000.0))
            .collect();
        // The preset's terms are the fit's features, so the fit is exact; a preset with
        // no cost gives the zero fit.
        Self::least_squares(&samples, &Self::zero(), 0.0).unwrap_or_else(Self::zero)
    }

    /// Predicted cost (ms) of a submission of `shape`: 0 when empty, never negative.
    pub fn predict_ms(&self, shape: BatchShape) -> f64 {
        if shape.blocks() == 0 {
            return 0.0;
        }
        let x = features(shape);
        let cost: f64 = x.iter().zip(&self.coefficients).map(|(x, k)| x * k).sum();
        if cost.is_finite() {
            cost.max(0.0)
        } else {
            0.0
        }
    }
}

/// Weighted normal equations of a least-squares fit over the [`features`].
#[derive(Clone, Debug)]
struct NormalEquations {
    xtx: [[f64; FEATURES]; FEATURES],
    xty: [f64; FEATURES],
}

impl NormalEquations {
    fn new() -> Self {
        NormalEquations {
            xtx: [[0.0; FEATURES]; FEATURES],
            xty: [0.0; FEATURES],
        }
    }

    fn add(&mut self, x: &[f64; FEATURES], y: f64, weight: f64) {
        for i in 0..FEATURES {
            for j in 0..FEATURES {
                self.xtx[i][j] += weight * x[i] * x[j];
            }
            self.xty[i] += weight * x[i] * y;
        }
    }

    /// Scales every sample so far by `factor` (exponential forgetting).
    fn decay(&mut self, factor: f64) {
        for i in 0..FEATURES {
            for j in 0..FEATURES {
                self.xtx[i][j] *= factor;
            }
            self.xty[i] *= factor;
        }
    }

    /// The coefficients minimising the squared residuals plus `ridge·|k − prior|²`;
    /// `None` when singular.
    fn solve(&self, prior: &BindCostFit, ridge: f64) -> Option<[f64; FEATURES]> {
        let mut a = self.xtx;
        let mut b = self.xty;
        for i in 0..FEATURES {
            a[i][i] += ridge;
            b[i] += ridge * prior.coefficients[i];
        }
        // Gaussian elimination with partial pivoting.
        let scale = a
            .iter()
            .flatten()
            .fold(0.0f64, |m, v| m.max(v.abs()))
            .max(f64::MIN_POSITIVE);
        for col in 0..FEATURES {
            let pivot = (col..FEATURES).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))?;
            if a[pivot][col].abs() <= scale * 1e-12 {
                return None;
            }
            a.swap(col, pivot);
            b.swap(col, pivot);
            let (upper, lower) = a.split_at_mut(col + 1);
            let pivot_row = &upper[col];
            for (offset, row) in lower.iter_mut().enumerate() {
                let f = row[col] / pivot_row[col];
                for (x, p) in row.iter_mut().zip(pivot_row).skip(col) {
                    *x -= f * p;
                }
                b[col + 1 + offset] -= f * b[col];
            }
        }
        let mut k = [0.0; FEATURES];
        for row in (0..FEATURES).rev() {
            let rest: f64 = (row + 1..FEATURES).map(|j| a[row][j] * k[j]).sum();
            k[row] = (b[row] - rest) / a[row][row];
        }
        k.iter().all(|v| v.is_finite()).then_some(k)
    }
}

/// A bind-cost fit learned from a device's frames: exponentially forgetting least
/// squares, pulled toward a prior (the `lavapipe` fit: cheap and linear) until the
/// frames say otherwise. A sample far above the prediction (a driver's stall, which no
/// batch shape explains) is clipped so that one stall does not teach a steep curve.
#[derive(Clone, Debug)]
pub struct OnlineFit {
    normal: NormalEquations,
    prior: BindCostFit,
    fit: BindCostFit,
    samples: u64,
}

/// Weight of the prior against the frames: the equivalent of this many unit samples.
const ONLINE_RIDGE: f64 = 1e-3;
/// Per-sample forgetting: the fit follows a device over about a thousand batches.
const ONLINE_FORGET: f64 = 0.999;
/// A sample counts at most this many times its prediction plus [`ONLINE_CLIP_MS`].
const ONLINE_CLIP_FACTOR: f64 = 3.0;
/// See [`ONLINE_CLIP_FACTOR`].
const ONLINE_CLIP_MS: f64 = 2.0;
/// Samples before clipping applies (the first ones have nothing to be clipped against).
const ONLINE_WARMUP: u64 = 16;

impl OnlineFit {
    /// A fit that starts at `prior`.
    pub fn new(prior: BindCostFit) -> Self {
        OnlineFit {
            normal: NormalEquations::new(),
            prior,
            fit: prior,
            samples: 0,
        }
    }

    /// Learns that a submission of `shape` cost `ms`.
    pub fn observe(&mut self, shape: BatchShape, ms: f64) {
        if shape.blocks() == 0 || !ms.is_finite() {
            return;
        }
        let predicted = self.fit.predict_ms(shape);
        let y = if self.samples >= ONLINE_WARMUP {
            ms.clamp(0.0, ONLINE_CLIP_FACTOR * predicted + ONLINE_CLIP_MS)
        } else {
            ms.max(0.0)
        };
        self.normal.decay(ONLINE_FORGET);
        self.normal.add(&features(shape), y, 1.0);
        self.samples += 1;
        if let Some(k) = self.normal.solve(&self.prior, ONLINE_RIDGE) {
            self.fit = BindCostFit { coefficients: k };
        }
    }

    /// The current fit.
    pub fn fit(&self) -> &BindCostFit {
        &self.fit
    }

    /// Samples learned from.
    pub fn samples(&self) -> u64 {
        self.samples
    }
}

/// Where the predictive controller's bind-cost fit comes from.
#[derive(Clone, Debug)]
enum CostModel {
    /// A device a preset describes.
    Known(BindCostFit),
    /// Learned from the frames.
    Learned(Box<OnlineFit>),
}

impl CostModel {
    fn fit(&self) -> &BindCostFit {
        match self {
            CostModel::Known(fit) => fit,
            CostModel::Learned(online) => online.fit(),
        }
    }
}

/// A controller that loads, every cycle, the blocks whose predicted bind cost fits the
/// room under α; see the [module docs](self).
#[derive(Clone, Debug)]
pub struct PredictivePolicy {
    estimator: Estimator,
    alpha_ms: f64,
    beta: f64,
    s_max_bytes: f64,
    block_bytes: u64,
    cost: CostModel,
    /// Batches observed, newest last, until their latency arrives.
    pending_shapes: Vec<BatchShape>,
    /// The render's latency estimates (latency less the predicted cost of its batch).
    bases: Ring<BASE_FRAMES_PREDICTIVE>,
    /// Recent non-empty batches: blocks bound, blocks in all, bind runs, unbind runs.
    shapes: Vec<BatchShape>,
    decision: Decision,
    telemetry: Telemetry,
}

impl PredictivePolicy {
    /// A fresh controller predicting with the fit of `preset`, or learning the device's
    /// cost from its frames when `None`.
    pub fn new(options: &PolicyOptions) -> Result<Self, PolicyError> {
        options.validate()?;
        let cost = match options.bind_cost {
            Some(preset) => CostModel::Known(BindCostFit::for_preset(preset)),
            None => CostModel::Learned(Box::new(OnlineFit::new(BindCostFit::for_preset(
                BindLatencyPreset::Lavapipe,
            )))),
        };
        let mut policy = PredictivePolicy {
            estimator: Estimator::new(options.alpha_ms),
            alpha_ms: options.alpha_ms,
            beta: options.beta,
            s_max_bytes: options.s_max_bytes(),
            block_bytes: options.s_min_bytes,
            cost,
            pending_shapes: Vec::new(),
            bases: Ring::new(),
            shapes: Vec::new(),
            decision: Decision {
                load_size_bytes: options.s_min_bytes,
                mip_bias: 0.0,
                block_budget: None,
            },
            telemetry: Telemetry::default(),
        };
        // Before any frame the room is α less nothing: the first cycle, which binds
        // the coarsest levels of the first view, is sized by the model alone.
        policy.decide(0.0);
        Ok(policy)
    }

    /// The fit predictions come from.
    pub fn cost_fit(&self) -> &BindCostFit {
        self.cost.fit()
    }

    /// The render's latency as estimated now (ms).
    pub fn base_ms(&self) -> f64 {
        median(self.bases.samples()).unwrap_or(0.0)
    }

    /// The shape a cycle planning `blocks` bound blocks is expected to submit, from the
    /// recent batches: evictions unbind blocks for the ones bound, and runs follow the
    /// layout.
    fn expected_shape(&self, blocks: u64) -> BatchShape {
        let (bound, unbound, bind_runs, unbind_runs) =
            self.shapes.iter().fold((0u64, 0u64, 0u64, 0u64), |(b, u, br, ur), s| {
                (b + s.bound, u + s.unbound, br + s.bind_runs, ur + s.unbind_runs)
            });
        if bound == 0 {
            // Nothing seen yet: every block its own run, nothing unbound.
            return BatchShape::binds(blocks, blocks);
        }
        let per = |x: u64| (blocks as f64 * x as f64 / bound as f64).ceil() as u64;
        BatchShape {
            bound: blocks,
            unbound: per(unbound),
            bind_runs: per(bind_runs).clamp(1, blocks.max(1)),
            unbind_runs: per(unbind_runs),
        }
    }

    /// The most blocks a cycle may bind so that its predicted cost fits `room_ms`; at
    /// least one (a cycle always makes progress), at most `s_max`'s.
    pub fn blocks_for_room(&self, room_ms: f64) -> u64 {
        let most = ((self.s_max_bytes / self.block_bytes as f64).floor() as u64).max(1);
        let fits = |blocks: u64| self.cost.fit().predict_ms(self.expected_shape(blocks)) <= room_ms;
        if !fits(1) {
            return 1;
        }
        let (mut lo, mut hi) = (1u64, most);
        if fits(hi) {
            return hi;
        }
        // Cost grows with the blocks: the largest count that fits, by bisection.
        while hi - lo > 1 {
            let mid = lo + (hi - lo) / 2;
            if fits(mid) {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        lo
    }

    fn decide(&mut self, base_ms: f64) {
        let room_ms = ((self.alpha_ms - base_ms) * ROOM_SHARE).max(0.0);
        let blocks = self.blocks_for_room(room_ms);
        let bias = self.beta * smoothstep(self.alpha_ms, BIAS_FULL_AT * self.alpha_ms, base_ms);
        // Room for one block or none (the render alone fills α): the paper's floor, s =
        // s_min in bytes, with no block budget. A budget of one block would take one mip a
        // cycle, where s_min's bytes take the coarse levels of several textures that share
        // a block; the floor costs the frame no more than the one block it replaces.
        let block_budget = (blocks > 1).then_some(BlockBudget {
            blocks,
            block_bytes: self.block_bytes,
        });
        self.decision = Decision {
            load_size_bytes: blocks.saturating_mul(self.block_bytes),
            mip_bias: bias.clamp(0.0, self.beta),
            block_budget,
        };
    }
}

/// Median of `samples` (the upper one of an even count); `None` when empty.
fn median(samples: &[f64]) -> Option<f64> {
    let mut sorted = samples.to_vec();
    sorted.sort_by(f64::total_cmp);
    sorted.get(sorted.len() / 2).copied()
}

impl LoadPolicy for PredictivePolicy {
    fn update(&mut self, frame_latency_ms: f64) -> Decision {
        let Some(e) = self.estimator.step(frame_latency_ms) else {
            self.telemetry.rejected_samples = self.estimator.rejected;
            return self.decision;
        };
        let frame_ms = e.dt * 1000.0;
        // The batch this latency carries: observed LATENCY_LAG batches before the newest.
        let carried = self
            .pending_shapes
            .len()
            .checked_sub(LATENCY_LAG + 1)
            .map(|i| self.pending_shapes[i])
            .unwrap_or_default();
        let base = self.base_ms();
        if let CostModel::Learned(online) = &mut self.cost {
            if self.bases.samples().len() >= BASE_FRAMES_PREDICTIVE / 2 {
                online.observe(carried, frame_ms - base);
            }
        }
        let predicted = self.cost.fit().predict_ms(carried);
        // A stall (far over every recent frame) is not the render's latency.
        if !e.stall {
            self.bases.push((frame_ms - predicted).max(0.0));
        }
        let base = self.base_ms();
        self.decide(base);
        self.telemetry = self.estimator.telemetry(
            &e,
            self.decision.load_size_bytes as f64 / self.s_max_bytes,
            self.decision,
        );
        self.decision
    }

    fn decision(&self) -> Decision {
        self.decision
    }

    fn telemetry(&self) -> Telemetry {
        let mut t = self.telemetry;
        t.load_size_mb = self.decision.load_size_bytes as f64 / BYTES_PER_MB;
        t
    }

    fn kind(&self) -> PolicyKind {
        PolicyKind::Predictive
    }

    fn observe_batch(&mut self, shape: BatchShape, _bytes_loaded: u64) {
        self.pending_shapes.push(shape);
        if self.pending_shapes.len() > LATENCY_LAG + 1 {
            self.pending_shapes.remove(0);
        }
        if shape.bound > 0 {
            self.shapes.push(shape);
            if self.shapes.len() > SHAPE_FRAMES {
                self.shapes.remove(0);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;

    fn presets() -> [BindLatencyPreset; 3] {
        [
            BindLatencyPreset::Desktop,
            BindLatencyPreset::H200Linux,
            BindLatencyPreset::Lavapipe,
        ]
    }

    /// Batches of 1 to 1,024 blocks as a cycle submits them: bound in rows of up to
    /// four blocks, or scattered, with and without unbinds.
    fn test_shapes() -> Vec<BatchShape> {
        let mut shapes = Vec::new();
        for blocks in 1..=1024u64 {
            shapes.push(BatchShape::binds(blocks, blocks.div_ceil(4)));
            shapes.push(BatchShape::binds(blocks, blocks));
            shapes.push(BatchShape {
                bound: blocks,
                bind_runs: blocks.div_ceil(3),
                unbound: blocks / 3,
                unbind_runs: (blocks / 3).div_ceil(2),
            });
        }
        shapes
    }

    #[test]
    fn the_preset_fits_predict_each_model_within_20_percent() {
        for preset in presets() {
            let model = BindLatencyModel::preset(preset);
            let fit = BindCostFit::for_preset(preset);
            for shape in test_shapes() {
                let expected = model.expected_cost_s(shape) * 1000.0;
                let predicted = fit.predict_ms(shape);
                assert!(
                    (predicted - expected).abs() <= 0.2 * expected,
                    "{preset}: {shape:?} predicted {predicted} ms, model {expected} ms"
                );
            }
        }
        assert_eq!(
            BindCostFit::for_preset(BindLatencyPreset::None).predict_ms(BatchShape::binds(9, 9)),
            0.0
        );
        assert_eq!(
            BindCostFit::for_preset(BindLatencyPreset::Desktop).predict_ms(BatchShape::default()),
            0.0
        );
    }

    #[test]
    fn an_online_fit_learns_each_model_from_noisy_latencies_within_20_percent() {
        // Frames of an 8 ms render ± 0.3 ms carrying batches of 1 to 1,024 blocks, each
        // latency the model's drawn cost (jitter and spikes included): what a host that
        // measures its frames feeds the controller, less the base it estimates.
        for preset in presets() {
            let model = BindLatencyModel::preset(preset);
            let mut rng = SplitMix64::stream(7, 1);
            let mut online = OnlineFit::new(BindCostFit::for_preset(BindLatencyPreset::Lavapipe));
            for _ in 0..3000 {
                let blocks = 1 + (rng.next_f64().powi(2) * 1023.0) as u64;
                let scattered = rng.next_f64() < 0.5;
                let runs = if scattered { blocks } else { blocks.div_ceil(4) };
                let shape = BatchShape::binds(blocks, runs);
                let render_noise = rng.range(-0.3, 0.3);
                online.observe(shape, model.cost_s(shape, &mut rng) * 1000.0 + render_noise);
            }
            for blocks in [1u64, 4, 16, 64, 256, 1024] {
                for shape in [
                    BatchShape::binds(blocks, blocks.div_ceil(4)),
                    BatchShape::binds(blocks, blocks),
                ] {
                    let expected = model.expected_cost_s(shape) * 1000.0;
                    let predicted = online.fit().predict_ms(shape);
                    // Within 20 %, or within the render's own noise for batches cheaper
                    // than it (a single block on lavapipe costs 0.05 ms).
                    assert!(
                        (predicted - expected).abs() <= (0.2 * expected).max(0.3),
                        "{preset}: {shape:?} learned {predicted} ms, model {expected} ms"
                    );
                }
            }
        }
    }

    #[test]
    fn a_cycle_gets_the_most_blocks_whose_predicted_cost_fits_the_room() {
        let options = PolicyOptions {
            alpha_ms: 12.0,
            bind_cost: Some(BindLatencyPreset::Desktop),
            ..PolicyOptions::default()
        };
        let mut policy = PredictivePolicy::new(&options).expect("valid");
        // Contiguous rows of four blocks, nothing unbound.
        for _ in 0..4 {
            policy.observe_batch(BatchShape::binds(64, 16), 64 * 65_536);
            policy.update(8.0);
        }
        let budget = policy.decision().block_budget.expect("a block budget");
        let fit = BindCostFit::for_preset(BindLatencyPreset::Desktop);
        let room = (12.0 - policy.base_ms()) * ROOM_SHARE;
        let cost = |n: u64| fit.predict_ms(BatchShape::binds(n, n.div_ceil(4)));
        assert!(
            cost(budget.blocks) <= room + 1e-9,
            "{} blocks cost {}",
            budget.blocks,
            cost(budget.blocks)
        );
        assert!(cost(budget.blocks + 1) > room, "one block more would still fit");
        assert_eq!(policy.decision().load_size_bytes, budget.blocks * 65_536);
        assert_eq!(policy.decision().mip_bias, 0.0);
    }

    #[test]
    fn the_base_is_the_latency_less_the_predicted_cost_and_a_spike_does_not_move_it() {
        let options = PolicyOptions {
            alpha_ms: 12.0,
            bind_cost: Some(BindLatencyPreset::Desktop),
            ..PolicyOptions::default()
        };
        let fit = BindCostFit::for_preset(BindLatencyPreset::Desktop);
        let mut policy = PredictivePolicy::new(&options).expect("valid");
        let shape = BatchShape::binds(80, 20);
        // Every frame carries the same batch; its latency is the render plus its cost.
        let latency = 7.5 + fit.predict_ms(shape);
        for frame in 0..40 {
            policy.observe_batch(shape, 80 * 65_536);
            // One frame in ten spikes by 10 ms.
            let spike = if frame % 10 == 5 { 10.0 } else { 0.0 };
            policy.update(latency + spike);
        }
        assert!((policy.base_ms() - 7.5).abs() < 1e-9, "base {}", policy.base_ms());
    }

    #[test]
    fn a_render_over_alpha_biases_and_loads_the_least() {
        let options = PolicyOptions {
            alpha_ms: 12.0,
            beta: 8.0,
            bind_cost: Some(BindLatencyPreset::Desktop),
            ..PolicyOptions::default()
        };
        let mut policy = PredictivePolicy::new(&options).expect("valid");
        for _ in 0..30 {
            policy.observe_batch(BatchShape::default(), 0);
            policy.update(18.0);
        }
        let d = policy.decision();
        // The paper's floor: s_min in bytes, no block budget.
        assert_eq!(d.block_budget, None);
        assert_eq!(d.load_size_bytes, options.s_min_bytes);
        assert!(d.mip_bias == 8.0, "bias {}", d.mip_bias);
        // Bad input leaves the decision alone.
        assert_eq!(policy.update(f64::NAN), d);
        assert_eq!(policy.telemetry().rejected_samples, 1);
    }
}
