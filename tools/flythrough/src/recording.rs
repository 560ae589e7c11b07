//! The window's camera path recorded as it is flown, or replayed.

use std::path::PathBuf;

use anyhow::Context;

use citystream_streaming::bench::path::{CameraPath, CameraPose, Keyframe};

/// Records the flown path: a keyframe per frame in which the camera moved,
/// `hold_s` on the keyframe where it then held still, `jump` where it teleported.
#[derive(Debug)]
pub(crate) struct Recorder {
    pub(crate) file: PathBuf,
    pub(crate) started_s: f64,
    pub(crate) keyframes: Vec<Keyframe>,
}

impl Recorder {
    pub(crate) fn new(file: PathBuf, started_s: f64) -> Self {
        Self {
            file,
            started_s,
            keyframes: Vec::new(),
        }
    }

    pub(crate) fn push(&mut self, time_s: f64, pose: &CameraPose, jumped: bool) {
        let t = time_s - self.started_s;
        if let Some(last) = self.keyframes.last_mut() {
            if t <= last.end_s() {
                return;
            }
            if !jumped && last.position == pose.position && last.look_at == pose.look_at {
                last.hold_s = t - last.t;
                return;
            }
        }
        let mut keyframe = Keyframe::new(t, pose.position, pose.look_at);
        keyframe.jump = jumped && !self.keyframes.is_empty();
        self.keyframes.push(keyframe);
    }

    /// Writes the path (atomically); `None` when nothing was recorded. On
    /// failure the recorder comes back, keyframes intact.
    pub(crate) fn save(self) -> std::result::Result<Option<SavedPath>, (Self, anyhow::Error)> {
        if self.keyframes.is_empty() {
            return Ok(None);
        }
        let written = CameraPath::new(self.keyframes.clone())
            .context("the recorded path")
            .and_then(|path| {
                let path = path.with_description("recorded in the flythrough window");
                path.save(&self.file)
                    .with_context(|| format!("writing the recorded path {}", self.file.display()))?;
                Ok(path.duration_s())
            });
        match written {
            Ok(duration_s) => Ok(Some(SavedPath {
                file: self.file,
                keyframes: self.keyframes.len(),
                duration_s,
            })),
            Err(e) => Err((self, e)),
        }
    }
}

/// A recording written to its file.
#[derive(Debug)]
pub(crate) struct SavedPath {
    pub(crate) file: PathBuf,
    pub(crate) keyframes: usize,
    pub(crate) duration_s: f64,
}

/// A path played at the camera clock's speed.
#[derive(Debug)]
pub(crate) struct Replay {
    pub(crate) path: CameraPath,
    /// Camera time of the path's start: the first frame that plays it.
    pub(crate) started_s: Option<f64>,
    pub(crate) previous_t: Option<f64>,
}

pub(crate) fn report_saved(saved: Option<SavedPath>) {
    match saved {
        Some(SavedPath {
            file,
            keyframes,
            duration_s,
        }) => eprintln!(
            "\nrecorded {keyframes} keyframes ({duration_s:.1} s) to {}; replay with --path {}",
            file.display(),
            file.display()
        ),
        None => eprintln!("\nnothing recorded"),
    }
}
