"""Content validation of scenes (vadgs.data.validate): one test per fault of the reliability trial.

Each test breaks one thing in a copy of the bundled sample scene and checks that loading (or
``validate_scene``, for what only a full decode finds) fails with a message that names the file
or the scene.json field, the expected and the actual.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from vadgs.checks import check_intrinsics, checking
from vadgs.data import ValidationReport, load_scene, sample_scene_path, validate_scene
from vadgs.data.checks import check_rigid
from vadgs.data.scene import npz_headers

from .sample_copy import copy_sample_scene


class TestValidateSceneSmoke:
    def test_sample_is_clean(self):
        report = validate_scene(sample_scene_path(), full=True)
        assert isinstance(report, ValidationReport) and report.ok and report.full
        items = [r.item for r in report.rows]
        assert {"poses", "images", "depth", "instances", "lidar", "split.test_frames"} <= set(items)
        table = report.format_table()
        assert table.splitlines()[0].split() == ["status", "check", "file", "message"]
        report.raise_if_errors()  # no-op

    def test_on_a_loaded_scene_at_half_scale(self):
        assert validate_scene(load_scene(sample_scene_path(), scale=0.5)).ok

    def test_bad_level(self):
        with pytest.raises(ValueError, match="validate: expected"):
            load_scene(sample_scene_path(), validate="some")

    def test_unparsable_scene_is_one_error_row(self, tmp_path):
        report = validate_scene(tmp_path)
        assert not report.ok and report.rows[0].item == "scene.json"


class TestCorruptFiles:
    def test_corrupt_png(self, tmp_path):
        root = copy_sample_scene(tmp_path)
        (root / "images/front/019.png").write_bytes(b"\x89PNG garbage")
        with pytest.raises(ValueError, match=r"images/front/019\.png.*not a decodable image"):
            load_scene(root)

    def test_zero_byte_png(self, tmp_path):
        root = copy_sample_scene(tmp_path)
        (root / "instances/front_left/017.png").write_bytes(b"")
        with pytest.raises(ValueError, match=r"instances/front_left/017\.png.*empty file \(0 bytes\)"):
            load_scene(root)

    def test_truncated_png_found_by_full_check(self, tmp_path):
        root = copy_sample_scene(tmp_path)
        p = root / "images/front/019.png"
        p.write_bytes(p.read_bytes()[:400])  # the header survives, the pixel data does not
        load_scene(root)  # headers only: loads
        report = validate_scene(root, full=True)
        assert [r.file for r in report.errors] == [str(p)]
        with pytest.raises(ValueError, match=r"019\.png"):
            load_scene(root, validate="full")
        scene = load_scene(root)
        with pytest.raises(ValueError, match=r"019\.png: not a decodable image"):
            scene.load_images([scene.view_id(19, "front")])

    def test_image_of_the_wrong_size(self, tmp_path):
        root = copy_sample_scene(tmp_path)
        Image.new("RGB", (200, 100)).save(root / "images/front_right/020.png")
        with pytest.raises(
            ValueError, match=r"020\.png: image: expected size 240x144 \(W x H\), got 200x100"
        ):
            load_scene(root)

    def test_image_of_the_wrong_size_at_half_scale(self, tmp_path):
        root = copy_sample_scene(tmp_path)
        Image.new("RGB", (200, 100)).save(root / "images/front_right/020.png")
        with pytest.raises(ValueError, match=r"expected size 240x144 \(the scene's 120x72 at scale 0.5\)"):
            load_scene(root, scale=0.5)

    def test_corrupt_depth_npz(self, tmp_path):
        root = copy_sample_scene(tmp_path)
        (root / "depth/front/016.npz").write_bytes(b"not a zip")
        with pytest.raises(ValueError, match=r"depth/front/016\.npz.*not a readable \.npz"):
            load_scene(root)

    def test_depth_of_the_wrong_shape_or_key(self, tmp_path):
        root = copy_sample_scene(tmp_path)
        np.savez(root / "depth/front/016.npz", depth=np.zeros((10, 10), np.float16))
        np.savez(root / "depth/front/017.npz", z=np.zeros((144, 240), np.float16))
        report = validate_scene(root)
        msgs = {Path(r.file).name: r.message for r in report.errors}
        assert "expected shape (H, W) = (144, 240), got (10, 10)" in msgs["016.npz"]
        assert "expected key 'depth'" in msgs["017.npz"]

    def test_nan_depth_of_a_test_view_fails_at_load(self, tmp_path):
        # test views' depth is read only after training: it is decoded at load
        root = copy_sample_scene(tmp_path)
        d = np.full((144, 240), np.nan, np.float16)
        np.savez_compressed(root / "depth/front/018.npz", depth=d)  # frame 18 is a test frame
        with pytest.raises(
            ValueError, match=r"018\.npz: depth: expected finite values, got 34560 non-finite"
        ):
            load_scene(root)

    def test_nan_depth_of_a_train_view_found_by_full_check_and_on_read(self, tmp_path):
        root = copy_sample_scene(tmp_path)
        d = np.zeros((144, 240), np.float16)
        d[0, 0] = np.inf
        np.savez_compressed(root / "depth/front/016.npz", depth=d)
        scene = load_scene(root)
        assert not validate_scene(root, full=True).ok
        with pytest.raises(ValueError, match=r"016\.npz: depth: expected finite"):
            scene.load_depths([scene.view_id(16, "front")])

    def test_zero_byte_lidar(self, tmp_path):
        root = copy_sample_scene(tmp_path)
        (root / "lidar/020.npz").write_bytes(b"")
        with pytest.raises(ValueError, match=r"lidar/020\.npz.*empty file \(0 bytes\)"):
            load_scene(root)

    def test_nan_lidar(self, tmp_path):
        root = copy_sample_scene(tmp_path)
        with np.load(root / "lidar/020.npz") as z:
            arrays = dict(z)
        arrays["points"][5] = np.nan
        np.savez_compressed(root / "lidar/020.npz", **arrays)
        scene = load_scene(root)  # headers only
        report = validate_scene(root, full=True)
        assert [Path(r.file).name for r in report.errors] == ["020.npz"]
        assert "1 non-finite points" in report.errors[0].message
        with pytest.raises(ValueError, match=r"020\.npz: points: expected finite values"):
            scene.lidar(20)

    def test_lidar_of_the_wrong_shape(self, tmp_path):
        root = copy_sample_scene(tmp_path)
        np.savez(root / "lidar/020.npz", points=np.zeros((5, 2), np.float32))
        with pytest.raises(ValueError, match=r"020\.npz: lidar \(frame 20\): points: expected \(N, 3\)"):
            load_scene(root)

    def test_all_lidar_empty(self, tmp_path):
        root = copy_sample_scene(tmp_path)
        for p in (root / "lidar").glob("*.npz"):
            np.savez(p, points=np.zeros((0, 3), np.float32), instance=np.zeros(0, np.uint16))
        with pytest.raises(ValueError, match=r"scene .*: .*all 8 LiDAR files are empty \(0 points\)"):
            load_scene(root)

    def test_one_empty_lidar_is_fine(self, tmp_path):
        root = copy_sample_scene(tmp_path)
        np.savez(root / "lidar/020.npz", points=np.zeros((0, 3), np.float32))
        assert load_scene(root).lidar(20).points.shape == (0, 3)


class TestMetadata:
    @pytest.mark.parametrize(
        ("edit", "match"),
        [
            (
                lambda m: m["cameras"]["front"].update(K=[[0, 0, 120], [0, 0, 72], [0, 0, 1]]),
                r"cameras.front.K: expected positive focal lengths K\[..., 0, 0\], K\[..., 1, 1\], "
                r"got fx=0, fy=0$",
            ),
            (
                lambda m: m["cameras"]["front"].update(K=[[192, 0, 120], [0, 192, 72], [0, 0, 0]]),
                r"cameras.front.K: expected \[\[fx, s, cx\], \[0, fy, cy\], \[0, 0, 1\]\], got \[\[192.0, ",
            ),
            (
                lambda m: m["cameras"]["front"].update(width="abc"),
                r"scene.json: cameras.front.width: expected an integer, got 'abc'",
            ),
            (
                lambda m: m["frames"][3].update(index="abc"),
                r"scene.json: frames\[3\].index: expected an integer, got 'abc'",
            ),
            (
                lambda m: m["frames"][3].update(timestamp="noon"),
                r"scene.json: frames\[3\].timestamp: expected a finite number, got 'noon'",
            ),
            (
                lambda m: m["instances"][0].update(dynamic="yes"),
                r"scene.json: instances\[0\].dynamic: expected true or false, got 'yes'",
            ),
            (
                lambda m: m["frames"][1]["views"][0].update(camera=3),
                r"scene.json: frames\[1\].views\[0\].camera: expected a non-empty string, got 3",
            ),
            (lambda m: m["split"].update(test_frames=[18, 18]), r"split.test_frames: .*duplicates \[18\]"),
            (
                lambda m: m["split"].update(test_frames=[18, 99]),
                r"split.test_frames: frame\(s\) \[99\] not in the scene \(it has 8 frames, 16..23\)",
            ),
            (
                lambda m: m["split"].update(train_frames=[16, "x"]),
                r"split.train_frames\[1\]: expected an integer",
            ),
            (lambda m: m["frames"][1].update(index=16), r"frames\[\]\.index: expected unique frame indices"),
        ],
    )
    def test_bad_field(self, tmp_path, edit, match):
        with pytest.raises(ValueError, match=match):
            load_scene(copy_sample_scene(tmp_path, edit), validate="none")

    @pytest.mark.parametrize(
        ("change", "match"),
        [
            (lambda T: T[:3, :3] * 1.05, r"max \|R\^T R - I\| = 0.10"),  # scaled
            (lambda T: T[:3, :3] @ np.array([[1, 0.2, 0], [0, 1, 0], [0, 0, 1]]), r"max \|R\^T R - I\|"),
            (lambda T: T[:3, :3] @ np.diag([1, 1, -1]), r"det \+1, got det -1"),  # reflection
        ],
        ids=["scaled", "sheared", "reflected"],
    )
    def test_non_rigid_pose(self, tmp_path, change, match):
        def edit(m: dict) -> None:
            T = np.array(m["frames"][2]["views"][1]["cam_to_world"])
            T[:3, :3] = change(T)
            m["frames"][2]["views"][1]["cam_to_world"] = T.tolist()

        with pytest.raises(
            ValueError, match=r"scene.json: frames\[2\].views\[1\].cam_to_world: expected .*" + match
        ):
            load_scene(copy_sample_scene(tmp_path, edit))

    def test_pose_last_row(self, tmp_path):
        def edit(m: dict) -> None:
            m["frames"][0]["ego_to_world"][3] = [0, 0, 1, 1]

        with pytest.raises(ValueError, match=r"frames\[0\].ego_to_world: expected last row \(0, 0, 0, 1\)"):
            load_scene(copy_sample_scene(tmp_path, edit))

    def test_track_pose(self, tmp_path):
        def edit(m: dict) -> None:
            key = next(iter(m["tracks"][0]["object_to_world"]))
            T = np.array(m["tracks"][0]["object_to_world"][key])
            T[:3, :3] *= 2
            m["tracks"][0]["object_to_world"][key] = T.tolist()

        with pytest.raises(ValueError, match=r"tracks\[0\].object_to_world\[\d+\]: expected a rigid"):
            load_scene(copy_sample_scene(tmp_path, edit))

    def test_unknown_frame_lidar_message(self):
        scene = load_scene(sample_scene_path())
        with pytest.raises(FileNotFoundError, match="no such frame"):
            scene.lidar(99)


class TestHelpers:
    def test_check_intrinsics(self):
        check_intrinsics(torch.tensor([[100.0, 0, 5], [0, 90, 4], [0, 0, 1]]), pinhole=True)
        with pytest.raises(ValueError, match="K: expected finite"):
            check_intrinsics(torch.full((3, 3), float("nan")), pinhole=True)
        with pytest.raises(ValueError, match=r"expected shape \(\*, 3, 3\), got \(4, 4\)"):
            check_intrinsics(torch.eye(4), pinhole=True)
        with pytest.raises(
            ValueError, match=r"^K: expected \[\[fx, s, cx\], \[0, fy, cy\], \[0, 0, 1\]\], got "
        ):
            check_intrinsics(torch.tensor([[100.0, 0, 5], [1e-3, 90, 4], [0, 0, 1]]), pinhole=True)
        check_intrinsics(torch.tensor([[100.0, 0, 5], [1e-3, 90, 4], [0, 0, 1]]))  # the form only when asked
        K = torch.tensor([[100.0, 0, 5], [0, 90, 4], [0, 0, 1]]).repeat(2, 1, 1)
        K[1, 1, 1] = -1.0
        with pytest.raises(
            ValueError, match=r"^k: expected positive focal lengths .*, got fx=100, fy=-1 at \(1,\)$"
        ):
            check_intrinsics(K, "k")

    def test_a_file_K_is_checked_with_value_checks_off(self):
        # VADGS_CHECKS / checking(False) skip the value checks of tensors the caller vouches for,
        # never those of a K read from a file or given by a user (pinhole=True)
        K = torch.tensor([[0.0, 0, 5], [0, 90, 4], [0, 0, 1]])
        with checking(False):
            check_intrinsics(K)  # a value check: off
            with pytest.raises(ValueError, match=r"^K: expected positive focal lengths .*, got fx=0, fy=90$"):
                check_intrinsics(K, pinhole=True)
            with pytest.raises(ValueError, match=r"^K: expected \[\[fx, s, cx\]"):
                check_intrinsics(torch.tensor([[9.0, 0, 5], [1.0, 9, 4], [0, 0, 1]]), pinhole=True)

    def test_check_rigid_tolerance(self):
        T = torch.eye(4)
        T[:3, :3] *= 1 + 1e-5  # rounding in a file: accepted
        check_rigid(T, "pose")
        with pytest.raises(ValueError, match="pose"):
            check_rigid(T, "pose", tol=1e-6)

    def test_npz_headers(self, tmp_path):
        np.savez_compressed(tmp_path / "a.npz", x=np.zeros((3, 4), np.float16))
        assert npz_headers(tmp_path / "a.npz") == {"x": ((3, 4), np.dtype(np.float16))}
        (tmp_path / "b.npz").write_bytes(b"")
        with pytest.raises(ValueError, match=r"b\.npz: not a readable \.npz archive \(an empty file"):
            npz_headers(tmp_path / "b.npz")
