"""Procedural images made in numpy: surface textures and HDR environment maps.

The generator hands these to Mitsuba as `mi.Bitmap`s. Everything here is plain numpy and
seeded, so a scene seed always yields the same pixels. Values are linear RGB (a float32
Bitmap carries no sRGB flag, so Mitsuba uses them as they are).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TEXTURE_KINDS = ("checker", "stripes", "noise")
# Textures are small: scenes are rendered at 16–256 px, and a 64² texture already shows
# more detail than a training crop resolves. Keeps scene loading cheap.
TEXTURE_RES = 64
# Lat-long environment resolution (height, width); enough for a smooth sky plus a sun blob.
ENV_RES = (64, 128)


@dataclass(frozen=True)
class TextureSpec:
    """Everything needed to recreate one texture: a pattern blending two colours."""

    kind: str  # one of TEXTURE_KINDS
    color_a: tuple[float, float, float]
    color_b: tuple[float, float, float]
    frequency: int  # checker cells / stripe count / noise lattice cells across the texture
    angle: float  # stripe direction in radians (ignored by the other kinds)
    seed: int  # noise lattice seed (ignored by the other kinds)


@dataclass(frozen=True)
class SkySpec:
    """A gradient sky over a ground colour with one bright sun blob."""

    zenith: tuple[float, float, float]
    horizon: tuple[float, float, float]
    ground: tuple[float, float, float]
    sun_azimuth: float  # radians
    sun_elevation: float  # radians above the horizon
    sun_radiance: float  # peak value of the blob: large, so the sun dominates like a real one
    sun_width: float  # blob standard deviation, radians


def _grid(res: int) -> tuple[np.ndarray, np.ndarray]:
    """Texel-centre coordinates in [0, 1)², as (v, u) arrays of shape (res, res)."""
    c = (np.arange(res) + 0.5) / res
    return np.meshgrid(c, c, indexing="ij")


def _checker_mask(spec: TextureSpec, res: int) -> np.ndarray:
    v, u = _grid(res)
    cells = np.floor(u * spec.frequency) + np.floor(v * spec.frequency)
    return (cells % 2).astype(np.float32)


def _stripes_mask(spec: TextureSpec, res: int) -> np.ndarray:
    v, u = _grid(res)
    along = u * np.cos(spec.angle) + v * np.sin(spec.angle)
    # A soft-edged square wave: hard edges would alias into the noisy inputs themselves.
    wave = np.sin(2 * np.pi * spec.frequency * along)
    return (0.5 + 0.5 * np.tanh(4.0 * wave)).astype(np.float32)


def value_noise(res: int, cells: int, rng: np.random.Generator, octaves: int = 3) -> np.ndarray:
    """Fractal value noise in [0, 1]: random lattice values, smoothstep-interpolated, summed
    over octaves with halving amplitude."""
    total = np.zeros((res, res))
    amplitude, norm = 1.0, 0.0
    for octave in range(octaves):
        n = cells * 2**octave
        lattice = rng.random((n + 1, n + 1))
        pos = (np.arange(res) + 0.5) / res * n
        i = np.minimum(pos.astype(int), n - 1)
        f = pos - i
        f = f * f * (3 - 2 * f)  # smoothstep: no visible lattice creases
        rows = lattice[i] * (1 - f)[:, None] + lattice[i + 1] * f[:, None]
        total += amplitude * (rows[:, i] * (1 - f) + rows[:, i + 1] * f)
        norm += amplitude
        amplitude *= 0.5
    return (total / norm).astype(np.float32)


def _noise_mask(spec: TextureSpec, res: int) -> np.ndarray:
    return value_noise(res, max(spec.frequency, 1), np.random.default_rng(spec.seed))


_MASKS = {"checker": _checker_mask, "stripes": _stripes_mask, "noise": _noise_mask}


def texture_image(spec: TextureSpec, res: int = TEXTURE_RES) -> np.ndarray:
    """(res, res, 3) float32 linear RGB: color_a where the pattern is 0, color_b where 1."""
    if spec.kind not in _MASKS:
        raise ValueError(f"unknown texture kind {spec.kind!r}; known: {', '.join(TEXTURE_KINDS)}")
    mask = _MASKS[spec.kind](spec, res)[..., None]
    a = np.asarray(spec.color_a, dtype=np.float32)
    b = np.asarray(spec.color_b, dtype=np.float32)
    return np.ascontiguousarray(a * (1 - mask) + b * mask, dtype=np.float32)


def _directions(shape: tuple[int, int]) -> np.ndarray:
    """Unit directions of lat-long texel centres in Mitsuba's envmap convention
    (+Y up; row 0 is the zenith; u wraps around the vertical axis)."""
    height, width = shape
    theta = (np.arange(height) + 0.5) / height * np.pi  # polar angle from +Y
    phi = (np.arange(width) + 0.5) / width * 2 * np.pi
    sin_t = np.sin(theta)[:, None]
    # Inverse of envmap.cpp's lookup u = atan2(x, -z) / 2π, v = acos(y) / π.
    x = sin_t * np.sin(phi)[None, :]
    y = np.cos(theta)[:, None] * np.ones_like(phi)[None, :]
    z = -sin_t * np.cos(phi)[None, :]
    return np.stack([x, y, z], axis=-1)


def sky_image(spec: SkySpec, shape: tuple[int, int] = ENV_RES) -> np.ndarray:
    """(H, W, 3) float32 HDR lat-long sky: zenith→horizon gradient, flat ground, sun blob."""
    d = _directions(shape)
    up = d[..., 1:2]
    zenith, horizon, ground = (np.asarray(c, dtype=np.float64) for c in (spec.zenith, spec.horizon, spec.ground))
    t = np.sqrt(np.clip(up, 0.0, 1.0))  # more horizon haze near the horizon than a linear ramp
    image = np.where(up >= 0, horizon * (1 - t) + zenith * t, ground * np.ones_like(up))
    # Sun direction in the same convention as the texel directions.
    el, az = spec.sun_elevation, spec.sun_azimuth
    sun = np.array([np.cos(el) * np.sin(az), np.sin(el), -np.cos(el) * np.cos(az)])
    angle = np.arccos(np.clip(d @ sun, -1.0, 1.0))
    blob = spec.sun_radiance * np.exp(-0.5 * (angle / spec.sun_width) ** 2)
    image = image + blob[..., None] * np.array([1.0, 0.93, 0.8])  # warm white sun
    return np.ascontiguousarray(image, dtype=np.float32)
