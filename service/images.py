"""Display transforms for previews and reports: HDR radiance → sRGB, scalar maps → viridis."""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from PIL import Image

SRGB_GAMMA_CUTOFF = 0.0031308  # IEC 61966-2-1 piecewise sRGB transfer function
SRGB_LINEAR_SLOPE = 12.92
# Anchors of matplotlib's viridis (perceptually uniform, readable in grey), linearly interpolated.
VIRIDIS = np.array([
    [0.267, 0.005, 0.329], [0.283, 0.141, 0.458], [0.254, 0.265, 0.530], [0.207, 0.372, 0.553],
    [0.164, 0.471, 0.558], [0.128, 0.567, 0.551], [0.135, 0.659, 0.518], [0.267, 0.749, 0.441],
    [0.478, 0.821, 0.318], [0.741, 0.873, 0.150], [0.993, 0.906, 0.144],
])


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """Linear → sRGB transfer curve, input sanitised and clamped to [0, 1]."""
    x = np.clip(np.nan_to_num(np.asarray(x, dtype=np.float64), nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    return np.where(x <= SRGB_GAMMA_CUTOFF, SRGB_LINEAR_SLOPE * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def tonemap(radiance: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """(H, W, 3) linear HDR → (H, W, 3) uint8 sRGB: scale by 2^exposure (stops), clip."""
    return np.round(linear_to_srgb(np.asarray(radiance, dtype=np.float64) * 2.0**exposure) * 255).astype(np.uint8)


def colormap(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """(H, W) scalars → (H, W, 3) uint8 viridis, `lo` dark to `hi` bright."""
    span = hi - lo if hi > lo else 1.0
    t = np.clip((np.nan_to_num(np.asarray(values, dtype=np.float64)) - lo) / span, 0.0, 1.0)
    position = t * (len(VIRIDIS) - 1)
    index = np.minimum(position.astype(int), len(VIRIDIS) - 2)
    frac = (position - index)[..., None]
    return np.round((VIRIDIS[index] * (1 - frac) + VIRIDIS[index + 1] * frac) * 255).astype(np.uint8)


def false_colour(values: np.ndarray, vmax: float | None = None) -> np.ndarray:
    """Non-negative map → viridis from 0 to `vmax` (default: the 99th percentile, so a few
    extreme pixels do not flatten the rest)."""
    finite = np.asarray(values)[np.isfinite(values)]
    top = vmax if vmax is not None else (float(np.percentile(finite, 99)) if finite.size else 1.0)
    return colormap(values, 0.0, top)


def png_bytes(rgb8: np.ndarray, compress_level: int = 6) -> bytes:
    """Lossless PNG; `compress_level` is zlib's (6: Pillow's default, 1: fastest)."""
    out = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb8), mode="RGB").save(out, format="PNG", compress_level=compress_level)
    return out.getvalue()


def write_png(path: str | Path, rgb8: np.ndarray) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(png_bytes(rgb8))
    return path
