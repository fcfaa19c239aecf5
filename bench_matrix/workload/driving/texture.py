"""Top-down ground texture of a circuit, rasterised once per circuit and mip-mapped."""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from .circuit import Circuit

TEXEL = 0.1  # metres per texel at mip level 0
N_LEVELS = 6  # level l has texels of TEXEL * 2**l metres
_MARGIN = 25.0  # grass around the circuit's bounding box, metres
_STAMP = 0.05  # spacing of the (s, d) stamping lattice, metres

_ASPHALT = np.array([92.0, 92.0, 96.0])
_WHITE = np.array([236.0, 236.0, 232.0])
_YELLOW = np.array([232.0, 190.0, 40.0])
_KERB_RED = np.array([196.0, 44.0, 40.0])
_GRASS = np.array([72.0, 118.0, 48.0])
_DRY_GRASS = np.array([128.0, 130.0, 70.0])
_SPECKLE = 24  # peak-to-peak per-texel brightness noise on grass and road
_SHIFTS = np.array([[20], [10], [0]], dtype=np.uint32)  # bit offsets of r, g, b in a packed texel

_CACHE: weakref.WeakKeyDictionary[Circuit, GroundTexture] = weakref.WeakKeyDictionary()


@dataclass(frozen=True, eq=False)
class GroundTexture:
    """Mip pyramid; level l texel (i, j) covers world x0 + j*size, y0 + i*size with size = TEXEL * 2**l."""

    x0: float
    y0: float
    width: float  # metres covered along x
    height: float  # metres covered along y
    levels: tuple[np.ndarray, ...]  # uint32 [rows_l, cols_l] holding r << 20 | g << 10 | b


def pack(rgb: np.ndarray) -> np.ndarray:
    """Pack uint8 RGB into 10-bit fields of a uint32 so that sums of up to four texels never carry."""
    rgb = rgb.astype(np.uint32)
    return (rgb[..., 0] << 20) | (rgb[..., 1] << 10) | rgb[..., 2]


def unpack_mean(packed: np.ndarray, count: int) -> np.ndarray:
    """Channel-first mean RGB (float32 [3, n]) from `packed` [n] sums of `count` packed texels."""
    return ((packed >> _SHIFTS) & 1023).astype(np.float32) * np.float32(1.0 / count)


def ground_texture(circuit: Circuit) -> GroundTexture:
    """The circuit's texture, rasterised on first use and cached while the circuit lives."""
    if circuit not in _CACHE:
        _CACHE[circuit] = rasterise(circuit)
    return _CACHE[circuit]


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], cell: int) -> np.ndarray:
    """Bilinearly interpolated value noise in [0, 1) with features `cell` texels wide."""
    coarse = rng.random((shape[0] // cell + 2, shape[1] // cell + 2), dtype=np.float32)
    fy, fx = (np.arange(n, dtype=np.float32) / cell for n in shape)
    iy, ix = fy.astype(np.intp), fx.astype(np.intp)
    ty, tx = (fy - iy)[:, None], (fx - ix)[None, :]
    top = coarse[iy][:, ix] * (1 - tx) + coarse[iy][:, ix + 1] * tx
    bottom = coarse[iy + 1][:, ix] * (1 - tx) + coarse[iy + 1][:, ix + 1] * tx
    return top * (1 - ty) + bottom * ty


def _grass(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    """Patchy green-to-dry grass colour, smooth over 4-texel blocks, uint8 RGB."""
    coarse = (shape[0] // 4, shape[1] // 4)
    patches = _smooth_noise(rng, coarse, 12)[..., None]
    shade = 0.8 + 0.4 * _smooth_noise(rng, coarse, 3)[..., None]
    base = (_GRASS * (1 - patches) + _DRY_GRASS * patches) * shade
    return np.repeat(np.repeat(base.astype(np.uint8), 4, axis=0), 4, axis=1)


def _road_codes(circuit: Circuit, s: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Palette index (0 asphalt, 1 white, 2 centre line, 3 red kerb) on the lattice s x d."""
    m, half = circuit.markings, circuit.lane_width / 2
    ad = np.abs(d)
    edge = (ad > half - m.edge_inset - m.edge_width) & (ad < half - m.edge_inset)
    zone = np.select([ad > half, edge, ad < m.centre_width / 2], [3, 1, 2], 0).astype(np.uint8)
    dash = np.mod(s, m.dash_length + m.dash_gap) < m.dash_length
    red = np.floor(s / m.kerb_stripe) % 2 == 0
    code = np.where(zone == 2, np.where(dash[:, None], 2, 0), zone)
    return np.where(zone == 3, np.where(red[:, None], 3, 1), code).astype(np.uint8)


def rasterise(circuit: Circuit) -> GroundTexture:
    """Paint grass, stamp the road band on an (s, d) lattice, add per-texel speckle, build the mips."""
    rng = np.random.default_rng([circuit.seed, 0x7E57])
    x, y, _ = circuit.pose_at(np.arange(0.0, circuit.length, 1.0))
    block = 2 ** (N_LEVELS - 1)
    x0, y0 = x.min() - _MARGIN, y.min() - _MARGIN
    rows, cols = (int(np.ceil((v.max() - v.min() + 2 * _MARGIN) / TEXEL / block)) * block for v in (y, x))
    image = _grass(rng, (rows, cols))

    reach = circuit.lane_width / 2 + circuit.markings.kerb_width
    s = np.arange(0.0, circuit.length, _STAMP)
    d = np.arange(-reach + _STAMP / 2, reach, _STAMP)
    cx, cy, heading = circuit.pose_at(s)
    j = (((cx - x0) / TEXEL).astype(np.float32)[:, None] - (np.sin(heading) / TEXEL).astype(np.float32)[:, None] * d)
    i = (((cy - y0) / TEXEL).astype(np.float32)[:, None] + (np.cos(heading) / TEXEL).astype(np.float32)[:, None] * d)
    palette = np.array([_ASPHALT, _WHITE, _YELLOW if circuit.markings.centre_yellow else _WHITE, _KERB_RED])
    image[i.astype(np.intp), j.astype(np.intp)] = palette.astype(np.uint8)[_road_codes(circuit, s, d)]

    image -= np.minimum(image, _SPECKLE // 2)
    tile = rng.integers(0, _SPECKLE, (128, 128, 1), dtype=np.uint8)
    image += np.tile(tile, (rows // 128 + 1, cols // 128 + 1, 1))[:rows, :cols]
    levels = [pack(image)]
    for _ in range(1, N_LEVELS):
        image = image.astype(np.uint16)
        image = ((image[0::2, 0::2] + image[1::2, 0::2] + image[0::2, 1::2] + image[1::2, 1::2]) // 4).astype(np.uint8)
        levels.append(pack(image))
    return GroundTexture(float(x0), float(y0), cols * TEXEL, rows * TEXEL, tuple(levels))
