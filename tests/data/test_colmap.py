"""Tests of vadgs.data.colmap on reconstructions written with pycolmap inside the test."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from vadgs.data import ColmapPoints, ColmapScene, Scene, load_colmap
from vadgs.data.colmap_model import colmap_camera_to_K
from vadgs.geometry import invert_rigid, project_points, scale_intrinsics

pycolmap = pytest.importorskip("pycolmap")

W, H = 80, 60


def _look_at(center: np.ndarray, target: np.ndarray) -> np.ndarray:
    """cam_from_world (3, 4) of an OpenCV camera at ``center`` looking at ``target``, z up."""
    z = target - center
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return np.concatenate([R, -R @ center[:, None]], axis=1)


def synthetic_model(
    root: Path,
    model: str = "PINHOLE",
    params: list[float] | None = None,
    n_images: int = 4,
    n_points: int = 40,
) -> dict:
    """Write a small model: one camera, ``n_images`` posed images, points seen by >= 2 images."""
    rng = np.random.default_rng(0)
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, model, 70.0, W, H)
    if params is not None:
        cam.params = params
    rec.add_camera_with_trivial_rig(cam)
    pts = rng.uniform([-1.0, -1.0, -0.5], [1.0, 1.0, 0.5], size=(n_points, 3))
    poses, obs = {}, {}
    for i in range(n_images):
        ang = 2 * np.pi * i / n_images
        center = np.array([6 * np.cos(ang), 6 * np.sin(ang), 1.0])
        cfw = _look_at(center, np.zeros(3))
        cam_pts = pts @ cfw[:, :3].T + cfw[:, 3]
        uv = np.asarray(cam.img_from_cam(cam_pts))  # COLMAP's own projection, COLMAP pixel convention
        keep = [j for j in range(n_points) if (i + j) % 4 != 0]  # each image misses a quarter
        img_id = i + 1
        name = f"img_{i:02d}.png"
        image = pycolmap.Image(name=name, keypoints=uv[keep], camera_id=1, image_id=img_id)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(cfw))
        poses[name] = cfw
        obs[img_id] = {j: k for k, j in enumerate(keep)}
    for j in range(n_points):
        track = pycolmap.Track()
        for img_id, kp in obs.items():
            if j in kp:
                track.add_element(img_id, kp[j])
        rec.add_point3D(pts[j], track, np.array([j, 2 * j, 255 - j], dtype=np.uint8))
    root.mkdir(parents=True, exist_ok=True)
    rec.write(str(root))
    return {"rec": rec, "points": pts, "poses": poses, "obs": obs, "camera": cam}


def _reprojection(scene: Scene, points: ColmapPoints) -> torch.Tensor:
    cams = scene.cameras(points.view_idx.tolist())
    uv, z = project_points(points.points[points.point_idx][:, None], cams.K, cams.world_to_cam)
    assert bool((z > 0).all())
    return (uv[:, 0] - points.uv).norm(dim=-1)


class TestLoadColmap:
    def test_smoke(self, tmp_path):
        synthetic_model(tmp_path / "sparse" / "0")
        out = load_colmap(tmp_path / "sparse" / "0")
        assert isinstance(out, ColmapScene)
        scene, points = out
        assert isinstance(scene, Scene) and isinstance(points, ColmapPoints)
        assert scene.lidar_loader is None and scene.tracks == {}
        # a photo collection is spoken of as photos: no frames, views or tracks
        assert scene.is_photo_collection
        assert repr(scene) == f"Scene({tmp_path.name!r}, 4 photos, 1 camera, 40 SfM points, scale=1.0)"

    def test_cardinality(self, tmp_path):
        synthetic_model(tmp_path / "m")
        scene, points = load_colmap(tmp_path / "m")
        assert scene.num_views == 4 and len(scene.frames) == 4
        assert scene.camera_names == ["camera_1"]
        assert scene.train_frames == [0, 1, 2, 3] and scene.test_frames == []
        P, T = 40, 30 * 4
        assert points.points.shape == (P, 3) and points.points.dtype == torch.float32
        assert points.colors.shape == (P, 3) and points.errors.shape == (P,)
        assert points.point_idx.shape == (T,) and points.view_idx.shape == (T,)
        assert points.point_idx.dtype == torch.int64 and points.view_idx.dtype == torch.int64
        assert points.uv.shape == (T, 2)
        assert points.point_views[0] is points.point_idx

    def test_intrinsics_pixel_offset(self, tmp_path):
        synthetic_model(tmp_path / "m", params=[70.0, 72.0, 41.0, 29.0])
        scene, _ = load_colmap(tmp_path / "m")
        K = scene.cameras_info["camera_1"].K
        # COLMAP pixel centres are at +0.5: vadgs cx = cx_colmap - 0.5
        torch.testing.assert_close(K, torch.tensor([[70.0, 0, 40.5], [0, 72.0, 28.5], [0, 0, 1]]))
        assert scene.image_size(0) == (H, W)

    def test_default_centre_is_image_centre(self):
        K, _ = colmap_camera_to_K(pycolmap.Camera.create_from_model_name(1, "SIMPLE_PINHOLE", 50.0, W, H))
        assert K[0, 2].item() == (W - 1) / 2 and K[1, 2].item() == (H - 1) / 2

    def test_poses_points_tracks_exact(self, tmp_path):
        syn = synthetic_model(tmp_path / "m")
        scene, points = load_colmap(tmp_path / "m")
        for v in scene.views:
            name = f"img_{v.frame:02d}.png"
            want = torch.eye(4, dtype=torch.float64)
            want[:3] = torch.from_numpy(syn["poses"][name])
            torch.testing.assert_close(invert_rigid(v.cam_to_world.double()), want, atol=1e-5, rtol=0)
        order = points.point_ids.argsort()
        torch.testing.assert_close(
            points.points[order].double(), torch.from_numpy(syn["points"]), atol=1e-6, rtol=0
        )
        j = torch.arange(40)
        want_col = torch.stack([j, 2 * j, 255 - j], dim=1).float() / 255
        torch.testing.assert_close(points.colors[order], want_col)
        # the TRACK table: exactly the (point, view) pairs written
        got = {(int(points.point_ids[p]) - 1, int(v)) for p, v in zip(points.point_idx, points.view_idx)}
        want_pairs = {(j, img_id - 1) for img_id, kp in syn["obs"].items() for j in kp}
        assert got == want_pairs

    def test_reprojection_matches_observations(self, tmp_path):
        synthetic_model(tmp_path / "m", params=[70.0, 72.0, 41.0, 29.0])
        scene, points = load_colmap(tmp_path / "m")
        err = _reprojection(scene, points)
        assert err.max() < 1e-3
        # the same check with COLMAP's raw principal point is off by half a pixel on each axis
        cams = scene.cameras(points.view_idx.tolist())
        K_raw = cams.K.clone()
        K_raw[:, :2, 2] += 0.5
        uv, _ = project_points(points.points[points.point_idx][:, None], K_raw, cams.world_to_cam)
        assert ((uv[:, 0] - points.uv).norm(dim=-1) - 0.5**0.5).abs().max() < 1e-3

    def test_rescale(self, tmp_path):
        synthetic_model(tmp_path / "m", params=[70.0, 72.0, 41.0, 29.0])
        full, _ = load_colmap(tmp_path / "m")
        half, points = load_colmap(tmp_path / "m", scale=0.5)
        assert half.image_size(0) == (H // 2, W // 2)
        torch.testing.assert_close(
            half.cameras_info["camera_1"].K, scale_intrinsics(full.cameras_info["camera_1"].K, 0.5)
        )
        assert _reprojection(half, points).max() < 1e-3

    def test_text_model(self, tmp_path):
        syn = synthetic_model(tmp_path / "bin")
        (tmp_path / "txt").mkdir()
        syn["rec"].write_text(str(tmp_path / "txt"))
        _, pa = load_colmap(tmp_path / "bin")
        _, pb = load_colmap(tmp_path / "txt")
        torch.testing.assert_close(pa.points, pb.points)
        assert torch.equal(pa.view_idx, pb.view_idx) and torch.equal(pa.point_idx, pb.point_idx)

    def test_images_dir(self, tmp_path):
        synthetic_model(tmp_path / "proj" / "sparse" / "0")
        images = tmp_path / "proj" / "images"
        images.mkdir()
        from PIL import Image

        for i in range(4):
            Image.fromarray(np.full((H, W, 3), 10 * i, np.uint8)).save(images / f"img_{i:02d}.png")
        scene, _ = load_colmap(tmp_path / "proj" / "sparse" / "0")  # images/ found by default
        assert scene.name == "proj"
        assert scene.views[2].image == images / "img_02.png"
        imgs = scene.load_images([2])
        assert imgs.shape == (1, 3, H, W) and imgs.dtype == torch.float32
        assert torch.allclose(imgs, torch.full_like(imgs, 20 / 255))
        half, _ = load_colmap(tmp_path / "proj" / "sparse" / "0", scale=0.5)
        assert half.load_images([0]).shape == (1, 3, H // 2, W // 2)

    def test_rig_frames(self, tmp_path):
        rec = pycolmap.Reconstruction()
        for cid in (1, 2):
            rec.add_camera(pycolmap.Camera.create_from_model_name(cid, "PINHOLE", 50.0, W, H))
        rig = pycolmap.Rig(rig_id=1)
        rig.add_ref_sensor(rec.cameras[1].sensor_id)
        offset = pycolmap.Rigid3d(pycolmap.Rotation3d(np.eye(3)), np.array([-0.5, 0.0, 0.0]))
        rig.add_sensor(rec.cameras[2].sensor_id, offset)
        rec.add_rig(rig)
        for f in range(3):
            frame = pycolmap.Frame(frame_id=f + 1, rig_id=1)
            frame.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(np.eye(3)), np.array([0.0, 0.0, -f]))
            images = []
            for cid in (2, 1):
                im = pycolmap.Image(
                    name=f"cam{cid}/{f}.png", keypoints=np.zeros((0, 2)), camera_id=cid, image_id=2 * f + cid
                )
                im.frame_id = f + 1
                frame.add_data_id(im.data_id)
                images.append(im)
            rec.add_frame(frame)
            for im in images:
                rec.add_image(im)
        (tmp_path / "rig").mkdir()
        rec.write(str(tmp_path / "rig"))
        scene, points = load_colmap(tmp_path / "rig")
        assert (
            len(scene.frames) == 3 and scene.num_views == 6 and scene.camera_names == ["camera_1", "camera_2"]
        )
        assert [scene.views[i].camera for i in scene.frames[1].view_ids] == ["camera_1", "camera_2"]
        centres = scene.cameras().centers
        torch.testing.assert_close(centres[scene.view_id(2, "camera_2")], torch.tensor([0.5, 0.0, 2.0]))
        assert points.points.shape == (0, 3) and points.point_idx.shape == (0,)

    def test_distortion_warns(self, tmp_path):
        synthetic_model(tmp_path / "m", model="OPENCV", params=[70.0, 70.0, 40.0, 30.0, 0.1, 0.0, 0.0, 0.0])
        with pytest.warns(UserWarning, match="IGNORES the distortion"):
            scene, _ = load_colmap(tmp_path / "m")
        torch.testing.assert_close(scene.cameras_info["camera_1"].K[0, 2], torch.tensor(39.5))

    def test_undistorted_radial_does_not_warn(self, tmp_path):
        synthetic_model(tmp_path / "m", model="SIMPLE_RADIAL", params=[70.0, 40.0, 30.0, 0.0])
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            load_colmap(tmp_path / "m")

    def test_exception(self, tmp_path):
        with pytest.raises(FileNotFoundError, match="no COLMAP model"):
            load_colmap(tmp_path)
        synthetic_model(tmp_path / "m")
        with pytest.raises(ValueError, match="scale"):
            load_colmap(tmp_path / "m", scale=0)
        with pytest.raises(FileNotFoundError, match="images_dir"):
            load_colmap(tmp_path / "m", images_dir=tmp_path / "nope")
        (tmp_path / "imgs").mkdir()
        with pytest.raises(FileNotFoundError, match="4 registered image"):
            load_colmap(tmp_path / "m", images_dir=tmp_path / "imgs")
        synthetic_model(tmp_path / "fish", model="OPENCV_FISHEYE")
        with pytest.raises(ValueError, match="unsupported COLMAP camera model OPENCV_FISHEYE"):
            load_colmap(tmp_path / "fish")
        (tmp_path / "bad").mkdir()
        (tmp_path / "bad" / "cameras.txt").write_text("1 PINHOLE not numbers\n")
        with pytest.raises(FileNotFoundError, match="missing images, points3D"):
            load_colmap(tmp_path / "bad")
        (tmp_path / "bad" / "images.txt").write_text("")
        (tmp_path / "bad" / "points3D.txt").write_text("")
        with pytest.raises(ValueError, match=r"cannot read .*cameras.txt: a line of 4 fields"):
            load_colmap(tmp_path / "bad")
