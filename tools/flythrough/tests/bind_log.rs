//! A flight's sparse binds and copies logged with `CITYSTREAM_BIND_LOG` and
//! replayed with `citystream bind-replay`, bind checker on: the replay runs
//! exactly the logged batches and copies, and a log with a double bind
//! injected is refused naming the block.

mod flight_support;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use citystream_cli::bind_replay::BindReplayArgs;
use flight_support::{fresh_dir, stderr, tiny_city};

/// The tiny city flown in scratch `name` with its binds logged to `binds.log` there and
/// checked, with `args` after the fixed clock's, and a forced mip tail or none (whatever the
/// environment says); the run must succeed. Returns the log's path and the flight's stderr.
fn logged_flight(name: &str, args: &[&str], tail: Option<&str>) -> (PathBuf, String) {
    let dir = fresh_dir("bind_replay", name);
    let city = tiny_city(&dir);
    let log = dir.join("binds.log");
    let mut flight = Command::new(env!("CARGO_BIN_EXE_flythrough"));
    flight
        .args([
            "--dataset",
            city.to_str().expect("utf-8"),
            "--clock",
            "fixed",
            "--frame-interval",
            "0",
        ])
        .args(["--out", dir.join("run").to_str().expect("utf-8")])
        .args(args)
        .env("CITYSTREAM_BIND_LOG", &log)
        .env("CITYSTREAM_CHECK_BINDS", "1");
    with_tail(&mut flight, tail);
    let flight = flight.output().expect("run flythrough");
    assert!(flight.status.success(), "flythrough failed: {}", stderr(&flight));
    (log, stderr(&flight))
}

/// `citystream bind-replay LOG` with a forced mip tail or none, in a process of its own as
/// the binary runs it (the tail is read from the process's environment): this test binary
/// again, running only [`bind_replay_child`].
fn bind_replay(log: &Path, tail: Option<&str>) -> Output {
    let mut command = Command::new(std::env::current_exe().expect("the test binary"));
    command
        .args(["bind_replay_child", "--exact", "--ignored", "--nocapture"])
        .env(REPLAY_LOG_ENV, log);
    with_tail(&mut command, tail);
    command.output().expect("run bind-replay")
}

/// The log [`bind_replay_child`] replays.
const REPLAY_LOG_ENV: &str = "CITYSTREAM_TEST_BIND_REPLAY_LOG";

/// No test of its own: the process [`bind_replay`] starts, which runs `citystream
/// bind-replay` on the log its environment names and exits as the binary would (its
/// summary on stdout; `Error: …` on stderr and status 1 on failure).
#[test]
#[ignore = "run by bind_replay in a process of its own"]
fn bind_replay_child() {
    let Some(log) = std::env::var_os(REPLAY_LOG_ENV) else {
        return;
    };
    let args = BindReplayArgs {
        log: log.into(),
        no_check: false,
    };
    if let Err(e) = citystream_cli::bind_replay::run(&args) {
        eprintln!("Error: {e:?}");
        std::process::exit(1);
    }
}

/// The number of operations a log's `batch N …` line announces.
fn operations_in(batch_line: &str) -> usize {
    batch_line
        .split_whitespace()
        .nth(1)
        .and_then(|n| n.parse().ok())
        .expect("count")
}

fn with_tail(command: &mut Command, tail: Option<&str>) {
    match tail {
        Some(tail) => command.env("CITYSTREAM_FORCE_MIP_TAIL", tail),
        None => command.env_remove("CITYSTREAM_FORCE_MIP_TAIL"),
    };
}

#[test]
fn a_logged_flight_replays_and_an_injected_double_bind_is_refused() {
    // A budget below what the view needs, so levels are dropped: unbinds and rebinds;
    // block binds of every level (the tail has its own test below).
    let (log, _) = logged_flight(
        "flight",
        &[
            "--frames",
            "240",
            "--bind-latency",
            "desktop",
            "--psnr-interval",
            "0",
            "--memory-budget-mb",
            "1",
        ],
        None,
    );
    let dir = log.parent().expect("the scratch directory").to_path_buf();
    let text = std::fs::read_to_string(&log).expect("the bind log");
    let count = |kind: &str| text.lines().filter(|l| l.starts_with(kind)).count();
    let (batches, unbinds, copies) = (count("batch "), count("unbind "), count("copy "));
    assert!(
        batches > 1 && unbinds > 0 && copies > 0,
        "{batches} batches, {unbinds} unbinds, {copies} copies"
    );

    let replay = bind_replay(&log, None);
    assert!(replay.status.success(), "replay failed: {}", stderr(&replay));
    let said = String::from_utf8_lossy(&replay.stdout).into_owned();
    let operations = count("bind ") + unbinds;
    assert!(
        said.contains(&format!(
            "{batches} batches ({operations} block operations) and {copies} copies"
        )),
        "{said}"
    );

    // The first bound block bound again, on the same memory, right after its batch.
    let mut lines: Vec<&str> = text.lines().collect();
    let batch_at = lines.iter().position(|l| l.starts_with("batch ")).expect("a batch");
    let first_bind = lines[batch_at + 1];
    assert!(first_bind.starts_with("bind "), "{first_bind}");
    let operations_in_batch = operations_in(lines[batch_at]);
    let at = batch_at + 1 + operations_in_batch;
    lines.insert(at, first_bind);
    lines.insert(at, "batch 1 0");
    let injected = dir.join("injected.log");
    std::fs::write(&injected, lines.join("\n") + "\n").expect("write");
    let refused = bind_replay(&injected, None);
    assert!(!refused.status.success(), "a double bind replayed");
    let fields: Vec<&str> = first_bind.split_whitespace().collect();
    let named = format!(
        "image {} layer {} level {} block ({}, {})",
        fields[1], fields[2], fields[3], fields[4], fields[5]
    );
    let message = stderr(&refused);
    assert!(
        message.contains(&named) && message.contains("without an unbind"),
        "{message}"
    );
}

