"""Issue 49, items 1 and 2: vadgs removes and replaces only what it wrote.

A run's files are exactly its checked manifest's (an entry that leaves the run, by ``..``, an
absolute path or a symlinked folder, stops ``--overwrite`` before anything is removed), and a
folder is a vadgs run by what vadgs wrote into it (its manifest, a ``config.json`` that parses as
a vadgs config, a checkpoint that loads as a vadgs checkpoint), never by file names. Each case
runs the CLI as a user would and compares a hash of the whole tree before and after.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from tests.reliability.test_run_folder import TINY, _error, _tree
from vadgs.cli import main
from vadgs.runfolder import MANIFEST
from vadgs.train.checkpoint import CHECKPOINT_NAME, load_checkpoint


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """A tiny finished run (2 steps of the bundled sample), copied by each test."""
    run = tmp_path_factory.mktemp("trained") / "run"
    assert main(["train", "--sample", "--out", str(run), *TINY]) == 0
    return run


@pytest.fixture
def run(trained, tmp_path) -> Path:
    dst = tmp_path / "run"
    shutil.copytree(trained, dst, symlinks=True)
    return dst


def _add_entry(run: Path, entry: str) -> None:
    path = run / MANIFEST
    data = json.loads(path.read_text())
    data["files"][entry] = {"size": 6}
    path.write_text(json.dumps(data))


@pytest.mark.parametrize("entry", ["../victim.txt", "ply/../../outside/v.txt"])
def test_manifest_entry_outside_the_run_stops_overwrite(run, tmp_path, capsys, entry):
    victim = (run / entry).resolve()
    victim.parent.mkdir(parents=True, exist_ok=True)
    victim.write_text("victim")
    _add_entry(run, entry)
    before = _tree(tmp_path)
    assert main(["train", "--sample", "--out", str(run), *TINY, "--overwrite"]) == 2
    line = _error(capsys)
    assert f"{run / MANIFEST}: entry {entry!r}" in line and "nothing was removed" in line
    assert _tree(tmp_path) == before
    assert victim.read_text() == "victim"
    assert load_checkpoint(run).step == 2  # the old run is whole
