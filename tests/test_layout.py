"""The package's shape: modules a reader can hold (none over 800 lines)."""

from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "perscli"
MAX_LINES = 800


def test_no_module_is_over_800_lines():
    sizes = {str(p.relative_to(SRC)): len(p.read_text().splitlines()) for p in SRC.rglob("*.py")}
    assert len(sizes) > 50
    big = {name: n for name, n in sizes.items() if n > MAX_LINES}
    assert not big, f"split these along their jobs: {big}"