/// A flight on a device with per-layer mip tails (forced, lavapipe has none)
/// logs its tails (`bind-tail`, the image lines' tail fields); the replay
/// needs the same tail and runs the log; a tail bound twice and a per-block
/// bind into a tail level, injected, are refused naming image and layer.
#[test]
fn a_flight_with_mip_tails_logs_and_replays_them_and_tail_misuse_is_refused() {
    let (log, _) = logged_flight("tails", &["--frames", "90", "--psnr-interval", "0"], Some("3"));
    let dir = log.parent().expect("the scratch directory").to_path_buf();
    let text = std::fs::read_to_string(&log).expect("the bind log");
    let tail_binds: Vec<&str> = text.lines().filter(|l| l.starts_with("bind-tail ")).collect();
    assert!(
        !tail_binds.is_empty(),
        "no tail was bound:\n{}",
        &text[..text.len().min(2000)]
    );
    let image_line = text.lines().find(|l| l.starts_with("image ")).expect("an image line");
    let fields: Vec<&str> = image_line.split_whitespace().collect();
    assert_eq!(fields.len(), 13, "{image_line}");
    assert_eq!(
        (fields[10], fields[12]),
        ("3", "0"),
        "a per-layer tail from level 3: {image_line}"
    );

    let replayed = bind_replay(&log, Some("3"));
    assert!(replayed.status.success(), "replay failed: {}", stderr(&replayed));
    // Without the tail, the log's tail blocks mean nothing here.
    let no_tail = bind_replay(&log, None);
    assert!(!no_tail.status.success(), "replayed without the logging device's tail");
    assert!(
        stderr(&no_tail).contains("mip tail from level 3"),
        "{}",
        stderr(&no_tail)
    );

    // Inject a batch after the first one that holds a tail bind.
    let inject = |name: &str, op: String| {
        let mut lines: Vec<String> = text.lines().map(str::to_owned).collect();
        let first_tail = lines
            .iter()
            .position(|l| l.starts_with("bind-tail "))
            .expect("a tail bind");
        let batch_at = (0..first_tail)
            .rev()
            .find(|&i| lines[i].starts_with("batch "))
            .expect("its batch");
        let operations = operations_in(&lines[batch_at]);
        let at = batch_at + 1 + operations;
        lines.insert(at, op);
        lines.insert(at, "batch 1 0".to_owned());
        let path = dir.join(name);
        std::fs::write(&path, lines.join("\n") + "\n").expect("write");
        bind_replay(&path, Some("3"))
    };
    let tail: Vec<&str> = tail_binds[0].split_whitespace().collect();
    let twice = inject("tail-twice.log", tail_binds[0].to_owned());
    assert!(!twice.status.success(), "a tail bound twice replayed");
    let message = stderr(&twice);
    assert!(
        message.contains(&format!("mip tail of image {} layer {}", tail[1], tail[2]))
            && message.contains("bound again"),
        "{message}"
    );
    // Level 5 of the same layer, bound as if it were an ordinary block.
    let per_block = inject(
        "per-block.log",
        format!("bind {} {} 5 0 0 {} {}", tail[1], tail[2], tail[4], tail[5]),
    );
    assert!(
        !per_block.status.success(),
        "a per-block bind into a tail level replayed"
    );
    let message = stderr(&per_block);
    assert!(
        message.contains(&format!("image {} layer {} level 5", tail[1], tail[2])) && message.contains("mip tail"),
        "{message}"
    );
}

/// With the error reference on (PSNR, the default), the streamed cache alone writes the
/// bind log: the reference's binds do not interleave with it or truncate it, and the
/// log replays.
#[test]
fn a_log_written_beside_the_error_reference_replays() {
    let (log, said) = logged_flight("with_reference", &["--frames", "60", "--psnr-interval", "10"], None);
    assert!(said.contains("error reference's are not logged"), "{said}");
    let text = std::fs::read_to_string(&log).expect("the bind log");
    assert_eq!(text.matches("citystream-bind-log").count(), 1, "one writer, one header");
    let replay = bind_replay(&log, None);
    assert!(replay.status.success(), "replay failed: {}", stderr(&replay));
}
