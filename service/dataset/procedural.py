"""Seeded procedural scenes for denoiser training: a spec is sampled, then turned into a dict.

Two steps so that the random choices are plain data (`SceneSpec`: comparable, printable,
testable without Mitsuba) and only `scene_dict` touches Mitsuba objects. One seed fixes the
whole scene including its camera path; `frame` only moves the camera along that path, so the
frames of a sequence share geometry, materials and lights and the renderer can produce
motion vectors between them (frame −1 exists too: it is the previous camera of frame 0).

Scenes are kept cheap for a CPU: a handful of analytic shapes, no media (so the plain `path`
integrator suffices), max depth 8, small textures. Layouts: a room lit from inside and open at
the front, open ground under a sky, and (only when asked for: they are not in the default mix, so
the scenes of every existing seed stay what they were) a closed room lit through a window
(service.dataset.window_room) or by a tiny bulb in a lampshade (service.dataset.shaded_lamp).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from service.dataset.textures import TEXTURE_KINDS, SkySpec, TextureSpec, sky_image, texture_image
from service.dataset.shaded_lamp import ShadeSpec, sample_shade, shade_shapes
from service.dataset.window_room import (WindowSpec, closed_room_bounds, front_wall, sample_window, sun_through,
                                         wall_panels)
from service.render.runtime import mitsuba

Color = tuple[float, float, float]
Vec3 = tuple[float, float, float]

LAYOUTS = ("room", "ground")   # the default mix, drawn per seed
WINDOW_LAYOUT = "window"        # only on request (sample_spec's `layout`)
SHADED_LAYOUT = "shaded"        # likewise
CLOSED_LAYOUTS = (WINDOW_LAYOUT, SHADED_LAYOUT)   # rooms closed on all four sides
# What a data set may ask for (`renderloop dataset --layout`): "mixed" is the seeds' own draw of
# LAYOUTS; the closed layouts are the recipe's extra data sets (scripts/train-weights.sh).
DATASET_LAYOUTS = ("mixed", *CLOSED_LAYOUTS)
SHAPES = ("sphere", "cube", "cylinder", "rectangle", "disk")
MATERIALS = ("diffuse", "textured", "roughplastic", "roughconductor", "conductor", "dielectric")
LIGHTS = ("area_rect", "area_sphere", "point", "spot", "constant", "sky", "firefly")
METALS = ("Au", "Ag", "Al", "Cu", "Cr")
MAX_DEPTH = 8  # enough for glass and inter-reflections; deeper paths cost CPU time for little
# Only closed shapes may be glass: an open cylinder or a one-sided panel of glass is not a
# physically meaningful refracting object and produces odd, uninformative images.
CLOSED_SHAPES = ("sphere", "cube")
THINLENS_PROBABILITY = 0.3
FIREFLY_PROBABILITY = 0.2

_SHAPE_WEIGHTS = (0.3, 0.25, 0.15, 0.15, 0.15)
_MATERIAL_WEIGHTS = (0.2, 0.2, 0.2, 0.15, 0.1, 0.15)
_ROOM_LIGHT_KINDS = ("area_rect_large", "area_rect_small", "area_sphere", "point", "spot")
_ROOM_LIGHT_WEIGHTS = (0.4, 0.2, 0.15, 0.15, 0.1)


@dataclass(frozen=True)
class MaterialSpec:
    kind: str  # one of MATERIALS
    color: Color = (0.5, 0.5, 0.5)
    texture: TextureSpec | None = None  # set for "textured", optional for "roughplastic"
    roughness: float = 0.0  # GGX alpha for the rough kinds
    metal: str = "Al"
    ior: float = 1.5


@dataclass(frozen=True)
class ObjectSpec:
    shape: str  # one of SHAPES
    position: Vec3  # centre of the footprint on the floor (y = 0)
    size: Vec3  # half extents (x, y, z); spheres/disks use size[0] as radius
    yaw: float  # degrees around +Y
    tilt: float  # degrees around the object's own X (panels only)
    material: MaterialSpec


@dataclass(frozen=True)
class LightSpec:
    kind: str  # one of LIGHTS
    position: Vec3 = (0.0, 0.0, 0.0)
    size: float = 0.0  # half side of a square area light, or a sphere radius
    color: Color = (1.0, 1.0, 1.0)  # radiance (area/env) or intensity (point/spot)
    target: Vec3 = (0.0, 0.0, 0.0)  # spot lights aim here
    cutoff: float = 30.0  # spot cone, degrees
    sky: SkySpec | None = None


@dataclass(frozen=True)
class CameraSpec:
    target: Vec3
    radius: float  # orbit radius around the target at frame 0
    azimuth: float  # degrees, 0 = looking along −Z from +Z
    height: float  # camera y at frame 0
    fov: float  # degrees
    aperture: float  # thin-lens radius; 0 = pinhole
    step_azimuth: float  # degrees per frame
    step_height: float  # per frame
    step_radius: float  # per frame
    bounds: tuple[Vec3, Vec3] | None  # camera box (rooms): keeps it inside the walls


@dataclass(frozen=True)
class SceneSpec:
    seed: int
    layout: str  # one of LAYOUTS
    room: Vec3  # width, height, depth (rooms); unused on open ground
    floor: MaterialSpec
    walls: MaterialSpec
    objects: tuple[ObjectSpec, ...]
    lights: tuple[LightSpec, ...]
    camera: CameraSpec
    window: WindowSpec | None = None  # the window layout's opening
    shade: ShadeSpec | None = None    # the shaded layout's lamp


# --- sampling the spec ---------------------------------------------------------------------


def _pick(rng: np.random.Generator, options: tuple[str, ...], weights: tuple[float, ...]) -> str:
    p = np.asarray(weights, dtype=np.float64)
    return options[int(rng.choice(len(options), p=p / p.sum()))]


def _color(rng: np.random.Generator, lo: float = 0.05, hi: float = 0.85) -> Color:
    return tuple(float(c) for c in rng.uniform(lo, hi, 3))


def _tint(rng: np.random.Generator, strength: float) -> Color:
    """A near-white light colour scaled to `strength` (mean channel value)."""
    c = 1.0 + rng.uniform(-0.3, 0.3, 3)
    c = c / c.mean() * strength
    return tuple(float(v) for v in c)


def _exposure(rng: np.random.Generator) -> float:
    """Log-normal brightness factor, so the data spans a wide HDR range."""
    return float(math.exp(rng.normal(0.0, 0.5)))


def _texture(rng: np.random.Generator) -> TextureSpec:
    return TextureSpec(
        kind=TEXTURE_KINDS[int(rng.integers(len(TEXTURE_KINDS)))],
        color_a=_color(rng),
        color_b=_color(rng),
        frequency=int(rng.integers(2, 12)),
        angle=float(rng.uniform(0, math.pi)),
        seed=int(rng.integers(2**31)),
    )


def _material(rng: np.random.Generator, shape: str) -> MaterialSpec:
    kind = _pick(rng, MATERIALS, _MATERIAL_WEIGHTS)
    if kind == "dielectric" and shape not in CLOSED_SHAPES:
        kind = "roughplastic"
    texture = _texture(rng) if kind == "textured" or (kind == "roughplastic" and rng.random() < 0.4) else None
    return MaterialSpec(
        kind=kind,
        color=_color(rng),
        texture=texture,
        roughness=float(rng.uniform(0.05, 0.5)),
        metal=METALS[int(rng.integers(len(METALS)))],
        ior=float(rng.uniform(1.3, 1.7)),
    )


def _surface_material(rng: np.random.Generator) -> MaterialSpec:
    """Floors and walls: diffuse, often textured, sometimes glossy plastic."""
    kind = _pick(rng, ("diffuse", "textured", "roughplastic"), (0.4, 0.4, 0.2))
    texture = _texture(rng) if kind != "diffuse" and rng.random() < 0.8 else None
    return MaterialSpec(kind=kind, color=_color(rng, 0.2, 0.8), texture=texture,
                        roughness=float(rng.uniform(0.1, 0.4)))


def _objects(rng: np.random.Generator, extent: tuple[float, float, float, float]) -> tuple[ObjectSpec, ...]:
    """2–5 objects on the floor inside (x0, x1, z0, z1), footprints not overlapping."""
    x0, x1, z0, z1 = extent
    placed: list[tuple[float, float, float]] = []  # (x, z, footprint radius)
    objects = []
    for _ in range(int(rng.integers(2, 6))):
        shape = _pick(rng, SHAPES, _SHAPE_WEIGHTS)
        size = tuple(float(s) for s in rng.uniform(0.2, 0.55, 3))
        footprint = max(size[0], size[2]) * (1.5 if shape == "cube" else 1.0)
        for _attempt in range(30):  # rejection sampling; a crowded floor just gets fewer objects
            x, z = float(rng.uniform(x0, x1)), float(rng.uniform(z0, z1))
            if all(math.hypot(x - px, z - pz) > footprint + pr for px, pz, pr in placed):
                break
        else:
            continue
        placed.append((x, z, footprint))
        objects.append(ObjectSpec(shape=shape, position=(x, 0.0, z), size=size,
                                  yaw=float(rng.uniform(0, 360)), tilt=float(rng.uniform(-20, 20)),
                                  material=_material(rng, shape)))
    return tuple(objects)


def _room_light(rng: np.random.Generator, room: Vec3) -> LightSpec:
    """One light for a room, its strength set for an irradiance of ~3 on the floor
    (times a log-normal exposure), so images are neither black nor blown out on average."""
    width, height, depth = room
    kind = _pick(rng, _ROOM_LIGHT_KINDS, _ROOM_LIGHT_WEIGHTS)
    irradiance = 3.0 * _exposure(rng)
    x, z = float(rng.uniform(-width / 4, width / 4)), float(rng.uniform(-depth / 4, depth / 4))
    drop = height - 0.5  # distance from the ceiling to the objects' middle
    if kind.startswith("area_rect"):
        half = float(rng.uniform(0.5, 1.1) if kind == "area_rect_large" else rng.uniform(0.1, 0.25))
        radiance = irradiance * drop**2 / (4 * half**2)
        return LightSpec("area_rect", position=(x, height - 0.01, z), size=half, color=_tint(rng, radiance))
    y = float(rng.uniform(height * 0.5, height - 0.3))
    if kind == "area_sphere":
        r = float(rng.uniform(0.05, 0.15))
        return LightSpec("area_sphere", position=(x, y, z), size=r,
                         color=_tint(rng, irradiance * y**2 / (math.pi * r**2)))
    intensity = _tint(rng, irradiance * y**2)
    if kind == "point":
        return LightSpec("point", position=(x, y, z), color=intensity)
    aim = (float(rng.uniform(-0.5, 0.5)), 0.0, float(rng.uniform(-0.5, 0.5)))
    return LightSpec("spot", position=(x + 0.3, y, z + 0.3), color=intensity, target=aim,
                     cutoff=float(rng.uniform(20, 50)))


def _firefly(rng: np.random.Generator, center: Vec3, spread: float) -> LightSpec:
    """A tiny, very bright sphere: paths that hit it by BSDF sampling make fireflies."""
    r = float(rng.uniform(0.01, 0.03))
    pos = (center[0] + float(rng.uniform(-spread, spread)), float(rng.uniform(0.3, 1.8)),
           center[2] + float(rng.uniform(-spread, spread)))
    return LightSpec("firefly", position=pos, size=r,
                     color=_tint(rng, 2.0 * _exposure(rng) * 2.0 / (math.pi * r**2)))


def _sky(rng: np.random.Generator) -> SkySpec:
    width = float(rng.uniform(0.04, 0.1))
    # Peak chosen so the sun alone gives an irradiance of ~3: E ≈ peak · 2πσ² for a Gaussian blob.
    peak = 3.0 * _exposure(rng) / (2 * math.pi * width**2)
    return SkySpec(zenith=_color(rng, 0.1, 0.6), horizon=_color(rng, 0.5, 1.2), ground=_color(rng, 0.05, 0.3),
                   sun_azimuth=float(rng.uniform(0, 2 * math.pi)),
                   sun_elevation=float(rng.uniform(math.radians(10), math.radians(70))),
                   sun_radiance=peak, sun_width=width)


def _ground_lights(rng: np.random.Generator) -> list[LightSpec]:
    if rng.random() < 0.6:
        lights = [LightSpec("sky", sky=_sky(rng))]
    else:
        lights = [LightSpec("constant", color=_tint(rng, float(rng.uniform(0.4, 1.5))))]
    if rng.random() < 0.3:  # an extra local light over the open ground
        pos = (float(rng.uniform(-2, 2)), float(rng.uniform(1.0, 3.0)), float(rng.uniform(-2, 2)))
        lights.append(LightSpec("point", position=pos, color=_tint(rng, 3.0 * _exposure(rng) * pos[1] ** 2)))
    return lights


def _camera(rng: np.random.Generator, layout: str, room: Vec3) -> CameraSpec:
    """An orbit around a target near the objects; small per-frame steps (a few pixels of
    motion at training resolutions) make the camera path of a sequence."""
    width, height, depth = room
    aperture = float(rng.uniform(0.02, 0.1)) if rng.random() < THINLENS_PROBABILITY else 0.0
    steps = dict(step_azimuth=float(rng.choice([-1, 1]) * rng.uniform(0.5, 2.5)),
                 step_height=float(rng.uniform(-0.03, 0.03)), step_radius=float(rng.uniform(-0.05, 0.05)))
    fov = float(rng.uniform(35, 60))
    if layout == "room":
        target = (float(rng.uniform(-0.3, 0.3)), float(rng.uniform(0.4, 0.9)), float(rng.uniform(-0.5, 0.0)))
        margin = 0.15
        bounds = ((-width / 2 + margin, margin, -depth / 2 + margin), (width / 2 - margin, height - margin, depth))
        return CameraSpec(target=target, radius=float(rng.uniform(2.0, 3.5)), azimuth=float(rng.uniform(-30, 30)),
                          height=float(rng.uniform(0.6, height - 0.5)), fov=fov, aperture=aperture,
                          bounds=bounds, **steps)
    target = (float(rng.uniform(-0.3, 0.3)), float(rng.uniform(0.2, 0.7)), float(rng.uniform(-0.3, 0.3)))
    return CameraSpec(target=target, radius=float(rng.uniform(2.2, 4.5)), azimuth=float(rng.uniform(0, 360)),
                      height=float(rng.uniform(0.3, 2.5)), fov=fov, aperture=aperture, bounds=None, **steps)


def sample_spec(seed: int, layout: str | None = None) -> SceneSpec:
    """All random choices of scene `seed`, in a fixed order (so one seed, one scene). `layout`:
    one of LAYOUTS or CLOSED_LAYOUTS instead of the seed's own draw (which is still made, so the
    rest of the scene comes from the same random stream)."""
    if layout not in (None, *LAYOUTS, *CLOSED_LAYOUTS):
        raise ValueError(f"unknown layout {layout!r}; known: {', '.join((*LAYOUTS, *CLOSED_LAYOUTS))}")
    rng = np.random.default_rng(seed)
    drawn = LAYOUTS[int(rng.integers(len(LAYOUTS)))]
    layout = layout or drawn
    room = (float(rng.uniform(3, 5)), float(rng.uniform(2.5, 3.5)), float(rng.uniform(3, 5)))
    floor, walls = _surface_material(rng), _surface_material(rng)
    window = shade = None
    w, _, d = room
    # Objects first in every layout: the rest of a seed's stream is the same whichever is asked for.
    objects = _objects(rng, (-2.0, 2.0, -2.0, 2.0) if layout == "ground"
                       else (-w / 2 + 0.5, w / 2 - 0.5, -d / 2 + 0.5, d / 2 - 1.5))
    if layout == "room":
        lights = [_room_light(rng, room)]
        if rng.random() < 0.3:
            lights.append(_room_light(rng, room))
    elif layout == WINDOW_LAYOUT:   # lit only by the sun and sky through the opening
        window = sample_window(rng, room)
        lights = [LightSpec("sky", sky=sun_through(rng, window, _sky(rng)))]
    elif layout == SHADED_LAYOUT:   # lit only by the bulb in its shade
        shade = sample_shade(rng, room, _exposure(rng), _tint(rng, 1.0))
        lights = []
    else:
        lights = _ground_lights(rng)
    if rng.random() < FIREFLY_PROBABILITY:
        lights.append(_firefly(rng, (0.0, 0.0, 0.0), 1.5))
    camera = _camera(rng, "room" if layout in CLOSED_LAYOUTS else layout, room)
    if layout in CLOSED_LAYOUTS:
        camera = dataclasses.replace(camera, bounds=closed_room_bounds(room))
    return SceneSpec(seed=seed, layout=layout, room=room, floor=floor, walls=walls, objects=objects,
                     lights=tuple(lights), camera=camera, window=window, shade=shade)


# --- spec → Mitsuba dict -------------------------------------------------------------------


def _rgb(c: Color) -> dict:
    return {"type": "rgb", "value": list(c)}


def _reflectance(mi, m: MaterialSpec):
    return {"type": "bitmap", "bitmap": mi.Bitmap(texture_image(m.texture))} if m.texture else _rgb(m.color)


def _bsdf(mi, m: MaterialSpec, two_sided: bool = False) -> dict:
    if m.kind in ("diffuse", "textured"):
        bsdf = {"type": "diffuse", "reflectance": _reflectance(mi, m)}
    elif m.kind == "roughplastic":
        bsdf = {"type": "roughplastic", "distribution": "ggx", "alpha": m.roughness,
                "diffuse_reflectance": _reflectance(mi, m)}
    elif m.kind == "roughconductor":
        bsdf = {"type": "roughconductor", "material": m.metal, "alpha": m.roughness}
    elif m.kind == "conductor":
        bsdf = {"type": "conductor", "material": m.metal}
    elif m.kind == "dielectric":
        return {"type": "dielectric", "int_ior": m.ior}  # refracts from both sides already
    else:
        raise ValueError(f"unknown material kind {m.kind!r}; known: {', '.join(MATERIALS)}")
    # Panels and disks are seen from both sides; one-sided BSDFs would render their backs black.
    return {"type": "twosided", "bsdf": bsdf} if two_sided else bsdf


def _rect(mi, position: Vec3, rotations: list[tuple[Vec3, float]], scale: Vec3) -> object:
    """to_world of a unit shape: scale first, then the rotations in order, then translate."""
    t = mi.ScalarTransform4f().translate(list(position))
    for axis, angle in rotations:
        t = t.rotate(list(axis), angle)
    return t.scale(list(scale))


def _object_shapes(mi, index: int, o: ObjectSpec) -> dict[str, dict]:
    x, _, z = o.position
    sx, sy, sz = o.size
    yaw = ((0.0, 1.0, 0.0), o.yaw)
    bsdf = _bsdf(mi, o.material, two_sided=o.shape in ("rectangle", "disk"))
    key = f"object{index}_{o.shape}"
    if o.shape == "sphere":
        return {key: {"type": "sphere", "center": [x, sx, z], "radius": sx, "bsdf": bsdf}}
    if o.shape == "cube":
        return {key: {"type": "cube", "to_world": _rect(mi, (x, sy, z), [yaw], (sx, sy, sz)), "bsdf": bsdf}}
    if o.shape == "cylinder":
        top = 2 * sy
        # Mitsuba's cylinder is an open tube: a disk caps it so the inside is never seen.
        cap = _rect(mi, (x, top, z), [((1.0, 0.0, 0.0), -90.0)], (sx, sx, 1.0))
        return {key: {"type": "cylinder", "p0": [x, 0.0, z], "p1": [x, top, z], "radius": sx, "bsdf": bsdf},
                key + "_cap": {"type": "disk", "to_world": cap, "bsdf": bsdf}}
    if o.shape == "rectangle":
        tilt = ((1.0, 0.0, 0.0), o.tilt)
        return {key: {"type": "rectangle", "to_world": _rect(mi, (x, sy, z), [yaw, tilt], (sx, sy, 1.0)),
                      "bsdf": bsdf}}
    if o.shape == "disk":
        return {key: {"type": "disk", "to_world": _rect(mi, (x, sx, z), [yaw], (sx, sx, 1.0)), "bsdf": bsdf}}
    raise ValueError(f"unknown shape {o.shape!r}; known: {', '.join(SHAPES)}")


def _surfaces(mi, spec: SceneSpec) -> dict[str, dict]:
    """Floor, plus ceiling and three walls for a room (the front stays open for the camera); the
    closed layouts' rooms have the front wall too, the window layout's window wall cut around
    the opening."""
    down = ((1.0, 0.0, 0.0), -90.0)  # rectangle normal +Z → +Y
    if spec.layout == "ground":
        return {"floor": {"type": "rectangle", "to_world": _rect(mi, (0, 0, 0), [down], (20, 20, 1)),
                          "bsdf": _bsdf(mi, spec.floor)}}
    w, h, d = spec.room
    walls = _bsdf(mi, spec.walls)
    surfaces = {
        "floor": {"type": "rectangle", "to_world": _rect(mi, (0, 0, 0), [down], (w / 2, d / 2, 1)),
                  "bsdf": _bsdf(mi, spec.floor)},
        "ceiling": {"type": "rectangle", "to_world": _rect(mi, (0, h, 0), [((1.0, 0.0, 0.0), 90.0)],
                                                           (w / 2, d / 2, 1)), "bsdf": walls},
        "wall_back": {"type": "rectangle", "to_world": _rect(mi, (0, h / 2, -d / 2), [], (w / 2, h / 2, 1)),
                      "bsdf": walls},
        "wall_left": {"type": "rectangle", "to_world": _rect(mi, (-w / 2, h / 2, 0), [((0.0, 1.0, 0.0), 90.0)],
                                                             (d / 2, h / 2, 1)), "bsdf": walls},
        "wall_right": {"type": "rectangle", "to_world": _rect(mi, (w / 2, h / 2, 0), [((0.0, 1.0, 0.0), -90.0)],
                                                              (d / 2, h / 2, 1)), "bsdf": walls},
    }
    if spec.window is not None:
        del surfaces[f"wall_{spec.window.wall}"]
        surfaces.update(wall_panels(mi, spec.room, spec.window, walls))
    elif spec.layout in CLOSED_LAYOUTS:
        surfaces.update(front_wall(mi, spec.room, walls))
    return surfaces


def _look_at(mi, origin: Vec3, target: Vec3):
    direction = np.subtract(target, origin)
    # look_at is degenerate when the view direction is parallel to `up`.
    up = [0.0, 0.0, 1.0] if abs(direction[1]) > 0.99 * np.linalg.norm(direction) else [0.0, 1.0, 0.0]
    return mi.ScalarTransform4f().look_at(origin=list(origin), target=list(target), up=up)


def _light(mi, index: int, light: LightSpec) -> dict[str, dict]:
    key = f"light{index}_{light.kind}"
    if light.kind == "area_rect":
        to_world = _rect(mi, light.position, [((1.0, 0.0, 0.0), 90.0)], (light.size, light.size, 1.0))
        return {key: {"type": "rectangle", "to_world": to_world,
                      "emitter": {"type": "area", "radiance": _rgb(light.color)}}}
    if light.kind in ("area_sphere", "firefly"):
        return {key: {"type": "sphere", "center": list(light.position), "radius": light.size,
                      "emitter": {"type": "area", "radiance": _rgb(light.color)}}}
    if light.kind == "point":
        return {key: {"type": "point", "position": list(light.position), "intensity": _rgb(light.color)}}
    if light.kind == "spot":
        return {key: {"type": "spot", "to_world": _look_at(mi, light.position, light.target),
                      "intensity": _rgb(light.color), "cutoff_angle": light.cutoff,
                      "beam_width": 0.75 * light.cutoff}}
    if light.kind == "constant":
        return {key: {"type": "constant", "radiance": _rgb(light.color)}}
    if light.kind == "sky":
        return {key: {"type": "envmap", "bitmap": mi.Bitmap(sky_image(light.sky))}}
    raise ValueError(f"unknown light kind {light.kind!r}; known: {', '.join(LIGHTS)}")


def camera_origin(camera: CameraSpec, frame: int) -> Vec3:
    """Camera position at `frame`: the orbit advanced by `frame` steps (smooth in `frame`)."""
    azimuth = math.radians(camera.azimuth + camera.step_azimuth * frame)
    radius = camera.radius + camera.step_radius * frame
    tx, _, tz = camera.target
    origin = np.array([tx + radius * math.sin(azimuth), camera.height + camera.step_height * frame,
                       tz + radius * math.cos(azimuth)])
    if camera.bounds is not None:
        origin = np.clip(origin, camera.bounds[0], camera.bounds[1])
    return tuple(float(v) for v in origin)


def sensor_dict(camera: CameraSpec, *, size: int, frame: int) -> dict:
    """The sensor of `camera` at `frame` (also loadable on its own, e.g. as a previous camera)."""
    mi = mitsuba()
    origin = camera_origin(camera, frame)
    sensor = {
        "type": "thinlens" if camera.aperture > 0 else "perspective",
        "fov": camera.fov,
        "to_world": _look_at(mi, origin, camera.target),
        "film": {"type": "hdrfilm", "width": size, "height": size, "pixel_format": "rgb",
                 "rfilter": {"type": "box"}},
        # The renderer seeds its own independent sampler per wavefront; this one only serves
        # plain mi.render calls (previews, debugging).
        "sampler": {"type": "independent", "sample_count": 16},
    }
    if camera.aperture > 0:
        # Focus on the orbit target: the objects near it are sharp, the rest is blurred.
        sensor["aperture_radius"] = camera.aperture
        sensor["focus_distance"] = float(np.linalg.norm(np.subtract(origin, camera.target)))
    return sensor


def scene_dict(spec: SceneSpec, *, size: int, frame: int = 0) -> dict:
    """The `mi.load_dict` dict of `spec` seen from the camera at `frame`."""
    if size < 1:
        raise ValueError(f"size must be >= 1, got {size}")
    mi = mitsuba()
    scene = {"type": "scene",
             "integrator": {"type": "path", "max_depth": MAX_DEPTH},
             "sensor": sensor_dict(spec.camera, size=size, frame=frame)}
    scene.update(_surfaces(mi, spec))
    for i, o in enumerate(spec.objects):
        scene.update(_object_shapes(mi, i, o))
    for i, light in enumerate(spec.lights):
        scene.update(_light(mi, i, light))
    if spec.shade is not None:
        scene.update(shade_shapes(spec.shade, len(spec.lights)))
    return scene


def generate_scene(seed: int, *, size: int, frame: int = 0, layout: str | None = None) -> dict:
    """Scene `seed` at `size`×`size`, camera at `frame` of its path. A single-frame scene is
    frame 0; `frame` may be −1, the previous camera that motion vectors of frame 0 refer to."""
    return scene_dict(sample_spec(seed, layout), size=size, frame=frame)
