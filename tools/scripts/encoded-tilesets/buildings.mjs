// Writes OUT/b0.glb … b3.glb (and the two images as OUT/facade.png, OUT/roof.png): four textured buildings (walls and a flat roof, normals,
// UVs that repeat the facade along each wall), one building per file, placed by a node
// translation on a 60 m grid. Every file embeds the same two PNGs (a 128×128 facade, a 64×64
// roof), as tilesets repeat images per tile. The images' grain comes from a fixed pseudo-random
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

// Each texel is the mean of 4×4 samples of `texel` (as a photograph's optics soften edges;
// hard one-texel edges in every 4×4 block would favour no block codec).
function png(size, texel) {
  const image = new PNG({ width: size, height: size });
  for (let y = 0; y < size; y++) {
    for (let x = 0; x < size; x++) {
      const sum = [0, 0, 0];
      for (let sy = 0; sy < 4; sy++) {
        for (let sx = 0; sx < 4; sx++) {
          texel(x + (sx + 0.5) / 4, y + (sy + 0.5) / 4).forEach((v, c) => (sum[c] += v));
        }
      }
      const i = (y * size + x) * 4;
      for (let c = 0; c < 3; c++) image.data[i + c] = Math.max(0, Math.min(255, Math.round(sum[c] / 16)));
      image.data[i + 3] = 255;
    }
  }
  return PNG.sync.write(image, { colorType: 2 });
}

const clamp = (v) => Math.max(0, Math.min(255, Math.round(v)));
// Weathering: value noise on a 4-texel lattice, bilinearly interpolated (spatially
// correlated, as the grain of photographed facades is; white noise per texel is not).
function grainOf(size, amplitude) {
  const cells = size / 4 + 1;
  const lattice = Array.from({ length: cells * cells }, () => (random() - 0.5) * amplitude);
  return (x, y) => {
    const [gx, gy] = [x / 4, y / 4];
    const [x0, y0] = [Math.floor(gx), Math.floor(gy)];
    const [fx, fy] = [gx - x0, gy - y0];
    const at = (i, j) => lattice[Math.min(j, cells - 1) * cells + Math.min(i, cells - 1)];
    const top = at(x0, y0) * (1 - fx) + at(x0 + 1, y0) * fx;
    const bottom = at(x0, y0 + 1) * (1 - fx) + at(x0 + 1, y0 + 1) * fx;
    return top * (1 - fy) + bottom * fy;
  };
}
const facadeGrain = grainOf(128, 24);
const roofGrain = grainOf(64, 30);
// Beige plaster with a 4×4 grid of windows (light frames, dark grey-blue panes that reflect
// a sky gradient) and some grain: the muted colours of a rendered European facade.
const facade = png(128, (x, y) => {
  const cx = x % 32, cy = y % 32;
  const grain = facadeGrain(x, y);
  if (cx >= 6 && cx < 26 && cy >= 5 && cy < 27) {
    if (cx < 8 || cx >= 24 || cy < 7 || cy >= 25 || (cx >= 15.5 && cx < 16.5)) return [235, 232, 220].map((v) => v + grain / 3);
    return [70 + cy * 2 + grain, 84 + cy * 2 + grain, 100 + cy * 2 + grain];
  }
  return [clamp(200 + grain + Math.floor(y / 32) * 4), clamp(178 + grain), clamp(146 + grain - Math.floor(x / 32) * 3)];
});
const roof = png(64, (x, y) => {
  const grain = roofGrain(x, y);
  const seam = x % 16 < 1 || y % 16 < 1 ? -30 : 0;
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
