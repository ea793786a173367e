"""Tests of vadgs.data.dgp: a synthetic DGP scene written in the test, and the real test scenes."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image

from vadgs.data import Scene, load_dgp
from vadgs.data._tracks import points_in_boxes
from vadgs.data.dgp import dgp_pose_to_matrix
from vadgs.geometry import invert_rigid, project_points

SHARED = Path(__file__).resolve().parents[2].parent / "shared"
DGP = SHARED / "data" / "real" / "dgp_test_scene"
needs_dgp = pytest.mark.skipif(
    not (DGP / "scene_02").is_dir(), reason="needs ../shared/data/real/dgp_test_scene"
)


# -- a synthetic DGP scene --------------------------------------------------------------------------------


def _quat(R: np.ndarray) -> tuple[float, float, float, float]:
    """Rotation matrix → (w, x, y, z) (Shepperd, for proper rotations)."""
    w = math.sqrt(max(0.0, 1 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1 + R[0, 0] - R[1, 1] - R[2, 2])) / 2, R[2, 1] - R[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1 - R[0, 0] + R[1, 1] - R[2, 2])) / 2, R[0, 2] - R[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1 - R[0, 0] - R[1, 1] + R[2, 2])) / 2, R[1, 0] - R[0, 1])
    return w, x, y, z


def _pose(T: np.ndarray) -> dict:
    w, x, y, z = _quat(T[:3, :3])
    return {
        "rotation": {"qw": w, "qx": x, "qy": y, "qz": z},
        "translation": dict(zip("xyz", T[:3, 3].tolist())),
    }


def _rigid(yaw: float, t: tuple[float, float, float], R: np.ndarray | None = None) -> np.ndarray:
    out = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    out[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ (np.eye(3) if R is None else R)
    out[:3, 3] = t
    return out


# camera axes (x right, y down, z forward) in a vehicle frame with x forward, y left, z up
CAM_IN_EGO = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])
W_IMG, H_IMG = 16, 12


def write_dgp(root: Path) -> dict:
    """Two samples, one camera, one LiDAR (non-identity extrinsics), one moving box, one parked."""
    root.mkdir(parents=True)
    for sub in ("calibration", "ontology", "rgb/CAM", "point_cloud/LIDAR", "bounding_box_3d/LIDAR"):
        (root / sub).mkdir(parents=True)
    lid_to_ego = _rigid(0.1, (0.5, 0.0, 1.8))
    cam_to_ego = _rigid(0.0, (1.5, 0.2, 1.5), CAM_IN_EGO)
    calib = {
        "names": ["LIDAR", "CAM"],
        "intrinsics": [
            {"fx": 0, "fy": 0, "cx": 0, "cy": 0, "skew": 0},
            {"fx": 20.0, "fy": 21.0, "cx": 7.5, "cy": 5.5, "skew": 0.0},
        ],
        "extrinsics": [_pose(lid_to_ego), _pose(cam_to_ego)],
    }
    (root / "calibration" / "c0.json").write_text(json.dumps(calib))
    onto = {"items": [{"id": 2, "name": "Car"}, {"id": 3, "name": "Bus/RV/Caravan"}]}
    (root / "ontology" / "o1.json").write_text(json.dumps(onto))
    world_offset = np.array([100.0, -2000.0, -10.0])
    ego = [_rigid(0.3, tuple(world_offset)), _rigid(0.3, tuple(world_offset + np.array([2.0, 1.0, 0.0])))]
    boxes = {  # id -> per sample object_to_world (DGP world), class
        7: (
            [
                _rigid(0.0, tuple(world_offset + np.array([10, 0, 1]))),
                _rigid(0.0, tuple(world_offset + np.array([14, 0, 1]))),
            ],
            2,
        ),
        9: ([_rigid(1.0, tuple(world_offset + np.array([5, 5, 1])))] * 2, 3),
    }
    world_pts = np.array([[10.0, 0.0, 1.0], [10.5, 0.3, 1.2], [30.0, 20.0, 3.0]]) + world_offset
    data, samples = [], []
    for si in range(2):
        stamp = f"2464-11-12T01:04:1{si}.000000Z"
        lid_pose = ego[si] @ lid_to_ego
        cam_pose = ego[si] @ cam_to_ego
        pts = (world_pts - lid_pose[:3, 3]) @ lid_pose[:3, :3]  # world → sensor frame
        np.savez(root / f"point_cloud/LIDAR/{si}.npz", data=np.concatenate([pts, np.ones((3, 1))], 1))
        Image.fromarray(np.full((H_IMG, W_IMG, 3), 40 * si, np.uint8)).save(root / f"rgb/CAM/{si}.jpg")
        anns = [
            {
                "box": {
                    "length": 4.0,
                    "width": 2.0,
                    "height": 1.5,
                    "pose": _pose(np.linalg.inv(lid_pose) @ poses[si]),
                },
                "class_id": cls,
                "instance_id": iid,
            }
            for iid, (poses, cls) in boxes.items()
        ]
        (root / f"bounding_box_3d/LIDAR/{si}.json").write_text(json.dumps({"annotations": anns}))
        keys = [f"l{si}", f"c{si}"]
        data.append(
            {
                "key": keys[0],
                "id": {"name": "LIDAR", "timestamp": stamp},
                "datum": {
                    "point_cloud": {
                        "filename": f"point_cloud/LIDAR/{si}.npz",
                        "pose": _pose(lid_pose),
                        "annotations": {"1": f"bounding_box_3d/LIDAR/{si}.json"},
                    }
                },
            }
        )
        data.append(
            {
                "key": keys[1],
                "id": {"name": "CAM", "timestamp": stamp.replace(":1" + str(si) + ".", f":0{9 - si}.9")},
                "datum": {
                    "image": {
                        "filename": f"rgb/CAM/{si}.jpg",
                        "width": W_IMG,
                        "height": H_IMG,
                        "pose": _pose(cam_pose),
                    }
                },
            }
        )
        samples.append({"calibration_key": "c0", "datum_keys": keys, "id": {"timestamp": stamp}})
    scene = {"samples": samples, "data": data, "ontologies": {"1": "o1"}}
    (root / "scene_abc.json").write_text(json.dumps(scene))
    return {
        "ego": ego,
        "lid_to_ego": lid_to_ego,
        "cam_to_ego": cam_to_ego,
        "boxes": boxes,
        "world_pts": world_pts,
        "offset": world_offset,
    }


class TestDgpPose:
    def test_matches_rotation(self):
        R = _rigid(0.7, (1.0, 2.0, 3.0), CAM_IN_EGO)
        np.testing.assert_allclose(dgp_pose_to_matrix(_pose(R)), R, atol=1e-12)

    def test_negative_and_unnormalised_quaternion(self):
        p = _pose(_rigid(0.7, (0.0, 0.0, 0.0)))
        p2 = {"rotation": {k: -3 * v for k, v in p["rotation"].items()}, "translation": p["translation"]}
        np.testing.assert_allclose(dgp_pose_to_matrix(p2), dgp_pose_to_matrix(p), atol=1e-12)

    def test_exception(self):
        with pytest.raises(ValueError, match="rotation"):
            dgp_pose_to_matrix({"translation": {"x": 0, "y": 0, "z": 0}})
        with pytest.raises(ValueError, match="finite"):
            dgp_pose_to_matrix(
                {
                    "rotation": dict.fromkeys(("qw", "qx", "qy", "qz"), 0.0),
                    "translation": dict.fromkeys("xyz", 0.0),
                }
            )


class TestPointsInBoxes:
    def test_feature(self):
        T = torch.eye(4)[None].repeat(2, 1, 1)
        T[1, :3, 3] = torch.tensor([10.0, 0, 0])
        T[1, :2, :2] = torch.tensor([[0.0, -1], [1, 0]])  # yawed 90°: length along world y
        pts = torch.tensor([[1.9, 0.9, 0.0], [10.0, 1.9, 0.0], [11.9, 0.0, 0.0], [0.0, 0.0, 0.8]])
        got = points_in_boxes(pts, T, torch.tensor([[4.0, 2.0, 1.5], [4.0, 2.0, 1.5]]))
        assert got.tolist() == [[True, False, False, False], [False, True, False, False]]


class TestLoadDgpSynthetic:
    def test_smoke(self, tmp_path):
        write_dgp(tmp_path / "s")
        scene = load_dgp(tmp_path / "s")
        assert isinstance(scene, Scene) and scene.num_views == 2 and scene.camera_names == ["CAM"]
        assert load_dgp(tmp_path / "s" / "scene_abc.json").num_views == 2

    def test_frames_and_poses(self, tmp_path):
        syn = write_dgp(tmp_path / "s")
        scene = load_dgp(tmp_path / "s", recenter=False)
        for fi in range(2):
            e2w = torch.from_numpy(syn["ego"][fi]).float()
            torch.testing.assert_close(scene.frames[fi].ego_to_world, e2w)
            c2w = torch.from_numpy(syn["ego"][fi] @ syn["cam_to_ego"]).float()
            torch.testing.assert_close(scene.views[fi].cam_to_world, c2w)
        torch.testing.assert_close(
            scene.cameras_info["CAM"].cam_to_ego, torch.from_numpy(syn["cam_to_ego"]).float()
        )
        assert [f.timestamp for f in scene.frames] == [0.0, 1.0]
        assert scene.views[0].timestamp == pytest.approx(-0.1)

    def test_recenter(self, tmp_path):
        syn = write_dgp(tmp_path / "s")
        scene = load_dgp(tmp_path / "s")
        torch.testing.assert_close(scene.frames[0].ego_to_world[:3, 3], torch.zeros(3))
        lid = scene.lidar(1)
        torch.testing.assert_close(
            lid.points, torch.from_numpy(syn["world_pts"] - syn["offset"]).float(), atol=1e-4, rtol=0
        )
        want_origin = (syn["ego"][1] @ syn["lid_to_ego"])[:3, 3] - syn["offset"]
        torch.testing.assert_close(lid.origin, torch.from_numpy(want_origin).float())

    def test_intrinsics_and_scale(self, tmp_path):
        write_dgp(tmp_path / "s")
        full = load_dgp(tmp_path / "s")
        torch.testing.assert_close(
            full.cameras_info["CAM"].K, torch.tensor([[20.0, 0, 7.5], [0, 21.0, 5.5], [0, 0, 1]])
        )
        half = load_dgp(tmp_path / "s", scale=0.5)
        assert half.image_size(0) == (H_IMG // 2, W_IMG // 2)
        torch.testing.assert_close(
            half.cameras_info["CAM"].K, torch.tensor([[10.0, 0, 3.5], [0, 10.5, 2.5], [0, 0, 1]])
        )
        img = half.load_images([1])
        assert img.shape == (1, 3, H_IMG // 2, W_IMG // 2) and img.dtype == torch.float32
        assert abs(img.mean().item() - 40 / 255) < 0.02

    def test_distortion_is_undistorted(self, tmp_path):
        """A calibration with OpenCV distortion: pinhole K, images remapped as cv2 would."""
        cv2 = pytest.importorskip("cv2")
        root = tmp_path / "s"
        write_dgp(root)
        cal_path = root / "calibration" / "c0.json"
        cal = json.loads(cal_path.read_text())
        dist = {"k1": 0.12, "k2": -0.03, "p1": 0.004, "p2": -0.002, "k3": 0.0, "fov": 60.0}
        cal["intrinsics"][1].update(dist)
        cal_path.write_text(json.dumps(cal))
        yy, xx = np.mgrid[0:H_IMG, 0:W_IMG]
        raw = np.stack([xx * 15, yy * 20, (xx + yy) * 8], -1).astype(np.uint8)
        Image.fromarray(raw).save(root / "rgb/CAM/1.jpg", quality=100)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            scene = load_dgp(root)
        K_raw = np.array([[20.0, 0, 7.5], [0, 21.0, 5.5], [0, 0, 1]])
        K = scene.cameras_info["CAM"].K.double().numpy()
        assert K[0, 0] != 20.0 and K[0, 0] / 20.0 == pytest.approx(K[1, 1] / 21.0)
        coeffs = np.array([dist[k] for k in ("k1", "k2", "p1", "p2", "k3")])
        mx, my = cv2.initUndistortRectifyMap(K_raw, coeffs, None, K, (W_IMG, H_IMG), cv2.CV_32FC1)
        decoded = np.asarray(Image.open(root / "rgb/CAM/1.jpg").convert("RGB")).astype(np.float32) / 255
        want = cv2.remap(decoded, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        got = scene.load_images([1])[0].permute(1, 2, 0).numpy()
        np.testing.assert_allclose(got, want, atol=1e-4)
        # a raw pixel, undistorted by OpenCV, lands where the reader's pinhole image holds its content
        raw_px = np.array([[[2.0, 3.0]], [[14.5, 10.0]], [[8.2, 1.7]]])
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)
        pinhole = cv2.undistortPoints(raw_px, K_raw, coeffs, P=K, criteria=crit)[:, 0].astype(np.float32)
        source = cv2.remap(np.stack([mx, my], -1), pinhole[None, :, 0], pinhole[None, :, 1], cv2.INTER_LINEAR)
        np.testing.assert_allclose(source[0], raw_px[:, 0], atol=0.05)  # bilinear in a 16x12 map

    def test_other_camera_models_are_refused(self, tmp_path):
        root = tmp_path / "s"
        write_dgp(root)
        cal_path = root / "calibration" / "c0.json"
        cal = json.loads(cal_path.read_text())
        cal["intrinsics"][1].update({"fisheye": 1, "xi": 0.5})
        cal_path.write_text(json.dumps(cal))
        with pytest.raises(ValueError, match=r"intrinsics\[CAM\]: camera model parameters .*'fisheye': 1"):
            load_dgp(root)

    def test_lidar_lands_in_camera(self, tmp_path):
        syn = write_dgp(tmp_path / "s")
        scene = load_dgp(tmp_path / "s")
        cams = scene.cameras([0])
        uv, z = project_points(scene.lidar(0).points[None], cams.K, cams.world_to_cam)
        # by hand: the first point in the camera frame of sample 0
        p = np.linalg.inv(syn["ego"][0] @ syn["cam_to_ego"]) @ np.append(syn["world_pts"][0], 1.0)
        torch.testing.assert_close(z[0, 0], torch.tensor(p[2]).float(), atol=1e-4, rtol=0)
        torch.testing.assert_close(
            uv[0, 0],
            torch.tensor([20 * p[0] / p[2] + 7.5, 21 * p[1] / p[2] + 5.5]).float(),
            atol=1e-3,
            rtol=0,
        )

    def test_tracks_and_instances(self, tmp_path):
        syn = write_dgp(tmp_path / "s")
        scene = load_dgp(tmp_path / "s", recenter=False)
        assert sorted(scene.tracks) == [7, 9]
        assert scene.classes() == {7: "car", 9: "bus_rv_caravan"}
        assert scene.instances[7].dynamic and not scene.instances[9].dynamic
        t = scene.tracks[7]
        assert t.valid.tolist() == [True, True]
        torch.testing.assert_close(t.size_lwh, torch.tensor([4.0, 2.0, 1.5]))
        for fi in range(2):
            torch.testing.assert_close(
                t.object_to_world[fi], torch.from_numpy(syn["boxes"][7][0][fi]).float()
            )
        # LiDAR points inside box 7 at frame 0 are labelled with its id
        assert scene.lidar(0).instance.tolist() == [7, 7, 0]
        assert scene.lidar(1).instance.tolist() == [0, 0, 0]  # the car moved on by 4 m

    def test_split(self, tmp_path):
        write_dgp(tmp_path / "s")
        scene = load_dgp(tmp_path / "s", test_frames=[1])
        assert scene.train_frames == [0] and scene.test_frames == [1]
        assert scene.train_views == [0] and scene.test_views == [1]

    def test_no_lidar(self, tmp_path):
        write_dgp(tmp_path / "s")
        scene = load_dgp(tmp_path / "s", lidar=None)
        assert scene.lidar_loader is None and scene.tracks == {}
        with pytest.raises(FileNotFoundError, match="no LiDAR"):
            scene.lidar(0)

    def test_exception(self, tmp_path):
        with pytest.raises(FileNotFoundError, match="no such folder"):
            load_dgp(tmp_path / "nope")
        (tmp_path / "empty").mkdir()
        with pytest.raises(FileNotFoundError, match="no scene"):
            load_dgp(tmp_path / "empty")
        write_dgp(tmp_path / "s")
        with pytest.raises(ValueError, match="unknown camera 'CAMERA_99'"):
            load_dgp(tmp_path / "s", cameras=["CAMERA_99"])
        with pytest.raises(ValueError, match="lidar: unknown sensor"):
            load_dgp(tmp_path / "s", lidar="VELODYNE")
        with pytest.raises(ValueError, match="test_frames"):
            load_dgp(tmp_path / "s", test_frames=[5])
        with pytest.raises(ValueError, match="scale"):
            load_dgp(tmp_path / "s", scale=-1)

    def test_broken_files(self, tmp_path):
        def broken(name: str, edit) -> Path:
            root = tmp_path / name
            write_dgp(root)
            edit(root)
            return root

        def drop(path: Path, *keys: str) -> None:
            d = json.loads(path.read_text())
            node = d
            for k in keys[:-1]:
                node = node[int(k)] if isinstance(node, list) else node[k]
            del node[keys[-1]]
            path.write_text(json.dumps(d))

        root = broken("json", lambda r: (r / "scene_abc.json").write_text("{ nope"))
        with pytest.raises(ValueError, match="not valid JSON"):
            load_dgp(root)
        root = broken("samples", lambda r: drop(r / "scene_abc.json", "samples"))
        with pytest.raises(ValueError, match="missing key 'samples'"):
            load_dgp(root)
        root = broken("pose", lambda r: drop(r / "scene_abc.json", "data", "1", "datum", "image", "pose"))
        with pytest.raises(ValueError, match="missing key 'pose'"):
            load_dgp(root)
        root = broken("fx", lambda r: drop(r / "calibration" / "c0.json", "intrinsics", "1", "fx"))
        with pytest.raises(ValueError, match="missing key 'fx'"):
            load_dgp(root)
        root = broken("calib", lambda r: (r / "calibration" / "c0.json").unlink())
        with pytest.raises(FileNotFoundError, match="calibration"):
            load_dgp(root)
        root = broken("image", lambda r: (r / "rgb" / "CAM" / "1.jpg").unlink())
        with pytest.raises(FileNotFoundError, match=r"1 referenced file\(s\) missing"):
            load_dgp(root)

        def nan_pose(r: Path) -> None:
            d = json.loads((r / "scene_abc.json").read_text())
            d["data"][1]["datum"]["image"]["pose"]["translation"]["x"] = float("nan")
            (r / "scene_abc.json").write_text(json.dumps(d))

        with pytest.raises(ValueError, match="finite"):
            load_dgp(broken("nan", nan_pose))


# -- the real DGP test scenes ------------------------------------------------------------------------------


def _box_corners(object_to_world: torch.Tensor, size_lwh: torch.Tensor) -> torch.Tensor:
    signs = torch.tensor(
        [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=torch.float32
    )
    local = signs * size_lwh / 2
    return local @ object_to_world[:3, :3].T + object_to_world[:3, 3]


def _box_checks(scene: Scene, root: Path, world_to_cam_of) -> tuple[list[float], list[float]]:
    """IoU of projected 3D boxes with the annotated 2D boxes, and the share of each box's LiDAR
    points that land inside its annotated 2D box (10 % margin)."""
    ious, inside = [], []
    for frame in scene.frames:
        lid = scene.lidar(frame.index)
        for vid in frame.view_ids:
            view = scene.views[vid]
            K = scene.cameras_info[view.camera].K[None]
            w2c = world_to_cam_of(vid)[None]
            H, W = scene.image_size(vid)
            uv, z = project_points(lid.points[None], K, w2c)
            uv, z = uv[0], z[0]
            ann_file = root / "bounding_box_2d" / view.camera / f"{frame.lidar.stem}.json"
            for a in json.loads(ann_file.read_text())["annotations"]:
                b = a["box"]
                x0, y0, x1, y1 = b["x"], b["y"], b["x"] + b["w"], b["y"] + b["h"]
                track = scene.tracks[a["instance_id"]]
                cuv, cz = project_points(
                    _box_corners(track.object_to_world[frame.index], track.size_lwh)[None], K, w2c
                )
                if bool((cz <= 0).any()):
                    ious.append(0.0)
                    continue
                px0, py0 = cuv[0].min(0).values.clamp(min=0).tolist()
                px1, py1 = cuv[0].max(0).values.tolist()
                px1, py1 = min(px1, W), min(py1, H)
                inter = max(0.0, min(x1, px1) - max(x0, px0)) * max(0.0, min(y1, py1) - max(y0, py0))
                union = (x1 - x0) * (y1 - y0) + max(0.0, px1 - px0) * max(0.0, py1 - py0) - inter
                ious.append(inter / union)
                mine = (lid.instance == a["instance_id"]) & (z > 0)
                if int(mine.sum()) >= 3:
                    q, m = uv[mine], 0.1 * max(x1 - x0, y1 - y0)
                    ok = (q[:, 0] >= x0 - m) & (q[:, 0] <= x1 + m) & (q[:, 1] >= y0 - m) & (q[:, 1] <= y1 + m)
                    inside.append(ok.float().mean().item())
    return ious, inside


def _lidar_coverage(scene: Scene, world_to_cam_of) -> float:
    """Share of LiDAR returns at 3–60 m that land in front of and inside at least one camera."""
    shares = []
    for frame in scene.frames:
        lid = scene.lidar(frame.index)
        lid = lid._replace(points=lid.points[::4])
        r = (lid.points - lid.origin).norm(dim=-1)
        keep = (r > 3) & (r < 60)
        seen = torch.zeros(len(r), dtype=torch.bool)
        for vid in frame.view_ids:
            K = scene.cameras_info[scene.views[vid].camera].K[None]
            uv, z = project_points(lid.points[None], K, world_to_cam_of(vid)[None])
            H, W = scene.image_size(vid)
            u, v = uv[0, :, 0], uv[0, :, 1]
            seen |= (z[0] > 0) & (u >= -0.5) & (u < W - 0.5) & (v >= -0.5) & (v < H - 0.5)
        shares.append(seen[keep].float().mean().item())
    return min(shares)


def _photo_error(scene: Scene, images: dict[int, torch.Tensor], perturb: torch.Tensor | None) -> float:
    """Median over cameras of the mean colour difference (0–255) of static LiDAR points (frame 1)
    seen in that camera at frames 0 and 2 (2.5 m apart); visibility by a 3-px z-buffer."""
    lid = scene.lidar(1)
    pts = lid.points[lid.instance == 0][::2]  # every other return is plenty

    def sample(vid: int, w2c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        H, W = scene.image_size(vid)
        uv, z = project_points(pts[None], scene.cameras_info[scene.views[vid].camera].K[None], w2c[None])
        uv, z = uv[0], z[0]
        ok = (
            (z > 2) & (z < 40) & (uv[:, 0] >= 0) & (uv[:, 0] <= W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= H - 1)
        )
        cell = 3
        ij = (uv / cell).floor().long()
        ij[:, 0] = ij[:, 0].clamp(0, W // cell)
        ij[:, 1] = ij[:, 1].clamp(0, H // cell)
        lin = ij[:, 1] * (W // cell + 1) + ij[:, 0]
        zbuf = torch.full(((W // cell + 1) * (H // cell + 1),), float("inf"))
        zbuf.scatter_reduce_(0, lin[ok], z[ok], reduce="amin")
        ok &= z <= zbuf[lin] * 1.03
        grid = torch.stack([2 * uv[:, 0] / (W - 1) - 1, 2 * uv[:, 1] / (H - 1) - 1], -1)
        col = F.grid_sample(images[vid][None], grid[None, None], align_corners=True)[0, :, 0].T
        return ok, col

    errs = []
    for cam in scene.camera_names:
        a, b = scene.view_id(0, cam), scene.view_id(2, cam)
        w2c_b = invert_rigid(scene.views[b].cam_to_world)
        if perturb is not None:
            w2c_b = perturb @ w2c_b
        ok_a, col_a = sample(a, invert_rigid(scene.views[a].cam_to_world))
        ok_b, col_b = sample(b, w2c_b)
        ok = ok_a & ok_b
        errs.append(255 * (col_a[ok] - col_b[ok]).abs().mean().item())
    return float(np.median(errs))


@pytest.fixture(scope="module")
def scene02() -> Scene:
    return load_dgp(DGP / "scene_02")


@needs_dgp
class TestLoadDgpReal:
    def test_cardinality(self, scene02):
        s = scene02
        assert len(s.frames) == 3 and s.num_views == 18 and len(s.camera_names) == 6
        assert s.camera_names[0] == "CAMERA_01" and s.image_size(0) == (1216, 1936)
        assert len(s.tracks) == 13 and set(s.classes().values()) <= {"car", "truck"}
        assert all(v.instances is None and v.depth is None for v in s.views)
        lid = s.lidar(0)
        assert lid.points.shape == (47230, 3) and lid.points.dtype == torch.float32
        assert lid.instance.dtype == torch.int64 and int((lid.instance > 0).sum()) > 500
        # the ego drives about 1.27 m per sample; the world has z up (camera y axis points down)
        steps = [f.ego_to_world[:3, 3] for f in s.frames]
        assert 1.1 < (steps[1] - steps[0]).norm() < 1.4
        assert s.views[0].cam_to_world[2, 1] < -0.99

    def test_camera_pose_is_lidar_pose_times_extrinsic(self, scene02):
        for view in scene02.views:
            via_ego = scene02.frames[view.frame].ego_to_world @ scene02.cameras_info[view.camera].cam_to_ego
            assert (via_ego[:3, 3] - view.cam_to_world[:3, 3]).norm() < 0.06  # camera fired ~90 ms earlier
            assert (via_ego[:3, :3] - view.cam_to_world[:3, :3]).abs().max() < 2e-3

    def test_lidar_lands_in_the_cameras(self, scene02):
        right = _lidar_coverage(scene02, lambda v: invert_rigid(scene02.views[v].cam_to_world))
        assert right > 0.95  # six cameras cover 360°: almost every return at 3–60 m is seen

        def wrong(v: int) -> torch.Tensor:  # the extrinsic inverted the wrong way round
            view = scene02.views[v]
            c2w = scene02.frames[view.frame].ego_to_world @ invert_rigid(
                scene02.cameras_info[view.camera].cam_to_ego
            )
            return invert_rigid(c2w)

        assert _lidar_coverage(scene02, wrong) < 0.5

    def test_boxes_match_annotated_2d_boxes(self, scene02):
        root = DGP / "scene_02"
        ious, inside = _box_checks(scene02, root, lambda v: invert_rigid(scene02.views[v].cam_to_world))
        assert len(ious) >= 30 and np.median(ious) > 0.9 and min(ious) > 0.7
        assert len(inside) >= 15 and min(inside) > 0.95
        ious_bad, inside_bad = _box_checks(scene02, root, lambda v: scene02.views[v].cam_to_world)
        assert np.median(ious_bad) < 0.1 and (not inside_bad or max(inside_bad) < 0.5)

    def test_photometric_consistency(self):
        scene = load_dgp(DGP / "scene_02", scale=0.25)
        ids = [scene.view_id(f, c) for c in scene.camera_names for f in (0, 2)]
        images = dict(zip(ids, scene.load_images(ids)))
        right = _photo_error(scene, images, None)
        tilt = torch.eye(4)
        a = math.radians(0.5)
        tilt[1:3, 1:3] = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        wrong = _photo_error(scene, images, tilt)
        assert right < 15 and wrong > 1.3 * right

    def test_scene_01_static_ego(self):
        s = load_dgp(DGP / "scene_01", scale=0.5)
        assert s.camera_names == ["CAMERA_01", "CAMERA_05", "CAMERA_06"] and s.num_views == 9
        moves = [(f.ego_to_world[:3, 3]).norm().item() for f in s.frames]
        assert max(moves) < 0.05
        assert s.load_images([0]).shape == (1, 3, 608, 968)
