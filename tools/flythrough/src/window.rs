//! `flythrough --window`: the streamed city in a window (docs/WINDOW.md).
//!
//! The frame is the headless one (the same streamer calls, the same passes
//! into the same off-screen target, the same clocks), followed by a blit of
//! that target into the acquired swapchain image; so a windowed frame under
//! `--clock fixed` is the headless frame of the same number, pixel for pixel.
//! Input (real or scripted) goes through one `Action` handler.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use glam::Vec3;
use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::{ElementState, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::keyboard::PhysicalKey;
use winit::window::{Window, WindowId};

use citystream_engine::commands::CommandContext;
use citystream_engine::present::{self, Presenter, Surface};
use citystream_engine::Device;
use citystream_streaming::bench::path::{CameraPath, CameraPose};
use citystream_streaming::bench::stats::PathClock;

use super::args::{frame_interval, writes_frame, Args, Clock, ControllerLatency, FIXED_STEP_MS};
use super::camera::{camera_path, focal_px, lowest_eye_height, pose_camera};
use super::city_gpu::city_targets;
use super::controls::{load_script, overview_pose, Action, FlyCamera, ScriptEvent, Throughput, HELP};
use super::dataset::{dataset_dir, open_city};
use super::device::flythrough_device;
use super::flight::{Flight, FrameSettings, GroundSizing};
use super::output::{write_csv_row, write_frame_png, CsvRow, CSV_HEADER};
use super::recording::{report_saved, Recorder, Replay};

/// Everything that needs the window: created on the first `resumed`.
struct Viewer {
    window: Arc<Window>,
    device: Arc<Device>,
    /// The streamed city and its frame, shared with the headless run.
    flight: Flight,
    presenter: Presenter,
    size: (u32, u32),
    needs_resize: bool,
    minimised_until: Option<Instant>,
    /// Hidden (minimised or covered, where the window system says so): no frames.
    occluded: bool,
    /// Frames were skipped or the swapchain recreated since the last frame.
    interrupted: bool,
    /// A scripted screenshot waits for the next rendered frame.
    screenshot_pending: bool,
    // Camera and input.
    camera: FlyCamera,
    replay: Option<Replay>,
    path: Option<CameraPath>,
    held: Vec<Action>,
    /// The left button is down: cursor motion turns the view.
    dragging: bool,
    /// The cursor's last position in the window.
    cursor: Option<(f64, f64)>,
    speed: f32,
    jumped: bool,
    // Toggles.
    streaming_paused: bool,
    colormap_blend: bool,
    recorder: Option<Recorder>,
    // Clocks and stats.
    time_s: f64,
    path_clock: PathClock,
    frame: u32,
    frame_ms: f64,
    last_frame_at: Option<Instant>,
    throughput: Throughput,
    pending: usize,
    title_at: Instant,
    /// The live stats last shown in the title bar.
    title: String,
    csv: std::io::BufWriter<std::fs::File>,
    screenshots: Vec<String>,
}

/// The winit application: the viewer once resumed, and the first error.
struct App<'a> {
    args: &'a Args,
    dir: PathBuf,
    device: Option<Arc<Device>>,
    script: Vec<ScriptEvent>,
    viewer: Option<Viewer>,
    error: Option<anyhow::Error>,
}

