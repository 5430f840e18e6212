"""Temporal multi-scale kernel-predicting denoiser (Vogels et al. 2018), in one module.

Per pyramid level, every frame of the window goes through

    encoder (2 conv3x3)  →  spatial feature extractor (residual blocks)
    neighbours only: warp to the center frame → temporal feature extractor (3 residual blocks)
    pre-λ kernel head (conv1x1)                                     ── prepare() stops here
    λ-module: kernel head with λ-dependent weights → k² logits/frame ── apply() starts here
    joint softmax over all frames' logits, filter demodulated radiance (eqs. 3–4)

and the levels are merged coarse → fine by the scale compositor (eq. 5, models.compositor), then the albedo is multiplied
back in. `prepare` computes everything λ-independent once; `apply` is the tail a λ edit re-runs.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import ClassVar

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from models.accumulation import accumulate_window
from models.candidate import CandidateGate, blend, clamp_around
from models.energy import SampleEnergy, measure_energy, restore_energy
from models.exposure import Exposure
from models.features import (HDR_MAX, PATH_FEATURES, demodulate, demodulation_albedo, log_transform, remodulate,
                             sanitize, sanitize_frame)
from models.frames import FrameTensors
from models.kernels import filter_padded, pad_for_kernel, unnormalised_weights
from models.layers import ConvPair, Pointwise, cat_channels_last, res_blocks, trunk_in_bfloat16
from models.compositor import ScaleCompositor  # noqa: F401  (re-exported: eq. 5)
from models.pyramid import down, down_frame, pad_to
from models.warp import flow_to_center, warp

from models.lambda_range import LAMBDA_MAX, LAMBDA_MIN  # noqa: F401  (re-exported: eq. 6 range)
from models.lambda_regions import Region, constant_regions, region_tiles


@dataclass
class DenoiserConfig:
    """The shipped network's configuration is the default (tests/models/test_shipped_config.py):
    a width-16 single-frame multi-scale KPCN whose window's neighbours only add samples, with the
    OIDN candidate in every level's joint softmax and read by the trunk, and the settings chosen
    after training on the validation scenes. The temporal KPCN is `temporal_config()`."""
    width: int = 16                # feature channels everywhere between encoder and kernel head
    spatial_blocks: int = 2        # residual blocks of the spatial feature extractor
    temporal_blocks: int = 3       # residual blocks of the temporal feature extractor (paper: 3)
    kernel_size: int = 5           # k; per level, so the 3-level pyramid reaches 5·4 = 20 px
    levels: int = 3                # pyramid levels (paper: 3)
    temporal_radius: int = 1       # M: window of 2M+1 frames the model is trained for
    lambda_width: int = 16         # hidden channels of the λ module: kernel head input and λ-MLP width
    lambda_rank: int = 2           # λ-dependent directions of the kernel head W(λ) = W₀ + Σ sᵣ(λ)ΔWᵣ
    composite_width: int = 8       # channels of the per-pixel α CNN (eq. 5)
    temporal: bool = False         # False: single-frame model (the window's consistent samples pooled in, models.accumulation)
    multiscale: bool = True        # False: finest level only, no compositing (the first training stage)
    oidn_candidate: bool = True    # an external denoiser's image joins every level's joint softmax (models.candidate)
    gate_width: int = 8            # hidden channels of the candidate gate
    # --- post-training settings (POST_TRAINING_SETTINGS): chosen on the validation scenes for
    # given weights; training runs without them (NEUTRAL_SETTINGS). Figures: docs/models.md.
    energy_tolerance: float = 0.03  # τ of models.energy: > 0 pulls the image's total towards the samples'; 0 = off
    energy_block: int = 32          # > 0 (with τ): then each block of this many pixels a side as well (models.energy)
    # Logits added to the candidate gate (models.candidate.CandidateGate.weight):
    # > 0 leans to the candidate, in full at λ = 1 and not at all at λ = 10.
    gate_offset: float = 2.0                  # the finest level's
    coarse_gate_offset: float | None = 10.0   # every coarser level's; None: gate_offset
    # With a candidate, eq. 5's swap never lifts a pixel above both its fine result and the
    # candidate's own value there (ScaleCompositor's cap); False = the block-wise cap alone.
    candidate_cap: bool = True
    # Each level's kernel result clamped to [c/(1+t), c·(1+t)] around the candidate c before the
    # blend, t widening to no clamp at λ = 10 (models.candidate.clamp_around); None = off.
    # A highlight the kernels spread beyond what OIDN saw is a relMSE outlier.
    kernel_clamp: float | None = 0.5
    # The kernels filter radiance ÷ max(albedo, floor), the candidate joins in that space, and
    # the result is multiplied back by the same (models.features.demodulation_albedo); the
    # trunk's own features stay as trained. 0 = the plain albedo. The sky seen directly (a camera
    # ray that misses: albedo 0) otherwise left bright dots along the edges of what borders it.
    albedo_floor: float = 0.05

    def without_post_training_settings(self) -> "DenoiserConfig":
        """This config with the settings chosen after training (on validation scenes, for given
        weights) off: what a fine-tuning run starts from and trains through."""
        return dataclasses.replace(self, **NEUTRAL_SETTINGS)

    @property
    def candidate_features(self) -> bool:
        """The trunk also reads the candidate (log of its demodulated image at each level): kernels
        predicted with a clean estimate of the image in view, as a cross-bilateral filter is
        guided by one. Every single-frame network with a candidate does; a temporal one cannot
        (a neighbour frame has no candidate of its own)."""
        return self.oidn_candidate and not self.temporal

    def level_gate_offset(self, level: int) -> float:
        """The logit offset of pyramid level `level` (0 = finest)."""
        return self.gate_offset if level == 0 or self.coarse_gate_offset is None else self.coarse_gate_offset

    @property
    def n_levels(self) -> int:
        return self.levels if self.multiscale else 1

    @property
    def alignment(self) -> int:
        """Sizes must divide by 2^(levels-1) for the 2×2 pyramid; inputs are padded to it."""
        return 2 ** (self.n_levels - 1)


# The post-training settings switched off: how a network trains, and how it runs before they
# are chosen for its weights.
NEUTRAL_SETTINGS: dict = {"energy_tolerance": 0.0, "energy_block": 0, "gate_offset": 0.0, "coarse_gate_offset": None,
                          "candidate_cap": False, "kernel_clamp": None, "albedo_floor": 0.0}


def temporal_config(**fields) -> DenoiserConfig:
    """The temporal multi-scale KPCN (Vogels et al. 2018: one kernel per warped frame of the
    2M+1 window, all jointly softmax-normalised), the product's named design, not shipped yet:
    the shipped sizes, the temporal extractor on, no candidate, no post-training settings."""
    return DenoiserConfig(**{"temporal": True, "oidn_candidate": False, **NEUTRAL_SETTINGS, **fields})


# The config fields chosen after training, on validation scenes, for given weights (above).
POST_TRAINING_SETTINGS = tuple(NEUTRAL_SETTINGS)
CANDIDATE_CHANNELS = 3   # trunk input channels DenoiserConfig.candidate_features adds (log demodulated RGB)

# Inference bands of rows for the λ tail: a band's F·k² weight planes and its 3-channel output
# stay in cache from the GEMM through exp to the last tap.
TILE_PIXELS = 32768

# --- λ ------------------------------------------------------------------------------------

def lambda_code(lam: Tensor) -> Tensor:
    """log λ / log 10 ∈ [0, 1]: the paper samples log λ uniformly, so this is the natural axis."""
    return torch.log(lam.clamp(LAMBDA_MIN, LAMBDA_MAX)) / math.log(LAMBDA_MAX)


def folded_if_uniform(code: Tensor) -> Tensor:
    """A λ code map (N,1,h,w) of one value per image as (N,1,1,1): there the kernel head folds into
    one GEMM (LambdaModule), the same logits up to float rounding. A painted rectangle leaves most
    bands of rows outside it uniform, so a λ edit pays the per-pixel path only where it painted."""
    first = code[:, :, :1, :1]
    return first if bool((code == first).all()) else code


# --- modules ------------------------------------------------------------------------------

class Encoder(ConvPair):
    """Two 3×3 convs from the frame's features (models.features.PATH_FEATURES) to the shared width."""


