//! The window's input and what it drives: actions from keys or a script and the fly camera;
//! and the upload rate its title shows (the camera path recorded or replayed is in
//! `recording.rs`).

use std::path::Path;

use anyhow::{bail, Context, Result};
use glam::Vec3;
use serde::Deserialize;
use winit::keyboard::KeyCode;

use citystream_dataset::Dataset;
use citystream_streaming::bench::path::CameraPose;

use super::args::FIXED_STEP_MS;

/// What a key (or a scripted event) does.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub(crate) enum Action {
    Forward,
    Back,
    Left,
    Right,
    Down,
    Up,
    /// Held: fly four times as fast.
    Fast,
    /// Jump to the dataset's overview.
    Overview,
    /// Play the camera path (`--path`, default the standard path) from its start.
    Replay,
    /// Stop or resume streaming (feedback and loading); the view keeps what is resident.
    PauseStreaming,
    /// Blend the City Colormap by mip level (Eq. 8) or show sampled colour only.
    ToggleColormap,
    /// Start or stop recording the camera path.
    Record,
    Quit,
}

impl Action {
    pub(crate) fn of_key(code: KeyCode) -> Option<Action> {
        Some(match code {
            KeyCode::KeyW | KeyCode::ArrowUp => Action::Forward,
            KeyCode::KeyS | KeyCode::ArrowDown => Action::Back,
            KeyCode::KeyA | KeyCode::ArrowLeft => Action::Left,
            KeyCode::KeyD | KeyCode::ArrowRight => Action::Right,
            KeyCode::KeyQ | KeyCode::PageDown => Action::Down,
            KeyCode::KeyE | KeyCode::PageUp => Action::Up,
            KeyCode::ShiftLeft | KeyCode::ShiftRight => Action::Fast,
            KeyCode::KeyO | KeyCode::Home => Action::Overview,
            KeyCode::KeyP => Action::Replay,
            KeyCode::Space => Action::PauseStreaming,
            KeyCode::KeyC => Action::ToggleColormap,
            KeyCode::KeyR => Action::Record,
            KeyCode::Escape => Action::Quit,
            _ => return None,
        })
    }

    /// Held actions move the camera while down; the others act once on press.
    pub(crate) fn is_held(self) -> bool {
        matches!(
            self,
            Action::Forward | Action::Back | Action::Left | Action::Right | Action::Down | Action::Up | Action::Fast
        )
    }
}

/// The controls, printed at start.
pub(crate) const HELP: &str =
    "controls: drag with the left mouse button to look, W/A/S/D fly, Q/E down/up, Shift faster, \
                    scroll wheel changes speed, O overview, P play the path, Space pause streaming, \
                    C colormap blending, R start/stop recording, Esc quit";

/// One scripted input event (`--input-script`), applied before frame `frame` renders.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ScriptEvent {
    pub(crate) frame: u32,
    #[serde(default)]
    pub(crate) press: Option<Action>,
    #[serde(default)]
    pub(crate) release: Option<Action>,
    /// A mouse drag, in pixels (x right, y down).
    #[serde(default)]
    pub(crate) look: Option<[f64; 2]>,
    /// Scroll-wheel notches (positive: faster).
    #[serde(default)]
    pub(crate) scroll: Option<f64>,
    /// Ask the window system for this inner size.
    #[serde(default)]
    pub(crate) resize: Option<[u32; 2]>,
    /// Minimise (and unmap) the window for this many wall-clock seconds.
    #[serde(default)]
    pub(crate) minimise_s: Option<f64>,
    /// Write the presented image of this frame to OUT/frames/.
    #[serde(default)]
    pub(crate) screenshot: bool,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct Script {
    pub(crate) events: Vec<ScriptEvent>,
}

