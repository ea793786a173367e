"""Tests of vadgs.data.waymo on a tiny Waymo v2 segment written as parquet components."""

from __future__ import annotations

import io
import math
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")

from vadgs.data import Scene, load_waymo  # noqa: E402
from vadgs.data.waymo_lidar import waymo_beam_inclinations, waymo_range_image_to_points  # noqa: E402
from vadgs.data.waymo_parquet import read_waymo_poses, waymo_camera_name  # noqa: E402
from vadgs.geometry import project_points  # noqa: E402

SEG = "1005081002024129653_5313_150_5333_150"
N_FRAMES = 7
T0_US = 1_557_965_000_000_000
YAW = 0.4
GLOBAL = np.array([-3500.0, 1200.0, 150.0])  # Waymo's global frame lies far from the origin
CAM_DX = {1: 0.05, 4: -0.02}  # each image's vehicle pose: the frame's, shifted along the heading
# camera_name: (extrinsic camera → vehicle in Waymo camera axes, f_u, f_v, c_u, c_v, width, height)
CAMS = {
    1: ((0.0, (1.5, 0.0, 1.5)), 20.0, 21.0, 16.0, 12.0, 32, 24),  # FRONT
    4: ((math.pi / 2, (0.0, 1.0, 1.5)), 15.0, 15.0, 16.0, 8.0, 32, 16),  # SIDE_LEFT, looking left
}
LIDAR_EXT = (0.3, (1.5, 0.0, 2.0))  # TOP laser: yaw 0.3, 2 m up
INCL = [-0.2, 0.0, 0.1]  # calibration order (lowest first); range-image rows are top first
RI_W = 9  # column 4 of 9 looks straight ahead in the vehicle frame (azimuth 0 after the yaw)


def rigid(yaw: float, t) -> np.ndarray:
    out = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    out[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    out[:3, 3] = t
    return out


def _ego(f: int, dx: float = 0.0) -> np.ndarray:
    """Vehicle → global at frame f (10 m/s along YAW), shifted by dx metres along the heading."""
    return rigid(YAW, GLOBAL + (f + dx) * np.array([math.cos(YAW), math.sin(YAW), 0.0]))


def _moving_world(f: int) -> np.ndarray:
    """The moving car: 10 m ahead of the FRONT camera at frame 3, then 15 m/s along YAW."""
    return _ego(3) @ rigid(0.0, (11.5 + 1.5 * (f - 3), 0.0, 1.5))


PARKED_WORLD = rigid(YAW + 1.0, GLOBAL + np.array([5.0, 9.0, 1.0]))
SIGN_WORLD = rigid(YAW, GLOBAL + np.array([12.0, -3.0, 2.5]))


def _range(f: int) -> float:
    return {1: 20.0, 3: 10.0}.get(f, 30.0)


def _jpeg(w: int, h: int, colour) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.full((h, w, 3), colour, np.uint8)).save(buf, format="JPEG", quality=95)
    return buf.getvalue()


def _write(root: Path, table: dict, component: str) -> None:
    (root / component).mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.table(table), root / component / f"{SEG}.parquet")


