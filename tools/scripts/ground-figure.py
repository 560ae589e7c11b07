#!/usr/bin/env python3
"""Composes docs/images/ground-refining.jpg from the frames of the ground demo of docs/MEASURED.md, "Ground imagery".

    flythrough --ground data/patches --path docs/paths/ground-demo.json --clock fixed \
        --bind-latency desktop --frame-interval 60 --psnr-interval 0 --width 960 --height 540 \
        --duration-s 52 --out out/ground-demo
    python3 tools/scripts/ground-figure.py out/ground-demo/frames docs/images/ground-refining.jpg

Top: the last frame with the enlarged region outlined; below, that region at three moments
of the flight. Needs Pillow (`pip install pillow`).
"""

import sys
from pathlib import Path

from PIL import Image, ImageDraw

# The frames shown enlarged (60 per second: 2 s, 11 s, 51 s) and the region, in pixels.
MOMENTS = [120, 660, 3060]
REGION = (320, 150, 470, 300)
GAP = 10


def main() -> int:
    if len(sys.argv) != 3:
        print(__doc__, file=sys.stderr)
        return 2
    frames, out = Path(sys.argv[1]), Path(sys.argv[2])
    images = []
    for frame in MOMENTS:
        path = frames / f"frame_{frame:05}.png"
        if not path.is_file():
            print(f"{path}: missing (run the demo with --frame-interval 60)", file=sys.stderr)
            return 1
        images.append(Image.open(path).convert("RGB"))
    top = images[-1].copy()
    width = top.width
    crop_side = (width - GAP * (len(MOMENTS) - 1)) // len(MOMENTS)
    figure = Image.new("RGB", (width, top.height + GAP + crop_side), "white")
    ImageDraw.Draw(top).rectangle(REGION, outline=(255, 215, 0), width=2)
    figure.paste(top, (0, 0))
    for i, image in enumerate(images):
        crop = image.crop(REGION).resize((crop_side, crop_side), Image.Resampling.NEAREST)
        figure.paste(crop, (i * (crop_side + GAP), top.height + GAP))
    figure.save(out, quality=88)
    print(f"wrote {out} ({figure.width}x{figure.height})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
