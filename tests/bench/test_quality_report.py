"""The denoiser quality report on a tiny data set with an untrained network: every section is
there, every number in it is finite, the crops it links exist; plus the measures it rests on."""
from __future__ import annotations

import math
import re
from pathlib import Path

import pytest
import torch

from models.checkpoint import save_checkpoint
from models.denoiser import Denoiser, temporal_config
from models.error_predictor import ErrorPredictor, ErrorPredictorConfig
from tests.models.conftest import PLAIN_ERROR_NETWORK
import bench.quality_eval as evaluation
import bench.quality_measures as measures
import bench.quality_report as quality

SPP_LEVELS = (16, 32, 64, 128)
NETWORK_ROWS = (evaluation.NOISY, evaluation.SINGLE, evaluation.MULTISCALE, evaluation.TEMPORAL)


def tiny_denoiser() -> Denoiser:
    torch.manual_seed(0)
    return Denoiser(temporal_config(width=8, lambda_width=8, temporal_blocks=1)).eval()


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> Path:
    from service.dataset.build import build_dataset

    root = tmp_path_factory.mktemp("quality")
    data, weights = root / "data", root / "weights"
    build_dataset(data, scenes=2, size=16, frames=3, seed=0, split="heldout", reference_spp=64, progress=False)
    save_checkpoint(weights / "denoiser.pt", tiny_denoiser(), extra={"command": "tiny untrained"})
    save_checkpoint(weights / "error_predictor.pt", ErrorPredictor(ErrorPredictorConfig(width=8, blocks=1, **PLAIN_ERROR_NETWORK)))
    crops = root / "docs" / quality.CROPS_DIR
    crops.mkdir(parents=True)
    (crops / "heldout_scene_of_an_older_data_set_reference.png").write_bytes(b"stale")
    return quality.run_quality_report(data, root / "docs", weights_dir=weights, builtin_scenes=("cornell-box",),
                                      builtin_size=16, reference_spp=64, lambdas=(1.0, 10.0))


def section(text: str, heading: str) -> str:
    """The markdown from `heading` to the next heading of the same or a higher level."""
    level = heading.split(" ")[0]
    start = text.index(heading + "\n")
    end = re.search(rf"^#{{1,{len(level)}}} ", text[start + len(heading):], re.M)
    return text[start:start + len(heading) + end.start()] if end else text[start:]


NUMBER = r"-?\d+(?:\.\d+)?|n/a"
NUMERIC_CELL = re.compile(rf"({NUMBER})×?(?: \[({NUMBER}), ({NUMBER})\])?")


def numeric_rows(table: str) -> list[list[float]]:
    """Numeric cells of every table row below a header ('0.12', '3.4×', '0.5 [0.1, 0.9]'; 'n/a' → nan)."""
    rows = []
    for line in table.splitlines():
        if not line.startswith("| ") or set(line) <= set("|-: "):
            continue
        numbers = []
        for cell in line.strip("|").split("|"):
            match = NUMERIC_CELL.fullmatch(cell.strip())
            if match:
                numbers += [math.nan if g == "n/a" else float(g) for g in match.groups() if g is not None]
        rows.append(numbers)
    return rows[1:]  # the first row of a table is its header


def test_report_states_command_machine_and_headline(report: Path) -> None:
    text = report.read_text()
    assert report.name == "denoiser.md"
    assert "Command: `renderloop bench --denoiser --data " in text
    assert "Machine: " in text and "cores" in text
    headline = re.search(r"SMAPE reduction of 16-spp inputs on held-out scenes: ([\d.]+)×", text)
    assert headline and math.isfinite(float(headline.group(1)))
    assert "ablations of the one trained network" in text


@pytest.mark.parametrize("heading", ["### Held-out procedural scenes", "### Built-in scenes"])
def test_quality_tables_cover_every_level_and_method(report: Path, heading: str) -> None:
    table = section(report.read_text(), heading)
    for spp in SPP_LEVELS:
        for method in NETWORK_ROWS:
            assert re.search(rf"^\| {spp} \| \**{re.escape(method)}\** \|", table, re.M), (spp, method)
    rows = numeric_rows(table)
    assert len(rows) >= len(SPP_LEVELS) * len(NETWORK_ROWS)
    assert all(len(r) == 6 and all(math.isfinite(x) for x in r) for r in rows)  # spp + 4 metrics + factor


def test_flicker_lambda_and_error_predictor_tables_are_finite(report: Path) -> None:
    text = report.read_text()
    flicker = numeric_rows(section(text, "## Temporal flicker"))
    assert len(flicker) >= len(NETWORK_ROWS)
    assert all(math.isfinite(x) for r in flicker for x in r)
    for heading in ("### Held-out scenes, 16 spp", "### Built-in scenes, 16 spp"):
        rows = numeric_rows(section(text, heading))
        assert [r[0] for r in rows] == [1.0, 10.0]
        assert all(math.isfinite(x) for r in rows for x in r)
    errors = numeric_rows(section(section(text, "## Error predictor vs true SMAPE"), "### Held-out scenes"))
    assert [r[0] for r in errors] == list(SPP_LEVELS)
    assert all(math.isfinite(x) for r in errors for x in r)


