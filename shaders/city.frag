#version 460
#extension GL_GOOGLE_include_directive : require
#extension GL_ARB_sparse_texture2 : require
#include "citystream.glsl"
#include "city_texture.glsl"
#include "lod.glsl"

// Visible pass: samples the sparse cache at max(required LOD with A_s = 8,
// finest resident level) and blends with the City Colormap colour by the
// displayed level (paper Eq. 8): c = (1 - M/M_max) c_s + (M/M_max) c_o.
// Unloaded or non-resident textures show the colormap colour.
layout(push_constant) uniform Push { CityDrawPush push; };
layout(std430, set = 0, binding = BINDING_CITY_MESHES) readonly buffer CityMeshes { CityMeshInfo city_meshes[]; };

layout(location = 0) in vec2 in_uv;
layout(location = 1) in vec3 in_normal;
layout(location = 2) flat in uint in_mesh_id;
layout(location = 0) out vec4 out_color;

const vec3 LIGHT_DIR = vec3(0.36, 0.80, 0.48);

void main() {
    CityMeshInfo mesh = city_meshes[in_mesh_id];
    vec2 size = vec2(mesh.texture_width, mesh.texture_height);
    float max_level = float(mesh.max_mip);
    float lod = clamp(anisotropic_lod(dFdx(in_uv) * size, dFdy(in_uv) * size, SAMPLE_ANISOTROPY), 0.0, max_level);
    vec4 c_o = colormap_colour(mesh.texture_id);
    vec4 c_s;
    float displayed;
    // viewport_light.w = 1: direct sampling, no City Colormap at all (the
    // pop-in comparison of Fig. 7): unloaded texels read as zero, as a
    // non-resident sparse texel does.
    bool direct = push.viewport_light.w != 0.0;
    vec3 colour = direct ? vec3(0.0) : c_o.rgb;
    if (sample_city_texture_level(mesh.texture_id, in_uv, lod, c_s, displayed)) {
        float t = max_level > 0.0 && !direct ? clamp(displayed / max_level, 0.0, 1.0) : 0.0;
        colour = mix(c_s.rgb, c_o.rgb, t);
    }
    float lambert = 0.35 + 0.65 * max(dot(normalize(in_normal), normalize(LIGHT_DIR)), 0.0);
    out_color = vec4(colour * mix(1.0, lambert, push.viewport_light.z), 1.0);
}
