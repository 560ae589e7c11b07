//! Camera paths: keyframed flythroughs with explicit pauses and jumps, and the standard
//! benchmark path of paper §4.1.
//!
//! # File format (version [`PATH_FORMAT_VERSION`], JSON; specified in `docs/PATHS.md`)
//!
//! ```json
//! {
//!   "version": 1,
//!   "description": "optional free text",
//!   "keyframes": [
//!     { "t": 0.0, "position": [0, 80, -60], "look_at": [0, 10, 0] },
//!     { "t": 6.0, "position": [40, 80, -20], "look_at": [40, 10, 40], "hold_s": 2.0 },
//!     { "t": 14.0, "position": [90, 80, 10], "look_at": [90, 10, 70] },
//!     { "t": 14.0, "position": [-50, 80, 0], "look_at": [0, 10, 0], "jump": true }
//!   ]
//! }
//! ```
//!
//! - `t`: seconds from the start of the path at which the camera reaches the keyframe.
//! - `position`, `look_at`: metres in dataset-local coordinates, the frame of the dataset's
//!   scene positions (relative to [`Scene::origin`], +y up).
//! - `hold_s` (optional, default 0): a **pause**: the camera holds still at this keyframe
//!   from `t` to `t + hold_s`.
//! - `jump` (optional, default false): a **jump**: the camera teleports to this keyframe at
//!   `t`, with no interpolation from the previous keyframe. Until then it stays at the
//!   previous keyframe.
//!
//! Validation ([`CameraPath::new`], [`CameraPath::from_json`]): the version must be
//! [`PATH_FORMAT_VERSION`]; there is at least one keyframe; every number is finite; `t` and
//! `hold_s` are not negative; the first keyframe is not a jump; each keyframe's `t` is later
//! than the previous keyframe's end (`t + hold_s`), except that a jump may happen exactly at
//! that end; `look_at` is at least [`MIN_VIEW_DISTANCE_M`] from `position`. Unknown keys are
//! errors, so a misspelt `hold_s` does not silently vanish. Every error names the keyframe.
//!
//! # Interpolation
//!
//! Between keyframes of one run (a run ends at a jump) position and look-at follow cubic
//! Hermite curves with Catmull-Rom tangents over time, so motion is C1-smooth through
//! keyframes. The tangent is zero at the ends of a run and at keyframes with a pause (the
//! camera eases in and out of them). Each tangent is clamped so that the curve's Bézier control
//! points stay inside the axis-aligned box of the path's keyframes; hence sampled positions
//! (look-at points) never leave the box of the keyframe positions (look-at points): a path
//! whose keyframes look at the city and fly above the roofs does so everywhere in between.
//!
//! # Contracts
//!
//! - [`CameraPath::sample`] never panics; it returns finite values with `look_at != position`
//!   for every `t`, clamping `t` to `[0, duration]` (NaN counts as 0).
//! - At the exact start and end of a pause the position is bit-identical to the keyframe's.
//! - [`standard_path`] is deterministic: the same scene and duration give the same path.
//! - No Vulkan, no I/O except [`CameraPath::load`] and [`CameraPath::save`].
//!
//! [`Scene::origin`]: citystream_dataset::Scene::origin

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use serde::{Deserialize, Serialize};

use citystream_dataset::Scene;

/// The camera path file version this build reads and writes.
pub const PATH_FORMAT_VERSION: u32 = 1;
/// Smallest allowed distance between a keyframe's `position` and `look_at`, metres.
pub const MIN_VIEW_DISTANCE_M: f32 = 1e-3;
/// Number of pauses in the standard path (paper §4.1).
pub const STANDARD_PAUSES: usize = 4;
/// Length of each pause in the standard path, seconds (paper §4.1).
pub const STANDARD_PAUSE_S: f64 = 2.0;
/// Number of jumps in the standard path (paper §4.1).
pub const STANDARD_JUMPS: usize = 4;
/// Default length of the standard path, seconds ("about a minute").
pub const DEFAULT_STANDARD_DURATION_S: f64 = 60.0;
/// The longest a camera path may last: one day. A replay runs at least one
/// frame per 60 Hz step, so longer paths are mistakes, not benchmarks.
pub const MAX_PATH_DURATION_S: f64 = 86_400.0;
/// Shortest standard path: the pauses plus one second for each of its ten flight segments.
pub const MIN_STANDARD_DURATION_S: f64 = STANDARD_PAUSES as f64 * STANDARD_PAUSE_S + STANDARD_SEGMENTS as f64;

