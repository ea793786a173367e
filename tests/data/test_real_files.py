"""The nuScenes and Waymo readers on real files (``../shared/data/real``; skipped when absent).

- nuScenes: one real keyframe of scene-0061 (six cameras, LIDAR_TOP, calibration and ego poses),
  as verbatim hand-trimmed tables (``v1.0-test``) and with the missing links added
  (``v1.0-test-linked``). The LiDAR is projected with the official devkit's formula written out
  here by hand (``map_pointcloud_to_image``: lidar → ego → global → ego at the camera's time →
  camera → ``K``), not imported.
- Waymo: one real frame as v2 parquet components (five distorted cameras at two image sizes,
  75 boxes, no LiDAR) and two genuine v2 release files (a float32 ``vehicle_pose``, a
  ``camera_hkp`` whose ``key.camera_name`` is a string). Boxes are compared with Waymo's own
  ``projected_lidar_box``; undistortion with OpenCV's ``projectPoints`` / ``undistortPoints``.

``docs/data.md`` ("Checked on real files") quotes the numbers these tests measure.
"""

from __future__ import annotations

import io
import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from vadgs.data import load_nuscenes, load_scene
from vadgs.geometry import project_points

REAL = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real"
NUS = REAL / "nuscenes_s0061_kf0"
WAYMO = REAL / "waymo_one_frame" / "v2_from_v1_pvps"
WAYMO_RELEASE = REAL / "waymo_one_frame" / "v2_release_testdata"
SEG = "1024360143612057520_3580_000_3600_000"
RELEASE_SEG = "10023947602400723454_1120_000_1140_000"
NUS_CAMERAS = [
    "CAM_FRONT_LEFT",
    "CAM_FRONT",
    "CAM_FRONT_RIGHT",
    "CAM_BACK_RIGHT",
    "CAM_BACK",
    "CAM_BACK_LEFT",
]
WAYMO_NAMES = {1: "FRONT", 2: "FRONT_LEFT", 3: "FRONT_RIGHT", 4: "SIDE_LEFT", 5: "SIDE_RIGHT"}

pytestmark = pytest.mark.shared
needs_nus = pytest.mark.skipif(not (NUS / "v1.0-test-linked").is_dir(), reason="needs ../shared/data/real")
needs_waymo = pytest.mark.skipif(not WAYMO.is_dir(), reason="needs ../shared/data/real")


# -- nuScenes ------------------------------------------------------------------------------------------


def _quat_to_matrix(q) -> np.ndarray:
    """pyquaternion's ``Quaternion(w, x, y, z).rotation_matrix``, by hand."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def devkit_lidar_to_image(version: str, camera: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``NuScenes.map_pointcloud_to_image`` (nuscenes-devkit) for the keyframe's LIDAR_TOP sweep.

    Returns ``(uv (2, N), depth (N,), mask (N,))``: the pixel of every LiDAR point, its depth in the
    camera, and the devkit's mask (depth > 1 m, 1 px inside the image borders).
    """
    meta = NUS / version
    table = {
        n: {r["token"]: r for r in json.loads((meta / f"{n}.json").read_text())}
        for n in ("sample_data", "calibrated_sensor", "ego_pose", "sensor")
    }

    def channel(sd: dict) -> str:
        return table["sensor"][table["calibrated_sensor"][sd["calibrated_sensor_token"]]["sensor_token"]][
            "channel"
        ]

    by_channel = {channel(sd): sd for sd in table["sample_data"].values() if sd["is_key_frame"]}
    lidar, cam = by_channel["LIDAR_TOP"], by_channel[camera]
    points = np.fromfile(NUS / lidar["filename"], dtype=np.float32).reshape(-1, 5)[:, :3].T.astype(np.float64)
    # 1. lidar -> ego at the sweep's time (calibrated_sensor of LIDAR_TOP)
    cs = table["calibrated_sensor"][lidar["calibrated_sensor_token"]]
    points = _quat_to_matrix(cs["rotation"]) @ points + np.array(cs["translation"])[:, None]
    # 2. ego -> global (ego_pose of the sweep)
    pose = table["ego_pose"][lidar["ego_pose_token"]]
    points = _quat_to_matrix(pose["rotation"]) @ points + np.array(pose["translation"])[:, None]
    # 3. global -> ego at the image's time (ego_pose of the camera reading)
    pose = table["ego_pose"][cam["ego_pose_token"]]
    points = _quat_to_matrix(pose["rotation"]).T @ (points - np.array(pose["translation"])[:, None])
    # 4. ego -> camera (calibrated_sensor of the camera)
    cs = table["calibrated_sensor"][cam["calibrated_sensor_token"]]
    points = _quat_to_matrix(cs["rotation"]).T @ (points - np.array(cs["translation"])[:, None])
    # 5. view_points(points, camera_intrinsic, normalize=True)
    depth = points[2]
    uv = (np.array(cs["camera_intrinsic"]) @ (points / depth))[:2]
    mask = (
        (depth > 1.0) & (uv[0] > 1) & (uv[0] < cam["width"] - 1) & (uv[1] > 1) & (uv[1] < cam["height"] - 1)
    )
    return uv, depth, mask


