"""`renderloop bench --versus-mitsuba` end to end on a tiny setting (real Mitsuba, real OIDN, the
real loop with tiny untrained networks), and the equal-error / equal-time reading its headline
rests on."""
from __future__ import annotations

import argparse
import math
import resource
from pathlib import Path
from types import SimpleNamespace

import drjit as dr
import numpy as np
import pytest

from bench.cli import main as bench_main
from bench import versus_mitsuba
from bench.versus_mitsuba import (add_arguments, measure_versus_mitsuba, report_name, run_versus_mitsuba_command,
                                  suite_scenes, write_report)
from bench.versus_mitsuba_costs import FixedCosts
from bench.loop_run import EXTRAPOLATION_LIMIT
from bench.versus_mitsuba_report import LOOP, UNIFORM, headline_table, ratio_cell, reading_cell, relmse_summary
from bench.common import Reference, load_bench_networks
from bench.versus_mitsuba_run import (Curve, CurvePoint, at_competitor_end, better_of, compare,
                                      least_at_competitor_ends, compile_loop_kernels, debiased_relmse,
                                      error_at_time, kernel_compile_seconds, make_loop, time_at_error)
from bench.versus_mitsuba_scene import (AOVS, COMPETITOR_CALL_LANES, REFERENCE_CALL_LANES, REFERENCE_CALLS, Crop, Film,
                                        competitor_scene, pass_plan, reference_scene, render_with_aovs, scaled_film)
from service.render.runtime import mitsuba

TINY_SCENE = "sun_room"  # a Gaussian film: both mi.render films run


def curve(key: str, points: list[tuple[float, float, float]]) -> Curve:
    """A curve from (spp, seconds, SMAPE) triples."""
    return Curve(key, key, [CurvePoint(spp, seconds, error, {}) for spp, seconds, error in points])


def loglog(x0: float, y0: float, x1: float, y1: float, y: float) -> float:
    """x at y on the straight line through two points in log-log (written out independently)."""
    u = (math.log(y) - math.log(y0)) / (math.log(y1) - math.log(y0))
    return math.exp(math.log(x0) + u * (math.log(x1) - math.log(x0)))


# The scenes measured so far, each time the run called its after_scene hook (the tiny run's).
SCENES_AT_EACH_HOOK: list[list[str]] = []


@pytest.fixture(scope="module")
def tiny_results(tmp_path_factory, tiny_weights_dir: Path):
    cache = tmp_path_factory.mktemp("cache")
    return measure_versus_mitsuba(megapixels=0.004, max_spp=64, reference_spp=256, scenes=[TINY_SCENE],
                                  weights_dir=tiny_weights_dir, cache_dir=cache, threads=1,
                                  command="renderloop bench --versus-mitsuba --tiny", costs_megapixels=0.008,
                                  after_scene=lambda so_far: SCENES_AT_EACH_HOOK.append(
                                      [run.scene.name for run in so_far.scenes]))


def test_each_finished_scene_is_handed_on_before_the_next_starts(tiny_results) -> None:
    # the command writes the report from this hook: a run cut short keeps every finished scene
    assert SCENES_AT_EACH_HOOK == [[TINY_SCENE]]


def test_scenes_run_in_the_order_named() -> None:
    names = ["point_object", "dof_desk", "kitchen_counter", "fine_texture"]
    assert [scene.name for scene in suite_scenes(names)] == names


def test_a_run_with_the_networks_on_cuda_writes_the_gpu_report_beside_the_cpu_one(monkeypatch) -> None:
    monkeypatch.setattr(versus_mitsuba, "network_device", lambda: "cpu")
    assert report_name() == "benchmarks-versus-mitsuba.md"
    monkeypatch.setattr(versus_mitsuba, "network_device", lambda: "cuda")
    assert report_name() == "benchmarks-versus-mitsuba-gpu.md"


