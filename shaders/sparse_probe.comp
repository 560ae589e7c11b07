#version 460
#extension GL_GOOGLE_include_directive : require
#extension GL_ARB_sparse_texture2 : require
#include "citystream.glsl"

// Samples a sparse image at explicit LODs and reports value and residency:
// the engine's check that bound blocks read back what was copied in and
// unbound ones report non-resident.
layout(local_size_x = 64) in;

layout(set = 0, binding = BINDING_PROBE_TEXTURE) uniform sampler2DArray sparse_texture;
layout(std430, set = 0, binding = BINDING_PROBE_POINTS) readonly buffer Points { ProbePoint points[]; };
layout(std430, set = 0, binding = BINDING_PROBE_RESULTS) writeonly buffer Results { ProbeResult results[]; };

void main() {
    uint i = gl_GlobalInvocationID.x;
    if (i >= points.length()) {
        return;
    }
    ProbePoint p = points[i];
    vec4 value = vec4(0.0);
    int code = sparseTextureLodARB(sparse_texture, vec3(p.uv, p.layer), p.lod, value);
    results[i].value = value;
    results[i].resident = sparseTexelsResidentARB(code) ? 1u : 0u;
    results[i].raw_code = code;
}
