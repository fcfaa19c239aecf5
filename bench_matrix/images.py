"""Image preprocessing as torchvision and Keras applications do it: geometry once, values at load time;
the checks of dataset.preprocess against the images."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from bench_matrix.errors import UserError
from bench_matrix.matrix.spec import Preprocess

CROP_SIDES = ("top", "bottom", "left", "right")
GEOMETRIC = ("crop", "resize", "resize_shorter", "center_crop")
IMAGE_ONLY = (*GEOMETRIC, "mean", "std")
LAYOUTS = {"nchw": "C×H×W", "nhwc": "H×W×C"}  # one sample of an image input, in each model layout
DEFAULT_SCALE = 1.0 / 255.0  # when dataset.preprocess.scale is not given: pixels 0..255 to [0, 1]


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


def pixel_scale(preprocess: Preprocess) -> float:
    """What image values are multiplied by: dataset.preprocess.scale as given, else 1/255."""
    return DEFAULT_SCALE if preprocess.scale is None else preprocess.scale


def value_range(images: np.ndarray) -> tuple[float, float]:
    """The smallest and the largest value of an image array."""
    return float(images.min()), float(images.max())


def check_preprocess(preprocess: Preprocess, inputs: dict[str, np.ndarray],
                     ranges: dict[str, tuple[float, float]], where: str, as_is: Sequence[str] = ()) -> None:
    """Refuse image preprocessing without images (inputs `ranges` names; `as_is`: arrays passed as is), a mean
    or std fitting no image's channels, and the default scale on images not pixels 0..255."""
    if not ranges:
        given = [key for key in IMAGE_ONLY if getattr(preprocess, key) is not None]
        passed = f" ({', '.join(as_is)}: in the model's per-sample shape, passed as stored)" if as_is else ""
        if given:
            raise UserError(f"dataset.preprocess.{given[0]} applies to images, but {where} has no image "
                            f"input ((N, H, W, C) arrays, or (N, H, W) uint8); its inputs: "
                            f"{', '.join(inputs)}{passed}")
    for name, span in ranges.items():
        channels = inputs[name].shape[-1]
        for key in ("mean", "std"):
            values = getattr(preprocess, key)
            if values is not None and len(values) not in (1, channels):
                raise UserError(f"dataset.preprocess.{key} has {len(values)} values, but the images of "
                                f"{where} have {channels} channel(s); give one value or one per channel")
        if preprocess.scale is None:
            _check_default_scale(name, inputs[name].dtype, span, where)


def _check_default_scale(name: str, dtype: np.dtype, span: tuple[float, float], where: str) -> None:
    """Refuse images the default scale (1/255) does not fit: negative values, values beyond 255, and
    floats (or booleans) already within [0, 1]; each needs dataset.preprocess.scale given."""
    low, high = span
    if low < 0:
        why = "negative values: already scaled or standardised"
    elif high > 255:
        why = "values beyond 255: not 8-bit pixels"
    elif 0 < high <= 1 and dtype.kind not in "ui":
        why = "already in [0, 1]"
    else:
        return
    raise UserError(f"{where}: input '{name}' holds {dtype} images with values {low:.4g} to {high:.4g} "
                    f"({why}), which the default scale (1/255, for pixels 0 to 255) would distort; set "
                    f"dataset.preprocess.scale to the factor the model's inputs need (1.0 uses the values "
                    f"as they are)")


def to_model_input(images: np.ndarray, preprocess: Preprocess, layout: str) -> np.ndarray:
    """Scale and normalise (N,H,W,C) images per channel, then lay them out as the model expects."""
    x = images.astype(np.float32) * np.float32(pixel_scale(preprocess))
    if preprocess.mean is not None:
        x = (x - np.asarray(preprocess.mean, np.float32)) / np.asarray(preprocess.std, np.float32)
    if layout == "nchw":
        x = x.transpose(0, 3, 1, 2)
    return np.ascontiguousarray(x)


def in_layout(shape: tuple[int, ...], layout: str) -> tuple[int, ...]:
    """The per-sample shape (H,W,C) of a stored image as the model sees it in `layout`."""
    h, w, c = shape
    return (c, h, w) if layout == "nchw" else (h, w, c)


def layout_note(images: dict[str, tuple[int, ...]], layout: str) -> str:
    """For a message about inputs that do not fit: which arrays (name -> per-sample shape as stored) were read
    as H×W×C images and laid out for the model, and how to say otherwise; empty without images."""
    if not images:
        return ""
    arrays = ", ".join(f"'{name}' ({', '.join(map(str, shape))})" for name, shape in images.items())
    other = "nhwc" if layout == "nchw" else "nchw"
    return (f"; the data's {arrays} per sample was read as H×W×C images and laid out "
            f"{LAYOUTS[layout]} for the model (its layout: {layout}); if the model takes "
            f"{LAYOUTS[other]}, set layout: {other} on the model, and data stored in the model's own "
            f"per-sample shape is passed as it is")


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
