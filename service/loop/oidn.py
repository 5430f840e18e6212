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


def _hwc(a: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """NaN → 0, ±Inf → the range's ends, clipped: OIDN's documented input ranges."""
    a = np.nan_to_num(np.asarray(a, dtype=np.float32), nan=0.0, posinf=hi, neginf=lo)
    return np.ascontiguousarray(np.clip(a, lo, hi), dtype=np.float32)


def oidn_image(color: np.ndarray, albedo: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(H, W, 3) noisy HDR radiance, albedo, normal → OIDN's (H, W, 3) estimate, ≥ 0.
    The colour goes in at the networks' exposure (models.exposure) and comes out in the scene's
    units again: the HDR_MAX clamp is then relative to the image, as the denoiser's is."""
    radiance = torch.from_numpy(np.ascontiguousarray(color, dtype=np.float32))   # (H, W, 3): one scale broadcasts
    exposure = Exposure.of(radiance.permute(2, 0, 1)[None])
    out = pyoidn.denoise(_hwc(exposure.forward(radiance[None])[0].numpy(), 0.0, HDR_MAX), _hwc(albedo, 0.0, 1.0),
                         _hwc(normal, -1.0, 1.0), hdr=True, quality="high")
    out = torch.from_numpy(np.maximum(np.asarray(out, dtype=np.float32), 0.0))
    return exposure.inverse(out[None])[0].numpy()


def oidn_tensor(frame: FrameTensors) -> torch.Tensor:
    """OIDN on every image of an (N, C, H, W) frame batch → (N, 3, H, W) on the frame's device."""
    def hwc(t: torch.Tensor, i: int) -> np.ndarray:
        return t[i].detach().float().permute(1, 2, 0).cpu().numpy()

    images = [oidn_image(hwc(frame.color, i), hwc(frame.albedo, i), hwc(frame.normal, i))
              for i in range(frame.color.shape[0])]
    stacked = torch.from_numpy(np.stack(images).transpose(0, 3, 1, 2).copy())
    return stacked.to(device=frame.color.device, dtype=frame.color.dtype)