def write_waymo(root: Path, distortion: float = 0.0, lidar_pose_shift: float | None = None) -> None:
    """7 frames, FRONT + SIDE_LEFT, the TOP laser, a moving car, a parked car, a sign."""
    ts = [T0_US + 100_000 * f for f in range(N_FRAMES)]
    seg = [SEG] * N_FRAMES
    _write(
        root,
        {
            "key.segment_context_name": seg,
            "key.frame_timestamp_micros": ts[::-1],  # not in time order on purpose
            "[VehiclePoseComponent].world_from_vehicle.transform": [
                _ego(f).ravel().tolist() for f in range(N_FRAMES)
            ][::-1],
        },
        "vehicle_pose",
    )
    cal = {"key.segment_context_name": [SEG] * 2, "key.camera_name": pa.array(list(CAMS), pa.int8())}
    for k, i in (("f_u", 1), ("f_v", 2), ("c_u", 3), ("c_v", 4)):
        cal[f"[CameraCalibrationComponent].intrinsic.{k}"] = [c[i] for c in CAMS.values()]
    for k in ("k1", "k2", "p1", "p2", "k3"):
        cal[f"[CameraCalibrationComponent].intrinsic.{k}"] = [0.0, distortion if k == "k1" else 0.0]
    cal["[CameraCalibrationComponent].extrinsic.transform"] = [
        rigid(*c[0]).ravel().tolist() for c in CAMS.values()
    ]
    cal["[CameraCalibrationComponent].width"] = pa.array([c[5] for c in CAMS.values()], pa.int32())
    cal["[CameraCalibrationComponent].height"] = pa.array([c[6] for c in CAMS.values()], pa.int32())
    cal["[CameraCalibrationComponent].rolling_shutter_direction"] = pa.array([1, 1], pa.int8())
    _write(root, cal, "camera_calibration")

    rows = [(f, c) for f in range(N_FRAMES) for c in (4, 1)]
    colours = {1: (200, 40, 10), 4: (10, 90, 220)}
    _write(
        root,
        {
            "key.segment_context_name": [SEG] * len(rows),
            "key.frame_timestamp_micros": [ts[f] for f, _ in rows],
            "key.camera_name": pa.array([c for _, c in rows], pa.int8()),
            "[CameraImageComponent].image": [_jpeg(CAMS[c][5], CAMS[c][6], colours[c]) for _, c in rows],
            "[CameraImageComponent].pose.transform": [_ego(f, CAM_DX[c]).ravel().tolist() for f, c in rows],
            "[CameraImageComponent].pose_timestamp": [(ts[f] * 1e-6 + CAM_DX[c] / 10.0) for f, c in rows],
        },
        "camera_image",
    )
    _write(
        root,
        {
            "key.segment_context_name": [SEG],
            "key.laser_name": pa.array([1], pa.int8()),
            "[LiDARCalibrationComponent].extrinsic.transform": [rigid(*LIDAR_EXT).ravel().tolist()],
            "[LiDARCalibrationComponent].beam_inclination.min": [INCL[0]],
            "[LiDARCalibrationComponent].beam_inclination.max": [INCL[-1]],
            "[LiDARCalibrationComponent].beam_inclination.values": [INCL],
        },
        "lidar_calibration",
    )
    images = []
    for f in range(N_FRAMES):
        ri = np.full((3, RI_W, 4), -1.0, np.float32)  # -1: no return
        ri[1, 4, 0] = _range(f)
        images.append(ri)
    _write(
        root,
        {
            "key.segment_context_name": seg,
            "key.frame_timestamp_micros": ts,
            "key.laser_name": pa.array([1] * N_FRAMES, pa.int8()),
            "[LiDARComponent].range_image_return1.values": [ri.ravel().tolist() for ri in images],
            "[LiDARComponent].range_image_return1.shape": [list(ri.shape) for ri in images],
        },
        "lidar",
    )
    if lidar_pose_shift is not None:
        poses = []
        for f in range(N_FRAMES):
            t = _ego(f, lidar_pose_shift)[:3, 3]
            poses.append(np.broadcast_to(np.array([0.0, 0.0, YAW, *t]), (3, RI_W, 6)).astype(np.float32))
        _write(
            root,
            {
                "key.segment_context_name": seg,
                "key.frame_timestamp_micros": ts,
                "key.laser_name": pa.array([1] * N_FRAMES, pa.int8()),
                "[LiDARPoseComponent].range_image_return1.values": [p.ravel().tolist() for p in poses],
                "[LiDARPoseComponent].range_image_return1.shape": [list(p.shape) for p in poses],
            },
            "lidar_pose",
        )
    box = {k: [] for k in ("ts", "obj", "cx", "cy", "cz", "l", "w", "h", "heading", "type")}
    for f in range(N_FRAMES):
        for obj, world, lwh, typ in (
            ("obj_sign", SIGN_WORLD, (0.2, 0.8, 0.8), 3),
            ("obj_parked", PARKED_WORLD, (4.6, 1.9, 1.6), 1),
            ("obj_moving", _moving_world(f), (4.0, 2.0, 1.5), 1),
        ):
            local = np.linalg.inv(_ego(f)) @ world
            for k, v in zip(
                box,
                (ts[f], obj, *local[:3, 3], *lwh, math.atan2(local[1, 0], local[0, 0]), typ),
            ):
                box[k].append(v)
    _write(
        root,
        {
            "key.segment_context_name": [SEG] * len(box["ts"]),
            "key.frame_timestamp_micros": box["ts"],
            "key.laser_object_id": box["obj"],
            **{f"[LiDARBoxComponent].box.center.{a}": box[f"c{a}"] for a in "xyz"},
            **{f"[LiDARBoxComponent].box.size.{a}": box[k] for a, k in zip("xyz", "lwh")},
            "[LiDARBoxComponent].box.heading": box["heading"],
            "[LiDARBoxComponent].type": pa.array(box["type"], pa.int8()),
        },
        "lidar_box",
    )


