"""Render one scene file with renderloop and with mi.render at the same spp, and compare.

The yardstick is Mitsuba itself, rendered with other seeds. Two checks, both noise-aware, so
that a bug smaller than the noise of one image still shows (tests/fidelity/test_planted_bugs.py
plants a max_depth one lower, a light 3 % dimmer and a film filter ignored, and each must fail):

- The mean radiance: within 1 % of mi.render's, and within Z_BOUND standard errors of it. The
  standard error comes from our per-pixel variance of the mean (our pixels' noise is
  independent), taken to be the same for mi.render's image at equal samples.
- Per pixel: with K_o and K_m seeds, ō and m̄ the seed means and v_o, v_m the per-pixel variances
  of one image, R = Σ w·(ō − m̄)² / Σ w·(v_o/K_o + v_m/K_m) is ≈ 1 when both estimate the same
  image and grows with any per-pixel bias (a filter's shape at edges, a missing bounce) — the sum
  of the squared biases over the sum of the variances. v_o is the larger of our estimate from
  every sample (FrameBuffer.variance, raw_variance) and the spread of our K_o = 2 images (which
  catches a rare event all of one image's samples missed); v_m is the spread of K_m = 4 images of
  mi.render's. With only two images each (one degree of freedom per pixel) a scene whose noise
  sits in a few edge pixels (max_depth 1: only the emitters' rims) read R 1.45 for a correct
  renderer. w = 1/(m² + ε) (m: the mean of all renders) keeps the bright emitter from deciding
  alone. R is computed for both of our estimates: the per-pixel (filter-importance-sampled) one
  the denoisers read and the splatted raw image users see, whose lower noise makes it the
  sharper test.

The earlier SMAPE ratios (smape_ratio, noise_floor_ratio) stay for the AOV layers.
"""
from __future__ import annotations

import tempfile
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Callable

import numpy as np

from service.render.effects import inspect_frames, make_integrator
from service.render.framebuffer import FrameBuffer
from service.render.renderer import render_samples
from service.render.runtime import mitsuba
from service.render.scenes import load_scene_info

SCENES = Path(__file__).parent / "scenes"
# SMAPE's ε (Vogels et al. 2018, eq. 2; docs/design.md); relMSE's for the per-pixel weights.
SMAPE_EPS = 1e-2
RELMSE_EPS = 1e-2
SEEDS = 2
MITSUBA_SEEDS = 4
MEAN_TOLERANCE = 0.01
# |mean difference| in standard errors: 4 leaves a correct renderer a 1-in-15 000 false alarm.
Z_BOUND = 4.0
# Per-pixel R of the real renderer: 0.56–1.02 on every fidelity scene (32², 512 spp); the planted
# bugs read 1.74–2.06 on the raw image (test_planted_bugs.py).
PIXEL_BOUND = 1.3


def smape(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean(np.abs(a - b) / (np.abs(a) + np.abs(b) + SMAPE_EPS)))


def pixel_ratio(ours: list[np.ndarray], theirs: list[np.ndarray], our_variance: np.ndarray) -> float:
    """R (module doc): squared difference of the seed means over its expectation under no bias;
    `our_variance`: per pixel, of one of our images, from its samples."""
    o, m = np.mean(ours, axis=0), np.mean(theirs, axis=0)
    spread = np.var(ours, axis=0, ddof=1) if len(ours) > 1 else 0.0
    expected = np.maximum(our_variance, spread) / len(ours) + np.var(theirs, axis=0, ddof=1) / len(theirs)
    weight = 1.0 / (((o + m) / 2) ** 2 + RELMSE_EPS)
    return float(np.sum(weight * (o - m) ** 2) / max(np.sum(weight * expected), 1e-30))


