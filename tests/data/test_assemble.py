"""vadgs.data.assemble: the last step of every loader (files, LiDAR loader, Scene, content checks)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from vadgs.data.assemble import (
    assemble_scene,
    check_scale,
    check_validate_level,
    file_image_loader,
    pinhole_camera,
)
from vadgs.data.scene import CameraInfo, FrameInfo, LidarFrame, Scene, ViewInfo
from vadgs.data.undistort import ImageUndistorter
from vadgs.geometry.camera import scale_intrinsics


def _parts(tmp_path, lidar_frames=(0, 1, 2)):
    cams = {"cam": CameraInfo("cam", torch.tensor([[2.0, 0, 0.5], [0, 2, 0.5], [0, 0, 1]]), (2, 2))}
    frames, views = [], []
    for i in range(3):
        img = tmp_path / f"{i}.png"
        img.write_bytes(b"")
        lid = tmp_path / f"{i}.npz" if i in lidar_frames else None
        if lid is not None:
            np.savez(lid, points=np.full((2, 3), float(i), dtype=np.float32))
        frames.append(FrameInfo(10 + i, float(i), None, (i,), lid))
        views.append(ViewInfo(i, 10 + i, "cam", float(i), torch.eye(4), img))
    return {"name": "t", "root": tmp_path, "cameras_info": cams, "frames": frames, "views": views}


def _read(frame: int, path) -> LidarFrame:
    with np.load(path) as z:
        pts = torch.from_numpy(z["points"])
    return LidarFrame(pts, torch.zeros(len(pts), dtype=torch.int64), torch.zeros(3))


class TestAssembleScene:
    def test_smoke(self, tmp_path):
        scene = assemble_scene("scene t", **_parts(tmp_path), test_frames=[11], read_lidar=_read)
        assert isinstance(scene, Scene)
        assert scene.train_frames == [10, 12] and scene.test_frames == [11]
        assert scene.instances == {} and scene.tracks == {} and scene.scale == 1.0
        assert scene.lidar(12).points.tolist() == [[2.0] * 3] * 2

    def test_explicit_train_frames_and_lidar_loader(self, tmp_path):
        def loader(frame: int) -> LidarFrame:
            return LidarFrame(torch.zeros(1, 3), torch.zeros(1, dtype=torch.int64), torch.zeros(3))

        scene = assemble_scene(
            "scene t", **_parts(tmp_path), test_frames=[], train_frames=[10], lidar_loader=loader, scale=2
        )
        assert scene.train_frames == [10] and scene.lidar_loader is loader and scene.scale == 2.0

    def test_no_lidar_files(self, tmp_path):
        scene = assemble_scene("scene t", **_parts(tmp_path, ()), test_frames=[], read_lidar=_read)
        assert scene.lidar_loader is None

    def test_missing_files(self, tmp_path):
        parts = _parts(tmp_path)
        (tmp_path / "1.png").unlink()
        (tmp_path / "2.npz").unlink()
        with pytest.raises(
            FileNotFoundError, match=r"^scene t: 2 referenced file\(s\) missing, e\.g\. \[.*1\.png"
        ):
            assemble_scene("scene t", **parts, test_frames=[])
        with pytest.raises(FileNotFoundError, match=r"^images_dir x: 2 registered image\(s\) missing"):
            assemble_scene("images_dir x", **parts, test_frames=[], missing_noun="registered image(s)")
        scene = assemble_scene("scene t", **parts, test_frames=[], read_lidar=_read, check_files=False)
        with pytest.raises(FileNotFoundError, match=r"^scene t: missing file .*2\.npz$"):
            scene.lidar(12)

    def test_lidar_of_unknown_frames(self, tmp_path):
        scene = assemble_scene("scene t", **_parts(tmp_path, (0, 1)), test_frames=[], read_lidar=_read)
        with pytest.raises(FileNotFoundError, match=r"^scene t: no LiDAR for frame 12$"):
            scene.lidar(12)
        with pytest.raises(
            FileNotFoundError, match=r"no LiDAR for frame 3: the scene has no such frame \(frames 10\.\.12\)"
        ):
            scene.lidar(3)

    def test_exception(self, tmp_path):
        parts = _parts(tmp_path)
        with pytest.raises(ValueError, match="validate: expected 'none', 'headers' or 'full', got 'fast'"):
            assemble_scene("scene t", **parts, test_frames=[], validate="fast")
        with pytest.raises(ValueError, match="read_lidar or lidar_loader"):
            assemble_scene("scene t", **parts, test_frames=[], read_lidar=_read, lidar_loader=lambda f: None)

    def test_validate_runs_the_content_checks(self, tmp_path):
        parts = _parts(tmp_path)  # the PNG files are empty: their headers fail
        assemble_scene("scene t", **parts, test_frames=[], validate="none")
        assemble_scene("scene t", **parts, test_frames=[], validate="headers", check_files=False)
        with pytest.raises(ValueError, match=r"3 problem\(s\): .*0\.png: image: not a decodable image"):
            assemble_scene("scene t", **parts, test_frames=[], validate="headers")


def test_check_validate_level():
    for level in ("none", "headers", "full"):
        check_validate_level(level)
    with pytest.raises(ValueError, match="got 'quick'"):
        check_validate_level("quick")


def test_check_scale():
    check_scale(0.5)
    for bad in (0, -1.0, "1", None):
        with pytest.raises(ValueError, match="scale: expected a positive number"):
            check_scale(bad)


class TestPinholeCamera:
    K = torch.tensor([[100.0, 0.0, 49.5], [0.0, 100.0, 29.5], [0.0, 0.0, 1.0]], dtype=torch.float64)

    def test_undistorted_and_scaled(self):
        c2e = np.eye(4)
        c2e[0, 3] = 1.5
        cam, und = pinhole_camera("c", self.K, torch.tensor([-0.2, 0.0, 0.0, 0.0]), (60, 100), 0.5, c2e, "c")
        assert und.distorted and cam.image_size == (30, 50) and cam.K.dtype == torch.float32
        torch.testing.assert_close(cam.K.double(), scale_intrinsics(und.K, 0.5).float().double())
        assert cam.cam_to_ego[0, 3].item() == 1.5

    def test_no_distortion_keeps_K(self):
        cam, und = pinhole_camera("c", self.K, torch.zeros(4), (60, 100), 1.0, np.eye(4), "c")
        assert not und.distorted and torch.equal(cam.K, self.K.float())

    def test_exception(self):
        with pytest.raises(ValueError, match=r"^Waymo cam: distortion: expected 4, 5, 8 or 12"):
            pinhole_camera("c", self.K, torch.zeros(3), (60, 100), 1.0, np.eye(4), "Waymo cam")


class TestFileImageLoader:
    def test_none_without_distortion(self):
        und = ImageUndistorter(TestPinholeCamera.K, torch.zeros(4), (60, 100))
        assert file_image_loader({"c": und}, "DGP") is None

    def test_undistorts_and_checks_size(self, tmp_path):
        from PIL import Image

        path = tmp_path / "a.png"
        Image.fromarray(np.full((60, 100, 3), 128, dtype=np.uint8)).save(path)
        und = ImageUndistorter(TestPinholeCamera.K, torch.tensor([-0.2, 0.0, 0.0, 0.0]), (60, 100))
        loader = file_image_loader({"c": und}, "DGP")
        img = loader(ViewInfo(0, 0, "c", 0.0, torch.eye(4), path))
        assert img.shape == (3, 60, 100) and float(img.max()) <= 1.0
        assert loader(ViewInfo(0, 0, "other", 0.0, torch.eye(4), path)).shape == (3, 60, 100)
        Image.fromarray(np.zeros((30, 100, 3), dtype=np.uint8)).save(path)
        with pytest.raises(
            ValueError, match=r"^DGP image .*a\.png: size 100x30 differs from the camera's 100x60$"
        ):
            loader(ViewInfo(0, 0, "c", 0.0, torch.eye(4), path))
