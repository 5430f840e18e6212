"""The one bridge between numpy images (HWC) and the networks' tensors (NCHW), both ways."""
from __future__ import annotations

import os

import numpy as np
import torch

from models.frames import FrameTensors
from service.render.framebuffer import FrameBuffer


TORCH_THREADS_ENV = "RENDERLOOP_TORCH_THREADS"


def configure_torch_threads() -> None:
    """Honour RENDERLOOP_TORCH_THREADS: on a busy 2-core host, torch's default of one thread per
    core made a 64² denoise 30× slower than one thread (docs/benchmarks.md, Notes)."""
    value = os.environ.get(TORCH_THREADS_ENV)
    if value:
        try:
            threads = int(value)
        except ValueError:
            raise ValueError(f"{TORCH_THREADS_ENV} must be a positive integer, got {value!r}") from None
        if threads < 1:
            raise ValueError(f"{TORCH_THREADS_ENV} must be a positive integer, got {value!r}")
        torch.set_num_threads(threads)


def nchw(array: np.ndarray) -> torch.Tensor:
    if array.ndim == 2:
        array = array[..., None]
    return torch.from_numpy(np.ascontiguousarray(array.transpose(2, 0, 1), dtype=np.float32))[None]


def frame_tensors(buffer: FrameBuffer) -> FrameTensors:
    motion = buffer.motion
    return FrameTensors(
        color=nchw(buffer.mean),
        variance=nchw(buffer.variance),
        albedo=nchw(buffer.albedo),
        normal=nchw(buffer.normal),
        depth=nchw(buffer.depth),
        motion=None if motion is None else nchw(motion),
        spp=nchw(buffer.spp.astype(np.float32)),
    )


def to_image(tensor: torch.Tensor) -> np.ndarray:
    """(1, C, H, W) tensor → (H, W, C) float32 array (C = 1 squeezed)."""
    image = tensor[0].detach().float().permute(1, 2, 0).cpu().numpy()
    return np.ascontiguousarray(image[..., 0] if image.shape[-1] == 1 else image)


def temporal_window(frame: int, frames: int, radius: int) -> tuple[list[int], int]:
    """Indices of the 2M+1 window around `frame`, clipped to the sequence, and the centre's position."""
    lo, hi = max(0, frame - radius), min(frames - 1, frame + radius)
    return list(range(lo, hi + 1)), frame - lo


def lam_tensor(lam_map: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(lam_map, dtype=np.float32))[None, None]
