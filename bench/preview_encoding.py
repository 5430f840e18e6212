"""What a PNG preview costs the server to make, on the preview a λ edit just made: the tonemap,
then the PNG at Pillow's default zlib level and at the service's PREVIEW_PNG_LEVEL, interleaved
round by round in one process so the host's load hits each alike (the side-by-side figure behind
service.api.imaging.PREVIEW_PNG_LEVEL; `renderloop bench --lambda-edit` reports it)."""
from __future__ import annotations

import statistics
import time
from dataclasses import dataclass

import numpy as np

from service.api.imaging import PREVIEW_PNG_LEVEL
from service.images import png_bytes, tonemap

DEFAULT_PNG_LEVEL = 6  # Pillow's (zlib's) default, what previews were encoded at before


@dataclass(frozen=True)
class PreviewEncoding:
    width: int
    height: int
    tonemap_ms: float
    png_ms: dict[int, float]  # zlib level → median ms
    png_mb: dict[int, float]  # zlib level → size in MB


def time_preview_encoding(radiance: np.ndarray, repeats: int = 5) -> PreviewEncoding:
    """Median ms of the tonemap and of each PNG level over `repeats` interleaved rounds (after one
    untimed round); the levels' PNGs must hold the same pixels (both are lossless)."""
    levels = (DEFAULT_PNG_LEVEL, PREVIEW_PNG_LEVEL)
    rgb = tonemap(radiance)
    sizes = {level: len(png_bytes(rgb, level)) / 1e6 for level in levels}
    times: dict[str, list[float]] = {"tonemap": [], **{str(level): [] for level in levels}}
    for _ in range(repeats):
        started = time.perf_counter()
        tonemap(radiance)
        times["tonemap"].append(time.perf_counter() - started)
        for level in levels:
            started = time.perf_counter()
            png_bytes(rgb, level)
            times[str(level)].append(time.perf_counter() - started)
    median_ms = {key: 1e3 * statistics.median(values) for key, values in times.items()}
    height, width = rgb.shape[:2]
    return PreviewEncoding(width, height, median_ms["tonemap"], {level: median_ms[str(level)] for level in levels}, sizes)


def encoding_line(encoding: PreviewEncoding) -> str:
    """The report's sentence for one measurement."""
    default, fast = encoding.png_ms[DEFAULT_PNG_LEVEL], encoding.png_ms[PREVIEW_PNG_LEVEL]
    return (f"The preview's PNG, side by side on the last edited {encoding.width}×{encoding.height} preview (fetched as "
            f"EXR; bench/preview_encoding.py, interleaved, medians): tonemap {encoding.tonemap_ms:.0f} ms, PNG at zlib "
            f"level {DEFAULT_PNG_LEVEL} (Pillow's default, the previews' before) {default:.0f} ms / "
            f"{encoding.png_mb[DEFAULT_PNG_LEVEL]:.2f} MB, at level {PREVIEW_PNG_LEVEL} (the service's now, "
            f"`PREVIEW_PNG_LEVEL`) {fast:.0f} ms / {encoding.png_mb[PREVIEW_PNG_LEVEL]:.2f} MB, the same pixels.")