@pytest.fixture
def wod(tmp_path):
    root = tmp_path / "training"
    write_waymo(root)
    return root


class TestRangeImage:
    def test_inclinations(self):
        np.testing.assert_allclose(waymo_beam_inclinations(3, -1.0, 1.0, INCL), [0.1, 0.0, -0.2])
        np.testing.assert_allclose(waymo_beam_inclinations(2, -1.0, 1.0), [0.5, -0.5])
        with pytest.raises(ValueError, match=r"beam_inclination\.values"):
            waymo_beam_inclinations(4, -1.0, 1.0, INCL)

    def test_points(self):
        ranges = np.zeros((3, RI_W))
        ranges[1, 4] = 10.0  # straight ahead of the vehicle (the extrinsic's yaw is corrected)
        ranges[0, 0] = 5.0  # top row (0.1 rad up), first column: azimuth π - yaw in the LiDAR frame
        ext = rigid(*LIDAR_EXT)
        pts = waymo_range_image_to_points(ranges, ext, np.array([0.1, 0.0, -0.2]))
        np.testing.assert_allclose(pts[1], [11.5, 0.0, 2.0], atol=1e-9)
        az = (2 * (RI_W - 0.5) / RI_W - 1) * math.pi  # in the vehicle frame
        want = np.array([math.cos(az) * math.cos(0.1), math.sin(az) * math.cos(0.1), math.sin(0.1)]) * 5
        np.testing.assert_allclose(pts[0], want + ext[:3, 3], atol=1e-9)
        with pytest.raises(ValueError, match="row_inclination"):
            waymo_range_image_to_points(ranges, ext, np.zeros(2))


