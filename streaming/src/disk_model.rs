//! A deterministic model of the time a loading cycle's reads take, for the clocks that
//! model time instead of measuring it (docs/BERLIN.md, "The read model").
//!
//! The paper's loader reads from an SSD on worker threads while frames go on, so a cycle
//! lasts as long as its reads and the next one finds the view's whole backlog. A model
//! of that disk gives each read of a cycle a start and a completion time, counted from
//! the cycle's start:
//!
//! * up to [`DiskModel::queue_depth`] reads are outstanding at once (the loader's
//!   threads, each reading one mip at a time), taken in the cycle's priority order, each
//!   by the first lane free;
//! * a read waits [`DiskModel::request_latency`] (the device's service time of one
//!   request, overlapping across lanes), then its bytes pass through one shared pipe of
//!   [`DiskModel::bytes_per_s`], one read after another.
//!
//! All arithmetic is in integer nanoseconds, so a schedule is the same on every machine.
//! [`ModelledReads`] holds a cycle's mips until a modelled clock passes their completion.

use std::fmt;
use std::str::FromStr;
use std::time::Duration;

use crate::source::StagedMip;

/// A disk as the loader's reads see it. Plain integers, so that options holding one stay
/// comparable (`Eq`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct DiskModel {
    /// Bytes per second through the device, shared by every read in flight.
    pub bytes_per_s: u64,
    /// Service time of one request before its bytes flow.
    pub request_latency: Duration,
    /// Reads outstanding at once.
    pub queue_depth: u32,
}

/// Error of a disk model's parameters or name.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum DiskModelError {
    /// A parameter out of its range.
    #[error("disk model: {name} is {value}, expected {expected}")]
    Invalid {
        /// The parameter.
        name: &'static str,
        /// Its value, worded.
        value: String,
        /// What it must be.
        expected: &'static str,
    },
    /// A name `--disk-model` does not know.
    #[error("unknown disk model `{0}` (expected none, 970evo, measured or measured:FILE)")]
    UnknownName(String),
}

impl DiskModel {
    /// The paper's SSD, a Samsung 970 EVO 1 TB, from Samsung's data sheet: sequential
    /// read up to 3,400 MB/s; random 4 KB reads at queue depth 1 (one thread) 15,000 IOPS,
    /// so 66.7 µs per request; and the paper's loader threads for the queue depth: its
    /// Intel i7-8700K runs 12 hardware threads, one read each. (At 12 reads in flight
    /// the model gives 180,000 random 4 KB reads a second, within the data sheet's
    /// 500,000 at queue depth 32 with 4 threads.)
    pub const SAMSUNG_970_EVO_1TB: DiskModel = DiskModel {
        bytes_per_s: 3_400_000_000,
        request_latency: Duration::from_nanos(66_667),
        queue_depth: 12,
    };

    /// Checks the parameters: a bandwidth of 1 KB/s to 1 TB/s, a latency under a second,
    /// a queue depth of 1 to 1,024.
    pub fn validate(&self) -> Result<(), DiskModelError> {
        let invalid = |name, value: String, expected| Err(DiskModelError::Invalid { name, value, expected });
        if !(1_000..=1_000_000_000_000).contains(&self.bytes_per_s) {
            return invalid(
                "bytes_per_s",
                self.bytes_per_s.to_string(),
                "1e3 to 1e12 bytes per second",
            );
        }
        if self.request_latency >= Duration::from_secs(1) {
            return invalid(
                "request_latency",
                format!("{:?}", self.request_latency),
                "under one second",
            );
        }
        if !(1..=1024).contains(&self.queue_depth) {
            return invalid("queue_depth", self.queue_depth.to_string(), "1 to 1024 reads");
        }
        Ok(())
    }

    /// Nanoseconds `bytes` take through the pipe, rounded up.
    fn transfer_ns(&self, bytes: u64) -> u64 {
        let ns = (u128::from(bytes) * 1_000_000_000).div_ceil(u128::from(self.bytes_per_s.max(1)));
        u64::try_from(ns).unwrap_or(u64::MAX)
    }

    /// The start and completion of reads of `sizes` bytes issued at once in this order,
    /// counted from their issue (module docs).
    pub fn schedule(&self, sizes: &[u64]) -> Vec<ModelledRead> {
        let latency = u64::try_from(self.request_latency.as_nanos()).unwrap_or(u64::MAX);
        let mut lanes = vec![0u64; self.queue_depth.max(1) as usize];
        let mut pipe_free = 0u64;
        sizes
            .iter()
            .map(|&bytes| {
                // The lane free first; ties to the lowest, so the schedule is unique.
                let (lane, &start) = lanes
                    .iter()
                    .enumerate()
                    .min_by_key(|&(i, &free)| (free, i))
                    .unwrap_or((0, &0));
                let flows = start.saturating_add(latency).max(pipe_free);
                let done = flows.saturating_add(self.transfer_ns(bytes));
                pipe_free = done;
                lanes[lane] = done;
                ModelledRead {
                    start: Duration::from_nanos(start),
                    done: Duration::from_nanos(done),
                }
            })
            .collect()
    }
}

