//! The build script citystream-gen, citystream-cli and citystream-flythrough share
//! (`build = "../build.rs"`).
//!
//! intel_tex_2 (the BC7 encoder of `gen` and `import`) links a C++ object
//! of its ASTC kernels without naming the C++ runtime it needs; citystream-gen,
//! which uses it, links that runtime for every crate above it.
//!
//! The tests that need a tool the setup script installs (Xvfb, nginx, the S3
//! emulator, Slurm) compile as ignored, so the harness reports them as skipped, where
//! the tool is missing and the setup script has not run. Once it ran, a
//! missing tool fails them.

use std::path::{Path, PathBuf};

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    if std::env::var("CARGO_CFG_TARGET_OS").as_deref() == Ok("linux") {
        println!("cargo:rustc-link-lib=dylib=stdc++");
    }
    for var in ["PATH", "CITYSTREAM_SETUP_STAMP_DIR", "CITYSTREAM_S3_EMULATOR_DIR"] {
        println!("cargo:rerun-if-env-changed={var}");
    }
    let stamp_dir =
        std::env::var_os("CITYSTREAM_SETUP_STAMP_DIR").map_or_else(|| "/var/lib/citystream".into(), PathBuf::from);
    let setup_ran = watch(&[stamp_dir.join("setup-v6")], 2);
    let on_path = |name: &str| -> Vec<PathBuf> {
        std::env::var_os("PATH")
            .map(|path| std::env::split_paths(&path).map(|dir| dir.join(name)).collect())
            .unwrap_or_default()
    };
    let s3_dir = std::env::var_os("CITYSTREAM_S3_EMULATOR_DIR")
        .map_or_else(|| "/opt/citystream/s3-emulator".into(), PathBuf::from);
    // (cfg, where the tool may be, how many folders up to watch while it is missing)
    let tools = [
        ("citystream_skip_xvfb", on_path("Xvfb"), 1),
        // Where `citystream_testing::nginx::binary` looks.
        (
            "citystream_skip_nginx",
            vec!["/usr/sbin/nginx".into(), "/usr/bin/nginx".into()],
            1,
        ),
        // Where `citystream_testing::s3_emulator::binary` looks; setup creates its folders.
        ("citystream_skip_s3", vec![s3_dir.join("bin").join("moto_server")], 3),
        // What `tools/scripts/slurm-local.sh` starts.
        ("citystream_skip_slurm", vec!["/usr/sbin/slurmctld".into()], 1),
    ];
    for (cfg, candidates, levels) in tools {
        println!("cargo:rustc-check-cfg=cfg({cfg})");
        if !watch(&candidates, levels) && !setup_ran {
            println!("cargo:rustc-cfg={cfg}");
        }
    }
}

/// Whether any of `paths` exists. Asks cargo to run this script again when
/// the one found changes or, while none exists, when something appears in the
/// nearest existing folder at most `levels` above each (a watched path that is
/// missing would rerun every build; a watched folder is scanned whole, so the
/// levels stay few).
fn watch(paths: &[PathBuf], levels: usize) -> bool {
    if let Some(found) = paths.iter().find(|path| path.exists()) {
        println!("cargo:rerun-if-changed={}", found.display());
        return true;
    }
    for path in paths {
        if let Some(folder) = path
            .ancestors()
            .skip(1)
            .take(levels)
            .find(|a| a.is_dir() && *a != Path::new("/"))
        {
            println!("cargo:rerun-if-changed={}", folder.display());
        }
    }
    false
}
