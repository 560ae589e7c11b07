//! Compiles every GLSL shader in `shaders/` to SPIR-V (Vulkan 1.2 target)
//! with `glslangValidator` and checks the result with `spirv-val`, and the
//! example host's own shaders (`examples/embed_host/shaders/`, prefixed
//! `embed_host_`), which include citystream's GLSL as any host's would. A
//! compile error fails the build with glslang's message and the file name.
//! Both tools must be on PATH (Debian: glslang-tools, spirv-tools).

use std::path::{Path, PathBuf};
use std::process::Command;

const STAGES: &[&str] = &["vert", "frag", "comp"];

/// Shaders that sample the texture cache, compiled a second time with
/// `CITYSTREAM_NO_SPARSE` defined (`*_arrays.spv`) for devices without sparse
/// residency, whose SPIR-V must not declare the SparseResidency capability
/// (the feedback pass reads the table only, so it has none either way).
const SPARSE_SAMPLERS: &[&str] = &["city.frag", "texture_probe.comp"];

/// The example host's shaders that sample the cache, likewise.
const EXAMPLE_SPARSE_SAMPLERS: &[&str] = &["host_visible.frag"];

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

    let sources = shader_sources(&shader_dir)
        .unwrap_or_else(|e| panic!("cannot read shader directory {}: {e}", shader_dir.display()));
    for entry in std::fs::read_dir(&include_dir).into_iter().flatten().flatten() {
        println!("cargo:rerun-if-changed={}", entry.path().display());
    }

    let example_dir = manifest.join("examples/embed_host/shaders");
    println!("cargo:rerun-if-changed={}", example_dir.display());
    // The example is optional in a packaged crate.
    let example_sources = shader_sources(&example_dir).unwrap_or_default();

    let mut failures = Vec::new();
    let all = sources
        .iter()
        .map(|s| (s, ""))
        .chain(example_sources.iter().map(|s| (s, "embed_host_")));
    for (source, prefix) in all {
        println!("cargo:rerun-if-changed={}", source.display());
        let output = out_dir.join(spv_name(source, prefix, ""));
        if let Err(message) = compile(source, &include_dir, &output, &[]) {
            failures.push(message);
        }
        let file = source.file_name().and_then(|n| n.to_str()).unwrap_or_default();
        let samples = if prefix.is_empty() {
            SPARSE_SAMPLERS.contains(&file)
        } else {
            EXAMPLE_SPARSE_SAMPLERS.contains(&file)
        };
        if samples {
            let output = out_dir.join(spv_name(source, prefix, "_arrays"));
            if let Err(message) = compile(source, &include_dir, &output, &["CITYSTREAM_NO_SPARSE"]) {
                failures.push(message);
            }
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

/// The shader sources (one of `STAGES` as extension) in `dir`, sorted.
fn shader_sources(dir: &Path) -> std::io::Result<Vec<PathBuf>> {
    let mut sources: Vec<PathBuf> = std::fs::read_dir(dir)?
        .filter_map(|entry| entry.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| STAGES.contains(&e))
        })
        .collect();
    sources.sort();
    Ok(sources)
}

fn spv_name(source: &Path, prefix: &str, suffix: &str) -> String {
    let file = source
        .file_name()
        .and_then(|n| n.to_str())
        .expect("shader names are UTF-8");
    format!("{prefix}{}{suffix}.spv", file.replace('.', "_"))
}

fn compile(source: &Path, include_dir: &Path, output_path: &Path, defines: &[&str]) -> Result<(), String> {
    let mut glslang = Command::new("glslangValidator");
    glslang
        .arg("--target-env")
        .arg("vulkan1.2")
        .arg(format!("-I{}", include_dir.display()))
        .args(defines.iter().map(|name| format!("-D{name}")))
        .arg("-o")
        .arg(output_path)
        .arg(source);
    run_tool(&mut glslang, "glslang-tools", source, || {
        format!("glslangValidator failed on {}", source.display())
    })?;
    let mut spirv_val = Command::new("spirv-val");
    spirv_val.arg("--target-env").arg("vulkan1.2").arg(output_path);
    run_tool(&mut spirv_val, "spirv-tools", source, || {
        format!(
            "spirv-val rejected {} (from {})",
            output_path.display(),
            source.display()
        )
    })
}

/// Runs `command` (a tool from Debian package `package`) on `source`; on
/// failure, `failed()` and everything the tool printed.
fn run_tool(
    command: &mut Command,
    package: &str,
    source: &Path,
    failed: impl FnOnce() -> String,
) -> Result<(), String> {
    let tool = command.get_program().to_string_lossy().into_owned();
    let output = command.output().map_err(|e| {
        format!(
            "cannot run {tool} for {} ({e}); install it with `make setup` (Debian package {package})",
            source.display()
        )
    })?;
    if !output.status.success() {
        return Err(format!(
            "{}:\n{}{}",
            failed(),
            String::from_utf8_lossy(&output.stdout),
            String::from_utf8_lossy(&output.stderr)
        ));
    }
    Ok(())
}
