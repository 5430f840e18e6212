"""The CLI's progress bar (`renderloop submit --wait`, Client.wait) shows the server's ETA, not
tqdm's linear extrapolation of the time per iteration (each iteration doubles the samples, so
that one under-estimates: "7 s left", 18 s in fact)."""
from __future__ import annotations

import io
from datetime import datetime, timedelta, timezone

from tqdm import tqdm

from service.client import show_progress


def test_the_progress_bar_counts_down_the_servers_eta_instead_of_extrapolating_iterations():
    out = io.StringIO()
    bar = tqdm(total=4, unit="it", desc="job", file=out, mininterval=0)
    finish = (datetime.now(timezone.utc) + timedelta(seconds=40)).isoformat()
    status = {"state": "running", "spp": 32.0, "predicted_error": 0.02, "iteration": 2,
              "eta_seconds": 40.0, "eta_finish_at": finish}
    show_progress(bar, status)
    bar.refresh()
    line = out.getvalue().splitlines()[-1] if "\n" in out.getvalue() else out.getvalue().split("\r")[-1]
    assert "left=40s" in line or "left=39s" in line, line
    assert "<" not in line, f"tqdm's own remaining-time estimate is still shown: {line}"
    show_progress(bar, {**status, "eta_seconds": None, "eta_finish_at": None})
    bar.refresh()
    assert "left=?" in out.getvalue().split("\r")[-1]
    bar.close()
