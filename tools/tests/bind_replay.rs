//! A flight's sparse binds and copies logged with `CITYSTREAM_BIND_LOG` and
//! replayed with `citystream bind-replay`, bind checker on: the replay runs
//! exactly the logged batches and copies, and a log with a double bind
//! injected is refused naming the block.

mod cli_support;

use std::process::Command;

use cli_support::{citystream, fresh_dir, stderr};

#[test]
fn a_logged_flight_replays_and_an_injected_double_bind_is_refused() {
    let dir = fresh_dir("bind_replay", "flight");
    let city = dir.join("city");
    let out = citystream(&["gen", "--preset", "tiny", "--out", city.to_str().expect("utf-8")]);
    assert!(out.status.success(), "gen failed: {}", stderr(&out));
    let log = dir.join("binds.log");
    // A budget below what the view needs, so levels are dropped: unbinds and rebinds.
    let flight = Command::new(env!("CARGO_BIN_EXE_flythrough"))
        .args([
            "--dataset",
            city.to_str().expect("utf-8"),
            "--frames",
            "240",
            "--clock",
            "fixed",
        ])
        .args([
            "--bind-latency",
            "desktop",
            "--frame-interval",
            "0",
            "--psnr-interval",
            "0",
        ])
        .args([
            "--memory-budget-mb",
            "1",
            "--out",
            dir.join("run").to_str().expect("utf-8"),
        ])
        .env("CITYSTREAM_BIND_LOG", &log)
        .env("CITYSTREAM_CHECK_BINDS", "1")
        .output()
        .expect("run flythrough");
    assert!(flight.status.success(), "flythrough failed: {}", stderr(&flight));
    let text = std::fs::read_to_string(&log).expect("the bind log");
    let count = |kind: &str| text.lines().filter(|l| l.starts_with(kind)).count();
    let (batches, unbinds, copies) = (count("batch "), count("unbind "), count("copy "));
    assert!(
        batches > 1 && unbinds > 0 && copies > 0,
        "{batches} batches, {unbinds} unbinds, {copies} copies"
    );

    let replay = citystream(&["bind-replay", log.to_str().expect("utf-8")]);
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
    let operations_in_batch: usize = lines[batch_at]
        .split_whitespace()
        .nth(1)
        .and_then(|n| n.parse().ok())
        .expect("count");
    let at = batch_at + 1 + operations_in_batch;
    lines.insert(at, first_bind);
    lines.insert(at, "batch 1 0");
    let injected = dir.join("injected.log");
    std::fs::write(&injected, lines.join("\n") + "\n").expect("write");
    let refused = citystream(&["bind-replay", injected.to_str().expect("utf-8")]);
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
