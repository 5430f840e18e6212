"""The checkpoint's files on disk: how a LoopState is written to and read from a folder.

A checkpoint folder (`DATA/jobs/<id>/state/`) holds
- `frame_<i>.npz`, one per frame: the FrameBuffer's sums by their field names (REQUIRED_ARRAYS
  always; `motion_sum`, `aov_sum` and the splat sums SPLAT_ARRAYS when the buffer has them) and
  `error`, the last predicted SMAPE map, once one was predicted;
- `lambda.npy`, the (H, W) float32 λ map all frames share;
- `state.json`: `version` (STATE_VERSION), `iteration`, `elapsed`, `frames`, per-frame `passes`
  and `aov_names`.

Writes are atomic: the folder is built beside the target as `<name>.tmp` and swapped in with
two renames (the old one to `<name>.old`, the new one in place), so a crash mid-write leaves the
previous checkpoint readable; a kill between the two renames leaves only `<name>.old`, which
`read_state` falls back to. When (and on which thread) a job writes is service/jobs/checkpoints.py's.
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np

from service.loop.state import LoopState
from service.render.framebuffer import SPLAT_ARRAYS, FrameBuffer

# Bump only with a reader for the old version: a restart must resume every job on disk.
STATE_VERSION = 1
REQUIRED_ARRAYS = ("radiance_sum", "radiance_sq_sum", "spp", "albedo_sum", "normal_sum", "depth_sum")
# Present only when the buffer has them: motion (animated scenes), the integrator's own AOVs,
# the raw image's splat sums (absent under a box filter).
OPTIONAL_ARRAYS = ("motion_sum", "aov_sum") + SPLAT_ARRAYS
ERROR_ARRAY = "error"
META_FILE, LAMBDA_FILE = "state.json", "lambda.npy"


def frame_file(index: int) -> str:
    return f"frame_{index}.npz"


def _sibling(directory: Path, suffix: str) -> Path:
    return directory.with_name(directory.name + suffix)


def frame_arrays(buf: FrameBuffer, error: np.ndarray | None) -> dict[str, np.ndarray]:
    """What one frame's npz holds: the buffer's arrays by field name, and its error map."""
    arrays = {name: getattr(buf, name) for name in REQUIRED_ARRAYS}
    arrays.update({name: getattr(buf, name) for name in OPTIONAL_ARRAYS if getattr(buf, name) is not None})
    if error is not None:
        arrays[ERROR_ARRAY] = error
    return arrays


def state_meta(state: LoopState) -> dict:
    return {"version": STATE_VERSION, "iteration": state.iteration, "elapsed": state.elapsed,
            "frames": len(state.buffers), "passes": [b.passes for b in state.buffers],
            "aov_names": [list(b.aov_names) for b in state.buffers]}


def write_state(state: LoopState, directory: str | Path) -> Path:
    """Write `state` to `directory` atomically: a crash mid-write leaves the previous one intact."""
    directory = Path(directory)
    tmp = _sibling(directory, ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for i, buf in enumerate(state.buffers):
        np.savez(tmp / frame_file(i), **frame_arrays(buf, state.error_maps[i]))
    np.save(tmp / LAMBDA_FILE, state.lam_map)
    (tmp / META_FILE).write_text(json.dumps(state_meta(state)))
    old = _sibling(directory, ".old")
    shutil.rmtree(old, ignore_errors=True)
    if directory.exists():
        os.replace(directory, old)
    os.replace(tmp, directory)
    shutil.rmtree(old, ignore_errors=True)
    return directory


def holds_state(directory: str | Path) -> bool:
    """Whether `directory` holds a checkpoint `read_state` can read (a kill between
    `write_state`'s two renames leaves only the `.old` copy)."""
    directory = Path(directory)
    return (directory / META_FILE).is_file() or (_sibling(directory, ".old") / META_FILE).is_file()


def _read_frame(path: Path, aov_names: list[str], passes: int) -> tuple[FrameBuffer, np.ndarray | None]:
    with np.load(path) as data:
        buf = FrameBuffer(**{name: data[name] for name in REQUIRED_ARRAYS})
        for name in OPTIONAL_ARRAYS:
            setattr(buf, name, data[name] if name in data else None)
        error = data[ERROR_ARRAY] if ERROR_ARRAY in data else None
    buf.aov_names = tuple(aov_names)
    buf.passes = passes
    return buf, error


def read_state(directory: str | Path) -> LoopState:
    """The LoopState written to `directory`; ValueError for a version this reader does not know."""
    directory = Path(directory)
    if not (directory / META_FILE).exists() and _sibling(directory, ".old").exists():
        directory = _sibling(directory, ".old")  # killed between the two renames
    meta = json.loads((directory / META_FILE).read_text())
    if meta.get("version") != STATE_VERSION:
        raise ValueError(f"checkpoint {directory} has version {meta.get('version')}, expected {STATE_VERSION}")
    frames = meta["frames"]
    aov_names = meta.get("aov_names", [[]] * frames)
    read = [_read_frame(directory / frame_file(i), aov_names[i], meta["passes"][i]) for i in range(frames)]
    return LoopState(iteration=meta["iteration"], buffers=[buf for buf, _ in read],
                     lam_map=np.load(directory / LAMBDA_FILE), error_maps=[error for _, error in read],
                     elapsed=meta["elapsed"])
