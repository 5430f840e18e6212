"""Intel Open Image Denoise on a frame's noisy colour, albedo and normal: the candidate image a
denoiser with `oidn_candidate` mixes into its joint softmax (models/candidate.py), and the
comparison the benchmarks run. The product's one call into `pyoidn`; whether a denoiser gets the
candidate is decided in one place, service/loop/denoise_frame.py.
"""
from __future__ import annotations

import numpy as np
import pyoidn
import torch

from models.exposure import Exposure
from models.features import HDR_MAX
from models.frames import FrameTensors

OIDN_SETTINGS = "RT filter, `hdr=True`, quality high, noisy colour + albedo + normal"


def _clean(image: torch.Tensor, lo: float, hi: float) -> torch.Tensor:
    """NaN → 0, ±Inf → the range's ends, clipped: OIDN's documented input ranges. (H, W, 3)
    float32, contiguous, on the image's device."""
    image = image.to(torch.float32)
    return torch.nan_to_num(image, nan=0.0, posinf=hi, neginf=lo).clamp(lo, hi).contiguous()


def oidn_hwc(color: torch.Tensor, albedo: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """(H, W, 3) noisy HDR radiance, albedo, normal tensors → OIDN's (H, W, 3) estimate, ≥ 0, on
    their device: OIDN's CPU device for CPU tensors, its CUDA device (on torch's current stream)
    for CUDA ones, so a GPU job never copies its frame to the host for OIDN.
    The colour goes in at the networks' exposure (models.exposure) and comes out in the scene's
    units again: the HDR_MAX clamp is then relative to the image, as the denoiser's is."""
    color = color.to(torch.float32)
    exposure = Exposure.of(color.permute(2, 0, 1)[None])   # (H, W, 3): one scale broadcasts
    out = pyoidn.denoise(_clean(exposure.forward(color[None])[0], 0.0, HDR_MAX),
                         _clean(albedo, 0.0, 1.0), _clean(normal, -1.0, 1.0), hdr=True, quality="high")
    return exposure.inverse(out.clamp_min(0.0)[None])[0]


def oidn_image(color: np.ndarray, albedo: np.ndarray, normal: np.ndarray, device: str = "cpu") -> np.ndarray:
    """oidn_hwc on (H, W, 3) host arrays → (H, W, 3) float32 array; `device` "cuda": copied to the
    GPU for OIDN's CUDA device and the result back."""
    def tensor(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).to(device)

    return oidn_hwc(tensor(color), tensor(albedo), tensor(normal)).cpu().numpy()


def oidn_tensor(frame: FrameTensors) -> torch.Tensor:
    """OIDN on every image of an (N, C, H, W) frame batch → (N, 3, H, W), on the frame's device."""
    def hwc(t: torch.Tensor, i: int) -> torch.Tensor:
        return t[i].detach().permute(1, 2, 0)

    images = [oidn_hwc(hwc(frame.color, i), hwc(frame.albedo, i), hwc(frame.normal, i))
              for i in range(frame.color.shape[0])]
    return torch.stack(images).permute(0, 3, 1, 2).to(dtype=frame.color.dtype).contiguous()
