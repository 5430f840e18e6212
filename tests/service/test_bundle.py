"""Hostile scene bundles: every check names the path at fault."""
from __future__ import annotations

import io
import struct
import time

import pytest

from service_harness import zip_bytes
from service.jobs.bundle import BundleError, BundleLimits, extract_zip, prepare_bundle, save_files
from service.jobs.zip_directory import DirectorySize, read_directory_size

SCENE = """<scene version="3.0.0">
  <include filename="parts/lights.xml"/>
  <shape type="obj"><string name="filename" value="meshes/box.obj"/></shape>
  <texture type="bitmap" id="t"><string name="filename" value="textures/wood.png"/></texture>
</scene>"""
LIGHTS = '<scene version="3.0.0"><emitter type="constant"/></scene>'
BOMB = """<?xml version="1.0"?>
<!DOCTYPE scene [<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;&a;&a;&a;&a;&a;&a;&a;">]>
<scene version="3.0.0"><string name="x" value="&b;"/></scene>"""


def make_zip(members: dict[str, bytes | str], symlinks: dict[str, str] = {}) -> io.BytesIO:
    return io.BytesIO(zip_bytes(members, symlinks))


def good_members(**overrides: str) -> dict[str, str]:
    members = {
        "scene.xml": SCENE,
        "parts/lights.xml": LIGHTS,
        "meshes/box.obj": "v 0 0 0\n",
        "textures/wood.png": "png",
    }
    members.update(overrides)
    return members


def unpack(tmp_path, members, symlinks={}, scene=None):
    root = tmp_path / "bundle"
    extract_zip(make_zip(members, symlinks), root)
    return prepare_bundle(root, scene)


def test_good_bundle_passes(tmp_path):
    entry = unpack(tmp_path, good_members())
    assert entry.name == "scene.xml"


@pytest.mark.parametrize("name", ["/etc/passwd", "../evil.xml", "a/../../evil.xml", "C:/x.xml", "..\\evil.xml"])
def test_zip_member_names_rejected(tmp_path, name):
    with pytest.raises(BundleError) as err:
        extract_zip(make_zip({**good_members(), name: "x"}), tmp_path / "bundle")
    assert name in str(err.value)
    assert not (tmp_path / "bundle").exists() or not any((tmp_path / "bundle").iterdir())


def test_zip_symlink_entry_rejected(tmp_path):
    with pytest.raises(BundleError, match="textures/link.png: symbolic links"):
        extract_zip(make_zip(good_members(), {"textures/link.png": "/etc/passwd"}), tmp_path / "bundle")


@pytest.mark.parametrize(
    "reference",
    ["/etc/passwd", "../../secret.png", "textures/../../x.png", "~/x.png"],
)
def test_scene_references_outside_rejected(tmp_path, reference):
    scene = SCENE.replace("textures/wood.png", reference)
    with pytest.raises(BundleError) as err:
        unpack(tmp_path, good_members(**{"scene.xml": scene}))
    assert reference in str(err.value)


def test_include_outside_rejected(tmp_path):
    scene = SCENE.replace("parts/lights.xml", "../outside.xml")
    with pytest.raises(BundleError, match=r"\.\./outside\.xml"):
        unpack(tmp_path, good_members(**{"scene.xml": scene}))


def test_nested_include_checked(tmp_path):
    lights = '<scene version="3.0.0"><include filename="/etc/hosts"/></scene>'
    with pytest.raises(BundleError, match="/etc/hosts"):
        unpack(tmp_path, good_members(**{"parts/lights.xml": lights}))


def test_default_substitution_cannot_smuggle_paths(tmp_path):
    scene = SCENE.replace("textures/wood.png", "$tex").replace(
        '<scene version="3.0.0">', '<scene version="3.0.0"><default name="tex" value="/etc/passwd"/>'
    )
    with pytest.raises(BundleError, match="/etc/passwd"):
        unpack(tmp_path, good_members(**{"scene.xml": scene}))


def test_entity_bomb_rejected(tmp_path):
    with pytest.raises(BundleError, match="scene.xml: DTDs are not allowed"):
        unpack(tmp_path, {"scene.xml": BOMB})


