//! Reads the include directory the engine's build script publishes
//! (`links = "citystream"`) as a host's build script would, so a test can
//! check that the metadata names citystream's GLSL includes.

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-env-changed=DEP_CITYSTREAM_INCLUDE");
    let include = std::env::var("DEP_CITYSTREAM_INCLUDE").unwrap_or_default();
    println!("cargo:rustc-env=CITYSTREAM_HOST_INCLUDE={include}");
}
