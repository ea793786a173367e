"""benchmarks/thin_lidar.py on the bundled sample: a sparser LiDAR for the training frames only."""

from __future__ import annotations

import runpy
from pathlib import Path

import numpy as np
import pytest

from vadgs.data import load_scene, sample_scene_path

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "thin_lidar.py"


@pytest.fixture(scope="module")
def thin():
    return runpy.run_path(str(SCRIPT))["thin_scene"]


def test_training_sweeps_thinned_test_sweeps_whole(thin, tmp_path):
    src = sample_scene_path()
    counts = thin(src, tmp_path / "sparse", keep=0.25, seed=3)
    full, sparse = load_scene(src), load_scene(tmp_path / "sparse")
    assert sparse.test_frames == full.test_frames
    before = after = 0
    for f in (fr.index for fr in full.frames):
        a, b = full.lidar(f), sparse.lidar(f)
        if f in full.test_frames:
            assert np.array_equal(a.points.numpy(), b.points.numpy())
            continue
        n = len(a.points)
        assert len(b.points) == round(0.25 * n)
        # a subset of the sweep, each point with its own instance id
        rows = dict(zip(map(tuple, a.points.tolist()), a.instance.tolist(), strict=True))
        assert all(rows[tuple(p)] == i for p, i in zip(b.points.tolist(), b.instance.tolist(), strict=True))
        before, after = before + n, after + len(b.points)
    assert counts == {"points_before": before, "points_after": after}
    assert after < 0.26 * before


def test_refuses_bad_input(thin, tmp_path):
    with pytest.raises(ValueError, match=r"keep: expected a fraction in \(0, 1\], got 1.5"):
        thin(sample_scene_path(), tmp_path / "a", keep=1.5)
    (tmp_path / "b").mkdir()
    with pytest.raises(FileExistsError, match=r"out: .* exists"):
        thin(sample_scene_path(), tmp_path / "b", keep=0.5)
