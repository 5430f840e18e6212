"""No module of the product or the measurement wing over 500 lines (docs/design.md, "Rules of the
house": one file per concept, small enough to read whole)."""
from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
MAX_LINES = 500
CHECKED = ("service", "models", "bench", "scripts")


def test_no_module_is_over_500_lines():
    sizes = {str(path.relative_to(REPO)): len(path.read_text(encoding="utf-8").splitlines())
             for top in CHECKED for path in sorted((REPO / top).rglob("*.py"))}
    assert len(sizes) > 100   # the modules were found
    assert {name: lines for name, lines in sizes.items() if lines > MAX_LINES} == {}
