"""Sample allocators: per-pixel weights → integer sample counts that sum exactly to a budget.

The paper (Vogels et al. 2018, §6) hands each new iteration's samples out in proportion to the
predicted post-denoise error and doubles the total every iteration. A raw error map is a poor
allocation on its own: NaNs and fireflies would swallow the budget, isolated hard pixels leave
their neighbours (which share the feature) untouched, and pixels predicted as "easy" would never
be revisited. So the weights pass through a fixed pipeline, one small function per step:

    sanitise → clamp outliers → dilate → normalise → mix in a floor → cap (water-fill) → round

Everything is vectorised numpy (loops only over filter offsets, never over pixels), so a 4K
frame allocates in a second or two. `models` does not import this; it is service-side policy.
"""
from __future__ import annotations

import math
import operator
import numpy as np
import torch

from models.exposure import Exposure
from models.features import relative_variance
from service.loop.spec import ALLOCATORS  # one list of kinds for the spec, CLI, API and here

__all__ = [
    "ALLOCATORS",
    "DEFAULT_CAP_MULTIPLE",
    "DEFAULT_CLAMP_PERCENTILE",
    "EDGE_SETTLE_SPP",
    "allocate_samples",
    "allocation_weights",
    "edge_top_up",
    "error_weights",
    "exposed_relative_variance",
    "iteration_budget",
    "uniform_weights",
    "variance_weights",
]

# Without a cap, one pixel with a wildly over-predicted error could take most of an iteration.
# 8× the uniform share still lets hard pixels converge ~3× faster in noise std per iteration.
DEFAULT_CAP_MULTIPLE = 8.0

# Clip the weights at this percentile of the positive ones: one firefly in an error map must not
# take the budget, yet the hardest pixels must keep their lead. Chosen on the validation scenes
# (docs/decisions.md, "Clamp the error map at its 99th percentile"): at 95 the hardest 5 % of a map were flattened to one
# level, and with the error network (d)/(b) at 128 spp averaged 0.979; at 99 0.965 (99.5 and no
# clamp the same within noise); with the true error map 0.945 → 0.920.
DEFAULT_CLAMP_PERCENTILE = 99.0

# A pixel whose samples all agreed beside one that did not (FrameBuffer.converged, not .settled)
# counts as settled only after this many: an edge covering a few per cent of it is missed by 16
# samples as often as not, by 64 at 5 % coverage 4 % of the time.
EDGE_SETTLE_SPP = 64

# Remainders closer than this are treated as tied, so float noise in the shares (e.g. two equal
# weights reached through different arithmetic) cannot masquerade as a real preference.
_REMAINDER_LEVELS = 1 << 20


# --- weights -----------------------------------------------------------------------------------


def _sanitise(weights: np.ndarray) -> np.ndarray:
    """float64 copy with NaN, ±Inf and negatives set to 0: garbage in a map must not steer samples."""
    w = np.array(weights, dtype=np.float64, copy=True)
    w[~np.isfinite(w) | (w < 0)] = 0.0
    return w


def uniform_weights(shape: tuple[int, int]) -> np.ndarray:
    """Equal weight everywhere: the non-adaptive baseline (and the paper's first iteration)."""
    height, width = _check_shape(shape)
    return np.ones((height, width), dtype=np.float64)


def variance_weights(relative_variance: np.ndarray) -> np.ndarray:
    """Mean over colour channels of the relative variance of the mean: the classic baseline.

    Accepts (H, W, C) or (H, W); non-finite entries count as 0 rather than poisoning the mean.
    """
    rv = _sanitise(relative_variance)
    if rv.ndim == 3:
        return rv.mean(axis=2)
    if rv.ndim == 2:
        return rv
    raise ValueError(f"relative_variance must be (H, W) or (H, W, C), got shape {rv.shape}")


