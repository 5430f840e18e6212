"""Preview images for people: radiance tonemapped, scalar maps colour-mapped, both to 8-bit PNG,
or the raw float values as a single-layer EXR."""
from __future__ import annotations

import numpy as np

from service.exr import ExrFrame, exr_to_bytes
from service.images import colormap, tonemap
from service.loop.spec import LAMBDA_RANGE

RADIANCE_LAYERS = ("denoised", "noisy")


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


def exr_bytes(layer: str, values: np.ndarray) -> bytes:
    """The raw layer as an EXR in the project layout (radiance as R,G,B; scalars by name)."""
    field = {"denoised": "color", "noisy": "noisy", "error": "error", "lambda": "lam"}.get(layer, layer)
    if layer == "spp":
        values = values.astype(np.uint32)
    return exr_to_bytes(ExrFrame(**{field: values}, header={"layer": layer}))
