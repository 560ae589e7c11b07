//! A stalled frame the streaming did not cause (a slow first frame, a
//! window move) must not open the controller's throttle: in the closed
//! loop with the `desktop` bind-latency model, no frame in the 1,000 after
//! the stall takes more than 2α. (The controller's histories span 200
//! frames; later frames depend on the path, not on the stall. Without the
//! stall rule of `controller`, a 500 ms first frame is followed by frames
//! of 57–114 ms within 13 frames on these seeds.)

use citystream_streaming::bench::sim::{self, SimConfig, SimError};
use citystream_streaming::bind_latency::BindLatencyPreset;
use citystream_streaming::controller::PolicyKind;

/// Frames after the stall that are checked.
const AFTERMATH: u64 = 1_000;

/// The largest frame latency in the `AFTERMATH` frames after a stall of
/// `stall_ms` at `stall_frame`, α = `alpha_ms`.
fn worst_after_stall(seed: u64, stall_frame: u64, stall_ms: f64, alpha_ms: f64) -> Result<f64, SimError> {
    let frames = stall_frame + 1 + AFTERMATH;
    let mut config = SimConfig::new(PolicyKind::Adaptive, BindLatencyPreset::Desktop, frames, seed);
    config.policy_options.alpha_ms = alpha_ms;
    config.render.stall = Some((stall_frame, stall_ms));
    let mut worst = 0.0f64;
    let mut stalled = 0.0;
    sim::run_traced(&config, |frame| {
        if frame.frame == stall_frame {
            stalled = frame.telemetry.frame_ms;
        } else if frame.frame > stall_frame {
            worst = worst.max(frame.telemetry.frame_ms);
        }
    })?;
    assert!(stalled >= stall_ms, "the stall frame took {stalled} ms");
    Ok(worst)
}

fn check(stall_frame: u64, stall_ms: f64) -> Result<(), SimError> {
    for seed in 1..=4 {
        for alpha_ms in [12.0, 16.0] {
            let worst = worst_after_stall(seed, stall_frame, stall_ms, alpha_ms)?;
            assert!(
                worst <= 2.0 * alpha_ms,
                "seed {seed}, α = {alpha_ms} ms: a frame of {worst} ms after a {stall_ms} ms stall at frame {stall_frame}"
            );
        }
    }
    Ok(())
}

#[test]
fn a_slow_first_frame_causes_no_stutter_afterwards() -> Result<(), SimError> {
    check(0, 500.0)
}

#[test]
fn a_stall_mid_run_causes_no_stutter_afterwards() -> Result<(), SimError> {
    check(2_000, 500.0)?;
    check(2_000, 20_000.0)
}

#[test]
fn a_stall_beyond_a_minute_is_refused_as_a_setting() {
    let mut config = SimConfig::new(PolicyKind::Adaptive, BindLatencyPreset::Desktop, 10, 1);
    config.render.stall = Some((0, 61_000.0));
    assert!(matches!(
        sim::run(&config),
        Err(SimError::InvalidConfig { name: "stall", .. })
    ));
}