def nuscenes_lidar_errors(version: str = "v1.0-test-linked") -> dict[str, tuple[int, float]]:
    """Per camera: (points in the image, max pixel distance vadgs ↔ devkit formula)."""
    scene = load_nuscenes(NUS, "scene-0061", version=version)
    world = scene.lidar(0).points
    out = {}
    for cam in scene.camera_names:
        uv, depth, mask = devkit_lidar_to_image(version, cam)
        cams = scene.cameras([scene.view_id(0, cam)])
        got, z = project_points(world[None], cams.K, cams.world_to_cam)
        err = np.linalg.norm(got[0].double().numpy().T - uv, axis=0)[mask]
        np.testing.assert_allclose(z[0].numpy()[mask], depth[mask], atol=1e-3)
        out[cam] = (int(mask.sum()), float(err.max()))
    return out


@needs_nus
class TestNuscenesReal:
    def test_linked_tables_give_six_views(self):
        scene = load_nuscenes(NUS, "scene-0061", version="v1.0-test-linked")
        assert scene.camera_names == NUS_CAMERAS and scene.num_views == 6 and len(scene.frames) == 1
        assert {scene.image_size(v) for v in range(6)} == {(900, 1600)}
        assert scene.tracks == {} and scene.instances == {}  # sample_annotation.json is []
        assert scene.lidar(0).points.shape == (34688, 3)
        img = scene.load_images([scene.view_id(0, "CAM_FRONT")])
        assert img.shape == (1, 3, 900, 1600) and 0.1 < float(img.mean()) < 0.9

    def test_lidar_projects_as_the_devkit(self):
        errors = nuscenes_lidar_errors()
        assert sorted(errors) == sorted(NUS_CAMERAS)
        for cam, (n, err) in errors.items():
            assert n > 2000, cam  # thousands of points in every image
            assert err < 0.1, (cam, err)

    def test_trimmed_tables_load_without_tracks(self):
        """The verbatim tables lack the annotation tables, log, map and every link: 0 tracks."""
        trimmed = load_nuscenes(NUS, "scene-0061", version="v1.0-test")
        linked = load_nuscenes(NUS, "scene-0061", version="v1.0-test-linked")
        assert trimmed.num_views == 6 and trimmed.tracks == {} and trimmed.instances == {}
        for a, b in zip(trimmed.views, linked.views):
            assert a.camera == b.camera and a.image == b.image
            torch.testing.assert_close(a.cam_to_world, b.cam_to_world, atol=0, rtol=0)
        torch.testing.assert_close(trimmed.lidar(0).points, linked.lidar(0).points, atol=0, rtol=0)

    def test_trimmed_tables_without_a_required_table_name_it(self, tmp_path):
        root = tmp_path / "nus"
        (root / "v1.0-test").mkdir(parents=True)
        for p in (NUS / "v1.0-test").glob("*.json"):
            if p.name != "ego_pose.json":
                shutil.copy(p, root / "v1.0-test" / p.name)
        with pytest.raises(FileNotFoundError, match=r"nuScenes table ego_pose\.json: missing file") as e:
            load_nuscenes(root, "scene-0061", version="v1.0-test")
        assert "\n" not in str(e.value)


