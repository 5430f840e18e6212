import pytest
import torch

from bench.lambda_edit import lambda_edit_section, lambda_maps, measure_lambda_edit
from bench.lambda_edit_ab import main as lambda_edit_ab
from bench.models_report import CASES, benchmark_models, denoise_ms_by_threads, main
from models.denoiser import Denoiser, DenoiserConfig
from models.pretrained import SHIPPED_WEIGHTS_DIR, load_denoiser
from tests.models.conftest import make_frame

REPORT_SIZE = 32


def test_benchmark_reports_time_and_memory_per_case():
    # one spawned process at 8×8: pins the row format the docs table is built from
    (row,) = benchmark_models(sizes=(8,), repeats=1, threads=1, cases=("lambda-tail",))
    assert row["model"] == "lambda-tail" and row["size"] == 8
    assert row["ms_min"] == row["ms_median"] > 0   # one repeat
    # ru_maxrss is KiB on Linux: a torch process holds a few hundred MB (a unit slip gives 0.3 or 3e5)
    assert 50 < row["peak_rss_mb"] < 20_000 and 0 <= row["peak_rss_growth_mb"] <= row["peak_rss_mb"]


@pytest.fixture(scope="module")
def models_report(tmp_path_factory) -> str:
    """`renderloop bench --models 32 …` once, as the CLI calls it (sys.argv = [renderloop, bench,
    --models]): every case at 32² on one thread, width 8, the shipped single-frame kind of network."""
    out = tmp_path_factory.mktemp("models")
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr("sys.argv", ["renderloop", "bench", "--models"])
        path = main([str(REPORT_SIZE), "--threads", "1", "--repeats", "3", "--width", "8", "--spatial-blocks", "1",
                     "--lambda-edit-size", "24", "16"], out=out)
    return path.read_text()


def report_rows(text: str) -> dict[str, dict[str, float | str]]:
    """The speed table's rows by case: size, threads and the median process CPU ms."""
    rows = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if len(cells) == 8 and cells[0] in CASES:
            rows[cells[0]] = {"size": cells[1], "threads": cells[2], "cpu_ms": float(cells[5])}
    return rows


def test_bench_main_reads_its_own_arguments_and_writes_the_report(models_report):
    text = models_report
    assert "width=8" in text and "oidn_candidate=True" in text and "temporal=False" in text
    # the λ edit's section: its three λ inputs, no server without a checkpoint's folder
    assert "## A λ edit at 24×16" in text and "| uniform map (global λ) |" in text and "| rectangle map |" in text
    assert "PUT /jobs" not in text
    assert "Command: `renderloop bench --models`" in text and "Date:" in text


def test_the_speed_report_has_one_row_per_case_at_the_size_and_threads_asked_for(models_report):
    rows = report_rows(models_report)
    assert list(rows) == list(CASES)
    assert {(row["size"], row["threads"]) for row in rows.values()} == {(f"{REPORT_SIZE}²", "1")}


def test_the_lambda_tail_costs_well_under_the_full_denoise_it_is_the_end_of(models_report):
    """`lambda-tail` is `apply` on `temporal-3`'s cached features, a part of that full pass: a tail
    that re-ran the preparation would cost about as much. CPU time, not wall time, so the load of
    a shared host does not decide it (measured at 32² under load 10: 2.4 ms vs 14.9 ms)."""
    rows = report_rows(models_report)
    assert rows["lambda-tail"]["cpu_ms"] < rows["temporal-3"]["cpu_ms"] / 2, rows


def test_a_single_frame_network_on_a_three_frame_window_costs_about_one_frame_not_three(models_report):
    """`window-3` pools the window's samples into the centre frame and filters that one frame
    (models/accumulation.py): about `multi-scale`'s cost (measured 11.0 vs 9.6 ms CPU at 32²),
    where filtering each of the three frames would cost three times as much."""
    rows = report_rows(models_report)
    assert rows["window-3"]["cpu_ms"] < 2 * max(rows["multi-scale"]["cpu_ms"], 1.0), rows


def test_thread_probe_times_a_denoiser_that_takes_the_oidn_candidate_at_the_size_asked_for():
    """The loop report's one-vs-two-thread note once read 'this denoiser needs candidate image'.
    The probe times a forward pass at the size it is given: 256× the pixels take far longer, where
    a probe that ignored its size would time both alike. (64× — 32² against 256², 17–25 ms against
    44–85 ms at load 10 — fell under the factor 2 in 2 of 13 runs at load 3.5: a 32² pass is mostly
    fixed cost, so a load spike on it closes the gap; 512² is 4× 256²'s work.)"""
    denoiser = Denoiser(DenoiserConfig(width=8, spatial_blocks=1, temporal=False, oidn_candidate=True)).eval()
    small = denoise_ms_by_threads(denoiser, 32, (1, 2), repeats=3)
    large = denoise_ms_by_threads(denoiser, 512, (1,), repeats=3)
    assert set(small.ms_median) == {1, 2} and (small.size, large.size) == (32, 512)
    assert large.ms_median[1] > 2 * small.ms_median[1], (small, large)


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
    assert "on a finished 48×32 cornell-box job" in section
    assert "| | Ray backend (the default) | thread backend (`--concurrency 1`) |" in section


@pytest.mark.slow
def test_the_before_after_script_times_both_trees_in_alternating_processes():
    results = lambda_edit_ab(["--before", "HEAD", "--size", "64", "48", "--rounds", "1", "--repeats", "1", "--threads", "1"])
    assert set(results) == {"before", "after"}
    assert all(len(ms) == 1 and ms[0] > 0 for cases in results.values() for ms in cases.values())
