"""Where the denoiser's two images disagree: an input the error network can read.

A denoiser with an OIDN candidate (models/candidate.py) blends two images of the same inputs:
its kernels' own image k and the candidate c. Where they disagree, at least one of them is
wrong, like the spread of an ensemble (docs/decisions.md, "The kernels' disagreement
with OIDN"): on the validation scenes the error network ranks no better than chance, this ranks
their error better than the network does. As an input channel the network can learn where to
trust it.

    D = box_5×5( mean_c |k − c| / (|k| + |c| + ε) )      (the SMAPE of eq. 2 between the two)
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import Tensor

from models.exposure import Exposure

if TYPE_CHECKING:
    from models.denoiser import Denoiser, DenoiserCache

DISAGREEMENT_EPSILON = 0.01  # SMAPE's ε (eq. 2)
DISAGREEMENT_BOX = 5         # pixels: single-pixel differences are mostly the inputs' noise


def kernel_disagreement(kernels: Tensor, candidate: Tensor) -> Tensor:
    """(N, 1, H, W) in [0, 1]: the two images' per-pixel SMAPE, box-filtered over 5×5
    (zero-padded, normalised by the pixels inside the image). Non-finite values read 0.
    Both at the candidate's exposure (models.exposure): ε is absolute, D must not change with the
    scene's units."""
    exposure = Exposure.of(candidate)
    k, c = exposure.forward(kernels.float()), exposure.forward(candidate.float())
    d = ((k - c).abs() / (k.abs() + c.abs() + DISAGREEMENT_EPSILON)).mean(1, keepdim=True)
    d = torch.nan_to_num(d, nan=0.0, posinf=0.0, neginf=0.0).clamp(0.0, 1.0)
    return F.avg_pool2d(d, DISAGREEMENT_BOX, 1, DISAGREEMENT_BOX // 2, count_include_pad=False)


def disagreement_feature(disagreement: Tensor) -> Tensor:
    """√D: the disagreement's useful range is 0.001–0.1, the root spreads it over [0, 1]."""
    return disagreement.clamp(0.0, 1.0).sqrt()


def apply_with_kernels_image(denoiser: "Denoiser", cache: "DenoiserCache",
                             lam: float | Tensor = 1.0) -> tuple[Tensor, Tensor]:
    """The denoiser's output and its kernels' image alone (each level's result before the
    candidate joins, composited the same way), from one pass of the λ tail."""
    kernel_levels: list[Tensor] = []
    output = denoiser.merge_levels(cache, denoiser.filter_levels(cache, lam, kernel_levels))
    return output, denoiser.merge_levels(cache, kernel_levels)


def apply_for_error_network(denoiser: "Denoiser", cache: "DenoiserCache", candidate: Tensor | None,
                            lam: float | Tensor, with_disagreement: bool) -> tuple[Tensor, Tensor | None]:
    """The denoised image (the λ tail of `cache`), and D if the error network reads it."""
    if not with_disagreement:
        return denoiser.apply(cache, lam), None
    if candidate is None:
        raise ValueError("an error network reading the kernels/candidate disagreement needs a denoiser with a "
                         "candidate image (oidn_candidate)")
    output, kernels = apply_with_kernels_image(denoiser, cache, lam)
    return output, kernel_disagreement(kernels, candidate)
