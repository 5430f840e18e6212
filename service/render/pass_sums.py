"""One render call's per-pixel sums, kept on the device across its chunks and read back once.

Each chunk used to come back as its own float64 numpy block, added into the FrameBuffer on the
host, with a read-back (a sync) per chunk: host and device never overlapped, and on a GPU the
host's adds and copies were most of a pass (bench/wavefront_probe.py --history). Here every chunk
of the pass adds into film-sized device arrays, one per FrameBuffer quantity and laid out as it
is (pixel-major, its channels adjacent), so the host reads each pixel once per pass and adds it
with contiguous numpy operations.

Float64 on the device. In float32, a pixel whose lanes straddle two of the LLVM backend's
work blocks (16 384 lanes) got its packets' partial sums from two threads in either order, and
two renders of one seed differed in the last bit at ~1 pixel in 16 000 (measured at 256²,
counts 0–40, 2^18-lane chunks). A float32 sample is exact in float64,
and so is a sum of a few of them unless their exponents lie ~29 binary orders apart, so the
order of the adds no longer shows: three renders bit-identical. The per-chunk float32 sums the
host used to widen to float64 differ from these by float32 rounding (≤ 1.1e-7 of the largest
sum, over box, tent, Gaussian, stratified, AOV and motion passes).
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np

from service.render.framebuffer import FrameBuffer


@dataclass(frozen=True)
class Quantity:
    """One FrameBuffer running sum and its channels per pixel."""

    buffer_field: str
    channels: int


BASE_QUANTITIES = (Quantity("radiance_sum", 3), Quantity("radiance_sq_sum", 3), Quantity("albedo_sum", 3),
                   Quantity("normal_sum", 3), Quantity("depth_sum", 1))
MOTION = Quantity("motion_sum", 2)


def quantities(motion: bool, aov_count: int) -> tuple[Quantity, ...]:
    """What a pass sums per pixel, in _trace_chunk's channel order."""
    extra = ((MOTION,) if motion else ()) + ((Quantity("aov_sum", aov_count),) if aov_count else ())
    return BASE_QUANTITIES + extra


class PassSums:
    """Device arrays of one render call's per-pixel sums and its count of non-finite samples."""

    def __init__(self, mi, pixel_count: int, motion: bool, aov_count: int):
        self.mi = mi
        self.quantities = quantities(motion, aov_count)
        self.arrays = [dr.zeros(mi.Float64, pixel_count * q.channels) for q in self.quantities]
        self.nonfinite = dr.zeros(mi.UInt32, 1)

    @property
    def channels(self) -> int:
        return sum(q.channels for q in self.quantities)

    def add(self, pixel, channels: list, finite) -> None:
        """Scatter one chunk's per-lane `channels` (in `quantities` order) to their `pixel`
        (device UInt32), and count the lanes that are not `finite`. Lanes of one pixel are
        consecutive, so Dr.Jit reduces them within a packet before its atomic (ReduceMode.Auto;
        the whole 13-channel scatter of a 1080p × 16 spp pass was 1.4 ms on an H100)."""
        if len(channels) != self.channels:
            raise ValueError(f"{len(channels)} channels for sums of {self.channels}")
        at = 0
        for quantity, target in zip(self.quantities, self.arrays):
            for c in range(quantity.channels):
                dr.scatter_reduce(dr.ReduceOp.Add, target, self.mi.Float64(channels[at + c]),
                                  pixel * quantity.channels + c)
            at += quantity.channels
        dr.scatter_reduce(dr.ReduceOp.Add, self.nonfinite, self.mi.UInt32(1), self.mi.UInt32(0), ~finite)

    @property
    def device_arrays(self) -> list:
        """What each chunk's kernel writes (to be evaluated with it)."""
        return [*self.arrays, self.nonfinite]

    def add_to(self, buffer: FrameBuffer) -> int:
        """Read the sums back (once per pass), add them to `buffer`'s float64 sums, and return
        the number of non-finite samples that were dropped."""
        for quantity, array in zip(self.quantities, self.arrays):
            target = getattr(buffer, quantity.buffer_field)   # (H, W) or (H, W, channels)
            np.add(target, np.asarray(array).reshape(target.shape), out=target)
        return int(np.asarray(self.nonfinite)[0])