/// Flight legs of the standard path: one before the first jump and one after each.
const STANDARD_LEGS: usize = STANDARD_JUMPS + 1;
/// Each leg flies start → middle → end.
const STANDARD_SEGMENTS: usize = 2 * STANDARD_LEGS;
/// The standard camera looks down at this angle below the horizon (an oblique bird's-eye
/// view: high mips in the foreground, the full range of mips towards the horizon).
const STANDARD_PITCH_DEG: f64 = 40.0;
/// Horizontal view direction (azimuth from +z towards +x) in the middle of the first leg.
const STANDARD_FIRST_HEADING_DEG: f64 = 20.0;
/// Each leg's heading turns by this from the previous one (five distinct headings), so every
/// jump lands on a new view even where the waypoints coincide (a one-building scene).
const STANDARD_LEG_TURN_DEG: f64 = 144.0;
/// Within a leg the heading swings from −this to +this.
const STANDARD_LEG_SWING_DEG: f64 = 15.0;
/// Target number of density grid cells along the longer horizontal side of the bounds.
const DENSITY_GRID_CELLS: usize = 8;
/// Flight altitude above the highest roof is at most this, metres, however big the city:
/// higher, the foreground would never need the finest mips.
const MAX_CLEARANCE_M: f64 = 250.0;

/// Errors of reading, validating and generating camera paths.
#[derive(Debug, thiserror::Error)]
pub enum PathError {
    // Messages include the underlying error instead of chaining it as a `source`, so that
    // printing an error with `{}` alone tells the whole story, without repeating it in chains.
    /// The file could not be read or written.
    #[error("camera path {}: {error}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        error: std::io::Error,
    },
    /// An error in a camera path file, with the file's name.
    #[error("camera path {}: {error}", path.display())]
    InFile {
        /// The file.
        path: PathBuf,
        /// What is wrong with its contents.
        error: Box<PathError>,
    },
    /// The text is not JSON, or the document is not an object of the expected shape.
    #[error("invalid camera path JSON: {0}")]
    Json(serde_json::Error),
    /// A keyframe is not an object of the expected shape (wrong type, unknown key, missing key).
    #[error("keyframe {index}: {error}")]
    KeyframeJson {
        /// Keyframe index, from 0.
        index: usize,
        /// The parse error.
        error: serde_json::Error,
    },
    /// The top-level object has a key the format does not define.
    #[error("unknown key `{0}` (expected `version`, `description`, `keyframes`)")]
    UnknownKey(String),
    /// The `version` key is missing.
    #[error("missing `version` (this build reads camera path version {PATH_FORMAT_VERSION})")]
    MissingVersion,
    /// The file's version is not the one this build reads.
    #[error("unsupported camera path version {found} (this build reads version {PATH_FORMAT_VERSION})")]
    UnsupportedVersion {
        /// The version found, as written.
        found: String,
    },
    /// The path has no keyframes.
    #[error("camera path has no keyframes")]
    Empty,
    /// A number is NaN or infinite (including values too large for an f32).
    #[error("keyframe {index}: `{field}` is not finite")]
    NonFinite {
        /// Keyframe index, from 0.
        index: usize,
        /// The key: `t`, `position`, `look_at` or `hold_s`.
        field: &'static str,
    },
    /// A keyframe ends after [`MAX_PATH_DURATION_S`].
    #[error("keyframe {index}: it ends at {end_s} s, after the longest path allowed ({MAX_PATH_DURATION_S} s)")]
    TooLong {
        /// Keyframe index, from 0.
        index: usize,
        /// Its `t + hold_s`.
        end_s: f64,
    },
    /// A time or duration is negative.
    #[error("keyframe {index}: `{field}` = {value} is negative")]
    Negative {
        /// Keyframe index, from 0.
        index: usize,
        /// The key: `t` or `hold_s`.
        field: &'static str,
        /// The value.
        value: f64,
    },
    /// A keyframe does not come after the end of the previous one.
    #[error(
        "keyframe {index}: t = {t} s is not after the end of keyframe {} (t + hold_s = {previous_end} s); \
         times must increase (only a jump may happen exactly at the previous end)",
        index - 1
    )]
    NotIncreasing {
        /// Keyframe index, from 1.
        index: usize,
        /// Its time.
        t: f64,
        /// The end of the previous keyframe (its `t + hold_s`).
        previous_end: f64,
    },
    /// The first keyframe is marked as a jump; there is nothing to jump from.
    #[error("keyframe 0: the first keyframe cannot be a jump")]
    FirstKeyframeJump,
    /// `look_at` is (almost) equal to `position`, so the view direction is undefined.
    #[error("keyframe {index}: `look_at` is within {MIN_VIEW_DISTANCE_M} m of `position`")]
    DegenerateView {
        /// Keyframe index, from 0.
        index: usize,
    },
    /// The requested standard path duration is too short or not finite.
    #[error(
        "path duration {duration_s} s must be finite, at least {MIN_STANDARD_DURATION_S} s and at most {MAX_PATH_DURATION_S} s"
    )]
    InvalidDuration {
        /// The requested duration.
        duration_s: f64,
    },
    /// The scene has no mesh with vertices, so there is nothing to fly over.
    #[error("the scene has no mesh with vertices; a camera path needs something to look at")]
    EmptyScene,
}