/// Runs the window until Esc, a close, or `--frames`/`--duration-s`.
pub(super) fn run(args: &Args) -> Result<()> {
    if args.clock == Clock::Modelled {
        bail!("--clock modelled is for headless benchmarks; the window uses real (default) or fixed");
    }
    let script = match &args.input_script {
        Some(path) => load_script(path)?,
        None => Vec::new(),
    };
    let event_loop = EventLoop::new().map_err(|e| {
        anyhow!(
            "cannot open a window: {e}. Is DISPLAY set to a running X server (or XWayland)? \
             Without --window the flythrough renders headless."
        )
    })?;
    let dir = dataset_dir(args)?;
    let extensions = present::instance_extensions(&event_loop).context("the window system's Vulkan extensions")?;
    let device = flythrough_device(args, "citystream flythrough window", Some(extensions))?;
    eprintln!("{HELP}");
    let mut app = App {
        args,
        dir,
        device: Some(Arc::clone(&device)),
        script,
        viewer: None,
        error: None,
    };
    event_loop.run_app(&mut app).context("the window's event loop")?;
    let viewer = app.viewer.take();
    let outcome = match viewer {
        Some(viewer) => viewer.finish(args),
        None => Ok(()),
    };
    if let Some(error) = app.error.take() {
        if let Err(also) = outcome {
            eprintln!("error while closing: {also:#}");
        }
        return Err(error);
    }
    outcome?;
    // Warnings too: swapchain misuse often shows as one.
    let messages = device.validation_log().messages();
    if device.instance().is_some_and(|i| i.validation_enabled()) {
        eprintln!("validation: {} message(s)", messages.len());
    }
    if let Some(first) = messages.first() {
        bail!(
            "{} Vulkan validation message(s) while the window ran; the first: {}: {}",
            messages.len(),
            first.id,
            first.text
        );
    }
    Ok(())
}

impl App<'_> {
    fn fail(&mut self, event_loop: &ActiveEventLoop, error: anyhow::Error) {
        if self.error.is_none() {
            self.error = Some(error);
        }
        event_loop.exit();
    }
}

impl ApplicationHandler for App<'_> {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.viewer.is_some() {
            return;
        }
        let Some(device) = self.device.take() else {
            return;
        };
        let screenshots = frame_interval(self.args) > 0 || self.script.iter().any(|e| e.screenshot);
        match Viewer::new(self.args, &self.dir, device, event_loop, screenshots) {
            Ok(viewer) => {
                self.viewer = Some(viewer);
                event_loop.set_control_flow(ControlFlow::Poll);
            }
            Err(e) => self.fail(event_loop, e),
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _: WindowId, event: WindowEvent) {
        let Some(viewer) = self.viewer.as_mut() else {
            return;
        };
        let result = match event {
            WindowEvent::CloseRequested => {
                event_loop.exit();
                Ok(())
            }
            WindowEvent::Resized(size) => {
                viewer.on_resize(size.width, size.height);
                Ok(())
            }
            WindowEvent::KeyboardInput { event, .. } => {
                if event.repeat {
                    return;
                }
                let PhysicalKey::Code(code) = event.physical_key else {
                    return;
                };
                match Action::of_key(code) {
                    Some(action) => viewer.act(action, event.state == ElementState::Pressed, self.args),
                    None => Ok(()),
                }
            }
            WindowEvent::MouseInput {
                state,
                button: MouseButton::Left,
                ..
            } => {
                viewer.dragging = state == ElementState::Pressed;
                Ok(())
            }
            WindowEvent::CursorMoved { position, .. } => {
                if let (true, Some((x, y))) = (viewer.dragging, viewer.cursor) {
                    viewer.look(position.x - x, position.y - y);
                }
                viewer.cursor = Some((position.x, position.y));
                Ok(())
            }
            WindowEvent::CursorLeft { .. } => {
                viewer.cursor = None;
                Ok(())
            }
            WindowEvent::MouseWheel { delta, .. } => {
                let notches = match delta {
                    MouseScrollDelta::LineDelta(_, y) => f64::from(y),
                    MouseScrollDelta::PixelDelta(p) => p.y / 40.0,
                };
                viewer.scroll(notches);
                Ok(())
            }
            WindowEvent::Occluded(occluded) => {
                // Minimised or fully covered: nothing to show, and presenting
                // to a hidden window may wait on a refresh that never comes.
                viewer.occluded = occluded;
                if !occluded {
                    let size = viewer.window.inner_size();
                    viewer.on_resize(size.width, size.height);
                    viewer.window.request_redraw();
                }
                Ok(())
            }
            WindowEvent::RedrawRequested => viewer.redraw(self.args, &mut self.script, event_loop),
            _ => Ok(()),
        };
        if viewer.quit_requested() {
            event_loop.exit();
        }
        if let Err(e) = result {
            self.fail(event_loop, e);
        }
    }

    fn about_to_wait(&mut self, event_loop: &ActiveEventLoop) {
        let Some(viewer) = self.viewer.as_mut() else {
            return;
        };
        match viewer.minimised_until {
            Some(until) if Instant::now() < until => {
                event_loop.set_control_flow(ControlFlow::WaitUntil(until));
            }
            Some(_) => {
                viewer.minimised_until = None;
                viewer.window.set_visible(true);
                viewer.window.set_minimized(false);
                let size = viewer.window.inner_size();
                viewer.on_resize(size.width, size.height);
                event_loop.set_control_flow(ControlFlow::Poll);
                viewer.window.request_redraw();
            }
            None if viewer.occluded => event_loop.set_control_flow(ControlFlow::Wait),
            None if viewer.size.0 == 0 => {
                // No area: look again shortly (a restore may bring no event
                // when the size did not change).
                let size = viewer.window.inner_size();
                viewer.on_resize(size.width, size.height);
                event_loop.set_control_flow(ControlFlow::WaitUntil(Instant::now() + Duration::from_millis(100)));
                viewer.window.request_redraw();
            }
            None => {
                event_loop.set_control_flow(ControlFlow::Poll);
                viewer.window.request_redraw();
            }
        }
    }
}

