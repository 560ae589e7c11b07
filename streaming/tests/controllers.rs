//! Both adaptive controllers driven through the same recorded latency traces: the paper's
//! still follows Eq. 4–7 to the last bit (against a second, plain transcription of the
//! equations and of the documented choices), and the headroom controller keeps its
//! promises on the simulated clock next to it.

use citystream_streaming::bench::sim::{self, SimConfig};
use citystream_streaming::bind_latency::BindLatencyPreset;
use citystream_streaming::controller::{AdaptivePolicy, Decision, LoadPolicy, PolicyKind, PolicyOptions};

/// Eq. 4–7 as the paper writes them, with the choices the controller's module docs make
/// (previous samples only, recursive edges, the stall rule), written out a second time.
struct PaperByHand {
    alpha: f64,
    beta: f64,
    s_min: f64,
    s_max: f64,
    tw: f64,
    l: f64,
    /// Ring buffers laid out as the controller's (the sums run in storage order).
    tw_ring: (Vec<f64>, usize),
    tbl_ring: (Vec<f64>, usize),
    tbu_ring: (Vec<f64>, usize),
    stall_run: u32,
    last: Decision,
}

fn push(ring: &mut (Vec<f64>, usize), cap: usize, v: f64) {
    if ring.0.len() < cap {
        ring.0.push(v);
    } else {
        ring.0[ring.1] = v;
    }
    ring.1 = (ring.1 + 1) % cap;
}

fn mean(values: impl Iterator<Item = f64>) -> Option<f64> {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    (n > 0).then(|| sum / n as f64)
}

impl PaperByHand {
    fn new(o: &PolicyOptions) -> Self {
        PaperByHand {
            alpha: o.alpha_ms / 1000.0,
            beta: o.beta,
            s_min: o.s_min_bytes as f64,
            s_max: o.s_max_mb * 1_048_576.0,
            tw: 0.0,
            l: 0.0,
            tw_ring: (Vec::new(), 0),
            tbl_ring: (Vec::new(), 0),
            tbu_ring: (Vec::new(), 0),
            stall_run: 0,
            last: Decision::new(o.s_min_bytes, 0.0),
        }
    }

    fn update(&mut self, ms: f64) -> Decision {
        if !ms.is_finite() || ms < 0.0 {
            return self.last;
        }
        let dt = ms.min(60_000.0) / 1000.0;
        // Eq. 5.
        let tw = (self.tw - (30.0 * (self.tw - dt).max(0.0)).powi(2) * dt).max(dt);
        let history = mean(self.tw_ring.0.iter().copied());
        let far_above = dt > 4.0 * history.unwrap_or(0.0).max(self.alpha);
        self.stall_run = if far_above { self.stall_run + 1 } else { 0 };
        let stall = far_above && self.stall_run <= 8;
        // Eq. 6.
        let twa = history.unwrap_or(tw);
        let tm = if twa > self.alpha {
            twa * (1.0 - 0.85) + self.alpha * 0.85
        } else {
            twa * (1.0 - 0.5) + self.alpha * 0.5
        };
        // Eq. 7's inputs: the newest five t_w, newest first, and the recursive edges.
        let n = self.tw_ring.0.len();
        let newest = (1..=n.min(5)).map(|j| self.tw_ring.0[(self.tw_ring.1 + 200 - j) % 200]);
        let tb = mean(newest).unwrap_or(tw);
        let tbl = mean(self.tbl_ring.0.iter().map(|&v| v.min(tw))).map_or(tw, |m| tw * (1.0 - 0.8) + m * 0.8);
        let tbu = mean(self.tbu_ring.0.iter().map(|&v| v.max(tw))).map_or(tw, |m| tw * (1.0 - 0.8) + m * 0.8);
        self.tw = tw;
        if !stall {
            push(&mut self.tw_ring, 200, tw);
            push(&mut self.tbl_ring, 40, tbl);
            push(&mut self.tbu_ring, 40, tbu);
        }
        // Eq. 4.
        let x = tw - tm;
        let a = x.abs();
        let step = (a + (10.0 * a).powi(2) + (30.0 * a).powi(3) + (50.0 * a).powi(4)) * dt;
        let l = if x > 0.0 {
            self.l - step
        } else if x < 0.0 {
            self.l + step
        } else {
            self.l
        };
        self.l = if l.is_nan() { 0.0 } else { l.clamp(0.0, 1.0) };
        let s = (self.l * self.s_max).max(self.s_min).min(self.s_max);
        // Eq. 7.
        let (e0, e1) = (0.96 * tbl, 1.2 * tbu);
        let step = if e1 <= e0 {
            if tb <= e0 {
                0.0
            } else {
                1.0
            }
        } else {
            let t = ((tb - e0) / (e1 - e0)).clamp(0.0, 1.0);
            t * t * (3.0 - 2.0 * t)
        };
        self.last = Decision::new(s.round() as u64, (self.beta * step).clamp(0.0, self.beta));
        self.last
    }
}