/// One keyframe of a [`CameraPath`]; the fields are the JSON keys.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Keyframe {
    /// Seconds from the start of the path at which the camera is here.
    pub t: f64,
    /// Eye position, dataset-local metres (relative to the scene origin, +y up).
    pub position: [f32; 3],
    /// Point the camera looks at, dataset-local metres.
    pub look_at: [f32; 3],
    /// A pause: the camera stays here from `t` to `t + hold_s`. Zero: no pause.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub hold_s: f64,
    /// A jump: the camera teleports here at `t` instead of flying from the previous keyframe.
    #[serde(default, skip_serializing_if = "is_false")]
    pub jump: bool,
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

fn is_false(v: &bool) -> bool {
    !*v
}

impl Keyframe {
    /// A keyframe with no pause and no jump.
    pub fn new(t: f64, position: [f32; 3], look_at: [f32; 3]) -> Self {
        Self {
            t,
            position,
            look_at,
            hold_s: 0.0,
            jump: false,
        }
    }

    /// When the camera leaves this keyframe: `t + hold_s`.
    pub fn end_s(&self) -> f64 {
        self.t + self.hold_s
    }
}

/// The camera at one instant.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraPose {
    /// Eye position, dataset-local metres.
    pub position: [f32; 3],
    /// Point looked at, dataset-local metres; never equal to `position`.
    pub look_at: [f32; 3],
    /// Whether the time lies in a pause (`[t, t + hold_s)` of a keyframe with `hold_s > 0`).
    pub in_pause: bool,
    /// Whether a jump lies between the previous sample's time and this one's, i.e. this is
    /// the first sample after the camera teleported (see [`CameraPath::sample`]).
    pub jumped: bool,
}

/// A pause of a path: the camera holds still from `start_s` for `duration_s`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pause {
    /// When the pause starts, seconds.
    pub start_s: f64,
    /// How long it lasts, seconds.
    pub duration_s: f64,
}

/// The JSON document. Keyframes are parsed one by one (see [`CameraPath::from_json`]) so that
/// errors can name them.
#[derive(Serialize)]
struct PathFileOut<'a> {
    version: u32,
    #[serde(skip_serializing_if = "Option::is_none")]
    description: Option<&'a str>,
    keyframes: &'a [Keyframe],
}

/// Hermite data of one keyframe: tangents (metres per second) of position and look-at.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Tangents {
    position: [f64; 3],
    look_at: [f64; 3],
}

/// A validated camera path.
///
/// Threading: `Send + Sync`. [`CameraPath::sample`] remembers the time of the previous call
/// (atomically) to report jumps; calls from several threads interleave that memory, so sample
/// from one thread (the frame loop) or use the pure [`CameraPath::sample_between`].
#[derive(Debug)]
pub struct CameraPath {
    description: Option<String>,
    keyframes: Vec<Keyframe>,
    tangents: Vec<Tangents>,
    /// Boxes of the keyframe positions and look-at points; samples stay inside them.
    position_box: ([f64; 3], [f64; 3]),
    look_at_box: ([f64; 3], [f64; 3]),
    /// Bits of the previous [`CameraPath::sample`] time; NaN when there was none.
    last_sample_bits: AtomicU64,
}

impl Clone for CameraPath {
    fn clone(&self) -> Self {
        Self {
            description: self.description.clone(),
            keyframes: self.keyframes.clone(),
            tangents: self.tangents.clone(),
            position_box: self.position_box,
            look_at_box: self.look_at_box,
            last_sample_bits: AtomicU64::new(self.last_sample_bits.load(Ordering::Relaxed)),
        }
    }
}

/// Paths are equal when their description and keyframes are; sampling memory is ignored.
impl PartialEq for CameraPath {
    fn eq(&self, other: &Self) -> bool {
        self.description == other.description && self.keyframes == other.keyframes
    }
}

fn finite3(v: [f32; 3]) -> bool {
    v.iter().all(|x| x.is_finite())
}

fn to_f64(v: [f32; 3]) -> [f64; 3] {
    v.map(f64::from)
}

fn distance(a: [f32; 3], b: [f32; 3]) -> f64 {
    (0..3)
        .map(|i| (f64::from(a[i]) - f64::from(b[i])).powi(2))
        .sum::<f64>()
        .sqrt()
}

