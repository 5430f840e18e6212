"""Preview images for people: radiance tonemapped, scalar maps colour-mapped, both to 8-bit PNG,
or the raw float values as a single-layer EXR."""
from __future__ import annotations

import io
import os
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

# Anchors of matplotlib's viridis (perceptually uniform, readable in grey), linearly interpolated.
_VIRIDIS = np.array(
    [
        [0.267, 0.005, 0.329],
        [0.283, 0.141, 0.458],
        [0.254, 0.265, 0.530],
        [0.207, 0.372, 0.553],
        [0.164, 0.471, 0.558],
        [0.128, 0.567, 0.551],
        [0.135, 0.659, 0.518],
        [0.267, 0.749, 0.441],
        [0.478, 0.821, 0.318],
        [0.741, 0.873, 0.150],
        [0.993, 0.906, 0.144],
    ]
)
RADIANCE_LAYERS = ("denoised", "noisy")
LAMBDA_RANGE = (1.0, 10.0)


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear → sRGB transfer curve (IEC 61966-2-1), input clamped to [0, 1]."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def tonemap(rgb: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """(H, W, 3) linear radiance → (H, W, 3) uint8: scale by 2^exposure, sRGB, clamp."""
    scaled = np.nan_to_num(rgb.astype(np.float64), nan=0.0, posinf=1.0, neginf=0.0) * 2.0**exposure
    return np.round(srgb_encode(scaled) * 255).astype(np.uint8)


def colormap(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """(H, W) scalars → (H, W, 3) uint8 viridis, `lo` dark to `hi` bright."""
    span = hi - lo if hi > lo else 1.0
    t = np.clip((np.nan_to_num(values.astype(np.float64)) - lo) / span, 0.0, 1.0)
    position = t * (len(_VIRIDIS) - 1)
    index = np.minimum(position.astype(int), len(_VIRIDIS) - 2)
    frac = (position - index)[..., None]
    rgb = _VIRIDIS[index] * (1 - frac) + _VIRIDIS[index + 1] * frac
    return np.round(rgb * 255).astype(np.uint8)


def _scalar_range(layer: str, values: np.ndarray) -> tuple[float, float]:
    if layer == "lambda":
        return LAMBDA_RANGE  # fixed, so the same λ always looks the same
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return 0.0, 1.0
    # Error maps have a few extreme pixels: normalise to the 99th percentile, not the max.
    hi = float(np.percentile(finite, 99)) if layer == "error" else float(finite.max())
    return 0.0, hi


def to_rgb8(layer: str, values: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    if layer in RADIANCE_LAYERS:
        return tonemap(values, exposure)
    lo, hi = _scalar_range(layer, values)
    return colormap(values.reshape(values.shape[:2]), lo, hi)


def png_bytes(rgb8: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(rgb8, mode="RGB").save(buffer, format="PNG")
    return buffer.getvalue()


def exr_bytes(layer: str, values: np.ndarray) -> bytes:
    """The raw layer as an EXR in the project layout (radiance as R,G,B; scalars by name)."""
    from service.exr import ExrFrame, write_exr

    field = {"denoised": "color", "noisy": "noisy", "error": "error", "lambda": "lam"}.get(layer, layer)
    if layer == "spp":
        values = values.astype(np.uint32)
    frame = ExrFrame(**{field: values}, header={"layer": layer})
    handle, name = tempfile.mkstemp(suffix=".exr")
    os.close(handle)
    try:
        write_exr(name, frame)
        return Path(name).read_bytes()
    finally:
        os.unlink(name)
