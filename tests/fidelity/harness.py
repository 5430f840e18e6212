"""Render one scene file with renderloop and with mi.render at the same spp, and compare.

The yardstick is Mitsuba itself: two mi.render runs with different seeds show how far two
correct N-spp images of this scene lie apart (per-pixel SMAPE); ours may differ from one of
them by at most 1.2× that, and the mean radiance by at most 1 %.

With a box filter both renderers have the same per-pixel noise and that is the test as stated.
With a wider filter hdrfilm splats each sample into every pixel of its footprint, so its pixels
average more samples than ours, where each sample stays in its own pixel (filter importance
sampling, filters.py); the noise floor of |ours − mi| is then sqrt((S_oo² + S_mm²)/2) for the
SMAPEs S_oo between two of our runs and S_mm between two of Mitsuba's, and ours must lie within
1.2× of that. A bias (a wrong filter, a lost parameter) shows up in both criteria alike.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.render.effects import inspect_frames, make_integrator
from service.render.framebuffer import FrameBuffer
from service.render.renderer import render_samples
from service.render.runtime import mitsuba
from service.render.scenes import load_scene_info

SCENES = Path(__file__).parent / "scenes"
# SMAPE's ε (Vogels et al. 2018, eq. 2; DESIGN.md).
SMAPE_EPS = 1e-2


def smape(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean(np.abs(a - b) / (np.abs(a) + np.abs(b) + SMAPE_EPS)))


@dataclass
class Comparison:
    ours: np.ndarray  # (H, W, 3 + AOVs)
    ours_b: np.ndarray  # a second run of ours, other seed
    mi_a: np.ndarray
    mi_b: np.ndarray

    @property
    def mean_ratio(self) -> float:
        reference = 0.5 * (self.mi_a[..., :3].mean() + self.mi_b[..., :3].mean())
        return float(self.ours[..., :3].mean() / reference)

    def smape_ratio(self, channels=slice(0, 3)) -> float:
        """SMAPE(ours, mi) / SMAPE(mi seed a, mi seed b): the test as stated (box filters)."""
        ours = smape(self.ours[..., channels], self.mi_a[..., channels])
        noise = smape(self.mi_b[..., channels], self.mi_a[..., channels])
        return ours / max(noise, 1e-9)

    def noise_floor_ratio(self, channels=slice(0, 3)) -> float:
        """SMAPE(ours, mi) / sqrt((S_oo² + S_mm²) / 2): the same test when the noise differs."""
        ours = smape(self.ours[..., channels], self.mi_a[..., channels])
        s_oo = smape(self.ours[..., channels], self.ours_b[..., channels])
        s_mm = smape(self.mi_b[..., channels], self.mi_a[..., channels])
        return ours / max(np.sqrt(0.5 * (s_oo**2 + s_mm**2)), 1e-9)


def mitsuba_render(mi, scene, spp: int, seed: int) -> np.ndarray:
    """mi.render's image as R, G, B followed by the integrator's AOVs in aov_names() order.

    The developed film's bitmap carries every channel by name (the returned tensor of an `aov`
    integrator run leaves some out), so the channels are taken from there."""
    mi.render(scene, spp=spp, seed=seed)
    return np.asarray(scene.sensors()[0].film().bitmap(raw=False), dtype=np.float32)


def ours(scene, integrator, spp: int, seed: int = 1) -> np.ndarray:
    h, w = (int(v) for v in scene.sensors()[0].film().crop_size()[::-1])
    buffer = FrameBuffer.empty(h, w)
    render_samples(scene, np.full((h, w), spp), buffer, integrator=integrator, seed=seed)
    return np.concatenate([buffer.mean] + ([buffer.aovs] if buffer.aovs is not None else []), axis=-1)


def compare_file(name: str, spp: int, **params: str) -> Comparison:
    """Ours through our own loader (or, with `params`, Mitsuba's parse with -D values) vs mi.render."""
    mi = mitsuba()
    path = SCENES / name
    if params:
        scene = mi.load_file(str(path), **params)
        integrator = None
    else:
        loaded = load_scene_info(path)
        scene = loaded.scene
        integrator = make_integrator(inspect_frames([loaded]))
    reference = mi.load_file(str(path), **params)  # the file exactly as written
    return Comparison(
        ours=ours(scene, integrator, spp, seed=1),
        ours_b=ours(scene, integrator, spp, seed=2),
        mi_a=mitsuba_render(mi, reference, spp, seed=101),
        mi_b=mitsuba_render(mi, reference, spp, seed=202),
    )
