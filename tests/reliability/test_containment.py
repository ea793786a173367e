"""Issue 33, containment: every file vadgs writes stays under the folder the user named, and a
scene's metadata cannot make vadgs read files outside the scene folder without an opt-in."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import pytest
import torch

from tests.data.sample_copy import copy_sample_scene
from vadgs.data import load_scene
from vadgs.data._json import ALLOW_OUTSIDE_ENV
from vadgs.data.export import export_scene
from vadgs.io import check_inside, safe_filename
from vadgs.train.init import InitConfig, init_gaussians
from vadgs.train.results.evaluate import save_test_panels

EVIL = "../../escaped"


def _tree(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def _rename_camera(meta: dict, old: str = "front", new: str = EVIL) -> None:
    meta["cameras"][new] = meta["cameras"].pop(old)
    for f in meta["frames"]:
        for v in f["views"]:
            if v["camera"] == old:
                v["camera"] = new


class TestNamesFromData:
    @pytest.mark.parametrize(
        ("name", "expected"),
        [
            ("front_left", "front_left"),
            ("../../etc/passwd", "__.._etc_passwd"),
            ("/abs/path", "_abs_path"),
            ("..", "_"),
            (".hidden", "_hidden"),
            ("a\\b\0c d", "a_b_c_d"),
            ("", "_"),
        ],
    )
    def test_safe_filename(self, name, expected):
        out = safe_filename(name)
        assert out == expected
        assert "/" not in out and not out.startswith(".") and Path("/r", out).parent == Path("/r")

    def test_check_inside_follows_symlinks(self, tmp_path):
        (tmp_path / "run").mkdir()
        (tmp_path / "run" / "link").symlink_to(tmp_path)
        assert check_inside(tmp_path / "run" / "a.png", tmp_path / "run", "x") == tmp_path / "run" / "a.png"
        with pytest.raises(ValueError, match=r"x: .* resolves to .*, outside"):
            check_inside(tmp_path / "run" / "link" / "a.png", tmp_path / "run", "x")
        with pytest.raises(ValueError, match="outside"):
            check_inside(tmp_path / "run" / ".." / "a.png", tmp_path / "run", "x")

    def test_render_panels_of_a_camera_named_dot_dot(self, tmp_path):
        """A camera named ``../../escaped`` wrote its panels two folders up (issue 33, case 2)."""
        root = copy_sample_scene(tmp_path / "data", _rename_camera)
        scene = load_scene(root, scale=0.25)
        model = init_gaussians(
            scene, InitConfig(voxel_size=1.0, max_points=300, max_object_points=30, sh_degree=0)
        )
        view = next(v.index for v in scene.views if v.camera == EVIL and v.frame in scene.test_frames)
        out = tmp_path / "run" / "renders"
        before = _tree(tmp_path)
        paths = save_test_panels(model, scene, out, [view])
        assert [p.parent for p in paths] == [out] and paths[0].name.startswith(
            f"view{view:03d}___.._escaped_"
        )
        assert _tree(tmp_path) - before == {"run", "run/renders", f"run/renders/{paths[0].name}"}

    def test_exported_scene_of_a_camera_named_dot_dot(self, tmp_path):
        root = copy_sample_scene(tmp_path / "data", _rename_camera)
        scene = load_scene(root, scale=0.25)
        out = tmp_path / "export"
        export_scene(scene, out, lidar=False)
        assert not (tmp_path / "escaped").exists() and not (tmp_path.parent / "escaped").exists()
        again = load_scene(out)  # the exported scene.json names the safe folder, the camera keeps its name
        assert EVIL in again.cameras_info and again.num_views == scene.num_views
        assert all(check_inside(v.image, out, "image") for v in again.views)


class TestSceneFilesOutsideTheScene:
    def _scene_reading(self, tmp_path, rel_of) -> Path:
        def edit(meta):
            view = meta["frames"][0]["views"][0]
            view["image"] = rel_of(view["image"])

        return copy_sample_scene(tmp_path, edit)

    @pytest.mark.parametrize("kind", ["dotdot", "absolute"])
    def test_refused_unless_allowed(self, tmp_path, kind, monkeypatch):
        monkeypatch.delenv(ALLOW_OUTSIDE_ENV, raising=False)
        outside = tmp_path / "outside.png"

        def rel_of(image):
            shutil.copy(tmp_path / "scene" / image, outside)
            return "../outside.png" if kind == "dotdot" else str(outside)

        root = self._scene_reading(tmp_path, rel_of)
        with pytest.raises(
            ValueError, match=r"scene.json: frames\[0\].views\[0\].image: expected a path inside"
        ):
            load_scene(root)
        assert load_scene(root, allow_outside=True).views[0].image.resolve() == outside.resolve()
        monkeypatch.setenv(ALLOW_OUTSIDE_ENV, "1")
        assert load_scene(root).views[0].image.resolve() == outside.resolve()

    def test_symlink_out_of_the_scene_warns_naming_the_file(self, tmp_path, monkeypatch):
        monkeypatch.delenv(ALLOW_OUTSIDE_ENV, raising=False)
        root = copy_sample_scene(tmp_path)
        meta = json.loads((root / "scene.json").read_text())
        image = root / meta["frames"][0]["views"][0]["image"]
        secret = tmp_path / "secret.png"
        shutil.move(image, secret)
        image.symlink_to(secret)
        with pytest.warns(UserWarning, match=r"1 file\(s\) outside the folder through symlinks.*secret.png"):
            load_scene(root)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            load_scene(root, allow_outside=True)

    def test_a_view_listed_twice_in_a_frame(self, tmp_path):
        root = copy_sample_scene(
            tmp_path, lambda m: m["frames"][1]["views"].append(m["frames"][1]["views"][0])
        )
        with pytest.raises(
            ValueError, match=r"frames\[1\].views\[3\].camera: camera 'front' already has a view"
        ):
            load_scene(root)

    def test_deeply_nested_json_names_the_file(self, tmp_path):
        (tmp_path / "scene.json").write_text("[" * 100_000 + "]" * 100_000)
        with pytest.raises(ValueError, match=r"scene.json: .*scene.json is nested too deeply"):
            load_scene(tmp_path)


def test_panels_keep_tensors_on_device():
    assert safe_filename(torch.tensor(3).item()) == "3"
