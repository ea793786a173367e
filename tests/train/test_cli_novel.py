from __future__ import annotations

import json
import shutil

import imageio.v2 as imageio
import pytest
from plyfile import PlyData

from vadgs.cli import main
from vadgs.cli._common import lidar_depth_line, metrics_summary
from vadgs.data import load_scene, sample_scene_path


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A 3-step run on a copy of the sample whose test views are repeated as novel views."""
    root = tmp_path_factory.mktemp("scene") / "sample"
    shutil.copytree(sample_scene_path(), root)
    meta = json.loads((root / "scene.json").read_text())
    test = set(meta["split"]["test_frames"])
    meta["novel_views"] = [
        dict(v, frame=f["index"], shift_ego_m=[0.0, 0.0, 0.0]) for f in meta["frames"] if f["index"] in test
        for v in f["views"]
    ]  # fmt: skip
    (root / "scene.json").write_text(json.dumps(meta))
    out = tmp_path_factory.mktemp("run") / "run"
    args = ["train", str(root), "--scale", "0.25", "--out", str(out), "--iterations", "3", "--no-progress"]
    args += ["--init.max-points", "400", "--init.voxel-size", "1.0", "--init.sh-degree", "1"]
    assert main(args) == 0
    return out


class TestCliNovel:
    def test_eval_novel(self, run, capsys):
        assert main(["eval", str(run), "--split", "novel", "--no-progress"]) == 0
        novel = json.loads((run / "eval_novel.json").read_text())
        assert novel["split"] == "novel" and list(novel["groups"]) == ["shift+0.0"]
        said_novel = capsys.readouterr().out
        assert main(["eval", str(run / "checkpoint.pt"), "--no-progress"]) == 0
        test = json.loads((run / "eval.json").read_text())
        # the "novel" views are the test views again: the same numbers
        assert novel["groups"]["shift+0.0"]["psnr"] == test["psnr"]
        assert novel["groups"]["shift+0.0"]["depth"] == test["depth"]
        # depth against the frames' own LiDAR sweeps, recorded and said in a line of its own
        lidar = test["depth"]["lidar"]
        assert lidar["pixels"] > 1000 and 0 < lidar["absrel"] < 1
        line = lidar_depth_line(lidar)
        assert line.startswith("depth vs the test frames' LiDAR AbsRel ")
        assert f"\n{line}\n" in capsys.readouterr().out
        assert f"\nshift+0.0: {line}\n" in said_novel
        metrics = json.loads((run / "metrics.json").read_text())
        assert metrics["test"]["depth"] == test["depth"] and line in metrics_summary(metrics)

    def test_eval_novel_without_novel_views(self, tmp_path, capsys):
        out = tmp_path / "r"
        args = [
            "train",
            "--sample",
            "--scale",
            "0.25",
            "--out",
            str(out),
            "--iterations",
            "1",
            "--no-progress",
        ]
        args += ["--init.max-points", "200", "--init.voxel-size", "1.0", "--init.sh-degree", "0"]
        assert main(args) == 0
        assert main(["eval", str(out), "--split", "novel", "--no-progress"]) == 2
        assert "no novel views" in capsys.readouterr().err

    def test_render_video(self, run, tmp_path):
        video = tmp_path / "v.mp4"
        args = ["render", str(run), "--video", str(video), "--trajectory", "shift:2", "--frames-between", "1"]
        assert main([*args, "--camera", "front_left", "--fps", "4", "--no-progress"]) == 0
        with imageio.get_reader(video, format="FFMPEG") as reader:
            frames = [f for f in reader]
        assert len(frames) == 15 and frames[0].shape == (36 + 4, 180, 3)  # + the timeline bar
        assert main(["render", str(run), "--video", str(video), "--trajectory", "spiral"]) == 2  # no such one

    def test_export(self, run, tmp_path):
        scene = load_scene(sample_scene_path(), scale=0.25)
        frame = scene.frames[3].index
        assert main(["export", str(run), "--frame", str(frame), "--out", str(tmp_path), "--inria"]) == 0
        ply = tmp_path / "point_cloud" / "iteration_3" / "point_cloud.ply"
        assert PlyData.read(str(ply))["vertex"].count > 0
        assert (tmp_path / "cameras.json").is_file() and (tmp_path / "cfg_args").is_file()
        assert (tmp_path / "sky.png").is_file()
        assert main(["export", str(run)]) == 0  # the first frame, into RUN/export/frame<F>
        first = scene.frames[0].index
        assert (run / "export" / f"frame{first:03d}" / f"world_frame{first:03d}.ply").is_file()
        assert main(["export", str(run), "--frame", "999"]) == 2

    def test_export_up_axis(self, run, tmp_path, capsys):
        """``--up -y``: the z-up export's points with their up on -y (y, z) -> (-z, y), exactly."""
        assert main(["export", str(run), "--out", str(tmp_path / "z")]) == 0
        assert main(["export", str(run), "--out", str(tmp_path / "y"), "--up", "-y"]) == 0
        assert "-y up) and" in capsys.readouterr().out
        a, b = (PlyData.read(str(next((tmp_path / d).glob("*.ply"))))["vertex"] for d in ("z", "y"))
        assert (b["x"] == a["x"]).all() and (b["y"] == -a["z"]).all() and (b["z"] == a["y"]).all()
        assert main(["export", str(run), "--out", str(tmp_path / "i"), "--inria", "--up", "y"]) == 2
        assert "--up y: not with --inria" in capsys.readouterr().err
