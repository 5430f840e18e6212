"""The Cornell box with its tall block replaced by a cube of homogeneous fog.

The smallest scene that needs a volumetric integrator: only the fog cube's interior carries a
medium, and the cube's null BSDF makes its boundary an invisible medium transition.
"""
from __future__ import annotations

from service.render.builtin.cornell import cornell_base

FOG_SIGMA_T = 5.0
FOG_ALBEDO = (0.9, 0.9, 0.9)


def veiled(frame: int = 0) -> dict:
    scene = cornell_base()
    # A scene is rendered with the integrator it declares, so the fog scene declares the
    # volumetric one itself (same depth as the box it is built from).
    scene["integrator"]["type"] = "volpath"
    fog_box = scene["large-box"]
    fog_box["bsdf"] = {"type": "null"}
    fog_box["interior"] = {
        "type": "homogeneous",
        "sigma_t": FOG_SIGMA_T,
        "albedo": {"type": "rgb", "value": list(FOG_ALBEDO)},
    }
    return scene
