//! Summary statistics with the keys of the paper's Table 3 rows, shared by
//! `citystream simulate` and the engine's flythrough `summary.json`.

use serde::Serialize;

/// Median, mean, maximum and minimum of a series.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Stats {
    /// Middle value (mean of the two middle values for an even count).
    pub median: f64,
    /// Arithmetic mean.
    pub mean: f64,
    /// Largest value.
    pub max: f64,
    /// Smallest value.
    pub min: f64,
}

impl Stats {
    /// Statistics of the finite samples; non-finite samples are skipped and
    /// an empty (or all non-finite) series gives all zeros.
    pub fn from_samples(samples: &[f64]) -> Stats {
        let mut v: Vec<f64> = samples.iter().copied().filter(|x| x.is_finite()).collect();
        if v.is_empty() {
            return Stats::default();
        }
        v.sort_unstable_by(f64::total_cmp);
        let n = v.len();
        let median = if n % 2 == 1 {
            v[n / 2]
        } else {
            0.5 * (v[n / 2 - 1] + v[n / 2])
        };
        let mean = v.iter().sum::<f64>() / n as f64;
        Stats {
            median,
            mean,
            max: v[n - 1],
            min: v[0],
        }
    }
}

/// A streaming run summarised like a row group of the paper's Table 3.
/// The JSON keys are an interface (`citystream simulate --json` and the
/// flythrough's `summary.json`); do not rename them.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Summary {
    /// Frames rendered.
    pub frames: u64,
    /// Texture bytes streamed (loaded and submitted) over the run.
    pub bytes_streamed: u64,
    /// Frame latency in ms, per frame.
    pub frame_ms: Stats,
    /// Weighted maximum frame latency `t_w` in ms, per frame.
    pub tw_ms: Stats,
    /// Mipmaps streamed per second of path time, per sampling window.
    pub mips_per_s: Stats,
    /// MB (2^20 bytes) streamed per second of path time, per sampling window: its mean is
    /// the bytes streamed over the path's seconds (the last, partial window aside).
    pub mb_per_s: Stats,
    /// Load size `s` in MB, per frame.
    pub load_size_mb: Stats,
    /// Mipmap bias `b`, per frame.
    pub mip_bias: Stats,
}

/// The paper's sampling interval for transfer rates (§4.2: "we capture a
/// measurement at every 0.10423 s interval").
pub const RATE_WINDOW_S: f64 = 0.10423;

/// Ticks of path time per second. Path time is counted in whole ticks so that it never
/// drifts: a sum of millions of `f64` frame steps gains microseconds a simulated day and
/// moves frames across rate windows. The tick divides both the fixed clock's step (1/60 s
/// is 5,000,000 ticks) and [`RATE_WINDOW_S`] (31,269,000 ticks), so both are exact; any
/// other step is rounded to 3.3 ns, and a `u64` of ticks lasts 1,900 years.
pub const PATH_TICKS_PER_S: u64 = 300_000_000;

/// [`RATE_WINDOW_S`] in ticks.
const RATE_WINDOW_TICKS: u64 = 31_269_000;

/// Path time as a whole number of [`PATH_TICKS_PER_S`] ticks.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord)]
pub struct PathClock {
    ticks: u64,
}

impl PathClock {
    /// A clock at the start of the path.
    pub fn new() -> Self {
        Self::default()
    }

    /// The ticks of a step of `ms` milliseconds: rounded to the nearest tick; a step that is
    /// not finite or not positive does not advance the path.
    pub fn ticks_of_ms(ms: f64) -> u64 {
        if !(ms.is_finite() && ms > 0.0) {
            return 0;
        }
        // Saturates at u64::MAX for absurd steps instead of wrapping.
        (ms * (PATH_TICKS_PER_S as f64 / 1000.0)).round() as u64
    }

    /// Advance by a step of `ms` milliseconds.
    pub fn advance_ms(&mut self, ms: f64) {
        self.ticks = self.ticks.saturating_add(Self::ticks_of_ms(ms));
    }

    /// Ticks since the start.
    pub fn ticks(self) -> u64 {
        self.ticks
    }

    /// Seconds since the start: one rounding from the exact tick count, never a sum.
    pub fn seconds(self) -> f64 {
        self.ticks as f64 / PATH_TICKS_PER_S as f64
    }

    /// The rate window this instant falls in (an instant on a boundary opens the next).
    pub fn rate_window(self) -> usize {
        usize::try_from(self.ticks / RATE_WINDOW_TICKS).unwrap_or(usize::MAX)
    }
}

/// Collects per-frame samples and turns them into a [`Summary`].
///
/// Transfer rates are counted per [`RATE_WINDOW_S`] window of path time (how far
/// the camera moved along its path, what a user watching the run sees pass): what
/// completed in the window divided by its length; windows in which nothing was
/// rendered (inside a long frame) count as zero. Where the path advances by a fixed
/// step, frames' modelled work takes less time than the path; dividing by work time
/// would overstate the rate.
#[derive(Clone, Debug, Default)]
pub struct SummaryBuilder {
    frame_ms: Vec<f64>,
    tw_ms: Vec<f64>,
    load_size_mb: Vec<f64>,
    mip_bias: Vec<f64>,
    window_mips: Vec<u64>,
    window_bytes: Vec<u64>,
    path: PathClock,
    bytes_streamed: u64,
}

