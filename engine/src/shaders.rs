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
shader!(TEXTURE_ID_FRAG, "texture_id.frag", "texture_id_frag.spv");
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
shader!(CITY_FRAG_ARRAYS, "city.frag", "city_frag_arrays.spv");
shader!(
    TEXTURE_PROBE_COMP_ARRAYS,
    "texture_probe.comp",
    "texture_probe_comp_arrays.spv"
);

/// `sparse` where `device` holds textures in sparse images, else
/// `arrays`: the same shader compiled with `CITYSTREAM_NO_SPARSE`, which a
/// device without `shaderResourceResidency` accepts.
pub fn for_backing(device: &crate::device::Device, sparse: ShaderSource, arrays: ShaderSource) -> ShaderSource {
    match device.texture_backing() {
        crate::device::TextureBacking::Sparse => sparse,
        crate::device::TextureBacking::Arrays => arrays,
    }
}

/// Every embedded shader, for tests that inspect them all.
pub const ALL: &[ShaderSource] = &[
    CITY_VERT,
    CITY_FRAG,
    CITY_TREE_VERT,
    DEPTH_ONLY_FRAG,
    TEXTURE_ID_FRAG,
    GROUND_VERT,
    GROUND_FRAG,
    FEEDBACK_FRAG,
    MESH_VERT,
    MESH_FRAG,
    FEEDBACK_COMPACT_COMP,
    CITY_CULL_COMP,
    SPARSE_PROBE_COMP,
    TEXTURE_PROBE_COMP,
    CITY_FRAG_ARRAYS,
    TEXTURE_PROBE_COMP_ARRAYS,
];

#[cfg(test)]
mod tests {
    use super::*;

    /// `OpCapability SparseResidency` (opcode 17, capability 41) in `shader`'s SPIR-V.
    fn declares_sparse_residency(shader: &ShaderSource) -> bool {
        const OP_CAPABILITY: u32 = 17;
        const SPARSE_RESIDENCY: u32 = 41;
        let words: Vec<u32> = shader
            .spirv
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        // After the five-word header, each instruction's first word holds its length
        // (high half) and opcode (low half).
        let mut at = 5;
        while let Some(&first) = words.get(at) {
            let length = (first >> 16) as usize;
            if first & 0xffff == OP_CAPABILITY && words.get(at + 1) == Some(&SPARSE_RESIDENCY) {
                return true;
            }
            at += length.max(1);
        }
        false
    }

    /// A device without sparse residency accepts every shader but the two that
    /// sample the sparse cache, which have variants for it, and the probe of
    /// sparse images themselves.
    #[test]
    fn only_the_sparse_samplers_need_shader_resource_residency() {
        let sparse = [CITY_FRAG.spirv, TEXTURE_PROBE_COMP.spirv, SPARSE_PROBE_COMP.spirv];
        for shader in ALL {
            let expected = sparse.contains(&shader.spirv);
            assert_eq!(declares_sparse_residency(shader), expected, "{}", shader.name);
        }
    }
}