# -- Waymo ---------------------------------------------------------------------------------------------


def _table(component: str, root: Path = WAYMO, segment: str = SEG, columns=None) -> dict:
    import pyarrow.parquet as pq

    return pq.read_table(root / component / f"{segment}.parquet", columns=columns).to_pydict()


def waymo_raw_cameras() -> dict[str, tuple[np.ndarray, np.ndarray, tuple[int, int]]]:
    """Per camera from the calibration file: raw K (pixel centres at integers), k1, k2, p1, p2, k3, (H, W)."""
    cc = _table("camera_calibration")
    p = "[CameraCalibrationComponent]."
    out = {}
    for i, c in enumerate(cc["key.camera_name"]):
        fu, fv, cu, cv = (cc[f"{p}intrinsic.{k}"][i] for k in ("f_u", "f_v", "c_u", "c_v"))
        K = np.array([[fu, 0.0, cu - 0.5], [0.0, fv, cv - 0.5], [0.0, 0.0, 1.0]])
        dist = np.array([cc[f"{p}intrinsic.{k}"][i] for k in ("k1", "k2", "p1", "p2", "k3")])
        out[WAYMO_NAMES[c]] = (K, dist, (cc[f"{p}height"][i], cc[f"{p}width"][i]))
    return out


def _box_corners(center, size, heading) -> np.ndarray:
    signs = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
    c, s = np.cos(heading), np.sin(heading)
    return (signs * size) @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T + center


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def _clip(box: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    h, w = size
    return np.r_[np.maximum(box[:2], -0.5), np.minimum(box[2:], [w - 0.5, h - 0.5])]


def waymo_box_ious(vehicles_from_tracks: bool = False) -> dict[str, list[float]]:
    """IoU of every 3D box projected with vadgs's cameras vs Waymo's ``projected_lidar_box``.

    Boxes come from ``lidar_box`` placed with the reader's vehicle pose (or, with
    ``vehicles_from_tracks``, only the vehicles, from the reader's own tracks). Each box's 8 corners
    (all in front of the camera) are projected and their bounding rectangle is clipped to the image,
    as Waymo's are. Returns the IoUs of three projections:

    - ``"pinhole"``: the reader's pinhole camera into the undistorted image, against Waymo's box
      whose corners are undistorted by OpenCV into the same image;
    - ``"distorted"``: the reader's camera pose with the raw K and distortion (OpenCV's
      ``projectPoints``), against Waymo's box in the raw image;
    - ``"distortion_ignored"``: the raw K without distortion (what vadgs did before), raw image.
    """
    cv2 = pytest.importorskip("cv2")
    from vadgs.data import load_waymo

    scene = load_waymo(WAYMO, SEG, lasers=None, min_motion_m=None)
    raw = waymo_raw_cameras()
    e2w = scene.frames[0].ego_to_world.double().numpy()
    corners_world: dict[str, np.ndarray] = {}
    if vehicles_from_tracks:
        for t in scene.tracks.values():
            name = scene.instances[t.id].name
            local = _box_corners(np.zeros(3), t.size_lwh.double().numpy(), 0.0)
            o2w = t.object_to_world[0].double().numpy()
            corners_world[name] = local @ o2w[:3, :3].T + o2w[:3, 3]
    else:
        lb = _table("lidar_box")
        p = "[LiDARBoxComponent].box."
        for i, obj in enumerate(lb["key.laser_object_id"]):
            centre = np.array([lb[f"{p}center.{a}"][i] for a in "xyz"])
            size = np.array([lb[f"{p}size.{a}"][i] for a in "xyz"])
            local = _box_corners(centre, size, lb[f"{p}heading"][i])
            corners_world[obj] = local @ e2w[:3, :3].T + e2w[:3, 3]
    pb = _table("projected_lidar_box")
    q = "[ProjectedLiDARBoxComponent].box."
    out: dict[str, list[float]] = {"pinhole": [], "distorted": [], "distortion_ignored": []}
    for i, obj in enumerate(pb["key.laser_object_id"]):
        if obj not in corners_world:
            continue
        cam = WAYMO_NAMES[pb["key.camera_name"][i]]
        K_raw, dist, size = raw[cam]
        cams = scene.cameras([scene.view_id(0, cam)])
        w2c = cams.world_to_cam[0].double().numpy()
        pc = corners_world[obj] @ w2c[:3, :3].T + w2c[:3, 3]
        if (pc[:, 2] < 0.5).any():
            continue
        cx, cy, sx, sy = (pb[f"{q}{k}"][i] for k in ("center.x", "center.y", "size.x", "size.y"))
        waymo = (
            np.array([cx - sx / 2, cy - sy / 2, cx + sx / 2, cy + sy / 2]) - 0.5
        )  # edge → centre convention
        K = cams.K[0].double().numpy()
        uv, _ = project_points(
            torch.from_numpy(corners_world[obj])[None], torch.from_numpy(K)[None], torch.from_numpy(w2c)[None]
        )
        uv = uv[0].numpy()
        rect = np.array(
            [[waymo[0], waymo[1]], [waymo[2], waymo[1]], [waymo[0], waymo[3]], [waymo[2], waymo[3]]]
        )
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)
        rect_pinhole = cv2.undistortPoints(rect[:, None], K_raw, dist, P=K, criteria=crit)[:, 0]
        out["pinhole"].append(
            _iou(
                _clip(np.r_[uv.min(0), uv.max(0)], size),
                _clip(np.r_[rect_pinhole.min(0), rect_pinhole.max(0)], size),
            )
        )
        distorted = cv2.projectPoints(pc, np.zeros(3), np.zeros(3), K_raw, dist)[0][:, 0]
        out["distorted"].append(_iou(_clip(np.r_[distorted.min(0), distorted.max(0)], size), waymo))
        plain = pc[:, :2] / pc[:, 2:] @ K_raw[:2, :2].T + K_raw[:2, 2]
        out["distortion_ignored"].append(_iou(_clip(np.r_[plain.min(0), plain.max(0)], size), waymo))
    return out


