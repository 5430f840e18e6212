"""The flattener: Mitsuba's own rules for <default>, $ and <include>, and the path wall.

Where a rule is Mitsuba's, the test also parses the original files with Mitsuba's parser and
checks it reaches the same value, so the rule is pinned against Mitsuba, not against our reading.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from service.render.flatten import MAX_INCLUDE_DEPTH, FlattenError, flatten_scene, parse_param_pairs
from service.render.runtime import mitsuba


def scene(body: str) -> str:
    return f'<scene version="3.0.0">\n{body}\n</scene>\n'


def bitmap(value: str, name: str = "filename") -> str:
    return f'<texture type="bitmap"><string name="{name}" value="{value}"/></texture>'


@pytest.fixture
def bundle(tmp_path):
    """`bundle({"scene.xml": text, "red.png": ""})` → the bundle root with those files."""

    def make(files: dict[str, str]) -> Path:
        root = tmp_path / "bundle"
        for name, text in files.items():
            path = root / name
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
        return root

    return make


def flat(root: Path, entry: str = "scene.xml", **params):
    return flatten_scene(root / entry, root=root, params=params or None)


def refused(root: Path, entry: str = "scene.xml", **params) -> str:
    with pytest.raises(FlattenError) as err:
        flat(root, entry, **params)
    message = str(err.value)
    assert str(root) not in message and str(root.parent) not in message  # no server paths
    return message


def flat_strings(flat_scene, name: str = "filename") -> list[str]:
    """The values Mitsuba itself reads for `<string name=...>` from the flattened document."""
    mi = mitsuba()
    state = mi.parser.parse_string(mi.parser.ParserConfig(mi.variant()), flat_scene.document)
    return [node.props[name] for node in state.nodes if name in node.props]


def mitsuba_strings(path: Path, name: str = "filename", **params) -> list[str]:
    """The same values from Mitsuba's own parse of the original files."""
    mi = mitsuba()
    state = mi.parser.parse_file(mi.parser.ParserConfig(mi.variant()), str(path), **params)
    return [node.props[name] for node in state.nodes if name in node.props]


def test_first_default_wins_like_mitsuba(bundle):
    root = bundle({"scene.xml": scene('<default name="p" value="a.png"/><default name="p" value="b.png"/>' + bitmap("$p")),
                   "a.png": "", "b.png": ""})
    assert flat_strings(flat(root)) == [str(root / "a.png")]
    assert mitsuba_strings(root / "scene.xml") == ["a.png"]


def test_caller_parameter_overrides_the_default(bundle):
    root = bundle({"scene.xml": scene('<default name="p" value="a.png"/>' + bitmap("$p")), "a.png": "", "b.png": ""})
    assert flat_strings(flat(root, p="b.png")) == [str(root / "b.png")]
    assert mitsuba_strings(root / "scene.xml", p="b.png") == ["b.png"]


def test_longest_parameter_name_is_substituted_first(bundle):
    body = '<default name="a" value="X"/><default name="ab" value="Y"/><string name="s" value="$ab-$a"/>'
    root = bundle({"scene.xml": scene(body)})
    assert flat_strings(flat(root), "s") == mitsuba_strings(root / "scene.xml", "s") == ["Y-X"]


def test_escaped_dollar_reaches_mitsuba_as_a_literal(bundle):
    root = bundle({"scene.xml": scene('<default name="a" value="X"/><string name="s" value="\\$a $a"/>')})
    assert flat_strings(flat(root), "s") == mitsuba_strings(root / "scene.xml", "s") == ["$a X"]


def test_dollar_in_a_property_name_makes_it_a_checked_filename(bundle):
    body = '<default name="n" value="filename"/><texture type="bitmap"><string name="$n" value="/etc/passwd"/></texture>'
    root = bundle({"scene.xml": scene(body)})
    message = refused(root)
    assert "'/etc/passwd'" in message and "absolute paths are not allowed" in message
    assert "root:" not in message