def test_tiny_run_writes_a_filled_report_with_every_section(tiny_results, tmp_path: Path) -> None:
    text = write_report(tiny_results, tmp_path).read_text()
    assert "$" not in text  # every template field was filled
    for needed in ("Command: `renderloop bench --versus-mitsuba --tiny`", "Machine:", "Mitsuba variant:",
                   "## Headline", "equal-error speed-up", "## The same in relMSE", "## Peak memory", "## Networks and OIDN, ms per megapixel",
                   "## Fixed costs per iteration", "state snapshot on the loop's thread", "checkpoint write",
                   "preview write", "What the writes cost the render",
                   "**A small run**", "renderloop bench --versus-mitsuba -o docs", "256 spp", "quality high",
                   "Our denoise (the full pass with its OIDN call) takes", "Kernel compiles, not in any time above",
                   "Read without extrapolating the competitor", "At the competitors' own last points the loop"):
        assert needed in text, needed
    assert "nan" not in text.lower().replace("nanos", "")
    assert f"{TINY_SCENE}:** one 16-spp iteration" in text  # the --costs-megapixels probe's table


def network_ms_within_the_loops_own(costs: FixedCosts, points: list[CurvePoint]) -> None:
    """The network stages time the calls the loop times itself (its "denoise": buffers → tensors,
    OIDN candidate, denoiser; its "error"), so in milliseconds they land within 10× of the loop's
    own figure for an iteration (measured 28 vs 21-41 ms), the λ tail, a part of that pass, within
    100× below it (measured 2-8 ms); a figure in seconds, or a lambda that times nothing, is
    1000× off."""
    loop_ms = [1000 * (p.stages["denoise"] + p.stages["error"]) for p in points]
    full_pass = sum(costs.ms[s] for s in ("to_tensors", "oidn_candidate", "denoiser", "error_network"))
    assert min(loop_ms) / 10 < full_pass < 10 * max(loop_ms), (full_pass, loop_ms)
    assert min(loop_ms) / 100 < costs.ms["lambda_tail"] < 10 * max(loop_ms), (costs.ms["lambda_tail"], loop_ms)
    # a copy into tensors is cheaper than the network that reads them (measured 0.3 vs 27 ms)
    assert costs.ms["to_tensors"] < costs.ms["denoiser"], costs.ms
    # the loop's thread copies the state in memory; the background thread writes files of it
    # (measured 0.04 ms against 8 ms each): a swapped or empty write timing breaks this
    assert costs.ms["snapshot"] < min(costs.ms["checkpoint"], costs.ms["preview"]), costs.ms


def test_fixed_costs_are_the_loops_own_stages_in_ms_and_the_probe_at_its_own_size(tiny_results) -> None:
    run = tiny_results.scenes[0]
    costs, points = run.costs, run.curves[LOOP].points
    # the table's iteration and render times are the loop curve's own stage times, in ms
    assert costs.iteration_ms == pytest.approx([1000 * sum(p.stages.values()) for p in points])
    assert costs.render_ms == pytest.approx([1000 * p.stages["render"] for p in points])
    assert costs.ms["render"] == pytest.approx(costs.render_ms[-1])
    network_ms_within_the_loops_own(costs, points)
    assert len(costs.iteration_ms) == 3 and 0 < costs.stall_share < 1
    # the tiny weights take no OIDN candidate: read off their config, the row times nothing
    assert not costs.takes_candidate and costs.ms["oidn_candidate"] == 0
    probe = tiny_results.probe
    assert probe.film.width * probe.film.height == pytest.approx(8000, rel=0.1)
    assert probe.costs.megapixels == pytest.approx(0.008, rel=0.1) and len(probe.costs.iteration_ms) == 1
    assert probe.costs.ms["snapshot"] < min(probe.costs.ms["checkpoint"], probe.costs.ms["preview"]), probe.costs.ms


def test_peak_memory_is_this_process_resident_set_while_each_curve_ran(tiny_results) -> None:
    """Each peak lies between the resident memory when its curve started (peak − growth) and this
    process's lifetime peak (ru_maxrss, KiB on Linux): a figure in KiB, or of virtual memory
    (several GB with torch and Dr.Jit), exceeds the latter; a negative growth is no peak."""
    lifetime_peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    run, probe = tiny_results.scenes[0], tiny_results.probe
    measured = [(key, c.peak_rss_mb, c.rss_growth_mb) for key, c in run.curves.items()]
    for key, peak, growth in measured + [("probe", probe.peak_rss_mb, probe.rss_growth_mb)]:
        assert 0 <= growth <= peak <= lifetime_peak_mb + 1, (key, peak, growth, lifetime_peak_mb)