impl SummaryBuilder {
    /// An empty builder.
    pub fn new() -> Self {
        Self::default()
    }

    /// Record one frame: its latency, how far the path advanced with it (`path_ms`: the
    /// latency itself where the camera moves in real time, a fixed step with the fixed
    /// clock), the policy's `t_w`, `s` and `b` for it, and the mips and bytes whose
    /// streaming completed during it.
    #[allow(clippy::too_many_arguments)]
    pub fn push_frame(
        &mut self,
        frame_ms: f64,
        path_ms: f64,
        tw_ms: f64,
        load_size_mb: f64,
        mip_bias: f64,
        mips: u64,
        bytes: u64,
    ) {
        self.frame_ms.push(frame_ms);
        self.tw_ms.push(tw_ms);
        self.load_size_mb.push(load_size_mb);
        self.mip_bias.push(mip_bias);
        self.path.advance_ms(path_ms);
        // Completions land at the end of the frame.
        let window = self.path.rate_window();
        if self.window_mips.len() <= window {
            self.window_mips.resize(window + 1, 0);
            self.window_bytes.resize(window + 1, 0);
        }
        self.window_mips[window] += mips;
        self.window_bytes[window] += bytes;
        self.bytes_streamed += bytes;
    }

    /// Seconds of path covered by the frames pushed so far.
    pub fn elapsed_s(&self) -> f64 {
        self.path.seconds()
    }

    /// The path time covered so far, exactly.
    pub fn path_clock(&self) -> PathClock {
        self.path
    }

    /// The summary. The last, partial window is left out of the rates
    /// unless it is the only one.
    pub fn finish(&self) -> Summary {
        let full = self.path.rate_window();
        let n = full.clamp(1, self.window_mips.len().max(1));
        let rate = |v: &[u64], scale: f64| -> Vec<f64> {
            (0..n)
                .map(|i| v.get(i).copied().unwrap_or(0) as f64 * scale / RATE_WINDOW_S)
                .collect()
        };
        Summary {
            frames: self.frame_ms.len() as u64,
            bytes_streamed: self.bytes_streamed,
            frame_ms: Stats::from_samples(&self.frame_ms),
            tw_ms: Stats::from_samples(&self.tw_ms),
            mips_per_s: Stats::from_samples(&rate(&self.window_mips, 1.0)),
            mb_per_s: Stats::from_samples(&rate(&self.window_bytes, 1.0 / crate::controller::BYTES_PER_MB)),
            load_size_mb: Stats::from_samples(&self.load_size_mb),
            mip_bias: Stats::from_samples(&self.mip_bias),
        }
    }
}