def test_dollar_in_a_ply_property_name_is_refused(bundle):
    body = '<default name="n" value="filename"/><shape type="ply"><string name="$n" value="/etc/passwd"/></shape>'
    assert "'/etc/passwd'" in refused(bundle({"scene.xml": scene(body)}))


def test_duplicate_defaults_first_absolute_is_refused(bundle):
    body = '<default name="p" value="/abs/red.png"/><default name="p" value="g.png"/>' + bitmap("$p")
    assert "'/abs/red.png'" in refused(bundle({"scene.xml": scene(body), "g.png": ""}))


def test_parents_default_reaches_into_the_include(bundle):
    child = scene('<default name="p" value="g.png"/>' + bitmap("$p"))
    root = bundle({"scene.xml": scene('<default name="p" value="red.png"/><include filename="sub/child.xml"/>'),
                   "sub/child.xml": child, "red.png": "", "g.png": ""})
    assert flat_strings(flat(root)) == [str(root / "red.png")]
    assert mitsuba_strings(root / "scene.xml") == ["red.png"]


def test_parents_absolute_default_inside_the_include_is_refused(bundle):
    child = scene('<default name="p" value="g.png"/>' + bitmap("$p"))
    root = bundle({"scene.xml": scene('<default name="p" value="/abs/red.png"/><include filename="sub/child.xml"/>'),
                   "sub/child.xml": child, "sub/g.png": "", "g.png": ""})
    assert "sub/child.xml" in (message := refused(root)) and "'/abs/red.png'" in message


def test_includes_defaults_stay_for_what_follows(bundle):
    root = bundle({"scene.xml": scene('<include filename="d.xml"/>' + bitmap("$p")),
                   "d.xml": scene('<default name="p" value="a.png"/>'), "a.png": ""})
    assert flat_strings(flat(root)) == [str(root / "a.png")]


def test_relative_paths_in_an_include_resolve_against_the_scene_folder_not_the_decoy(bundle):
    child = scene(bitmap("outside/red.png"))
    root = bundle({"scene.xml": scene('<include filename="sub/child.xml"/>'), "sub/child.xml": child,
                   "sub/outside/red.png": ""})
    assert "'outside/red.png' is not in the bundle" in refused(root)


def test_sub_folder_texture_named_from_the_root_is_found(bundle):
    root = bundle({"scene.xml": scene('<include filename="sub/child.xml"/>'),
                   "sub/child.xml": scene(bitmap("sub/tex.png")), "sub/tex.png": ""})
    assert flat_strings(flat(root)) == [str(root / "sub" / "tex.png")]


def test_nested_include_resolves_against_the_including_files_folder_first(bundle):
    # Mitsuba prepends the including file's folder to the resolver for <include>.
    root = bundle({"scene.xml": scene('<include filename="sub/child.xml"/>'),
                   "sub/child.xml": scene('<include filename="grand.xml"/>'),
                   "sub/grand.xml": scene('<string name="s" value="in sub"/>'),
                   "grand.xml": scene('<string name="s" value="at root"/>')})
    document = flat(root).document
    assert "in sub" not in document and "at root" not in document  # plain props of included scenes drop
    assert sorted(str(p.relative_to(root)) for p in flat(root).files)[:2] == ["scene.xml", "sub/child.xml"]
    assert root / "sub" / "grand.xml" in flat(root).files


def test_non_scene_include_becomes_a_named_object(bundle):
    root = bundle({"scene.xml": scene('<shape type="sphere"><include filename="m.xml" name="bsdf"/></shape>'),
                   "m.xml": '<bsdf version="3.0.0" type="diffuse" name="ignored"/>'})
    document = flat(root).document
    assert '<bsdf type="diffuse" name="bsdf"/>' in document and "version" not in document.split("\n", 1)[1]


@pytest.mark.parametrize("reference", ["../secret.png", "sub/../../secret.png", "~/x.png", "/etc/hosts", "C:/x.png"])
def test_references_escaping_the_root_are_refused(bundle, reference):
    root = bundle({"scene.xml": scene(bitmap(reference)), "sub/x.png": ""})
    (root.parent / "secret.png").write_text("")
    assert repr(reference) in refused(root)