class TestLoadWaymo:
    def test_smoke(self, wod):
        scene = load_waymo(wod, SEG)
        assert isinstance(scene, Scene) and scene.name == SEG
        assert scene.camera_names == ["FRONT", "SIDE_LEFT"]
        assert len(scene.frames) == N_FRAMES and scene.num_views == 2 * N_FRAMES
        assert scene.cameras_info["SIDE_LEFT"].image_size == (16, 32)
        assert all(v.image is None for v in scene.views)

    def test_split_every_fourth(self, wod):
        scene = load_waymo(wod, SEG)
        assert scene.test_frames == [2, 6] and scene.train_frames == [0, 1, 3, 4, 5]
        assert load_waymo(wod, SEG, test_frames=[0]).test_frames == [0]
        assert len(load_waymo(wod, SEG, frames=range(2, 7)).frames) == 5

    def test_poses(self, wod):
        scene = load_waymo(wod, SEG, recenter=False)
        for f in (0, 5):
            torch.testing.assert_close(
                scene.frames[f].ego_to_world.double(), torch.from_numpy(_ego(f)), atol=1e-3, rtol=0
            )
        # SIDE_LEFT looks along the vehicle's +y: its optical axis (OpenCV z) is the world's YAW + 90°
        c2w = scene.views[scene.view_id(2, "SIDE_LEFT")].cam_to_world
        torch.testing.assert_close(
            c2w[:3, 2], torch.tensor([-math.sin(YAW), math.cos(YAW), 0.0]), atol=1e-6, rtol=0
        )
        torch.testing.assert_close(c2w[:3, 1], torch.tensor([0.0, 0.0, -1.0]), atol=1e-6, rtol=0)  # y down
        want = (_ego(2, CAM_DX[4]) @ rigid(*CAMS[4][0]))[:3, 3]
        torch.testing.assert_close(c2w[:3, 3].double(), torch.from_numpy(want), atol=1e-3, rtol=0)
        assert scene.views[scene.view_id(2, "FRONT")].timestamp == pytest.approx(0.205, abs=1e-6)
        rec = load_waymo(wod, SEG)
        torch.testing.assert_close(rec.frames[0].ego_to_world[:3, 3], torch.zeros(3), atol=1e-6, rtol=0)

    def test_intrinsics_pixel_offset(self, wod):
        scene = load_waymo(wod, SEG)
        torch.testing.assert_close(
            scene.cameras_info["FRONT"].K, torch.tensor([[20.0, 0, 15.5], [0, 21.0, 11.5], [0, 0, 1]])
        )

    def test_lidar_point_projects_to_known_pixel(self, wod):
        for scale in (1.0, 0.5):
            scene = load_waymo(wod, SEG, scale=scale)
            lid = scene.lidar(1)
            assert lid.points.shape == (1, 3)  # the -1 (no return) pixels are dropped
            want_world = (_ego(1) @ np.array([21.5, 0.0, 2.0, 1.0]))[:3] - GLOBAL
            torch.testing.assert_close(
                lid.points[0].double(), torch.from_numpy(want_world), atol=1e-3, rtol=0
            )
            cams = scene.cameras([scene.view_id(1, "FRONT")])
            uv, z = project_points(lid.points[None], cams.K, cams.world_to_cam)
            # in FRONT's frame (its pose 5 cm ahead): 19.95 m ahead, 0.5 m up → column 15.5 (the centre)
            pixel = torch.tensor([15.5, 11.5 - 21.0 * 0.5 / 19.95])
            want = pixel if scale == 1.0 else scale * (pixel + 0.5) - 0.5
            assert float(z[0, 0]) == pytest.approx(19.95, abs=1e-3)
            assert float((uv[0, 0] - want).abs().max()) < 0.01
            torch.testing.assert_close(
                lid.origin.double(),
                torch.from_numpy((_ego(1) @ rigid(*LIDAR_EXT))[:3, 3] - GLOBAL),
                atol=1e-3,
                rtol=0,
            )

    def test_lidar_pixel_pose(self, tmp_path):
        root = tmp_path / "training"
        write_waymo(root, lidar_pose_shift=0.3)
        got = load_waymo(root, SEG).lidar(1).points[0].double()
        want = (_ego(1, 0.3) @ np.array([21.5, 0.0, 2.0, 1.0]))[:3] - GLOBAL
        torch.testing.assert_close(got, torch.from_numpy(want), atol=1e-3, rtol=0)

    def test_box_projects_onto_known_rectangle(self, wod):
        scene = load_waymo(wod, SEG)
        track = scene.tracks[1]  # obj_moving
        length, w, h = track.size_lwh.tolist()
        assert (length, w, h) == pytest.approx((4.0, 2.0, 1.5))
        signs = [(sx, sy, sz) for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
        corners = torch.tensor([[sx * length / 2, sy * w / 2, sz * h / 2, 1.0] for sx, sy, sz in signs])
        world = (track.object_to_world[3] @ corners.T).T[:, :3]
        cams = scene.cameras([scene.view_id(3, "FRONT")])
        uv, z = project_points(world[None], cams.K, cams.world_to_cam)
        # in FRONT's frame the box spans x in [-1, 1], y in [-0.75, 0.75], z in [7.95, 11.95]
        rect = [
            float(v) for v in (uv[0, :, 0].min(), uv[0, :, 1].min(), uv[0, :, 0].max(), uv[0, :, 1].max())
        ]
        want = [15.5 - 20 / 7.95, 11.5 - 21 * 0.75 / 7.95, 15.5 + 20 / 7.95, 11.5 + 21 * 0.75 / 7.95]
        assert rect == pytest.approx(want, abs=0.01)
        assert float(z.min()) == pytest.approx(7.95, abs=1e-3)

    def test_tracks_and_instances(self, wod):
        scene = load_waymo(wod, SEG)
        assert {i: (v.name, v.class_name, v.dynamic) for i, v in scene.instances.items()} == {
            1: ("obj_moving", "vehicle", True),
            2: ("obj_parked", "vehicle", False),
            3: ("obj_sign", "sign", False),
        }
        assert sorted(scene.tracks) == [1] and bool(scene.tracks[1].valid.all())
        centres = scene.tracks[1].object_to_world[:, :3, 3]
        torch.testing.assert_close(
            (centres[1:] - centres[:-1]).norm(dim=-1), torch.full((N_FRAMES - 1,), 1.5), atol=1e-4, rtol=0
        )
        assert sorted(load_waymo(wod, SEG, min_motion_m=None).tracks) == [1, 2]
        assert scene.lidar(3).instance.tolist() == [1]  # the LiDAR return at 10 m hits the moving car
        assert scene.lidar(1).instance.tolist() == [0]

    def test_images(self, wod):
        scene = load_waymo(wod, SEG, scale=0.5)
        ids = [scene.view_id(4, "FRONT"), scene.view_id(5, "FRONT")]
        imgs = scene.load_images(ids)
        assert imgs.shape == (2, 3, 12, 16)
        torch.testing.assert_close(imgs[0, :, 6, 8], torch.tensor([200, 40, 10]) / 255.0, atol=0.03, rtol=0)
        side = scene.load_images([scene.view_id(4, "SIDE_LEFT")])
        assert side.shape == (1, 3, 8, 16)
        torch.testing.assert_close(side[0, :, 4, 8], torch.tensor([10, 90, 220]) / 255.0, atol=0.03, rtol=0)

    def test_camera_subset_no_lidar(self, wod):
        scene = load_waymo(wod, SEG, cameras=["SIDE_LEFT"], lasers=None)
        assert scene.camera_names == ["SIDE_LEFT"] and scene.num_views == N_FRAMES
        with pytest.raises(FileNotFoundError, match="no LiDAR"):
            scene.lidar(0)

    def test_distortion_is_undistorted(self, tmp_path):
        """A distorted camera gets the pinhole K of its undistorted image; a world point lands on the
        pixel that the distortion model, applied by hand, maps to the raw pixel it projects to."""
        root = tmp_path / "training"
        write_waymo(root, distortion=0.1)  # SIDE_LEFT: k1 = 0.1 (pincushion), FRONT: none
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            scene = load_waymo(root, SEG)
        torch.testing.assert_close(
            scene.cameras_info["FRONT"].K, torch.tensor([[20.0, 0, 15.5], [0, 21.0, 11.5], [0, 0, 1]])
        )
        K = scene.cameras_info["SIDE_LEFT"].K.double()
        f, c = 15.0, torch.tensor([15.5, 7.5], dtype=torch.float64)  # raw f_u = f_v, c - 0.5
        assert K[0, 0] > f and K[0, 0] == pytest.approx(K[1, 1]) and K[:2, 2].tolist() == c.tolist()
        vid = scene.view_id(3, "SIDE_LEFT")
        c2w = scene.views[vid].cam_to_world.double()
        p_cam = torch.tensor([1.2, -0.4, 5.0], dtype=torch.float64)
        p_world = c2w[:3, :3] @ p_cam + c2w[:3, 3]
        x = p_cam[:2] / p_cam[2]
        raw = f * x * (1 + 0.1 * float(x @ x)) + c  # Waymo's (OpenCV's) model, by hand
        pinhole = project_points(p_world[None, None], K[None], torch.linalg.inv(c2w)[None])[0][0, 0]
        xn = (pinhole.double() - c) / K[0, 0]
        back = f * xn * (1 + 0.1 * float(xn @ xn)) + c
        torch.testing.assert_close(back, raw, atol=1e-3, rtol=0)
        assert (pinhole.double() - raw).abs().max() > 0.05  # the distortion is not negligible here
        img = scene.load_images([vid])[0]
        torch.testing.assert_close(img[:, 8, 16], torch.tensor([10, 90, 220]) / 255.0, atol=0.03, rtol=0)

    def test_string_camera_names_and_float32_poses(self, wod):
        """Release files may hold key.camera_name as a string and transforms as float32."""
        want = load_waymo(wod, SEG)
        for comp in ("camera_calibration", "camera_image"):
            path = wod / comp / f"{SEG}.parquet"
            t = pq.read_table(path)
            names = pa.array(
                [{1: "FRONT", 4: "SIDE_LEFT"}[c] for c in t.column("key.camera_name").to_pylist()]
            )
            pq.write_table(
                t.set_column(t.schema.get_field_index("key.camera_name"), "key.camera_name", names), path
            )
        path = wod / "vehicle_pose" / f"{SEG}.parquet"
        t = pq.read_table(path)
        col = "[VehiclePoseComponent].world_from_vehicle.transform"
        pq.write_table(
            t.set_column(t.schema.get_field_index(col), col, t.column(col).cast(pa.list_(pa.float32(), 16))),
            path,
        )
        got = load_waymo(wod, SEG)
        assert got.camera_names == want.camera_names and got.num_views == want.num_views
        for a, b in zip(got.views, want.views):
            torch.testing.assert_close(a.cam_to_world, b.cam_to_world, atol=2e-3, rtol=0)
        assert read_waymo_poses(wod, SEG).world_from_vehicle.dtype == torch.float64
        t = pq.read_table(wod / "camera_image" / f"{SEG}.parquet")
        bad = pa.array(["FRONT"] + ["REAR"] * (t.num_rows - 1))
        pq.write_table(
            t.set_column(t.schema.get_field_index("key.camera_name"), "key.camera_name", bad),
            wod / "camera_image" / f"{SEG}.parquet",
        )
        with pytest.raises(ValueError, match=r"key\.camera_name: expected a camera id .* got 'REAR'"):
            load_waymo(wod, SEG)

    def test_camera_name(self):
        assert [waymo_camera_name(v) for v in (2, np.int8(3), "4", "side_right", b"FRONT")] == [
            "FRONT_LEFT",
            "FRONT_RIGHT",
            "SIDE_LEFT",
            "SIDE_RIGHT",
            "FRONT",
        ]
        for bad in (0, 6, "REAR", None, 1.0):
            with pytest.raises(ValueError, match=r"key\.camera_name"):
                waymo_camera_name(bad)

    def test_exception(self, wod):
        with pytest.raises(ValueError, match=rf"segment: unknown segment 'nope'.*{SEG}"):
            load_waymo(wod, "nope")
        with pytest.raises(ValueError, match=r"cameras: unknown camera 'REAR'.*FRONT"):
            load_waymo(wod, SEG, cameras=["REAR"])
        with pytest.raises(ValueError, match=r"lasers: unknown laser 'FRONT', have \['TOP'\]"):
            load_waymo(wod, SEG, lasers=["FRONT"])
        with pytest.raises(ValueError, match="frames: expected"):
            load_waymo(wod, SEG, frames=[7])
        with pytest.raises(FileNotFoundError, match="dataset_dir"):
            load_waymo(wod / "missing", SEG)
        (wod / "camera_calibration" / f"{SEG}.parquet").unlink()
        with pytest.raises(FileNotFoundError, match="component 'camera_calibration': missing file"):
            load_waymo(wod, SEG)

    def test_missing_column(self, wod):
        path = wod / "lidar_calibration" / f"{SEG}.parquet"
        pq.write_table(
            pq.read_table(path).drop_columns(["[LiDARCalibrationComponent].beam_inclination.min"]), path
        )
        with pytest.raises(ValueError, match=r"'lidar_calibration'.*missing column.*beam_inclination\.min"):
            load_waymo(wod, SEG)

    def test_missing_image(self, wod):
        path = wod / "camera_image" / f"{SEG}.parquet"
        t = pq.read_table(path)
        pq.write_table(t.slice(0, t.num_rows - 1), path)  # drops FRONT at the last frame
        with pytest.raises(ValueError, match=r"frame 6 .* has no FRONT image"):
            load_waymo(wod, SEG)

    def test_no_pyarrow(self, wod, monkeypatch):
        monkeypatch.setitem(sys.modules, "pyarrow.parquet", None)
        with pytest.raises(ImportError, match=r"pip install 'vadgs\[waymo\]'"):
            load_waymo(wod, SEG)


class TestConvertWaymo:
    def test_export_round_trip(self, wod, tmp_path):
        from vadgs.data import export_scene, load_scene

        scene = load_waymo(wod, SEG, frames=range(0, 4))
        again = load_scene(export_scene(scene, tmp_path / "out"))
        assert again.camera_names == ["FRONT", "SIDE_LEFT"] and again.num_views == 8
        assert again.image_size(again.view_id(1, "SIDE_LEFT")) == (16, 32)
        torch.testing.assert_close(again.load_images([2]), scene.load_images([2]), atol=1 / 255, rtol=0)
        torch.testing.assert_close(again.lidar(3).points, scene.lidar(3).points)
        assert again.lidar(3).instance.tolist() == [1] and sorted(again.tracks) == [1]
        assert again.test_frames == [2]

    def test_cli(self, wod, tmp_path):
        from vadgs.cli import main
        from vadgs.data import load_scene

        out = tmp_path / "conv"
        assert main(["convert", "waymo", str(wod), "--scene", SEG, "--out", str(out), "--frames", "0:3"]) == 0
        assert load_scene(out).num_views == 6

    def test_cli_no_lidar_needs_no_lidar_component(self, wod, tmp_path, capsys):
        from vadgs.cli import main
        from vadgs.data import load_scene

        for comp in ("lidar", "lidar_pose"):
            (wod / comp / f"{SEG}.parquet").unlink(missing_ok=True)
        out = tmp_path / "conv"
        args = ["convert", "waymo", str(wod), "--scene", SEG, "--out", str(out), "--frames", "0:2"]
        assert main(args) != 0
        err = capsys.readouterr().err
        assert "Waymo component 'lidar': missing file" in err and "--no-lidar" in err
        with pytest.raises(FileNotFoundError, match="a segment without LiDAR loads with lasers=None"):
            load_waymo(wod, SEG, frames=range(2))
        assert main([*args, "--no-lidar"]) == 0
        scene = load_scene(out)
        assert scene.num_views == 4 and scene.lidar_loader is None
