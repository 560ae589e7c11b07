//! intel_tex_2 (the BC7 encoder of `gen` and `import`) links a C++ object
//! of its ASTC kernels without naming the C++ runtime it needs.

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    if std::env::var("CARGO_CFG_TARGET_OS").as_deref() == Ok("linux") {
        println!("cargo:rustc-link-lib=dylib=stdc++");
    }
}