def exposed_relative_variance(mean: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """(H, W, 3) sample mean and variance of the mean → Var/(mean² + ε) per channel, taken at the
    networks' exposure (models.exposure): ε is absolute, so without it a scene at 10⁻⁶ had every
    pixel's weight ∝ its raw variance and one at 10¹² ∝ 1/mean² in the dark. Inside the trained
    range the exposure is 1 and this is models.features.relative_variance of the buffer."""
    m = torch.from_numpy(np.asarray(mean, dtype=np.float64)).permute(2, 0, 1)[None]
    v = torch.from_numpy(np.asarray(variance, dtype=np.float64)).permute(2, 0, 1)[None]
    exposure = Exposure.of(m)
    rv = relative_variance(exposure.forward(m), exposure.forward_variance(v))
    return rv[0].permute(1, 2, 0).numpy().astype(np.float32)


def error_weights(predicted_smape: np.ndarray) -> np.ndarray:
    """The paper's allocator: weight = predicted post-denoise SMAPE per pixel."""
    err = _sanitise(predicted_smape)
    if err.ndim != 2:
        raise ValueError(f"predicted_smape must be (H, W), got shape {err.shape}")
    return err


def allocation_weights(
    kind: str,
    *,
    predicted_error: np.ndarray | None = None,
    relative_variance: np.ndarray | None = None,
    shape: tuple[int, int],
) -> np.ndarray:
    """Weights for allocator `kind`; fails at once on an unknown kind or a missing input."""
    if kind == "error":
        weights = error_weights(_require(predicted_error, "predicted_error", kind))
    elif kind == "variance":
        weights = variance_weights(_require(relative_variance, "relative_variance", kind))
    elif kind == "uniform":
        weights = uniform_weights(shape)
    else:
        raise ValueError(f"unknown allocator {kind!r}; known allocators: {', '.join(ALLOCATORS)}")
    expected = _check_shape(shape)
    if weights.shape != expected:
        raise ValueError(f"{kind} weights have shape {weights.shape}, expected {expected}")
    return weights


def _require(value: np.ndarray | None, name: str, kind: str) -> np.ndarray:
    if value is None:
        raise ValueError(f"allocator {kind!r} needs {name}")
    return value


def _check_shape(shape: tuple[int, ...]) -> tuple[int, int]:
    if len(shape) != 2 or any(int(s) < 0 for s in shape):
        raise ValueError(f"shape must be (H, W) with non-negative sizes, got {tuple(shape)}")
    return int(shape[0]), int(shape[1])


# --- budget ------------------------------------------------------------------------------------


def iteration_budget(total_so_far: int) -> int:
    """Samples for the next iteration: as many as all earlier ones together, so the total doubles.

    The first iteration's budget (spp_first × pixels, uniform) is set by the loop, not here.
    """
    total = operator.index(total_so_far)
    if total <= 0:
        raise ValueError(
            f"total_so_far must be positive (the first iteration comes from spp_first), got {total}"
        )
    return total


# --- allocation pipeline -----------------------------------------------------------------------


def _clamp_outliers(w: np.ndarray, percentile: float | None) -> np.ndarray:
    """Clip at a percentile of the *positive* weights.

    Taken over positive pixels only: in a mostly-zero map the percentile over all pixels would be
    0 and clamping would erase exactly the pixels that need samples.
    """
    if percentile is None or percentile >= 100.0:
        return w
    positive = w[w > 0]
    if positive.size == 0:
        return w
    return np.minimum(w, np.percentile(positive, percentile))


def _max_filter(w: np.ndarray, radius: int) -> np.ndarray:
    """Square max filter, separable; zero padding is neutral because weights are ≥ 0.

    Hand-rolled rather than scipy.ndimage so the service does not need scipy at runtime.
    """
    if radius == 0 or w.size == 0:
        return w
    out = _max_filter_axis(w, radius, axis=0)
    return _max_filter_axis(out, radius, axis=1)


def _max_filter_axis(w: np.ndarray, radius: int, axis: int) -> np.ndarray:
    length = w.shape[axis]
    out = w.copy()
    for shift in range(1, min(radius, length - 1) + 1):  # offsets, not pixels
        lo = [slice(None)] * 2
        hi = [slice(None)] * 2
        lo[axis], hi[axis] = slice(0, length - shift), slice(shift, length)
        np.maximum(out[tuple(lo)], w[tuple(hi)], out=out[tuple(lo)])  # neighbour below/right
        np.maximum(out[tuple(hi)], w[tuple(lo)], out=out[tuple(hi)])  # neighbour above/left
    return out


def _shares(w: np.ndarray, floor_fraction: float) -> np.ndarray:
    """Fractions of the budget per pixel (sum 1): weight-proportional plus a uniform floor.

    All-zero weights carry no information, so they fall back to uniform instead of dividing by 0.
    """
    n = w.size
    total = w.sum()
    proportional = w / total if total > 0 else np.full(w.shape, 1.0 / n)
    return (1.0 - floor_fraction) * proportional + floor_fraction / n


def _effective_cap(
    budget: int, n: int, cap_fraction: float | None, max_per_pixel: int | None
) -> int:
    """Integer per-pixel cap; never below the uniform share, so the budget is always feasible.

    An integer cap keeps the guarantee exact after rounding (count ≤ cap, not ≤ cap + 1).
    """
    caps = []
    if cap_fraction is not None:
        caps.append(cap_fraction * budget)
    if max_per_pixel is not None:
        caps.append(float(max_per_pixel))
    if not caps:
        caps.append(DEFAULT_CAP_MULTIPLE * budget / n)
    return max(math.floor(min(caps)), math.ceil(budget / n))


def _water_fill(shares: np.ndarray, budget: int, cap: int) -> np.ndarray:
    """Real-valued counts x = min(cap, t·share) with the scale t chosen so Σx = budget.

    Capping pixels and handing their excess to the others in proportion to their shares,
    repeated until nothing exceeds the cap, converges to exactly this; sorting the shares finds
    the number of capped pixels in one vectorised pass instead of iterating.
    """
    x = budget * shares
    if x.size == 0 or x.max() <= cap:
        return x
    positive = shares > 0
    n_positive = int(positive.sum())
    if n_positive * cap <= budget:
        # Happens with floor_fraction = 0: the weighted pixels are all full, so the rest
        # of the budget goes evenly to zero-weight pixels (cap ≥ budget / n keeps them ≤ cap).
        rest = (budget - n_positive * cap) / max(shares.size - n_positive, 1)
        return np.where(positive, float(cap), rest)
    flat = shares.ravel()
    order = np.argsort(-flat, kind="stable")
    q = flat[order]
    tail = np.cumsum(q[::-1])[::-1]  # Σ_{j≥k} q_j, summed small-to-large for accuracy
    k = np.arange(q.size)
    # k capped pixels leave (budget − k·cap) for the rest at scale t_k = that / tail_k; k is right
    # once the largest uncapped pixel fits: t_k·q_k ≤ cap (cross-multiplied to avoid 0/0).
    fits = (budget - k * cap) * q <= cap * tail
    n_capped = int(np.argmax(fits))
    scale = (budget - n_capped * cap) / tail[n_capped]
    out = np.minimum(scale * flat, float(cap))
    out[order[:n_capped]] = float(cap)
    return out.reshape(shares.shape)


def _round_exact(x: np.ndarray, budget: int, cap: int, rng: np.random.Generator) -> np.ndarray:
    """Largest-remainder rounding of x to integers summing exactly to `budget`, each ≤ cap.

    Ties in the remainder are broken by a seeded random permutation, so equal pixels (e.g. a
    uniform map with fewer samples than pixels) are picked fairly yet reproducibly.
    """
    # In place, one full-film array reused per step (~12 passes at 2 MP, the same values as the
    # plain expressions: the whole part is exact in float64, so flat − counts is flat − floor(flat)).
    flat = np.clip(x.ravel(), 0.0, float(cap))
    whole = np.floor(flat)
    counts = whole.astype(np.int64)
    remainder = np.subtract(flat, whole, out=flat)
    missing = budget - int(counts.sum())
    if missing != 0:
        level = np.multiply(remainder, _REMAINDER_LEVELS, out=whole)
        np.floor(level, out=level)
        np.minimum(level, _REMAINDER_LEVELS - 1, out=level)
        tie_rank = rng.permutation(flat.size)
        key = level.astype(np.int64)  # remainder first, then the tie rank
        key *= flat.size
        key += tie_rank
        if missing > 0:
            key[counts >= cap] = -1  # a full pixel must not take a rounding sample
            counts[_top(key, missing)] += 1
        else:
            # Only float error in Σx can get here: take back from the smallest remainders.
            key[counts <= 0] = np.iinfo(np.int64).max
            counts[_top(-key, -missing)] -= 1
    if int(counts.sum()) != budget:  # an invariant, kept loud rather than silently off by one
        raise RuntimeError(f"allocation sums to {int(counts.sum())}, not the budget {budget}")
    return counts.reshape(x.shape)


def _top(key: np.ndarray, k: int) -> np.ndarray:
    """Indices of the k largest keys; argpartition keeps rounding O(n) on huge frames."""
    if k >= key.size:
        return np.arange(key.size)
    return np.argpartition(-key, k - 1)[:k]


def _validate(
    weights: np.ndarray,
    budget: int,
    floor_fraction: float,
    clamp_percentile: float | None,
    dilate_radius: int,
    cap_fraction: float | None,
    max_per_pixel: int | None,
) -> None:
    if np.ndim(weights) != 2:
        raise ValueError(f"weights must be (H, W), got shape {np.shape(weights)}")
    if budget < 0:
        raise ValueError(f"budget must be ≥ 0, got {budget}")
    if budget > 0 and np.size(weights) == 0:
        raise ValueError(f"cannot place {budget} samples in an empty image")
    if not 0.0 <= floor_fraction <= 1.0:
        raise ValueError(f"floor_fraction must be in [0, 1], got {floor_fraction}")
    if clamp_percentile is not None and not 0.0 < clamp_percentile <= 100.0:
        raise ValueError(f"clamp_percentile must be in (0, 100], got {clamp_percentile}")
    if dilate_radius < 0:
        raise ValueError(f"dilate_radius must be ≥ 0, got {dilate_radius}")
    if cap_fraction is not None and not cap_fraction > 0.0:
        raise ValueError(f"cap_fraction_per_pixel must be > 0, got {cap_fraction}")
    if max_per_pixel is not None and max_per_pixel < 1:
        raise ValueError(f"max_per_pixel must be ≥ 1, got {max_per_pixel}")


def allocate_samples(
    weights: np.ndarray,
    budget: int,
    *,
    floor_fraction: float = 0.05,
    clamp_percentile: float | None = DEFAULT_CLAMP_PERCENTILE,
    dilate_radius: int = 1,
    cap_fraction_per_pixel: float | None = None,
    max_per_pixel: int | None = None,
    seed: int = 0,
    floor_only: np.ndarray | None = None,
) -> np.ndarray:
    """Integer samples per pixel, (H, W) int64, summing exactly to `budget`.

    weights: (H, W) importance, any scale; NaN/Inf/negative count as 0; all-zero → uniform.
    floor_fraction: share of the budget spread uniformly so that no pixel starves.
    clamp_percentile: clip weights at this percentile of the positive ones (None/100: off).
    dilate_radius: max-filter radius so the neighbours of a hard pixel are sampled too.
    cap_fraction_per_pixel / max_per_pixel: most samples one pixel may get (fraction of the
        budget / absolute); the tighter wins; neither → DEFAULT_CAP_MULTIPLE × budget / pixels.
        A cap too small for the budget is raised to ⌈budget / pixels⌉: samples are never lost.
    seed: only breaks ties between equal rounding remainders.
    floor_only: (H, W) bool, pixels that get only the floor whatever their neighbours (their
        samples all agreed: nothing to gain). Applied after dilation, which would otherwise
        spread a hard neighbour's weight onto them.
    """
    budget = operator.index(budget)
    _validate(weights, budget, floor_fraction, clamp_percentile, dilate_radius,
              cap_fraction_per_pixel, max_per_pixel)
    shape = np.shape(weights)
    if budget == 0:
        return np.zeros(shape, dtype=np.int64)
    w = _sanitise(weights)
    w = _clamp_outliers(w, clamp_percentile)
    w = _max_filter(w, dilate_radius)
    if floor_only is not None:
        if np.shape(floor_only) != shape:
            raise ValueError(f"floor_only mask {np.shape(floor_only)} does not match the weights {shape}")
        w = np.where(floor_only, 0.0, w)
    shares = _shares(w, floor_fraction)
    cap = _effective_cap(budget, w.size, cap_fraction_per_pixel, max_per_pixel)
    x = _water_fill(shares, budget, cap)
    return _round_exact(x, budget, cap, np.random.default_rng(seed))


def edge_top_up(converged: np.ndarray, settled: np.ndarray, spp: np.ndarray, budget: int) -> np.ndarray:
    """(H, W) int64 samples that bring each pixel whose samples all agreed but whose neighbours'
    did not (`converged` & ~`settled`, FrameBuffer) up to EDGE_SETTLE_SPP, out of `budget`:
    such a pixel (background beside an object's edge) gets only the allocator's floor otherwise,
    yet 16 misses do not show it empty. At most half the budget: scaled down (floor) beyond it."""
    need = np.where(converged & ~settled, np.maximum(EDGE_SETTLE_SPP - spp.astype(np.int64), 0), 0)
    total = int(need.sum())
    if total > budget // 2:
        need = need * (budget // 2) // total
    return need.astype(np.int64)