fn validate(keyframes: &[Keyframe]) -> Result<(), PathError> {
    if keyframes.is_empty() {
        return Err(PathError::Empty);
    }
    for (index, k) in keyframes.iter().enumerate() {
        let non_finite = |field| PathError::NonFinite { index, field };
        if !k.t.is_finite() {
            return Err(non_finite("t"));
        }
        if !finite3(k.position) {
            return Err(non_finite("position"));
        }
        if !finite3(k.look_at) {
            return Err(non_finite("look_at"));
        }
        if !k.hold_s.is_finite() {
            return Err(non_finite("hold_s"));
        }
        if k.t < 0.0 {
            return Err(PathError::Negative {
                index,
                field: "t",
                value: k.t,
            });
        }
        if k.hold_s < 0.0 {
            return Err(PathError::Negative {
                index,
                field: "hold_s",
                value: k.hold_s,
            });
        }
        if !k.end_s().is_finite() {
            return Err(non_finite("hold_s"));
        }
        if k.end_s() > MAX_PATH_DURATION_S {
            return Err(PathError::TooLong {
                index,
                end_s: k.end_s(),
            });
        }
        if distance(k.position, k.look_at) < f64::from(MIN_VIEW_DISTANCE_M) {
            return Err(PathError::DegenerateView { index });
        }
        if index == 0 {
            if k.jump {
                return Err(PathError::FirstKeyframeJump);
            }
        } else {
            let previous_end = keyframes[index - 1].end_s();
            let in_order = if k.jump {
                k.t >= previous_end
            } else {
                k.t > previous_end
            };
            if !in_order {
                return Err(PathError::NotIncreasing {
                    index,
                    t: k.t,
                    previous_end,
                });
            }
        }
    }
    Ok(())
}

fn bounding_box(points: impl Iterator<Item = [f32; 3]>) -> ([f64; 3], [f64; 3]) {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in points {
        for a in 0..3 {
            lo[a] = lo[a].min(f64::from(p[a]));
            hi[a] = hi[a].max(f64::from(p[a]));
        }
    }
    (lo, hi)
}

/// Catmull-Rom tangent at `here` over the motion time from the previous keyframe's end to the
/// next keyframe, clamped per axis so that the Bézier control points `here ∓ m·dt/3` of the
/// two adjacent segments stay inside `[lo, hi]` (which contains `here`).
fn clamped_tangent(
    previous: [f32; 3],
    here: [f32; 3],
    next: [f32; 3],
    (dt_in, dt_out): (f64, f64),
    (lo, hi): ([f64; 3], [f64; 3]),
) -> [f64; 3] {
    let mut m = [0.0; 3];
    for a in 0..3 {
        let p = f64::from(here[a]);
        let raw = (f64::from(next[a]) - f64::from(previous[a])) / (dt_in + dt_out);
        // From p + m·dt_out/3 ∈ [lo, hi] and p − m·dt_in/3 ∈ [lo, hi]; both ranges hold 0.
        let low = ((lo[a] - p) * 3.0 / dt_out).max((p - hi[a]) * 3.0 / dt_in);
        let high = ((hi[a] - p) * 3.0 / dt_out).min((p - lo[a]) * 3.0 / dt_in);
        m[a] = if low <= high { raw.clamp(low, high) } else { 0.0 };
    }
    m
}

fn compute_tangents(
    keyframes: &[Keyframe],
    position_box: ([f64; 3], [f64; 3]),
    look_at_box: ([f64; 3], [f64; 3]),
) -> Vec<Tangents> {
    let zero = Tangents {
        position: [0.0; 3],
        look_at: [0.0; 3],
    };
    (0..keyframes.len())
        .map(|k| {
            let here = &keyframes[k];
            // Zero at run ends (path ends, next to a jump) and at pauses: the camera eases.
            if k == 0 || k + 1 == keyframes.len() || here.jump || here.hold_s > 0.0 || keyframes[k + 1].jump {
                return zero;
            }
            let previous = &keyframes[k - 1];
            let next = &keyframes[k + 1];
            let dts = (here.t - previous.end_s(), next.t - here.t);
            Tangents {
                position: clamped_tangent(previous.position, here.position, next.position, dts, position_box),
                look_at: clamped_tangent(previous.look_at, here.look_at, next.look_at, dts, look_at_box),
            }
        })
        .collect()
}

fn hermite(
    p0: [f32; 3],
    m0: [f64; 3],
    p1: [f32; 3],
    m1: [f64; 3],
    dt: f64,
    s: f64,
    bx: ([f64; 3], [f64; 3]),
) -> [f64; 3] {
    let s2 = s * s;
    let s3 = s2 * s;
    let h00 = 2.0 * s3 - 3.0 * s2 + 1.0;
    let h10 = s3 - 2.0 * s2 + s;
    let h01 = -2.0 * s3 + 3.0 * s2;
    let h11 = s3 - s2;
    let mut out = [0.0; 3];
    for a in 0..3 {
        let v = h00 * f64::from(p0[a]) + h10 * dt * m0[a] + h01 * f64::from(p1[a]) + h11 * dt * m1[a];
        // The curve lies in the box in exact arithmetic; clamp away rounding.
        out[a] = v.clamp(bx.0[a], bx.1[a]);
    }
    out
}

fn to_f32(v: [f64; 3]) -> [f32; 3] {
    v.map(|x| x as f32)
}

