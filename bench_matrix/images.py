"""Image preprocessing as torchvision and Keras applications do it: geometry once, values at load time."""

from __future__ import annotations

import numpy as np

from bench_matrix.errors import UserError
from bench_matrix.matrix.spec import Preprocess

CROP_SIDES = ("top", "bottom", "left", "right")


def geometric(image: np.ndarray, preprocess: Preprocess) -> np.ndarray:
    """One (H,W,C) image cropped, resized, shorter side resized, then centre-cropped (each step if given)."""
    if preprocess.crop is not None:
        image = _crop(image, preprocess.crop)
    if preprocess.resize is not None:
        image = _resize(image, *preprocess.resize)
    if preprocess.resize_shorter is not None:
        image = _resize(image, *shorter_side_size(image.shape[:2], preprocess.resize_shorter))
    if preprocess.center_crop is not None:
        image = _center_crop(image, *preprocess.center_crop)
    return image


def geometric_shape(size: tuple[int, int], preprocess: Preprocess) -> tuple[int, int]:
    """The (height, width) `geometric` makes of an image of `size` (height, width), without pixels."""
    h, w = size
    if preprocess.crop is not None:
        top, bottom, left, right = preprocess.crop
        h, w = len(range(h)[top:bottom]), len(range(w)[left:right])
    if preprocess.resize is not None:
        h, w = preprocess.resize
    if preprocess.resize_shorter is not None:
        h, w = shorter_side_size((h, w), preprocess.resize_shorter)
    if preprocess.center_crop is not None:
        h, w = preprocess.center_crop
    return h, w


def shorter_side_size(size: tuple[int, ...], shorter: int) -> tuple[int, int]:
    """(height, width) with the shorter side `shorter` and the aspect ratio kept (torchvision's rounding)."""
    h, w = size[0], size[1]
    if h <= w:
        return shorter, int(shorter * w / h)
    return int(shorter * h / w), shorter


def to_model_input(images: np.ndarray, preprocess: Preprocess, layout: str) -> np.ndarray:
    """Scale and normalise (N,H,W,C) images per channel, then lay them out as the model expects."""
    x = images.astype(np.float32) * np.float32(preprocess.scale)
    if preprocess.mean is not None:
        x = (x - np.asarray(preprocess.mean, np.float32)) / np.asarray(preprocess.std, np.float32)
    if layout == "nchw":
        x = x.transpose(0, 3, 1, 2)
    return np.ascontiguousarray(x)


def in_layout(shape: tuple[int, ...], layout: str) -> tuple[int, ...]:
    """The per-sample shape (H,W,C) of a stored image as the model sees it in `layout`."""
    h, w, c = shape
    return (c, h, w) if layout == "nchw" else (h, w, c)


def _crop(image: np.ndarray, crop: tuple) -> np.ndarray:
    top, bottom, left, right = crop
    cropped = image[top:bottom, left:right]
    if 0 in cropped.shape[:2]:
        bounds = ", ".join(f"{side}: {value}" for side, value in zip(CROP_SIDES, crop) if value is not None)
        raise UserError(f"dataset.preprocess.crop {{{bounds}}} leaves no pixels of a {image.shape[1]}×"
                        f"{image.shape[0]} image (width×height); crop bounds are row and column indices")
    return cropped


def _resize(image: np.ndarray, h: int, w: int) -> np.ndarray:
    """Bilinear resize (antialiased when shrinking, as PIL and torchvision do) of each channel."""
    if tuple(image.shape[:2]) == (h, w):
        return image
    from PIL import Image

    mode, dtype = ("L", np.uint8) if image.dtype == np.uint8 else ("F", np.float32)
    return np.stack([np.asarray(Image.fromarray(image[..., c].astype(dtype), mode=mode)
                                .resize((w, h), Image.BILINEAR)) for c in range(image.shape[2])], -1)


def _center_crop(image: np.ndarray, h: int, w: int) -> np.ndarray:
    """The centre h × w of an image (torchvision's rounding); an image smaller than that is refused."""
    height, width = image.shape[:2]
    if h > height or w > width:
        raise UserError(f"dataset.preprocess.center_crop [{h}, {w}] (height, width) is larger than a "
                        f"{width}×{height} image (width×height) after resizing; give a smaller center_crop "
                        f"or a larger resize_shorter")
    top, left = int(round((height - h) / 2.0)), int(round((width - w) / 2.0))
    return image[top:top + h, left:left + w]