def test_missing_reference_named(tmp_path):
    members = good_members()
    del members["meshes/box.obj"]
    with pytest.raises(BundleError, match="scene.xml:3: .meshes/box.obj. is not in the bundle"):
        unpack(tmp_path, members)


def test_symlink_on_disk_out_of_bundle_rejected(tmp_path):
    root = tmp_path / "bundle"
    extract_zip(make_zip(good_members()), root)
    (root / "textures" / "wood.png").unlink()
    (root / "textures" / "wood.png").symlink_to("/etc/passwd")
    with pytest.raises(BundleError, match="textures/wood.png"):
        prepare_bundle(root, None)


def test_caps_on_size_and_count(tmp_path):
    with pytest.raises(BundleError, match="more than 3 files"):
        extract_zip(make_zip(good_members(extra="x")), tmp_path / "a", BundleLimits(max_files=3))
    with pytest.raises(BundleError, match="exceeds"):
        extract_zip(make_zip({"big.bin": "x" * 5000}), tmp_path / "b", BundleLimits(max_bytes=4096))


def test_entry_must_be_named_when_ambiguous(tmp_path):
    with pytest.raises(BundleError, match="name the scene XML"):
        unpack(tmp_path, good_members(**{"other.xml": LIGHTS}))
    assert unpack(tmp_path / "x", good_members(**{"other.xml": LIGHTS}), scene="scene.xml").name == "scene.xml"


def test_loose_files_upload(tmp_path):
    root = tmp_path / "bundle"
    save_files(((name, io.BytesIO(data.encode())) for name, data in good_members().items()), root)
    assert prepare_bundle(root, "scene.xml").name == "scene.xml"
    with pytest.raises(BundleError, match=r"\.\./x.png: '\.\.'"):
        save_files([("../x.png", io.BytesIO(b"x"))], tmp_path / "other")


def test_default_limits_fit_real_scenes():
    from service.jobs.bundle import MAX_BUNDLE_BYTES, MAX_BUNDLE_FILES

    assert MAX_BUNDLE_FILES >= 4096 and MAX_BUNDLE_BYTES >= 1024**3
    assert BundleLimits() == BundleLimits(max_bytes=MAX_BUNDLE_BYTES, max_files=MAX_BUNDLE_FILES)


def test_zipped_folder_unpacks_without_its_top_folder(tmp_path):
    members = {f"myscene/{name}": data for name, data in good_members().items()}
    members["__MACOSX/myscene/._scene.xml"] = "junk"
    root = tmp_path / "bundle"
    written = extract_zip(make_zip(members), root)
    assert "scene.xml" in {p.as_posix() for p in written} and (root / "parts" / "lights.xml").is_file()
    assert prepare_bundle(root, None).name == "scene.xml"


def test_spec_names_a_scene_inside_a_sub_folder(tmp_path):
    scene = SCENE.replace("parts/lights.xml", "../parts/lights.xml").replace('"meshes/', '"../meshes/').replace('"textures/', '"../textures/')
    members = {f"cbox/{name}": data for name, data in good_members(**{"scenes/cbox.xml": scene}).items() if name != "scene.xml"}
    root = tmp_path / "bundle"
    extract_zip(make_zip(members), root)
    assert prepare_bundle(root, "scenes/cbox.xml") == root / "scenes" / "cbox.xml"


def test_file_and_folder_with_the_same_name_is_a_bundle_error(tmp_path):
    with pytest.raises(BundleError, match="a: is both a file and a folder"):
        extract_zip(make_zip({**good_members(), "a": "x", "a/b.txt": "y"}), tmp_path / "bundle")
    with pytest.raises(BundleError, match="a: is both a file and a folder"):
        save_files([("a/b.txt", io.BytesIO(b"y")), ("a", io.BytesIO(b"x"))], tmp_path / "loose")


@pytest.mark.parametrize("name", ["x" * 256 + ".png", "d/" + "é" * 128 + ".png", "/".join(["abc"] * 300)])
def test_over_long_member_names_are_bundle_errors(tmp_path, name):
    with pytest.raises(BundleError, match="longer than"):
        extract_zip(make_zip({**good_members(), name: "x"}), tmp_path / "bundle")
    with pytest.raises(BundleError, match="longer than"):
        prepare_bundle_with_scene(tmp_path, name)