impl CameraPath {
    /// Validates `keyframes` (see the module docs) and prepares them for sampling.
    pub fn new(keyframes: Vec<Keyframe>) -> Result<Self, PathError> {
        validate(&keyframes)?;
        let position_box = bounding_box(keyframes.iter().map(|k| k.position));
        let look_at_box = bounding_box(keyframes.iter().map(|k| k.look_at));
        let tangents = compute_tangents(&keyframes, position_box, look_at_box);
        Ok(Self {
            description: None,
            keyframes,
            tangents,
            position_box,
            look_at_box,
            last_sample_bits: AtomicU64::new(f64::NAN.to_bits()),
        })
    }

    /// Sets the free-text description written to the file.
    pub fn with_description(mut self, description: impl Into<String>) -> Self {
        self.description = Some(description.into());
        self
    }

    /// The free-text description, if any.
    pub fn description(&self) -> Option<&str> {
        self.description.as_deref()
    }

    /// The keyframes, in time order.
    pub fn keyframes(&self) -> &[Keyframe] {
        &self.keyframes
    }

    /// Parses and validates a camera path document (see the module docs for the format).
    pub fn from_json(text: &str) -> Result<Self, PathError> {
        let value: serde_json::Value = serde_json::from_str(text).map_err(PathError::Json)?;
        let Some(object) = value.as_object() else {
            return Err(PathError::Json(serde::de::Error::custom(
                "a camera path is a JSON object with `version` and `keyframes`",
            )));
        };
        if let Some(key) = object
            .keys()
            .find(|k| !matches!(k.as_str(), "version" | "description" | "keyframes"))
        {
            return Err(PathError::UnknownKey(key.clone()));
        }
        match object.get("version") {
            None => return Err(PathError::MissingVersion),
            Some(v) if v.as_u64() == Some(u64::from(PATH_FORMAT_VERSION)) => {}
            Some(v) => return Err(PathError::UnsupportedVersion { found: v.to_string() }),
        }
        let description = match object.get("description") {
            None | Some(serde_json::Value::Null) => None,
            Some(serde_json::Value::String(s)) => Some(s.clone()),
            Some(_) => {
                return Err(PathError::Json(serde::de::Error::custom(
                    "`description` must be a string",
                )));
            }
        };
        let Some(list) = object.get("keyframes") else {
            return Err(PathError::Json(serde::de::Error::missing_field("keyframes")));
        };
        let Some(list) = list.as_array() else {
            return Err(PathError::Json(serde::de::Error::custom(
                "`keyframes` must be an array",
            )));
        };
        let keyframes = list
            .iter()
            .enumerate()
            .map(|(index, v)| Keyframe::deserialize(v).map_err(|error| PathError::KeyframeJson { index, error }))
            .collect::<Result<Vec<_>, _>>()?;
        let path = Self::new(keyframes)?;
        Ok(match description {
            Some(d) => path.with_description(d),
            None => path,
        })
    }

