//! `citystream simulate`: run the streaming policy on the simulated-clock
//! harness and print a Table 3 style summary.

use std::io::Write;
use std::path::PathBuf;

use anyhow::{Context, Result};
use citystream_streaming::bench::sim::{self, FrameSample, SimConfig};
use citystream_streaming::bench::stats::{table3, Summary};
use citystream_streaming::bind_latency::BindLatencyPreset;
use citystream_streaming::controller::{PolicyKind, PolicyOptions};

/// Options of `citystream simulate`.
#[derive(Debug, clap::Args)]
pub struct SimulateArgs {
    /// Load policy: adaptive (the paper's Eq. 4-7), headroom (docs/CONTROLLER.md), baseline or
    /// fixed.
    #[arg(long, default_value = "adaptive")]
    policy: PolicyKind,
    /// Bind-latency preset: none, lavapipe or desktop.
    #[arg(long = "bind-latency", default_value = "desktop")]
    bind_latency: BindLatencyPreset,
    /// Frames to simulate (the paper's 68.6 s benchmark is about 13 000
    /// frames at 5 ms).
    #[arg(long, default_value_t = 13_000)]
    frames: u64,
    /// Seed of the render trace, the city layout and the latency spikes.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
    /// Target maximum frame latency α in ms (adaptive).
    #[arg(long, default_value_t = 16.0)]
    alpha: f64,
    /// Maximum mipmap bias β (adaptive).
    #[arg(long, default_value_t = 8.0)]
    beta: f64,
    /// Load size s in MB (fixed).
    #[arg(long = "load-size-mb", default_value_t = 1.0)]
    load_size_mb: f64,
    /// Mipmap bias b (fixed).
    #[arg(long = "mip-bias", default_value_t = 0.0)]
    mip_bias: f64,
    /// Also run the baseline with the same seed and print both, with the
    /// reductions of frame latency and the share of MB transferred.
    #[arg(long)]
    compare: bool,
    /// Write every frame of the (main) run as CSV: the quantities of the
    /// paper's Fig. 6 (t_w, t_m, t_b, t_bl, t_bu, s, b, transfers).
    #[arg(long)]
    trace: Option<PathBuf>,
}

fn config(args: &SimulateArgs, policy: PolicyKind) -> SimConfig {
    let mut c = SimConfig::new(policy, args.bind_latency, args.frames, args.seed);
    c.policy_options = PolicyOptions {
        alpha_ms: args.alpha,
        beta: args.beta,
        fixed_load_size_mb: args.load_size_mb,
        fixed_mip_bias: args.mip_bias,
        ..PolicyOptions::default()
    };
    c
}

fn simulate(args: &SimulateArgs, policy: PolicyKind) -> Result<Summary> {
    let report = sim::run(&config(args, policy))
        .with_context(|| format!("simulating policy `{policy}` with preset `{}`", args.bind_latency))?;
    Ok(report.summary)
}

fn simulate_traced(args: &SimulateArgs, path: &PathBuf) -> Result<Summary> {
    let file = std::fs::File::create(path).with_context(|| format!("creating trace file {}", path.display()))?;
    let mut out = std::io::BufWriter::new(file);
    writeln!(
        out,
        "frame,time_s,frame_ms,tw_ms,tm_ms,twa_ms,tb_ms,tbl_ms,tbu_ms,load_factor,load_size_mb,mip_bias,mips,bytes"
    )?;
    let mut write_error = None;
    let mut row = |f: &FrameSample| {
        if write_error.is_some() {
            return;
        }
        let t = &f.telemetry;
        if let Err(e) = writeln!(
            out,
            "{},{:.6},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.6},{:.4},{:.4},{},{}",
            f.frame,
            f.time_s,
            t.frame_ms,
            t.tw_ms,
            t.tm_ms,
            t.twa_ms,
            t.tb_ms,
            t.tbl_ms,
            t.tbu_ms,
            t.load_factor,
            t.load_size_mb,
            t.mip_bias,
            f.mips,
            f.bytes
        ) {
            write_error = Some(e);
        }
    };
    let report = sim::run_traced(&config(args, args.policy), &mut row).with_context(|| {
        format!(
            "simulating policy `{}` with preset `{}`",
            args.policy, args.bind_latency
        )
    })?;
    if let Some(e) = write_error {
        return Err(e).with_context(|| format!("writing trace file {}", path.display()));
    }
    out.flush()
        .with_context(|| format!("writing trace file {}", path.display()))?;
    Ok(report.summary)
}

/// Run the subcommand.
pub fn run(args: &SimulateArgs) -> Result<()> {
    let main = match &args.trace {
        Some(path) => simulate_traced(args, path)?,
        None => simulate(args, args.policy)?,
    };
    if !args.compare {
        if args.json {
            println!("{}", serde_json::to_string_pretty(&main)?);
        } else {
            let title = format!("{} / {}", args.policy, args.bind_latency);
            print!("{}", table3(&[(&title, &main)]));
        }
        return Ok(());
    }
    let base = simulate(args, PolicyKind::Baseline)?;
    let ratio = |a: f64, b: f64| if b > 0.0 { a / b } else { f64::NAN };
    let max_reduction = 1.0 - ratio(main.frame_ms.max, base.frame_ms.max);
    let mean_reduction = 1.0 - ratio(main.frame_ms.mean, base.frame_ms.mean);
    let bytes_share = ratio(main.bytes_streamed as f64, base.bytes_streamed as f64);
    if args.json {
        let out = serde_json::json!({
            "baseline": base,
            args.policy.name(): main,
            "max_frame_reduction": max_reduction,
            "mean_frame_reduction": mean_reduction,
            "bytes_share_of_baseline": bytes_share,
        });
        println!("{}", serde_json::to_string_pretty(&out)?);
    } else {
        let title = format!("{} (alpha {} ms, beta {})", args.policy, args.alpha, args.beta);
        print!("{}", table3(&[("No adaptive algorithms", &base), (&title, &main)]));
        println!(
            "max frame latency -{:.1} %, mean frame latency -{:.1} %, MB transferred {:.1} % of baseline \
             (preset {}, {} frames, seed {})",
            100.0 * max_reduction,
            100.0 * mean_reduction,
            100.0 * bytes_share,
            args.bind_latency,
            args.frames,
            args.seed
        );
    }
    Ok(())
}
