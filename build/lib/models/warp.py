"""Backward warping along screen-space motion (Vogels et al. 2018 §4.2, temporal features).

`warp(features, motion)` gathers, for every pixel x of the target frame, the source frame's
value at x + motion(x). With the EXR convention (motion of frame t points into frame t-1),
warping frame t-1's features by frame t's motion aligns them with frame t.
Bilinear weights are computed by hand rather than with grid_sample so that an integer shift
has fractional part exactly 0 and moves values exactly.
"""
from __future__ import annotations

import torch
from torch import Tensor


def warp(features: Tensor, motion: Tensor) -> tuple[Tensor, Tensor]:
    """features (N,C,H,W), motion (N,2,H,W) in pixels (x, y) → (warped (N,C,H,W), valid (N,1,H,W)).

    valid is 1 where the sample point lies on screen, 0 where it falls off (or motion is
    not finite); warped is 0 there.
    """
    n, c, h, w = features.shape
    finite = torch.isfinite(motion).all(dim=1, keepdim=True)
    motion = torch.where(finite, motion, torch.zeros((), dtype=motion.dtype, device=motion.device))
    ys = torch.arange(h, dtype=motion.dtype, device=motion.device).view(1, h, 1)
    xs = torch.arange(w, dtype=motion.dtype, device=motion.device).view(1, 1, w)
    px = xs + motion[:, 0]          # (N,H,W) sample position in the source frame
    py = ys + motion[:, 1]
    valid = finite[:, 0] & (px >= 0) & (px <= w - 1) & (py >= 0) & (py <= h - 1)

    x0, y0 = torch.floor(px), torch.floor(py)
    fx, fy = px - x0, py - y0           # fractional parts: exactly 0 for integer shifts
    # gather whole pixels (rows of C values): a view for channels-last features, one copy otherwise
    rows = features.permute(0, 2, 3, 1).reshape(n, h * w, c)
    batch = torch.arange(n, device=features.device).view(n, 1)
    mask = valid.to(features.dtype)

    def tap(xi: Tensor, yi: Tensor, weight: Tensor) -> tuple[Tensor, Tensor]:
        # off-screen corners get weight 0 (zero padding); indices are clamped only to stay legal
        inside = (xi >= 0) & (xi <= w - 1) & (yi >= 0) & (yi <= h - 1)
        idx = (yi.clamp(0, h - 1) * w + xi.clamp(0, w - 1)).long().view(n, h * w)
        return rows[batch, idx], (weight * inside * mask).view(n, h * w, 1)

    corners = [tap(x0, y0, (1 - fx) * (1 - fy)), tap(x0 + 1, y0, fx * (1 - fy)),
               tap(x0, y0 + 1, (1 - fx) * fy), tap(x0 + 1, y0 + 1, fx * fy)]
    out = corners[0][0] * corners[0][1]
    for value, weight in corners[1:]:
        out.addcmul_(value, weight)
    return out.view(n, h, w, c).permute(0, 3, 1, 2), mask.unsqueeze(1)


def flow_to_center(motions: list[Tensor | None], center: int, j: int) -> tuple[Tensor | None, Tensor | None]:
    """Accumulated motion from the center frame to frame j, and its validity.

    motions[i] maps frame i → frame i-1. Past frames chain the given vectors (sampling each
    at the already displaced position). Future frames have no stored forward motion, so the
    backward vectors of the later frame are negated: exact for rigid translation, an
    approximation elsewhere; the temporal features see the validity mask and learn to trust
    it less. Returns (None, None) for the center itself.
    """
    if j == center:
        return None, None
    ref = next(m for m in motions if m is not None) if any(m is not None for m in motions) else None
    if ref is None:
        return None, None
    flow = torch.zeros_like(ref)
    valid = torch.ones_like(ref[:, :1])
    steps = range(center, j, -1) if j < center else range(center + 1, j + 1)
    sign = 1.0 if j < center else -1.0
    for n, i in enumerate(steps):
        m = motions[i] if motions[i] is not None else torch.zeros_like(ref)
        if n == 0:                      # flow is still zero: sampling is the identity
            flow = sign * m
            continue
        step, v = warp(sign * m, flow)
        flow, valid = flow + step, valid * v
    return flow, valid
