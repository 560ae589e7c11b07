// node swap-textures.mjs IN.glb OUT.glb FACADE.ktx2 ROOF.ktx2: the same glTF with its two
// PNG textures replaced by KTX2 images under KHR_texture_basisu (required: no PNG fallback).
// Geometry, materials and nodes are written back unchanged.
import fs from 'node:fs';
import { NodeIO } from '@gltf-transform/core';
import { KHRTextureBasisu } from '@gltf-transform/extensions';

const [input, output, facade, roof] = process.argv.slice(2);
const io = new NodeIO().registerExtensions([KHRTextureBasisu]);
const doc = await io.read(input);
doc.createExtension(KHRTextureBasisu).setRequired(true);
const images = { facade: fs.readFileSync(facade), roof: fs.readFileSync(roof) };
for (const texture of doc.getRoot().listTextures()) {
  texture.setImage(images[texture.getName()]).setMimeType('image/ktx2').setURI('');
}
fs.writeFileSync(output, await io.writeBinary(doc));
