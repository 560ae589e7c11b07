//! The streaming controller of a run: the policy the options ask for, and the frame
//! latency it is given (measured, or modelled with the bind latency).

use std::time::Duration;

use anyhow::{bail, Context, Result};

use citystream_streaming::bind_latency::{BindLatencyModel, BindLatencyPreset};
use citystream_streaming::controller::PolicyOptions;
use citystream_streaming::rng::SplitMix64;

use super::args::{Args, Clock, FIXED_COPY_BYTES_PER_S};

/// The streaming policy the options ask for.
pub(crate) fn build_policy(args: &Args) -> Result<Box<dyn citystream_streaming::controller::LoadPolicy>> {
    let Some(policy) = args.controller.policy(args.policy) else {
        bail!(
            "--controller {} applies to --policy adaptive; --policy {} has no controller",
            args.controller.name(),
            args.policy
        );
    };
    policy
        .build(&PolicyOptions {
            alpha_ms: args.alpha,
            beta: args.beta,
            s_max_mb: 64.0,
            s_min_bytes: 64 * 1024,
            fixed_load_size_mb: args.load_size_mb,
            fixed_mip_bias: args.mip_bias,
            bind_cost: bind_cost_preset(args),
        })
        .context("building the streaming policy")
}

/// The bind-latency preset that describes the device the predictive controller predicts
/// for: the modelled one (`--bind-latency`), except where the real clock measures a
/// device no model charges (`--clock real --bind-latency none`): that one it learns.
pub(crate) fn bind_cost_preset(args: &Args) -> Option<BindLatencyPreset> {
    match (args.clock, args.bind_latency) {
        (Clock::Real, BindLatencyPreset::None) => None,
        (_, preset) => Some(preset),
    }
}

/// The latency (ms) of a frame the controller is given: measured with the
/// real clock (after sleeping through the modelled bind cost, as a driver
/// would stall), modelled with the others: `render_ms`, the binds' modelled cost and the
/// copies' time.
pub(crate) fn frame_latency(
    clock: Clock,
    render_ms: f64,
    applied: &citystream_engine::texture_cache::CycleReport,
    other_upload_bytes: u64,
    latency: &BindLatencyModel,
    rng: &mut SplitMix64,
    measured_ms: impl FnOnce() -> f64,
) -> f64 {
    let mut bind_cost_ms = 0.0;
    if applied.bind_shape.blocks() > 0 {
        // Charged by the blocks' layout, not by where their memory happened to lie.
        bind_cost_ms = latency.cost_s(applied.bind_shape, rng) * 1000.0;
        if clock == Clock::Real && bind_cost_ms > 0.0 {
            std::thread::sleep(Duration::from_secs_f64(bind_cost_ms / 1000.0));
        }
    }
    match clock {
        Clock::Real => measured_ms(),
        Clock::Fixed | Clock::Modelled => {
            let copied = applied.bytes_uploaded + other_upload_bytes;
            render_ms + bind_cost_ms + copied as f64 / FIXED_COPY_BYTES_PER_S * 1000.0
        }
    }
}