def test_uniform_curves_fall_with_spp_at_the_levels_asked(tiny_results) -> None:
    run = tiny_results.scenes[0]
    assert set(run.curves) == {"mitsuba", "mitsuba-box", LOOP, UNIFORM}  # a Gaussian film: both films ran
    for key in ("mitsuba", "mitsuba-box"):
        points = run.curves[key].points
        assert [p.spp for p in points] == [16, 32, 64]
        errors = [p.smape for p in points]
        assert errors == sorted(errors, reverse=True) and errors[0] > errors[-1], (key, errors)
        for p in points:  # a point's wall time is its render plus its OIDN call, nothing left out
            assert p.seconds == pytest.approx(p.stages["render"] + p.stages["oidn"]), (key, p)
    assert [p.spp for p in run.curves[LOOP].points] == [16, 32, 64]
    loop_seconds = [p.seconds for p in run.curves[LOOP].points]
    assert loop_seconds == sorted(loop_seconds)  # cumulative
    # every curve ran inside the measurement, one after the other: together at most its wall time
    # (measured 33 of 54 s); a curve timed in ms, or counted twice, exceeds it
    timed = sum(p.seconds for key in ("mitsuba", "mitsuba-box") for p in run.curves[key].points)
    timed += run.curves[LOOP].points[-1].seconds + run.curves[UNIFORM].points[-1].seconds
    assert timed < tiny_results.seconds, (timed, tiny_results.seconds)
    assert run.film.width * run.film.height == pytest.approx(4000, rel=0.1)


def test_speedup_is_read_off_the_better_competitor_as_documented(tiny_results) -> None:
    run = tiny_results.scenes[0]
    loop = run.curves[LOOP]
    comparisons = [compare(loop, run.curves[k]) for k in ("mitsuba", "mitsuba-box")]
    chosen = run.versus_mitsuba
    assert chosen.other_seconds.value == min(c.other_seconds.value for c in comparisons)
    assert chosen.target == loop.points[-1].smape and chosen.loop_seconds == loop.points[-1].seconds
    assert chosen.speedup == pytest.approx(chosen.other_seconds.value / loop.points[-1].seconds)
    other = run.curves[chosen.other].points
    bracket = [(a, b) for a, b in zip(other, other[1:]) if min(a.smape, b.smape) <= chosen.target <= max(a.smape, b.smape)]
    if bracket:  # the curves meet: a log-log interpolation between the two bracketing points
        (a, b) = bracket[0]
        assert chosen.other_seconds.how == "interpolated"
        assert chosen.other_seconds.value == pytest.approx(loglog(a.seconds, a.smape, b.seconds, b.smape, chosen.target))
    else:
        assert chosen.other_seconds.how == "extrapolated"
    assert ("~" in headline_table([run]).splitlines()[2]) == (chosen.other_seconds.how == "extrapolated"
                                                             or chosen.other_error.how == "extrapolated"
                                                             or run.versus_uniform.other_seconds.how == "extrapolated")


def test_equal_error_time_interpolates_where_the_curves_meet() -> None:
    loop = curve(LOOP, [(16, 1.0, 0.08), (32, 2.0, 0.05)])
    other = curve("mitsuba", [(16, 1.0, 0.10), (32, 2.0, 0.07), (64, 4.0, 0.04)])
    c = compare(loop, other)
    assert c.other_seconds.how == "interpolated"
    assert c.other_seconds.value == pytest.approx(loglog(2.0, 0.07, 4.0, 0.04, 0.05))
    assert c.speedup == pytest.approx(c.other_seconds.value / 2.0) and c.speedup > 1
    assert c.other_error.how == "interpolated" and c.other_error.value == pytest.approx(0.07)
    assert c.error_ratio == pytest.approx(0.05 / 0.07)


def test_extrapolation_is_flagged_when_the_curves_do_not_meet() -> None:
    loop = curve(LOOP, [(16, 1.0, 0.03), (32, 2.0, 0.02)])
    never_that_low = curve("mitsuba", [(16, 1.0, 0.10), (32, 2.0, 0.08), (64, 4.0, 0.06)])
    already_lower = curve("mitsuba-box", [(16, 4.0, 0.015), (32, 8.0, 0.01)])
    for other in (never_that_low, already_lower):
        reading = time_at_error(other, 0.02)
        assert reading.how == "extrapolated" and math.isfinite(reading.value)
    assert time_at_error(never_that_low, 0.02).value > 4.0  # beyond its last point
    assert time_at_error(already_lower, 0.02).value < 4.0  # before its first
    assert error_at_time(already_lower, 2.0).how == "extrapolated"
    flat = curve("mitsuba", [(16, 1.0, 0.05), (32, 2.0, 0.05), (64, 4.0, 0.06)])
    assert time_at_error(flat, 0.02).how == "not reached" and math.isinf(time_at_error(flat, 0.02).value)
    best = better_of(loop, [never_that_low, already_lower])
    # the competitor that reaches the loop's SMAPE sooner is the one compared
    assert best.other == "mitsuba-box"
    assert best.speedup == pytest.approx(time_at_error(already_lower, 0.02).value / 2.0)


