"""The driving scenes labelled by the bend ahead: five classes from the expert's turn command w."""

from __future__ import annotations

import numpy as np

BEND_CLASSES = ("sharp_left", "left", "straight", "right", "sharp_right")
# |w| below 1 is straight, 1 to 3 a bend, above 3 a sharp bend (w > 0 turns left). On the default circuits
# (4000 samples, 20 circuits, seed 0) these round cuts, near the 20th and 60th percentiles of |w|, give every
# class 18-21% of the samples.
STRAIGHT_W = 1.0
SHARP_W = 3.0


def bend_classes(w: np.ndarray) -> np.ndarray:
    """The class id (index into BEND_CLASSES) of each turn command w; a tie goes to the gentler class."""
    sharpness = np.digitize(np.abs(w), [STRAIGHT_W, SHARP_W], right=True)  # 0 straight, 1 bend, 2 sharp
    return (2 - np.sign(w) * sharpness).astype(np.int64)