def test_dot_dot_that_stays_inside_is_accepted(bundle):
    root = bundle({"scene.xml": scene(bitmap("sub/../red.png")), "red.png": "", "sub/x": ""})
    assert flat_strings(flat(root)) == [str(root / "red.png")]


def test_symlink_out_of_the_root_is_refused_and_one_inside_is_followed(bundle, tmp_path):
    root = bundle({"scene.xml": scene(bitmap("out.png") + bitmap("in.png")), "real.png": ""})
    (tmp_path / "outside.png").write_text("secret")
    os.symlink(tmp_path / "outside.png", root / "out.png")
    os.symlink(root / "real.png", root / "in.png")
    assert "'out.png' points outside the bundle" in refused(root)
    (root / "out.png").unlink()
    os.symlink(root / "real.png", root / "out.png")
    assert flat_strings(flat(root)) == [str(root / "real.png")] * 2


def test_missing_file_is_named(bundle):
    assert "'nope.png' is not in the bundle" in refused(bundle({"scene.xml": scene(bitmap("nope.png"))}))


def test_include_cycle_is_refused(bundle):
    root = bundle({"scene.xml": scene('<include filename="a.xml"/>'), "a.xml": scene('<include filename="b.xml"/>'),
                   "b.xml": scene('<include filename="a.xml"/>')})
    assert "include cycle scene.xml -> a.xml -> b.xml -> a.xml" in refused(root)


def test_include_depth_is_bounded(bundle):
    files = {"scene.xml": scene('<include filename="f0.xml"/>')}
    for level in range(MAX_INCLUDE_DEPTH + 1):
        files[f"f{level}.xml"] = scene(f'<include filename="f{level + 1}.xml"/>')
    assert f"deeper than {MAX_INCLUDE_DEPTH}" in refused(bundle(files))


def test_unknown_parameter_lists_the_scenes_defaults(bundle):
    root = bundle({"scene.xml": scene('<default name="spp" value="4"/><default name="integrator" value="path"/>')})
    assert refused(root, colour="red") == "unknown scene parameter colour; the scene's <default> parameters: spp, integrator"


def test_parameter_used_without_a_default_is_known(bundle):
    root = bundle({"scene.xml": scene('<string name="s" value="$mode"/>')})
    assert flat_strings(flat(root, mode="rgb"), "s") == ["rgb"]
    assert "undefined parameter $mode" in refused(root)


def test_parameter_values_obey_the_path_rules(bundle):
    root = bundle({"scene.xml": scene('<default name="tex" value="a.png"/>' + bitmap("$tex")), "a.png": ""})
    assert "'/etc/passwd'" in refused(root, tex="/etc/passwd")
    assert "'../x.png'" in refused(root, tex="../x.png")


def test_optional_parameters_apply_only_where_used(bundle):
    root = bundle({"scene.xml": scene('<default name="frame" value="0"/><integer name="i" value="$frame"/>')})
    assert '<integer name="i" value="3"/>' in flatten_scene(root / "scene.xml", root=root, optional_params={"frame": "3", "width": "8"}).document


def test_plain_strings_pass_and_file_like_strings_are_checked(bundle):
    root = bundle({"scene.xml": scene('<string name="mode" value="rgb"/><string name="lut" value="data/lut.cube"/>'),
                   "data/lut.cube": ""})
    assert flat_strings(flat(root), "mode") == ["rgb"]
    assert flat_strings(flat(root), "lut") == [str(root / "data" / "lut.cube")]
    root = bundle({"scene.xml": scene('<string name="anything" value="/etc/passwd"/>')})
    assert "'/etc/passwd'" in refused(root)


def test_plugin_type_must_be_a_plain_name(bundle):
    root = bundle({"scene.xml": scene('<shape type="../../tmp/evil"/>')})
    assert "plugin type '../../tmp/evil'" in refused(root)


def test_path_element_is_refused(bundle):
    assert "<path> is not supported" in refused(bundle({"scene.xml": scene('<path value="/"/>')}))


