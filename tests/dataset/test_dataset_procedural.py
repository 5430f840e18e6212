import numpy as np
import pytest

from service.dataset.procedural import generate_scene, sample_spec
from service.dataset.window_room import WINDOW_WALLS
from service.dataset.textures import TEXTURE_KINDS, TextureSpec, texture_image
from service.render.runtime import mitsuba

SEEDS = range(30)


def canonical(value):
    """The dict with Mitsuba objects (Bitmap, Transform) turned into comparable plain data."""
    mi = mitsuba()
    if isinstance(value, dict):
        return {k: canonical(v) for k, v in value.items()}
    if isinstance(value, list):
        return [canonical(v) for v in value]
    if isinstance(value, mi.Bitmap):
        return ("bitmap", np.asarray(value).tobytes())
    if isinstance(value, mi.ScalarTransform4f):
        return ("transform", np.asarray(value.matrix).round(6).tobytes())
    return value


def types_in(value) -> set[str]:
    """Every plugin "type" in a nested scene dict."""
    if not isinstance(value, dict):
        return set()
    found = {value["type"]} if isinstance(value.get("type"), str) else set()
    return found.union(*(types_in(v) for v in value.values()))


def test_same_seed_same_scene():
    assert canonical(generate_scene(7, size=16)) == canonical(generate_scene(7, size=16))
    assert sample_spec(7) == sample_spec(7)


def test_different_seeds_differ():
    dicts = [canonical(generate_scene(s, size=16)) for s in range(5)]
    assert all(dicts[i] != dicts[j] for i in range(5) for j in range(i))


def test_scenes_cover_the_promised_variety():
    found = set().union(*(types_in(generate_scene(s, size=16)) for s in SEEDS))
    shapes = {"sphere", "cube", "rectangle", "cylinder", "disk"}
    materials = {"diffuse", "bitmap", "roughplastic", "roughconductor", "conductor", "dielectric", "twosided"}
    lights = {"area", "point", "spot", "constant", "envmap"}
    cameras = {"perspective", "thinlens"}
    assert shapes | materials | lights | cameras <= found, sorted(shapes | materials | lights | cameras - found)
    specs = [sample_spec(s) for s in SEEDS]
    assert {s.layout for s in specs} == {"room", "ground"}
    assert any(light.kind == "firefly" for s in specs for light in s.lights)
    textures = {m.texture.kind for s in specs for m in [s.floor, s.walls, *(o.material for o in s.objects)] if m.texture}
    assert textures == set(TEXTURE_KINDS)


def test_frames_move_only_the_camera():
    a, b = canonical(generate_scene(3, size=16, frame=0)), canonical(generate_scene(3, size=16, frame=1))
    assert a["sensor"]["to_world"] != b["sensor"]["to_world"]
    assert {k: v for k, v in a.items() if k != "sensor"} == {k: v for k, v in b.items() if k != "sensor"}


def test_glass_only_on_closed_shapes():
    for s in SEEDS:
        for o in sample_spec(s).objects:
            assert o.material.kind != "dielectric" or o.shape in ("sphere", "cube")


@pytest.mark.parametrize("kind", TEXTURE_KINDS)
def test_textures_are_finite_rgb_between_their_two_colours(kind):
    spec = TextureSpec(kind, (0.1, 0.2, 0.3), (0.8, 0.7, 0.6), frequency=4, angle=0.3, seed=1)
    image = texture_image(spec, res=32)
    assert image.shape == (32, 32, 3) and image.dtype == np.float32
    assert np.all(image >= 0.1 - 1e-6) and np.all(image <= 0.8 + 1e-6)
    assert image.std() > 0.01  # a pattern, not a flat colour


@pytest.mark.parametrize("seed", [0, 1, 4, 6, 8])
def test_generated_scenes_load_and_render_finite(seed):
    mi = mitsuba()
    scene = mi.load_dict(generate_scene(seed, size=8, frame=1))
    image = np.asarray(mi.render(scene, spp=2))
    assert image.shape == (8, 8, 3) and np.isfinite(image).all()


