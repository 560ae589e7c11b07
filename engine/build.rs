//! Compiles every GLSL shader in `shaders/` to SPIR-V (Vulkan 1.2 target)
//! with `glslangValidator` and checks the result with `spirv-val`, and the
//! example host's own shaders (`examples/embed_host/shaders/`, prefixed
//! `embed_host_`), which include citystream's GLSL as any host's would. A
//! compile error fails the build with glslang's message and the file name.
//! Both tools must be on PATH (Debian: glslang-tools, spirv-tools).

use std::path::{Path, PathBuf};
use std::process::Command;

const STAGES: &[&str] = &["vert", "frag", "comp"];

fn main() {
    let manifest = PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR"));
    let shader_dir = manifest.join("../shaders");
    let include_dir = shader_dir.join("include");
    let out_dir = PathBuf::from(std::env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"));
    println!("cargo:rerun-if-changed={}", shader_dir.display());
    println!("cargo:rerun-if-changed={}", include_dir.display());
    // Build metadata for the build scripts of crates that depend on this one
    // (`links = "citystream"`): they read it as DEP_CITYSTREAM_INCLUDE.
    let include_abs = include_dir.canonicalize().unwrap_or_else(|_| include_dir.clone());
    println!("cargo:include={}", include_abs.display());

    let mut sources: Vec<PathBuf> = std::fs::read_dir(&shader_dir)
        .unwrap_or_else(|e| panic!("cannot read shader directory {}: {e}", shader_dir.display()))
        .filter_map(|entry| entry.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| STAGES.contains(&e))
        })
        .collect();
    sources.sort();
    for entry in std::fs::read_dir(&include_dir).into_iter().flatten().flatten() {
        println!("cargo:rerun-if-changed={}", entry.path().display());
    }

    let example_dir = manifest.join("examples/embed_host/shaders");
    println!("cargo:rerun-if-changed={}", example_dir.display());
    let mut example_sources: Vec<PathBuf> = std::fs::read_dir(&example_dir)
        .into_iter()
        .flatten()
        .filter_map(|entry| entry.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| STAGES.contains(&e))
        })
        .collect();
    example_sources.sort();

    let mut failures = Vec::new();
    let all = sources
        .iter()
        .map(|s| (s, ""))
        .chain(example_sources.iter().map(|s| (s, "embed_host_")));
    for (source, prefix) in all {
        println!("cargo:rerun-if-changed={}", source.display());
        if let Err(message) = compile(source, &include_dir, &out_dir, prefix) {
            failures.push(message);
        }
    }
    if !failures.is_empty() {
        for failure in &failures {
            eprintln!("{failure}");
        }
        panic!(
            "{} shader(s) failed to compile:\n{}",
            failures.len(),
            failures.join("\n")
        );
    }
}

fn spv_name(source: &Path, prefix: &str) -> String {
    let file = source
        .file_name()
        .and_then(|n| n.to_str())
        .expect("shader names are UTF-8");
    format!("{prefix}{}.spv", file.replace('.', "_"))
}

fn compile(source: &Path, include_dir: &Path, out_dir: &Path, prefix: &str) -> Result<(), String> {
    let output_path = out_dir.join(spv_name(source, prefix));
    let output = Command::new("glslangValidator")
        .arg("--target-env")
        .arg("vulkan1.2")
        .arg(format!("-I{}", include_dir.display()))
        .arg("-o")
        .arg(&output_path)
        .arg(source)
        .output()
        .map_err(|e| {
            format!(
                "cannot run glslangValidator for {} ({e}); install it with `make setup` (Debian package glslang-tools)",
                source.display()
            )
        })?;
    if !output.status.success() {
        return Err(format!(
            "glslangValidator failed on {}:\n{}{}",
            source.display(),
            String::from_utf8_lossy(&output.stdout),
            String::from_utf8_lossy(&output.stderr)
        ));
    }
    let validation = Command::new("spirv-val")
        .arg("--target-env")
        .arg("vulkan1.2")
        .arg(&output_path)
        .output()
        .map_err(|e| {
            format!(
                "cannot run spirv-val for {} ({e}); install Debian package spirv-tools",
                source.display()
            )
        })?;
    if !validation.status.success() {
        return Err(format!(
            "spirv-val rejected {} (from {}):\n{}{}",
            output_path.display(),
            source.display(),
            String::from_utf8_lossy(&validation.stdout),
            String::from_utf8_lossy(&validation.stderr)
        ));
    }
    Ok(())
}