def test_errors_point_at_the_file_and_line(bundle):
    root = bundle({"scene.xml": scene('<include filename="sub/c.xml"/>'), "sub/c.xml": scene("\n" + bitmap("/x"))})
    assert refused(root).startswith("sub/c.xml:3: '/x'")
    flat_scene = flat(bundle({"scene.xml": scene('\n\n<shape type="sphere"/>')}))
    assert flat_scene.locate(2) == "scene.xml:4"


def test_dtd_and_entities_are_refused(bundle):
    bomb = '<?xml version="1.0"?><!DOCTYPE s [<!ENTITY a "aa">]><scene version="3.0.0"/>'
    assert "DTDs are not allowed" in refused(bundle({"scene.xml": bomb}))


def test_flattened_document_needs_no_parameters(bundle):
    root = bundle({"scene.xml": scene('<default name="r" value="2"/><shape type="sphere"><float name="radius" value="$r"/></shape>')})
    assert "$" not in flat(root).document
    assert flat_strings(flat(root, r="3"), "radius") == [3.0]


def test_param_pairs_parse_like_dash_d():
    assert parse_param_pairs(["a=1", "b=x=y", "a=2"]) == {"a": "2", "b": "x=y"}
    with pytest.raises(FlattenError, match="NAME=VALUE"):
        parse_param_pairs(["novalue"])


# -- the loader (service/render/scenes.py) goes through the flattener ------------------------------

SENSOR = """<sensor type="perspective"><transform name="to_world"><lookat origin="0,0,5" target="0,0,0" up="0,1,0"/></transform>
  <film type="hdrfilm"><integer name="width" value="$res"/><integer name="height" value="4"/></film></sensor>"""


def test_loader_takes_parameters_and_finds_sub_folder_textures(bundle):
    from service.render.scenes import load_scene

    child = scene('<shape type="sphere"><bsdf type="diffuse">' + bitmap("sub/tex.png").replace("<texture", '<texture name="reflectance"') + "</bsdf></shape>")
    root = bundle({"scene.xml": scene('<default name="res" value="4"/>' + SENSOR + '<include filename="sub/child.xml"/>'),
                   "sub/child.xml": child})
    mi = mitsuba()
    mi.Bitmap(np.full((2, 2, 3), 0.5, dtype=np.float32)).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, True).write(str(root / "sub" / "tex.png"))
    assert list(load_scene(root / "scene.xml", params={"res": "6"}).sensors()[0].film().size()) == [6, 4]


def test_loader_refuses_unknown_parameters_and_frame(bundle):
    from service.render.scenes import SceneError, load_scene

    root = bundle({"scene.xml": scene('<default name="res" value="4"/>' + SENSOR)})
    with pytest.raises(SceneError, match="unknown scene parameter nope; the scene's <default> parameters: res"):
        load_scene(root / "scene.xml", params={"nope": "1"})
    with pytest.raises(SceneError, match="'frame' is set by the renderer"):
        load_scene(root / "scene.xml", params={"frame": "1"})


def test_loader_errors_point_into_the_users_file_without_server_paths(bundle):
    from service.render.scenes import SceneError, load_scene

    root = bundle({"scene.xml": scene('<default name="res" value="4"/>' + SENSOR + '\n<include filename="sub/c.xml"/>'),
                   "sub/c.xml": scene('\n\n<shape type="sphere"><float name="radius" value="abc"/></shape>')})
    with pytest.raises(SceneError) as err:
        load_scene(root / "scene.xml")
    assert "sub/c.xml:4" in str(err.value) and str(root) not in str(err.value)


def test_loader_never_loads_plugins_from_the_bundle(bundle):
    from service.render.scenes import SceneError, load_scene

    root = bundle({"scene.xml": scene('<default name="res" value="4"/>' + SENSOR + '<shape type="evilplug"/>'),
                   "plugins/evilplug.so": "not a library"})
    with pytest.raises(SceneError) as err:
        load_scene(root / "scene.xml")
    assert 'Plugin "evilplug" not found' in str(err.value)  # never dlopen()ed from the bundle
