"""Training on COLMAP projects: the CLI end to end, initialisation from SfM points, VAD-GS from tracks."""

from __future__ import annotations

import json

import pytest
import torch

from vadgs.cli import main as _main
from vadgs.data import load_colmap
from vadgs.data.colmap_model import distorted_cameras
from vadgs.data.observations import sfm_observations
from vadgs.train.init import InitConfig, init_gaussians
from vadgs.train.scenes import open_scene
from vadgs.train.vad import build_visibility_index

from ..data.colmap_sample import write_sample_colmap

pycolmap = pytest.importorskip("pycolmap")

FAST = ["--scale", "0.25", "--no-progress", "--init.sh-degree", "0", "--init.max-points", "400"]


def main(argv: list[str]) -> int:
    """``vadgs --threads 1 ...``: one thread, as on a loaded test machine."""
    return _main(argv if argv[0] == "--threads" else ["--threads", "1", *argv])


def _files(root):
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


class TestColmapCli:
    def test_train_eval_render_resume(self, tmp_path, capsys):
        root, out = tmp_path / "proj", tmp_path / "run"
        write_sample_colmap(root, model="SIMPLE_RADIAL", k=0.02, n_points=400)
        before = _files(root)
        assert main(["train", str(root), "--out", str(out), "--iterations", "3", *FAST]) == 0  # detected
        said = capsys.readouterr().out
        assert "undistorted 24 images with pycolmap into" in said and "normalised the COLMAP frame" in said
        ref = json.loads((out / "config.json").read_text())["scene"]
        assert ref["kind"] == "colmap" and ref["test_every"] == 8 and ref["name"] == "proj"
        assert ref["path"] == str((out / "undistorted" / "sparse").resolve())
        assert ref["images"] == str((out / "undistorted" / "images").resolve())
        assert distorted_cameras(ref["path"]) == [] and ref["undistorted"] == [
            "1 SIMPLE_RADIAL",
            "2 SIMPLE_RADIAL",
            "3 SIMPLE_RADIAL",
        ]
        assert len(ref["transform"]) == 4
        assert _files(root) == before  # nothing written into the user's project
        metrics = json.loads((out / "metrics.json").read_text())
        assert metrics["steps"] == 3 and metrics["test"]["num_views"] == 3
        # eval reopens the scene from the reference: the same test views, the same numbers
        assert main(["eval", str(out), "--no-progress"]) == 0
        ev = json.loads((out / "eval.json").read_text())
        assert ev["num_views"] == 3 and ev["psnr"] == pytest.approx(metrics["test"]["psnr"], abs=1e-6)
        assert main(["render", str(out), "--views", "0", "--no-progress"]) == 0
        assert len(list((out / "renders").glob("*.png"))) == 1
        assert main(["train", "--out", str(out), "--resume", "--iterations", "5", "--no-progress"]) == 0
        assert "resuming" in capsys.readouterr().out
        assert json.loads((out / "metrics.json").read_text())["steps"] == 5
        # reopening gives identical cameras, the same split and the SfM points
        a, b = open_scene(ref), open_scene(ref)
        assert [v.image.name for v in (a.views[i] for i in a.test_views)] == ["016.png"] * 3
        assert all(torch.equal(x.cam_to_world, y.cam_to_world) for x, y in zip(a.views, b.views))
        assert a.sfm_points is not None and a.sfm_points.points.shape == (400, 3)

    def test_flags(self, tmp_path, capsys):
        root = tmp_path / "proj"
        write_sample_colmap(root, n_points=100)
        out = tmp_path / "a"
        args = ["train", str(root / "sparse" / "0"), "--colmap-scene", "--out", str(out), "--iterations", "1"]
        assert (
            main([*args, "--test-every", "0", "--no-normalize", "--images", str(root / "images"), *FAST]) == 0
        )
        ref = json.loads((out / "config.json").read_text())["scene"]
        assert ref["test_every"] == 0 and ref["transform"] is None and ref["undistorted"] == []
        assert "test" not in json.loads((out / "metrics.json").read_text())  # no held-out views
        capsys.readouterr()
        bad = [
            (["train", "--sample", "--test-every", "4"], "--test-every: only for a COLMAP scene"),
            (["train", "--sample", "--colmap-scene"], "no COLMAP model"),
            (["train", str(tmp_path / "b"), "--images", str(root)], "neither a benchmark scene"),
            (["train", str(root), "--images", str(tmp_path / "nope")], "--images"),
            (["train", str(root), "--colmap", str(root)], "--colmap: not with a COLMAP scene"),
            (["train", str(root), "--dgp", "--colmap-scene"], "--dgp, --colmap-scene"),
        ]
        (tmp_path / "b").mkdir()
        for argv, message in bad:
            assert main([*argv, "--out", str(tmp_path / "x"), "--no-progress"]) == 2, argv
            err = capsys.readouterr().err
            assert message in err and err.count("\n") == 1, (argv, err)
        assert main(["train", "--out", str(out), "--resume", "--test-every", "2"]) == 2
        assert "--test-every cannot be honoured" in capsys.readouterr().err

    def test_extra_colmap_must_match_the_scene(self, tmp_path, capsys):
        write_sample_colmap(tmp_path / "castle", n_points=50, link_images=False, name_prefix="castle_")
        argv = [
            "train",
            "--sample",
            "--colmap",
            str(tmp_path / "castle"),
            "--out",
            str(tmp_path / "r"),
            *FAST,
        ]
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("vadgs train: error: --colmap ") and err.count("\n") == 1
        assert "24 of 24 registered image names match none" in err and "castle_front/016.png" in err
        assert not (tmp_path / "r" / "metrics.json").exists()


