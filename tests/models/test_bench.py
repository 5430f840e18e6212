from models.bench import benchmark_models


def test_benchmark_reports_time_and_memory_per_case():
    # one spawned process at 8×8: pins the row format the docs table is built from
    (row,) = benchmark_models(sizes=(8,), repeats=1, threads=1, cases=("lambda-tail",))
    assert row["model"] == "lambda-tail" and row["size"] == 8
    assert row["ms_median"] > 0 and row["cpu_ms_median"] >= 0 and row["peak_rss_growth_mb"] >= 0