impl Viewer {
    fn new(
        args: &Args,
        dir: &Path,
        device: Arc<Device>,
        event_loop: &ActiveEventLoop,
        screenshots: bool,
    ) -> Result<Self> {
        let (dataset, city, _) = open_city(args, dir)?;
        let opened = (dataset, city);
        let attributes = Window::default_attributes()
            .with_title(format!("citystream · {}", dir.display()))
            .with_inner_size(PhysicalSize::new(args.width, args.height));
        let window = Arc::new(event_loop.create_window(attributes).context("creating the window")?);
        let inner = window.inner_size();
        let size = (inner.width.max(16), inner.height.max(16));
        let surface = Surface::new(&device, Arc::clone(&window) as Arc<dyn present::PresentWindow>)
            .context("creating the window's Vulkan surface")?;
        let presenter = Presenter::new(
            &device,
            surface,
            size,
            args.present_mode,
            args.frames_in_flight,
            screenshots,
        )
        .context("creating the swapchain")?;
        if presenter.mode() != args.present_mode {
            eprintln!(
                "note: the display has no {} presentation; using {}",
                args.present_mode.name(),
                presenter.mode().name()
            );
        }
        let size = presenter.extent();
        let scene = &opened.0.scene;
        let path = match &args.path {
            Some(name) => Some(camera_path(name, scene)?),
            None => None,
        };
        let replay = path.as_ref().map(|path| {
            path.restart();
            Replay {
                path: path.clone(),
                started_s: Some(0.0),
                previous_t: None,
            }
        });
        let start = match &path {
            Some(path) => path.sample_between(None, 0.0),
            None => overview_pose(&opened.0),
        };
        let ground_y = scene.bounds.min[1];
        let mut commands = CommandContext::new(&device, "window setup")?;
        // The ground's levels: down to what the path's lowest eye needs, or every level
        // the imagery has when the camera flies freely.
        let flight = Flight::new(args, &device, &mut commands, dir, opened, size, |scene_box| {
            GroundSizing {
                focal_px: focal_px(size.1, &pose_camera(&start, scene_box)),
                lowest_eye_m: path.as_ref().map(|path| {
                    let duration_s = args.duration_s.unwrap_or(path.duration_s()).max(0.0);
                    lowest_eye_height(path, duration_s, ground_y)
                }),
            }
        })?;
        let extent = flight.extent;
        std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
        let csv_path = args.out.join("frames.csv");
        let mut csv = std::io::BufWriter::new(
            std::fs::File::create(&csv_path).with_context(|| format!("creating {}", csv_path.display()))?,
        );
        writeln!(csv, "{CSV_HEADER}")?;
        eprintln!(
            "scene: {} ({} meshes, {} textures), {}x{} window, {} presentation, {} frame(s) in flight",
            dir.display(),
            flight.dataset.scene.meshes.len(),
            flight.dataset.textures.len(),
            size.0,
            size.1,
            presenter.mode().name(),
            args.frames_in_flight
        );
        let recorder = args.record.clone().map(|file| {
            eprintln!("recording the camera path to {}", file.display());
            Recorder::new(file, 0.0)
        });
        Ok(Self {
            window,
            device,
            flight,
            presenter,
            size,
            needs_resize: false,
            minimised_until: None,
            occluded: false,
            interrupted: false,
            screenshot_pending: false,
            camera: FlyCamera::from_pose(&start),
            replay,
            path,
            held: Vec::new(),
            dragging: false,
            cursor: None,
            speed: extent / 20.0,
            jumped: false,
            streaming_paused: false,
            colormap_blend: true,
            recorder,
            time_s: 0.0,
            path_clock: PathClock::new(),
            frame: 0,
            frame_ms: FIXED_STEP_MS,
            last_frame_at: None,
            throughput: Throughput::default(),
            pending: 0,
            title_at: Instant::now(),
            title: String::new(),
            csv,
            screenshots: Vec::new(),
        })
    }

