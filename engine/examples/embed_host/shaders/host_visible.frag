#version 460
#extension GL_GOOGLE_include_directive : require
// Sampling sparse images needs it; the texture-array variant (-DCITYSTREAM_NO_SPARSE) does not.
#ifndef CITYSTREAM_NO_SPARSE
#extension GL_ARB_sparse_texture2 : require
#endif
#define CITYSTREAM_SET 1
#include "citystream_host.glsl"

// The host's visible pass: streamed texture, blended with the City
// Colormap by displayed level (Eq. 8), then the host's own fog.
layout(push_constant) uniform Push {
    mat4 view_proj;
    vec4 params;
} push;

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
    vec3 colour = citystream_shade(mesh.texture, in_uv, uvec2(mesh.width, mesh.height), false);
    // params.z: the distance at which the host's fog is strongest.
    float fog = clamp((1.0 / gl_FragCoord.w) / push.params.z, 0.0, 0.6);
    out_color = vec4(mix(colour, vec3(0.55, 0.7, 0.9), fog), 1.0);
}
