"""Display transforms for previews: HDR radiance → sRGB PNG, scalar maps → false colour."""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from PIL import Image

SRGB_GAMMA_CUTOFF = 0.0031308  # IEC 61966-2-1 piecewise sRGB transfer function
SRGB_LINEAR_SLOPE = 12.92


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(np.nan_to_num(x, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    return np.where(x <= SRGB_GAMMA_CUTOFF, SRGB_LINEAR_SLOPE * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def tonemap(radiance: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """(H, W, 3) linear HDR → (H, W, 3) uint8 sRGB, clipped like a film's display transform."""
    return (linear_to_srgb(radiance * exposure) * 255 + 0.5).astype(np.uint8)


def false_colour(values: np.ndarray, vmax: float | None = None) -> np.ndarray:
    """(H, W) non-negative map → (H, W, 3) uint8, black → red → yellow → white ("heat")."""
    v = np.nan_to_num(np.asarray(values, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    top = vmax if vmax is not None else (np.percentile(v, 99) if v.size else 1.0)
    t = np.clip(v / top, 0, 1) if top > 0 else np.zeros_like(v)
    rgb = np.stack([np.clip(3 * t, 0, 1), np.clip(3 * t - 1, 0, 1), np.clip(3 * t - 2, 0, 1)], axis=-1)
    return (rgb * 255 + 0.5).astype(np.uint8)


def png_bytes(rgb8: np.ndarray) -> bytes:
    out = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb8)).save(out, format="PNG")
    return out.getvalue()


def write_png(path: str | Path, rgb8: np.ndarray) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(png_bytes(rgb8))
    return path
