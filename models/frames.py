"""One frame's worth of tensors handed to the networks.

Everything is NCHW float; radiance is linear HDR. Motion follows the EXR contract
(docs/design.md): pixel (x, y) in frame t was at (x + mx, y + my) in frame t-1.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

from torch import Tensor


@dataclass
class FrameTensors:
    color: Tensor            # (N,3,H,W) noisy sample mean, linear HDR
    variance: Tensor         # (N,3,H,W) variance of that mean (not of one sample)
    albedo: Tensor           # (N,3,H,W) first-hit diffuse reflectance
    normal: Tensor           # (N,3,H,W) shading normal, components in [-1, 1]
    depth: Tensor            # (N,1,H,W) first-hit distance
    motion: Tensor | None = None  # (N,2,H,W) pixels to the previous frame, or None = static
    spp: Tensor | None = None     # (N,1,H,W) samples per pixel so far (the loop's count map), or None

    @property
    def size(self) -> tuple[int, int]:
        return int(self.color.shape[-2]), int(self.color.shape[-1])

    def map(self, fn: Callable[[str, Tensor], Tensor]) -> "FrameTensors":
        """Apply fn(name, tensor) to every present buffer (padding, pooling, device moves)."""
        fields = {k: fn(k, getattr(self, k)) for k in ("color", "variance", "albedo", "normal", "depth")}
        for optional in ("motion", "spp"):
            value = getattr(self, optional)
            fields[optional] = None if value is None else fn(optional, value)
        return replace(self, **fields)

    def to(self, device) -> "FrameTensors":
        return self.map(lambda _, t: t.to(device))