/// When one modelled read starts and completes, from its cycle's start.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ModelledRead {
    /// It takes a lane.
    pub start: Duration,
    /// Its last byte arrives.
    pub done: Duration,
}

/// What `--disk-model` names: no model, the paper's SSD, or figures measured on this
/// machine (by the loader bench, or from a file it wrote).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum DiskModelChoice {
    /// Reads take no modelled time (a cycle lasts one frame).
    None,
    /// [`DiskModel::SAMSUNG_970_EVO_1TB`].
    Evo970,
    /// This machine's figures: measured now, or read from the file named.
    Measured(Option<std::path::PathBuf>),
}

impl DiskModelChoice {
    /// The name as `FromStr` accepts it.
    pub fn name(&self) -> String {
        match self {
            DiskModelChoice::None => "none".into(),
            DiskModelChoice::Evo970 => "970evo".into(),
            DiskModelChoice::Measured(None) => "measured".into(),
            DiskModelChoice::Measured(Some(file)) => format!("measured:{}", file.display()),
        }
    }
}

impl fmt::Display for DiskModelChoice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.name())
    }
}

impl FromStr for DiskModelChoice {
    type Err = DiskModelError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim() {
            "none" => Ok(DiskModelChoice::None),
            "970evo" => Ok(DiskModelChoice::Evo970),
            "measured" => Ok(DiskModelChoice::Measured(None)),
            other => match other.strip_prefix("measured:") {
                Some(file) if !file.is_empty() => Ok(DiskModelChoice::Measured(Some(file.into()))),
                _ => Err(DiskModelError::UnknownName(s.to_owned())),
            },
        }
    }
}

/// A cycle's mips held until the modelled clock passes their completion, and whether
/// the cycle is still reading. Times are on the host's modelled clock.
#[derive(Debug, Default)]
pub struct ModelledReads {
    /// `(ready, mip)`, in the order they arrive.
    held: Vec<(Duration, StagedMip)>,
    /// The last read of the last cycle completes.
    reading_until: Duration,
}

impl ModelledReads {
    /// Nothing held.
    pub fn new() -> Self {
        Self::default()
    }

    /// Holds the mips of a cycle issued at `issued`, each with its completion counted
    /// from the issue, and the cycle's last completion (`reads_take`: failed and
    /// refused reads took their time too).
    pub fn hold_cycle(&mut self, issued: Duration, mips: Vec<(Duration, StagedMip)>, reads_take: Duration) {
        self.held
            .extend(mips.into_iter().map(|(done, mip)| (issued.saturating_add(done), mip)));
        // Loader threads finish in any order: arrival order, then texture and level.
        self.held.sort_by_key(|(ready, mip)| (*ready, mip.texture, mip.level));
        self.reading_until = self.reading_until.max(issued.saturating_add(reads_take));
    }

    /// The mips whose reads completed by `now`, in arrival order.
    pub fn release(&mut self, now: Duration) -> Vec<StagedMip> {
        let arrived = self.held.partition_point(|(ready, _)| *ready <= now);
        self.held.drain(..arrived).map(|(_, mip)| mip).collect()
    }

    /// Whether a cycle is still reading at `now`. A cycle whose reads completed by `now`
    /// is over once the host releases its mips to the cache and submits their binds in
    /// the same frame, so a host asks before it releases, and the next cycle's reads
    /// start in the frame the last one's binds go out.
    pub fn busy(&self, now: Duration) -> bool {
        now < self.reading_until
    }

    /// Mips held.
    pub fn held(&self) -> usize {
        self.held.len()
    }

