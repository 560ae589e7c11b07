//! `flythrough`: renders a city headless along a camera path. With a
//! dataset it runs the paper's pipeline (Algorithm 1): feedback, compaction,
//! controller, loading task, sparse binds and copies, then the frame with
//! City Colormap blending. It writes PNG frames and `summary.json`.

use anyhow::{bail, Context, Result};
use clap::Parser;

use citystream_streaming::disk_model::DiskModelChoice;

use crate::args::{Args, Clock, ControllerLatency, Sparse, Strategy, FIXED_RENDER_MS, FIXED_STEP_MS};
use crate::dataset::dataset_dir;
use crate::device::flythrough_device;
use crate::headless::stream_city;
use crate::placeholder::placeholder_city;
use crate::pop_in::pop_in;

mod args;
mod camera;
mod city_gpu;
mod controller;
mod controls;
mod dataset;
mod depth_slabs;
mod device;
mod disk;
mod flight;
mod ground;
mod headless;
mod measure;
mod output;
mod passes;
mod placeholder;
mod pop_in;
mod preload;
mod recording;
mod tree;
mod window;

fn main() -> Result<()> {
    let args = Args::parse();
    if args.strategy != Strategy::Feedback && (args.placeholder || args.pop_in) {
        bail!(
            "--strategy {} streams a dataset; leave out --placeholder and --pop-in",
            args.strategy.name()
        );
    }
    if args.strategy == Strategy::TextureArrays && args.sparse == Sparse::On {
        bail!("--strategy texture-arrays holds textures without sparse residency; leave out --sparse on");
    }
    // Refused before any device or dataset work.
    controller::build_policy(&args)?;
    if args.clock != Clock::Modelled && args.display_period_ms != FIXED_STEP_MS {
        bail!("--display-period-ms models a display: it needs --clock modelled");
    }
    if args.clock == Clock::Real && args.render_ms != FIXED_RENDER_MS {
        bail!("--render-ms is the modelled render cost of a frame: it needs --clock fixed or modelled");
    }
    if args.disk_model != DiskModelChoice::None && (args.clock == Clock::Real || args.window) {
        bail!(
            "--disk-model {} times reads on a modelled clock: it needs --clock fixed or modelled, headless \
             (with --clock real the reads take what the disk takes)",
            args.disk_model
        );
    }
    let has_display = args.clock == Clock::Modelled || (args.window && args.clock == Clock::Real);
    if args.controller_latency != ControllerLatency::Work && !has_display {
        bail!("--controller-latency period needs a display: --clock modelled, or --window with --clock real");
    }
    if args.window {
        return window::run(&args);
    }
    let device = flythrough_device(&args, "citystream flythrough", None)?;
    let frames_dir = args.out.join("frames");
    std::fs::create_dir_all(&frames_dir).with_context(|| format!("creating {}", frames_dir.display()))?;
    if args.placeholder {
        return placeholder_city(&args, &device);
    }
    let dir = dataset_dir(&args)?;
    if args.pop_in {
        pop_in(&args, &device, &dir)
    } else {
        stream_city(&args, &device, &dir)
    }
}
