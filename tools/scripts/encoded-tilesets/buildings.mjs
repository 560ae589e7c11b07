// Writes OUT/b0.glb … b3.glb (and the two images as OUT/facade.png, OUT/roof.png): four textured buildings (walls and a flat roof, normals,
// UVs that repeat the facade along each wall), one building per file, placed by a node
// translation on a 60 m grid. Every file embeds the same two PNGs (a 128×128 facade, a 64×64
// roof), as tilesets repeat images per tile. The images come from a fixed pseudo-random
// sequence, so a run writes the same files.
import fs from 'node:fs';
import path from 'node:path';
import { Document, NodeIO } from '@gltf-transform/core';
import { PNG } from 'pngjs';

const out = process.argv[2];
fs.mkdirSync(out, { recursive: true });

let state = 12345;
function random() {
  state = (Math.imul(state, 1103515245) + 12345) >>> 0;
  return (state >>> 8) / 16777216;
}

function png(size, texel) {
  const image = new PNG({ width: size, height: size });
  for (let y = 0; y < size; y++) {
    for (let x = 0; x < size; x++) {
      const [r, g, b] = texel(x, y);
      const i = (y * size + x) * 4;
      image.data[i] = r;
      image.data[i + 1] = g;
      image.data[i + 2] = b;
      image.data[i + 3] = 255;
    }
  }
  return PNG.sync.write(image, { colorType: 2 });
}

const clamp = (v) => Math.max(0, Math.min(255, Math.round(v)));
// Plaster with a 4×4 grid of windows (frames, panes with a sky gradient) and some grain.
const facade = png(128, (x, y) => {
  const cx = x % 32, cy = y % 32;
  const grain = (random() - 0.5) * 10;
  if (cx >= 6 && cx < 26 && cy >= 5 && cy < 27) {
    if (cx < 8 || cx >= 24 || cy < 7 || cy >= 25 || cx === 16) return [235, 232, 220].map((v) => clamp(v + grain / 3));
    return [clamp(60 + cy * 2 + grain), clamp(90 + cy * 3 + grain), clamp(140 + cy * 2 + grain)];
  }
  return [clamp(196 + grain + (y >> 5) * 6), clamp(150 + grain), clamp(110 + grain - (x >> 5) * 4)];
});
const roof = png(64, (x, y) => {
  const grain = (random() - 0.5) * 12;
  const seam = x % 16 === 0 || y % 16 === 0 ? -30 : 0;
  return [clamp(110 + grain + seam), clamp(105 + grain + seam), clamp(100 + grain + seam)];
});

fs.writeFileSync(path.join(out, 'facade.png'), facade);
fs.writeFileSync(path.join(out, 'roof.png'), roof);

// Width (x), depth (z), height (y), position on the grid.
const buildings = [
  [20, 14, 32, [0, 0, 0]],
  [16, 16, 18, [60, 0, 0]],
  [28, 12, 24, [0, 0, -60]],
  [12, 22, 40, [60, 0, -60]],
];

const io = new NodeIO();
for (const [n, [w, d, h, at]] of buildings.entries()) {
  const doc = new Document();
  const buffer = doc.createBuffer();
  const texture = (name, bytes) => doc.createTexture(name).setImage(bytes).setMimeType('image/png');
  const material = (name, image) =>
    doc.createMaterial(name).setBaseColorTexture(texture(name, image)).setMetallicFactor(0).setRoughnessFactor(1);
  const walls = { positions: [], normals: [], uvs: [], indices: [] };
  const top = { positions: [], normals: [], uvs: [], indices: [] };
  const quad = (part, corners, normal, uvs) => {
    const base = part.positions.length / 3;
    corners.forEach((c, i) => {
      part.positions.push(...c);
      part.normals.push(...normal);
      part.uvs.push(...uvs[i]);
    });
    part.indices.push(base, base + 1, base + 2, base, base + 2, base + 3);
  };
  const [x0, x1, z0, z1] = [-w / 2, w / 2, -d / 2, d / 2];
  // One facade texture repeat per 8 m of wall and of height.
  const wall = (a, b, normal, length) =>
    quad(walls, [[...a, 0], [...b, 0], [...b, h], [...a, h]].map(([x, z, y]) => [x, y, z]), normal, [
      [0, h / 8], [length / 8, h / 8], [length / 8, 0], [0, 0],
    ]);
  wall([x0, z1], [x1, z1], [0, 0, 1], w);
  wall([x1, z1], [x1, z0], [1, 0, 0], d);
  wall([x1, z0], [x0, z0], [0, 0, -1], w);
  wall([x0, z0], [x0, z1], [-1, 0, 0], d);
  quad(top, [[x0, h, z1], [x1, h, z1], [x1, h, z0], [x0, h, z0]], [0, 1, 0], [[0, 1], [1, 1], [1, 0], [0, 0]]);
  const mesh = doc.createMesh(`building-${n}`);
  for (const [part, mat] of [[walls, material('facade', facade)], [top, material('roof', roof)]]) {
    const accessor = (type, array) => doc.createAccessor().setType(type).setArray(array).setBuffer(buffer);
    mesh.addPrimitive(
      doc
        .createPrimitive()
        .setAttribute('POSITION', accessor('VEC3', new Float32Array(part.positions)))
        .setAttribute('NORMAL', accessor('VEC3', new Float32Array(part.normals)))
        .setAttribute('TEXCOORD_0', accessor('VEC2', new Float32Array(part.uvs)))
        .setIndices(accessor('SCALAR', new Uint16Array(part.indices)))
        .setMaterial(mat),
    );
  }
  const node = doc.createNode(`building-${n}`).setMesh(mesh).setTranslation(at);
  doc.createScene('city').addChild(node);
  fs.writeFileSync(path.join(out, `b${n}.glb`), await io.writeBinary(doc));
}
