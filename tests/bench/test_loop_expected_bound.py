"""(x), the allocation by the expected true error (bench/loop_expected_bound.py): replicas in
lockstep, each handed the mean of the others' true error maps, on real loops of a real scene."""
from __future__ import annotations

import statistics
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench.common import load_bench_networks
from bench.loop_expected_bound import (REPLICA_SEED_STRIDE, OwnTrueError, leave_one_out_means, lockstep_iteration,
                                       run_expected_bound)
from bench.loop_run import QUICK, BenchScene, Headline, LoopMethod, loop_spec
from bench.loop_seeds import bound_line, seed_table
from models.pretrained import Networks
from service.loop.loop import RenderLoop, converged_error

SCENE = BenchScene("cornell-box", "cornell-box", "built-in")
EXPECTED = LoopMethod("x", "expected-error bound", "error", "kpcn", False, replicas=2)
SETTINGS = replace(QUICK, size=16, iterations=2)


def _reference() -> np.ndarray:
    """A stand-in reference: the bound reads only how far each denoised image is from it."""
    return np.full((16, 16, 3), 0.3, dtype=np.float32)


def test_each_replica_gets_the_mean_of_the_other_replicas_maps() -> None:
    maps = [np.full((2, 3), v, dtype=np.float32) for v in (1.0, 2.0, 6.0)]
    means = leave_one_out_means(maps)
    np.testing.assert_allclose([m[0, 0] for m in means], [4.0, 3.5, 1.5])
    assert all(m.dtype == np.float32 and m.shape == (2, 3) for m in means)


def test_a_lockstep_iteration_hands_each_replica_the_others_true_error(tiny_weights_dir: Path) -> None:
    nets = load_bench_networks(tiny_weights_dir)
    stand_ins = [OwnTrueError(_reference()) for _ in range(2)]
    loops = [RenderLoop(loop_spec(SCENE, EXPECTED, replace(SETTINGS, seed=seed), 2),
                        Networks(nets.networks.denoiser, s))
             for seed, s in zip((0, REPLICA_SEED_STRIDE), stand_ins)]
    records = lockstep_iteration(loops, stand_ins)
    assert [r.iteration for r in records] == [0, 0] and all(loop.state.iteration == 1 for loop in loops)
    own = [s.last.copy() for s in stand_ins]
    assert not np.array_equal(own[0], own[1])  # two seeds, two noise patterns
    for loop, other in zip(loops, reversed(own)):
        _, error, converged = loop.owned_outputs()[0]
        np.testing.assert_array_equal(error, converged_error(converged, other))
    # the next iteration allocates by those maps: more samples where the other replica erred more
    lockstep_iteration(loops, stand_ins)
    spp = loops[0].state.buffers[0].spp.astype(float) - 16
    high, low = own[1] > np.median(own[1]), own[1] <= np.median(own[1])
    assert spp.sum() == 16 * 16 * 16 and spp[high].mean() > spp[low].mean()


def test_the_expected_bound_reports_replica_zero_at_each_iteration(tiny_weights_dir: Path) -> None:
    nets = load_bench_networks(tiny_weights_dir)
    run = run_expected_bound(SCENE, EXPECTED, SETTINGS, nets, _reference(), replicas=2)
    assert [row.spp_mean for row in run.rows] == [16, 32] and run.method.key == "x"
    assert all(np.isfinite(row.metrics["smape"]) for row in run.rows)
    assert run.spp_map.shape == (16, 16) and run.spp_map.sum() == 32 * 256


def _head(d_b: dict[str, float], o_b: dict[str, float], x_b: dict[str, float]) -> Headline:
    median = lambda ratios: statistics.median(ratios.values()) if ratios else float("nan")
    return Headline({}, {}, {}, {}, d_b, median(d_b), o_b, median(o_b), x_b)


def test_the_seed_table_and_bound_line_show_the_expected_bound_only_where_it_ran() -> None:
    with_x = {0: _head({"a": 0.90, "b": 0.80}, {"a": 0.85, "b": 0.78}, {"a": 0.89, "b": 0.79})}
    table = seed_table(with_x)
    assert "SMAPE (x)/(b)" in table and "gap (d)/(b) − (x)/(b)" in table
    assert "| a | 0.900 (0.900–0.900) | 0.850 (0.850–0.850) | 0.050 (0.050–0.050) | 0.890 (0.890–0.890) | " \
           "0.010 (0.010–0.010) |" in table
    line = bound_line(with_x)
    assert "median gap (d)/(b) − (x)/(b) **0.010 (0.010–0.010)** (within 0.02)" in line
    without_x = {0: _head({"a": 0.90}, {"a": 0.85}, {})}
    assert "(x)" not in seed_table(without_x) and "(x)" not in bound_line(without_x)
