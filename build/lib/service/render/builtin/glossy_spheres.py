"""Three spheres on the Cornell floor, one per hard-to-denoise material family."""
from __future__ import annotations

from service.render.builtin.cornell import cornell_base

# Glass behind glass needs a few more bounces than the diffuse box to look transparent.
GLOSSY_MAX_DEPTH = 12
SPHERE_RADIUS = 0.3
FLOOR_Y = -1.0


def _sphere(x: float, z: float, bsdf: dict) -> dict:
    return {"type": "sphere", "center": [x, FLOOR_Y + SPHERE_RADIUS, z], "radius": SPHERE_RADIUS, "bsdf": bsdf}


def glossy_spheres(frame: int = 0) -> dict:
    scene = cornell_base()
    del scene["large-box"], scene["small-box"]
    scene["integrator"]["max_depth"] = GLOSSY_MAX_DEPTH
    scene["gold-sphere"] = _sphere(-0.6, -0.3, {"type": "roughconductor", "material": "Au", "alpha": 0.15})
    scene["plastic-sphere"] = _sphere(0.6, -0.3, {
        "type": "roughplastic",
        "distribution": "ggx",
        "alpha": 0.2,
        "diffuse_reflectance": {"type": "rgb", "value": [0.1, 0.25, 0.6]},
    })
    scene["glass-sphere"] = _sphere(0.0, 0.35, {"type": "dielectric", "int_ior": "bk7", "ext_ior": "air"})
    return scene