def prepare_bundle_with_scene(tmp_path, scene):
    root = tmp_path / "named"
    extract_zip(make_zip(good_members()), root)
    return prepare_bundle(root, scene)


def test_scene_parameters_are_checked_at_upload(tmp_path):
    scene = SCENE.replace("textures/wood.png", "$tex").replace(
        '<scene version="3.0.0">', '<scene version="3.0.0"><default name="tex" value="textures/wood.png"/>'
    )
    root = tmp_path / "bundle"
    extract_zip(make_zip(good_members(**{"scene.xml": scene})), root)
    with pytest.raises(BundleError, match="'/etc/passwd'"):
        prepare_bundle(root, None, params={"tex": "/etc/passwd"})
    root = tmp_path / "again"
    extract_zip(make_zip(good_members(**{"scene.xml": scene})), root)
    with pytest.raises(BundleError, match="unknown scene parameter spp; the scene's <default> parameters: tex"):
        prepare_bundle(root, None, params={"spp": "4"})


def test_nesting_deep_across_includes_is_a_bundle_error(tmp_path):
    # Each file stays under the per-file cap; the chain of includes goes past it.
    level = '<shape type="sphere">' * 40 + "{inner}" + "</shape>" * 40
    members = {"scene.xml": '<scene version="3.0.0">' + level.format(inner='<include filename="a.xml"/>') + "</scene>",
               "a.xml": '<scene version="3.0.0">' + level.format(inner='<include filename="b.xml"/>') + "</scene>",
               "b.xml": '<scene version="3.0.0">' + level.format(inner="") + "</scene>"}
    with pytest.raises(BundleError, match="nested deeper than 100"):
        unpack(tmp_path, members, scene="scene.xml")


def zip_with_entries(count: int, name_bytes: int = 8) -> bytearray:
    return bytearray(zip_bytes({f"{i:0{name_bytes}d}.txt": "" for i in range(count)}))


def test_entry_cap_applies_before_the_zip_directory_is_parsed(tmp_path):
    archive = zip_with_entries(20)
    # Spoil every central-directory entry: parsing the directory would fail ("bad magic number"),
    # so only a check of the end record's count can name the cap.
    archive[:] = archive.replace(b"PK\x01\x02", b"XX\x01\x02")
    with pytest.raises(BundleError, match="bundle: 20 entries, above the cap of 4 files"):
        extract_zip(io.BytesIO(bytes(archive)), tmp_path / "bundle", BundleLimits(max_files=4))


def test_a_zip_directory_larger_than_the_cap_needs_is_refused_even_when_its_count_lies(tmp_path):
    archive = zip_with_entries(40, name_bytes=900)
    end = archive.rfind(b"PK\x05\x06")
    archive[end + 8:end + 12] = struct.pack("<2H", 1, 1)  # "one entry", over a 40-entry directory
    with pytest.raises(BundleError, match="a zip directory of .* bytes, more than 4 files need"):
        extract_zip(io.BytesIO(bytes(archive)), tmp_path / "bundle", BundleLimits(max_files=4))


def test_zip64_end_record_counts_are_read():
    directory = struct.pack("<4sQ2H2L4Q", b"PK\x06\x06", 44, 45, 45, 0, 0, 70_000, 70_000, 5_000_000, 0)
    locator = struct.pack("<4sLQL", b"PK\x06\x07", 0, 0, 1)
    end = struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, 0xFFFF, 0xFFFF, 0xFFFFFFFF, 0xFFFFFFFF, 0)
    stream = io.BytesIO(directory + locator + end)
    assert read_directory_size(stream) == DirectorySize(entries=70_000, size=5_000_000)
    assert stream.tell() == 0


def test_layout_check_of_4096_loose_files_is_linear(tmp_path):
    names = [f"d{i % 64}/f{i}.txt" for i in range(4096)]
    started = time.monotonic()
    save_files(((name, io.BytesIO(b"x")) for name in names), tmp_path / "loose")
    assert time.monotonic() - started < 15  # quadratic: ~35 s on a 2-core machine