def test_a_nearly_flat_competitor_never_reaches_the_loops_error_instead_of_a_guess_of_ages() -> None:
    # glass_shelf at 2 MP: OIDN's bias holds mi.render + OIDN at ~0.031 from 16 to 128 spp, so its
    # power law would need ~10⁹× the loop's time to reach the loop's 0.0270
    loop = curve(LOOP, [(16, 14.7, 0.0283), (128, 111.0, 0.0270)])
    flat = curve("mitsuba", [(16, 23.0, 0.0318), (32, 43.7, 0.0317), (64, 85.7, 0.0316), (128, 167.7, 0.0314)])
    c = compare(loop, flat)
    assert c.other_seconds.how == "not reached" and math.isinf(c.other_seconds.value)
    assert reading_cell(c.other_seconds, ".2f") == "never" and ratio_cell(c.speedup, c.other_seconds) == "n/a"
    # within EXTRAPOLATION_LIMIT times its last time, the same power law is still read, marked
    steeper = curve("mitsuba", [(16, 23.0, 0.0318), (128, 167.7, 0.0290)])
    reading = time_at_error(steeper, 0.0270)
    assert reading.how == "extrapolated" and 167.7 < reading.value <= EXTRAPOLATION_LIMIT * 167.7


def test_a_competitor_already_lower_on_a_curve_that_does_not_fall_is_bounded_by_its_first_point() -> None:
    rising = curve("mitsuba", [(16, 3.0, 0.010), (32, 6.0, 0.012)])
    reading = time_at_error(rising, 0.02)
    assert reading.how == "at most" and reading.value == pytest.approx(3.0) and reading.measured
    c = compare(curve(LOOP, [(16, 2.0, 0.03), (32, 4.0, 0.02)]), rising)
    assert reading_cell(c.other_seconds, ".2f") == "≤3.00" and ratio_cell(c.speedup, c.other_seconds) == "≤0.75×"


def test_the_relmse_summary_counts_a_competitor_that_never_gets_as_low_as_ahead_and_an_unreadable_loop_not() -> None:
    loop = curve(LOOP, [(16, 1.0, 0.03), (32, 2.0, 0.02)])
    flat = curve("mitsuba", [(16, 1.0, 0.05), (32, 2.0, 0.05)])
    below_noise = compare(curve(LOOP, [(16, 1.0, 0.03), (32, 2.0, -1e-6)]), flat)
    runs = [SimpleNamespace(versus_mitsuba_relmse=compare(loop, flat)), SimpleNamespace(versus_mitsuba_relmse=below_noise)]
    assert math.isinf(runs[1].versus_mitsuba_relmse.speedup)  # `never` either way: the loop's error is what differs
    assert "on **1 of 1** scenes" in relmse_summary(runs)


def test_the_reading_at_a_competitors_last_point_interpolates_the_loops_curve_and_needs_no_power_law() -> None:
    loop = curve(LOOP, [(16, 1.0, 0.08), (32, 2.0, 0.05), (64, 4.0, 0.03)])
    other = curve("mitsuba", [(16, 1.5, 0.09), (32, 3.0, 0.07), (64, 6.0, 0.06)])
    reading = at_competitor_end(loop, other)
    assert reading.measured and reading.loop_seconds.how == "interpolated"
    assert (reading.target, reading.other_seconds) == (0.06, 6.0)
    assert reading.loop_seconds.value == pytest.approx(loglog(2.0, 0.05, 1.0, 0.08, 0.06))
    assert reading.speedup == pytest.approx(6.0 / reading.loop_seconds.value) and reading.speedup > 1


