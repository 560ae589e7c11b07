//! Image error against a reference, as the flythrough, the bench, the report and the tests
//! report it.
//!
//! One convention for every figure: every measured frame counts. A frame identical to its
//! reference has an MSE of 0 and an unbounded PSNR; it counts at [`PSNR_CEILING_DB`], so the
//! better a run streams, the more (not the fewer) of its frames pull its mean up. The mean
//! squared error over all measured frames needs no ceiling; the PSNR of that mean
//! ([`ErrorFigures::psnr_of_mean_mse_db`]) sums up a run.
//!
//! The start-up fill and the streaming after it are reported apart: in the first
//! [`STARTUP_S`] seconds of path time nothing is resident yet and every policy is equally
//! wrong, and those frames' squared error can outweigh all others. The PSNR of the mean
//! MSE of the frames after it ([`ErrorFigures::streaming`]) is the headline when runs
//! are compared; the start-up's is [`ErrorFigures::startup`].

use citystream_streaming::bench::stats::Stats;
use citystream_streaming::shortfall::ShortfallCause;
use serde::ser::SerializeMap;
use serde::{Deserialize, Serialize, Serializer};

/// The PSNR a frame identical to its reference counts as, in dB (an MSE of 6.5e-6). One
/// 8-bit step on one channel of one pixel is 100.5 dB at 320×180 and more at larger sizes,
/// so such a frame counts at the ceiling too; `ErrorFrames::identical` counts exact matches
/// only, and the MSE keeps every difference.
pub const PSNR_CEILING_DB: f64 = 100.0;

/// Seconds of path time the start-up fill lasts, for the error figures: frames measured
/// before it count as the fill, frames from it on as streaming.
pub const STARTUP_S: f64 = 1.0;

/// Peak value of an 8-bit channel, squared: the numerator of PSNR.
const PEAK_SQUARED: f64 = 255.0 * 255.0;

/// Mean squared error over RGB between two images of the same size.
pub fn mse(a: &image::RgbaImage, b: &image::RgbaImage) -> f64 {
    let mut sum = 0.0f64;
    let mut n = 0u64;
    for (p, q) in a.pixels().zip(b.pixels()) {
        for c in 0..3 {
            let d = f64::from(p.0[c]) - f64::from(q.0[c]);
            sum += d * d;
            n += 1;
        }
    }
    sum / n.max(1) as f64
}

/// PSNR of an MSE over 8-bit channels, in dB, at most [`PSNR_CEILING_DB`] (an MSE of 0, an
/// identical image, gives the ceiling). An MSE that is no measurement (NaN, negative) gives
/// NaN, never the ceiling.
pub fn psnr_of_mse_db(mse: f64) -> f64 {
    if mse > 0.0 {
        (10.0 * (PEAK_SQUARED / mse).log10()).min(PSNR_CEILING_DB)
    } else if mse == 0.0 {
        PSNR_CEILING_DB
    } else {
        f64::NAN
    }
}

/// Peak signal-to-noise ratio of `a` against `b` over RGB, in dB, at most
/// [`PSNR_CEILING_DB`].
pub fn psnr_db(a: &image::RgbaImage, b: &image::RgbaImage) -> f64 {
    psnr_of_mse_db(mse(a, b))
}

/// One measured frame: its MSE and the PSNR it counts as.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameError {
    pub mse: f64,
    pub psnr_db: f64,
}

impl FrameError {
    /// The error of a frame with this MSE.
    pub fn of_mse(mse: f64) -> Self {
        FrameError {
            mse,
            psnr_db: psnr_of_mse_db(mse),
        }
    }

    /// The error of `image` against `reference`.
    pub fn of_images(image: &image::RgbaImage, reference: &image::RgbaImage) -> Self {
        Self::of_mse(mse(image, reference))
    }

    /// Whether the frame equalled its reference.
    pub fn identical(&self) -> bool {
        self.mse == 0.0
    }
}

/// Every measured frame of a run, in order, with its path time.
#[derive(Debug, Clone, Default)]
pub struct ErrorSeries {
    frames: Vec<(f64, FrameError)>,
}

impl ErrorSeries {
    pub fn new() -> Self {
        Self::default()
    }

    /// Counts one frame measured at `path_s` seconds of path time.
    pub fn push(&mut self, path_s: f64, frame: FrameError) {
        self.frames.push((path_s, frame));
    }

