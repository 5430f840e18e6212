"""Turn the three forms of PUT /jobs/{id}/lambda into one (H, W) float32 λ map."""
from __future__ import annotations

import io

import numpy as np
from PIL import Image, UnidentifiedImageError

from service.api.schemas import LambdaRect
from service.exr import ExrError, exr_channels_from_bytes
from service.loop.spec import LAMBDA_RANGE, lambda_problem

MAX_MAP_BYTES = 64 * 1024 * 1024
# Integer image modes → their full-scale value; "I" is how Pillow may open a 16-bit PNG.
MASK_FULL_SCALE = {"L": 255.0, "I;16": 65535.0, "I": 65535.0}
EXR_MAGIC = b"\x76\x2f\x31\x01"


class LambdaMapError(ValueError):
    """The λ request cannot be applied to this image (422); the message says why."""


def constant(shape: tuple[int, int], value: float) -> np.ndarray:
    return np.full(shape, value, dtype=np.float32)


def paint_rects(base: np.ndarray, rects: list[LambdaRect]) -> np.ndarray:
    """Rectangles painted over `base` in order; each must overlap the image."""
    height, width = base.shape
    lam = base.astype(np.float32, copy=True)
    for i, rect in enumerate(rects):
        if rect.x >= width or rect.y >= height:
            raise LambdaMapError(f"rects[{i}] starts at ({rect.x}, {rect.y}), outside the {width}×{height} image")
        lam[rect.y : rect.y + rect.h, rect.x : rect.x + rect.w] = rect.value  # clipped at the edges
    return lam


def _decode_exr(data: bytes, max_pixels: int) -> np.ndarray:
    try:
        channels = exr_channels_from_bytes(data, max_pixels=max_pixels)
    except ExrError as exc:
        raise LambdaMapError(f"λ map: {exc}") from exc
    if "lambda" in channels:
        return channels["lambda"]
    if len(channels) == 1:
        return next(iter(channels.values()))
    raise LambdaMapError(f"λ map EXR must have one channel or a 'lambda' channel, found {sorted(channels)}")


def _decode_image(data: bytes, max_pixels: int) -> np.ndarray:
    try:
        image = Image.open(io.BytesIO(data))  # reads the header only
        if image.width * image.height > max_pixels:
            raise LambdaMapError(f"λ map declares a {image.width}x{image.height} image; "
                                 f"at most {max_pixels} pixels are accepted")
        image.load()
    except (UnidentifiedImageError, OSError, Image.DecompressionBombError) as exc:
        raise LambdaMapError("λ map is neither a PNG nor an EXR image") from exc
    if image.mode not in MASK_FULL_SCALE and image.mode != "F":
        raise LambdaMapError(f"λ map must be single-channel (grey), got image mode {image.mode}")
    values = np.asarray(image, dtype=np.float32)
    if image.mode == "F":
        return values  # float pixels are λ itself, like an EXR's
    return mask_to_lambda(values, MASK_FULL_SCALE[image.mode])


def mask_to_lambda(values: np.ndarray, full_scale: float) -> np.ndarray:
    """An integer grey mask (what a paint program saves) spans LAMBDA_RANGE linearly:
    0 → the smallest λ (smoothest), full scale → the largest (most detail)."""
    low, high = LAMBDA_RANGE
    if values.size and float(values.max()) > full_scale:
        raise LambdaMapError(f"λ mask values must lie in [0, {full_scale:g}]")
    return (low + (high - low) * values / full_scale).astype(np.float32)


def decode_map(data: bytes, shape: tuple[int, int]) -> np.ndarray:
    """An uploaded single-channel image, checked against the job: EXR (or float) pixels are
    λ itself; an 8- or 16-bit grey PNG is a mask mapped linearly onto LAMBDA_RANGE."""
    if len(data) > MAX_MAP_BYTES:
        raise LambdaMapError(f"λ map upload exceeds {MAX_MAP_BYTES // (1024 * 1024)} MiB")
    # Header first: a few hundred KB can declare gigapixels. Nothing larger than the job's
    # own image can be right, so that is the cap.
    max_pixels = shape[0] * shape[1]
    values = _decode_exr(data, max_pixels) if data[:4] == EXR_MAGIC else _decode_image(data, max_pixels)
    values = np.asarray(values, dtype=np.float32)
    if values.ndim != 2:
        raise LambdaMapError(f"λ map must be single-channel, got shape {values.shape}")
    if values.shape != shape:
        raise LambdaMapError(
            f"λ map is {values.shape[1]}×{values.shape[0]}, the job's image is {shape[1]}×{shape[0]}"
        )
    problem = lambda_problem(values)
    if problem:
        raise LambdaMapError(f"λ map: {problem}; got [{float(np.nanmin(values)):g}, {float(np.nanmax(values)):g}]")
    return values