    fn quit_requested(&self) -> bool {
        self.held.contains(&Action::Quit)
    }

    fn on_resize(&mut self, width: u32, height: u32) {
        if width == 0 || height == 0 {
            // Minimised: no swapchain can have this size; render nothing until restored.
            self.size = (0, 0);
            return;
        }
        if (width, height) != self.size {
            self.size = (width, height);
            self.needs_resize = true;
        }
    }

    /// A press or release of `action` (a key, or a scripted event).
    fn act(&mut self, action: Action, pressed: bool, args: &Args) -> Result<()> {
        if action.is_held() || action == Action::Quit {
            self.held.retain(|a| *a != action);
            if pressed {
                self.held.push(action);
                if action != Action::Fast && action != Action::Quit {
                    self.take_over();
                }
            }
            return Ok(());
        }
        if !pressed {
            return Ok(());
        }
        match action {
            Action::Overview => {
                self.take_over();
                let look_distance = self.camera.look_distance;
                self.camera = FlyCamera::from_pose(&overview_pose(&self.flight.dataset));
                self.camera.look_distance = look_distance;
                self.jumped = true;
            }
            Action::Replay => {
                let path = match &self.path {
                    Some(path) => path.clone(),
                    None => camera_path("standard", &self.flight.dataset.scene)?,
                };
                path.restart();
                self.replay = Some(Replay {
                    path,
                    started_s: None,
                    previous_t: None,
                });
                self.jumped = true;
                eprintln!("\nplaying the camera path from its start");
            }
            Action::PauseStreaming => {
                self.streaming_paused = !self.streaming_paused;
                eprintln!(
                    "\nstreaming {}",
                    if self.streaming_paused { "paused" } else { "resumed" }
                );
            }
            Action::ToggleColormap => {
                self.colormap_blend = !self.colormap_blend;
                eprintln!("\ncolormap blending {}", if self.colormap_blend { "on" } else { "off" });
            }
            Action::Record => match self.recorder.take() {
                Some(recorder) => match recorder.save() {
                    Ok(saved) => report_saved(saved),
                    Err((recorder, e)) => {
                        // Keep recording: R again retries, closing the window fails the run.
                        eprintln!("\nwarning: {e:#}; still recording");
                        self.recorder = Some(recorder);
                    }
                },
                None => {
                    let file = args
                        .record
                        .clone()
                        .unwrap_or_else(|| args.out.join("recorded_path.json"));
                    eprintln!("\nrecording the camera path to {}", file.display());
                    self.recorder = Some(Recorder::new(file, self.time_s));
                }
            },
            _ => {}
        }
        Ok(())
    }

    /// The user flies: a path that was playing stops where it is.
    fn take_over(&mut self) {
        if self.replay.take().is_some() {
            eprintln!("\npath replay stopped: free flight");
        }
    }

