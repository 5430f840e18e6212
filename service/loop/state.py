"""What the loop must keep to resume after a crash: buffers, λ map, error maps, clock."""
from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from service.render.framebuffer import SPLAT_ARRAYS, FrameBuffer

STATE_VERSION = 1
BUFFER_ARRAYS = ("radiance_sum", "radiance_sq_sum", "spp", "albedo_sum", "normal_sum", "depth_sum")
COPIED_ARRAYS = BUFFER_ARRAYS + ("motion_sum", "aov_sum") + SPLAT_ARRAYS  # every array field of a FrameBuffer


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

    def save(self, directory: str | Path) -> Path:
        """Write atomically: a crash mid-save leaves the previous checkpoint intact."""
        directory = Path(directory)
        tmp = directory.with_name(directory.name + ".tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        for i, buf in enumerate(self.buffers):
            arrays = {name: getattr(buf, name) for name in BUFFER_ARRAYS}
            if buf.motion_sum is not None:
                arrays["motion_sum"] = buf.motion_sum
            if buf.aov_sum is not None:  # the scene integrator's own AOV channels
                arrays["aov_sum"] = buf.aov_sum
            arrays.update({name: getattr(buf, name) for name in SPLAT_ARRAYS if getattr(buf, name) is not None})
            if self.error_maps[i] is not None:
                arrays["error"] = self.error_maps[i]
            np.savez(tmp / f"frame_{i}.npz", **arrays)
        np.save(tmp / "lambda.npy", self.lam_map)
        meta = {"version": STATE_VERSION, "iteration": self.iteration, "elapsed": self.elapsed,
                "frames": len(self.buffers), "passes": [b.passes for b in self.buffers],
                "aov_names": [list(b.aov_names) for b in self.buffers]}
        (tmp / "state.json").write_text(json.dumps(meta))
        old = directory.with_name(directory.name + ".old")
        shutil.rmtree(old, ignore_errors=True)
        if directory.exists():
            os.replace(directory, old)
        os.replace(tmp, directory)
        shutil.rmtree(old, ignore_errors=True)
        return directory

    @staticmethod
    def exists(directory: str | Path) -> bool:
        """Whether `directory` holds a checkpoint `load` can read (a kill between `save`'s two
        renames leaves only the `.old` copy)."""
        directory = Path(directory)
        old = directory.with_name(directory.name + ".old")
        return (directory / "state.json").is_file() or (old / "state.json").is_file()

    @classmethod
    def load(cls, directory: str | Path) -> "LoopState":
        directory = Path(directory)
        if not (directory / "state.json").exists() and directory.with_name(directory.name + ".old").exists():
            directory = directory.with_name(directory.name + ".old")  # crashed between the two renames
        meta = json.loads((directory / "state.json").read_text())
        if meta.get("version") != STATE_VERSION:
            raise ValueError(f"checkpoint {directory} has version {meta.get('version')}, expected {STATE_VERSION}")
        buffers, errors = [], []
        for i in range(meta["frames"]):
            with np.load(directory / f"frame_{i}.npz") as data:
                buf = FrameBuffer(**{name: data[name] for name in BUFFER_ARRAYS})
                buf.motion_sum = data["motion_sum"] if "motion_sum" in data else None
                buf.aov_sum = data["aov_sum"] if "aov_sum" in data else None
                for name in SPLAT_ARRAYS:  # the raw image's splat sums (absent under a box filter)
                    setattr(buf, name, data[name] if name in data else None)
                buf.aov_names = tuple(meta.get("aov_names", [[]] * meta["frames"])[i])
                buf.passes = meta["passes"][i]
                errors.append(data["error"] if "error" in data else None)
            buffers.append(buf)
        return cls(meta["iteration"], buffers, np.load(directory / "lambda.npy"), errors, meta["elapsed"])


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
