// node require-extension.mjs IN.glb OUT.glb: the same GLB whose materials keep their
// base-colour texture under KHR_materials_pbrSpecularGlossiness (as `diffuseTexture`), which
// the file lists as required. Edits the JSON chunk only; the binary chunk is copied as is.
import fs from 'node:fs';

const [input, output] = process.argv.slice(2);
const glb = fs.readFileSync(input);
const jsonLength = glb.readUInt32LE(12);
const json = JSON.parse(glb.subarray(20, 20 + jsonLength).toString('utf8'));
const bin = glb.subarray(20 + jsonLength);
const name = 'KHR_materials_pbrSpecularGlossiness';
for (const material of json.materials) {
  const pbr = material.pbrMetallicRoughness;
  material.extensions = { [name]: { diffuseTexture: pbr.baseColorTexture } };
}
json.extensionsUsed = [...(json.extensionsUsed ?? []), name];
json.extensionsRequired = [...(json.extensionsRequired ?? []), name];
let text = Buffer.from(JSON.stringify(json), 'utf8');
text = Buffer.concat([text, Buffer.alloc((4 - (text.length % 4)) % 4, 0x20)]);
const header = Buffer.alloc(20);
header.write('glTF', 0);
header.writeUInt32LE(2, 4);
header.writeUInt32LE(20 + text.length + bin.length, 8);
header.writeUInt32LE(text.length, 12);
header.write('JSON', 16);
fs.writeFileSync(output, Buffer.concat([header, text, bin]));