@dataclass
class Comparison:
    ours_all: list[np.ndarray]  # per seed: (H, W, 3 + AOVs), the per-pixel estimates
    raw_all: list[np.ndarray]  # per seed: (H, W, 3), the splatted raw image
    mean_variance: list[float]  # per seed: variance of our image's mean radiance
    variance: np.ndarray  # (H, W, 3) per-pixel variance of our per-pixel estimates (seeds' mean)
    raw_variance: np.ndarray  # (H, W, 3) the same of our raw image
    mi_all: list[np.ndarray]  # per seed: mi.render's (H, W, 3 + AOVs)

    # The first two of each, as the SMAPE checks and single-image tests read them.
    @property
    def ours(self) -> np.ndarray:
        return self.ours_all[0]

    @property
    def ours_b(self) -> np.ndarray:
        return self.ours_all[1]

    @property
    def mi_a(self) -> np.ndarray:
        return self.mi_all[0]

    @property
    def mi_b(self) -> np.ndarray:
        return self.mi_all[1]

    @property
    def mean_ratio(self) -> float:
        reference = np.mean([m[..., :3].mean() for m in self.mi_all])
        return float(np.mean([o[..., :3].mean() for o in self.ours_all]) / reference)

    @property
    def mean_z(self) -> float:
        """Our mean minus mi.render's, in standard errors (mi.render's taken equal to ours)."""
        ours = np.mean([o[..., :3].mean() for o in self.ours_all])
        theirs = np.mean([m[..., :3].mean() for m in self.mi_all])
        variance = np.mean(self.mean_variance) / len(self.ours_all) + np.mean(self.mean_variance) / len(self.mi_all)
        return float((ours - theirs) / max(np.sqrt(variance), 1e-30))

    def pixel_ratio(self, raw: bool = False) -> float:
        mine = self.raw_all if raw else [o[..., :3] for o in self.ours_all]
        return pixel_ratio(mine, [m[..., :3] for m in self.mi_all], self.raw_variance if raw else self.variance)

    def failures(self) -> list[str]:
        """What the fidelity check rejects (empty: ours renders the scene as mi.render does)."""
        found = []
        if abs(self.mean_ratio - 1) >= MEAN_TOLERANCE:
            found.append(f"mean {self.mean_ratio:.4f}x mi.render's")
        if abs(self.mean_z) >= Z_BOUND:
            found.append(f"mean {self.mean_ratio:.4f}x mi.render's is {self.mean_z:+.1f} standard errors off")
        for raw, label in ((False, "per-pixel estimate"), (True, "raw image")):
            ratio = self.pixel_ratio(raw)
            if ratio >= PIXEL_BOUND:
                found.append(f"{label}: per-pixel R {ratio:.2f} (squared differences over their noise)")
        return found

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


def ours(scene, integrator, spp: int, seed: int = 1) -> FrameBuffer:
    h, w = (int(v) for v in scene.sensors()[0].film().crop_size()[::-1])
    buffer = FrameBuffer.empty(h, w)
    render_samples(scene, np.full((h, w), spp), buffer, integrator=integrator, seed=seed)
    return buffer


def _channels(buffer: FrameBuffer) -> np.ndarray:
    return np.concatenate([buffer.mean] + ([buffer.aovs] if buffer.aovs is not None else []), axis=-1)


def _mean_variance(buffer: FrameBuffer) -> float:
    """Variance of the image's mean radiance: our pixels' estimates are independent, and the
    channels' mean of each pixel has at most the channels' mean variance."""
    return float(buffer.variance.mean(axis=-1).sum() / buffer.spp.size**2)


@lru_cache(maxsize=32)
def _mitsuba_renders(name: str, spp: int, seeds: int, params: tuple[tuple[str, str], ...]) -> tuple[np.ndarray, ...]:
    """mi.render of the file exactly as written, one image per seed (shared by the planted-bug
    tests, which compare a bugged copy of ours against the same references)."""
    mi = mitsuba()
    reference = mi.load_file(str(SCENES / name), **dict(params))
    return tuple(mitsuba_render(mi, reference, spp, seed=101 * (s + 1)) for s in range(seeds))


def _our_scene(path: Path, params: dict[str, str]):
    """Ours through our own loader (or, with `params`, Mitsuba's parse with -D values)."""
    if params:
        return mitsuba().load_file(str(path), **params), None
    loaded = load_scene_info(path)
    return loaded.scene, make_integrator(inspect_frames([loaded]))


def compare_file(name: str, spp: int, *, seeds: int = SEEDS, ours_edit: Callable[[str], str] | None = None,
                 **params: str) -> Comparison:
    """Ours vs mi.render of tests/fidelity/scenes/`name`. `ours_edit` plants a bug: ours renders
    the edited XML (written beside nothing else, so only asset-free scenes), mi.render the file."""
    with tempfile.TemporaryDirectory() as folder:
        path = SCENES / name
        if ours_edit is not None:
            path = Path(folder) / name
            path.write_text(ours_edit((SCENES / name).read_text()))
        scene, integrator = _our_scene(path, params)
        buffers = [ours(scene, integrator, spp, seed=s + 1) for s in range(seeds)]
    return Comparison(
        ours_all=[_channels(b) for b in buffers],
        raw_all=[b.raw for b in buffers],
        mean_variance=[_mean_variance(b) for b in buffers],
        variance=np.mean([b.variance for b in buffers], axis=0),
        raw_variance=np.mean([b.raw_variance for b in buffers], axis=0),
        mi_all=list(_mitsuba_renders(name, spp, MITSUBA_SEEDS, tuple(sorted(params.items())))),
    )
