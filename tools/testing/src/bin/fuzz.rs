//! `fuzz`: runs the fuzz harnesses of `citystream_testing::fuzz` (dataset files, camera paths,
//! glTF/GLB import, KTX2/DDS/PNG textures, patch sets, remote reads, 3D Tiles) and fails on
//! any input that panics, runs longer than `--hang-s` or makes the process's heap grow by
//! more than `--max-alloc-mb` above what it held before the input. An input still running
//! whose heap growth passes `--runaway-alloc-mb` (a read without end, of a device) is
//! stopped like a hang, before it exhausts the machine's memory. Failing inputs are saved
//! under `--out` to reproduce them.
//!
//!     fuzz --target dataset --inputs 1000000 --seed 1

use std::alloc::System;
use std::panic::AssertUnwindSafe;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use citystream_testing::fuzz::{Harness, Outcome, Target};
use clap::Parser;
use peakmem_alloc::{PeakMemAlloc, PeakMemAllocTrait, INSTRUMENTED_SYSTEM};

#[global_allocator]
static GLOBAL: &PeakMemAlloc<System> = &INSTRUMENTED_SYSTEM;

#[derive(Debug, Parser)]
#[command(name = "fuzz", about = "Mutation fuzzing of every citystream parser")]
struct Args {
    /// Harnesses to run, in order (all by default).
    #[arg(long, value_enum, num_args = 1..)]
    target: Vec<Target>,
    /// Inputs per harness.
    #[arg(long, default_value_t = 10_000)]
    inputs: u64,
    /// Stop a harness after this many seconds even if fewer inputs ran.
    #[arg(long)]
    time_limit_s: Option<f64>,
    /// Seed of the input stream; the same seed gives the same inputs.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Largest heap growth one input may cause, in MiB.
    #[arg(long, default_value_t = 256)]
    max_alloc_mb: u64,
    /// An input running longer than this many seconds is a hang.
    #[arg(long, default_value_t = 10.0)]
    hang_s: f64,
    /// An input whose heap growth passes this many MiB while it runs ends the run at once,
    /// saved like a hang (at least `--max-alloc-mb`).
    #[arg(long, default_value_t = 1024)]
    runaway_alloc_mb: u64,
    /// Scratch files and failing inputs go here.
    #[arg(long, default_value = "out/fuzz")]
    out: PathBuf,
    /// Runs the saved failing inputs given (named `TARGET-SEED-INDEX--SEEDFILE.bin`, as
    /// this tool saves them) once each and reports what they do, instead of fuzzing.
    #[arg(long, num_args = 1..)]
    replay: Vec<PathBuf>,
}

/// Totals of one harness.
#[derive(Debug, Default)]
struct Totals {
    inputs: u64,
    accepted: u64,
    rejected: u64,
    panics: u64,
    over_alloc: u64,
    max_alloc: usize,
    max_input: Duration,
    first_failure: Option<String>,
    /// Distinct panic sites (the first line of the message) and how often each was hit.
    panic_sites: std::collections::BTreeMap<String, u64>,
}

/// The input being run, for the watchdog: its start, and `TARGET-SEED-INDEX--SEEDFILE`
/// (what `--replay` reads back from a saved input's name).
#[derive(Default)]
struct Current {
    started: Option<Instant>,
    label: String,
    bytes: Vec<u8>,
}