@pytest.fixture(scope="module")
def colmap(tmp_path_factory):
    root = tmp_path_factory.mktemp("sfm") / "proj"
    syn = write_sample_colmap(root, n_points=600)
    return syn, load_colmap(root / "sparse" / "0", scale=0.25, test_every=8)


class TestSfmScene:
    def test_init_from_sfm_points(self, colmap):
        _, (scene, points) = colmap
        model = init_gaussians(scene, InitConfig(voxel_size=0.0, sh_degree=0))
        assert model.num_gaussians == 600 and model.track_ids == []
        torch.testing.assert_close(model.params["means"].detach(), points.points)

    def test_visibility_sets_are_the_track_table(self, colmap):
        syn, (scene, points) = colmap
        # the loaded view of each written (sample) view, by name
        by_name = {str(v.image).split("/images/")[-1]: v.index for v in scene.views}
        loaded_view = {i: by_name[n] for i, n in enumerate(syn["names"])}
        # point order: load_colmap sorts by COLMAP id (written in order 1..P)
        assert points.point_ids.tolist() == list(range(1, 601))
        for frames, allowed in ((None, set(scene.train_views)), ([f.index for f in scene.frames], None)):
            index = build_visibility_index(scene, voxel_size=0.5, frames=frames)
            grid = index.grid
            kept, _ = sfm_observations(scene, frames)
            obs = {(j, loaded_view[v]) for j, v in syn["obs"]}
            if allowed is not None:
                obs = {(j, v) for j, v in obs if v in allowed}
            observed = sorted({j for j, _ in obs})
            assert kept.shape[0] == len(observed) == grid.point_to_voxel.shape[0]
            want: dict[int, set[int]] = {int(m): set() for m in grid.point_to_voxel.unique()}
            vox_of = {j: int(grid.point_to_voxel[k]) for k, j in enumerate(observed)}
            for j, v in obs:
                want[vox_of[j]].add(v)
            got = {m: set(grid.views_of(m).tolist()) for m in range(len(grid))}
            assert got == want
            if allowed is not None:
                assert not set(grid.vis_views.tolist()) & set(scene.test_views)
        assert index.track_grids == {} and index.derives_instances

    def test_no_points_no_lidar(self, colmap):
        import dataclasses

        _, (scene, _) = colmap
        with pytest.raises(ValueError, match="no LiDAR and no SfM points"):
            build_visibility_index(dataclasses.replace(scene, sfm_points=None))

    def test_vad_event_on_colmap_scene(self, tmp_path):
        root, out = tmp_path / "proj", tmp_path / "vad"
        write_sample_colmap(root, n_points=1500)
        # 21 training views; one cycle per event: the first at step 20, before 90 % of 24 steps
        argv = ["train", str(root), "--out", str(out), "--iterations", "24", "--vad"]
        argv += ["--vad.every-cycles", "1", "--vad.max-instances", "1", "--vad.references", "1"]
        argv += ["--vad.reconstruct.max-crop", "48", *FAST]
        assert main(argv) == 0
        events = json.loads((out / "metrics.json").read_text())["vad_events"]
        assert len(events) == 1 and events[0]["step"] == 20
        ev = events[0]
        assert ev["tested"] > 0 and ev["flagged_instances"] > 0
        assert [i["class"] for i in ev["instances"]] == ["static"]  # a derived ground cell
        # MVS on the SfM-only scene (points thinned to one per cell of their spacing)
        assert ev["instances"][0]["reason"] == "ok" and ev["added"] > 50
        logged = [
            json.loads(line)["event"]
            for line in (out / "log.jsonl").read_text().splitlines()
            if "event" in line
        ]
        assert len(logged) == 1 and logged[0]["added"] == ev["added"]

    def test_vad_on_a_rig_of_two_image_sizes(self, tmp_path):
        """Cameras of different sizes (front_left cropped to 120x200): an event adds Gaussians."""
        root, out = tmp_path / "proj", tmp_path / "vad"
        write_sample_colmap(root, n_points=1500, crop={"front_left": (120, 200)})
        sizes = {
            (c.height, c.width) for c in pycolmap.Reconstruction(str(root / "sparse" / "0")).cameras.values()
        }
        assert sizes == {(120, 200), (144, 240)}
        argv = ["train", str(root), "--out", str(out), "--iterations", "24", "--vad"]
        argv += ["--vad.every-cycles", "1", "--vad.references", "2", "--vad.work-budget", "None"]
        argv += ["--vad.reconstruct.max-crop", "48", *FAST]
        assert main(argv) == 0
        (event,) = json.loads((out / "metrics.json").read_text())["vad_events"]
        assert event["flagged_instances"] > 0 and event["added"] > 50
        scene = open_scene(json.loads((out / "config.json").read_text())["scene"])
        refs = {scene.image_size(r) for e in event["instances"] if e["added"] for r in e["references"]}
        assert refs == {(30, 50), (36, 60)}  # Gaussians added from references of both sizes