    /// Reads and validates a camera path file. Errors name the file.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, PathError> {
        let path = path.as_ref();
        let text = citystream_dataset::ensure_regular_file(path)
            .and_then(|()| std::fs::read_to_string(path))
            .map_err(|error| PathError::Io {
                path: path.to_path_buf(),
                error,
            })?;
        Self::from_json(&text).map_err(|e| PathError::InFile {
            path: path.to_path_buf(),
            error: Box::new(e),
        })
    }

    /// The path as a pretty-printed JSON document that [`CameraPath::from_json`] reads back
    /// to an equal path (f32 and f64 values round-trip exactly).
    pub fn to_json(&self) -> Result<String, PathError> {
        let file = PathFileOut {
            version: PATH_FORMAT_VERSION,
            description: self.description.as_deref(),
            keyframes: &self.keyframes,
        };
        let mut text = serde_json::to_string_pretty(&file).map_err(PathError::Json)?;
        text.push('\n');
        Ok(text)
    }

    /// Writes [`CameraPath::to_json`] to `path` atomically: to a new file beside it, flushed
    /// to disk, then renamed over `path`, so a crash or a full disk leaves either the old file
    /// or the new one, never a torn mix.
    pub fn save(&self, path: impl AsRef<Path>) -> Result<(), PathError> {
        let path = path.as_ref();
        let text = self.to_json()?;
        let io = |error| PathError::Io {
            path: path.to_path_buf(),
            error,
        };
        let name = path
            .file_name()
            .ok_or_else(|| io(std::io::Error::new(std::io::ErrorKind::InvalidInput, "not a file name")))?;
        let dir = match path.parent() {
            Some(parent) if !parent.as_os_str().is_empty() => parent.to_path_buf(),
            _ => std::path::PathBuf::from("."),
        };
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.subsec_nanos());
        let temp = dir.join(format!(
            ".{}.{}-{nanos}.tmp",
            name.to_string_lossy(),
            std::process::id()
        ));
        // Only a file this call created is ever removed.
        let mut file = std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&temp)
            .map_err(io)?;
        let written = (|| {
            use std::io::Write;
            file.write_all(text.as_bytes())?;
            // The replaced file's permissions carry over (a path to a symlink
            // is replaced by the file, not written through).
            if let Ok(old) = std::fs::metadata(path) {
                if old.is_file() {
                    file.set_permissions(old.permissions())?;
                }
            }
            file.sync_all()?;
            std::fs::rename(&temp, path)
        })();
        if let Err(error) = written {
            let _ = std::fs::remove_file(&temp);
            return Err(io(error));
        }
        // The rename is durable once the directory is; where it cannot be opened (a platform
        // without directory handles) the file is still complete.
        if let Ok(dir) = std::fs::File::open(&dir) {
            let _ = dir.sync_all();
        }
        Ok(())
    }

    /// Length of the path: the end of the last keyframe (its `t + hold_s`), seconds.
    pub fn duration_s(&self) -> f64 {
        self.keyframes.last().map_or(0.0, Keyframe::end_s)
    }

    /// The pauses, in time order.
    pub fn pauses(&self) -> Vec<Pause> {
        self.keyframes
            .iter()
            .filter(|k| k.hold_s > 0.0)
            .map(|k| Pause {
                start_s: k.t,
                duration_s: k.hold_s,
            })
            .collect()
    }

    /// The times of the jumps, in order.
    pub fn jumps(&self) -> Vec<f64> {
        self.keyframes.iter().filter(|k| k.jump).map(|k| k.t).collect()
    }

    /// The camera at `t_s` seconds; `jumped` is true when a jump lies between the time of the
    /// previous call to `sample` on this path and `t_s` (false on the first call). A frame
    /// loop calling this once per frame with its clock thus sees `jumped` on exactly the first
    /// frame after each jump. [`CameraPath::restart`] forgets the previous call.
    pub fn sample(&self, t_s: f64) -> CameraPose {
        let t = self.clamp_time(t_s);
        let previous = f64::from_bits(self.last_sample_bits.swap(t.to_bits(), Ordering::Relaxed));
        self.sample_between((!previous.is_nan()).then_some(previous), t)
    }

    /// Forgets the previous [`CameraPath::sample`] call, as at the start of a run.
    pub fn restart(&self) {
        self.last_sample_bits.store(f64::NAN.to_bits(), Ordering::Relaxed);
    }

    /// The camera at `t_s`, with `jumped` true when a jump lies in `(previous_t_s, t_s]` (or
    /// `(t_s, previous_t_s]` going back). Pure: no memory of earlier calls.
    pub fn sample_between(&self, previous_t_s: Option<f64>, t_s: f64) -> CameraPose {
        let t = self.clamp_time(t_s);
        let jumped = previous_t_s.is_some_and(|p| {
            let p = self.clamp_time(p);
            let (lo, hi) = if p <= t { (p, t) } else { (t, p) };
            self.keyframes.iter().any(|k| k.jump && k.t > lo && k.t <= hi)
        });
        let (position, look_at, in_pause) = self.pose_at(t);
        CameraPose {
            position,
            look_at: separate_look_at(position, look_at),
            in_pause,
            jumped,
        }
    }

    fn clamp_time(&self, t_s: f64) -> f64 {
        if t_s.is_nan() {
            0.0
        } else {
            t_s.clamp(0.0, self.duration_s())
        }
    }

    /// Position, look-at and whether `t` (already clamped) lies in a pause.
    fn pose_at(&self, t: f64) -> ([f32; 3], [f32; 3], bool) {
        let after = self.keyframes.partition_point(|k| k.t <= t);
        let Some(k) = after.checked_sub(1) else {
            // Before the first keyframe: wait there.
            let first = &self.keyframes[0];
            return (first.position, first.look_at, false);
        };
        let here = &self.keyframes[k];
        if t < here.end_s() {
            return (here.position, here.look_at, true);
        }
        let Some(next) = self.keyframes.get(k + 1) else {
            return (here.position, here.look_at, false);
        };
        if next.jump {
            return (here.position, here.look_at, false);
        }
        let dt = next.t - here.end_s();
        let s = ((t - here.end_s()) / dt).clamp(0.0, 1.0);
        let (m0, m1) = (&self.tangents[k], &self.tangents[k + 1]);
        let position = hermite(
            here.position,
            m0.position,
            next.position,
            m1.position,
            dt,
            s,
            self.position_box,
        );
        let look_at = hermite(
            here.look_at,
            m0.look_at,
            next.look_at,
            m1.look_at,
            dt,
            s,
            self.look_at_box,
        );
        (to_f32(position), to_f32(look_at), false)
    }
}

