#version 460
#extension GL_GOOGLE_include_directive : require
#include "citystream.glsl"

// The texture each pixel shows, for attributing a frame's image error by
// cause (docs/CONTROLLER.md): texture id + 1 in the red, green and blue
// bytes of an RGBA8 UNORM target, so 0 is a pixel no city mesh covers. Each
// byte k is written as (k + 0.25) / 255: it converts back to k whether the
// device rounds float-to-unorm conversions to nearest or toward zero.
layout(std430, set = 0, binding = BINDING_CITY_MESHES) readonly buffer CityMeshes { CityMeshInfo city_meshes[]; };

layout(location = 0) in vec2 in_uv;
layout(location = 1) in vec3 in_normal;
layout(location = 2) flat in uint in_mesh_id;
layout(location = 0) out vec4 out_color;

void main() {
    uint id = city_meshes[in_mesh_id].texture_id + 1u;
    vec3 bytes = vec3(float(id & 0xFFu), float((id >> 8) & 0xFFu), float((id >> 16) & 0xFFu));
    out_color = vec4((bytes + 0.25) / 255.0, 1.0);
}
