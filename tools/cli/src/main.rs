//! `citystream`: datasets, simulation and benchmarks from the command line.

use anyhow::Result;
use clap::{Parser, Subcommand};

use citystream_bench::{bench, report, simulate};
use citystream_cli::{bind_replay, cache_report, info, merge, path, upgrade, verify};
use citystream_gen::command as gen;
use citystream_gen::{atlas, atlas_tree, city, patches};
use citystream_import::command as import;

#[derive(Debug, Parser)]
#[command(
    name = "citystream",
    version,
    about = "citystream dataset, simulation and benchmark tool"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Generate a synthetic city dataset.
    Gen(city::GenArgs),
    /// Pack a dataset's textures into square atlases.
    Atlas(atlas::AtlasArgs),
    /// Build a texture-atlas tree (Buchholz & Döllner) from a dataset.
    AtlasTree(atlas_tree::AtlasTreeArgs),
    /// Report how a dataset's textures pack into the sparse cache (utilisation).
    CacheReport(cache_report::CacheReportArgs),
    /// Import a glTF 2.0 scene or an OGC 3D Tiles tileset as a dataset.
    Import(import::ImportArgs),
    /// Print totals of a dataset.
    Info(info::InfoArgs),
    /// Join the shards of a sharded build (`gen`/`import` `--shard I/N`) into one dataset.
    Merge(merge::MergeArgs),
    /// Write the standard benchmark camera path (paper §4.1) of a dataset.
    Path(path::PathArgs),
    /// Cut an image into a simulated aerial survey over a city (the ground layer's patches).
    Patches(patches::PatchesArgs),
    /// Run the streaming policy on the simulated-clock harness.
    Simulate(simulate::SimulateArgs),
    /// Check every offset, length and mip of a dataset.
    Verify(verify::VerifyArgs),
    /// Rewrite a dataset of an older format version as the current one, atomically.
    Upgrade(upgrade::UpgradeArgs),
    /// Compare flythrough runs: Table 3 markdown and Fig. 6 / speed-vs-error charts.
    Report(report::ReportArgs),
    /// Run the flythrough under each policy on one dataset and report the comparison.
    Bench(bench::BenchArgs),
    /// Replay a bind log (`CITYSTREAM_BIND_LOG`) on this machine's device, with the bind checker.
    BindReplay(bind_replay::BindReplayArgs),
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Gen(args) => gen::run(&args),
        Command::Atlas(args) => atlas::run(&args),
        Command::AtlasTree(args) => atlas_tree::run(&args),
        Command::CacheReport(args) => cache_report::run(&args),
        Command::Import(args) => import::run(&args),
        Command::Info(args) => info::run(&args),
        Command::Merge(args) => merge::run(&args),
        Command::Path(args) => path::run(&args),
        Command::Patches(args) => patches::run(&args),
        Command::Simulate(args) => simulate::run(&args),
        Command::Verify(args) => verify::run(&args),
        Command::Upgrade(args) => upgrade::run(&args),
        Command::Report(args) => report::run(&args),
        Command::Bench(args) => bench::run(&args),
        Command::BindReplay(args) => bind_replay::run(&args),
    }
}
