"""``docs/vad.md`` as written: every Python block runs (in order, in one namespace, from the
repository's root; the blocks use the bundled sample and few steps), and every function its map
(paper section or equation -> ``module.function``) names is where the map says."""

from __future__ import annotations

import importlib
import inspect
import os
import re
from pathlib import Path

import pytest

DOC = Path(__file__).resolve().parents[1] / "docs" / "vad.md"


def python_blocks(text: str) -> list[str]:
    """The fenced ```python blocks of a Markdown text, in order."""
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def test_python_blocks_of_docs_vad_run(capsys):
    pytest.importorskip("gsplat.strategy")
    blocks = python_blocks(DOC.read_text())
    assert len(blocks) == 3
    namespace: dict = {"__name__": "docs_vad"}
    cwd = os.getcwd()
    os.chdir(DOC.parents[1])
    try:
        for k, block in enumerate(blocks):
            exec(compile(block, f"{DOC.name}[python block {k}]", "exec"), namespace)
    finally:
        os.chdir(cwd)
    out = capsys.readouterr().out
    # block 0: the trainer's VAD-GS event; block 1: the own loop's event summary; block 2: one instance
    assert namespace["trainer"].state["vad_events"] and "visibility-aware densification:" in out
    assert any(e["added"] > 0 for e in namespace["state"]["vad_events"])
    assert namespace["rec"].reason == "ok" and namespace["rec"].points.shape[0] > 0


MAP_HEADING = "## Where each step lives: paper → function"


def map_rows(text: str) -> list[tuple[str, str]]:
    """``(paper, function)`` of every row of the map's table (the section under :data:`MAP_HEADING`)."""
    section = text.split(MAP_HEADING, 1)[1].split("\n## ", 1)[0]
    lines = [ln for ln in section.splitlines() if ln.startswith("|")]
    assert lines[0].strip() == "| Paper (section / equation) | Step | Function |", lines[0]
    rows = []
    for ln in lines[2:]:  # after the header and its rule
        cells = [c.strip() for c in ln.strip().strip("|").split("|")]
        assert len(cells) == 3, ln
        rows.append((cells[0], cells[2]))
    return rows


def resolve(dotted: str) -> tuple[str, object]:
    """The module and object named ``package.module.name[.attribute]``: the longest importable module
    prefix, then attributes (a method of a class: ``module.Class.method``)."""
    parts = dotted.split(".")
    for i in range(len(parts) - 1, 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ModuleNotFoundError:
            continue
        for p in parts[i:]:
            obj = getattr(obj, p)  # AttributeError: the map names something that is not there
        return ".".join(parts[:i]), obj
    raise ModuleNotFoundError(dotted)


def test_map_names_functions_where_they_live():
    rows = map_rows(DOC.read_text())
    assert len(rows) >= 30
    for paper, cell in rows:
        names = re.findall(r"`([^`]+)`", cell)
        assert len(names) == 1 and cell == f"`{names[0]}`", f"{paper}: one `module.function`, got {cell!r}"
        name = names[0]
        assert name.startswith("vadgs.") and not any(p.startswith("_") for p in name.split(".")), name
        module, obj = resolve(name)
        assert callable(obj), name
        defined = inspect.getmodule(obj).__name__  # where it is defined, not only re-exported
        assert defined == module, f"{name}: defined in {defined}"


def test_map_covers_the_papers_steps():
    """Each step the paper names has its row: the sections of the method and the named functions."""
    rows = map_rows(DOC.read_text())
    papers = " ".join(p for p, _ in rows)
    for section in ("Sec. 4.1", "Sec. 4.2", "Sec. 4.3", "Sec. 4.4", "Sec. 5.2", "eq.diversity", "eq.loss",
                    'Supp. "Visibility Reasoning"', 'Supp. "View Selection"'):  # fmt: skip
        assert section in papers, section
    functions = {f.strip("`") for _, f in rows}
    for name in (
        "vadgs.select.score.diversity_score",
        "vadgs.train.vad.crops.matching_region",
        "vadgs.train.vad.survey.instance_frame",
        "vadgs.train.objective.render_hard_depth",
    ):
        assert name in functions, name


def test_map_check_fails_on_a_moved_function():
    """The checks above are not vacuous: names that left their module do not resolve there."""
    for moved in (
        "vadgs.train.vad.reconstruct.instance_frame",
        "vadgs.train.vad.event.add_reconstruction",
        "vadgs.nowhere.function",
    ):
        with pytest.raises(AttributeError):
            resolve(moved)
    # re-exported, not defined there: the map must name the defining module
    module, obj = resolve("vadgs.train.vad.VisibilityAwareDensification")
    assert module == "vadgs.train.vad" and inspect.getmodule(obj).__name__ == "vadgs.train.vad.strategy"
