//! The flythrough runs of each benchmark scenario: the policies compared, the
//! controllers, the pressure runs, the strategies and the ground.

use std::path::Path;

/// `--strategy` of the flythrough runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum StrategyArg {
    /// The paper's GPU feedback.
    Feedback,
    /// The texture-atlas tree (the dataset must be a tree).
    AtlasTree,
    /// Texture arrays without sparse residency (docs/STRATEGIES.md).
    TextureArrays,
}

impl StrategyArg {
    pub(crate) fn name(self) -> &'static str {
        match self {
            StrategyArg::Feedback => "feedback",
            StrategyArg::AtlasTree => "atlas-tree",
            StrategyArg::TextureArrays => "texture-arrays",
        }
    }
}

/// One policy configuration of the benchmark.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PolicyRun {
    /// Subdirectory of the output directory, also the file-safe run name.
    pub dir: &'static str,
    /// Name shown in the table and charts.
    pub name: &'static str,
    /// Policy arguments of the flythrough.
    pub args: &'static [&'static str],
}

/// The benchmark's runs, in the order they execute and are reported:
/// the paper's baseline and adaptive α = 12 and 16 ms, and a fixed load
/// size of 4 MB with no mipmap bias.
pub const POLICY_RUNS: [PolicyRun; 4] = [
    PolicyRun {
        dir: "baseline",
        name: "baseline",
        args: &["--policy", "baseline"],
    },
    PolicyRun {
        dir: "adaptive-a12",
        name: "adaptive α=12 ms",
        args: &["--policy", "adaptive", "--alpha", "12"],
    },
    PolicyRun {
        dir: "adaptive-a16",
        name: "adaptive α=16 ms",
        args: &["--policy", "adaptive", "--alpha", "16"],
    },
    PolicyRun {
        dir: "fixed-s4-b0",
        name: "fixed s=4 MB b=0",
        args: &["--policy", "fixed", "--load-size-mb", "4", "--mip-bias", "0"],
    },
];

/// One flythrough run of a benchmark.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct BenchRun {
    pub dir: String,
    pub name: String,
    pub args: Vec<String>,
}

impl BenchRun {
    /// The run into `dir`, shown as `name`, with the flythrough arguments `args` then `extra`.
    pub(crate) fn new(dir: &str, name: &str, args: &[&str], extra: impl IntoIterator<Item = String>) -> Self {
        BenchRun {
            dir: dir.into(),
            name: name.into(),
            args: args.iter().map(|a| a.to_string()).chain(extra).collect(),
        }
    }

    pub(crate) fn of_policy(policy: &PolicyRun, extra: &[&str]) -> Self {
        Self::new(
            policy.dir,
            policy.name,
            policy.args,
            extra.iter().map(|a| a.to_string()),
        )
    }
}

/// Camera seconds of a pressure run.
pub const PRESSURE_DURATION_S: f64 = 30.0;
/// Image size of a pressure run.
pub const PRESSURE_SIZE: (u32, u32) = (1920, 1080);

/// The runs of `--scenario controllers` on each benchmark: the baseline and both
/// controllers at α = 12 ms (the pressure benchmark's α), with `extra`.
pub(crate) fn controller_runs(extra: &[String]) -> Vec<BenchRun> {
    [
        ("baseline", "baseline", &["--policy", "baseline"][..]),
        (
            "paper-a12",
            "paper α=12 ms",
            &["--policy", "adaptive", "--controller", "paper", "--alpha", "12"][..],
        ),
        (
            "headroom-a12",
            "headroom α=12 ms",
            &["--policy", "adaptive", "--controller", "headroom", "--alpha", "12"][..],
        ),
    ]
    .into_iter()
    .map(|(dir, name, args)| BenchRun::new(dir, name, args, extra.iter().cloned()))
    .collect()
}

/// `--budget-mb` of `--scenario pressure` and `strategies` when not given.
pub(crate) const DEFAULT_BUDGET_MB: u64 = 256;

