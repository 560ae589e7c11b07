//! `tools/scripts/gpu-check.sh` empties its scratch folder on every run: only a folder it
//! made itself (or an empty one) is ever taken.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The repository's root.
fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn scratch(name: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR"))
        .join("gpu-check-script")
        .join(name);
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("scratch directory");
    dir
}

/// The check with `GPU_CHECK_WORK=work`, a 1 s budget and its results under `dir`.
fn gpu_check(work: &Path, dir: &Path, home: &Path) -> Output {
    Command::new("bash")
        .arg("tools/scripts/gpu-check.sh")
        .current_dir(root())
        .env("GPU_CHECK_WORK", work)
        .env("GPU_CHECK_BUDGET_S", "1")
        .env("GPU_CHECK_PYTHON", "none")
        .env("GPU_CHECK_PACK", dir.join("no-pack"))
        .env("GPU_CHECK_DATA", dir.join("data"))
        .env("OUT", dir.join("out"))
        .env("HOME", home)
        .output()
        .expect("bash runs")
}

#[test]
fn a_scratch_folder_holding_files_the_check_did_not_make_is_refused_untouched() {
    let dir = scratch("refused");
    // The pack's folder (its binaries cannot be rebuilt on the GPU machine) and a home
    // directory, both given as scratch.
    let pack = dir.join(".gpu-check");
    let home = dir.join("home");
    for folder in [&pack, &home] {
        std::fs::create_dir_all(folder.join("bin")).expect("bin");
        std::fs::write(folder.join("bin/citystream"), b"keep me").expect("written");
    }
    for work in [pack.clone(), home.clone()] {
        let run = gpu_check(&work, &dir, &home);
        let stderr = String::from_utf8_lossy(&run.stderr);
        assert_eq!(run.status.code(), Some(2), "{}: {stderr}", work.display());
        assert!(stderr.contains("holds files this check did not make"), "{stderr}");
        assert_eq!(
            std::fs::read(work.join("bin/citystream")).expect("bin/ kept"),
            b"keep me",
            "{}",
            work.display()
        );
    }
}

#[test]
fn a_new_scratch_folder_is_marked_and_taken_again() {
    let dir = scratch("marked");
    let work = dir.join("work");
    let run = gpu_check(&work, &dir, &dir);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!stderr.contains("holds files this check did not make"), "{stderr}");
    assert!(work.join(".citystream-gpu-check-work").is_file(), "{stderr}");
    // What the first run left is the check's own: the second run takes the folder.
    let again = gpu_check(&work, &dir, &dir);
    let stderr = String::from_utf8_lossy(&again.stderr);
    assert!(!stderr.contains("holds files this check did not make"), "{stderr}");
    assert_ne!(again.status.code(), Some(2), "{stderr}");
}
