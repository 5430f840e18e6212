"""The denoiser report names the loop's row after what the weights do with a window: the
shipped single-frame network's row is the pooled window, a temporal network's the temporal
multi-scale filter; the committed page (docs/denoiser.md) says the same of the shipped weights."""
from __future__ import annotations

import re
from pathlib import Path

from bench.quality_eval import POOLED, TEMPORAL, window_method
from bench.quality_report import window_description
from models.denoiser import Denoiser, temporal_config
from models.pretrained import load_denoiser

PAGE = Path(__file__).resolve().parents[2] / "docs" / "denoiser.md"


def test_the_loop_row_is_named_after_what_the_weights_do_with_a_window():
    single, temporal = Denoiser(), Denoiser(temporal_config(width=8, lambda_width=8, temporal_blocks=1))
    assert (window_method(single), window_method(temporal)) == (POOLED, TEMPORAL)
    assert "frame by frame" in window_description(single) and "pooled" in window_description(single)
    assert "jointly" in window_description(temporal)


def test_the_committed_denoiser_page_names_the_shipped_networks_loop_row():
    shipped = window_method(load_denoiser())
    text = PAGE.read_text()
    bold_rows = set(re.findall(r"^\| \d+ \| \*\*(.+?)\*\* \|", text, flags=re.MULTILINE))
    assert bold_rows == {shipped}, bold_rows
    other = TEMPORAL if shipped == POOLED else POOLED
    assert other not in text, f"docs/denoiser.md names '{other}', which the shipped weights do not run"
