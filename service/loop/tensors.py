"""The one bridge between numpy images (HWC) and the networks' tensors (NCHW), both ways."""
from __future__ import annotations

import os

import numpy as np
import torch

from models.exposure import Exposure
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


def frame_tensors(buffer: FrameBuffer, device: torch.device | str | None = None) -> FrameTensors:
    """The networks' input for one frame: every layer written from the buffer's sums straight
    into the planes of one (1, C, H, W) float32 host block (no HWC temporaries: ~3× less time at
    2 MP), which goes to `device` (default: stays on the host) in one copy; the fields are
    channel slices of it. The mean (and a box film's variance) the final image reads anyway come
    from the buffer's per-pass cache, copied into their planes."""
    height, width = buffer.shape
    motion = buffer.motion_sum is not None
    widths = {"color": 3, "variance": 3, "albedo": 3, "normal": 3, "depth": 1, "spp": 1, **({"motion": 2} if motion else {})}
    # numpy's allocation, not torch.empty's: numpy asks the kernel for huge pages on large arrays
    # (madvise), and first touching torch's 4 KiB pages cost ~40 ms of page faults at 2 MP
    host = np.empty((1, sum(widths.values()), height, width), dtype=np.float32)
    planes, first = {}, 0
    for name, channels in widths.items():
        planes[name] = host[0, first:first + channels]
        first += channels

    def hwc(name: str) -> np.ndarray:
        return planes[name].transpose(1, 2, 0)  # a view: writing it fills the plane

    np.copyto(hwc("color"), buffer.mean)
    if buffer.splat_weight is None:
        # a box film's raw variance is this variance: computed once, kept for the final image
        np.copyto(hwc("variance"), buffer.raw_variance)
    else:
        buffer.variance_into(hwc("variance"))
    buffer.per_sample_into(buffer.albedo_sum, hwc("albedo"))
    buffer.per_sample_into(buffer.normal_sum, hwc("normal"))
    buffer.per_sample_into(buffer.depth_sum, planes["depth"][0])
    np.copyto(planes["spp"][0], buffer.spp, casting="unsafe")
    if motion:
        buffer.per_sample_into(buffer.motion_sum, hwc("motion"))
    block = torch.from_numpy(host)
    if device is not None:
        block = block.to(device)
    fields, first = {}, 0
    for name, channels in widths.items():
        fields[name] = block[:, first:first + channels]
        first += channels
    return FrameTensors(**fields)


def samples_exposure(buffer: FrameBuffer) -> Exposure:
    """The networks' exposure (models.exposure) of a frame's sample mean, once per pass of
    samples (FrameBuffer.cached): the final image and the change calibration both read it."""
    return buffer.cached("exposure", lambda: Exposure.of(nchw(buffer.mean)))


def to_image(tensor: torch.Tensor) -> np.ndarray:
    """(1, C, H, W) tensor → (H, W, C) float32 array (C = 1 squeezed). Made contiguous where the
    tensor lives (on a GPU the transpose runs there), so the host gets HWC in one copy."""
    image = tensor[0].detach().float().permute(1, 2, 0).contiguous().cpu().numpy()
    return np.ascontiguousarray(image[..., 0] if image.shape[-1] == 1 else image)


def temporal_window(frame: int, frames: int, radius: int) -> tuple[list[int], int]:
    """Indices of the 2M+1 window around `frame`, clipped to the sequence, and the centre's position."""
    lo, hi = max(0, frame - radius), min(frames - 1, frame + radius)
    return list(range(lo, hi + 1)), frame - lo


def lam_tensor(lam_map: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(lam_map, dtype=np.float32))[None, None]
