"""The tiny sample scene and training config of ``tests/train`` (the same fixtures, re-exported), and a
tiny finished run of the bundled sample (``trained``, copied for each test by ``run``)."""

import shutil
from pathlib import Path

import pytest

from tests.train.conftest import tiny_config, tiny_scene  # noqa: F401
from vadgs.cli import main

#: ``vadgs train`` flags of a run of a few seconds.
TINY = ["--scale", "0.25", "--no-progress", "--init.max-points", "300", "--init.voxel-size", "1.0"]
TINY += ["--init.sh-degree", "0", "--iterations", "2"]


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