    /// The frames with their path times.
    pub fn frames(&self) -> &[(f64, FrameError)] {
        &self.frames
    }

    /// The figures `summary.json` carries; `None` when no frame was measured.
    pub fn figures(&self) -> Option<ErrorFigures> {
        if self.frames.is_empty() {
            return None;
        }
        let psnrs: Vec<f64> = self.frames.iter().map(|(_, f)| f.psnr_db).collect();
        let mses: Vec<f64> = self.frames.iter().map(|(_, f)| f.mse).collect();
        let mean_mse = mses.iter().sum::<f64>() / mses.len() as f64;
        let phase = |startup: bool| {
            PhaseError::of(
                self.frames
                    .iter()
                    .filter(|(t, _)| (*t < STARTUP_S) == startup)
                    .map(|(_, f)| *f),
            )
        };
        Some(ErrorFigures {
            psnr_db: Stats::from_samples(&psnrs),
            psnr_ceiling_db: PSNR_CEILING_DB,
            error_frames: ErrorFrames {
                measured: self.frames.len() as u64,
                identical: self.frames.iter().filter(|(_, f)| f.identical()).count() as u64,
            },
            mse: Stats::from_samples(&mses),
            psnr_of_mean_mse_db: psnr_of_mse_db(mean_mse),
            startup: phase(true),
            streaming: phase(false),
        })
    }
}

/// The error of one phase of a run (the start-up fill, or the streaming after it).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PhaseError {
    /// PSNR of the mean MSE of the phase's measured frames.
    pub psnr_of_mean_mse_db: f64,
    pub error_frames: ErrorFrames,
}

impl PhaseError {
    /// The phase's figures over `frames`; `None` when it has none.
    pub fn of(frames: impl Iterator<Item = FrameError>) -> Option<Self> {
        let (mut measured, mut identical, mut sum) = (0u64, 0u64, 0.0f64);
        for frame in frames {
            measured += 1;
            identical += u64::from(frame.identical());
            sum += frame.mse;
        }
        (measured > 0).then(|| PhaseError {
            psnr_of_mean_mse_db: psnr_of_mse_db(sum / measured as f64),
            error_frames: ErrorFrames { measured, identical },
        })
    }
}

/// A frame's MSE split by why each pixel is coarser than its reference's: the
/// [`ShortfallCause`] of the texture the pixel shows (docs/CONTROLLER.md, "Where the error
/// comes from"). The parts partition the frame's squared error, so they sum to its MSE.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct ErrorCauses {
    /// Not requested yet (feedback lag).
    pub lag_mse: f64,
    /// Requested and waiting (the load size).
    pub load_mse: f64,
    /// Shown coarser by the mip bias.
    pub bias_mse: f64,
    /// Dropped, evicted or refused for room (the budget).
    pub budget_mse: f64,
}

impl ErrorCauses {
    /// The split of [`mse`]`(image, reference)` by the cause `cause_of` names for each pixel
    /// (its column and row). A pixel whose colours agree adds nothing, whatever its cause.
    pub fn of_images(
        image: &image::RgbaImage,
        reference: &image::RgbaImage,
        mut cause_of: impl FnMut(u32, u32) -> ShortfallCause,
    ) -> Self {
        let mut sums = [0.0f64; 4];
        let mut n = 0u64;
        for ((x, y, p), q) in image.enumerate_pixels().zip(reference.pixels()) {
            let mut squared = 0.0;
            for c in 0..3 {
                let d = f64::from(p.0[c]) - f64::from(q.0[c]);
                squared += d * d;
            }
            n += 3;
            if squared > 0.0 {
                sums[cause_of(x, y).index()] += squared;
            }
        }
        let n = n.max(1) as f64;
        Self::from_parts(sums.map(|sum| sum / n))
    }

    /// The parts in [`ShortfallCause::ALL`] order.
    pub fn parts(&self) -> [f64; 4] {
        [self.lag_mse, self.load_mse, self.bias_mse, self.budget_mse]
    }

    fn from_parts(parts: [f64; 4]) -> Self {
        ErrorCauses {
            lag_mse: parts[0],
            load_mse: parts[1],
            bias_mse: parts[2],
            budget_mse: parts[3],
        }
    }

    /// The part of `cause`.
    pub fn part(&self, cause: ShortfallCause) -> f64 {
        self.parts()[cause.index()]
    }

    /// The frame's MSE: the sum of the parts.
    pub fn total(&self) -> f64 {
        self.parts().iter().sum()
    }