/// The pressure scenario's runs: the four policies under the budget, then
/// adaptive α = 12 ms with ring eviction, then without a budget.
pub(crate) fn pressure_runs(budget_mb: u64) -> Vec<BenchRun> {
    let budget = budget_mb.to_string();
    let shared = ["--psnr-interval", "60", "--frame-interval", "0"];
    let mut runs: Vec<BenchRun> = POLICY_RUNS
        .iter()
        .map(|policy| {
            let mut run = BenchRun::of_policy(policy, &shared);
            run.args.extend(["--memory-budget-mb".to_string(), budget.clone()]);
            run
        })
        .collect();
    // The paper's ring eviction on the same cache, for comparison.
    let mut ring = BenchRun::of_policy(&POLICY_RUNS[1], &shared);
    ring.dir = "adaptive-a12-ring".into();
    ring.name = "adaptive α=12 ms, ring eviction".into();
    ring.args.extend(
        ["--memory-budget-mb", budget.as_str(), "--eviction", "ring"]
            .iter()
            .map(|a| a.to_string()),
    );
    runs.push(ring);
    let mut unbudgeted = BenchRun::of_policy(&POLICY_RUNS[1], &shared);
    unbudgeted.dir = "unbudgeted-a12".into();
    unbudgeted.name = "unbudgeted α=12 ms".into();
    unbudgeted
        .args
        .extend(["--memory-budget-mb".to_string(), "unlimited".to_string()]);
    runs.push(unbudgeted);
    runs
}

/// What the two runs of a comparison scenario (`strategies`, `ground`) share: the policy
/// and the PSNR interval, no PNG frames.
pub(crate) const COMPARISON_ARGS: [&str; 8] = [
    "--policy",
    "adaptive",
    "--alpha",
    "16",
    "--psnr-interval",
    "30",
    "--frame-interval",
    "0",
];

/// The two runs of `--scenario strategies`: the same policy, budget and PSNR interval.
pub(crate) fn strategy_runs(budget_mb: u64, tree: bool) -> Vec<BenchRun> {
    let budget = ["--memory-budget-mb".to_string(), budget_mb.to_string()];
    let run = |dir: &str, strategy: StrategyArg, budget: &[String]| {
        let strategy = ["--strategy".into(), strategy.name().into()];
        BenchRun::new(dir, dir, &COMPARISON_ARGS, budget.iter().cloned().chain(strategy))
    };
    let mut runs = vec![run(StrategyArg::Feedback.name(), StrategyArg::Feedback, &budget)];
    if tree {
        runs.push(run(StrategyArg::AtlasTree.name(), StrategyArg::AtlasTree, &budget));
    }
    // Without a budget the arrays hold the whole city where the device can; with one they
    // stream within it.
    runs.push(run(STRATEGY_ARRAYS_RESIDENT, StrategyArg::TextureArrays, &[]));
    runs.push(run(STRATEGY_ARRAYS_STREAMED, StrategyArg::TextureArrays, &budget));
    runs
}

/// The texture-array runs of `--scenario strategies`: fully resident, streamed.
pub(crate) const STRATEGY_ARRAYS_RESIDENT: &str = "texture-arrays";
pub(crate) const STRATEGY_ARRAYS_STREAMED: &str = "texture-arrays-streamed";

/// The two runs of `--scenario ground`: the same policy and PSNR interval, the second
/// with the imagery.
pub(crate) fn ground_runs(patches: &Path, budget_mb: Option<u64>) -> Vec<BenchRun> {
    let budget = budget_mb.map(|b| ["--memory-budget-mb".to_string(), b.to_string()]);
    let run = |dir: &str, name: &str, extra: &[String]| {
        let extra = budget.iter().flatten().chain(extra).cloned();
        BenchRun::new(dir, name, &COMPARISON_ARGS, extra)
    };
    vec![
        run("no-ground", "without ground", &[]),
        run(
            "ground",
            "with ground",
            &["--ground".to_string(), patches.display().to_string()],
        ),
    ]
}
