"""benchmarks/novel_views.py on the bundled sample with novel views that repeat its test views."""

from __future__ import annotations

import importlib.util
import json
import shutil
from pathlib import Path

import pytest
import torch

from vadgs.cli import main as cli
from vadgs.data import load_scene, sample_scene_path

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "novel_views.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("novel_views", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    """The sample with its test views repeated as two novel groups (``shift+0.0`` and ``again``)."""
    torch.set_num_threads(2)
    root = tmp_path_factory.mktemp("scene") / "sample"
    shutil.copytree(sample_scene_path(), root)
    meta = json.loads((root / "scene.json").read_text())
    test = set(meta["split"]["test_frames"])
    views = [dict(v, frame=f["index"]) for f in meta["frames"] if f["index"] in test for v in f["views"]]
    meta["novel_views"] = [dict(v, shift_ego_m=[0.0, 0.0, 0.0]) for v in views]
    meta["novel_views"] += [dict(v, group="again") for v in views]  # a group named in scene.json
    (root / "scene.json").write_text(json.dumps(meta))
    return root


@pytest.fixture(scope="module")
def checkpoint(scene_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "baseline"
    args = [
        "train",
        str(scene_dir),
        "--scale",
        "0.25",
        "--out",
        str(out),
        "--iterations",
        "2",
        "--no-progress",
    ]
    args += ["--init.max-points", "400", "--init.voxel-size", "1.0", "--init.sh-degree", "0"]
    assert cli(args) == 0
    return out / "checkpoint.pt"


class TestNovelViewsBenchmark:
    def test_evaluate_and_losses(self, bench, scene_dir, checkpoint):
        scene = load_scene(scene_dir, scale=0.25)
        model, raster, step = bench.load_variant(checkpoint)
        assert step == 2
        res = bench.evaluate_views(model, scene, raster)
        assert list(res) == ["test", "shift+0.0", "again"]
        loss = bench.losses(res)
        assert list(loss) == ["shift+0.0", "again", "mean"]
        # the novel views are the test views again: nothing is lost
        assert all(v == 0 for v in loss["mean"].values() if v is not None)
        assert loss["mean"]["PSNR"] == 0 and loss["mean"]["AbsRel all"] == 0
        md = bench.tables({"baseline": res, "vadgs": res})
        assert md.count("| VAD-GS |") == 6 and "AbsRel facade>5m" in md

    def test_depth_normals_of_a_plane(self, bench):
        K = torch.tensor([[10.0, 0, 4.5], [0, 10.0, 3.5], [0, 0, 1]])
        n = bench.depth_normals(torch.full((8, 10), 5.0), K)
        torch.testing.assert_close(
            n[:, 1:-1, 1:-1], torch.tensor([0.0, 0, -1])[:, None, None].expand(3, 6, 8)
        )
        assert float(n[:, 0].abs().sum()) == 0  # border: unknown

    def test_main_writes_json_table_figure(self, bench, scene_dir, checkpoint, tmp_path):
        fig = tmp_path / "fig.png"
        args = [str(checkpoint.parent.parent), "--variants", "baseline", "--scene", str(scene_dir)]
        args += ["--scale", "0.25", "--out", str(tmp_path / "out"), "--figure", str(fig), "--threads", "2"]
        assert bench.main(args) == 0
        data = json.loads((tmp_path / "out" / "baseline.json").read_text())
        assert data["step"] == 2 and set(data["views"]) == {"test", "shift+0.0", "again"}
        assert "| baseline | test (6) |" in (tmp_path / "out" / "table.md").read_text()
        assert fig.is_file() and fig.stat().st_size > 1000
        with pytest.raises(SystemExit):
            bench.main(["--scene", str(scene_dir), "--checkpoint", "nameonly"])
