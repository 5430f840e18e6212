"""Which pixel each lane of a wavefront chunk traces, built on the device.

A pass gives pixel p exactly n_p lanes, consecutive and in pixel order (docs/design.md, "Runtime
facts"). Expanding that map on the host (np.repeat: 33 M uint32 at 1080p × 16 spp) and
uploading it per chunk was host work per *sample*; on a GPU the host's share of a pass was ~80 %
(bench/wavefront_probe.py --history, H100: 920 ms wall, 163 ms of kernels). Here the host
describes a chunk per *row* — the pixels it touches and how many lanes each gets — and the
device expands it:

- a uniform count needs nothing uploaded: lane l of a chunk starting at pixel p0, r lanes into
  it, traces pixel p0 + (l + r) // n;
- uneven runs put a 1 at the first lane of every row but the first and take the inclusive prefix
  sum (a stream compaction's inverse, Blelloch 1990, "Prefix sums and their applications"):
  lane l's row is the number of row starts at or before it. O(lanes) on the device, O(rows) on
  the host, where dr.repeat's binary search would cost log2(rows) gathers per lane.

Every per-chunk number reaches the kernel as an opaque value or an array, never a literal, so one
kernel serves every chunk and pass (a literal first pixel built a new kernel per chunk, ~0.34 s
each on the LLVM backend: tests/render/test_renderer.py).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import drjit as dr
import numpy as np

# Bytes: what Dr.Jit's LLVM backend takes as an aligned input array (see `aligned`).
KERNEL_ALIGNMENT = 64


def aligned(array: np.ndarray) -> np.ndarray:
    """`array` (contiguous) with its data on a 64-byte boundary. Dr.Jit's LLVM backend reads a
    numpy array in place and writes its alignment into the kernel (`align 64` or `align 1`),
    so the same kernel hashed differently whenever malloc placed a small lane array elsewhere
    and was built again (~0.4 s each; seen on 2 of 8 digit groups per pass, stratified_lanes.py)."""
    array = np.ascontiguousarray(array)
    if array.ctypes.data % KERNEL_ALIGNMENT == 0:
        return array
    raw = np.empty(array.nbytes + KERNEL_ALIGNMENT, dtype=np.uint8)
    start = -raw.ctypes.data % KERNEL_ALIGNMENT
    out = raw[start:start + array.nbytes].view(array.dtype).reshape(array.shape)
    out[...] = array
    return out


def upload(mi, array: np.ndarray):
    """A host uint32 array as a device mi.UInt32 (aligned, so the kernel's hash stays put)."""
    return mi.UInt32(aligned(np.asarray(array, dtype=np.uint32)))


@dataclass(frozen=True)
class ChunkRows:
    """One chunk's `size` lanes as runs, in lane order: row k is pixel `pixels[k]` with
    `lanes[k]` ≥ 1 consecutive lanes. A uniform chunk (`uniform` = n > 0 lanes per pixel) has no
    arrays: its lanes continue pixel `first_pixel`, of which `skipped` lanes were traced by the
    previous chunk."""

    size: int
    pixels: np.ndarray | None = None     # row → flat pixel index (int64, ascending)
    lanes: np.ndarray | None = None      # row → lanes in this chunk (int64, ≥ 1)
    uniform: int = 0
    first_pixel: int = 0
    skipped: int = 0


def independent_chunks(counts: np.ndarray, max_wavefront: int) -> Iterator[ChunkRows]:
    """The pass's lanes (pixel order, pixel p repeated counts[p] times) cut every max_wavefront
    lanes, each chunk as its rows; a pixel may straddle two chunks. O(pixels) over the pass."""
    flat = np.asarray(counts, dtype=np.int64).ravel()
    total = int(flat.sum())
    if not total:
        return
    if int(flat.min()) == int(flat.max()):
        spp = int(flat[0])
        for first in range(0, total, max_wavefront):
            yield ChunkRows(size=min(max_wavefront, total - first), uniform=spp,
                            first_pixel=first // spp, skipped=first % spp)
        return
    pixels = np.flatnonzero(flat)
    ends = np.cumsum(flat[pixels])
    for first in range(0, total, max_wavefront):
        last = min(first + max_wavefront, total)
        k0 = int(np.searchsorted(ends, first, side="right"))
        k1 = int(np.searchsorted(ends, last - 1, side="right")) + 1
        row_ends = np.minimum(ends[k0:k1], last)
        row_starts = np.maximum(ends[k0:k1] - flat[pixels[k0:k1]], first)
        yield ChunkRows(size=last - first, pixels=pixels[k0:k1], lanes=row_ends - row_starts)


def lane_rows(mi, rows: ChunkRows):
    """Each lane's row in the chunk (device UInt32); for a uniform chunk counted from
    `first_pixel`."""
    if rows.uniform:
        shifted = dr.arange(mi.UInt32, rows.size) + dr.opaque(mi.UInt32, rows.skipped)
        return shifted // dr.opaque(mi.UInt32, rows.uniform)
    if len(rows.lanes) == 1:
        return dr.zeros(mi.UInt32, rows.size)
    marks = dr.zeros(mi.UInt32, rows.size)
    dr.scatter(marks, mi.UInt32(1), upload(mi, _run_starts(rows)[1:]))
    return dr.prefix_reduce(dr.ReduceOp.Add, marks, exclusive=False)


def lane_within_row(mi, rows: ChunkRows, row):
    """Each lane's index within its row's run (device UInt32), from its `row` (lane_rows)."""
    lane = dr.arange(mi.UInt32, rows.size)
    if rows.uniform:
        return lane + dr.opaque(mi.UInt32, rows.skipped) - row * dr.opaque(mi.UInt32, rows.uniform)
    return lane - dr.gather(mi.UInt32, upload(mi, _run_starts(rows)), row)


def _run_starts(rows: ChunkRows) -> np.ndarray:
    """Each row's first lane in the chunk."""
    return np.cumsum(rows.lanes) - rows.lanes


def row_pixels(mi, rows: ChunkRows, row):
    """The flat pixel (device UInt32) of each lane, from its `row` (lane_rows)."""
    if rows.uniform:
        return row + dr.opaque(mi.UInt32, rows.first_pixel)
    return dr.gather(mi.UInt32, upload(mi, rows.pixels), row)


def lane_pixels(mi, rows: ChunkRows):
    """Lane → flat pixel index (device UInt32) of the chunk, rows expanded on the device."""
    return row_pixels(mi, rows, lane_rows(mi, rows))