    /// The mean of each part over `frames`; `None` when there are none.
    pub fn mean(frames: impl Iterator<Item = ErrorCauses>) -> Option<Self> {
        let (mut sums, mut count) = ([0.0f64; 4], 0u64);
        for frame in frames {
            for (sum, part) in sums.iter_mut().zip(frame.parts()) {
                *sum += part;
            }
            count += 1;
        }
        (count > 0).then(|| Self::from_parts(sums.map(|sum| sum / count as f64)))
    }
}

/// The error causes of a run's measured frames, start-up and streaming apart (as
/// [`ErrorFigures`] splits them): `summary.json`'s `error_causes`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CauseFigures {
    /// Mean parts over the start-up fill's measured frames (path time below [`STARTUP_S`]).
    pub startup: Option<ErrorCauses>,
    /// Mean parts over the frames after it: they sum to the mean MSE behind
    /// `streaming_psnr_of_mean_mse_db`.
    pub streaming: Option<ErrorCauses>,
}

impl CauseFigures {
    /// The figures of frames measured at the given path times; `None` without frames.
    pub fn of(frames: &[(f64, ErrorCauses)]) -> Option<Self> {
        if frames.is_empty() {
            return None;
        }
        let phase = |startup: bool| {
            ErrorCauses::mean(
                frames
                    .iter()
                    .filter(|(t, _)| (*t < STARTUP_S) == startup)
                    .map(|(_, c)| *c),
            )
        };
        Some(CauseFigures {
            startup: phase(true),
            streaming: phase(false),
        })
    }
}

/// How many frames were measured, and how many of them equalled their reference.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct ErrorFrames {
    pub measured: u64,
    pub identical: u64,
}

/// The image-error figures of a run, as `summary.json` carries them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ErrorFigures {
    /// PSNR per measured frame, identical frames at the ceiling.
    pub psnr_db: Stats,
    pub psnr_ceiling_db: f64,
    pub error_frames: ErrorFrames,
    /// MSE per measured frame (over RGB, 8-bit channels).
    pub mse: Stats,
    /// PSNR of the mean MSE over every measured frame. It reaches the ceiling only when
    /// every measured frame is identical.
    pub psnr_of_mean_mse_db: f64,
    /// The frames of the start-up fill (path time below [`STARTUP_S`]); `None` when none
    /// was measured.
    pub startup: Option<PhaseError>,
    /// The frames after it: the headline error; `None` when none was measured.
    pub streaming: Option<PhaseError>,
}

/// The keys of [`ErrorFigures`] in `summary.json`, after a prefix (`""` for the city's,
/// `"ground_"` for the ground's).
pub const ERROR_KEYS: [&str; 9] = [
    "psnr_db",
    "psnr_ceiling_db",
    "error_frames",
    "mse",
    "psnr_of_mean_mse_db",
    "startup_psnr_of_mean_mse_db",
    "startup_error_frames",
    "streaming_psnr_of_mean_mse_db",
    "streaming_error_frames",
];

/// Serializes a run's error figures as top-level keys with a prefix, each `null` when no
/// frame was measured except the ceiling, which is the convention and always stated. Use
/// with `#[serde(flatten)]`.
#[derive(Debug, Clone, Copy)]
pub struct PrefixedErrorFigures {
    pub prefix: &'static str,
    pub figures: Option<ErrorFigures>,
}

impl Serialize for PrefixedErrorFigures {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        let key = |name: &str| format!("{}{name}", self.prefix);
        let f = self.figures.as_ref();
        let mut map = serializer.serialize_map(Some(ERROR_KEYS.len()))?;
        map.serialize_entry(&key("psnr_db"), &f.map(|f| f.psnr_db))?;
        map.serialize_entry(&key("psnr_ceiling_db"), &PSNR_CEILING_DB)?;
        map.serialize_entry(&key("error_frames"), &f.map(|f| f.error_frames))?;
        map.serialize_entry(&key("mse"), &f.map(|f| f.mse))?;
        map.serialize_entry(&key("psnr_of_mean_mse_db"), &f.map(|f| f.psnr_of_mean_mse_db))?;
        let phase = |f: &ErrorFigures, startup: bool| if startup { f.startup } else { f.streaming };
        for (name, startup) in [("startup", true), ("streaming", false)] {
            let p = f.and_then(|f| phase(f, startup));
            map.serialize_entry(
                &key(&format!("{name}_psnr_of_mean_mse_db")),
                &p.map(|p| p.psnr_of_mean_mse_db),
            )?;
            map.serialize_entry(&key(&format!("{name}_error_frames")), &p.map(|p| p.error_frames))?;
        }
        map.end()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn psnr_of_a_known_difference() {
        let a = image::RgbaImage::from_pixel(4, 4, image::Rgba([10, 20, 30, 255]));
        let mut b = a.clone();
        assert_eq!(psnr_db(&a, &b), PSNR_CEILING_DB);
        // One channel of one pixel off by 48: MSE 48² / 48 = 48.
        b.put_pixel(0, 0, image::Rgba([58, 20, 30, 0]));
        assert!((mse(&a, &b) - 48.0).abs() < 1e-12);
        assert!((psnr_db(&a, &b) - 10.0 * (65025.0f64 / 48.0).log10()).abs() < 1e-12);
    }