pub(crate) fn load_script(path: &Path) -> Result<Vec<ScriptEvent>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading the input script {}", path.display()))?;
    let script: Script =
        serde_json::from_str(&text).with_context(|| format!("parsing the input script {}", path.display()))?;
    let mut events = script.events;
    for (i, e) in events.iter().enumerate() {
        let actions = [
            e.press.is_some(),
            e.release.is_some(),
            e.look.is_some(),
            e.scroll.is_some(),
            e.resize.is_some(),
            e.minimise_s.is_some(),
            e.screenshot,
        ];
        if actions.iter().filter(|a| **a).count() != 1 {
            bail!(
                "{}: event {i} (frame {}) must do exactly one of press, release, look, scroll, resize, \
                 minimise_s, screenshot",
                path.display(),
                e.frame
            );
        }
        let finite = e.look.is_none_or(|l| l.iter().all(|v| v.is_finite()))
            && e.scroll.is_none_or(f64::is_finite)
            && e.minimise_s
                .is_none_or(|s| s.is_finite() && (0.0..=3600.0).contains(&s));
        if !finite {
            bail!(
                "{}: event {i} (frame {}): numbers must be finite (minimise_s within 0..=3600)",
                path.display(),
                e.frame
            );
        }
        if let Some([w, h]) = e.resize {
            if !(16..=8192).contains(&w) || !(16..=8192).contains(&h) {
                bail!(
                    "{}: event {i} (frame {}): resize {w}x{h} is outside 16..=8192 per side",
                    path.display(),
                    e.frame
                );
            }
        }
    }
    // Stable: events of one frame keep their order.
    events.sort_by_key(|e| e.frame);
    Ok(events)
}

/// The free-flying camera: a position and a view direction.
#[derive(Clone, Copy, Debug)]
pub(crate) struct FlyCamera {
    pub(crate) position: Vec3,
    pub(crate) yaw: f32,
    pub(crate) pitch: f32,
    /// Distance of the look-at point written to recorded paths.
    pub(crate) look_distance: f32,
}

impl FlyCamera {
    pub(crate) fn from_pose(pose: &CameraPose) -> Self {
        let position = Vec3::from(pose.position);
        let offset = Vec3::from(pose.look_at) - position;
        let distance = offset.length().max(1e-3);
        let dir = offset / distance;
        Self {
            position,
            yaw: dir.z.atan2(dir.x),
            pitch: dir.y.clamp(-1.0, 1.0).asin(),
            look_distance: distance,
        }
    }

    pub(crate) fn direction(&self) -> Vec3 {
        Vec3::new(
            self.yaw.cos() * self.pitch.cos(),
            self.pitch.sin(),
            self.yaw.sin() * self.pitch.cos(),
        )
    }

    pub(crate) fn pose(&self) -> CameraPose {
        CameraPose {
            position: self.position.to_array(),
            look_at: (self.position + self.direction() * self.look_distance).to_array(),
            in_pause: false,
            jumped: false,
        }
    }
}

/// The dataset's overview: above the middle of its bounds, looking down on it.
pub(crate) fn overview_pose(dataset: &Dataset) -> CameraPose {
    let bounds = dataset.scene.bounds;
    let (min, max) = (Vec3::from(bounds.min), Vec3::from(bounds.max));
    let centre = (min + max) * 0.5;
    let size = max - min;
    let extent = size.x.max(size.z).max(1.0);
    let eye = Vec3::new(centre.x, max.y + extent * 0.45, centre.z - extent * 0.55);
    CameraPose {
        position: eye.to_array(),
        look_at: centre.to_array(),
        in_pause: false,
        jumped: false,
    }
}

/// Bytes uploaded over the last second, for the MB/s the title shows.
#[derive(Debug, Default)]
pub(crate) struct Throughput {
    pub(crate) samples: std::collections::VecDeque<(f64, u64)>,
}

impl Throughput {
    pub(crate) fn push(&mut self, time_s: f64, bytes: u64) -> f64 {
        self.samples.push_back((time_s, bytes));
        while self.samples.front().is_some_and(|(t, _)| time_s - t > 1.0) {
            self.samples.pop_front();
        }
        let span = self.samples.front().map_or(0.0, |(t, _)| time_s - t).max(1e-3);
        self.samples.iter().map(|(_, b)| *b).sum::<u64>() as f64 / 1e6 / span.max(FIXED_STEP_MS / 1000.0)
    }
}