def test_the_reading_at_a_competitors_last_point_is_a_bound_when_the_loops_first_point_is_already_as_low() -> None:
    loop = curve(LOOP, [(16, 2.0, 0.02), (32, 4.0, 0.015)])
    weak = curve("mitsuba", [(16, 1.0, 0.05), (32, 3.0, 0.03)])
    reading = at_competitor_end(loop, weak)
    assert reading.loop_seconds.how == "at most" and reading.measured
    assert reading.loop_seconds.value == 2.0 and reading.speedup == pytest.approx(1.5)


def test_the_least_favourable_competitor_end_is_reported_and_a_loop_that_never_gets_there_reads_zero() -> None:
    loop = curve(LOOP, [(16, 1.0, 0.08), (32, 2.0, 0.05), (64, 4.0, 0.04)])
    scene_filter = curve("mitsuba", [(16, 1.0, 0.10), (32, 2.0, 0.09), (64, 4.0, 0.08)])
    box = curve("mitsuba-box", [(16, 1.0, 0.07), (32, 2.0, 0.05), (64, 4.0, 0.045)])
    least = least_at_competitor_ends(loop, [scene_filter, box])
    # the box film's last point (0.045) takes the loop longer than the scene filter's (0.08): it is the one shown
    assert least.other == "mitsuba-box" and least.speedup < at_competitor_end(loop, scene_filter).speedup
    unreachable = curve("mitsuba-box", [(16, 1.0, 0.02), (32, 2.0, 0.01)])
    flat_loop = curve(LOOP, [(16, 1.0, 0.05), (32, 2.0, 0.05)])
    assert least_at_competitor_ends(flat_loop, [scene_filter, unreachable]).speedup == 0


def test_debiased_relmse_reads_the_error_against_the_truth_through_a_noisy_reference() -> None:
    rng = np.random.default_rng(4)
    truth = rng.uniform(0.5, 2.0, size=(256, 256, 3))
    image = truth + 0.02 * truth * rng.standard_normal(truth.shape)            # 2 % relative error
    sigma_ref = 0.03 * truth                                                   # a noisier reference
    reference = Reference((truth + sigma_ref * rng.standard_normal(truth.shape)).astype(np.float32),
                          (sigma_ref**2).astype(np.float32))
    against_truth = float(np.mean((image - truth) ** 2 / (truth**2 + 0.01)))
    naive = float(np.mean((image - reference.mean) ** 2 / (reference.mean.astype(np.float64) ** 2 + 0.01)))
    assert naive > 2.5 * against_truth                     # the reference's noise dominates the plain reading
    assert debiased_relmse(image, reference) == pytest.approx(against_truth, rel=0.05)


def test_readings_in_relmse_use_the_points_relmse() -> None:
    loop = Curve(LOOP, LOOP, [CurvePoint(16, 1.0, 0.05, {}, 4e-4), CurvePoint(32, 2.0, 0.04, {}, 2e-4)])
    other = Curve("mitsuba", "mitsuba", [CurvePoint(16, 1.0, 0.03, {}, 8e-4), CurvePoint(32, 2.0, 0.02, {}, 4e-4),
                                         CurvePoint(64, 4.0, 0.015, {}, 1e-4)])
    by_smape, by_relmse = compare(loop, other), compare(loop, other, "relmse")
    assert by_smape.speedup < 1 < by_relmse.speedup        # behind in SMAPE, ahead in relMSE
    assert by_relmse.target == 2e-4 and by_relmse.metric == "relmse"
    assert by_relmse.other_seconds.value == pytest.approx(loglog(2.0, 4e-4, 4.0, 1e-4, 2e-4))
    assert better_of(loop, [other], "relmse") == by_relmse


def test_pass_plan_renders_a_level_in_the_fewest_power_of_four_calls_within_the_lane_cap() -> None:
    # the competitor at 2 MP: a power of 4 in one call, 128 spp as two of 64
    assert pass_plan(16, 2_000_000) == (16, 1)
    assert pass_plan(32, 2_000_000) == (16, 2)
    assert pass_plan(128, 2_000_000) == (64, 2)
    assert pass_plan(64, 10_000) == (64, 1)
    # a reference: many calls for its spread, within its own lane cap
    assert pass_plan(1024, 2_000_000, REFERENCE_CALL_LANES, REFERENCE_CALLS) == (16, 64)
    assert pass_plan(256, 10_000, REFERENCE_CALL_LANES, min_calls=4) == (64, 4)
    assert pass_plan(1024, 2_000_000, max_lanes=2 ** 27) == (64, 16)


