"""Mitsuba's `direct` integrator, traced so that its primary intersection also feeds the features.

Every sample also needs first-hit features (albedo, normal, depth) for the denoiser. For most
integrators they come from a second intersection along the same ray, which costs little next
to a path. A `direct` sample is only ~3 rays, so that extra intersection was ~17 % of the pass
(docs/fidelity.md) and kept `direct` under 0.9× of `mi.render`'s throughput.

So for a plain `DirectIntegrator` the same estimator is traced here, step for step as
Mitsuba 3.9's src/integrators/direct.cpp computes it (the estimator is in its docs: emitter
and BSDF sampling combined by the power heuristic, each strategy's sample count weighting
its share), and its surface interaction is handed back for the features. Whatever this
module does not reproduce exactly falls back to the integrator's own `sample()`:
`hide_emitters` (which re-intersects past area emitters), polarized variants (Mueller
matrices), and any integrator whose description does not parse. The fidelity suite pins
this path against `mi.render` (tests/fidelity/scenes/direct_*.xml).
"""
from __future__ import annotations

import re
from dataclasses import dataclass

import drjit as dr

_SAMPLE_COUNTS = re.compile(r"emitter_samples\s*=\s*(\d+)\s*,\s*bsdf_samples\s*=\s*(\d+)")


@dataclass(frozen=True)
class DirectSettings:
    """The parameters of a `direct` integrator instance that its estimator depends on."""

    emitter_samples: int
    bsdf_samples: int

    @property
    def frac_emitter(self) -> float:
        return self.emitter_samples / (self.emitter_samples + self.bsdf_samples)

    @property
    def frac_bsdf(self) -> float:
        return self.bsdf_samples / (self.emitter_samples + self.bsdf_samples)

    @property
    def weight_emitter(self) -> float:
        """Each emitter sample's share of its strategy (used only when there is one)."""
        return 1.0 / max(self.emitter_samples, 1)

    @property
    def weight_bsdf(self) -> float:
        return 1.0 / max(self.bsdf_samples, 1)


def direct_settings(mi, integrator) -> DirectSettings | None:
    """The settings when `integrator` is a `direct` this module reproduces exactly, else None.

    Mitsuba exposes the sample counts only through the plugin's description
    ("DirectIntegrator[ emitter_samples = E, bsdf_samples = B ]"); anything else is None.
    """
    if integrator.class_name() != "DirectIntegrator" or mi.is_polarized:
        return None
    if getattr(integrator, "hide_emitters", True):
        return None
    match = _SAMPLE_COUNTS.search(str(integrator))
    if match is None:
        return None
    emitter_samples, bsdf_samples = int(match.group(1)), int(match.group(2))
    if emitter_samples + bsdf_samples == 0:
        return None
    return DirectSettings(emitter_samples, bsdf_samples)


def _power_heuristic(pdf_a, pdf_b):
    """Veach's power heuristic (β = 2); a non-finite weight (both pdfs 0 or ∞) counts as 0."""
    a2, b2 = dr.square(pdf_a), dr.square(pdf_b)
    w = a2 / (a2 + b2)
    return dr.select(dr.isfinite(w), w, 0.0)


def sample_direct(mi, settings: DirectSettings, scene, sampler, ray):
    """(radiance, surface interaction of the primary hit) for one wavefront of camera rays."""
    si = scene.ray_intersect(ray, mi.RayFlags.All, True)
    result = dr.zeros(mi.Spectrum)

    # Emitters seen directly (hide_emitters is handled by the integrator's own sample()).
    visible = si.emitter(scene)
    result += visible.eval(si, visible != None)  # noqa: E711 — a Dr.Jit pointer comparison

    active = si.is_valid()
    ctx = mi.BSDFContext()
    bsdf = si.bsdf(ray)

    # Emitter sampling: only where the BSDF has a smooth lobe to evaluate.
    sample_emitter = active & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
    for _ in range(settings.emitter_samples):
        ds, emitter_value = scene.sample_emitter_direction(si, sampler.next_2d(sample_emitter), True, sample_emitter)
        active_e = sample_emitter & (ds.pdf != 0.0)
        wo = si.to_local(ds.d)
        bsdf_value, bsdf_pdf = bsdf.eval_pdf(ctx, si, wo, active_e)
        mis = dr.select(ds.delta, 1.0,
                        _power_heuristic(ds.pdf * settings.frac_emitter, bsdf_pdf * settings.frac_bsdf)
                        * settings.weight_emitter)
        result += dr.select(active_e, mis * bsdf_value * emitter_value, 0.0)

    # BSDF sampling: keep the directions that land on an emitter.
    for _ in range(settings.bsdf_samples):
        bs, bsdf_value = bsdf.sample(ctx, si, sampler.next_1d(active), sampler.next_2d(active), active)
        active_b = active & dr.any(bsdf_value != 0.0)
        si_bsdf = scene.ray_intersect(si.spawn_ray(si.to_world(bs.wo)), active_b)
        emitter = si_bsdf.emitter(scene, active_b)
        active_b &= emitter != None  # noqa: E711
        emitter_value = emitter.eval(si_bsdf, active_b)
        delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        ds = mi.DirectionSample3f(scene, si_bsdf, si)
        emitter_pdf = dr.select(delta, 0.0, scene.pdf_emitter_direction(si, ds, active_b))
        mis = _power_heuristic(bs.pdf * settings.frac_bsdf, emitter_pdf * settings.frac_emitter)
        result += dr.select(active_b, bsdf_value * emitter_value * mis * settings.weight_bsdf, 0.0)
    return result, si
