//! A deterministic, seeded model of what sparse memory binding costs
//! (`vkQueueBindSparse`), and a [`SparseBinder`] wrapper that charges it.
//!
//! The paper (§2.3) saw a binding cost "linearly increasing … with every
//! memory block bound, even more so when memory blocks are bound sparsely
//! and irregularly", plus unpredictable stutters (§4.2) that remain "even
//! when the load size is set to a constant low value of 0.05MB". If the
//! k-th block of a batch costs `a + c·(2k − 1)`, a batch of `n` blocks costs
//! `a·n + c·n²`, so the model is
//!
//! ```text
//! cost(n, runs) = per_call + a·n·(1 + jitter) + c·n² + scatter·(runs − 1) + spike
//! ```
//!
//! for a non-empty batch of `n` blocks bound or unbound in `runs` contiguous runs (an
//! empty batch costs nothing), with `jitter` uniform in `[−j, j]` and, with
//! probability `p` per submission, a spike uniform in `[spike_min,
//! spike_max]`; plus, for a driver measured per bind entry,
//! `per_bind_entry · bind_runs + per_unbind_entry · unbind_runs`. Randomness comes from
//! a seeded [`SplitMix64`], so a run is reproducible.
//!
//! Runs are counted from the blocks' layout in the image ([`BatchShape::of`]: adjacent
//! columns of one row of one level merge), not from where the allocator placed their
//! memory: two runs that differ only in chunk placement cost the same.
//!
//! # Presets
//!
//! * `none`: every cost 0.
//! * `lavapipe`: measured on lavapipe: about 45 µs per call plus 4–6 µs per
//!   block (`a` = 5 µs, `j` = 0.2), no growth, no spikes. Far too cheap to
//!   show the problem the paper solves.
//! * `desktop`: calibrated from the paper's Table 3 baseline (Berlin atlas,
//!   RTX 2080 Ti, Windows 10). Derivation:
//!   1. Without adaptive streaming, every cycle may load `s_max` = 64 MB =
//!      1024 blocks of 64 KiB, and the maximum frame latency is 471.16 ms;
//!      the frames without a large batch render in about 4.5 ms (median of
//!      the adaptive rows), so one full batch costs about 470 ms.
//!   2. With the adaptive controller the load size stays near 1 MB
//!      (16 blocks) and the median frame barely moves (4.5 vs 6.8 ms for
//!      mostly small batches), so a 1 MB batch must cost around 0.1 ms.
//!   3. A pure `c·n²` law links the two: `470 ms / 1024² = 0.448 µs`, and
//!      `16² · 0.448 µs = 0.115 ms`. A large linear term cannot fit both
//!      (a 1 MB batch at 0.1 ms allows at most ~6 µs per block, i.e. 6 ms
//!      of the 470), so `per_call` = 5 µs and `a` = 0.5 µs are small and
//!      `c = (470 − 0.005 − 0.512) ms / 1024² = 0.447734 µs`, giving
//!      `cost(1024) = 470.0 ms` and `cost(16) = 0.128 ms` for contiguous
//!      batches.
//!   4. Scattered binding costs 20 µs per extra run (at most +20 ms for
//!      1024 single-block runs), and 1 % of submissions stall 4–12 ms,
//!      the size of the residual stutters in Table 3's α = 12 ms row (max
//!      frame 15.98 ms against a 4.55 ms median).
//! * `h200-linux`: measured on an NVIDIA H200 (driver 580.159, Linux,
//!   2026-12-04; docs/REAL_GPU.md, "What binding costs on the H200": `bind_cost`, batches
//!   of 1 to 4,096 blocks of a BC1 image of 2048² layers, contiguous and scattered, bound
//!   then unbound, median of 7). The cost is linear in the bind entries, where a run of
//!   adjacent blocks of a row is one entry (4 blocks of 512 × 256 texels across a 2048²
//!   level). The cost per entry is the least-squares slope over the table's points of
//!   at most 1,024 entries (the largest batch a 64 MB load size makes): 24.77 µs a bind
//!   entry, 18.11 µs an unbind entry. The cost of a call is what a single block's bind
//!   took (0.150 and 0.131 ms, mean 0.1405) less one bind entry: 115.7 µs. Nothing
//!   quadratic, no spikes (the bench's medians saw none). Every point of the table up to
//!   1,024 entries is within 14 % of the model (1,024 contiguous blocks, 256 entries:
//!   6.46 ms against 6.31 measured; scattered, 1,024 entries: 25.5 against 23.2).
//!
//! Threading: the model is plain data; [`LatencyBinder`] is `Send` and,
//! like every [`SparseBinder`], used by one thread at a time.

