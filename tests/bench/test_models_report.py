import pytest
import torch

from bench.lambda_edit import lambda_edit_section, lambda_maps, measure_lambda_edit
from bench.lambda_edit_ab import main as lambda_edit_ab
from bench.models_report import benchmark_models, denoise_ms_by_threads, main
from models.denoiser import Denoiser, DenoiserConfig
from models.pretrained import SHIPPED_WEIGHTS_DIR, load_denoiser
from tests.models.conftest import make_frame


def test_benchmark_reports_time_and_memory_per_case():
    # one spawned process at 8×8: pins the row format the docs table is built from
    (row,) = benchmark_models(sizes=(8,), repeats=1, threads=1, cases=("lambda-tail",))
    assert row["model"] == "lambda-tail" and row["size"] == 8
    assert row["ms_min"] == row["ms_median"] > 0   # one repeat
    # ru_maxrss is KiB on Linux: a torch process holds a few hundred MB (a unit slip gives 0.3 or 3e5)
    assert 50 < row["peak_rss_mb"] < 20_000 and 0 <= row["peak_rss_growth_mb"] <= row["peak_rss_mb"]


def test_the_window_case_times_a_single_frame_network_pooling_three_frames():
    single = DenoiserConfig(width=8, spatial_blocks=1, temporal=False, oidn_candidate=True)
    (row,) = benchmark_models(sizes=(8,), repeats=1, threads=1, cases=("window-3",), config=single)
    assert row["model"] == "window-3" and row["ms_median"] > 0


def test_bench_main_reads_its_own_arguments_and_writes_the_report(monkeypatch, tmp_path):
    """`renderloop bench --models` calls main() with sys.argv = [renderloop, bench, --models]."""
    monkeypatch.setattr("sys.argv", ["renderloop", "bench", "--models"])
    path = main(["8", "--threads", "1", "--repeats", "1", "--width", "8", "--spatial-blocks", "1",
                 "--lambda-edit-size", "24", "16"], out=tmp_path)
    text = path.read_text()
    assert "width=8" in text and "| temporal-3 | 8² | 1 |" in text and "| window-3 | 8² | 1 |" in text
    # the λ edit's section: its three λ inputs, no server without a checkpoint's folder
    assert "## A λ edit at 24×16" in text and "| uniform map (global λ) |" in text and "| rectangle map |" in text
    assert "PUT /jobs" not in text
    assert "Command: `renderloop bench --models`" in text and "Date:" in text


def test_thread_probe_times_a_denoiser_that_takes_the_oidn_candidate():
    """The loop report's one-vs-two-thread note once read 'this denoiser needs candidate image'."""
    denoiser = Denoiser(DenoiserConfig(width=8, spatial_blocks=1, temporal=False, oidn_candidate=True)).eval()
    timing = denoise_ms_by_threads(denoiser, 16, (1, 2), repeats=1)
    assert set(timing.ms_median) == {1, 2} and all(ms > 0 for ms in timing.ms_median.values())


def test_the_lambda_edit_times_each_lambda_input_on_the_shipped_network():
    timing = measure_lambda_edit(load_denoiser(), None, (40, 24), repeats=2, threads=1)
    assert list(timing.ms) == list(lambda_maps(40, 24)) and all(len(ms) == 2 and min(ms) > 0 for ms in timing.ms.values())
    section = lambda_edit_section(timing)
    assert "## A λ edit at 40×24" in section and "| per-pixel map (a gradient: too many values to fold) |" in section


def test_the_nudged_map_takes_the_per_pixel_path_and_the_uniform_one_the_folded_path():
    """The 'before' row must really time the per-pixel path, else the report compares a path with itself."""
    denoiser = load_denoiser()
    frame = make_frame(24, 40)
    with torch.no_grad():
        cache = denoiser.prepare([frame], 0, torch.rand(1, 3, 24, 40))
        codes = {name: denoiser._lambda_code(cache, lam) for name, lam in lambda_maps(40, 24).items()}
    shapes = [tuple(code.shape[-2:]) for code in codes.values()]
    assert shapes == [(1, 1), (24, 40), (24, 40)]


@pytest.mark.slow
def test_the_lambda_edit_reports_the_http_round_trip_against_a_real_server():
    timing = measure_lambda_edit(load_denoiser(), SHIPPED_WEIGHTS_DIR, (48, 32), repeats=1, threads=1, http_requests=2)
    assert list(timing.http) == ["ray", "thread"]
    for http in timing.http.values():
        assert isinstance(http, dict), http
        assert http["requests"] == 2 and http["height"] == 32 and http["p50_ms"] > 0
        assert http["tail_passes"] >= 2 and http["full_passes"] == 0
    section = lambda_edit_section(timing)
    assert section.count("`PUT /jobs/{id}/lambda` over HTTP on a finished 48×32") == 2 and "thread backend" in section


@pytest.mark.slow
def test_the_before_after_script_times_both_trees_in_alternating_processes():
    results = lambda_edit_ab(["--before", "HEAD", "--size", "64", "48", "--rounds", "1", "--repeats", "1", "--threads", "1"])
    assert set(results) == {"before", "after"}
    assert all(len(ms) == 1 and ms[0] > 0 for cases in results.values() for ms in cases.values())
