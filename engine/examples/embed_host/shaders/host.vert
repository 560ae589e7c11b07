#version 460
// The example host's own vertex stage: its own vertex layout and push
// constants; nothing here is citystream's.
layout(location = 0) in vec3 in_position;
layout(location = 1) in vec2 in_uv;
layout(location = 2) in uint in_mesh;

layout(push_constant) uniform Push {
    mat4 view_proj;
    vec4 params;  // x: log2 visible pixels per pixel of this pass, y: foreground distance
} push;

layout(location = 0) out vec2 out_uv;
layout(location = 1) flat out uint out_mesh;

invariant gl_Position;

void main() {
    gl_Position = push.view_proj * vec4(in_position, 1.0);
    out_uv = in_uv;
    out_mesh = in_mesh;
}