def test_references_render_with_the_independent_sampler_and_competitors_with_the_scenes_own() -> None:
    # living_room declares `stratified`, which is biased over the 16-spp calls a 2 MP reference
    # is rendered in; the reference must be unbiased, the competitor the scene as written.
    (scene,) = suite_scenes(["living_room"])
    film = Film(64, 40)
    reference_sensor = reference_scene(scene, film).sensors()[0]
    competitor_sampler = competitor_scene(scene, film).sensors()[0].sampler()
    assert reference_sensor.sampler().class_name() == "IndependentSampler"
    assert competitor_sampler.class_name() == "StratifiedSampler"
    assert reference_sensor.sampler().sample_count() == competitor_sampler.sample_count()
    width, height = (int(v) for v in reference_sensor.film().crop_size())
    assert (width, height) == (64, 40)


# stratified + box: bit for bit; Gaussian: float32 sums added in another order (seen up to 1.3e-6
# relative; another seed, the one difference that would matter, moves pixels by tens of per cent)
@pytest.mark.parametrize("name, rtol", [("living_room", 0.0), ("sun_room", 1e-4)])
def test_the_competitors_features_rendered_apart_are_the_images_of_an_aov_integrator_wrapping_the_scenes(
        name: str, rtol: float) -> None:
    # The competitor renders colour and features in two calls because wrapping cost ~2x a plain
    # render (bench.experiments.competitor_features); what OIDN gets must not change, in one call
    # or in two averaged.
    (scene,) = suite_scenes([name])
    loaded = competitor_scene(scene, Film(40, 30))
    mi = mitsuba()
    wrapped = mi.load_dict({"type": "aov", "aovs": AOVS, "img": loaded.integrator()})
    for spp, max_lanes in ((16, COMPETITOR_CALL_LANES), (32, 16 * 40 * 30)):
        per_call, calls = pass_plan(spp, 40 * 30, max_lanes)
        old = sum(mi.render(loaded, integrator=wrapped, spp=per_call, seed=7 + i) for i in range(calls)) / calls
        old = np.asarray(old, dtype=np.float32)
        new = render_with_aovs(loaded, spp, 7, max_lanes)
        assert calls == spp // 16
        np.testing.assert_allclose(new.color, old[..., :3], rtol=rtol, atol=0)
        np.testing.assert_allclose(new.albedo, old[..., 3:6], rtol=rtol, atol=0)
        np.testing.assert_allclose(new.normal, old[..., 6:9], rtol=rtol, atol=1e-6 if rtol else 0)
        assert new.albedo.max() > 0.1 and np.abs(new.normal).max() > 0.5   # the features were rendered


def test_a_cropped_reference_renders_the_whole_films_pixels_in_its_window() -> None:
    # bench.experiments.crop_reference scores a 2 MP image's windows against windows rendered alone:
    # a window shifted by a pixel, or resampled, would read as error. Away from its margin a window
    # rendered alone differs from the whole film's render there by noise only (0.009 mean |diff| at
    # 256 spp), a fifth of what one pixel over differs (0.046).
    (scene,) = suite_scenes(["hard_shadows"])
    film = Film(64, 48)
    crop = Crop(20, 12, 24, 16)
    mi = mitsuba()
    whole = np.asarray(mi.render(reference_scene(scene, film), spp=256, seed=1), dtype=np.float64)[..., :3]
    window = np.asarray(mi.render(reference_scene(scene, film, crop), spp=256, seed=2), dtype=np.float64)[..., :3]
    assert window.shape == (16, 24, 3)
    inner = lambda x: x[4:-4, 4:-4].mean(-1)   # noqa: E731
    aligned = np.abs(inner(window) - inner(crop.of(whole))).mean()
    shifted = np.abs(inner(window) - inner(Crop(21, 12, 24, 16).of(whole))).mean()
    assert aligned < 0.5 * shifted


def versus_mitsuba_parser() -> argparse.ArgumentParser:
    """The mode's own flags plus the `renderloop bench` flags it shares (bench/cli.py)."""
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    parser.add_argument("-o", "--out", type=Path, default=Path("bench-reports"))
    parser.add_argument("--weights", type=Path, default=None)
    parser.add_argument("--cache", type=Path, default=Path("bench-cache"))
    parser.add_argument("--reference-spp", type=int, default=None)
    return parser