class TemporalExtractor(nn.Module):
    """Fuses a neighbour's warped features with the center's; residual on the warped
    features, so a window of one frame (no temporal work) sees the same feature space."""

    def __init__(self, width: int, blocks: int):
        super().__init__()
        self.fuse = Pointwise(2 * width + 1, width)
        self.blocks = res_blocks(width, blocks)

    def forward(self, warped: Tensor, center: Tensor, valid: Tensor) -> Tensor:
        x = cat_channels_last([warped, center, valid])
        return warped + self.blocks(F.relu_(self.fuse(x)))


class LambdaModule(nn.Module):
    """Loss specialisation (Vogels §6), the last layer of the kernel predictor made
    λ-dependent: a 2-layer MLP maps log λ to `rank` mixing coefficients s(λ), and the
    pointwise kernel head is W(λ) = W₀ + Σᵣ (sᵣ(λ) − sᵣ(1))·ΔWᵣ (bias folded in as a constant
    input channel). Anchoring at s(1) makes λ = 1 exactly the symmetric network W₀ whatever the
    λ stage learns, so specialising never costs quality at the default λ (without the anchor
    the λ stage cost 4 % SMAPE at λ = 1 with everything else frozen).
    For a global λ this folds into ONE matrix product per level, so re-running
    the tail costs a GEMM plus the filtering; a per-pixel λ map costs 1 + rank GEMMs
    (measured faster than one GEMM over the stacked [h; s₁h; …]: 250 vs 300 ms at 512²)."""

    def __init__(self, cin: int, width: int, k: int, rank: int):
        super().__init__()
        self.mix = nn.Sequential(Pointwise(1, width), nn.ReLU(), Pointwise(width, rank))
        self.base = nn.Parameter(torch.empty(k * k, cin + 1).uniform_(-cin ** -0.5, cin ** -0.5))
        self.delta = nn.Parameter(torch.zeros(rank, k * k, cin + 1))   # start as "no specialisation"

    def forward(self, hidden: Tensor, code: Tensor) -> Tensor:
        """hidden (N,F,C+1,H,W) with a ones channel last, code (N,1,H,W) or (N,1,1,1)
        → logits (N,F·k²,H,W), one k×k kernel per frame."""
        n, f, c, h, w = hidden.shape
        flat = hidden.reshape(n * f, c, h * w)
        s = self.mix(code) - self.mix(code.new_zeros(1, 1, 1, 1))          # (N,rank,h|1,w|1); code(λ=1) = 0
        if s.shape[-1] == 1 and s.shape[-2] == 1:                           # global λ: fold
            weight = self.base + torch.einsum("nr,rkc->nkc", s.flatten(1), self.delta)
            logits = torch.bmm(weight.repeat_interleave(f, 0), flat)
        else:                                                                # λ map: mix per pixel
            logits = torch.bmm(self.base.expand(n * f, -1, -1), flat)
            s = s.flatten(2).repeat_interleave(f, 0).unsqueeze(2)            # (N·F,rank,1,HW)
            for r in range(self.delta.shape[0]):
                logits = logits.addcmul_(torch.bmm(self.delta[r].expand(n * f, -1, -1), flat), s[:, r])
        return logits.view(n, -1, h, w)


