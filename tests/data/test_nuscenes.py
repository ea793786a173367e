"""Tests of vadgs.data.nuscenes on a tiny nuScenes dataset written in the official table layout."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from vadgs.data import Scene, load_nuscenes
from vadgs.data.nuscenes import nuscenes_class_name, nuscenes_pose_to_matrix
from vadgs.geometry import project_points

# camera axes (x right, y down, z forward) in an ego frame with x forward, y left, z up
CAM_IN_EGO = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])
W_IMG, H_IMG = 32, 24
K_NUS = [[20.0, 0.0, 15.5], [0.0, 21.0, 11.5], [0.0, 0.0, 1.0]]
N_FRAMES = 7
GLOBAL = np.array([400.0, 1100.0, 0.5])  # nuScenes' global frame lies far from the origin


def _quat(R: np.ndarray) -> list[float]:
    """Rotation matrix → (w, x, y, z)."""
    w = math.sqrt(max(0.0, 1 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1 + R[0, 0] - R[1, 1] - R[2, 2])) / 2, R[2, 1] - R[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1 - R[0, 0] + R[1, 1] - R[2, 2])) / 2, R[0, 2] - R[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1 - R[0, 0] - R[1, 1] + R[2, 2])) / 2, R[1, 0] - R[0, 1])
    return [w, x, y, z]


def _rigid(yaw: float, t, R: np.ndarray | None = None) -> np.ndarray:
    out = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    out[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ (np.eye(3) if R is None else R)
    out[:3, 3] = t
    return out


def _ego(t_s: float) -> np.ndarray:
    """Ego → global at time t (s): driving at 5 m/s while turning slowly."""
    yaw = 0.3 + 0.05 * t_s
    return _rigid(yaw, GLOBAL + np.array([5.0 * t_s * math.cos(0.3), 5.0 * t_s * math.sin(0.3), 0.0]))


CALIB = {
    "LIDAR_TOP": _rigid(0.05, (0.9, 0.0, 1.8)),
    "CAM_FRONT": _rigid(0.0, (1.5, 0.1, 1.5), CAM_IN_EGO),
    "CAM_BACK": _rigid(math.pi, (-1.0, 0.0, 1.5), CAM_IN_EGO),
}
CAM_DT = {"CAM_FRONT": -0.012, "CAM_BACK": 0.03}  # each camera fires off the LiDAR's time
BOX_CAM = (3, "CAM_FRONT")  # (frame, camera) where the moving car sits 10 m ahead, aligned


def write_nuscenes(root: Path, version: str = "v1.0-mini") -> dict:
    """7 keyframes, LIDAR_TOP + CAM_FRONT + CAM_BACK, a moving car, a parked car, a pedestrian."""
    meta = root / version
    meta.mkdir(parents=True)
    tables: dict[str, list] = {
        k: [] for k in ("scene", "sample", "sample_data", "ego_pose", "sample_annotation")
    }
    tables["sensor"] = [
        {"token": "s_lid", "channel": "LIDAR_TOP", "modality": "lidar"},
        {"token": "s_cf", "channel": "CAM_FRONT", "modality": "camera"},
        {"token": "s_cb", "channel": "CAM_BACK", "modality": "camera"},
        {"token": "s_radar", "channel": "RADAR_FRONT", "modality": "radar"},
    ]
    tables["calibrated_sensor"] = [
        {
            "token": f"cs_{ch}",
            "sensor_token": tok,
            "translation": CALIB[ch][:3, 3].tolist(),
            "rotation": _quat(CALIB[ch][:3, :3]),
            "camera_intrinsic": K_NUS if ch.startswith("CAM") else [],
        }
        for ch, tok in (("LIDAR_TOP", "s_lid"), ("CAM_FRONT", "s_cf"), ("CAM_BACK", "s_cb"))
    ]
    tables["category"] = [
        {"token": "c_car", "name": "vehicle.car", "description": ""},
        {"token": "c_ped", "name": "human.pedestrian.adult", "description": ""},
    ]
    tables["instance"] = [
        {"token": "i_parked", "category_token": "c_car", "nbr_annotations": N_FRAMES},
        {"token": "i_moving", "category_token": "c_car", "nbr_annotations": N_FRAMES},
        {"token": "i_ped", "category_token": "c_ped", "nbr_annotations": N_FRAMES},
    ]
    for sub in ("samples/LIDAR_TOP", "samples/CAM_FRONT", "samples/CAM_BACK", "sweeps/CAM_FRONT"):
        (root / sub).mkdir(parents=True)

    t0_us = 1_532_402_927_647_951
    # the moving car: at frame BOX_CAM[0] it sits 10 m ahead of CAM_FRONT, aligned with the ego
    fb, cb = BOX_CAM
    tb = fb * 0.5 + CAM_DT[cb]
    cam_world = _ego(tb) @ CALIB[cb]
    box_at_fb = _rigid(0.3 + 0.05 * tb, (cam_world @ np.array([0.0, 0.0, 10.0, 1.0]))[:3])
    moving = [box_at_fb @ _rigid(0.0, (1.5 * (f - fb), 0.0, 0.0)) for f in range(N_FRAMES)]
    parked = _rigid(1.2, GLOBAL + np.array([3.0, 8.0, 0.8]))
    # a LiDAR point 12 m in front of CAM_BACK at frame 1, 1 m right, 0.5 m up → known pixel
    lid_frame, lid_cam, p_cam = 1, "CAM_BACK", np.array([1.0, -0.5, 12.0])
    p_world = (_ego(lid_frame * 0.5 + CAM_DT[lid_cam]) @ CALIB[lid_cam] @ np.append(p_cam, 1.0))[:3]
    pixel = (15.5 + 20.0 * 1.0 / 12.0, 11.5 + 21.0 * -0.5 / 12.0)

    tokens = [f"smp{i}" for i in range(N_FRAMES)]
    for i, tok in enumerate(tokens):
        t_s = i * 0.5
        tables["sample"].append(
            {
                "token": tok,
                "timestamp": t0_us + round(t_s * 1e6),
                "scene_token": "scn1",
                "prev": tokens[i - 1] if i else "",
                "next": tokens[i + 1] if i + 1 < N_FRAMES else "",
            }
        )
        for ch, dt in (
            ("LIDAR_TOP", 0.0),
            ("CAM_FRONT", CAM_DT["CAM_FRONT"]),
            ("CAM_BACK", CAM_DT["CAM_BACK"]),
        ):
            ts = t0_us + round((t_s + dt) * 1e6)
            ep = _ego(t_s + dt)
            tables["ego_pose"].append(
                {
                    "token": f"ep_{ch}_{i}",
                    "timestamp": ts,
                    "rotation": _quat(ep[:3, :3]),
                    "translation": ep[:3, 3].tolist(),
                }
            )
            ext = "pcd.bin" if ch == "LIDAR_TOP" else "jpg"
            fname = f"samples/{ch}/n015__{ch}__{ts}.{ext}"
            tables["sample_data"].append(
                {
                    "token": f"sd_{ch}_{i}",
                    "sample_token": tok,
                    "ego_pose_token": f"ep_{ch}_{i}",
                    "calibrated_sensor_token": f"cs_{ch}",
                    "timestamp": ts,
                    "fileformat": "pcd" if ch == "LIDAR_TOP" else "jpg",
                    "is_key_frame": True,
                    "height": 0 if ch == "LIDAR_TOP" else H_IMG,
                    "width": 0 if ch == "LIDAR_TOP" else W_IMG,
                    "filename": fname,
                    "prev": "",
                    "next": "",
                }
            )
            if ch == "LIDAR_TOP":
                lid_world = ep @ CALIB[ch]
                pts = [p_world if i == lid_frame else GLOBAL + 50, moving[i][:3, 3], parked[:3, 3]]
                local = (np.array(pts) - lid_world[:3, 3]) @ lid_world[:3, :3]
                cloud = np.concatenate([local, np.full((3, 1), 7.0), np.arange(3)[:, None]], 1)
                cloud.astype(np.float32).tofile(root / fname)
            else:
                colour = (200, 40, 10) if ch == "CAM_FRONT" else (10, 90, 220)
                Image.fromarray(np.full((H_IMG, W_IMG, 3), colour, np.uint8)).save(root / fname, quality=95)
        # a non-keyframe sweep of CAM_FRONT pointing at the same sample, with a wild ego pose: ignored
        tables["ego_pose"].append(
            {"token": f"ep_sweep_{i}", "timestamp": 0, "rotation": [1, 0, 0, 0], "translation": [0, 0, 0]}
        )
        tables["sample_data"].append(
            {
                "token": f"sd_sweep_{i}",
                "sample_token": tok,
                "ego_pose_token": f"ep_sweep_{i}",
                "calibrated_sensor_token": "cs_CAM_FRONT",
                "timestamp": t0_us,
                "is_key_frame": False,
                "height": H_IMG,
                "width": W_IMG,
                "filename": f"sweeps/CAM_FRONT/{i}.jpg",
            }
        )
        ped = _rigid(0.0, GLOBAL + np.array([-5.0 + 1.0 * i, -4.0, 0.9]))
        for inst, pose, wlh in (
            ("i_parked", parked, [1.9, 4.5, 1.6]),
            ("i_moving", moving[i], [2.0, 4.0, 1.5]),
            ("i_ped", ped, [0.6, 0.7, 1.8]),
        ):
            tables["sample_annotation"].append(
                {
                    "token": f"ann_{inst}_{i}",
                    "sample_token": tok,
                    "instance_token": inst,
                    "translation": pose[:3, 3].tolist(),
                    "size": wlh,
                    "rotation": _quat(pose[:3, :3]),
                    "num_lidar_pts": 1,
                }
            )
    tables["scene"] = [
        {"token": "scn0", "name": "scene-0001", "first_sample_token": "", "nbr_samples": 0, "log_token": "l"},
        {
            "token": "scn1",
            "name": "scene-0061",
            "first_sample_token": tokens[0],
            "nbr_samples": N_FRAMES,
            "log_token": "l",
        },
    ]
    tables["log"] = [{"token": "l", "location": "singapore-onenorth"}]
    for name, rows in tables.items():
        (meta / f"{name}.json").write_text(json.dumps(rows))
    return {
        "moving": moving,
        "parked": parked,
        "p_world": p_world,
        "pixel": pixel,
        "lid": (lid_frame, lid_cam),
    }


@pytest.fixture
def nus(tmp_path):
    syn = write_nuscenes(tmp_path / "nuscenes")
    return tmp_path / "nuscenes", syn


class TestHelpers:
    def test_pose(self):
        T = _rigid(0.7, (1.0, 2.0, 3.0), CAM_IN_EGO)
        np.testing.assert_allclose(nuscenes_pose_to_matrix(_quat(T[:3, :3]), T[:3, 3]), T, atol=1e-12)
        with pytest.raises(ValueError, match="translation"):
            nuscenes_pose_to_matrix([1, 0, 0, 0], [0, 0])
        with pytest.raises(ValueError, match="quaternion"):
            nuscenes_pose_to_matrix([0, 0, 0, 0], [0, 0, 0])

    def test_class_name(self):
        assert nuscenes_class_name("vehicle.emergency.police") == "emergency_police"


class TestLoadNuscenes:
    def test_smoke(self, nus):
        root, _ = nus
        scene = load_nuscenes(root, "scene-0061")
        assert isinstance(scene, Scene)
        assert scene.camera_names == ["CAM_FRONT", "CAM_BACK"]
        assert len(scene.frames) == N_FRAMES and scene.num_views == 2 * N_FRAMES
        assert [scene.views[i].camera for i in scene.frames[1].view_ids] == ["CAM_FRONT", "CAM_BACK"]

    def test_split_every_fourth(self, nus):
        root, _ = nus
        scene = load_nuscenes(root, "scene-0061")
        assert scene.test_frames == [2, 6] and scene.train_frames == [0, 1, 3, 4, 5]
        assert scene.test_views == [4, 5, 12, 13]
        assert load_nuscenes(root, "scene-0061", test_frames=()).test_frames == []
        sub = load_nuscenes(root, "scene-0061", frames=range(1, 4))
        assert len(sub.frames) == 3 and sub.test_frames == [2]

    def test_poses_use_each_cameras_own_ego_pose(self, nus):
        root, _ = nus
        scene = load_nuscenes(root, "scene-0061", recenter=False)
        for fi in (0, 4):
            for c in ("CAM_FRONT", "CAM_BACK"):
                want = _ego(fi * 0.5 + CAM_DT[c]) @ CALIB[c]
                got = scene.views[scene.view_id(fi, c)].cam_to_world.double()
                torch.testing.assert_close(got, torch.from_numpy(want), atol=1e-4, rtol=0)
            torch.testing.assert_close(
                scene.frames[fi].ego_to_world.double(), torch.from_numpy(_ego(fi * 0.5)), atol=1e-4, rtol=0
            )
        assert scene.views[scene.view_id(2, "CAM_BACK")].timestamp == pytest.approx(1.03, abs=1e-6)
        torch.testing.assert_close(
            scene.cameras_info["CAM_BACK"].cam_to_ego, torch.from_numpy(CALIB["CAM_BACK"]).float()
        )

    def test_recenter(self, nus):
        root, _ = nus
        scene = load_nuscenes(root, "scene-0061")
        torch.testing.assert_close(scene.frames[0].ego_to_world[:3, 3], torch.zeros(3), atol=1e-5, rtol=0)
        far = load_nuscenes(root, "scene-0061", recenter=False)
        d = far.views[5].cam_to_world[:3, 3] - scene.views[5].cam_to_world[:3, 3]
        torch.testing.assert_close(d, torch.from_numpy(GLOBAL).float(), atol=1e-3, rtol=0)

    def test_lidar_point_projects_to_known_pixel(self, nus):
        root, syn = nus
        frame, cam = syn["lid"]
        for scale in (1.0, 0.5):
            scene = load_nuscenes(root, "scene-0061", scale=scale)
            lid = scene.lidar(frame)
            assert lid.points.shape == (3, 3) and lid.points.dtype == torch.float32
            torch.testing.assert_close(
                lid.points[0].double(), torch.from_numpy(syn["p_world"] - GLOBAL), atol=1e-3, rtol=0
            )
            cams = scene.cameras([scene.view_id(frame, cam)])
            uv, z = project_points(lid.points[None, :1], cams.K, cams.world_to_cam)
            want = (
                torch.tensor(syn["pixel"])
                if scale == 1.0
                else scale * (torch.tensor(syn["pixel"]) + 0.5) - 0.5
            )
            assert float(z[0, 0]) == pytest.approx(12.0, abs=1e-3)
            assert float((uv[0, 0] - want).abs().max()) < 0.02
        # the origin is the LiDAR position
        torch.testing.assert_close(
            lid.origin.double(),
            torch.from_numpy((_ego(frame * 0.5) @ CALIB["LIDAR_TOP"])[:3, 3] - GLOBAL),
            atol=1e-3,
            rtol=0,
        )

    def test_box_projects_onto_known_rectangle(self, nus):
        root, _ = nus
        scene = load_nuscenes(root, "scene-0061")
        fb, cb = BOX_CAM
        track = scene.tracks[2]  # the moving car
        length, w, h = track.size_lwh.tolist()
        assert (length, w, h) == pytest.approx((4.0, 2.0, 1.5))  # nuScenes' (w, l, h) reordered
        corners = torch.tensor(
            [
                [sx * length / 2, sy * w / 2, sz * h / 2, 1.0]
                for sx in (-1, 1)
                for sy in (-1, 1)
                for sz in (-1, 1)
            ]
        )
        world = (track.object_to_world[fb] @ corners.T).T[:, :3]
        cams = scene.cameras([scene.view_id(fb, cb)])
        uv, z = project_points(world[None], cams.K, cams.world_to_cam)
        # in camera coordinates the box spans x in [-1, 1], y in [-0.75, 0.75], z in [8, 12]
        rect = [uv[0, :, 0].min(), uv[0, :, 1].min(), uv[0, :, 0].max(), uv[0, :, 1].max()]
        want = [15.5 - 20 / 8, 11.5 - 21 * 0.75 / 8, 15.5 + 20 / 8, 11.5 + 21 * 0.75 / 8]
        assert [float(v) for v in rect] == pytest.approx(want, abs=0.01)
        assert float(z.min()) == pytest.approx(8.0, abs=1e-3) and float(z.max()) == pytest.approx(
            12.0, abs=1e-3
        )

    def test_tracks_and_instances(self, nus):
        root, _ = nus
        scene = load_nuscenes(root, "scene-0061")
        # ids by first appearance: parked 1, moving 2, pedestrian 3
        assert {i: (v.name, v.class_name, v.dynamic) for i, v in scene.instances.items()} == {
            1: ("i_parked", "car", False),
            2: ("i_moving", "car", True),
            3: ("i_ped", "pedestrian_adult", True),
        }
        assert sorted(scene.tracks) == [2] and scene.tracks[2].class_name == "car"
        assert bool(scene.tracks[2].valid.all())
        steps = scene.tracks[2].object_to_world[1:, :3, 3] - scene.tracks[2].object_to_world[:-1, :3, 3]
        torch.testing.assert_close(steps.norm(dim=-1), torch.full((N_FRAMES - 1,), 1.5), atol=1e-4, rtol=0)
        # every vehicle with min_motion_m=None
        assert sorted(load_nuscenes(root, "scene-0061", min_motion_m=None).tracks) == [1, 2]
        # LiDAR points inside a box carry its persistent id in every frame
        for f in (0, 3, 6):
            assert scene.lidar(f).instance.tolist()[1:] == [2, 1]

    def test_images(self, nus):
        root, _ = nus
        scene = load_nuscenes(root, "scene-0061", scale=0.5)
        assert scene.image_size(0) == (12, 16)
        imgs = scene.load_images([scene.view_id(0, "CAM_FRONT"), scene.view_id(0, "CAM_BACK")])
        assert imgs.shape == (2, 3, 12, 16)
        torch.testing.assert_close(imgs[0, :, 6, 8], torch.tensor([200, 40, 10]) / 255.0, atol=0.03, rtol=0)
        torch.testing.assert_close(imgs[1, :, 6, 8], torch.tensor([10, 90, 220]) / 255.0, atol=0.03, rtol=0)
        torch.testing.assert_close(scene.cameras_info["CAM_FRONT"].K[0], torch.tensor([10.0, 0.0, 7.5]))

    def test_camera_distortion_is_undistorted(self, nus):
        """nuScenes has no distortion; a table with camera_distortion (nuImages layout) is undistorted."""
        cv2 = pytest.importorskip("cv2")
        root, _ = nus
        meta = root / "v1.0-mini"
        cal = json.loads((meta / "calibrated_sensor.json").read_text())
        dist = [0.1, -0.02, 0.003, 0.001, 0.0]
        for c in cal:
            c["camera_distortion"] = dist if c["token"] == "cs_CAM_BACK" else [0.0] * 5
        (meta / "calibrated_sensor.json").write_text(json.dumps(cal))
        path = next((root / "samples" / "CAM_BACK").glob("*.jpg"))
        yy, xx = np.mgrid[0:H_IMG, 0:W_IMG]
        Image.fromarray(np.stack([xx * 8, yy * 10, (xx + yy) * 4], -1).astype(np.uint8)).save(
            path, quality=100
        )
        scene = load_nuscenes(root, "scene-0061")
        torch.testing.assert_close(scene.cameras_info["CAM_FRONT"].K, torch.tensor(K_NUS))
        K = scene.cameras_info["CAM_BACK"].K.double().numpy()
        assert K[0, 0] != K_NUS[0][0] and K[:2, 2].tolist() == [15.5, 11.5]
        mx, my = cv2.initUndistortRectifyMap(
            np.array(K_NUS), np.array(dist), None, K, (W_IMG, H_IMG), cv2.CV_32FC1
        )
        raw = np.asarray(Image.open(path).convert("RGB")).astype(np.float32) / 255
        want = cv2.remap(raw, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        vid = next(v.index for v in scene.views if v.image == path)
        np.testing.assert_allclose(scene.load_images([vid])[0].permute(1, 2, 0).numpy(), want, atol=1e-4)
        cal[2]["camera_distortion"] = [0.1] * 6  # nuImages' fisheye CAM_BACK has 6: not OpenCV's
        (meta / "calibrated_sensor.json").write_text(json.dumps(cal))
        with pytest.raises(ValueError, match=r"CAM_BACK calibrated_sensor\.camera_distortion: .* got 6"):
            load_nuscenes(root, "scene-0061")

    def test_camera_subset(self, nus):
        root, _ = nus
        scene = load_nuscenes(root, "scene-0061", cameras=["CAM_BACK"], lidar=None)
        assert scene.camera_names == ["CAM_BACK"] and scene.num_views == N_FRAMES
        with pytest.raises(FileNotFoundError, match="no LiDAR"):
            scene.lidar(0)

    def test_exception(self, nus, tmp_path):
        root, _ = nus
        with pytest.raises(ValueError, match=r"scene_name: unknown scene 'scene-9999'.*scene-0061"):
            load_nuscenes(root, "scene-9999")
        with pytest.raises(ValueError, match=r"cameras: unknown camera 'CAM_FRONT_LEFT'.*CAM_BACK"):
            load_nuscenes(root, "scene-0061", cameras=["CAM_FRONT_LEFT"])
        with pytest.raises(ValueError, match=r"lidar: unknown LiDAR channel 'RADAR_FRONT'"):
            load_nuscenes(root, "scene-0061", lidar="RADAR_FRONT")
        with pytest.raises(FileNotFoundError, match="version: no table folder"):
            load_nuscenes(root, "scene-0061", version="v1.0-trainval")
        with pytest.raises(ValueError, match="test_frames: unknown frame"):
            load_nuscenes(root, "scene-0061", test_frames=[7])
        with pytest.raises(ValueError, match="scale"):
            load_nuscenes(root, "scene-0061", scale=0)
        (root / "v1.0-mini" / "ego_pose.json").unlink()
        with pytest.raises(FileNotFoundError, match=r"nuScenes table ego_pose\.json: missing file"):
            load_nuscenes(root, "scene-0061")

    def test_missing_files(self, nus):
        root, _ = nus
        next((root / "samples" / "CAM_BACK").glob("*.jpg")).unlink()
        with pytest.raises(FileNotFoundError, match="1 referenced file"):
            load_nuscenes(root, "scene-0061")
        assert load_nuscenes(root, "scene-0061", check_files=False).num_views == 2 * N_FRAMES

    def test_without_annotation_tables(self, nus):
        """A keyframe extract without annotation tables loads with no instances and no tracks."""
        root, _ = nus
        full = load_nuscenes(root, "scene-0061")
        for name in ("sample_annotation", "instance", "category", "log"):
            (root / "v1.0-mini" / f"{name}.json").unlink()
        scene = load_nuscenes(root, "scene-0061")
        assert scene.instances == {} and scene.tracks == {}
        assert scene.num_views == full.num_views
        assert (scene.lidar(3).instance == 0).all()

    def test_annotations_need_instance_table(self, nus):
        root, _ = nus
        (root / "v1.0-mini" / "instance.json").unlink()
        with pytest.raises(FileNotFoundError, match=r"nuScenes table instance\.json: missing file"):
            load_nuscenes(root, "scene-0061")

    def test_without_sample_links(self, nus):
        """Without first_sample_token / next, the keyframes are the scene's samples in time order."""
        root, _ = nus
        full = load_nuscenes(root, "scene-0061")
        meta = root / "v1.0-mini"
        scenes = json.loads((meta / "scene.json").read_text())
        for sc in scenes:
            sc.pop("first_sample_token")
        (meta / "scene.json").write_text(json.dumps(scenes))
        samples = json.loads((meta / "sample.json").read_text())
        for s in samples:
            s.pop("prev", None), s.pop("next", None)
        (meta / "sample.json").write_text(json.dumps(samples[::-1]))
        scene = load_nuscenes(root, "scene-0061")
        assert [f.timestamp for f in scene.frames] == [f.timestamp for f in full.frames]
        for a, b in zip(scene.views, full.views):
            torch.testing.assert_close(a.cam_to_world, b.cam_to_world)
        with pytest.raises(ValueError, match=r"scene-0001: scene\.json has no first_sample_token"):
            load_nuscenes(root, "scene-0001")

    def test_missing_token(self, nus):
        root, _ = nus
        path = root / "v1.0-mini" / "sample_annotation.json"
        anns = json.loads(path.read_text())
        anns[4]["instance_token"] = "nope"
        path.write_text(json.dumps(anns))
        with pytest.raises(ValueError, match=r"token 'nope' not in instance\.json"):
            load_nuscenes(root, "scene-0061")