    fn look(&mut self, dx: f64, dy: f64) {
        self.take_over();
        // A scripted drag of any size stays a finite angle.
        let (dx, dy) = (dx.clamp(-1e4, 1e4), dy.clamp(-1e4, 1e4));
        const RADIANS_PER_PIXEL: f32 = 0.004;
        self.camera.yaw += dx as f32 * RADIANS_PER_PIXEL;
        self.camera.pitch = (self.camera.pitch - dy as f32 * RADIANS_PER_PIXEL).clamp(-1.5, 1.5);
    }

    fn scroll(&mut self, notches: f64) {
        let factor = 1.25f32.powf(notches.clamp(-20.0, 20.0) as f32);
        let extent = self.flight.extent;
        self.speed = (self.speed * factor).clamp(extent * 1e-4, extent * 2.0);
    }

    /// Moves the camera by the held keys over `dt_s` seconds, or along the
    /// path being replayed; returns this frame's pose.
    fn advance_camera(&mut self, dt_s: f64) -> CameraPose {
        if let Some(replay) = self.replay.as_mut() {
            let t = self.time_s - *replay.started_s.get_or_insert(self.time_s);
            let pose = replay.path.sample_between(replay.previous_t, t);
            replay.previous_t = Some(t);
            let look_distance = self.camera.look_distance;
            self.camera = FlyCamera::from_pose(&pose);
            self.camera.look_distance = look_distance;
            // The path's own look-at, exactly, so a recording reproduces it.
            return CameraPose {
                jumped: pose.jumped || std::mem::take(&mut self.jumped),
                ..pose
            };
        }
        let forward = self.camera.direction();
        let right = forward.cross(Vec3::Y).normalize_or_zero();
        let mut velocity = Vec3::ZERO;
        for action in &self.held {
            velocity += match action {
                Action::Forward => forward,
                Action::Back => -forward,
                Action::Right => right,
                Action::Left => -right,
                Action::Up => Vec3::Y,
                Action::Down => -Vec3::Y,
                _ => Vec3::ZERO,
            };
        }
        let fast = if self.held.contains(&Action::Fast) { 4.0 } else { 1.0 };
        self.camera.position += velocity.normalize_or_zero() * self.speed * fast * dt_s as f32;
        let mut pose = self.camera.pose();
        pose.jumped = std::mem::take(&mut self.jumped);
        pose
    }

    /// Applies the script's events due before this frame, up to a minimise
    /// (the rest wait until the window shows again).
    fn apply_script(&mut self, args: &Args, script: &mut Vec<ScriptEvent>) -> Result<()> {
        while script.first().is_some_and(|e| e.frame <= self.frame) {
            let event = script.remove(0);
            if let Some(action) = event.press {
                self.act(action, true, args)?;
            } else if let Some(action) = event.release {
                self.act(action, false, args)?;
            } else if let Some([dx, dy]) = event.look {
                self.look(dx, dy);
            } else if let Some(notches) = event.scroll {
                self.scroll(notches);
            } else if let Some([w, h]) = event.resize {
                if let Some(size) = self.window.request_inner_size(PhysicalSize::new(w, h)) {
                    self.on_resize(size.width, size.height);
                }
            } else if let Some(seconds) = event.minimise_s {
                // What a window manager does on iconify: the window is unmapped and has no area.
                self.window.set_minimized(true);
                self.window.set_visible(false);
                self.on_resize(0, 0);
                self.minimised_until = Some(Instant::now() + Duration::from_secs_f64(seconds));
                return Ok(());
            } else if event.screenshot {
                self.screenshot_pending = true;
            }
        }
        Ok(())
    }