/// The frame latencies of a simulated run of `policy` (desktop bind latency, α = 12 ms).
fn recorded_trace(policy: PolicyKind, frames: u64) -> Vec<f64> {
    let mut config = SimConfig::new(policy, BindLatencyPreset::Desktop, frames, 3);
    config.policy_options.alpha_ms = 12.0;
    let mut latencies = Vec::new();
    sim::run_traced(&config, |f| latencies.push(f.telemetry.frame_ms)).expect("a valid simulation");
    latencies
}

/// A trace with the hard cases: a 500 ms first frame, zeros, subnormals, NaN, infinities,
/// negatives, huge values, steady stretches and spikes.
fn hostile_trace() -> Vec<f64> {
    let mut trace = vec![500.0];
    for i in 0u64..3000 {
        trace.push(match i % 97 {
            0 => f64::NAN,
            13 => 0.0,
            17 => 5e-324,
            29 => f64::INFINITY,
            31 => -3.0,
            41 => 1e300,
            53 => 45.0,
            _ => 6.0 + (i.wrapping_mul(2_654_435_761) % 1000) as f64 / 125.0,
        });
    }
    trace
}

#[test]
fn the_paper_controller_follows_its_equations_to_the_last_bit_on_recorded_traces() {
    let traces = [
        recorded_trace(PolicyKind::Adaptive, 4000),
        recorded_trace(PolicyKind::Headroom, 4000),
        recorded_trace(PolicyKind::Baseline, 4000),
        hostile_trace(),
    ];
    for options in [
        PolicyOptions {
            alpha_ms: 12.0,
            ..PolicyOptions::default()
        },
        PolicyOptions::default(),
        PolicyOptions {
            alpha_ms: 3.0,
            beta: 2.5,
            s_max_mb: 8.0,
            ..PolicyOptions::default()
        },
    ] {
        for (t, trace) in traces.iter().enumerate() {
            let mut policy = AdaptivePolicy::new(&options).expect("valid options");
            let mut by_hand = PaperByHand::new(&options);
            for (frame, &ms) in trace.iter().enumerate() {
                let (d, expected) = (policy.update(ms), by_hand.update(ms));
                assert!(
                    d.load_size_bytes == expected.load_size_bytes
                        && d.mip_bias.to_bits() == expected.mip_bias.to_bits(),
                    "trace {t}, frame {frame} ({ms} ms), {options:?}: {d:?}, the equations give {expected:?}"
                );
            }
        }
    }
}

/// Frames over `limit` ms after the first second of a trace.
fn over_after_first_second(latencies: &[f64], limit: f64) -> usize {
    let mut clock = 0.0;
    latencies
        .iter()
        .filter(|&&ms| {
            clock += ms;
            clock > 1000.0 && ms > limit
        })
        .count()
}

#[test]
fn on_the_same_simulated_flights_the_headroom_controller_biases_less_and_stalls_no_more() {
    // Render hiccups off: a frame over 2α is then the streaming's (its bind cost, with the
    // `desktop` model's random 4–12 ms spikes), not the simulated renderer's.
    let run = |policy, seed| {
        let mut config = SimConfig::new(policy, BindLatencyPreset::Desktop, 13_000, seed);
        config.policy_options.alpha_ms = 12.0;
        config.render.hiccup_probability = 0.0;
        let mut latencies = Vec::new();
        let mut bias = 0.0;
        let report = sim::run_traced(&config, |f| {
            latencies.push(f.telemetry.frame_ms);
            bias += f.telemetry.mip_bias;
        })
        .expect("a valid simulation");
        (report.summary.bytes_streamed, latencies, bias / 13_000.0)
    };
    let worst = |ms: &[f64]| ms.iter().copied().fold(0.0, f64::max);
    for seed in 1..=3 {
        let (paper_bytes, paper_ms, paper_bias) = run(PolicyKind::Adaptive, seed);
        let (headroom_bytes, headroom_ms, headroom_bias) = run(PolicyKind::Headroom, seed);
        let (baseline_bytes, baseline_ms, _) = run(PolicyKind::Baseline, seed);
        let over = |ms: &[f64]| over_after_first_second(ms, 24.0);
        assert!(
            over(&headroom_ms) <= over(&paper_ms),
            "seed {seed}: {} frames over 2α, the paper's {}",
            over(&headroom_ms),
            over(&paper_ms)
        );
        assert!(
            worst(&headroom_ms) <= 0.05 * worst(&baseline_ms),
            "seed {seed}: worst {} ms",
            worst(&headroom_ms)
        );
        assert!(
            headroom_bias < 0.1 * paper_bias,
            "seed {seed}: mean bias {headroom_bias}, the paper's {paper_bias}"
        );
        assert!(
            headroom_bytes >= paper_bytes && headroom_bytes as f64 >= 0.9 * baseline_bytes as f64,
            "seed {seed}: {headroom_bytes} bytes, the paper's {paper_bytes}, the baseline's {baseline_bytes}"
        );
    }
}
