//! The fuzz harnesses in a short, fixed-seed run (the long runs are documented in
//! docs/TOOLS.md, "Fuzzing"): every parser sees mutated inputs, none panics, hangs or
//! over-allocates.

use std::process::Command;

#[test]
fn every_harness_survives_a_short_fixed_seed_campaign() {
    let out = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("fuzz-short");
    let _ = std::fs::remove_dir_all(&out);
    let output = Command::new(env!("CARGO_BIN_EXE_fuzz"))
        .args(["--inputs", "3000", "--seed", "7", "--hang-s", "20", "--out"])
        .arg(&out)
        .output()
        .expect("fuzz runs");
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "fuzzing found failures:\n{stdout}\n{stderr}");
    let rows: Vec<Vec<&str>> = stdout
        .lines()
        .filter(|l| l.starts_with("| ") && !l.starts_with("| target"))
        .map(|l| l.trim_matches('|').split('|').map(str::trim).collect())
        .collect();
    let targets: Vec<&str> = rows.iter().map(|r| r[0]).collect();
    assert_eq!(
        targets,
        ["dataset", "path", "gltf", "texture", "patches", "remote", "tileset"],
        "{stdout}"
    );
    for row in &rows {
        let number = |i: usize| {
            row[i]
                .parse::<u64>()
                .unwrap_or_else(|_| panic!("column {i} of {row:?}"))
        };
        assert_eq!(number(1), 3000, "{row:?}");
        assert_eq!(number(1), number(2) + number(3) + number(4), "{row:?}");
        // Mutations are both refused and (where they touch nothing that matters) accepted.
        assert!(number(2) > 0 && number(3) > 0, "{row:?}");
        assert_eq!((number(4), number(5)), (0, 0), "panics or over-allocations: {row:?}");
    }
}

#[test]
fn bad_options_are_refused() {
    for args in [
        &["--hang-s", "0"][..],
        &["--hang-s", "NaN"],
        &["--time-limit-s", "0"],
        &["--target", "everything"],
        &["--inputs", "many"],
    ] {
        let output = Command::new(env!("CARGO_BIN_EXE_fuzz"))
            .args(args)
            .output()
            .expect("fuzz runs");
        assert!(!output.status.success(), "{args:?} accepted");
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(stderr.contains(args[0]), "{args:?}: {stderr}");
    }
}

#[test]
fn inputs_that_once_failed_stay_fixed() {
    // tools/test-data/fuzz holds inputs the harnesses found failing (panics inside the gltf
    // crate, a 136-byte DDS that made the decoder allocate 432 MiB, Draco and Basis files that
    // made their decoders allocate gigabytes or panic); each must now finish with a small
    // heap: a plain error, or (a damaged Draco value that now wraps as the reference
    // decoder's does) a mesh of damaged values.
    let corpus = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../test-data/fuzz");
    let mut files: Vec<_> = std::fs::read_dir(&corpus)
        .expect("corpus")
        .map(|e| e.expect("entry").path())
        .collect();
    files.sort();
    assert!(files.len() >= 6);
    let out = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("fuzz-replay");
    let output = Command::new(env!("CARGO_BIN_EXE_fuzz"))
        .arg("--out")
        .arg(&out)
        .arg("--replay")
        .args(&files)
        .output()
        .expect("fuzz runs");
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert_eq!(stdout.lines().count(), files.len(), "{stdout}");
    for line in stdout.lines() {
        assert!(
            line.contains(": Rejected; heap growth ")
                || (line.contains("draco") && line.contains(": Accepted; heap growth ")),
            "{line}"
        );
        let kib: f64 = line
            .split("heap growth ")
            .nth(1)
            .and_then(|rest| rest.split(' ').next())
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("no heap growth in {line}"));
        assert!(kib < 1024.0, "{line}");
    }
}
