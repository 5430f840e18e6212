"""Which integrators, sensors and films the per-pixel-count wavefront can drive, and how.

The renderer calls an integrator's per-ray `sample()` on a wavefront it built itself (one lane
per sample, each pixel its own count). That works for every `SamplingIntegrator`; it cannot
work for integrators that write to the film themselves (particle tracers splat wherever a light
path lands, so no lane belongs to one pixel) nor for output the RGB frame buffer cannot hold
(Stokes vectors). Those are refused before anything is instantiated, with one line that names
the plugin and what to use instead.

Mitsuba's differentiable integrators (`prb`, `prbvolpath`, `prb_basic`, `direct_projective`,
`prb_projective`) are Python classes whose `sample()` takes an AD mode and state; in primal
mode they compute the same radiance as their `render()` does, so they are driven through that
signature (`sample_lane`).
"""
from __future__ import annotations

import drjit as dr

# plugin name -> why it cannot run here and what to use instead.
REFUSED_INTEGRATORS = {
    "ptracer": "splats light paths to whatever pixel they reach, so samples cannot be handed out "
    "per pixel; use 'path' (or 'volpath' with media), which converges to the same image",
    "stokes": "writes Stokes-vector channels that only a polarized variant computes; "
    "render the inner integrator directly, or use Mitsuba's own mi.render in a *_polarized variant",
}
SUPPORTED_SENSORS = ("perspective", "thinlens", "orthographic", "telecentric")
SUPPORTED_FILMS = ("hdrfilm",)


def integrator_refusal(name: str, variant: str) -> str | None:
    """Why integrator plugin `name` cannot be driven per pixel in `variant`, or None."""
    if name == "stokes" and "polarized" in variant:
        return None
    if name in REFUSED_INTEGRATORS:
        return f"integrator '{name}' is not supported: it {REFUSED_INTEGRATORS[name]}"
    return None


def sensor_refusal(name: str, variant: str) -> str | None:
    if name in SUPPORTED_SENSORS:
        return None
    return (f"sensor '{name}' is not supported: only cameras that map film pixels to rays can be "
            f"sampled per pixel ({', '.join(SUPPORTED_SENSORS)}); render it with Mitsuba's mi.render")


def film_refusal(name: str, variant: str) -> str | None:
    if name in SUPPORTED_FILMS:
        return None
    return f"film '{name}' is not supported: the frame buffer holds RGB radiance; use <film type=\"hdrfilm\">"


def instance_refusal(mi, integrator) -> str | None:
    """The last check, on the instantiated plugin: anything that is no SamplingIntegrator."""
    if isinstance(integrator, mi.SamplingIntegrator):
        return None
    return (f"integrator {integrator.class_name()} is not supported: it is not a sampling integrator, so its "
            "samples cannot be handed out per pixel; use 'path' (or 'volpath' with media)")


def is_ad_integrator(mi, integrator) -> bool:
    return isinstance(integrator, mi.ad.integrators.common.ADIntegrator)


def sample_lane(mi, integrator, scene, sampler, ray, medium=None):
    """(radiance, valid, aovs) for one wavefront of rays, whichever signature `sample` has.

    `medium`: the sensor's medium (a camera inside fog), which Mitsuba's SamplingIntegrator
    hands to `sample()` as the ray's starting medium; without it a volumetric integrator starts
    the ray in vacuum until it crosses a medium boundary."""
    if is_ad_integrator(mi, integrator):
        # Primal mode, no adjoint state: exactly what ADIntegrator.render() evaluates per ray
        # (it takes no starting medium: Mitsuba's own render() does not pass the sensor's).
        radiance, valid, aovs, _ = integrator.sample(
            mode=dr.ADMode.Primal, scene=scene, sampler=sampler, ray=ray, depth=mi.UInt32(0),
            δL=None, δaovs=None, state_in=None, active=mi.Bool(True),
        )
        return radiance, valid, list(aovs)
    radiance, valid, aovs = integrator.sample(scene, sampler, ray, medium, True)
    return radiance, valid, list(aovs)


def to_rgb(mi, value, wavelengths, active=True):
    """Linear sRGB of a sample the way hdrfilm develops it: spectral samples through the CIE
    matching functions at the lane's wavelengths (mi.spectrum_to_srgb), polarized ones by their
    intensity, monochromatic ones as grey."""
    if mi.is_polarized:
        value = mi.unpolarized_spectrum(value)
    if mi.is_spectral:
        return mi.spectrum_to_srgb(value, wavelengths, active)
    if mi.is_monochromatic:
        return mi.Color3f(value[0])
    return value
