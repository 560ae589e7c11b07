#version 460
#extension GL_GOOGLE_include_directive : require
#include "citystream.glsl"

// Compaction (paper §3.3): append every mesh whose summed weight reaches tau
// to a dense array through an atomic counter, and reset the sparse per-mesh
// array for the next frame. Only the counter and the dense entries are read
// back to the host.
layout(local_size_x = 256) in;

layout(std430, set = 0, binding = BINDING_COMPACT_SPARSE) buffer Sparse { MeshFeedback meshes[]; };
layout(std430, set = 0, binding = BINDING_COMPACT_DENSE) writeonly buffer Dense { FeedbackEntry entries[]; };
layout(std430, set = 0, binding = BINDING_COMPACT_COUNTER) buffer Counter { FeedbackCounter counter; };
layout(push_constant) uniform Push { CompactPush push; };

void main() {
    // Two-dimensional dispatch so arrays beyond 65535 workgroups fit.
    uint i = gl_GlobalInvocationID.x + gl_GlobalInvocationID.y * gl_NumWorkGroups.x * gl_WorkGroupSize.x;
    if (i >= push.mesh_count) {
        return;
    }
    MeshFeedback m = meshes[i];
    if (m.min_mip != FEEDBACK_UNSEEN && m.weight >= push.tau) {
        uint slot = atomicAdd(counter.count, 1u);
        if (slot < push.capacity) {
            entries[slot] = FeedbackEntry(m.min_mip, m.weight, i);
        } else {
            atomicAdd(counter.dropped, 1u);
        }
    }
    meshes[i] = MeshFeedback(FEEDBACK_UNSEEN, 0u);
}