use std::fmt;
use std::str::FromStr;
use std::time::Duration;

use citystream_cache::{BindError, BindOp, BindReport, SparseBinder};

use crate::rng::SplitMix64;

/// The sparse block size the presets assume (64 KiB, lavapipe and most
/// desktop drivers for BC1 sparse images).
pub const SPARSE_BLOCK_BYTES: u64 = 65_536;

/// Error parsing a preset name.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("unknown bind-latency preset `{0}` (expected none, lavapipe, desktop or h200-linux)")]
pub struct UnknownPreset(pub String);

/// Named bind-latency presets.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum BindLatencyPreset {
    /// No cost.
    None,
    /// lavapipe as measured.
    Lavapipe,
    /// A desktop driver calibrated from Table 3 (see the module docs).
    Desktop,
    /// An NVIDIA H200 under Linux as measured (see the module docs).
    H200Linux,
}

impl BindLatencyPreset {
    /// The name `FromStr` accepts.
    pub fn name(self) -> &'static str {
        match self {
            BindLatencyPreset::None => "none",
            BindLatencyPreset::Lavapipe => "lavapipe",
            BindLatencyPreset::Desktop => "desktop",
            BindLatencyPreset::H200Linux => "h200-linux",
        }
    }
}

impl fmt::Display for BindLatencyPreset {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for BindLatencyPreset {
    type Err = UnknownPreset;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "none" => Ok(BindLatencyPreset::None),
            "lavapipe" => Ok(BindLatencyPreset::Lavapipe),
            "desktop" => Ok(BindLatencyPreset::Desktop),
            "h200-linux" => Ok(BindLatencyPreset::H200Linux),
            _ => Err(UnknownPreset(s.to_owned())),
        }
    }
}

/// Parameters of the cost model, in seconds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BindLatencyModel {
    /// Fixed cost of a non-empty submission.
    pub per_call_s: f64,
    /// Linear cost per block, `a`.
    pub per_block_s: f64,
    /// Relative jitter `j` of the linear term, uniform in `[−j, j]`.
    pub per_block_jitter: f64,
    /// Quadratic coefficient `c` (cost of block k grows by `2c` per block).
    pub quadratic_s: f64,
    /// Cost per contiguous run beyond the first.
    pub per_extra_run_s: f64,
    /// Probability of a spike per non-empty submission.
    pub spike_probability: f64,
    /// Smallest spike.
    pub spike_min_s: f64,
    /// Largest spike.
    pub spike_max_s: f64,
    /// Cost per entry of bound blocks (a run of adjacent blocks).
    pub per_bind_entry_s: f64,
    /// Cost per entry of unbound blocks.
    pub per_unbind_entry_s: f64,
}

/// What a bind submission holds, as the models charge it: blocks bound and unbound, and
/// the runs (bind entries) each makes in the image's layout.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct BatchShape {
    /// Blocks bound.
    pub bound: u64,
    /// Blocks unbound.
    pub unbound: u64,
    /// Runs of the bound blocks ([`count_runs`]).
    pub bind_runs: u64,
    /// Runs of the unbound blocks.
    pub unbind_runs: u64,
}

