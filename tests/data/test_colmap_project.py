"""Opening a COLMAP project (:mod:`vadgs.data.colmap_project`): undistortion, its cache, the recipe."""

from __future__ import annotations

import json

import pytest
import torch

from vadgs.data import colmap_project
from vadgs.data.colmap_model import distorted_cameras
from vadgs.data.colmap_project import open_colmap_project, reopen_colmap_project, undistort_colmap

from .colmap_sample import write_sample_colmap

pycolmap = pytest.importorskip("pycolmap")


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    root = tmp_path_factory.mktemp("colmap") / "proj"
    return root, write_sample_colmap(root)


class TestUndistortion:
    @pytest.mark.parametrize("model", ["SIMPLE_RADIAL", "OPENCV"])
    def test_distorted_project_is_undistorted(self, tmp_path, model):
        root = tmp_path / "proj"
        write_sample_colmap(root, model=model, k=0.05, n_points=300)
        before = sorted(p.relative_to(root) for p in root.rglob("*"))
        assert distorted_cameras(root / "sparse" / "0") == [f"1 {model}", f"2 {model}", f"3 {model}"]
        with pytest.raises(ValueError, match="distorted"):
            open_colmap_project(root)
        colmap, recipe = open_colmap_project(root, undistort_dir=tmp_path / "run" / "undistorted")
        assert recipe["undistorted"] == distorted_cameras(root / "sparse" / "0")
        assert recipe["path"] == str((tmp_path / "run" / "undistorted" / "sparse").resolve())
        assert distorted_cameras(recipe["path"]) == []  # PINHOLE now
        assert sorted(p.relative_to(root) for p in root.rglob("*")) == before  # the input is untouched
        scene = colmap.scene
        assert scene.num_views == 24 and len(scene.test_views) == 3 and scene.name == "proj"
        assert scene.load_images([0]).shape[1] == 3
        # undistortion keeps the poses and the points: the normalisation is the same as without it
        pin = tmp_path / "pin"
        write_sample_colmap(pin, n_points=300)
        _, pin_recipe = open_colmap_project(pin)
        torch.testing.assert_close(torch.tensor(recipe["transform"]), torch.tensor(pin_recipe["transform"]))
        # a second call replaces its own output; a foreign folder is refused
        open_colmap_project(root, undistort_dir=tmp_path / "run" / "undistorted")
        (tmp_path / "other").mkdir()
        (tmp_path / "other" / "keep.txt").write_text("x")
        with pytest.raises(ValueError, match="refusing to replace"):
            open_colmap_project(root, undistort_dir=tmp_path / "other")

    def test_pycolmap_is_quiet_unless_asked(self, tmp_path, capfd, monkeypatch):

        root = tmp_path / "proj"
        write_sample_colmap(root, model="OPENCV", k=0.05, n_points=100)
        args = (root / "sparse" / "0", root / "images")
        capfd.readouterr()
        undistort_colmap(*args, tmp_path / "quiet")
        assert "Undistorting image" not in capfd.readouterr().err
        monkeypatch.setattr(colmap_project, "COLMAP_LOG_LEVEL", 0)  # what ``vadgs --debug`` sets
        undistort_colmap(*args, tmp_path / "loud")
        assert capfd.readouterr().err.count("Undistorting image") == 24

    def test_recipe_reopens_identically(self, project):
        root, _ = project
        colmap, recipe = open_colmap_project(root, scale=0.5)
        assert recipe["undistorted"] == [] and recipe["test_every"] == 8
        again = reopen_colmap_project(json.loads(json.dumps(recipe)))  # as stored in a checkpoint
        assert again.scene.name == colmap.scene.name
        assert again.scene.test_views == colmap.scene.test_views
        for a, b in zip(again.scene.views, colmap.scene.views):
            assert torch.equal(a.cam_to_world, b.cam_to_world)
        for k, info in colmap.scene.cameras_info.items():
            assert torch.equal(again.scene.cameras_info[k].K, info.K)
            assert again.scene.cameras_info[k].image_size == info.image_size == (72, 120)

    def test_exception(self, tmp_path):
        with pytest.raises(FileNotFoundError, match="no COLMAP model"):
            open_colmap_project(tmp_path)
        write_sample_colmap(tmp_path / "p", n_points=50, link_images=False)
        with pytest.raises(FileNotFoundError, match="no images/ folder"):
            open_colmap_project(tmp_path / "p")
        with pytest.raises(FileNotFoundError, match="images_dir"):
            open_colmap_project(tmp_path / "p", images_dir=tmp_path / "nope")