fn main() -> Result<()> {
    let args = Args::parse();
    if !(args.hang_s.is_finite() && args.hang_s > 0.0) {
        anyhow::bail!("--hang-s {} must be a positive number of seconds", args.hang_s);
    }
    if let Some(limit) = args.time_limit_s.filter(|l| !(l.is_finite() && *l > 0.0)) {
        anyhow::bail!("--time-limit-s {limit} must be a positive number of seconds");
    }
    if args.runaway_alloc_mb < args.max_alloc_mb {
        anyhow::bail!(
            "--runaway-alloc-mb {} must be at least --max-alloc-mb {}",
            args.runaway_alloc_mb,
            args.max_alloc_mb
        );
    }
    let targets = if args.target.is_empty() {
        Target::ALL.to_vec()
    } else {
        args.target.clone()
    };
    let failures = args.out.join("failures");
    std::fs::create_dir_all(&failures).with_context(|| format!("creating {}", failures.display()))?;

    // Panics are expected findings: keep the message, print it once in the report.
    let last_panic = Arc::new(Mutex::new(String::new()));
    {
        let last_panic = Arc::clone(&last_panic);
        std::panic::set_hook(Box::new(move |info| {
            if let Ok(mut message) = last_panic.lock() {
                *message = info.to_string();
            }
        }));
    }
    let current = Arc::new(Mutex::new(Current::default()));
    spawn_watchdog(Arc::clone(&current), &args, failures.clone());
    if !args.replay.is_empty() {
        return replay(&args, &current, &last_panic);
    }

    let mut failed = false;
    println!("| target | inputs | accepted | rejected | panics | over {} MiB | max heap growth KiB | slowest input ms | wall s | inputs/s |", args.max_alloc_mb);
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for target in targets {
        let harness = Harness::new(target, &args.out.join(format!("work-{}", target.name())))
            .with_context(|| format!("building the {} harness", target.name()))?;
        let totals = run_harness(&harness, &args, &current, &last_panic, &failures)?;
        let wall = totals.1.as_secs_f64();
        let t = totals.0;
        println!(
            "| {} | {} | {} | {} | {} | {} | {:.0} | {:.1} | {:.1} | {:.0} |",
            target.name(),
            t.inputs,
            t.accepted,
            t.rejected,
            t.panics,
            t.over_alloc,
            t.max_alloc as f64 / 1024.0,
            t.max_input.as_secs_f64() * 1e3,
            wall,
            t.inputs as f64 / wall.max(1e-9)
        );
        if let Some(first) = &t.first_failure {
            eprintln!("{}: {first}", target.name());
            for (site, hits) in &t.panic_sites {
                eprintln!("{}: {hits} input(s) {site}", target.name());
            }
            failed = true;
        }
    }
    if failed {
        anyhow::bail!("fuzzing found failing inputs; they are saved in {}", failures.display());
    }
    Ok(())
}

fn run_harness(
    harness: &Harness,
    args: &Args,
    current: &Mutex<Current>,
    last_panic: &Mutex<String>,
    failures: &std::path::Path,
) -> Result<(Totals, Duration)> {
    let started = Instant::now();
    let mut totals = Totals::default();
    let bound = usize::try_from(args.max_alloc_mb.saturating_mul(1 << 20)).unwrap_or(usize::MAX);
    let mut last_progress = Instant::now();
    let name = harness.target().name();
    for index in 0..args.inputs {
        if args
            .time_limit_s
            .is_some_and(|limit| started.elapsed().as_secs_f64() >= limit)
        {
            break;
        }
        let (seed_index, bytes) = harness.input(args.seed, index);
        let seed_name = harness.seed_names()[seed_index];
        let label = format!("{name}-{}-{index}--{seed_name}", args.seed);
        let Measured { result, growth, took } = watched(current, label, harness, seed_index, &bytes, last_panic);
        totals.inputs += 1;
        totals.max_alloc = totals.max_alloc.max(growth);
        totals.max_input = totals.max_input.max(took);
        let mut failure = None;
        match result {
            Ok(Outcome::Accepted) => totals.accepted += 1,
            Ok(Outcome::Rejected) => totals.rejected += 1,
            Err(message) => {
                totals.panics += 1;
                let site = message.lines().next().unwrap_or_default().to_string();
                *totals.panic_sites.entry(site).or_insert(0) += 1;
                failure = Some(format!("input {index} panicked: {message}"));
            }
        }
        if growth > bound {
            totals.over_alloc += 1;
            failure.get_or_insert_with(|| {
                format!(
                    "input {index} grew the heap by {:.1} MiB",
                    growth as f64 / f64::from(1 << 20)
                )
            });
        }
        if let Some(failure) = failure {
            let path = failures.join(format!("{name}-{}-{index}--{seed_name}.bin", args.seed));
            std::fs::write(&path, &bytes).with_context(|| format!("saving {}", path.display()))?;
            totals
                .first_failure
                .get_or_insert_with(|| format!("{failure} (saved as {})", path.display()));
        }
        if last_progress.elapsed() >= Duration::from_secs(10) {
            last_progress = Instant::now();
            eprintln!(
                "{name}: {} inputs in {:.0} s ({} accepted, {} panics, {} over the heap bound)",
                totals.inputs,
                started.elapsed().as_secs_f64(),
                totals.accepted,
                totals.panics,
                totals.over_alloc
            );
        }
    }
    Ok((totals, started.elapsed()))
}

/// What one input did: its outcome or panic message, the heap growth it caused (peak
/// over the input) and its duration.
struct Measured {
    result: std::result::Result<Outcome, String>,
    growth: usize,
    took: Duration,
}