# --- the λ-independent state ---------------------------------------------------------------

@dataclass
class LevelCache:
    padded: list[Tensor]   # demodulated radiance per frame, warped to the center (center first), kernel-padded
    hidden: Tensor         # (N,F,C+1,H,W) pre-λ kernel-head features of all frames, ones channel last
    candidate: Tensor | None = None     # demodulated external candidate at this level (N,3,H,W)
    gate_hidden: Tensor | None = None   # (N,1,G+1,H,W) pre-λ candidate-gate features, ones channel last


@dataclass
class DenoiserCache:
    levels: list[LevelCache]       # finest first
    albedo: Tensor                 # padded center demodulation albedo (DenoiserConfig.albedo_floor), for remodulation
    size: tuple[int, int]          # original (H, W) to crop back to
    n_bad: int = 0                 # NaN/Inf values replaced while sanitising the filtered window
    energy: SampleEnergy | None = None   # the center's samples' energy (models.energy)
    # the center's exposure (models.exposure): every cached radiance is exposed by it, and
    # merge_levels takes the output back out, so a λ edit stays in the same units
    exposure: Exposure | None = None


class Denoiser(nn.Module):
    kind: ClassVar[str] = "denoiser"

    def __init__(self, config: DenoiserConfig | None = None):
        super().__init__()
        self.config = cfg = config or DenoiserConfig()
        self.features = PATH_FEATURES
        cin = self.features.channels + (CANDIDATE_CHANNELS if cfg.candidate_features else 0)
        self.encoder = Encoder(cin, cfg.width)
        self.spatial = res_blocks(cfg.width, cfg.spatial_blocks)
        self.temporal = TemporalExtractor(cfg.width, cfg.temporal_blocks) if cfg.temporal else None
        self.kernel_head = Pointwise(cfg.width, cfg.lambda_width)
        self.specialise = LambdaModule(cfg.lambda_width, cfg.lambda_width, cfg.kernel_size, cfg.lambda_rank)
        self.composite = ScaleCompositor(cfg.composite_width) if cfg.multiscale else None
        self.gate = CandidateGate(
            cfg.lambda_width, cfg.gate_width, LambdaModule(cfg.gate_width, cfg.lambda_width, 1, cfg.lambda_rank),
        ) if cfg.oidn_candidate else None

    # -- prepare: everything before λ -----------------------------------------------------

    def filtered_window(self, window: list[FrameTensors], center: int) -> tuple[list[FrameTensors], int]:
        """The window as this network filters it, and its center (the candidate's and error network's
        input): a single-frame network's is one frame, the window's consistent samples pooled in."""
        if self.temporal is not None or len(window) == 1:
            return window, center
        # pooled in the networks' exposure, so sanitising clamps fireflies relative to the image
        exposure = Exposure.of(window[center % len(window)].color)
        pooled = accumulate_window([sanitize_frame(exposure.forward_frame(f))[0] for f in window], center % len(window))
        return [exposure.inverse_frame(pooled)], 0

    def prepare(self, window: list[FrameTensors], center: int, candidate: Tensor | None = None) -> DenoiserCache:
        """candidate: (N,3,H,W) linear radiance of an external denoiser on the center of
        `filtered_window(window, center)` (OIDN), required exactly when the config has `oidn_candidate`."""
        if (candidate is None) == self.config.oidn_candidate:
            raise ValueError("this denoiser " + ("needs" if self.config.oidn_candidate else "takes no")
                             + " candidate image (DenoiserConfig.oidn_candidate)")
        if not window or not -len(window) <= center < len(window):
            raise IndexError(f"center {center} outside a window of {len(window)} frames")
        center %= len(window)
        if self.temporal is None:  # one frame filtered: the center, its neighbours' samples pooled in
            window, center = self.filtered_window(window, center)
        if len(window) == 1:       # nothing to warp, and no feature reads the sample count
            window = [dataclasses.replace(window[0], motion=None, spp=None)]
        # One exposure for the whole window, the center's: radiance enters the networks' range
        # before sanitising, so the firefly clamp (HDR_MAX) is relative to the image's exposure.
        exposure = Exposure.of(window[center].color)
        cleaned = [sanitize_frame(exposure.forward_frame(f)) for f in window]
        frames, n_bad = [f for f, _ in cleaned], sum(n for _, n in cleaned)
        size = frames[center].size
        energy = (measure_energy(frames[center].color, frames[center].variance, self.config.energy_block)
                  if self.config.energy_tolerance > 0 else None)
        align = self.config.alignment
        frames = [f.map(lambda _, t: pad_to(t, align)) for f in frames]
        albedos = [demodulation_albedo(f.albedo, self.config.albedo_floor) for f in frames]
        albedo = albedos[center]

        # Demodulate once at full resolution and pool the result: re-demodulating pooled buffers
        # (D(c)/D(a) ≠ D(c/a) on textures and albedo edges) made every coarse result differ
        # from D(fine) by a texture-shaped bias, and eq. 5 then learned α → 0.
        images = [demodulate(f.color, a) for f, a in zip(frames, albedos)]
        extra = (self._demodulated_candidate(exposure.forward(candidate), frames[center].variance, albedo, align)
                 if candidate is not None else None)
        n_bad += extra[2] if extra is not None else 0
        guide = extra[0] if self.config.candidate_features else None
        levels = []
        for level in range(self.config.n_levels):
            if level:
                frames = [down_frame(f) for f in frames]
                images = [down(i) for i in images]
                # pooled like the images (variance of a 4-pixel mean ÷ 4), so a level whose
                # gate is saturated returns exactly D(candidate) and eq. 5 then changes nothing
                extra = None if extra is None else (down(extra[0]), down(extra[1]) * 0.25, 0)
            guide = extra[0] if self.config.candidate_features else None
            cache = self._prepare_level(frames, images, center, guide)
            if extra is not None:
                cache.candidate = extra[0]
                cache.gate_hidden = self.gate.prepare(cache.hidden[:, 0, :-1], images[center], extra[0], extra[1])
            levels.append(cache)
        return DenoiserCache(levels, albedo, size, n_bad, energy, exposure)

    @staticmethod
    def _demodulated_candidate(candidate: Tensor, variance: Tensor, albedo: Tensor, align: int) -> tuple[Tensor, Tensor, int]:
        """Candidate and the center's variance in the kernels' demodulated space (Var(x/a) = Var(x)/a²);
        albedo: the padded center's demodulation albedo."""
        clean, n_bad = sanitize(candidate.float(), 0.0, HDR_MAX)
        scale = demodulate(torch.ones_like(albedo), albedo)
        return demodulate(pad_to(clean, align), albedo), variance * scale * scale, n_bad

    def _trunk_inputs(self, frames: list[FrameTensors], guide: Tensor | None = None,
                      dtype: torch.dtype | None = None) -> Tensor:
        """All frames as one channels-last batch; guide: the demodulated candidate (candidate_features).
        dtype: a single frame's is built in it at once (a bfloat16 trunk would copy it again)."""
        extra = [log_transform(guide)] if guide is not None else []
        if len(frames) == 1:
            return cat_channels_last(self.features.planes(frames[0]) + extra, dtype)
        return torch.cat([self.features.build(f).permute(0, 2, 3, 1) for f in frames], 0).permute(0, 3, 1, 2)

    def _prepare_level(self, frames: list[FrameTensors], images: list[Tensor], center: int,
                       guide: Tensor | None = None) -> LevelCache:
        """One pyramid level's trunk (reading `guide`, the demodulated candidate, with
        candidate_features), warping and pre-λ kernel head."""
        n = frames[0].color.shape[0]
        bf16 = trunk_in_bfloat16(frames[0].color)
        inputs = self._trunk_inputs(frames, guide, torch.bfloat16 if bf16 else None)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            feats = self.spatial(self.encoder(inputs)).float().split(n, 0)
        motions = [f.motion for f in frames]
        c_feat, c_img = feats[center], images[center]
        out_images, feats_to_center = [c_img], [c_feat]
        for j in range(len(frames)):
            if j == center:
                continue
            flow, valid = flow_to_center(motions, center, j)
            if flow is None:                                   # static scene: nothing to warp
                w_feat, w_img, valid = feats[j], images[j], torch.ones_like(c_img[:, :1])
            else:
                warped, v = warp(cat_channels_last([feats[j], images[j]]), flow)
                valid = valid * v
                w_feat, w_img = warped[:, :-3], warped[:, -3:]
            t_feat = self.temporal(w_feat, c_feat, valid)
            # Off-screen taps fall back to the center's own pixel: the joint softmax then only
            # mixes real radiance, so the output stays in the convex hull.
            out_images.append(valid * w_img + (1 - valid) * c_img)
            feats_to_center.append(t_feat)
        # (N,F,C+1,H,W) planes for the λ tail's GEMM; the last channel is the bias input
        c_hid = self.config.lambda_width
        hidden = c_img.new_empty(n, len(frames), c_hid + 1, *c_img.shape[-2:])
        hidden[:, :, c_hid] = 1.0
        for j, f in enumerate(feats_to_center):
            self.kernel_head.relu_into(f, hidden[:, j, :c_hid])
        k = self.config.kernel_size
        return LevelCache([pad_for_kernel(i, k).contiguous() for i in out_images], hidden)

    # -- apply: the cheap λ tail ----------------------------------------------------------

    def apply(self, cache: DenoiserCache, lam: float | Tensor = 1.0) -> Tensor:
        return self.merge_levels(cache, self.filter_levels(cache, lam))

    def filter_levels(self, cache: DenoiserCache, lam: float | Tensor = 1.0,
                      kernel_only: list[Tensor] | None = None) -> list[Tensor]:
        """Each pyramid level's own filtered, demodulated result (finest first, padded sizes).
        kernel_only: a list to receive each level's result before the candidate joins (training)."""
        results = []
        for i, (level, code) in enumerate(zip(cache.levels, self._level_codes(cache, lam))):
            regions = self._painted_regions(code, kernel_only)
            if regions is not None:
                results.append(self._regional_result(level, regions, i))
                continue
            result = self._kernel_result(level, code)
            if kernel_only is not None:
                kernel_only.append(result)
            if level.candidate is not None:                                       # eq. 4 + one candidate
                weight = self.gate.weight(level.gate_hidden, code, self.config.level_gate_offset(i))
                if kernel_only is None and not torch.is_grad_enabled():
                    result = self._join_candidate_in_place(result, level.candidate, code, weight)
                else:
                    if self.config.kernel_clamp is not None:
                        result = clamp_around(result, level.candidate, self.config.kernel_clamp, code)
                    result = blend(result, level.candidate, weight)
            results.append(result)
        return results

    @staticmethod
    def _painted_regions(code: Tensor, kernel_only: list[Tensor] | None) -> list[Region] | None:
        """A λ map's rectangles of one value (models.lambda_regions), at inference only."""
        if code.shape[-2:] == (1, 1) or kernel_only is not None or torch.is_grad_enabled():
            return None
        return constant_regions(code)

    def _regional_result(self, level: LevelCache, regions: list[Region], i: int) -> Tensor:
        """One level's kernel result with the candidate joined, tile by tile of a painted map's
        rectangles: each tile's kernel head and gate fold at its one λ (one GEMM each instead
        of 1 + rank and the λ MLP per pixel), the same values up to float rounding."""
        k = self.config.kernel_size
        out = level.padded[0].new_empty(level.padded[0].shape[:2] + level.hidden.shape[-2:])
        for rows, cols, code in region_tiles(regions, TILE_PIXELS):
            weights = unnormalised_weights(self.specialise(level.hidden[..., rows, cols], code))
            padded = [p[:, :, rows.start:rows.stop + k - 1, cols.start:cols.stop + k - 1] for p in level.padded]
            result = filter_padded(padded, weights, k)
            if level.candidate is not None:
                weight = self.gate.weight(level.gate_hidden[..., rows, cols], code, self.config.level_gate_offset(i))
                result = self._join_candidate_in_place(result, level.candidate[..., rows, cols], code, weight)
            out[:, :, rows, cols] = result
        return out

    def _join_candidate_in_place(self, result: Tensor, candidate: Tensor, code: Tensor, weight: Tensor) -> Tensor:
        """clamp_around then blend (models.candidate) written over the fresh kernel result:
        min(max(r, lo), hi) is clamp(r, lo, hi) element for element, lerp_ is lerp."""
        t = self.config.kernel_clamp
        if t is not None:
            band = 1.0 + t / (1.0 - code).clamp_min(1e-6)     # clamp_around's band
            result.clamp_(min=candidate / band, max=candidate * band)
        return result.lerp_(candidate, weight)

    def _kernel_result(self, level: LevelCache, code: Tensor) -> Tensor:
        """λ-specialised logits → joint softmax (eq. 4) → filtered radiance (eq. 3) of one level.
        Without autograd the three run together per band of rows: the level's F·k² weight planes
        (79 MB at 512², 3 frames) then never leave the cache, which halves the λ tail
        (docs/models-speed.md). With autograd the whole level at once."""
        k = self.config.kernel_size
        h, w = level.hidden.shape[-2:]
        rows = h if torch.is_grad_enabled() else max(1, TILE_PIXELS // w)
        if rows >= h:
            return filter_padded(level.padded, unnormalised_weights(self.specialise(level.hidden, code)), k)
        out = level.padded[0].new_empty(level.padded[0].shape[:2] + (h, w))
        for y0 in range(0, h, rows):
            y1 = min(h, y0 + rows)
            band = code if code.shape[-2:] == (1, 1) else folded_if_uniform(code[..., y0:y1, :])
            weights = unnormalised_weights(self.specialise(level.hidden[..., y0:y1, :], band))
            out[:, :, y0:y1] = filter_padded([p[:, :, y0:y1 + k - 1] for p in level.padded], weights, k)
        return out

    def candidate_weights(self, cache: DenoiserCache, lam: float | Tensor = 1.0) -> list[Tensor]:
        """The candidate's share σ(g) of each level's softmax (finest first), for diagnostics."""
        if self.gate is None:
            return []
        return [self.gate.weight(level.gate_hidden, code, self.config.level_gate_offset(i))
                for i, (level, code) in enumerate(zip(cache.levels, self._level_codes(cache, lam)))]

    def _level_codes(self, cache: DenoiserCache, lam: float | Tensor) -> list[Tensor]:
        """The λ code of each level, finest first: a per-pixel λ map follows the pyramid."""
        code = self._lambda_code(cache, lam)
        codes = []
        for level in cache.levels:
            if code.shape[-2:] != (1, 1) and code.shape[-2:] != level.hidden.shape[-2:]:
                code = down(code)
            codes.append(code)
        return codes

    def merge_levels(self, cache: DenoiserCache, results: list[Tensor], alphas: list[Tensor] | None = None) -> Tensor:
        """Scale compositor coarse → fine (eq. 5), albedo back in, crop to the input size.
        alphas: a list to receive each step's α (coarsest step first), for diagnostics."""
        out = results[-1]
        for i in reversed(range(len(results) - 1)):
            cap = cache.levels[i].candidate if self.config.candidate_cap else None
            out = self.composite(results[i], out, alphas, cap)
        h, w = cache.size
        out = remodulate(out, cache.albedo)[..., :h, :w]
        if cache.energy is not None:
            out = restore_energy(out, cache.energy, self.config.energy_tolerance)
        return out if cache.exposure is None else cache.exposure.inverse(out)

    def _lambda_code(self, cache: DenoiserCache, lam: float | Tensor) -> Tensor:
        """λ (float, (H,W) or (N|1,1,H,W)) → log-code at the padded size, or (N,1,1,1) if global."""
        ref = cache.albedo
        n = ref.shape[0]
        if not isinstance(lam, Tensor):
            lam = torch.tensor(float(lam))
        lam = torch.nan_to_num(lam.to(device=ref.device, dtype=ref.dtype), nan=LAMBDA_MIN)
        if lam.numel() == 1:
            return lambda_code(lam.reshape(1, 1, 1, 1).expand(n, 1, 1, 1))
        h, w = cache.size
        if lam.dim() == 2 and lam.shape == (h, w):
            lam = lam.view(1, 1, h, w)
        if lam.dim() != 4 or lam.shape[1] != 1 or lam.shape[-2:] != (h, w) or lam.shape[0] not in (1, n):
            raise ValueError(f"λ map must be a float or broadcastable to ({n},1,{h},{w}); got {tuple(lam.shape)}")
        # A map of one value (the service sends every λ edit as a map) is a global λ: the kernel
        # head folds into one GEMM per level instead of 1 + rank (LambdaModule), the same logits
        # up to float rounding. Not under autograd, where λ's gradient must reach every pixel.
        if not lam.requires_grad and bool((lam == lam[0, 0, 0, 0]).all()):
            return lambda_code(lam[:1, :1, :1, :1].expand(n, 1, 1, 1))
        return lambda_code(pad_to(lam.expand(n, 1, h, w), self.config.alignment))

    def forward(self, window: list[FrameTensors], center: int, lam: float | Tensor = 1.0,
                candidate: Tensor | None = None) -> Tensor:
        return self.apply(self.prepare(window, center, candidate), lam)
