"""Every Python block of ``docs/vad.md`` runs as written: in order, in one namespace, from the
repository's root (the blocks use the bundled sample and few steps)."""

from __future__ import annotations

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
