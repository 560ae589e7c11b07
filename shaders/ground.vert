#version 460
#extension GL_GOOGLE_include_directive : require
#include "citystream.glsl"

// The ground pass's one quad over the imagery's area, at the ground's height; no vertex
// buffer: six vertices, two triangles.
layout(push_constant) uniform Push { GroundPush push; };

layout(location = 0) out vec2 out_ground;

const vec2 CORNERS[6] = vec2[](vec2(0, 0), vec2(1, 0), vec2(1, 1), vec2(0, 0), vec2(1, 1), vec2(0, 1));

void main() {
    vec2 ground = mix(push.area.xy, push.area.zw, CORNERS[gl_VertexIndex]);
    out_ground = ground;
    vec4 clip = push.view_proj * vec4(ground.x, push.params.x, ground.y, 1.0);
    // Imagery drapes over the city's own ground surfaces at the same height: a bias of a
    // fixed fraction of the (reversed) depth makes it win there at every distance, where a
    // height offset would z-fight far away, and hides a wall's foot only `height × bias`
    // high.
    clip.z *= 1.0 + push.params.z;
    gl_Position = clip;
}