    fn redraw(&mut self, args: &Args, script: &mut Vec<ScriptEvent>, event_loop: &ActiveEventLoop) -> Result<()> {
        if self.minimised_until.is_some() || self.occluded {
            self.interrupted = true;
            return Ok(());
        }
        self.apply_script(args, script)?;
        if self.minimised_until.is_some() || self.size.0 == 0 {
            self.interrupted = true;
            return Ok(());
        }
        if self.needs_resize {
            self.resize()?;
            // The resize waited for the GPU: not this frame's latency.
            self.interrupted = true;
            if self.size.0 == 0 {
                return Ok(());
            }
        }
        if self.quit_requested() {
            return Ok(());
        }
        if std::mem::take(&mut self.interrupted) {
            // Time hidden or waiting is neither frame latency for the
            // controller nor camera time (a path resumes where it was).
            self.flight.restart_latency_clock();
            self.last_frame_at = None;
        }
        // This frame's camera time: wall-clock time since the last frame (at
        // most a second: a stall does not skip the path ahead), or the fixed step.
        let now = Instant::now();
        let dt_s = match args.clock {
            _ if self.frame == 0 => 0.0,
            Clock::Real => self
                .last_frame_at
                .map_or(0.0, |at| now.duration_since(at).as_secs_f64().min(1.0)),
            _ => FIXED_STEP_MS / 1000.0,
        };
        let done = args.frames.is_some_and(|n| self.frame >= n)
            || args.duration_s.is_some_and(|d| self.time_s + dt_s > d + 1e-9);
        if done {
            event_loop.exit();
            return Ok(());
        }
        self.last_frame_at = Some(now);
        // Whole ticks, so a long fixed-clock flight does not drift.
        self.path_clock.advance_ms(dt_s * 1000.0);
        self.time_s = self.path_clock.seconds();
        let screenshot = std::mem::take(&mut self.screenshot_pending) || writes_frame(args, self.frame);
        self.render(args, screenshot, dt_s, now)
    }

    /// Recreates the swapchain and the render targets at the window's size.
    fn resize(&mut self) -> Result<()> {
        self.needs_resize = false;
        let shown = self
            .presenter
            .resize(self.size.0, self.size.1)
            .context("recreating the swapchain")?;
        if !shown {
            // The window system says it has no area after all: wait for the next resize.
            self.size = (0, 0);
            return Ok(());
        }
        let (width, height) = self.presenter.extent();
        let target = &self.flight.targets.target;
        if (width, height) != (target.width(), target.height()) {
            // The presenter waited for the device: the old targets are unused.
            self.flight.targets = city_targets(&self.device, width, height)?;
        }
        self.size = (width, height);
        Ok(())
    }

