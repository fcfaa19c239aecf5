"""Front-camera renderer: ground-plane ray casting into the circuit texture, sky, haze and lighting."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .circuit import Circuit, Pose
from .texture import N_LEVELS, TEXEL, ground_texture, unpack_mean

_MAX_RANGE = 400.0  # ground beyond this distance is drawn as sky/haze, metres
_SUBPIXELS = np.array([(-0.375, -0.125), (0.125, -0.375), (0.375, 0.125), (-0.125, 0.375)])  # rotated grid
_HORIZON_SKY = np.array([[196.0], [208.0], [220.0]], dtype=np.float32)
_ZENITH_SKY = np.array([[70.0], [120.0], [200.0]], dtype=np.float32)


@dataclass(frozen=True)
class Lighting:
    """Per-image photometric conditions: exposure, tint, haze and a soft shadow band on the ground."""

    brightness: float = 1.0
    contrast: float = 1.0
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    visibility: float = 250.0  # distance at which haze hides half of the ground colour, metres
    shadow_strength: float = 0.0  # darkening at the band's core, 0 = no shadow
    shadow_distance: float = 10.0  # band centre, metres ahead of the camera
    shadow_angle: float = 0.0  # band normal relative to the car's forward axis, radians
    shadow_width: float = 3.0  # metres

    @classmethod
    def sample(cls, rng: np.random.Generator) -> Lighting:
        """Draw varied but plausible daylight conditions."""
        red, green, blue = (float(t) for t in 1.0 + rng.uniform(-0.12, 0.12, 3))
        return cls(
            brightness=float(rng.uniform(0.6, 1.3)),
            contrast=float(rng.uniform(0.7, 1.2)),
            tint=(red, green, blue),
            visibility=float(rng.uniform(80.0, 400.0)),
            shadow_strength=float(rng.uniform(0.0, 0.6) * (rng.random() < 0.5)),
            shadow_distance=float(rng.uniform(3.0, 30.0)),
            shadow_angle=float(rng.uniform(-1.0, 1.0)),
            shadow_width=float(rng.uniform(1.0, 6.0)),
        )


@dataclass(frozen=True, eq=False)
class _RayPlan:
    """Pose-independent ray geometry: ground samples in car coordinates, grouped by mip level."""

    ground_index: np.ndarray  # flat pixel indices of ground pixels, sorted by mip level
    level_spans: tuple[tuple[int, int, int], ...]  # (level, start, stop) into ground_index
    sample_fwd: np.ndarray  # [subpixels, n_ground] metres ahead of the camera
    sample_left: np.ndarray  # [subpixels, n_ground] metres to the left
    centre_fwd: np.ndarray  # [n_ground] pixel-centre ground point
    centre_left: np.ndarray
    ground_range: np.ndarray  # [n_ground] camera-to-ground distance, metres
    sky: np.ndarray  # [3, rows * cols] channel-first sky gradient, float32


@dataclass(frozen=True)
class Camera:
    """Pinhole front camera on the car's centreline, pitched down towards the road."""

    height: float = 1.3
    pitch_deg: float = 8.0
    hfov_deg: float = 96.0
    rows: int = 66
    cols: int = 200

    @property
    def focal(self) -> float:
        """Focal length in pixels."""
        return self.cols / 2 / np.tan(np.radians(self.hfov_deg) / 2)

    def _rays(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unnormalised (ahead, left, up) directions of rays through image offsets u (right), v (down)."""
        f, p = self.focal, np.radians(self.pitch_deg)
        return f * np.cos(p) - v * np.sin(p), -u, -(f * np.sin(p) + v * np.cos(p))

    def _ground(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, ...]:
        """Ground hit (ahead, left, range, hit) of rays; rays missing the ground stop at _MAX_RANGE."""
        ahead, left, up = self._rays(u, v)
        norm = np.sqrt(ahead**2 + left**2 + up**2)
        t = self.height / np.maximum(-up, self.height * norm / _MAX_RANGE)
        return t * ahead, t * left, t * norm, -up * _MAX_RANGE > self.height * norm

    @cached_property
    def plan(self) -> _RayPlan:
        """Ray geometry shared by every render with this camera."""
        v, u = (np.mgrid[: self.rows, : self.cols].reshape(2, -1) + 0.5
                - np.array([[self.rows], [self.cols]]) / 2)
        fwd, left, rng, hit = self._ground(u, v)
        ground = np.flatnonzero(hit)
        # Mip level whose texels are about half a pixel's lateral footprint (range / focal metres).
        level = np.clip(np.round(np.log2(rng[ground] / self.focal / (2 * TEXEL))), 0, N_LEVELS - 1)
        order = np.argsort(level, kind="stable")
        ground, level = ground[order], level[order].astype(int)
        spans = tuple((int(lv), int(np.searchsorted(level, lv)), int(np.searchsorted(level, lv, "right")))
                      for lv in np.unique(level))
        sub_fwd, sub_left, _, _ = self._ground(u[ground] + _SUBPIXELS[:, :1], v[ground] + _SUBPIXELS[:, 1:])

        ahead, across, up = self._rays(u, v)
        blend = np.clip(np.arctan2(up, np.hypot(ahead, across)) / np.radians(30.0), 0.0, 1.0) ** 0.6
        sky = (_HORIZON_SKY * (1 - blend) + _ZENITH_SKY * blend).astype(np.float32)
        return _RayPlan(ground, spans, sub_fwd.astype(np.float32), sub_left.astype(np.float32),
                        fwd[ground].astype(np.float32), left[ground].astype(np.float32),
                        rng[ground].astype(np.float32), sky)


def render(circuit: Circuit, pose: Pose, lighting: Lighting = Lighting(), camera: Camera = Camera()) -> np.ndarray:
    """Render the camera image [rows, cols, 3] uint8 seen from pose (x, y, yaw) on the circuit."""
    plan, texture = camera.plan, ground_texture(circuit)
    x, y, yaw = pose
    cos, sin = np.float32(np.cos(yaw)), np.float32(np.sin(yaw))
    wx = (x - texture.x0) + cos * plan.sample_fwd - sin * plan.sample_left
    wy = (y - texture.y0) + sin * plan.sample_fwd + cos * plan.sample_left
    np.clip(wx, 0, texture.width - 1e-3, out=wx)
    np.clip(wy, 0, texture.height - 1e-3, out=wy)
    packed = np.empty(len(plan.ground_index), dtype=np.uint32)
    for level, start, stop in plan.level_spans:
        image, scale = texture.levels[level], np.float32(1.0 / (TEXEL * 2**level))
        index = (wy[:, start:stop] * scale).astype(np.intp) * image.shape[1]
        index += (wx[:, start:stop] * scale).astype(np.intp)
        np.sum(image.ravel()[index], axis=0, out=packed[start:stop])
    ground = unpack_mean(packed, len(_SUBPIXELS))

    across = (plan.centre_fwd - lighting.shadow_distance) * np.float32(np.cos(lighting.shadow_angle))
    across += plan.centre_left * np.float32(np.sin(lighting.shadow_angle))
    across *= np.float32(1.0 / lighting.shadow_width)
    haze = plan.ground_range / (plan.ground_range + np.float32(lighting.visibility))
    ground *= (1 - haze) * (1 - lighting.shadow_strength / (1 + across * across))
    ground += haze * _HORIZON_SKY

    out = plan.sky.copy()
    out[:, plan.ground_index] = ground
    tint = np.asarray(lighting.tint, np.float32)[:, None] * np.float32(lighting.brightness)
    out *= tint * np.float32(lighting.contrast)
    out += tint * np.float32(128.0 * (1 - lighting.contrast))
    np.clip(out, 0, 255, out=out)
    return out.astype(np.uint8).T.reshape(camera.rows, camera.cols, 3)
