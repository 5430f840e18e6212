"""LoopState.snapshot: the copy a background checkpoint writes must not see the next iteration."""
from __future__ import annotations

import numpy as np

from service.loop.state import COPIED_ARRAYS, LoopState


def state_with_splats(height: int = 6, width: int = 5) -> LoopState:
    state = LoopState.new(frames=2, height=height, width=width, lam=1.0)
    rng = np.random.default_rng(1)
    for buf in state.buffers:
        buf.radiance_sum[:] = rng.random(buf.radiance_sum.shape)
        buf.spp[:] = 4
        buf.add_splat(rng.random((height, width, 11)))
    state.error_maps = [rng.random((height, width)).astype(np.float32), None]
    state.iteration, state.elapsed = 2, 3.5
    return state


def assert_same(snapshot: LoopState, state: LoopState) -> None:
    assert (snapshot.iteration, snapshot.elapsed) == (state.iteration, state.elapsed)
    np.testing.assert_array_equal(snapshot.lam_map, state.lam_map)
    for copy, error in zip(snapshot.error_maps, state.error_maps, strict=True):
        assert (copy is None) == (error is None)
        if error is not None:
            np.testing.assert_array_equal(copy, error)
    for copy, buf in zip(snapshot.buffers, state.buffers):
        for name in COPIED_ARRAYS:
            if getattr(buf, name) is None:
                assert getattr(copy, name) is None
            else:
                np.testing.assert_array_equal(getattr(copy, name), getattr(buf, name))


def test_a_snapshot_does_not_change_when_the_next_iteration_adds_to_the_state():
    state = state_with_splats()
    snapshot = state.snapshot()
    expected = state.snapshot()
    for buf in state.buffers:  # what the next render and a λ edit do: add in place, replace the map
        buf.radiance_sum += 1.0
        buf.spp += 4
        buf.add_splat(np.ones(buf.shape + (11,)))
    state.lam_map[:] = 5.0
    state.error_maps[0][:] = 0.0
    assert_same(snapshot, expected)


def test_a_snapshot_into_an_earlier_ones_arrays_reuses_them_and_equals_a_fresh_copy():
    state = state_with_splats()
    spare = state.snapshot()
    for buf in state.buffers:
        buf.radiance_sum *= 2.0
        buf.spp += 8
    state.iteration += 1
    again = state.snapshot(reuse=spare)
    assert again.buffers[0].radiance_sum is spare.buffers[0].radiance_sum  # no new allocation
    assert again.buffers[0].radiance_sum is not state.buffers[0].radiance_sum
    assert_same(again, state)
    assert again.lam_map is not spare.lam_map  # the λ map may live on in a published preview


def test_a_snapshot_of_another_size_ignores_the_spare():
    spare = state_with_splats(4, 4).snapshot()
    state = state_with_splats()
    assert_same(state.snapshot(reuse=spare), state)
