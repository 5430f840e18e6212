"""Test-time augmentation of the error map: the error network run on dihedral views of its inputs
(flips, transposes), each prediction brought back to the image's orientation and the views averaged.

A convolutional network is equivariant to translations only; its learned 3×3 kernels are not
symmetric, so a flipped input gives a slightly different map, and the mean over the dihedral
group D4 is an ensemble of k correlated predictors at k× the cost (test-time augmentation as in
Krizhevsky et al. 2012, §4.1; the 8-view D4 form as in Simonyan & Zisserman 2015, §3.2).

Every input the error network reads (radiance, variance, albedo, world-space normals, depth, the
sample-count map, the denoised image, the disagreement) is a per-pixel scalar field or a vector in
world space, which a flip of the screen moves but does not change. Screen-space motion is the one
direction-dependent buffer: a flip along x negates its x component, a transpose swaps x and y.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn as nn
from torch import Tensor

from models.error_predictor import ErrorMap
from models.frames import FrameTensors

VIEW_COUNTS = (1, 2, 4, 8)
Combine = Literal["mean", "geometric"]
LOG_FLOOR = 1e-8  # a prediction of 0 (softplus underflow) must not send the geometric mean to 0


@dataclass(frozen=True)
class View:
    """One element of D4 on an (…, H, W) tensor: transpose H and W first, then flip `flips` axes."""

    transpose: bool
    flip_h: bool
    flip_w: bool

    @property
    def _dims(self) -> list[int]:
        return [d for d, on in ((-2, self.flip_h), (-1, self.flip_w)) if on]

    def forward(self, x: Tensor) -> Tensor:
        y = x.transpose(-2, -1) if self.transpose else x
        return y.flip(self._dims) if self._dims else y

    def inverse(self, x: Tensor) -> Tensor:
        y = x.flip(self._dims) if self._dims else x
        return y.transpose(-2, -1) if self.transpose else y

    def motion(self, m: Tensor) -> Tensor:
        """(N, 2, H, W) screen-space motion (x, y) in pixels, viewed: moved like any plane, then its
        components swapped by a transpose and negated along each flipped axis."""
        m = self.forward(m)
        if self.transpose:
            m = m.flip(1)  # (x, y) → (y, x): the new x axis is the old y axis
        sign = torch.tensor([-1.0 if self.flip_w else 1.0, -1.0 if self.flip_h else 1.0], dtype=m.dtype, device=m.device)
        return m * sign.view(1, 2, 1, 1)


# The first k of these are the k views: 2 = identity + mirror, 4 = the flips (no transpose, so a
# non-square image keeps its shape), 8 = all of D4.
D4 = (View(False, False, False), View(False, False, True), View(False, True, False), View(False, True, True),
      View(True, False, False), View(True, False, True), View(True, True, False), View(True, True, True))


def view_frame(frame: FrameTensors, view: View) -> FrameTensors:
    """Every buffer of `frame` seen through `view` (motion's components transformed too)."""
    return frame.map(lambda name, t: view.motion(t) if name == "motion" else view.forward(t))


def combine_views(maps: list[Tensor], combine: Combine) -> Tensor:
    """The mean of the un-flipped maps, or their geometric mean (the mean of logs: an error that one
    view puts 10× too high weighs as much as one 10× too low)."""
    stacked = torch.stack(maps)
    if combine == "geometric":
        return stacked.clamp_min(LOG_FLOOR).log().mean(0).exp()
    return stacked.mean(0)


class ErrorTTA(nn.Module):
    """An ErrorMap that averages `network` over its first `views` dihedral views. 1 view is the
    network itself, bit for bit. Chosen once at start-up (models.pretrained.load_networks)."""

    def __init__(self, network: ErrorMap, views: int, combine: Combine = "mean"):
        super().__init__()
        if views not in VIEW_COUNTS:
            raise ValueError(f"test-time views must be one of {VIEW_COUNTS}, got {views}")
        if combine not in ("mean", "geometric"):
            raise ValueError(f"views combine by 'mean' or 'geometric', got {combine!r}")
        self.network = network
        self.views = D4[:views]
        self.combine: Combine = combine

    @property
    def change_scale(self) -> float | None:
        return self.network.change_scale

    @property
    def reads_disagreement(self) -> bool:
        return self.network.reads_disagreement

    @property
    def config(self):
        """The wrapped network's configuration (what start-up checks read)."""
        return self.network.config

    def forward(self, frame: FrameTensors, denoised: Tensor, disagreement: Tensor | None = None) -> Tensor:
        if len(self.views) == 1:
            return self.network(frame, denoised, disagreement)
        maps = []
        for view in self.views:
            seen = None if disagreement is None else view.forward(disagreement)
            maps.append(view.inverse(self.network(view_frame(frame, view), view.forward(denoised), seen)))
        return combine_views(maps, self.combine).contiguous()