impl BatchShape {
    /// The shape of `batch`.
    pub fn of(batch: &[BindOp]) -> Self {
        let (binds, unbinds): (Vec<BindOp>, Vec<BindOp>) =
            batch.iter().copied().partition(|op| matches!(op, BindOp::Bind { .. }));
        BatchShape {
            bound: binds.len() as u64,
            unbound: unbinds.len() as u64,
            bind_runs: count_runs(&binds),
            unbind_runs: count_runs(&unbinds),
        }
    }

    /// `blocks` bound in `runs` runs, nothing unbound.
    pub fn binds(blocks: u64, runs: u64) -> Self {
        BatchShape {
            bound: blocks,
            bind_runs: runs,
            ..Self::default()
        }
    }

    /// Blocks bound or unbound.
    pub fn blocks(&self) -> u64 {
        self.bound + self.unbound
    }

    /// Runs of both.
    pub fn runs(&self) -> u64 {
        self.bind_runs + self.unbind_runs
    }
}

impl std::ops::AddAssign for BatchShape {
    /// Several submissions counted as one.
    fn add_assign(&mut self, other: Self) {
        self.bound += other.bound;
        self.unbound += other.unbound;
        self.bind_runs += other.bind_runs;
        self.unbind_runs += other.unbind_runs;
    }
}

impl BindLatencyModel {
    /// The parameters of a preset.
    pub fn preset(preset: BindLatencyPreset) -> Self {
        let zero = BindLatencyModel {
            per_call_s: 0.0,
            per_block_s: 0.0,
            per_block_jitter: 0.0,
            quadratic_s: 0.0,
            per_extra_run_s: 0.0,
            spike_probability: 0.0,
            spike_min_s: 0.0,
            spike_max_s: 0.0,
            per_bind_entry_s: 0.0,
            per_unbind_entry_s: 0.0,
        };
        match preset {
            BindLatencyPreset::None => zero,
            BindLatencyPreset::Lavapipe => BindLatencyModel {
                per_call_s: 45e-6,
                per_block_s: 5e-6,
                per_block_jitter: 0.2,
                ..zero
            },
            BindLatencyPreset::Desktop => BindLatencyModel {
                per_call_s: 5e-6,
                per_block_s: 0.5e-6,
                per_block_jitter: 0.0,
                quadratic_s: (470e-3 - 5e-6 - 1024.0 * 0.5e-6) / (1024.0 * 1024.0),
                per_extra_run_s: 20e-6,
                spike_probability: 0.01,
                spike_min_s: 4e-3,
                spike_max_s: 12e-3,
                ..zero
            },
            BindLatencyPreset::H200Linux => BindLatencyModel {
                per_call_s: 115.7e-6,
                per_bind_entry_s: 24.77e-6,
                per_unbind_entry_s: 18.11e-6,
                ..zero
            },
        }
    }

    /// The cost without jitter or spikes of a submission of `batch`.
    pub fn expected_cost_s(&self, batch: BatchShape) -> f64 {
        let blocks = batch.blocks();
        if blocks == 0 {
            return 0.0;
        }
        let n = blocks as f64;
        self.per_call_s
            + self.per_block_s * n
            + self.quadratic_s * n * n
            + self.per_extra_run_s * batch.runs().saturating_sub(1) as f64
            + self.per_bind_entry_s * batch.bind_runs as f64
            + self.per_unbind_entry_s * batch.unbind_runs as f64
    }

    /// The modelled cost of one submission of `batch`, drawing jitter and spikes from
    /// `rng`. Always finite and `>= 0`.
    pub fn cost_s(&self, batch: BatchShape, rng: &mut SplitMix64) -> f64 {
        let blocks = batch.blocks();
        if blocks == 0 {
            return 0.0;
        }
        let n = blocks as f64;
        let jitter = 1.0 + self.per_block_jitter * (2.0 * rng.next_f64() - 1.0);
        let spike = if rng.next_f64() < self.spike_probability {
            rng.range(self.spike_min_s, self.spike_max_s)
        } else {
            0.0
        };
        (self.expected_cost_s(batch) - self.per_block_s * n + self.per_block_s * n * jitter + spike).max(0.0)
    }
}

