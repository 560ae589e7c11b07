//! The generators' progress line on stderr.

use std::io::{IsTerminal, Write};
use std::time::Instant;

/// A one-line progress report on stderr, redrawn in place on a terminal and printed every
/// `step` per cent otherwise, with the rate and the time left.
pub(crate) struct Progress {
    total: usize,
    done: usize,
    /// Items done before this run (a resumed write): not part of the rate.
    start_done: usize,
    unit: &'static str,
    step: usize,
    start: Instant,
    last_step: usize,
    enabled: bool,
    terminal: bool,
}

impl Progress {
    /// Progress of `total` textures, every 10 %; silent for fewer than 10,000.
    pub(crate) fn new(total: usize, quiet: bool) -> Self {
        Self::resumed(total, 0, "textures", 10, quiet || total < 10_000)
    }

    /// Progress of `total` items of `unit`, `done` of them before this run, every `step` %.
    pub(crate) fn resumed(total: usize, done: usize, unit: &'static str, step: usize, quiet: bool) -> Self {
        let step = step.max(1);
        Self {
            total,
            done,
            start_done: done,
            unit,
            step,
            start: Instant::now(),
            last_step: done * 100 / total.max(1) / step,
            enabled: !quiet,
            terminal: std::io::stderr().is_terminal(),
        }
    }

    pub(crate) fn advance(&mut self, n: usize) {
        self.done += n;
        let percent = self.done * 100 / self.total.max(1);
        if !self.enabled || (!self.terminal && percent / self.step == self.last_step) {
            return;
        }
        self.last_step = percent / self.step;
        let elapsed = self.start.elapsed().as_secs_f64();
        let rate = (self.done - self.start_done) as f64 / elapsed.max(1e-9);
        let left = (self.total - self.done) as f64 / rate.max(1e-9);
        let line = format!(
            "gen: {}/{} {} ({percent}%), {rate:.1}/s, {} elapsed, about {} left",
            self.done,
            self.total,
            self.unit,
            duration(elapsed),
            duration(left)
        );
        let mut err = std::io::stderr().lock();
        // Progress output is best effort: a closed stderr must not stop generation.
        let _ = if self.terminal {
            write!(err, "\r{line}\x1b[K")
        } else {
            writeln!(err, "{line}")
        };
    }

    pub(crate) fn finish(&self) {
        if self.enabled && self.terminal {
            let _ = writeln!(std::io::stderr());
        }
    }
}

/// Seconds as `1 h 02 min`, `3 min 07 s` or `42 s`.
fn duration(seconds: f64) -> String {
    let s = seconds.max(0.0).round() as u64;
    if s >= 3600 {
        format!("{} h {:02} min", s / 3600, s % 3600 / 60)
    } else if s >= 60 {
        format!("{} min {:02} s", s / 60, s % 60)
    } else {
        format!("{s} s")
    }
}
