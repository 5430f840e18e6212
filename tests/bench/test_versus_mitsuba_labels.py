"""The network table of `renderloop bench --versus-mitsuba` labels its OIDN-candidate row from the
weights that ran: the shipped denoiser (recipe kpcn-single-frame-oidn) takes OIDN's image, so its
row is an OIDN call, not "0: these weights take none" (what the committed 2 MP report said beside
679 ms / MP)."""
from __future__ import annotations

from types import SimpleNamespace

from bench.versus_mitsuba_costs import STAGES, FixedCosts
from bench.versus_mitsuba_report import network_table
from bench.versus_mitsuba_run import Curve, CurvePoint
from models.pretrained import load_networks

TAKES_ONE = "OIDN candidate inside the denoiser (an OIDN call, quality high: these weights take one)"
TAKES_NONE = "OIDN candidate inside the denoiser (0: these weights take none)"


def scene_run(takes_candidate: bool, candidate_ms: float) -> SimpleNamespace:
    """What network_table reads of one scene: its fixed costs, its film, its mi.render curve's OIDN calls."""
    ms = {key: 10.0 for key, _, _ in STAGES} | {"oidn_candidate": candidate_ms}
    costs = FixedCosts("scene", 2.0, ms, [100.0], [50.0], takes_candidate)
    mitsuba = Curve("mitsuba", "mi.render + OIDN", [CurvePoint(16, 1.0, 0.1, {"oidn": 1.2})])
    return SimpleNamespace(costs=costs, film=SimpleNamespace(megapixels=2.0), curves={"mitsuba": mitsuba})


def row(table: str, label: str) -> list[str]:
    return next(line for line in table.splitlines() if line.startswith(f"| {label} |")).strip("|").split("|")


def test_weights_that_take_the_oidn_candidate_label_its_row_an_oidn_call() -> None:
    table = network_table([scene_run(True, 1358.0)], None, 2)
    assert TAKES_NONE not in table
    assert row(table, TAKES_ONE)[1].strip() == "679"  # 1358 ms over 2 MP


def test_weights_without_the_candidate_keep_their_zero_row() -> None:
    table = network_table([scene_run(False, 0.0)], None, 2)
    assert TAKES_ONE not in table and row(table, TAKES_NONE)[1].strip() == "0"


def test_the_shipped_denoiser_takes_the_oidn_candidate() -> None:
    """The fixed costs read `takes_candidate` off the loaded denoiser's config; the shipped one's is on."""
    assert load_networks().denoiser.config.oidn_candidate


def test_the_network_table_points_to_the_http_round_trip_report() -> None:
    table = network_table([scene_run(True, 1358.0)], None, 2)
    assert "docs/lambda-edit.md (`renderloop bench --lambda-edit`)" in table
