"""The files one job keeps under `DATA/jobs/<id>/`.

    bundle/            the uploaded scene bundle (checked by service.jobs.bundle)
    state/             the loop checkpoint (LoopState.save/load)
    lambda.npy         the job's current λ map (H, W) float32; newest request wins
    previews/frame_NNN.npz   latest preview layers of one frame plus their version
    result/frame_NNN.exr     the final multi-layer EXR per frame

Every write goes to a temporary name first and is renamed into place, so a reader (or a
restart after `kill -9`) sees either the old or the new file, never half of one.
"""
from __future__ import annotations

import io
import os
import uuid
from dataclasses import dataclass
from pathlib import Path
import numpy as np

PREVIEW_LAYERS = ("denoised", "noisy", "error", "spp", "lambda")


@dataclass
class Preview:
    """One frame's preview layers at one version; absent layers are None."""

    version: int
    layers: dict[str, np.ndarray | None]


def _atomic_bytes(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.{uuid.uuid4().hex}.tmp")  # unique: writers may overlap
    with open(tmp, "wb") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)


class JobFiles:
    """Paths and atomic reads/writes for one job's artifacts folder."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)

    @property
    def bundle_dir(self) -> Path:
        return self.root / "bundle"

    @property
    def state_dir(self) -> Path:
        return self.root / "state"

    @property
    def lambda_path(self) -> Path:
        return self.root / "lambda.npy"

    def preview_path(self, frame: int) -> Path:
        return self.root / "previews" / f"frame_{frame:03d}.npz"

    def result_path(self, frame: int) -> Path:
        return self.root / "result" / f"frame_{frame:03d}.exr"

    # -- checkpoint (LoopState.save swaps it in atomically itself) ----------------------------

    def has_checkpoint(self) -> bool:
        old = self.root / "state.old"  # a kill between LoopState.save's two renames leaves this
        return (self.state_dir / "state.json").is_file() or (old / "state.json").is_file()

    # -- λ map ----------------------------------------------------------------------------------

    def save_lambda(self, lam: np.ndarray) -> None:
        buffer = io.BytesIO()
        np.save(buffer, np.ascontiguousarray(lam, dtype=np.float32))
        _atomic_bytes(self.lambda_path, buffer.getvalue())

    def load_lambda(self) -> np.ndarray | None:
        if not self.lambda_path.is_file():
            return None
        return np.load(self.lambda_path)

    # -- previews -------------------------------------------------------------------------------

    def save_preview(self, frame: int, preview: Preview) -> None:
        arrays = {name: value for name, value in preview.layers.items() if value is not None}
        buffer = io.BytesIO()
        np.savez(buffer, version=np.int64(preview.version), **arrays)
        _atomic_bytes(self.preview_path(frame), buffer.getvalue())

    def load_preview(self, frame: int) -> Preview | None:
        path = self.preview_path(frame)
        if not path.is_file():
            return None
        with np.load(path) as data:
            layers = {name: (data[name] if name in data.files else None) for name in PREVIEW_LAYERS}
            return Preview(version=int(data["version"]), layers=layers)

    def save_results(self, frames: list) -> None:
        """Write one EXR per frame (`service.exr.ExrFrame`s), each renamed into place."""
        from service.exr import write_exr  # OpenEXR only where results are written

        for index, frame in enumerate(frames):
            path = self.result_path(index)
            tmp = path.with_name(f"{path.stem}.{uuid.uuid4().hex}.tmp.exr")
            write_exr(tmp, frame)
            os.replace(tmp, path)