def waymo_undistortion_check(
    points_per_camera: int = 400, seed: int = 0
) -> dict[str, tuple[float, float, float]]:
    """Per camera: (max |cv2.undistortPoints(raw pixel) - reader's pinhole projection| in px,
    max |undistorted image at an integer pinhole pixel - raw image at OpenCV's raw pixel|,
    max distance raw pixel ↔ pinhole pixel, i.e. how much undistortion moves a pixel).

    World points are drawn in front of each camera; their raw pixels come from OpenCV's
    ``projectPoints`` with the calibration's K and distortion, the pinhole ones from the reader's
    camera.
    """
    cv2 = pytest.importorskip("cv2")
    from vadgs.data import load_waymo

    scene = load_waymo(WAYMO, SEG, lasers=None)
    raw = waymo_raw_cameras()
    rng = np.random.default_rng(seed)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)
    images = _table("camera_image", columns=["key.camera_name", "[CameraImageComponent].image"])
    out = {}
    for cam, (K_raw, dist, (h, w)) in raw.items():
        vid = scene.view_id(0, cam)
        cams = scene.cameras([vid])
        K = cams.K[0].double().numpy()
        c2w = torch.linalg.inv(cams.world_to_cam[0].double()).numpy()
        # points whose pinhole pixels cover the undistorted image, at 5-60 m
        pix = np.c_[rng.uniform(0, w - 1, points_per_camera), rng.uniform(0, h - 1, points_per_camera)]
        depth = rng.uniform(5.0, 60.0, points_per_camera)
        p_cam = np.c_[(pix - K[:2, 2]) / np.diag(K)[:2], np.ones(points_per_camera)] * depth[:, None]
        p_world = p_cam @ c2w[:3, :3].T + c2w[:3, 3]
        # the reader's pinhole projection (float64 world → camera with the reader's pose)
        uv, _ = project_points(torch.from_numpy(p_world)[None], cams.K.double(), cams.world_to_cam.double())
        uv = uv[0].numpy()
        # Waymo's (OpenCV's) model into the raw image, then OpenCV's undistortion with the reader's K
        raw_px = cv2.projectPoints(p_cam, np.zeros(3), np.zeros(3), K_raw, dist)[0][:, 0]
        back = cv2.undistortPoints(raw_px[:, None], K_raw, dist, P=K, criteria=crit)[:, 0]
        point_err = float(np.abs(back - uv).max())
        # image content: the undistorted image at integer pixels = the raw image at their raw position
        q = np.round(uv[:100]).clip([0, 0], [w - 1, h - 1])
        q_cam = np.c_[(q - K[:2, 2]) / np.diag(K)[:2], np.ones(len(q))]
        q_raw = cv2.projectPoints(q_cam, np.zeros(3), np.zeros(3), K_raw, dist)[0][:, 0].astype(np.float32)
        jpeg = images["[CameraImageComponent].image"][
            images["key.camera_name"].index(next(k for k, n in WAYMO_NAMES.items() if n == cam))
        ]
        raw_img = np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGB")).astype(np.float32) / 255.0
        want = cv2.remap(
            raw_img, q_raw[None, :, 0], q_raw[None, :, 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )[0]
        und = scene.load_images([vid])[0].permute(1, 2, 0).numpy()
        got = und[q[:, 1].astype(int), q[:, 0].astype(int)]
        out[cam] = (
            point_err,
            float(np.abs(got - want).max()),
            float(np.linalg.norm(raw_px - uv, axis=1).max()),
        )
    return out


@needs_waymo
class TestWaymoReal:
    @pytest.fixture(autouse=True)
    def _pyarrow(self):
        pytest.importorskip("pyarrow")

    def test_five_views_at_two_sizes(self):
        from vadgs.data import load_waymo

        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no "distortion is ignored" any more
            scene = load_waymo(WAYMO, SEG, lasers=None)
        assert scene.camera_names == list(WAYMO_NAMES.values()) and scene.num_views == 5
        sizes = [scene.image_size(v) for v in range(5)]
        assert sizes == [(1280, 1920)] * 3 + [(886, 1920)] * 2
        assert [len(g) for g in scene.size_groups()] == [3, 2]
        assert len(scene.instances) == 75
        imgs = [scene.load_images([v]) for v in (0, 3)]
        assert imgs[0].shape == (1, 3, 1280, 1920) and imgs[1].shape == (1, 3, 886, 1920)
        half = load_waymo(WAYMO, SEG, lasers=None, scale=0.5)
        assert half.image_size(3) == (443, 960) and half.load_images([3]).shape == (1, 3, 443, 960)

    def test_undistortion_against_opencv(self):
        for cam, (point_err, image_err, moved) in waymo_undistortion_check().items():
            assert point_err < 0.1, (cam, point_err)  # pinhole K and pose consistent with the raw model
            assert image_err < 2e-3, (cam, image_err)  # the image was remapped with that model
            assert moved > 2.0, (cam, moved)  # the distortion matters (pixels move by several px)

    def test_boxes_project_onto_waymos_projected_boxes(self):
        ious = waymo_box_ious()
        assert len(ious["pinhole"]) >= 50
        assert np.median(ious["pinhole"]) >= 0.9
        assert np.median(ious["distorted"]) >= 0.9
        vehicles = waymo_box_ious(vehicles_from_tracks=True)  # the reader's own tracks
        assert len(vehicles["pinhole"]) >= 20 and np.median(vehicles["pinhole"]) >= 0.9

    def test_release_vehicle_pose_float32(self):
        from vadgs.data.waymo_parquet import read_waymo_poses

        raw = _table("vehicle_pose", WAYMO_RELEASE, RELEASE_SEG)
        col = raw["[VehiclePoseComponent].world_from_vehicle.transform"]
        poses = read_waymo_poses(WAYMO_RELEASE, RELEASE_SEG)
        assert (
            poses.world_from_vehicle.shape == (199, 4, 4) and poses.world_from_vehicle.dtype == torch.float64
        )
        dt = poses.timestamps_us.diff()
        assert bool((dt > 99_000).all() and (dt < 101_000).all())
        R = poses.world_from_vehicle[:, :3, :3]
        torch.testing.assert_close(
            R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(199, 3, 3), atol=1e-5, rtol=0
        )
        order = np.argsort(raw["key.frame_timestamp_micros"])
        want = np.asarray(col, dtype=np.float32)[order].reshape(-1, 4, 4).astype(np.float64)
        np.testing.assert_array_equal(poses.world_from_vehicle.numpy(), want)

    def test_real_frame_with_float32_pose_and_string_camera_names(self, tmp_path):
        """The real frame rewritten as the release files store things: float32 vehicle_pose and
        ``key.camera_name`` strings (as in the release's camera_hkp) loads to the same scene."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        from vadgs.data import load_waymo
        from vadgs.data.waymo_parquet import waymo_camera_name

        hkp = _table("camera_hkp", WAYMO_RELEASE, RELEASE_SEG, columns=["key.camera_name"])["key.camera_name"]
        assert isinstance(hkp[0], str)
        assert {waymo_camera_name(v) for v in hkp} == set(WAYMO_NAMES.values())
        root = tmp_path / "v2"
        shutil.copytree(WAYMO, root)
        for comp in ("camera_calibration", "camera_image"):
            path = root / comp / f"{SEG}.parquet"
            t = pq.read_table(path)
            names = pa.array([WAYMO_NAMES[c] for c in t.column("key.camera_name").to_pylist()], pa.string())
            i = t.schema.get_field_index("key.camera_name")
            pq.write_table(t.set_column(i, "key.camera_name", names), path)
        path = root / "vehicle_pose" / f"{SEG}.parquet"
        t = pq.read_table(path)
        col = "[VehiclePoseComponent].world_from_vehicle.transform"
        i = t.schema.get_field_index(col)
        pq.write_table(t.set_column(i, col, t.column(col).cast(pa.list_(pa.float32(), 16))), path)
        got, want = load_waymo(root, SEG, lasers=None), load_waymo(WAYMO, SEG, lasers=None)
        assert got.camera_names == want.camera_names and got.num_views == 5
        for a, b in zip(got.views, want.views):
            # the recentring offset is the float32 vehicle position (km from the origin): ~1 mm off
            torch.testing.assert_close(a.cam_to_world, b.cam_to_world, atol=2e-3, rtol=0)
        torch.testing.assert_close(got.load_images([4]), want.load_images([4]))

    def test_convert_no_lidar(self, tmp_path, capsys):
        from vadgs.cli import main
        from vadgs.data import load_waymo

        out = tmp_path / "conv"
        args = ["convert", "waymo", str(WAYMO), "--scene", SEG, "--out", str(out), "--scale", "0.25"]
        assert main(args) != 0  # the frame has no lidar component
        assert "Waymo component 'lidar': missing file" in capsys.readouterr().err
        assert main([*args, "--no-lidar"]) == 0
        conv, scene = load_scene(out), load_waymo(WAYMO, SEG, lasers=None, scale=0.25)
        assert conv.num_views == 5 and conv.lidar_loader is None
        assert [conv.image_size(v) for v in range(5)] == [(320, 480)] * 3 + [(222, 480)] * 2
        for name in scene.camera_names:
            torch.testing.assert_close(conv.cameras_info[name].K, scene.cameras_info[name].K)
        torch.testing.assert_close(conv.load_images([3]), scene.load_images([3]), atol=1 / 255, rtol=0)