/// Interpolation can, in principle, bring the look-at point onto the eye; move it off along
/// −y (down) by at least one f32 step so that a view direction always exists.
fn separate_look_at(position: [f32; 3], mut look_at: [f32; 3]) -> [f32; 3] {
    if look_at == position {
        let y = position[1];
        look_at[1] = y - (y.abs() * 1e-6).max(MIN_VIEW_DISTANCE_M);
    }
    look_at
}

/// Mesh-centre counts on a horizontal grid over the scene bounds.
struct DensityGrid {
    nx: usize,
    nz: usize,
    min: [f64; 2],
    cell: [f64; 2],
    /// Per cell: meshes, and the sum of their centres (for the mean).
    counts: Vec<u64>,
    centre_sums: Vec<[f64; 3]>,
}

impl DensityGrid {
    fn new(scene: &Scene, lo: [f64; 3], hi: [f64; 3]) -> Self {
        let size = [hi[0] - lo[0], hi[2] - lo[2]];
        let longest = size[0].max(size[1]);
        let cells_along = |s: f64| {
            if longest > 0.0 {
                ((DENSITY_GRID_CELLS as f64 * s / longest).round() as usize).clamp(1, DENSITY_GRID_CELLS)
            } else {
                1
            }
        };
        let (nx, nz) = (cells_along(size[0]), cells_along(size[1]));
        let mut grid = Self {
            nx,
            nz,
            min: [lo[0], lo[2]],
            cell: [size[0] / nx as f64, size[1] / nz as f64],
            counts: vec![0; nx * nz],
            centre_sums: vec![[0.0; 3]; nx * nz],
        };
        for mesh in scene
            .meshes
            .iter()
            .filter(|m| m.vertex_count > 0 && m.bounds.is_valid())
        {
            let c = to_f64(mesh.bounds.center());
            let i = grid.cell_of(c);
            grid.counts[i] += 1;
            for (sum, v) in grid.centre_sums[i].iter_mut().zip(c) {
                *sum += v;
            }
        }
        grid
    }

    fn cell_of(&self, p: [f64; 3]) -> usize {
        let index = |v: f64, min: f64, cell: f64, n: usize| {
            if cell > 0.0 {
                (((v - min) / cell).floor().max(0.0) as usize).min(n - 1)
            } else {
                0
            }
        };
        index(p[2], self.min[1], self.cell[1], self.nz) * self.nx + index(p[0], self.min[0], self.cell[0], self.nx)
    }

    /// Occupied cells, densest first (ties: lower index first).
    fn densest_first(&self) -> Vec<usize> {
        let mut cells: Vec<usize> = (0..self.counts.len()).filter(|&i| self.counts[i] > 0).collect();
        cells.sort_by_key(|&i| (std::cmp::Reverse(self.counts[i]), i));
        cells
    }

    /// Mean mesh centre of an occupied cell.
    fn mean_centre(&self, i: usize) -> [f64; 3] {
        let n = self.counts[i] as f64;
        self.centre_sums[i].map(|s| s / n)
    }
}

