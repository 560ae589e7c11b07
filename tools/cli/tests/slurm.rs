//! Sharded builds under a real scheduler: a one-node Slurm cluster on this machine
//! (`tools/scripts/slurm-local.sh`), the job scripts of docs/SHARDS.md
//! (`tools/scripts/slurm/*.sbatch`, submitted as they are) writing into the S3 emulator,
//! array jobs, a dependent merge, a requeued task, a merge refused while a shard is
//! missing, and a flipped byte of a shard in S3 refused by name.

mod cli_support;
mod tileset_support;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

use citystream_dataset::remote::{open_dataset, RemoteOptions};
use citystream_dataset::Dataset;
use citystream_testing::tool_tests::env_refs;
use cli_support::{assert_same_content, citystream, emulator_with_bucket, fresh_dir, stderr};

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn script(name: &str) -> PathBuf {
    repo().join("tools/scripts/slurm").join(name)
}

/// A free loopback port and the one after it (slurmctld's and slurmd's).
fn free_port_pair() -> u16 {
    loop {
        let a = std::net::TcpListener::bind("127.0.0.1:0").expect("a port");
        let port = a.local_addr().expect("address").port();
        if port < 65_000 && std::net::TcpListener::bind(("127.0.0.1", port + 1)).is_ok() {
            return port;
        }
    }
}

/// The cluster, stopped when dropped.
struct Cluster {
    dir: PathBuf,
    port: u16,
    conf: PathBuf,
}

impl Cluster {
    fn start(work: &Path) -> Cluster {
        let dir = work.join("slurm");
        let port = free_port_pair();
        let out = Command::new("bash")
            .arg(repo().join("tools/scripts/slurm-local.sh"))
            .arg("start")
            .env("SLURM_LOCAL_DIR", &dir)
            .env("SLURM_LOCAL_PORT", port.to_string())
            .output()
            .expect("slurm-local.sh runs");
        assert!(out.status.success(), "slurm-local.sh start: {}", stderr(&out));
        let conf = dir.join("etc/slurm.conf");
        Cluster { dir, port, conf }
    }

    /// A Slurm client command against this cluster, with `env`.
    fn run(&self, program: &str, args: &[&str], env: &[(&str, &str)]) -> Output {
        Command::new(program)
            .args(args)
            .env("SLURM_CONF", &self.conf)
            .envs(env.iter().copied())
            .output()
            .expect("a Slurm command runs")
    }

    /// `sbatch --parsable ARGS…`: the job id.
    fn submit(&self, args: &[&str], env: &[(&str, &str)]) -> String {
        let mut all = vec!["--parsable"];
        all.extend_from_slice(args);
        let out = self.run("sbatch", &all, env);
        assert!(out.status.success(), "sbatch {args:?}: {}", stderr(&out));
        let text = String::from_utf8_lossy(&out.stdout);
        text.trim().split(';').next().expect("a job id").to_owned()
    }

    /// Every task's state of job `id` (`scontrol show job`), with the reason of each.
    fn states(&self, id: &str) -> Vec<(String, String)> {
        let out = self.run("scontrol", &["show", "job", "-o", id], &[]);
        String::from_utf8_lossy(&out.stdout)
            .lines()
            .filter_map(|line| {
                let field = |key: &str| {
                    line.split_whitespace()
                        .find_map(|f| f.strip_prefix(key))
                        .map(str::to_owned)
                };
                Some((field("JobState=")?, field("Reason=").unwrap_or_default()))
            })
            .collect()
    }

    /// Waits until every task of job `id` ended (or can never start); its states.
    fn wait(&self, id: &str, limit: Duration) -> Vec<String> {
        let start = Instant::now();
        loop {
            let states = self.states(id);
            let ended = |(state, reason): &(String, String)| {
                !matches!(
                    state.as_str(),
                    "PENDING" | "RUNNING" | "CONFIGURING" | "COMPLETING" | "REQUEUED"
                ) || reason == "DependencyNeverSatisfied"
            };
            if !states.is_empty() && states.iter().all(ended) {
                return states.into_iter().map(|(s, _)| s).collect();
            }
            assert!(
                start.elapsed() < limit,
                "job {id} still not done after {limit:?}: {states:?}"
            );
            std::thread::sleep(Duration::from_millis(250));
        }
    }
}