/// Runs one input under the watchdog's eye, named `label` for it.
fn watched(
    current: &Mutex<Current>,
    label: String,
    harness: &Harness,
    seed_index: usize,
    bytes: &[u8],
    last_panic: &Mutex<String>,
) -> Measured {
    if let Ok(mut c) = current.lock() {
        c.label = label;
        c.bytes.clear();
        c.bytes.extend_from_slice(bytes);
        // Before the watchdog looks: the peak it reads is then this input's.
        GLOBAL.reset_peak_memory();
        c.started = Some(Instant::now());
    }
    let measured = measure(harness, seed_index, bytes, last_panic);
    if let Ok(mut c) = current.lock() {
        c.started = None;
    }
    measured
}

fn measure(harness: &Harness, seed_index: usize, bytes: &[u8], last_panic: &Mutex<String>) -> Measured {
    GLOBAL.reset_peak_memory();
    let started = Instant::now();
    let result = std::panic::catch_unwind(AssertUnwindSafe(|| harness.run(seed_index, bytes)));
    let (growth, took) = (GLOBAL.get_peak_memory(), started.elapsed());
    let result = result.map_err(|_| last_panic.lock().map(|m| m.clone()).unwrap_or_default());
    Measured { result, growth, took }
}

/// Runs each saved input once: outcome, heap growth, time, and the panic if any (a hang
/// or a runaway heap ends the replay as it ends a run).
fn replay(args: &Args, current: &Mutex<Current>, last_panic: &Mutex<String>) -> Result<()> {
    for file in &args.replay {
        let name = file.file_name().and_then(|n| n.to_str()).unwrap_or_default();
        let target = Target::ALL
            .into_iter()
            .find(|t| name.starts_with(&format!("{}-", t.name())))
            .with_context(|| format!("{}: the name does not start with a target", file.display()))?;
        let seed_name = name
            .strip_suffix(".bin")
            .and_then(|n| n.split_once("--"))
            .map(|(_, seed)| seed)
            .with_context(|| format!("{}: the name does not end with --SEEDFILE.bin", file.display()))?;
        let harness = Harness::new(target, &args.out.join(format!("replay-{}", target.name())))?;
        let seed_index = harness
            .seed_names()
            .iter()
            .position(|n| *n == seed_name)
            .with_context(|| format!("{}: {} has no seed {seed_name}", file.display(), target.name()))?;
        let bytes = std::fs::read(file).with_context(|| format!("reading {}", file.display()))?;
        let label = name.strip_suffix(".bin").unwrap_or(name).to_owned();
        let Measured { result, growth, took } = watched(current, label, &harness, seed_index, &bytes, last_panic);
        let outcome = match result {
            Ok(outcome) => format!("{outcome:?}"),
            Err(message) => format!("panicked: {message}"),
        };
        println!(
            "{}: {outcome}; heap growth {:.0} KiB; {:.1} ms",
            file.display(),
            growth as f64 / 1024.0,
            took.as_secs_f64() * 1e3
        );
    }
    Ok(())
}

/// Ends the process when one input runs longer than `--hang-s` or its heap growth passes
/// `--runaway-alloc-mb` while it runs, saving it first under its label (replayable).
fn spawn_watchdog(current: Arc<Mutex<Current>>, args: &Args, failures: PathBuf) {
    let hang = Duration::from_secs_f64(args.hang_s);
    let runaway = usize::try_from(args.runaway_alloc_mb.saturating_mul(1 << 20)).unwrap_or(usize::MAX);
    // Often enough that a read of /dev/zero (GB/s) is stopped near the bound.
    let poll = Duration::from_millis(10).min(hang);
    std::thread::spawn(move || loop {
        std::thread::sleep(poll);
        let Ok(c) = current.lock() else { continue };
        let Some(started) = c.started else { continue };
        let growth = GLOBAL.get_peak_memory();
        let why = if started.elapsed() > hang {
            format!("ran longer than {:.1} s (a hang)", hang.as_secs_f64())
        } else if growth > runaway {
            format!(
                "grew the heap by {:.0} MiB while running, past --runaway-alloc-mb {} (a read without end)",
                growth as f64 / f64::from(1 << 20),
                runaway >> 20
            )
        } else {
            continue;
        };
        let path = failures.join(format!("{}.bin", c.label));
        let _ = std::fs::write(&path, &c.bytes);
        eprintln!("fuzz: input {} {why}; saved as {}", c.label, path.display());
        std::process::exit(3);
    });
}