class TestConvertNuscenes:
    def test_export_round_trip(self, nus, tmp_path):
        from vadgs.data import export_scene, load_scene

        root, syn = nus
        scene = load_nuscenes(root, "scene-0061", scale=0.5)
        again = load_scene(export_scene(scene, tmp_path / "out"))
        assert again.camera_names == scene.camera_names and again.num_views == scene.num_views
        assert again.test_frames == [2, 6] and again.train_frames == [0, 1, 3, 4, 5]
        for a, b in zip(scene.views, again.views):
            torch.testing.assert_close(a.cam_to_world, b.cam_to_world)
        torch.testing.assert_close(again.cameras_info["CAM_BACK"].K, scene.cameras_info["CAM_BACK"].K)
        torch.testing.assert_close(again.load_images([3]), scene.load_images([3]), atol=1 / 255, rtol=0)
        frame, _ = syn["lid"]
        torch.testing.assert_close(again.lidar(frame).points, scene.lidar(frame).points)
        assert again.lidar(3).instance.tolist() == [0, 2, 1]
        assert sorted(again.tracks) == [2] and again.instances[3].class_name == "pedestrian_adult"
        torch.testing.assert_close(again.tracks[2].object_to_world, scene.tracks[2].object_to_world)

    def test_cli(self, nus, tmp_path, capsys):
        from vadgs.cli import main
        from vadgs.data import load_scene

        root, _ = nus
        out = tmp_path / "conv"
        argv = ["convert", "nuscenes", str(root), "--scene", "scene-0061", "--out", str(out)]
        assert main([*argv, "--cameras", "CAM_FRONT", "--frames", "1:5", "--scale", "0.5"]) == 0
        scene = load_scene(out)
        assert (
            scene.camera_names == ["CAM_FRONT"] and len(scene.frames) == 4 and scene.image_size(0) == (12, 16)
        )
        assert scene.test_frames == [2]
        assert main([*argv[:3], "--scene", "scene-9999", "--out", str(out)]) == 2
        assert "unknown scene 'scene-9999'" in capsys.readouterr().err
