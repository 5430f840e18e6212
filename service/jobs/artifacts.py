"""The files one job keeps under `DATA/jobs/<id>/`.

    bundle/            the uploaded scene bundle (checked by service.jobs.bundle), its files hard
                       links to `DATA/blobs/` (service/jobs/blobs.py: one copy per content)
    state/             the loop checkpoint (service/jobs/checkpoints.py)
    lambda.npy         the job's current λ map (H, W) float32; newest request wins
    previews/frame_NNN.npz   latest preview layers of one frame plus their version
    result/frame_NNN.exr     the final multi-layer EXR per frame

Every write goes to a temporary name first and is renamed into place, so a reader (or a
restart after `kill -9`) sees either the old or the new file, never half of one.
"""
from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.atomic import atomic_write, atomic_write_bytes
from service.exr import ExrFrame, write_exr
from service.jobs.checkpoints import JobCheckpoint

PREVIEW_LAYERS = ("denoised", "noisy", "error", "spp", "lambda")


@dataclass
class Preview:
    """One frame's preview layers at one version; absent layers are None."""

    version: int
    layers: dict[str, np.ndarray | None]


class JobFiles:
    """Paths and atomic reads/writes for one job's artifacts folder."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)

    @property
    def data_dir(self) -> Path:
        """DATA of `DATA/jobs/<id>/`: where the shared blobs live."""
        return self.root.parent.parent

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

    @property
    def checkpoint(self) -> JobCheckpoint:
        """The job's checkpoint in `state/` (service/jobs/checkpoints.py owns it); a running
        job keeps one instance for its background writes."""
        return JobCheckpoint(self.state_dir, name=self.root.name[:8])

    # -- λ map ----------------------------------------------------------------------------------

    def save_lambda(self, lam: np.ndarray) -> None:
        buffer = io.BytesIO()
        np.save(buffer, np.ascontiguousarray(lam, dtype=np.float32))
        atomic_write_bytes(self.lambda_path, buffer.getvalue())

    def load_lambda(self) -> np.ndarray | None:
        if not self.lambda_path.is_file():
            return None
        return np.load(self.lambda_path)

    # -- previews -------------------------------------------------------------------------------

    def save_preview(self, frame: int, preview: Preview) -> None:
        arrays = {name: value for name, value in preview.layers.items() if value is not None}
        buffer = io.BytesIO()
        np.savez(buffer, version=np.int64(preview.version), **arrays)
        atomic_write_bytes(self.preview_path(frame), buffer.getvalue())

    def load_preview(self, frame: int) -> Preview | None:
        path = self.preview_path(frame)
        if not path.is_file():
            return None
        with np.load(path) as data:
            layers = {name: (data[name] if name in data.files else None) for name in PREVIEW_LAYERS}
            return Preview(version=int(data["version"]), layers=layers)

    def save_results(self, frames: list[ExrFrame]) -> None:
        """Write one EXR per frame, each renamed into place."""
        for index, frame in enumerate(frames):
            atomic_write(self.result_path(index), lambda tmp, frame=frame: write_exr(tmp, frame))