def test_crops_are_written_and_linked(report: Path) -> None:
    text = report.read_text()
    links = re.findall(r"\]\((denoiser/[^)]+\.png)\)", text)
    assert any("temporal" in link for link in links) and any("true-SMAPE" in link for link in links)
    for link in links:
        assert (report.parent / link).stat().st_size > 0
    written = {f"{quality.CROPS_DIR}/{p.name}" for p in (report.parent / quality.CROPS_DIR).glob("*.png")}
    assert written == set(links)        # crops of an earlier run's example images are gone


def test_ablation_reuses_the_trained_weights() -> None:
    trained = tiny_denoiser()
    single = evaluation.ablation(trained, multiscale=False, temporal=False)
    assert single.composite is None and single.temporal is None
    for name, value in single.state_dict().items():
        assert torch.equal(value, trained.state_dict()[name]), name


def test_evaluate_takes_the_temporal_result_from_its_one_prepare_and_counts_it_as_windowed(monkeypatch) -> None:
    from tests.models.conftest import make_frame

    denoiser = tiny_denoiser()
    window = [make_frame(16, 16, spp=16) for _ in range(3)]
    image = evaluation.EvalImage("held-out", "s", 32, window, 1, torch.rand(1, 3, 16, 16))
    methods, _ = evaluation.make_methods(denoiser, use_oidn=False)
    prepares = []
    original = Denoiser.prepare
    monkeypatch.setattr(Denoiser, "prepare", lambda self, *a, **k: prepares.append(self) or original(self, *a, **k))
    with torch.no_grad():
        out = evaluation.evaluate([image], methods, denoiser, ErrorPredictor(ErrorPredictorConfig(width=8, blocks=1, **PLAIN_ERROR_NETWORK)), ())[0]
        assert sum(p is denoiser for p in prepares) == 2   # MULTISCALE's, and one for TEMPORAL + error map
        torch.testing.assert_close(out.results[evaluation.TEMPORAL], evaluation.windowed(denoiser, image))


def test_lambda_measures_see_noise_and_blur() -> None:
    torch.manual_seed(0)
    x = torch.linspace(0, 1, 32)
    reference = (0.2 + 0.6 * (x[None, :] > 0.5).float() + 0.3 * torch.sin(20 * x)[:, None]).expand(1, 3, 32, 32)
    same = measures.lambda_measures(reference, reference)
    noisy = measures.lambda_measures(reference * (1 + 0.3 * torch.randn(1, 1, 32, 32)), reference)
    blurred = measures.lambda_measures(torch.nn.functional.avg_pool2d(reference, 5, 1, 2, count_include_pad=False),
                                      reference)
    assert same["noise"] == 0 and same["detail"] == pytest.approx(1) and same["grad_corr"] == pytest.approx(1)
    assert noisy["noise"] > 0.01 and noisy["detail"] > 1
    assert blurred["detail"] < 0.9


def test_rank_correlation_matches_a_monotone_map() -> None:
    a = torch.rand(1, 1, 8, 8).numpy()
    assert measures.spearman(a, a ** 3) == pytest.approx(1)
    assert measures.pearson(a, -a) == pytest.approx(-1)


def test_report_states_the_held_out_references_own_noise(report: Path) -> None:
    match = re.search(r"relative standard error of their pixels \(same ε\):\n([\d.]+)\.", report.read_text())
    assert match and 0 < float(match.group(1)) < 1


def test_pyramid_section_reports_each_coarse_level_and_its_alpha(report: Path) -> None:
    rows = re.findall(r"^\| (\d) \(1/(\d+)\) \| ([\d.]+) \| ([\d.]+) \| ([\d.]+) \| ([\d.]+) \|$",
                      section(report.read_text(), "## Pyramid levels"), re.M)
    assert [(int(level), int(scale)) for level, scale, *_ in rows] == [(1, 2), (2, 4)]   # 3-level pyramid
    (own1, finest1, noisy1, alpha1), (own2, finest2, noisy2, alpha2) = [[float(v) for v in row[2:]] for row in rows]
    # 2×2 averaging halves per-pixel noise, so the noisy input pooled twice is well below pooled once
    # (measured 0.0243 → 0.0099): the noisy input pooled once too few times, or columns swapped with
    # the untrained network's results (0.58-0.78, not pooled noise), break this
    assert noisy2 < 0.75 * noisy1, (noisy1, noisy2)
    for smape in (own1, finest1, noisy1, own2, finest2, noisy2):
        assert 0 < smape < 1, rows  # a SMAPE (ε > 0) is below 1 per pixel: not a relMSE or a percent
    assert 0 < alpha1 < 1 and 0 < alpha2 < 1