    #[test]
    fn error_causes_partition_the_mse() {
        // Pseudo-random images and causes: the four parts sum to the MSE.
        let mut rng = citystream_streaming::rng::SplitMix64::new(7);
        let mut byte = || (rng.next_u64() & 0xFF) as u8;
        let (w, h) = (37, 23);
        let a = image::RgbaImage::from_fn(w, h, |_, _| image::Rgba([byte(), byte(), byte(), 255]));
        let b = image::RgbaImage::from_fn(w, h, |x, y| {
            let p = a.get_pixel(x, y).0;
            // A third of the pixels equal, the rest off by up to 255 per channel.
            if (x + y) % 3 == 0 {
                image::Rgba(p)
            } else {
                image::Rgba([byte(), byte(), byte(), 0])
            }
        });
        let cause_of = |x: u32, y: u32| ShortfallCause::ALL[((x * 7 + y * 3) % 4) as usize];
        let causes = ErrorCauses::of_images(&a, &b, cause_of);
        let total = mse(&a, &b);
        assert!(total > 0.0);
        assert!(((causes.total() - total) / total).abs() < 1e-6, "{causes:?} vs {total}");
        for cause in ShortfallCause::ALL {
            assert!(causes.part(cause) > 0.0, "{cause:?}");
        }
        // One pixel off by 48 on one channel, charged to the bias: the whole MSE there.
        let mut c = a.clone();
        c.put_pixel(
            3,
            4,
            image::Rgba([
                a.get_pixel(3, 4).0[0].wrapping_add(48),
                a.get_pixel(3, 4).0[1],
                a.get_pixel(3, 4).0[2],
                255,
            ]),
        );
        let one = ErrorCauses::of_images(&c, &a, |x, y| {
            if (x, y) == (3, 4) {
                ShortfallCause::Bias
            } else {
                ShortfallCause::Lag
            }
        });
        assert_eq!(one.lag_mse, 0.0);
        assert!((one.bias_mse - mse(&c, &a)).abs() < 1e-12);
        // Identical images: nothing to attribute.
        assert_eq!(ErrorCauses::of_images(&a, &a, cause_of).total(), 0.0);
    }

    #[test]
    fn cause_figures_average_each_phase_apart() {
        assert_eq!(CauseFigures::of(&[]), None);
        let frame = |lag, load| ErrorCauses {
            lag_mse: lag,
            load_mse: load,
            ..ErrorCauses::default()
        };
        let figures = CauseFigures::of(&[(0.5, frame(4.0, 0.0)), (1.0, frame(1.0, 2.0)), (2.0, frame(3.0, 0.0))])
            .expect("frames");
        assert_eq!(figures.startup, Some(frame(4.0, 0.0)));
        assert_eq!(figures.streaming, Some(frame(2.0, 1.0)));
    }

    #[test]
    fn psnr_of_hard_mses() {
        assert_eq!(psnr_of_mse_db(0.0), PSNR_CEILING_DB);
        // Below the ceiling's MSE the ceiling holds; far above, the PSNR goes negative.
        assert_eq!(psnr_of_mse_db(1e-300), PSNR_CEILING_DB);
        assert!((psnr_of_mse_db(PEAK_SQUARED) - 0.0).abs() < 1e-12);
        assert!(psnr_of_mse_db(1e6) < 0.0);
        // A NaN or negative MSE is no measurement of an identical frame: NaN, not 100 dB.
        assert!(psnr_of_mse_db(f64::NAN).is_nan());
        assert!(psnr_of_mse_db(-1.0).is_nan());
        assert_eq!(psnr_of_mse_db(f64::INFINITY), f64::NEG_INFINITY);
    }