def test_window_rooms_are_closed_and_lit_only_by_a_sun_shining_in_through_the_opening():
    mi = mitsuba()
    walls = set()
    for seed in range(12):
        spec = sample_spec(seed, "window")
        walls.add(spec.window.wall)
        assert [light.kind for light in spec.lights if light.kind != "firefly"] == ["sky"]
        sky = spec.lights[0].sky
        # the direction to the sun points out through the window wall and down into the room
        sun = np.array([np.cos(sky.sun_elevation) * np.sin(sky.sun_azimuth), np.sin(sky.sun_elevation),
                        -np.cos(sky.sun_elevation) * np.cos(sky.sun_azimuth)])
        outward = {"back": (0, 0, -1), "left": (-1, 0, 0), "right": (1, 0, 0)}[spec.window.wall]
        assert sun @ np.array(outward) > 0 and sun[1] > 0
        (low, high), (w, h, d) = spec.camera.bounds, spec.room
        assert high[2] < d / 2 and low[0] > -w / 2 and high[0] < w / 2   # the camera stays inside
        (u, v), (hw, hh) = spec.window.centre, spec.window.half
        span = w if spec.window.wall == "back" else d
        assert -span / 2 < u - hw and u + hw < span / 2 and 0 < v - hh and v + hh < h
        shapes = generate_scene(seed, size=8, layout="window")
        assert "wall_front" in shapes and f"wall_{spec.window.wall}" not in shapes
        assert any(k.startswith(f"wall_{spec.window.wall}_") for k in shapes)
    assert walls == set(WINDOW_WALLS)
    image = np.asarray(mi.render(mi.load_dict(generate_scene(12, size=32, layout="window")), spp=64))
    assert np.isfinite(image).all() and image.mean() > 0.01   # light gets in


def test_shaded_rooms_are_closed_and_lit_only_by_a_tiny_bulb_inside_its_shade():
    mi = mitsuba()
    for seed in range(12):
        spec = sample_spec(seed, "shaded")
        shade, (w, h, d) = spec.shade, spec.room
        assert [light.kind for light in spec.lights] in ([], ["firefly"])
        x, y, z = shade.centre
        assert abs(x) < w / 2 and abs(z) < d / 2 and 0 < y - shade.shade_half_height and y + shade.shade_half_height < h
        assert shade.bulb_radius < shade.shade_radius / 4       # a bulb well inside its shade
        (low, high) = spec.camera.bounds
        assert high[2] < d / 2 and low[0] > -w / 2 and high[0] < w / 2   # the camera stays inside
        shapes = generate_scene(seed, size=8, layout="shaded")
        assert "wall_front" in shapes
        bulb = next(v for k, v in shapes.items() if k.endswith("_bulb"))
        cylinder = next(v for k, v in shapes.items() if k.endswith("_shade"))
        assert "emitter" in bulb and cylinder["type"] == "cylinder" and "emitter" not in cylinder
    # lit, finite, and with fireflies: a few pixels carry far more than the typical pixel
    image = np.asarray(mi.render(mi.load_dict(generate_scene(3, size=32, layout="shaded")), spp=16))
    luminance = image.mean(-1)
    assert np.isfinite(image).all() and image.mean() > 0.01
    assert luminance.max() > 20 * np.median(luminance)

def test_asking_for_a_layout_keeps_the_rest_of_the_seeds_scene_and_the_default_mix_unchanged():
    for seed in range(6):
        own = sample_spec(seed)
        assert sample_spec(seed, own.layout) == own
        for layout in ("window", "shaded"):
            closed = sample_spec(seed, layout)
            assert (closed.room, closed.floor, closed.walls) == (own.room, own.floor, own.walls)
    with pytest.raises(ValueError, match="unknown layout"):
        sample_spec(0, "attic")
