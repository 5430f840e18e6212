"""The checkpoint's files (service/jobs/checkpoint_format.py), pinned by name: a checkpoint a
running server wrote before an upgrade must still resume after it, so the names, keys and
version on disk are read here without the module's own constants."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from service.jobs.checkpoint_format import holds_state, read_state, write_state
from service.loop.state import LoopState

HEIGHT, WIDTH = 6, 5
SIX_SUMS = ("radiance_sum", "radiance_sq_sum", "spp", "albedo_sum", "normal_sum", "depth_sum")
SPLATS = ("splat_weight", "splat_radiance", "splat_sq_radiance", "splat_sq_radiance_sq", "splat_weight_sq")


def two_frame_state() -> LoopState:
    """Frame 0: motion, splat sums and an error map; frame 1: the integrator's AOVs, no error."""
    rng = np.random.default_rng(7)
    state = LoopState.new(frames=2, height=HEIGHT, width=WIDTH, lam=2.0)
    for buf in state.buffers:
        buf.radiance_sum[:] = rng.random(buf.radiance_sum.shape)
        buf.spp[:] = rng.integers(1, 9, buf.spp.shape)
        buf.passes = 3
    state.buffers[0].motion_sum = rng.random((HEIGHT, WIDTH, 2))
    state.buffers[0].add_splat(rng.random((HEIGHT, WIDTH, 11)))
    state.buffers[1].aov_sum, state.buffers[1].aov_names = rng.random((HEIGHT, WIDTH, 2)), ("dd.y.T", "albedo.R")
    state.error_maps = [rng.random((HEIGHT, WIDTH)).astype(np.float32), None]
    state.iteration, state.elapsed = 4, 12.5
    return state


def test_a_written_checkpoint_is_the_version_1_files_by_name(tmp_path):
    state = two_frame_state()
    folder = write_state(state, tmp_path / "state")
    assert sorted(os.listdir(folder)) == ["frame_0.npz", "frame_1.npz", "lambda.npy", "state.json"]
    assert json.loads((folder / "state.json").read_text()) == {
        "version": 1, "iteration": 4, "elapsed": 12.5, "frames": 2, "passes": [3, 3],
        "aov_names": [[], ["dd.y.T", "albedo.R"]]}
    np.testing.assert_array_equal(np.load(folder / "lambda.npy"), np.full((HEIGHT, WIDTH), 2.0, np.float32))
    with np.load(folder / "frame_0.npz") as frame:
        assert set(frame.files) == set(SIX_SUMS) | set(SPLATS) | {"motion_sum", "error"}
        np.testing.assert_array_equal(frame["splat_radiance"], state.buffers[0].splat_radiance)
        np.testing.assert_array_equal(frame["error"], state.error_maps[0])
    with np.load(folder / "frame_1.npz") as frame:
        assert set(frame.files) == set(SIX_SUMS) | {"aov_sum"}
        np.testing.assert_array_equal(frame["spp"], state.buffers[1].spp)


def test_version_1_files_written_by_hand_resume_as_the_state_they_hold(tmp_path):
    """The files as the pre-move writer (LoopState.save) laid them out, written without it."""
    rng = np.random.default_rng(3)
    folder = tmp_path / "state"
    folder.mkdir()
    sums = {name: rng.random((HEIGHT, WIDTH, 3)) for name in SIX_SUMS}
    sums["spp"], sums["depth_sum"] = np.full((HEIGHT, WIDTH), 16, np.int64), rng.random((HEIGHT, WIDTH))
    error = rng.random((HEIGHT, WIDTH)).astype(np.float32)
    np.savez(folder / "frame_0.npz", **sums, error=error, motion_sum=rng.random((HEIGHT, WIDTH, 2)))
    np.save(folder / "lambda.npy", np.full((HEIGHT, WIDTH), 3.0, np.float32))
    (folder / "state.json").write_text(json.dumps(
        {"version": 1, "iteration": 2, "elapsed": 7.25, "frames": 1, "passes": [2], "aov_names": [[]]}))
    assert holds_state(folder)
    state = read_state(folder)
    assert (state.iteration, state.elapsed, state.spp_mean) == (2, 7.25, 16.0)
    np.testing.assert_array_equal(state.buffers[0].radiance_sum, sums["radiance_sum"])
    np.testing.assert_array_equal(state.error_maps[0], error)
    assert state.buffers[0].splat_weight is None and state.buffers[0].aov_sum is None
    assert state.buffers[0].passes == 2 and state.lam_map[0, 0] == 3.0


def test_a_checkpoint_reads_back_as_the_state_that_was_written(tmp_path):
    state = two_frame_state()
    back = read_state(write_state(state, tmp_path / "state"))
    assert (back.iteration, back.elapsed) == (state.iteration, state.elapsed)
    np.testing.assert_array_equal(back.lam_map, state.lam_map)
    np.testing.assert_array_equal(back.error_maps[0], state.error_maps[0])
    assert back.error_maps[1] is None
    for read, written in zip(back.buffers, state.buffers, strict=True):
        assert (read.passes, read.aov_names) == (written.passes, written.aov_names)
        np.testing.assert_array_equal(read.raw, written.raw)  # the splat sums, where there are any
        np.testing.assert_array_equal(read.mean, written.mean)
    np.testing.assert_array_equal(back.buffers[0].motion_sum, state.buffers[0].motion_sum)
    np.testing.assert_array_equal(back.buffers[1].aov_sum, state.buffers[1].aov_sum)


def test_a_kill_between_the_two_renames_leaves_the_previous_checkpoint_readable(tmp_path):
    write_state(two_frame_state(), tmp_path / "state")
    os.replace(tmp_path / "state", tmp_path / "state.old")  # write_state's first rename, then the kill
    assert holds_state(tmp_path / "state")
    assert read_state(tmp_path / "state").iteration == 4


def test_an_unknown_version_is_refused_with_its_number(tmp_path):
    folder = write_state(two_frame_state(), tmp_path / "state")
    meta = json.loads((folder / "state.json").read_text())
    (folder / "state.json").write_text(json.dumps({**meta, "version": 2}))
    with pytest.raises(ValueError, match="version 2, expected 1"):
        read_state(folder)
