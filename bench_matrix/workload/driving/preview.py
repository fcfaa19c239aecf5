"""Write a contact sheet of sample frames with their [v, w] labels: python -m ...driving.preview OUT.png."""

from __future__ import annotations

import argparse

import numpy as np
from PIL import Image, ImageDraw

from .dataset import generate

_SCALE = 2  # enlarge frames so markings are easy to see
_CAPTION = 16  # caption strip height, pixels


def contact_sheet(images: np.ndarray, labels: np.ndarray, columns: int = 3) -> Image.Image:
    """Tile frames (upscaled) in a grid with "v=.. w=.." written below each."""
    height, width = images.shape[1] * _SCALE, images.shape[2] * _SCALE
    rows = -(-len(images) // columns)
    sheet = Image.new("RGB", (columns * width, rows * (height + _CAPTION)), "white")
    draw = ImageDraw.Draw(sheet)
    for k, (image, (v, w)) in enumerate(zip(images, labels)):
        x, y = (k % columns) * width, (k // columns) * (height + _CAPTION)
        sheet.paste(Image.fromarray(image).resize((width, height), Image.NEAREST), (x, y))
        draw.text((x + 4, y + height + 2), f"v={v:5.2f}  w={w:+5.2f}", fill="black")
    return sheet


def main() -> None:
    """Generate a small data set and save a contact sheet of evenly spaced frames."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("out", help="output PNG path")
    parser.add_argument("--count", type=int, default=12, help="frames to show")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    data = generate(max(args.count * 8, 96), seed=args.seed)
    pick = np.linspace(0, len(data) - 1, args.count).astype(int)
    contact_sheet(data.images[pick], data.labels[pick]).save(args.out)
    print(f"wrote {args.out}: {args.count} frames from seed {args.seed}")


if __name__ == "__main__":
    main()
