#version 460
#extension GL_GOOGLE_include_directive : require
#include "citystream.glsl"

// The texture each pixel shows, for attributing a frame's image error by
// cause (docs/CONTROLLER.md): texture id + 1 in the red, green and blue
// bytes of an RGBA8 UNORM target (k / 255 converts back to k exactly), so
// 0 is a pixel no city mesh covers.
layout(std430, set = 0, binding = BINDING_CITY_MESHES) readonly buffer CityMeshes { CityMeshInfo city_meshes[]; };

layout(location = 0) in vec2 in_uv;
layout(location = 1) in vec3 in_normal;
layout(location = 2) flat in uint in_mesh_id;
layout(location = 0) out vec4 out_color;

void main() {
    uint id = (city_meshes[in_mesh_id].texture_id + 1u) & 0xFFFFFFu;
    out_color = unpackUnorm4x8(id | 0xFF000000u);
}