/// Number of contiguous runs in a batch: blocks of the same image, layer,
/// level and row whose columns follow each other merge into one run.
pub fn count_runs(batch: &[BindOp]) -> u64 {
    let mut keys: Vec<_> = batch.iter().map(BindOp::block).collect();
    keys.sort_unstable();
    keys.dedup();
    let mut runs = 0u64;
    let mut prev: Option<citystream_cache::BlockKey> = None;
    for k in keys {
        let continues = prev.is_some_and(|p| {
            (p.image, p.layer, p.mip, p.y) == (k.image, k.layer, k.mip, k.y) && p.x.checked_add(1) == Some(k.x)
        });
        if !continues {
            runs += 1;
        }
        prev = Some(k);
    }
    runs
}

/// A binder that binds nothing, for simulations: the [`LatencyBinder`]
/// around it supplies the only cost.
#[derive(Clone, Copy, Debug, Default)]
pub struct NullBinder;

impl SparseBinder for NullBinder {
    fn submit(&mut self, batch: &[BindOp]) -> Result<BindReport, BindError> {
        let blocks = u32::try_from(batch.len()).unwrap_or(u32::MAX);
        Ok(BindReport {
            blocks,
            entries: u32::try_from(count_runs(batch)).unwrap_or(u32::MAX),
            seconds: 0.0,
        })
    }
}

/// Whether [`LatencyBinder`] only accounts the modelled time or also
/// waits it out.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LatencyMode {
    /// Add the modelled time to the report (for a simulated clock).
    Account,
    /// Also sleep for it, so a real render loop feels the stall.
    Sleep,
}

/// Wraps any binder and charges the modelled binding cost on top of it.
#[derive(Debug)]
pub struct LatencyBinder<B> {
    inner: B,
    model: BindLatencyModel,
    rng: SplitMix64,
    mode: LatencyMode,
    modelled_total_s: f64,
}

impl<B: SparseBinder> LatencyBinder<B> {
    /// Wrap `inner` with `model`, drawing randomness from `seed`.
    pub fn new(inner: B, model: BindLatencyModel, seed: u64, mode: LatencyMode) -> Self {
        LatencyBinder {
            inner,
            model,
            rng: SplitMix64::stream(seed, 0xB1ED),
            mode,
            modelled_total_s: 0.0,
        }
    }

    /// The wrapped binder.
    pub fn inner(&self) -> &B {
        &self.inner
    }

    /// Modelled seconds charged so far.
    pub fn modelled_total_s(&self) -> f64 {
        self.modelled_total_s
    }
}

