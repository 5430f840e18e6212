import numpy as np
import pytest

from service.dataset.procedural import generate_scene, sample_spec
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
