import json

from vadgs.cli import main


class TestVisibilityCommand:
    def test_sample_scene(self, tmp_path):
        assert main(["visibility", "--out", str(tmp_path)]) == 0
        metrics = json.loads((tmp_path / "visibility.json").read_text())
        pngs = list(tmp_path.glob("visibility_view*.png"))
        assert len(pngs) == 1 and pngs[0].stat().st_size > 10_000
        assert metrics["voxels"] > 1000
        # a real check of the whole chain (loader, LiDAR accumulation, voxels, z-buffer) against GT depth
        assert metrics["gt_pixels_covered"] > 0.4
        assert metrics["within_one_voxel"] > 0.6

    def test_missing_scene_is_a_clear_error(self, tmp_path, capsys):
        assert main(["visibility", str(tmp_path / "nope"), "--out", str(tmp_path)]) == 2
        assert "no scene.json" in capsys.readouterr().err

    def test_unknown_command(self, capsys):
        assert main(["frobnicate"]) == 2
        assert "vadgs: error: expected a command" in capsys.readouterr().err


class TestColmapProject:
    """``check`` and ``visibility`` take what ``train`` takes: a COLMAP project is detected (issue 32)."""

    def test_visibility_on_a_colmap_project(self, tmp_path):
        import pytest

        pytest.importorskip("pycolmap")
        from tests.data.colmap_sample import write_sample_colmap

        root, out = tmp_path / "proj", tmp_path / "vis"
        made = write_sample_colmap(root, n_points=400)
        assert main(["visibility", str(root), "--out", str(out)]) == 0
        metrics = json.loads((out / "visibility.json").read_text())
        # the voxels come from the SfM points seen by a training view (every 8th image, 016.png, is held out)
        train = {v for v, name in enumerate(made["names"]) if not name.endswith("/016.png")}
        expected = len({p for p, v in made["obs"] if v in train})
        assert metrics["points_from"] == "sfm" and metrics["sfm_points"] == expected
        assert 0 < metrics["voxels"] <= expected and metrics["visible_voxels_in_view"] > 0
        assert metrics["scene"] == "proj" and metrics["camera"].startswith("camera_")
        assert (out / f"visibility_view{metrics['view']:03d}.png").stat().st_size > 5_000

    def test_failed_visibility_leaves_no_folder(self, tmp_path, capsys):
        out = tmp_path / "new" / "vis"
        assert main(["visibility", str(tmp_path / "nope"), "--out", str(out)]) == 2
        assert "neither a benchmark scene (no scene.json) nor a COLMAP model" in capsys.readouterr().err
        assert not (tmp_path / "new").exists()
        assert main(["visibility", "--view", "999", "--out", str(out)]) == 2
        assert "--view: expected < 24" in capsys.readouterr().err and not (tmp_path / "new").exists()

    def test_check_on_a_colmap_project(self, tmp_path, capsys):
        import pytest

        pytest.importorskip("pycolmap")
        from tests.data.colmap_sample import write_sample_colmap

        root = tmp_path / "proj"
        write_sample_colmap(root, n_points=100, crop={"front": (144, 240)})  # images copied, full size
        assert main(["check", str(root)]) == 0
        out = capsys.readouterr().out
        assert "cameras.camera_1.K" in out and "24 files (headers)" in out and "ok (7 checks" in out
        (root / "images/front_left/019.png").unlink()
        (root / "images/front/018.png").write_bytes(b"x")
        assert main(["check", str(root)]) == 1
        out = capsys.readouterr().out
        assert "front_left/019.png  missing file" in out and "front/018.png       not a decodable" in out
        assert "2 error(s)" in out
        # a distorted project is checked as it is (nothing undistorted, nothing written), with a note
        distorted = tmp_path / "dist"
        write_sample_colmap(distorted, model="SIMPLE_RADIAL", k=0.02, n_points=100)
        before = sorted(distorted.rglob("*"))
        assert main(["check", str(distorted)]) == 0
        out = capsys.readouterr().out
        assert out.count("note: COLMAP camera") == 3 and "IGNORES the distortion" in out
        assert sorted(distorted.rglob("*")) == before