impl<B: SparseBinder> SparseBinder for LatencyBinder<B> {
    fn submit(&mut self, batch: &[BindOp]) -> Result<BindReport, BindError> {
        let mut report = self.inner.submit(batch)?;
        if batch.is_empty() {
            return Ok(report);
        }
        let cost = self.model.cost_s(BatchShape::of(batch), &mut self.rng);
        self.modelled_total_s += cost;
        if self.mode == LatencyMode::Sleep && cost > 0.0 {
            std::thread::sleep(Duration::from_secs_f64(cost.min(60.0)));
        }
        report.seconds += cost;
        Ok(report)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use citystream_cache::{BlockKey, MemorySlot};

    #[derive(Debug, Default)]
    struct CountingBinder {
        submits: u32,
    }

    impl SparseBinder for CountingBinder {
        fn submit(&mut self, batch: &[BindOp]) -> Result<BindReport, BindError> {
            self.submits += 1;
            Ok(BindReport {
                blocks: batch.len() as u32,
                entries: batch.len() as u32,
                seconds: 0.0,
            })
        }
    }

    fn bind(x: u32, y: u32) -> BindOp {
        BindOp::Bind {
            block: BlockKey {
                image: 0,
                layer: 0,
                mip: 0,
                x,
                y,
            },
            memory: MemorySlot {
                chunk: 0,
                offset: u64::from(x) * SPARSE_BLOCK_BYTES,
            },
        }
    }

    #[test]
    fn desktop_calibration_points() {
        let m = BindLatencyModel::preset(BindLatencyPreset::Desktop);
        // 64 MB = 1024 blocks, one run: 470 ms by construction.
        assert!((m.expected_cost_s(BatchShape::binds(1024, 1)) - 0.470).abs() < 1e-12);
        // 1 MB = 16 blocks: 5 µs + 8 µs + 256 · 0.447734 µs = 0.12762 ms.
        let c = (470e-3 - 5e-6 - 512e-6) / 1_048_576.0;
        assert!((m.expected_cost_s(BatchShape::binds(16, 1)) - (5e-6 + 8e-6 + 256.0 * c)).abs() < 1e-15);
        assert!((m.expected_cost_s(BatchShape::binds(16, 1)) - 0.12762e-3).abs() < 1e-8);
        // Grows faster than linearly: 64 blocks cost more than 4 × 16.
        assert!(m.expected_cost_s(BatchShape::binds(64, 1)) > 4.0 * m.expected_cost_s(BatchShape::binds(16, 1)));
        // Scattered is worse: 16 single-block runs add 15 · 20 µs.
        assert!(
            (m.expected_cost_s(BatchShape::binds(16, 16)) - m.expected_cost_s(BatchShape::binds(16, 1)) - 300e-6).abs()
                < 1e-15
        );
        assert_eq!(m.expected_cost_s(BatchShape::binds(0, 0)), 0.0);
    }

    #[test]
    fn h200_linux_matches_its_measured_table() {
        let m = BindLatencyModel::preset(BindLatencyPreset::H200Linux);
        // (blocks, entries, measured bind ms, measured unbind ms) of the H200's table, up
        // to 1,024 entries: contiguous rows merge 4 blocks into an entry.
        let table = [
            (1, 1, 0.150, 0.126),
            (16, 4, 0.207, 0.173),
            (64, 16, 0.491, 0.384),
            (256, 64, 1.750, 1.194),
            (1024, 256, 6.306, 4.364),
            (64, 64, 1.515, 1.121),
            (256, 256, 6.126, 4.314),
            (1024, 1024, 23.220, 17.231),
        ];
        for (blocks, entries, bind_ms, unbind_ms) in table {
            let bind = m.expected_cost_s(BatchShape::binds(blocks, entries)) * 1e3;
            let unbind = m.expected_cost_s(BatchShape {
                unbound: blocks,
                unbind_runs: entries,
                ..BatchShape::default()
            }) * 1e3;
            assert!(
                (bind / bind_ms - 1.0).abs() < 0.15,
                "{blocks} blocks bound: {bind} ms, measured {bind_ms}"
            );
            assert!(
                (unbind / unbind_ms - 1.0).abs() < 0.15,
                "{blocks} blocks unbound: {unbind} ms, measured {unbind_ms}"
            );
        }
        // Linear: no growth per block beyond the entries, no spikes.
        let mut rng = SplitMix64::new(1);
        let a = m.cost_s(BatchShape::binds(1024, 256), &mut rng);
        assert!((a - m.expected_cost_s(BatchShape::binds(1024, 256))).abs() < 1e-15);
        assert!(m.expected_cost_s(BatchShape::binds(1024, 256)) * 70.0 < 0.470);
    }

    #[test]
    fn batch_shapes_count_runs_of_binds_and_unbinds_apart() {
        let unbind = |x, y| BindOp::Unbind {
            block: BlockKey {
                image: 0,
                layer: 0,
                mip: 0,
                x,
                y,
            },
        };
        let shape = BatchShape::of(&[bind(0, 0), bind(1, 0), unbind(2, 0), unbind(3, 1), bind(3, 2)]);
        assert_eq!(
            shape,
            BatchShape {
                bound: 3,
                unbound: 2,
                bind_runs: 2,
                unbind_runs: 2
            }
        );
        assert_eq!("h200-linux".parse(), Ok(BindLatencyPreset::H200Linux));
        assert_eq!(BindLatencyPreset::H200Linux.to_string(), "h200-linux");
    }

    #[test]
    fn lavapipe_is_45us_plus_4_to_6us_per_block() {
        let m = BindLatencyModel::preset(BindLatencyPreset::Lavapipe);
        let mut rng = SplitMix64::new(3);
        for _ in 0..100 {
            let c = m.cost_s(BatchShape::binds(10, 1), &mut rng);
            assert!((45e-6 + 40e-6 - 1e-12..=45e-6 + 60e-6 + 1e-12).contains(&c), "{c}");
        }
        let none = BindLatencyModel::preset(BindLatencyPreset::None);
        assert_eq!(none.cost_s(BatchShape::binds(1000, 1000), &mut rng), 0.0);
    }

    #[test]
    fn spikes_are_seeded_and_rare() {
        let m = BindLatencyModel::preset(BindLatencyPreset::Desktop);
        let draw = |seed| {
            let mut rng = SplitMix64::new(seed);
            (0..20_000)
                .map(|_| m.cost_s(BatchShape::binds(1, 1), &mut rng))
                .collect::<Vec<_>>()
        };
        let a = draw(11);
        assert_eq!(a, draw(11));
        let spikes = a.iter().filter(|&&c| c > 1e-3).count();
        // p = 0.01 over 20 000 draws: 200 expected, σ = √(200 · 0.99) ≈ 14.
        assert!((130..=270).contains(&spikes), "{spikes}");
        assert!(a.iter().all(|&c| (0.0..=12e-3 + 1e-4).contains(&c)));
    }

    #[test]
    fn runs_merge_adjacent_columns() {
        assert_eq!(count_runs(&[]), 0);
        assert_eq!(count_runs(&[bind(0, 0), bind(1, 0), bind(2, 0)]), 1);
        assert_eq!(count_runs(&[bind(2, 0), bind(0, 0)]), 2);
        assert_eq!(count_runs(&[bind(0, 0), bind(1, 1)]), 2);
        assert_eq!(count_runs(&[bind(u32::MAX, 0), bind(0, 1)]), 2);
    }

    #[test]
    fn wrapper_adds_modelled_time() -> Result<(), BindError> {
        let model = BindLatencyModel::preset(BindLatencyPreset::Lavapipe);
        let mut b = LatencyBinder::new(CountingBinder::default(), model, 1, LatencyMode::Account);
        let empty = b.submit(&[])?;
        assert_eq!(empty.seconds, 0.0);
        let r = b.submit(&[bind(0, 0), bind(1, 0)])?;
        assert_eq!(r.blocks, 2);
        assert!(r.seconds >= 45e-6 + 8e-6 && r.seconds <= 45e-6 + 12e-6 + 1e-12);
        assert_eq!(b.inner().submits, 2);
        assert!((b.modelled_total_s() - r.seconds).abs() < 1e-15);
        Ok(())
    }

    #[test]
    fn sleep_mode_waits_out_the_modelled_time() -> Result<(), BindError> {
        let model = BindLatencyModel::preset(BindLatencyPreset::Lavapipe);
        let mut b = LatencyBinder::new(NullBinder, model, 5, LatencyMode::Sleep);
        let start = std::time::Instant::now();
        let r = b.submit(&[bind(0, 0), bind(1, 0), bind(5, 3)])?;
        // sleep() waits at least as long as asked, whatever the machine.
        assert!(start.elapsed().as_secs_f64() >= r.seconds);
        assert!(r.seconds >= 45e-6 + 12e-6);
        assert_eq!((r.blocks, r.entries), (3, 2));
        Ok(())
    }
}