impl Drop for Cluster {
    fn drop(&mut self) {
        let _ = Command::new("bash")
            .arg(repo().join("tools/scripts/slurm-local.sh"))
            .arg("stop")
            .env("SLURM_LOCAL_DIR", &self.dir)
            .env("SLURM_LOCAL_PORT", self.port.to_string())
            .output();
    }
}

#[test]
#[cfg_attr(
    any(citystream_skip_slurm, citystream_skip_s3),
    ignore = "Slurm or the S3 emulator is not installed and `make setup` has not run"
)]
fn a_slurm_array_builds_shards_into_s3_and_a_dependent_job_merges_them() {
    let started = Instant::now();
    let dir = fresh_dir("slurm", "array");
    let cluster = Cluster::start(&dir);
    let (_s3, client_env) = emulator_with_bucket(&dir);
    let bin = env!("CARGO_BIN_EXE_citystream");
    let mut env = env_refs(&client_env);
    env.push(("CITYSTREAM", bin));
    let logs = dir.join("logs");
    std::fs::create_dir_all(&logs).expect("logs");
    let log = |name: &str| format!("--output={}/{name}", logs.display());
    let read_log = |name: &str| std::fs::read_to_string(logs.join(name)).unwrap_or_default();
    let gen_script = script("gen-shards.sbatch");
    let merge_script = script("merge-shards.sbatch");
    let (gen_s, merge_s) = (
        gen_script.to_str().expect("utf-8"),
        merge_script.to_str().expect("utf-8"),
    );

    // Shards stage under the temporary directory by their URL and index: an earlier run's
    // would be resumed.
    for url in [
        "s3://cities/medium",
        "s3://cities/requeued",
        "s3://cities/imported",
        "s3://cities/missing",
    ] {
        for index in 0..4 {
            let _ = std::fs::remove_dir_all(staging_of(url, index));
        }
    }

    // The one-process build to compare with.
    let single = dir.join("single");
    let one = citystream(&[
        "gen",
        "--preset",
        "medium",
        "--seed",
        "1",
        "--quiet",
        "--out",
        single.to_str().expect("utf-8"),
    ]);
    assert!(one.status.success(), "{}", stderr(&one));

    // A 4-task array into the emulator, the merge after it.
    let url = "s3://cities/medium";
    let array = cluster.submit(
        &["--array=0-3", &log("gen-%a.out"), gen_s, "medium", "1", url, "4"],
        &env,
    );
    let merge = cluster.submit(
        &[
            &format!("--dependency=afterok:{array}"),
            &log("merge.out"),
            merge_s,
            url,
        ],
        &env,
    );
    let states = cluster.wait(&array, Duration::from_secs(600));
    assert!(
        states.iter().all(|s| s == "COMPLETED"),
        "array {states:?}: {}",
        read_log("gen-0.out")
    );
    let states = cluster.wait(&merge, Duration::from_secs(300));
    assert_eq!(states, ["COMPLETED"], "merge: {}", read_log("merge.out"));
    let env_pairs: Vec<(&str, &str)> = env.clone();
    let verify = Command::new(bin)
        .args(["verify", url])
        .envs(env_pairs.iter().copied())
        .output()
        .expect("verify");
    assert!(verify.status.success(), "verify: {}", stderr(&verify));
    for (k, v) in &env_pairs {
        std::env::set_var(k, v);
    }
    let merged = open_dataset(url, &RemoteOptions::default()).expect("open the merged dataset");
    let one_process = Dataset::open(&single).expect("open the one-process build");
    assert_same_content(&merged, &one_process);
    eprintln!(
        "slurm: array of 4 and its merge, verified and compared: {:.1} s",
        started.elapsed().as_secs_f64()
    );

    // A task requeued mid-write: killed, started again by Slurm, and resumed.
    let url = "s3://cities/requeued";
    let array = cluster.submit(
        &[
            "--array=0-1",
            "--open-mode=append",
            &log("requeue-%a.out"),
            gen_s,
            "medium",
            "1",
            url,
            "2",
        ],
        &env,
    );
    let task = format!("{array}_0");
    let staging = staging_of(url, 0);
    let wait_start = Instant::now();
    // Requeued while running, once its first checkpoint is durable: the journal grew past
    // what it held when it was first seen (its header, naming the job).
    let mut first_seen = None;
    loop {
        let running = cluster
            .states(&task)
            .first()
            .is_some_and(|(state, _)| state == "RUNNING");
        let journal = std::fs::read_dir(&staging)
            .into_iter()
            .flatten()
            .flatten()
            .find_map(|w| w.path().join("resume.journal").metadata().ok().map(|m| m.len()));
        if let Some(len) = journal {
            let first = *first_seen.get_or_insert(len);
            if running && len > first {
                break;
            }
        }
        assert!(
            wait_start.elapsed() < Duration::from_secs(120),
            "task 0 never ran to a checkpoint ({}): {}",
            staging.display(),
            read_log("requeue-0.out")
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    let requeue = cluster.run("scontrol", &["requeue", &task], &[]);
    assert!(requeue.status.success(), "scontrol requeue: {}", stderr(&requeue));
    let status = Command::new(bin)
        .args(["merge", "--status", url])
        .envs(env_pairs.iter().copied())
        .output()
        .expect("merge --status");
    let text = String::from_utf8_lossy(&status.stdout);
    assert!(
        text.contains("shard 0/2: running") || text.contains("shard 0/2: missing"),
        "while requeued: {text}"
    );
    // A merge while shard 0 is not done: refused, naming it, nothing written.
    let early = Command::new(bin)
        .args(["merge", url])
        .envs(env_pairs.iter().copied())
        .output()
        .expect("merge");
    if !cluster.wait_done_quick(&array) {
        assert!(!early.status.success(), "a merge ran while shard 0 was requeued");
        assert!(
            stderr(&early).contains("shard 0 of 2 is not complete")
                || stderr(&early).contains("shard 0 is not complete"),
            "{}",
            stderr(&early)
        );
    }
    // Requeued tasks are held until released on some versions; release it (no-op otherwise).
    let _ = cluster.run("scontrol", &["release", &task], &[]);
    let states = cluster.wait(&array, Duration::from_secs(600));
    assert!(
        states.iter().all(|s| s == "COMPLETED"),
        "requeued array {states:?}: {}",
        read_log("requeue-0.out")
    );
    assert!(
        read_log("requeue-0.out").contains("resuming shard 0/2"),
        "the requeued task did not resume: {}",
        read_log("requeue-0.out")
    );
    let merge = cluster.submit(&[&log("merge-requeued.out"), merge_s, url], &env);
    assert_eq!(
        cluster.wait(&merge, Duration::from_secs(300)),
        ["COMPLETED"],
        "{}",
        read_log("merge-requeued.out")
    );
    // Each shard checked every mip against its CRC before its upload; the CRCs are the
    // one-process build's.
    let merged = open_dataset(url, &RemoteOptions::default()).expect("open the requeued build");
    assert_same_content(&merged, &one_process);

    // A tileset imported by a 3-task array of `import-shards.sbatch`, merged: the
    // one-process import.
    let tileset = tileset_support::row_of_walls(&dir, 6);
    let tileset_s = tileset.to_str().expect("utf-8");
    let single_import = dir.join("single-import");
    let one = citystream(&["import", tileset_s, "--out", single_import.to_str().expect("utf-8")]);
    assert!(one.status.success(), "{}", stderr(&one));
    let url = "s3://cities/imported";
    let import_script = script("import-shards.sbatch");
    let array = cluster.submit(
        &[
            "--array=0-2",
            &log("import-%a.out"),
            import_script.to_str().expect("utf-8"),
            tileset_s,
            url,
            "3",
        ],
        &env,
    );
    let merge = cluster.submit(
        &[
            &format!("--dependency=afterok:{array}"),
            &log("merge-import.out"),
            merge_s,
            url,
        ],
        &env,
    );
    let states = cluster.wait(&array, Duration::from_secs(300));
    assert!(
        states.iter().all(|s| s == "COMPLETED"),
        "import array {states:?}: {}",
        read_log("import-0.out")
    );
    assert_eq!(
        cluster.wait(&merge, Duration::from_secs(300)),
        ["COMPLETED"],
        "{}",
        read_log("merge-import.out")
    );
    let merged = open_dataset(url, &RemoteOptions::default()).expect("open the imported dataset");
    assert_same_content(&merged, &Dataset::open(&single_import).expect("the one-process import"));

    // A merge submitted while a shard is missing: the job fails naming it, nothing written.
    let url = "s3://cities/missing";
    let array = cluster.submit(
        &["--array=0", &log("missing-%a.out"), gen_s, "tiny", "1", url, "2"],
        &env,
    );
    let merge = cluster.submit(
        &[
            &format!("--dependency=afterok:{array}"),
            &log("merge-missing.out"),
            merge_s,
            url,
        ],
        &env,
    );
    cluster.wait(&array, Duration::from_secs(120));
    assert_eq!(cluster.wait(&merge, Duration::from_secs(120)), ["FAILED"]);
    assert!(
        read_log("merge-missing.out").contains("shard 1 of 2 is missing"),
        "{}",
        read_log("merge-missing.out")
    );
    assert!(
        open_dataset(url, &RemoteOptions::default()).is_err(),
        "a refused merge wrote a dataset"
    );
    eprintln!("slurm test: {:.1} s of wall time", started.elapsed().as_secs_f64());
}

/// The staging directory of shard `index` of `url` (`ShardWrite::begin`: the URL's CRC and
/// the index, under the temporary directory the tasks inherit).
fn staging_of(url: &str, index: u32) -> PathBuf {
    std::env::temp_dir()
        .join("citystream-shards")
        .join(format!("{:08x}-{index}", crc32fast::hash(url.as_bytes())))
}

impl Cluster {
    /// Whether every task of `id` has already completed (the requeued one included).
    fn wait_done_quick(&self, id: &str) -> bool {
        let states = self.states(id);
        !states.is_empty() && states.iter().all(|(s, _)| s == "COMPLETED")
    }
}

#[test]
#[cfg_attr(
    citystream_skip_s3,
    ignore = "the S3 emulator is not installed and `make setup` has not run"
)]
fn a_flipped_byte_of_a_shard_stored_in_s3_is_refused_by_name() {
    let dir = fresh_dir("slurm", "flipped");
    let (_s3, client_env) = emulator_with_bucket(&dir);
    let env = env_refs(&client_env);
    let bin = env!("CARGO_BIN_EXE_citystream");
    let run = |args: &[&str]| {
        Command::new(bin)
            .args(args)
            .envs(env.iter().copied())
            .output()
            .expect("citystream runs")
    };
    let url = "s3://cities/flipped";
    for shard in ["0/2", "1/2"] {
        let out = run(&[
            "gen", "--preset", "tiny", "--seed", "1", "--quiet", "--shard", shard, "--out", url,
        ]);
        assert!(out.status.success(), "{}", stderr(&out));
    }
    // Flip one byte of shard 1's pack in the store, as bit rot or a partial overwrite would.
    for (k, v) in &env {
        std::env::set_var(k, v);
    }
    let bucket = citystream_dataset::remote::ObjectBucket::new(url, &RemoteOptions::from_env().expect("options"))
        .expect("bucket");
    let pack_key = bucket
        .list("shards/1/")
        .expect("list")
        .into_iter()
        .map(|(k, _)| k)
        .find(|k| k.ends_with("/textures.pack"))
        .expect("shard 1's pack");
    let mut pack = bucket.get(&pack_key).expect("get").expect("the pack");
    let at = pack.len() / 2;
    pack[at] ^= 0x40;
    bucket.put(&pack_key, pack).expect("put the flipped pack");
    let refused = run(&["merge", url]);
    assert!(!refused.status.success(), "a merge took a damaged shard");
    let why = stderr(&refused);
    assert!(why.contains("shard 1 of 2") && why.contains("damaged"), "{why}");
    assert!(
        open_dataset(url, &RemoteOptions::default()).is_err(),
        "a refused merge wrote a dataset"
    );
}

#[test]
fn the_slurm_scripts_in_shards_md_are_the_files_the_tests_submit() {
    let doc = std::fs::read_to_string(repo().join("docs/SHARDS.md")).expect("SHARDS.md");
    for name in ["gen-shards.sbatch", "import-shards.sbatch", "merge-shards.sbatch"] {
        let file = std::fs::read_to_string(script(name)).expect("script");
        let block = format!("`tools/scripts/slurm/{name}`:\n\n```sh\n{file}```");
        assert!(doc.contains(&block), "docs/SHARDS.md does not show {name} as it is");
    }
}
