"""PNG figures of the committed reports, rewritten only when the picture changed.

A report's re-run draws its figures again. Renders and denoises sum in parallel, so the same
content comes back a few pixel levels apart from run to run, and a byte-for-byte rewrite would
re-commit megabytes of images nobody can tell apart (docs/ held 6.9 MB of them). A figure is
therefore written only when there is none yet, its size changed, or more than
CHANGED_PIXEL_SHARE of its pixels moved by more than PIXEL_TOLERANCE levels: the images change
when what the report shows changes, not on every run.
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from PIL import Image

PIXEL_TOLERANCE = 8           # of 255: below what one can see side by side
CHANGED_PIXEL_SHARE = 0.001   # a figure with more pixels moved than this shows something new


def decoded(png: bytes) -> np.ndarray:
    with Image.open(io.BytesIO(png)) as image:
        return np.asarray(image.convert("RGBA"), dtype=np.int16)


def same_picture(old_png: bytes, new_png: bytes) -> bool:
    """True when the two PNGs show the same picture up to run-to-run noise."""
    old, new = decoded(old_png), decoded(new_png)
    if old.shape != new.shape:
        return False
    moved = np.abs(old - new).max(axis=-1) > PIXEL_TOLERANCE
    return float(moved.mean()) <= CHANGED_PIXEL_SHARE


def write_png_if_changed(path: Path, png: bytes) -> bool:
    """Write `png` to `path` unless the file there already shows the same picture; True if written."""
    if path.is_file() and same_picture(path.read_bytes(), png):
        return False
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(png)
    return True


def save_figure(fig, path: Path, **savefig_options) -> Path:
    """matplotlib's `fig.savefig(path, …)` as a PNG, keeping an existing file that shows the same."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", **savefig_options)
    write_png_if_changed(path, buffer.getvalue())
    return path
