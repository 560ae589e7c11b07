#version 460

// Depth pre-pass of the feedback: writes depth only, so the feedback pass
// after it runs for the nearest surface alone.

// city.vert's outputs, declared (not read) so the stage interfaces match.
layout(location = 0) in vec2 in_uv;
layout(location = 1) in vec3 in_normal;
layout(location = 2) flat in uint in_mesh_id;

void main() {
}
