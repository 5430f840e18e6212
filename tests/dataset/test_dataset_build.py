import json
from pathlib import Path

import numpy as np
import pytest

from service.dataset.build import ITEMS, MANIFEST, DatasetError, build_dataset, item_path, read_manifest
from service.dataset.procedural import sample_spec
from service.dataset.splits import scene_seeds
from service.exr import read_exr

UNIFORM = {"spp16": 16, "spp32": 32, "spp64": 64, "spp128": 128}


def frames_of(root: Path, split: str) -> list[tuple[int, int]]:
    entry = read_manifest(root)["splits"][split]
    return [(e["scene"], e["frame"]) for e in entry["entries"]]


def test_every_item_has_the_right_sample_counts_and_layers(sequence_dataset, tiny):
    for scene, frame in frames_of(sequence_dataset, "train"):
        for item, spp in UNIFORM.items():
            exr = read_exr(item_path(sequence_dataset, "train", scene, frame, item))
            assert exr.spp.shape == (16, 16) and np.all(exr.spp == spp)
            assert np.array_equal(exr.color, exr.noisy)
            for layer in (exr.noisy, exr.variance, exr.albedo, exr.normal, exr.depth, exr.motion):
                assert layer is not None and np.isfinite(layer).all()
            assert exr.motion.shape == (16, 16, 2)
            assert exr.header["scene"] == f"procedural-{scene}"
        for item, mean_spp in (("adaptive32", 32), ("adaptive64", 64)):
            spp = read_exr(item_path(sequence_dataset, "train", scene, frame, item)).spp
            assert spp.sum() == mean_spp * spp.size  # the doubling budget, spent exactly
            assert spp.min() >= 16
        reference = read_exr(item_path(sequence_dataset, "train", scene, frame, "reference"))
        assert np.all(reference.spp == tiny["reference_spp"]) and np.isfinite(reference.color).all()


def test_single_frame_scenes_have_no_motion(still_dataset):
    for scene, frame in frames_of(still_dataset, "heldout"):
        assert read_exr(item_path(still_dataset, "heldout", scene, frame, "spp16")).motion is None


def test_manifest_lists_items_seeds_settings_and_the_command(sequence_dataset):
    manifest = json.loads((sequence_dataset / "manifest.json").read_text())
    assert manifest["items"] == list(ITEMS)
    entry = manifest["splits"]["train"]
    assert entry["scene_seeds"] == scene_seeds("train", 2, 0)
    assert (entry["size"], entry["frames"], entry["reference_spp"], entry["complete"]) == (16, 3, 64, True)
    assert entry["command"].startswith("renderloop dataset -o ") and "--frames 3" in entry["command"]
    assert len(entry["entries"]) == 6
    for e in entry["entries"]:
        assert all((sequence_dataset / path).is_file() for path in e["items"].values())


def test_rerun_skips_finished_items_and_redoes_broken_ones(still_dataset, tiny):
    files = sorted(still_dataset.glob("heldout/**/*.exr"))
    mtimes = {f: f.stat().st_mtime_ns for f in files}
    build_dataset(still_dataset, scenes=2, frames=1, split="heldout", **tiny)
    assert {f: f.stat().st_mtime_ns for f in files} == mtimes

    scene, frame = frames_of(still_dataset, "heldout")[0]
    removed = item_path(still_dataset, "heldout", scene, frame, "spp64")
    torn = item_path(still_dataset, "heldout", scene, frame, "reference")
    removed.unlink()
    torn.write_bytes(torn.read_bytes()[:100])  # what an interrupted non-atomic write would leave
    build_dataset(still_dataset, scenes=2, frames=1, split="heldout", **tiny)
    assert removed.is_file() and np.all(read_exr(removed).spp == 64)
    assert np.all(read_exr(torn).spp == 64)
    unchanged = [f for f in files if f not in (removed, torn)]
    assert all(f.stat().st_mtime_ns == mtimes[f] for f in unchanged)
    assert not list(still_dataset.glob("**/.*partial*"))


def test_resuming_with_other_settings_is_refused(still_dataset, tiny):
    with pytest.raises(DatasetError, match="size=16"):
        build_dataset(still_dataset, scenes=2, frames=1, split="heldout", **{**tiny, "size": 32})


@pytest.mark.parametrize("change, message", [
    ({"scenes": 0}, "--scenes"), ({"size": 4}, "--size"), ({"frames": 0}, "--frames"),
    ({"split": "test"}, "--split"), ({"reference_spp": 0}, "--reference-spp"), ({"seed": -1}, "--seed"),
])
def test_bad_settings_raise_before_rendering(tmp_path, tiny, change, message):
    settings = {"scenes": 1, "frames": 1, "split": "train", **tiny, **change}
    with pytest.raises(DatasetError, match=message):
        build_dataset(tmp_path / "out", **settings)
    assert not (tmp_path / "out").exists()


def test_a_window_data_set_records_its_layout_and_refuses_to_resume_as_another(tmp_path, tiny):
    root = tmp_path / "windows"
    build_dataset(root, scenes=1, frames=1, split="train", layout="window", **tiny)
    entry = read_manifest(root)["splits"]["train"]
    assert entry["layout"] == "window" and "--layout window" in entry["command"]
    assert sample_spec(entry["scene_seeds"][0], "window").window is not None
    with pytest.raises(DatasetError, match="layout=window"):
        build_dataset(root, scenes=1, frames=1, split="train", **tiny)


def test_a_manifest_from_before_layouts_were_recorded_resumes_as_the_default_mix(still_dataset, tiny):
    manifest = read_manifest(still_dataset)
    del manifest["splits"]["heldout"]["layout"]
    (still_dataset / MANIFEST).write_text(json.dumps(manifest))
    build_dataset(still_dataset, scenes=2, frames=1, split="heldout", **tiny)   # no DatasetError
    with pytest.raises(DatasetError, match="layout=mixed"):
        build_dataset(still_dataset, scenes=2, frames=1, split="heldout", layout="window", **tiny)