    fn render(&mut self, args: &Args, screenshot: bool, dt_s: f64, now: Instant) -> Result<()> {
        let pose = self.advance_camera(dt_s);
        if let Some(recorder) = self.recorder.as_mut() {
            recorder.push(self.time_s, &pose, pose.jumped);
        }
        let camera = pose_camera(&pose, self.flight.scene_box);
        let mut recorded = self.flight.record(
            self.frame,
            &camera,
            &FrameSettings {
                time_s: self.time_s,
                // Paused: no feedback, so the loader is handed nothing new (the atlas
                // tree pages from the view and goes on).
                feedback: !self.streaming_paused,
                every_seen_mesh: false,
                colormap_blend: self.colormap_blend,
                share_visible_culling: None,
                // Flown by hand the path is not known: the motion is extrapolated.
                path: None,
            },
        )?;
        if let Some(feedback) = recorded.feedback {
            self.pending = feedback.pending;
        }
        // Time spent waiting for the display (an image to draw into, the present) is not the
        // frame's work: under vsync it is the display period's, and a controller fed it sees
        // no room (docs/CONTROLLER.md, "Under vsync").
        let acquire_started = Instant::now();
        let acquired = self.presenter.acquire(recorded.slot)?;
        let mut display_wait = acquire_started.elapsed();
        if let Some(image) = &acquired {
            let (rec, target) = self.flight.recording(&recorded)?;
            self.presenter.record_blit(rec, image, target, screenshot)?;
        }
        let (waits, signals) = match &acquired {
            Some(image) => (vec![image.wait], vec![image.signal]),
            None => (Vec::new(), Vec::new()),
        };
        self.flight.submit(&mut recorded, self.frame_ms, &waits, &signals)?;
        let presented = acquired.is_some();
        match acquired {
            Some(image) => {
                let present_started = Instant::now();
                if !self.presenter.present(image)? {
                    self.needs_resize = true;
                }
                display_wait += present_started.elapsed();
            }
            None => self.needs_resize = true,
        }
        if screenshot && !presented {
            eprintln!(
                "\nwarning: frame {} was not presented (the swapchain was out of date): no screenshot of it",
                self.frame
            );
        }
        if screenshot && presented {
            // The copy was recorded after the blit; a swapchain now out of
            // date still held this frame's image when it ran.
            self.flight.gpu.streamer.wait_for_frame(recorded.index)?;
            write_frame_png(
                args,
                self.frame,
                &self.presenter.read_screenshot()?,
                &mut self.screenshots,
            )?;
        }

        let interval_ms = self.flight.latency(&recorded);
        self.frame_ms = match (args.clock, args.controller_latency) {
            (Clock::Real, ControllerLatency::Work) => (interval_ms - display_wait.as_secs_f64() * 1000.0).max(0.0),
            _ => interval_ms,
        };
        let applied = &recorded.applied;
        let streamer = &self.flight.gpu.streamer;
        let resident = streamer.bound_bytes();
        let telemetry = streamer.policy().telemetry();
        write_csv_row(
            &mut self.csv,
            &CsvRow {
                frame: self.frame,
                time_s: self.time_s,
                frame_ms: self.frame_ms,
                telemetry: &telemetry,
                applied,
                resident,
                deficit: recorded.feedback.and_then(|f| f.deficit),
                error: None,
                ground_error: None,
                camera: &camera,
                cycle_started: recorded.cycle_started,
                reads_in_flight_bytes: recorded.reads_in_flight_bytes,
                prefetch_pass: recorded.prefetched,
                causes: None,
            },
        )?;
        let mb_per_s = self.throughput.push(self.time_s, applied.bytes_uploaded);
        if now.duration_since(self.title_at) >= Duration::from_millis(250) || self.frame == 0 {
            self.title_at = now;
            let budget = args
                .memory_budget_mb()
                .0
                .map_or_else(|| "unlimited".to_owned(), |mb| format!("{mb} MB"));
            let mut title = format!(
                "citystream · {:.1} ms · s {:.2} MB · b {:.2} · {:.1} MB/s · {:.0} MB / {budget} · {} pending",
                self.frame_ms,
                telemetry.load_size_mb,
                telemetry.mip_bias,
                mb_per_s,
                resident as f64 / 1e6,
                self.pending
            );
            if self.streaming_paused {
                title.push_str(" · streaming paused");
            }
            if !self.colormap_blend {
                title.push_str(" · no colormap");
            }
            if self.recorder.is_some() {
                title.push_str(" · REC");
            }
            self.window.set_title(&title);
            self.title = title;
        }
        self.frame += 1;
        Ok(())
    }

    /// After the event loop: save a recording in progress, wait for the GPU,
    /// report, and fail on textures that could not be loaded.
    fn finish(mut self, args: &Args) -> Result<()> {
        self.device.wait_idle()?;
        self.csv.flush()?;
        if let Some(recorder) = self.recorder.take() {
            report_saved(recorder.save().map_err(|(_, e)| e)?);
        }
        eprintln!(
            "{} frames ({:.1} s of camera time), {} screenshot(s), frames.csv in {}\nlast status: {}",
            self.frame,
            self.time_s,
            self.screenshots.len(),
            args.out.display(),
            self.title
        );
        self.flight.finish_loading()?;
        let streamer = &self.flight.gpu.streamer;
        let failed = streamer.failed_textures();
        if failed > 0 {
            let first = streamer
                .load_failures()
                .first()
                .map(|f| format!("; the first: {}", f.reason))
                .unwrap_or_default();
            let message = format!("{failed} texture(s) failed to load{first}");
            if !args.allow_load_failures {
                bail!("{message} (--allow-load-failures exits 0)");
            }
            eprintln!("warning: {message}");
        }
        Ok(())
    }
}

impl Drop for Viewer {
    fn drop(&mut self) {
        // The streamer, targets, command buffers and swapchain may still be
        // in use by frames in flight; they go once the GPU is done (also on
        // error paths, which skip `finish`).
        let _ = self.device.wait_idle();
    }
}