/// The paper's Table 3 layout for several runs: one block per run with
/// the rows frame latency, `t_w`, Mip/s, MB/s, `s` and `b`, and the columns
/// median, average and max.
pub fn table3(runs: &[(&str, &Summary)]) -> String {
    use std::fmt::Write;
    let mut out = String::new();
    let _ = writeln!(out, "{:<28}{:>12}{:>12}{:>12}", "", "Median", "Average", "Max");
    for (name, s) in runs {
        let _ = writeln!(
            out,
            "{name} ({} frames, {:.1} MB streamed)",
            s.frames,
            s.bytes_streamed as f64 / crate::controller::BYTES_PER_MB
        );
        for (label, st) in [
            ("Frame latency (ms)", &s.frame_ms),
            ("t_w latency (ms)", &s.tw_ms),
            ("Transfer rate (Mip/s)", &s.mips_per_s),
            ("Transfer rate (MB/s)", &s.mb_per_s),
            ("Load size s (MB)", &s.load_size_mb),
            ("Mipmap bias b", &s.mip_bias),
        ] {
            let _ = writeln!(out, "  {label:<26}{:>12.2}{:>12.2}{:>12.2}", st.median, st.mean, st.max);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stats_by_hand() {
        // Sorted: 1 2 3 10 → median (2 + 3)/2 = 2.5, mean 16/4 = 4.
        let s = Stats::from_samples(&[3.0, 1.0, 10.0, 2.0, f64::NAN]);
        assert_eq!(
            s,
            Stats {
                median: 2.5,
                mean: 4.0,
                max: 10.0,
                min: 1.0
            }
        );
        assert_eq!(Stats::from_samples(&[5.0, 1.0, 2.0]).median, 2.0);
        assert_eq!(Stats::from_samples(&[]), Stats::default());
    }

    #[test]
    fn rates_per_window() {
        // Eleven 20 ms frames end at 0.02, 0.04, …, 0.22 s. Frames 0–4 (ending
        // at ≤ 0.10 s, window 0) stream one 1 MiB mip each, the rest nothing.
        // Window 1 (0.10423–0.20846 s) holds frames 5–9: zero. Frame 10 ends
        // in the partial third window, which is left out.
        let mut b = SummaryBuilder::new();
        for i in 0..11 {
            let (m, by) = if i < 5 { (1, 1 << 20) } else { (0, 0) };
            b.push_frame(20.0, 20.0, 1.0, 1.0, 0.0, m, by);
        }
        let s = b.finish();
        assert_eq!(s.frames, 11);
        assert_eq!(s.bytes_streamed, 5 << 20);
        // 5 mips / 0.10423 s = 47.971 mip/s in window 0, 0 in window 1.
        assert!((s.mips_per_s.max - 5.0 / 0.10423).abs() < 1e-9, "{s:?}");
        assert_eq!(s.mips_per_s.min, 0.0);
        assert!((s.mips_per_s.mean - 2.5 / 0.10423).abs() < 1e-9);
        assert!((s.mb_per_s.mean - s.mips_per_s.mean).abs() < 1e-9);
    }

    #[test]
    fn rates_are_per_second_of_path_not_of_work() {
        // 600 frames of 8 ms of work on a path advancing 1/60 s each (the fixed clock):
        // 10 s of path, 4.8 s of work. 3 MiB complete every 6th frame: 300 MiB in all.
        let mut b = SummaryBuilder::new();
        for i in 0..600 {
            let bytes = if i % 6 == 5 { 3 << 20 } else { 0 };
            b.push_frame(8.0, 1000.0 / 60.0, 1.0, 1.0, 0.0, u64::from(bytes > 0), bytes);
        }
        assert!((b.elapsed_s() - 10.0).abs() < 1e-9);
        let s = b.finish();
        let per_path_second = (s.bytes_streamed as f64 / f64::from(1 << 20)) / 10.0;
        assert!((per_path_second - 30.0).abs() < 1e-9);
        // The windows' mean is the path rate within 1 % (the last, partial window aside);
        // per second of work it would read 62.5.
        assert!(
            (s.mb_per_s.mean / per_path_second - 1.0).abs() < 0.01,
            "{} MB/s against {per_path_second}",
            s.mb_per_s.mean
        );
    }

    #[test]
    fn a_day_at_60_hz_keeps_exact_time_and_windows() {
        // 24 hours of the fixed clock's 1/60 s steps, 5,184,000 frames. Frame k (from 1)
        // ends at exactly k/60 s and so, by integer arithmetic, in rate window
        // floor(k/60 / 0.10423) = k * 100000 / 625380. A sum of f64 steps drifts by 1.4 us
        // over the day and puts 111 frames in the wrong window.
        const FRAMES: u64 = 24 * 3600 * 60;
        let mut b = SummaryBuilder::new();
        let mut expected_windows = vec![0u64; (FRAMES * 100_000 / 625_380) as usize + 1];
        for k in 1..=FRAMES {
            // Bytes that differ frame to frame, so a frame in the wrong window shows.
            let bytes = k % 7 + 1;
            b.push_frame(8.0, 1000.0 / 60.0, 1.0, 1.0, 0.0, 1, bytes);
            expected_windows[(k * 100_000 / 625_380) as usize] += bytes;
            if k % 3600 == 0 || k == FRAMES {
                assert_eq!(b.path_clock().ticks(), k * 5_000_000, "ticks after frame {k}");
                // Both are the correctly rounded k/60.
                assert_eq!(b.elapsed_s(), k as f64 / 60.0, "time after frame {k}");
            }
        }
        assert_eq!(b.elapsed_s(), 86_400.0);
        assert_eq!(b.window_bytes, expected_windows);
        let s = b.finish();
        assert_eq!(s.frames, FRAMES);
        // The windows of the rates: every full one, the partial last one left out.
        let full = (FRAMES * 100_000 / 625_380) as usize;
        let expected_max = expected_windows[..full].iter().max().copied().unwrap_or(0);
        let mb = expected_max as f64 / crate::controller::BYTES_PER_MB / RATE_WINDOW_S;
        assert_eq!(s.mb_per_s.max, mb);
    }

    #[test]
    fn path_clock_rounds_steps_to_ticks_and_ignores_bad_ones() {
        let mut clock = PathClock::new();
        clock.advance_ms(f64::NAN);
        clock.advance_ms(-5.0);
        clock.advance_ms(0.0);
        assert_eq!(clock.ticks(), 0);
        clock.advance_ms(1000.0 / 60.0);
        assert_eq!(clock.ticks(), 5_000_000);
        // 0.1 ms is 30,000 ticks; a third of a tick is rounded away.
        clock.advance_ms(0.1 + 1e-6 / 3.0);
        assert_eq!(clock.ticks(), 5_030_000);
        clock.advance_ms(f64::INFINITY);
        assert_eq!(clock.ticks(), 5_030_000);
        // A boundary instant opens the next window.
        let mut at_boundary = PathClock::new();
        at_boundary.advance_ms(104.23);
        assert_eq!(at_boundary.rate_window(), 1);
        assert_eq!(PathClock::ticks_of_ms(1e300), u64::MAX);
    }
}
