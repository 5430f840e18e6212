from bench.models_report import benchmark_models, denoise_ms_by_threads, main
from models.denoiser import Denoiser, DenoiserConfig


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
    path = main(["8", "--threads", "1", "--repeats", "1", "--width", "8", "--spatial-blocks", "1"], out=tmp_path)
    text = path.read_text()
    assert "width=8" in text and "| temporal-3 | 8² | 1 |" in text and "| window-3 | 8² | 1 |" in text
    assert "Command: `renderloop bench --models`" in text and "Date:" in text


def test_thread_probe_times_a_denoiser_that_takes_the_oidn_candidate():
    """The loop report's one-vs-two-thread note once read 'this denoiser needs candidate image'."""
    denoiser = Denoiser(DenoiserConfig(width=8, spatial_blocks=1, temporal=False, oidn_candidate=True)).eval()
    timing = denoise_ms_by_threads(denoiser, 16, (1, 2), repeats=1)
    assert set(timing.ms_median) == {1, 2} and all(ms > 0 for ms in timing.ms_median.values())