    #[test]
    fn every_measured_frame_counts() {
        let mut series = ErrorSeries::new();
        assert_eq!(series.figures(), None);
        for (path_s, mse) in [(0.0, 100.0), (0.5, 0.0), (1.0, 0.0), (3.0, 2.0)] {
            series.push(path_s, FrameError::of_mse(mse));
        }
        let f = series.figures().expect("measured");
        assert_eq!(
            f.error_frames,
            ErrorFrames {
                measured: 4,
                identical: 2
            }
        );
        assert_eq!(f.psnr_ceiling_db, PSNR_CEILING_DB);
        let psnr_100 = 10.0 * (PEAK_SQUARED / 100.0).log10();
        let psnr_2 = 10.0 * (PEAK_SQUARED / 2.0).log10();
        assert!((f.psnr_db.mean - (psnr_100 + psnr_2 + 200.0) / 4.0).abs() < 1e-9);
        assert_eq!(f.psnr_db.max, PSNR_CEILING_DB);
        assert_eq!(f.psnr_db.min, psnr_100);
        assert!((f.mse.mean - 25.5).abs() < 1e-12);
        assert!((f.psnr_of_mean_mse_db - 10.0 * (PEAK_SQUARED / 25.5).log10()).abs() < 1e-12);
        // Apart: the start-up fill (before 1 s of path) and the streaming after it.
        let startup = f.startup.expect("start-up frames");
        let streaming = f.streaming.expect("streaming frames");
        assert_eq!(
            startup.error_frames,
            ErrorFrames {
                measured: 2,
                identical: 1
            }
        );
        assert_eq!(
            streaming.error_frames,
            ErrorFrames {
                measured: 2,
                identical: 1
            }
        );
        assert!((startup.psnr_of_mean_mse_db - 10.0 * (PEAK_SQUARED / 50.0).log10()).abs() < 1e-12);
        assert!((streaming.psnr_of_mean_mse_db - 10.0 * (PEAK_SQUARED / 1.0).log10()).abs() < 1e-12);
    }

    #[test]
    fn a_run_measured_only_after_start_up_has_no_start_up_figures() {
        let mut series = ErrorSeries::new();
        series.push(STARTUP_S, FrameError::of_mse(4.0));
        let f = series.figures().expect("measured");
        assert_eq!(f.startup, None);
        assert_eq!(f.streaming.map(|p| p.psnr_of_mean_mse_db), Some(f.psnr_of_mean_mse_db));
    }

    #[test]
    fn all_identical_reaches_the_ceiling() {
        let mut series = ErrorSeries::new();
        series.push(0.0, FrameError::of_mse(0.0));
        let f = series.figures().expect("measured");
        assert_eq!(f.psnr_of_mean_mse_db, PSNR_CEILING_DB);
        assert_eq!(
            f.error_frames,
            ErrorFrames {
                measured: 1,
                identical: 1
            }
        );
    }

    #[test]
    fn prefixed_keys() {
        #[derive(Serialize)]
        struct Summary {
            frames: u32,
            #[serde(flatten)]
            city: PrefixedErrorFigures,
            #[serde(flatten)]
            ground: PrefixedErrorFigures,
        }
        let mut series = ErrorSeries::new();
        series.push(0.0, FrameError::of_mse(0.0));
        series.push(2.0, FrameError::of_mse(0.0));
        let summary = Summary {
            frames: 1,
            city: PrefixedErrorFigures {
                prefix: "",
                figures: series.figures(),
            },
            ground: PrefixedErrorFigures {
                prefix: "ground_",
                figures: None,
            },
        };
        let json: serde_json::Value = serde_json::to_value(&summary).expect("serializes");
        for key in ERROR_KEYS {
            assert!(!json[key].is_null(), "{key}: {json}");
            let ground = format!("ground_{key}");
            assert_eq!(json[&ground].is_null(), key != "psnr_ceiling_db", "{ground}: {json}");
        }
        assert_eq!(json["error_frames"]["identical"], 2);
        assert_eq!(json["psnr_of_mean_mse_db"], PSNR_CEILING_DB);
        assert_eq!(json["streaming_error_frames"]["measured"], 1);
        assert_eq!(json["startup_psnr_of_mean_mse_db"], PSNR_CEILING_DB);
    }
}
