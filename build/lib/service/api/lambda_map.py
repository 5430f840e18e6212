"""Turn the three forms of PUT /jobs/{id}/lambda into one (H, W) float32 λ map."""
from __future__ import annotations

import io

import numpy as np
from PIL import Image, UnidentifiedImageError

from service.api.schemas import LambdaRect
from service.exr import ExrError, exr_channels_from_bytes
from service.loop.spec import lambda_problem

MAX_MAP_BYTES = 64 * 1024 * 1024
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
    if image.mode not in ("L", "I", "I;16", "F"):
        raise LambdaMapError(f"λ map must be single-channel (grey), got image mode {image.mode}")
    return np.asarray(image)


def decode_map(data: bytes, shape: tuple[int, int]) -> np.ndarray:
    """An uploaded single-channel image whose pixel values are λ, checked against the job."""
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
