// The per-texture table (TextureData) at its fixed binding in set CITYSTREAM_SET.
#ifndef TEXTURE_TABLE_GLSL
#define TEXTURE_TABLE_GLSL

layout(std430, set = CITYSTREAM_SET, binding = BINDING_TEXTURE_DATA) readonly buffer TextureTable { TextureData texture_data[]; };

#endif