    /// Bytes held.
    pub fn held_bytes(&self) -> u64 {
        self.held.iter().map(|(_, mip)| mip.bytes.len() as u64).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mip(texture: u32, bytes: usize) -> StagedMip {
        StagedMip {
            texture,
            level: 0,
            bytes: vec![0; bytes],
        }
    }

    /// 1 MB/s, 1 ms per request, one lane: reads follow each other.
    const SLOW: DiskModel = DiskModel {
        bytes_per_s: 1_000_000,
        request_latency: Duration::from_millis(1),
        queue_depth: 1,
    };

    #[test]
    fn one_read_takes_its_latency_and_its_bytes_over_the_bandwidth() {
        // 50,000 bytes at 1 MB/s: 50 ms, after 1 ms of latency.
        let s = SLOW.schedule(&[50_000]);
        assert_eq!(s[0].start, Duration::ZERO);
        assert_eq!(s[0].done, Duration::from_millis(51));
        // The second read on the one lane starts when the first is done.
        let s = SLOW.schedule(&[50_000, 10_000]);
        assert_eq!(s[1].start, Duration::from_millis(51));
        assert_eq!(s[1].done, Duration::from_millis(51 + 1 + 10));
    }

    #[test]
    fn lanes_overlap_latency_but_share_the_bandwidth() {
        let four = DiskModel { queue_depth: 4, ..SLOW };
        // Four reads of 1,000 bytes (1 ms each through the pipe) start together; their
        // latencies overlap, their bytes do not.
        let s = four.schedule(&[1_000; 4]);
        let done: Vec<u64> = s.iter().map(|r| r.done.as_micros() as u64).collect();
        assert_eq!(done, [2_000, 3_000, 4_000, 5_000]);
        assert!(s.iter().all(|r| r.start == Duration::ZERO));
        // The fifth takes the lane freed first.
        let s = four.schedule(&[1_000; 5]);
        assert_eq!(s[4].start, Duration::from_millis(2));
        assert_eq!(s[4].done, Duration::from_millis(6));
    }

    #[test]
    fn the_paper_s_ssd_reads_64_mb_in_the_time_its_data_sheet_says() {
        let evo = DiskModel::SAMSUNG_970_EVO_1TB;
        evo.validate().expect("the data sheet's figures are valid");
        // 64 MB of 128 KiB mips: bandwidth-bound, 64 MiB / 3.4 GB/s = 19.74 ms, plus one
        // latency before the first byte.
        let sizes = vec![128 * 1024u64; 512];
        let last = evo.schedule(&sizes).last().expect("512 reads").done;
        let expected = 64.0 * 1048576.0 / 3.4e9 + 66.667e-6;
        assert!(
            (last.as_secs_f64() - expected).abs() < 1e-6,
            "{last:?} against {expected} s"
        );
        // Small random reads are latency-bound: 12 lanes of 66.7 µs.
        let small = evo.schedule(&[4096; 1200]);
        let iops = 1200.0 / small.last().expect("1,200 reads").done.as_secs_f64();
        assert!((170_000.0..181_000.0).contains(&iops), "{iops} reads a second");
    }

    #[test]
    fn bad_parameters_and_names_are_refused() {
        for bad in [
            DiskModel { bytes_per_s: 0, ..SLOW },
            DiskModel { queue_depth: 0, ..SLOW },
            DiskModel {
                request_latency: Duration::from_secs(2),
                ..SLOW
            },
        ] {
            assert!(matches!(bad.validate(), Err(DiskModelError::Invalid { .. })), "{bad:?}");
        }
        assert_eq!("970evo".parse(), Ok(DiskModelChoice::Evo970));
        assert_eq!("none".parse(), Ok(DiskModelChoice::None));
        assert_eq!("measured".parse(), Ok(DiskModelChoice::Measured(None)));
        assert_eq!(
            "measured:out/disk.json".parse(),
            Ok(DiskModelChoice::Measured(Some("out/disk.json".into())))
        );
        for bad in ["", "ssd", "measured:", "970EVO"] {
            assert!(bad.parse::<DiskModelChoice>().is_err(), "{bad:?}");
        }
    }

    #[test]
    fn held_mips_arrive_in_the_frame_whose_clock_passes_their_completion() {
        // A cycle issued at t = 100 ms on the model above: mips of 20,000 and 30,000
        // bytes complete 21 ms and 21 + 31 = 52 ms later.
        let issued = Duration::from_millis(100);
        let sizes = [20_000u64, 30_000];
        let sched = SLOW.schedule(&sizes);
        let mut reads = ModelledReads::new();
        reads.hold_cycle(
            issued,
            vec![(sched[1].done, mip(2, 30_000)), (sched[0].done, mip(1, 20_000))],
            sched[1].done,
        );
        // Frames of 1/60 s from t = 100 ms: the first mip at the frame at or after
        // 121 ms (frame 2, at 133.3 ms), the second at or after 152 ms (frame 4, 166.7 ms):
        // the cycle reads through frames 0 to 3 and ends in frame 4.
        let frame_times: Vec<Duration> = (0..6).map(|f| issued + Duration::from_nanos(f * 16_666_667)).collect();
        let mut arrivals = Vec::new();
        for (frame, &now) in frame_times.iter().enumerate() {
            assert_eq!(reads.busy(now), frame <= 3, "frame {frame}");
            for m in reads.release(now) {
                arrivals.push((frame, m.texture));
            }
        }
        assert_eq!(arrivals, [(2, 1), (4, 2)]);
        assert_eq!(reads.held(), 0);
    }
}