def test_command_refuses_an_unknown_scene_and_a_max_below_16(capsys) -> None:
    parse = versus_mitsuba_parser().parse_args
    assert run_versus_mitsuba_command(parse(["--versus-mitsuba", "--scenes", "no_such_scene"])) == 2
    assert "unknown scene(s) no_such_scene" in capsys.readouterr().err
    assert run_versus_mitsuba_command(parse(["--versus-mitsuba", "--max-spp", "8"])) == 2
    assert "--max-spp must be at least 16" in capsys.readouterr().err
    args = parse(["--versus-mitsuba", "--scenes", "metals,sun_room", "--megapixels", "0.5"])
    assert args.scenes == ["metals", "sun_room"] and args.megapixels == 0.5 and args.max_spp == 1024
    assert args.costs_megapixels is None


def test_renderloop_bench_dispatches_the_versus_mitsuba_mode(capsys) -> None:
    assert bench_main(["--versus-mitsuba", "--scenes", "no_such_scene"]) == 2  # bench/cli.py → this mode
    assert "unknown scene(s) no_such_scene" in capsys.readouterr().err


def test_the_final_images_composition_is_a_row_of_the_fixed_costs_with_a_plausible_figure(tiny_results,
                                                                                          tmp_path: Path) -> None:
    # it times RenderLoop.denoised after forgetting the kept share: the raw image, its variance, the
    # window means and the blend, a few numpy passes over the film (measured 0.8 s at 2 MP before
    # issue 43's cuts): more than nothing, less than the loop's own network passes plus 1 s
    run = tiny_results.scenes[0]
    costs, points = run.costs, run.curves[LOOP].points
    network_ms = max(1000 * (p.stages["denoise"] + p.stages["error"]) for p in points)
    assert 0 < costs.ms["final_image"] < network_ms + 1000, (costs.ms["final_image"], network_ms)
    text = write_report(tiny_results, tmp_path).read_text()
    row = next(line for line in text.splitlines() if line.startswith("| final image (raw image"))
    assert float(row.split("|")[3]) == pytest.approx(costs.ms["final_image"], abs=0.051), row


def kernels_new_to_this_process() -> int:
    """JIT kernels launched since the last call that this process had not launched before: built,
    or loaded from Dr.Jit's cache on disk (so the count does not depend on what that cache holds)."""
    return sum(1 for entry in dr.kernel_history()
               if entry.get("type") == dr.KernelType.JIT and (not entry.get("cache_hit") or entry.get("cache_disk")))


def test_the_warm_up_builds_every_kernel_the_timed_loop_launches(tiny_weights_dir: Path) -> None:
    # sun_room stratifies: its later iterations launch a kernel per sequence length and lane map
    scene = suite_scenes([TINY_SCENE])[0]
    # a film size no other test renders: the film's width is a literal in the kernels, so these are
    # new to the process whatever ran before (a kernel also names the loaded scene's registry ids,
    # which a later load may reuse once the earlier scene is freed)
    film = scaled_film(scene, 0.0031)
    networks = load_bench_networks(tiny_weights_dir).networks
    enabled = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        cold = make_loop(scene, film, networks, "error", 3)
        kernels_new_to_this_process()
        cold_counts = []
        for _ in cold.run():
            cold_counts.append(kernels_new_to_this_process())
        warm = make_loop(scene, film, networks, "error", 3)
        with kernel_compile_seconds() as compiled:
            compile_loop_kernels(warm)
        kernels_new_to_this_process()
        warm_counts = []
        for _ in warm.run():
            warm_counts.append(kernels_new_to_this_process())
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, enabled)
    # Without the warm-up the later iterations build kernels of their own (uneven counts: 4-5
    # measured), so this check can fail; with it, on the same scene file loaded again, at most one
    # is left: the same loop builds one kernel more or less from run to run (the cold first
    # iteration read 2 or 3), likely a host array's alignment, which Dr.Jit's LLVM backend writes
    # into the kernel (lane_map.aligned).
    assert sum(cold_counts[1:]) >= 3, cold_counts
    assert sum(warm_counts) <= 1, warm_counts
    assert math.isfinite(compiled[0]) and compiled[0] >= 0.0  # filled on exit (0 when all came from disk)
