#version 460
#extension GL_GOOGLE_include_directive : require
#include "citystream.glsl"

layout(set = 0, binding = BINDING_MESH_TEXTURES) uniform sampler2DArray textures;
layout(push_constant) uniform Push { DrawPush push; };

layout(location = 0) in vec2 in_uv;
layout(location = 1) in vec3 in_normal;
layout(location = 0) out vec4 out_color;

void main() {
    vec4 texel = texture(textures, vec3(in_uv, float(push.layer)));
    float lambert = 0.35 + 0.65 * max(dot(normalize(in_normal), normalize(push.light_dir_weight.xyz)), 0.0);
    float shade = mix(1.0, lambert, push.light_dir_weight.w);
    out_color = vec4(texel.rgb * push.tint.rgb * shade, 1.0);
}
