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
