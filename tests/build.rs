//! A host's build script, as docs/EMBEDDING.md ("Shaders") quotes it: it reads
//! the include directory the engine's build script publishes
//! (`links = "citystream"`) and compiles the example host's visible shader
//! against it, so a test can check the metadata and the SPIR-V it made.

use std::path::PathBuf;

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-env-changed=DEP_CITYSTREAM_INCLUDE");
    let manifest = PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR"));
    let glsl_path = manifest.join("../engine/examples/embed_host/shaders/host_visible.frag");

    let include = std::env::var("DEP_CITYSTREAM_INCLUDE").expect("citystream-engine publishes it");
    let out_dir = PathBuf::from(std::env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"));
    let spv_path = out_dir.join("host_visible.frag.spv");
    println!("cargo:rerun-if-changed={}", glsl_path.display());
    println!("cargo:rerun-if-changed={include}");
    let status = std::process::Command::new("glslangValidator")
        .args(["--target-env", "vulkan1.3"])
        .arg(format!("-I{include}"))
        .arg("-o")
        .arg(&spv_path)
        .arg(&glsl_path)
        .status()
        .expect("glslangValidator on PATH");
    assert!(status.success(), "glslangValidator failed on {}", glsl_path.display());

    println!("cargo:rustc-env=CITYSTREAM_HOST_INCLUDE={include}");
    println!("cargo:rustc-env=CITYSTREAM_HOST_SPV={}", spv_path.display());
}