/// The standard benchmark path of paper §4.1 for a dataset's scene: a bird's-eye flythrough
/// over dense and sparse areas with exactly [`STANDARD_PAUSES`] pauses of
/// [`STANDARD_PAUSE_S`] and [`STANDARD_JUMPS`] jumps to new views, `duration_s` long.
///
/// Construction (deterministic):
/// - Density: the mesh bounds centres are counted on a grid of about 8 × 8 cells over the
///   horizontal extent of the bounds. Occupied cells are ranked by count.
/// - Five flight legs, separated by the four jumps. Leg `i` looks at a sparse cell, then the
///   `i`-th densest cell, then another sparse cell (sparse: the least occupied cells, in
///   turn); the camera pauses over the dense cell on legs 0–3 and flies through it on leg 4. Each look-at point is the
///   mean mesh centre of its cell, so it is inside the scene bounds. Consecutive waypoints
///   use different cells where the scene has enough occupied cells.
/// - The eye flies at one altitude above the highest roof: the bounds' top plus
///   `max(1 m, half the bounds' height, min(10 % of the horizontal extent, 250 m))`, and looks
///   down at 40° towards its target. The heading turns by 144° at every jump and swings by
///   ±15° along each leg, so the eye always moves and every jump is to a new view.
/// - Flight time (the duration less the pauses) is shared among the ten flight segments,
///   half evenly and half in proportion to their length.
///
/// Errors: [`PathError::InvalidDuration`] below [`MIN_STANDARD_DURATION_S`],
/// above [`MAX_PATH_DURATION_S`] or non-finite;
/// [`PathError::EmptyScene`] when no mesh has vertices.
pub fn standard_path(scene: &Scene, duration_s: f64) -> Result<CameraPath, PathError> {
    if !duration_s.is_finite() || !(MIN_STANDARD_DURATION_S..=MAX_PATH_DURATION_S).contains(&duration_s) {
        return Err(PathError::InvalidDuration { duration_s });
    }
    let mut bounds = citystream_dataset::Aabb::EMPTY;
    for mesh in scene
        .meshes
        .iter()
        .filter(|m| m.vertex_count > 0 && m.bounds.is_valid())
    {
        bounds.union(&mesh.bounds);
    }
    if !bounds.is_valid() {
        return Err(PathError::EmptyScene);
    }
    let (lo, hi) = (to_f64(bounds.min), to_f64(bounds.max));
    let grid = DensityGrid::new(scene, lo, hi);
    let dense = grid.densest_first();
    let sparse: Vec<usize> = dense.iter().rev().copied().collect();

    let horizontal_extent = (hi[0] - lo[0]).max(hi[2] - lo[2]);
    let height = hi[1] - lo[1];
    let clearance = 1.0f64
        .max(0.5 * height)
        .max((0.1 * horizontal_extent).min(MAX_CLEARANCE_M));
    let eye_y = hi[1] + clearance;
    let tan_pitch = STANDARD_PITCH_DEG.to_radians().tan();

    // Look-at point, clamped into the bounds against rounding, and the eye for a heading.
    let target = |cell: usize| -> [f32; 3] {
        let c = grid.mean_centre(cell);
        to_f32([0, 1, 2].map(|a| c[a].clamp(lo[a], hi[a])))
    };
    let eye = |look_at: [f32; 3], heading_deg: f64| -> [f32; 3] {
        let back = (eye_y - f64::from(look_at[1])) / tan_pitch;
        let (sin, cos) = heading_deg.to_radians().sin_cos();
        to_f32([
            f64::from(look_at[0]) - back * sin,
            eye_y,
            f64::from(look_at[2]) - back * cos,
        ])
    };

    // Waypoints: per leg start (sparse), middle (dense, the pause), end (sparse). Sparse
    // cells are taken in turn, skipping ones that would repeat a neighbouring waypoint.
    let mut sparse_cursor = 0;
    let mut next_sparse = |avoid: &[usize]| {
        let offset = (0..sparse.len())
            .find(|&o| !avoid.contains(&sparse[(sparse_cursor + o) % sparse.len()]))
            .unwrap_or(0);
        let cell = sparse[(sparse_cursor + offset) % sparse.len()];
        sparse_cursor += offset + 1;
        cell
    };
    let mut legs = Vec::with_capacity(STANDARD_LEGS);
    let mut previous_end = None;
    for leg in 0..STANDARD_LEGS {
        let heading = STANDARD_FIRST_HEADING_DEG + STANDARD_LEG_TURN_DEG * leg as f64;
        let middle = dense[leg % dense.len()];
        let start = next_sparse(&[middle, previous_end.unwrap_or(middle)]);
        let end = next_sparse(&[middle, start]);
        previous_end = Some(end);
        let cells = [start, middle, end];
        let mut waypoints = [([0.0f32; 3], [0.0f32; 3]); 3];
        for (i, (waypoint, cell)) in waypoints.iter_mut().zip(cells).enumerate() {
            let look_at = target(cell);
            // The eye swings across the leg, so it moves even where the targets coincide.
            let swing = STANDARD_LEG_SWING_DEG * (i as f64 - 1.0);
            *waypoint = (eye(look_at, heading + swing), look_at);
        }
        legs.push(waypoints);
    }

    let segment_lengths: Vec<f64> = legs
        .iter()
        .flat_map(|w| [distance(w[0].0, w[1].0), distance(w[1].0, w[2].0)])
        .collect();
    let total_length: f64 = segment_lengths.iter().sum();
    let flight_s = duration_s - STANDARD_PAUSES as f64 * STANDARD_PAUSE_S;
    let segment_s = |i: usize| {
        let even = flight_s / STANDARD_SEGMENTS as f64;
        if total_length > 0.0 {
            0.5 * even + 0.5 * flight_s * segment_lengths[i] / total_length
        } else {
            even
        }
    };

    let mut keyframes = Vec::with_capacity(3 * STANDARD_LEGS);
    let mut t = 0.0;
    for (leg, waypoints) in legs.iter().enumerate() {
        let [(p0, l0), (p1, l1), (p2, l2)] = *waypoints;
        keyframes.push(Keyframe {
            jump: leg > 0,
            ..Keyframe::new(t, p0, l0)
        });
        t += segment_s(2 * leg);
        let hold_s = if leg < STANDARD_PAUSES { STANDARD_PAUSE_S } else { 0.0 };
        keyframes.push(Keyframe {
            hold_s,
            ..Keyframe::new(t, p1, l1)
        });
        t += hold_s + segment_s(2 * leg + 1);
        keyframes.push(Keyframe::new(t, p2, l2));
    }
    Ok(CameraPath::new(keyframes)?.with_description(format!(
        "standard benchmark path (paper §4.1): {duration_s} s bird's-eye flythrough, \
         {STANDARD_PAUSES} pauses of {STANDARD_PAUSE_S} s, {STANDARD_JUMPS} jumps"
    )))
}
