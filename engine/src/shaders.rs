//! SPIR-V compiled from `shaders/` at build time (see `build.rs`).

/// citystream's GLSL include directory, for hosts that compile their own
/// shaders against `citystream_host.glsl` (`glslangValidator -I`) at run
/// time. A host's build script gets the same path from cargo as the
/// environment variable `DEP_CITYSTREAM_INCLUDE`.
pub const INCLUDE_DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../shaders/include");

/// One embedded shader.
#[derive(Clone, Copy, Debug)]
pub struct ShaderSource {
    /// The GLSL file it was compiled from.
    pub name: &'static str,
    /// SPIR-V bytes.
    pub spirv: &'static [u8],
}

macro_rules! shader {
    ($ident:ident, $file:literal, $spv:literal) => {
        #[doc = concat!("`shaders/", $file, "`.")]
        pub const $ident: ShaderSource = ShaderSource {
            name: $file,
            spirv: include_bytes!(concat!(env!("OUT_DIR"), "/", $spv)),
        };
    };
}

shader!(CITY_VERT, "city.vert", "city_vert.spv");
shader!(CITY_FRAG, "city.frag", "city_frag.spv");
shader!(CITY_TREE_VERT, "city_tree.vert", "city_tree_vert.spv");
shader!(DEPTH_ONLY_FRAG, "depth_only.frag", "depth_only_frag.spv");
shader!(GROUND_VERT, "ground.vert", "ground_vert.spv");
shader!(GROUND_FRAG, "ground.frag", "ground_frag.spv");
shader!(FEEDBACK_FRAG, "feedback.frag", "feedback_frag.spv");
shader!(MESH_VERT, "mesh.vert", "mesh_vert.spv");
shader!(MESH_FRAG, "mesh.frag", "mesh_frag.spv");
shader!(
    FEEDBACK_COMPACT_COMP,
    "feedback_compact.comp",
    "feedback_compact_comp.spv"
);
shader!(CITY_CULL_COMP, "city_cull.comp", "city_cull_comp.spv");
shader!(TEXTURE_PROBE_COMP, "texture_probe.comp", "texture_probe_comp.spv");
shader!(SPARSE_PROBE_COMP, "sparse_probe.comp", "sparse_probe_comp.spv");

/// Every embedded shader, for tests that inspect them all.
pub const ALL: &[ShaderSource] = &[
    CITY_VERT,
    CITY_FRAG,
    CITY_TREE_VERT,
    DEPTH_ONLY_FRAG,
    GROUND_VERT,
    GROUND_FRAG,
    FEEDBACK_FRAG,
    MESH_VERT,
    MESH_FRAG,
    FEEDBACK_COMPACT_COMP,
    CITY_CULL_COMP,
    SPARSE_PROBE_COMP,
    TEXTURE_PROBE_COMP,
];
