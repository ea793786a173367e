"""Every Python block of README.md and docs/*.md runs, as written, in the order of its file.

The blocks of one file share one namespace and run in a temporary working directory (a fresh
clone's view: nothing but the package and the bundled sample). A ``>>>`` block is a doctest: its
outputs are checked too (``...`` matches anything). An HTML comment on the line before a block
says what it needs:

- ``<!-- needs: shared -->``: the data of ``../shared`` (a checkout next to the repository,
  or the folder ``VADGS_SHARED`` names); ``../shared`` in the block is read from there; without
  it the block is skipped (the others run, the file's test is then reported as skipped);
- ``<!-- setup: colmap_project -->``: a small COLMAP project (``project/sparse/0``, ``project/images``)
  is written into the working directory first;
- ``<!-- setup: argoverse2_log -->``: a small Argoverse 2 log (``av2/val/<log_id>``) is written first;
- ``<!-- no-run: reason -->``: not run (an outline of a loop, a cluster command); rare.
"""

from __future__ import annotations

import doctest
import os
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("VADGS_SHARED", ROOT.parent / "shared"))
FILES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
# docs/vad.md's blocks run in tests/test_docs_vad.py (each checked against what it should print)
NOT_YET = {"vad.md": "run by tests/test_docs_vad.py"}

_BLOCK = re.compile(r"(?:<!--\s*(?P<marks>[^>]*?)\s*-->\s*\n)?```python\n(?P<code>.*?)```", re.S)


def blocks(path: Path) -> list[tuple[int, dict[str, str], str]]:
    """``(line, marks, code)`` of each Python block of a Markdown file."""
    text = path.read_text()
    out = []
    for m in _BLOCK.finditer(text):
        marks = {}
        for part in (m["marks"] or "").split(";"):
            key, _, value = part.partition(":")
            if key.strip():
                marks[key.strip()] = value.strip()
        out.append((text[: m.start("code")].count("\n"), marks, m["code"]))
    return out


def _colmap_project(folder: Path) -> None:
    from tests.data.colmap_sample import write_sample_colmap

    write_sample_colmap(folder / "project", n_points=400)


def _argoverse2_log(folder: Path) -> None:
    from tests.data.argoverse2_log import write_log

    write_log(folder / "av2" / "val")


SETUPS = {"colmap_project": _colmap_project, "argoverse2_log": _argoverse2_log}


def _run(code: str, namespace: dict, where: str) -> None:
    if code.lstrip().startswith(">>>"):
        test = doctest.DocTestParser().get_doctest(code, namespace, where, where, 0)
        runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
        out: list[str] = []
        runner.run(test, out=out.append, clear_globs=False)
        assert not runner.failures, "".join(out)
    else:
        exec(compile(code, where, "exec"), namespace)


@pytest.mark.parametrize("path", [f for f in FILES if blocks(f)], ids=lambda p: p.name)
def test_python_blocks_run(path, tmp_path, monkeypatch):
    if path.name in NOT_YET:
        pytest.skip(f"{path.name}: {NOT_YET[path.name]}")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    namespace: dict = {"__name__": f"docs_{path.stem}"}
    skipped = []
    for line, marks, code in blocks(path):
        where = f"{path.relative_to(ROOT)}:{line + 1}"
        if "no-run" in marks:
            assert marks["no-run"], f"{where}: no-run needs a reason"
            continue
        if "needs" in marks:
            assert marks["needs"] == "shared", f"{where}: unknown need {marks['needs']!r}"
            if not SHARED.is_dir():
                skipped.append(where)
                continue
            code = code.replace("../shared/", f"{SHARED}/")
        elif "../shared" in code:
            raise AssertionError(f"{where}: reads ../shared without <!-- needs: shared -->")
        if "setup" in marks:
            SETUPS[marks["setup"]](tmp_path)
        _run(code, namespace, where)
    if skipped:
        pytest.skip(f"the other blocks ran; {', '.join(skipped)} need ../shared")
