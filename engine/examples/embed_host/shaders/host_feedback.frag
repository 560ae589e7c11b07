#version 460
#extension GL_GOOGLE_include_directive : require
#extension GL_ARB_sparse_texture2 : require
// citystream's bindings go to set 1; set 0 is the host's own.
#define CITYSTREAM_SET 1
#include "citystream_host.glsl"

// The host's feedback pass: each fragment tells citystream what its mesh needs.
layout(early_fragment_tests) in;

layout(push_constant) uniform Push {
    mat4 view_proj;
    vec4 params;
} push;

// The host's own per-mesh data.
struct HostMesh {
    uint texture;
    uint width;
    uint height;
    uint pad;
};
layout(std430, set = 0, binding = 0) readonly buffer HostMeshes { HostMesh host_meshes[]; };

layout(location = 0) in vec2 in_uv;
layout(location = 1) flat in uint in_mesh;
layout(location = 0) out vec4 out_color;

void main() {
    HostMesh mesh = host_meshes[in_mesh];
    citystream_write_feedback(in_mesh, mesh.texture, in_uv, uvec2(mesh.width, mesh.height), push.params.x,
                              1.0 / gl_FragCoord.w, push.params.y, true);
    out_color = vec4(1.0);
}
