"""No module of ``vadgs`` over :data:`MAX_LINES` lines (the batched PatchMatch aside, one kernel
sequence read top to bottom): a module past it holds more than one concept and is cut by them."""

from __future__ import annotations

from pathlib import Path

import vadgs

ROOT = Path(vadgs.__file__).parent
MAX_LINES = 600
EXEMPT = {"mvs/patchmatch.py"}


def module_lengths(root: Path) -> dict[str, int]:
    """Each ``.py`` file below ``root`` (POSIX path relative to it) → its number of lines."""
    return {p.relative_to(root).as_posix(): len(p.read_text().splitlines()) for p in root.rglob("*.py")}


def test_no_module_is_over_the_limit():
    lengths = module_lengths(ROOT)
    assert len(lengths) > 100  # the walk found the package
    over = {m: n for m, n in lengths.items() if n > MAX_LINES and m not in EXEMPT}
    assert not over, f"modules over {MAX_LINES} lines: {over}"


def test_the_count_sees_a_long_module(tmp_path):
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "long.py").write_text("x = 1\n" * (MAX_LINES + 1))
    (tmp_path / "short.py").write_text("y = 2\n")
    assert module_lengths(tmp_path) == {"pkg/long.py": MAX_LINES + 1, "short.py": 1}
