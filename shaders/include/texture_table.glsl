// The per-texture table (TextureData) at its fixed binding in set 0.
#ifndef TEXTURE_TABLE_GLSL
#define TEXTURE_TABLE_GLSL

layout(std430, set = 0, binding = BINDING_TEXTURE_DATA) readonly buffer TextureTable { TextureData texture_data[]; };

#endif
