"""What the loop must keep to resume after a crash: buffers, λ map, error maps, clock.

This is the state in memory only; its files on disk (the checkpoint format) are
service/jobs/checkpoint_format.py's, and when a job writes them service/jobs/checkpoints.py's.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from service.render.framebuffer import SPLAT_ARRAYS, FrameBuffer

# Every array field of a FrameBuffer: what a snapshot copies.
COPIED_ARRAYS = ("radiance_sum", "radiance_sq_sum", "spp", "albedo_sum", "normal_sum", "depth_sum",
                 "motion_sum", "aov_sum") + SPLAT_ARRAYS


@dataclass
class LoopState:
    iteration: int  # finished iterations
    buffers: list[FrameBuffer]
    lam_map: np.ndarray  # (H, W) float32, λ per pixel shared by all frames
    error_maps: list[np.ndarray | None] = field(default_factory=list)  # last predicted SMAPE per frame
    elapsed: float = 0.0  # loop wall time so far (seconds), so time limits survive restarts

    @classmethod
    def new(cls, frames: int, height: int, width: int, lam: float) -> "LoopState":
        return cls(
            iteration=0,
            buffers=[FrameBuffer.empty(height, width) for _ in range(frames)],
            lam_map=np.full((height, width), lam, dtype=np.float32),
            error_maps=[None] * frames,
        )

    @property
    def spp_mean(self) -> float:
        return float(np.mean([b.spp.mean() for b in self.buffers]))

    def snapshot(self, reuse: "LoopState | None" = None) -> "LoopState":
        """A copy the next iteration cannot change, for a checkpoint written in the background
        (service/jobs/checkpoint_writer.py): the buffers' sums, the error maps and the λ map
        are copied (the renderer adds to the sums in place; a λ edit may replace the map).
        `reuse`: an earlier snapshot nothing reads any more (its write landed), whose buffer
        arrays are overwritten instead of allocated again: at 2 MP a fresh copy's page faults
        cost more than the copy itself."""
        spares: list[FrameBuffer | None] = [None] * len(self.buffers)
        if reuse is not None and len(reuse.buffers) == len(self.buffers):
            spares = list(reuse.buffers)
        return LoopState(
            iteration=self.iteration,
            buffers=[_copy_buffer(buf, spare) for buf, spare in zip(self.buffers, spares)],
            lam_map=self.lam_map.copy(),  # small, and may live on in a published preview: never reused
            error_maps=[None if e is None else e.copy() for e in self.error_maps],
            elapsed=self.elapsed,
        )


def _copy_array(array: np.ndarray | None, spare: np.ndarray | None) -> np.ndarray | None:
    if array is None:
        return None
    if spare is not None and spare.shape == array.shape and spare.dtype == array.dtype:
        np.copyto(spare, array)
        return spare
    return array.copy()


def _copy_buffer(buf: FrameBuffer, spare: FrameBuffer | None) -> FrameBuffer:
    """FrameBuffer.copy, writing into `spare`'s arrays where their shapes match."""
    arrays = {name: _copy_array(getattr(buf, name), getattr(spare, name, None)) for name in COPIED_ARRAYS}
    return FrameBuffer(**arrays, aov_names=buf.aov_names, passes=buf.passes, meta=dict(buf.meta),
                       footprint=buf.footprint)
