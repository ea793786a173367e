"""load_argoverse2 on a small log written in Argoverse 2's layout from known geometry.

Checked against the closed-form truth of the log (tests/data/argoverse2_log.py) and, where the
``av2`` devkit is installed, against its own readers: ``AV2SensorDataLoader`` (image matching,
labels), ``av2.geometry.interpolate.interpolate_pose``, ``PinholeCamera`` projections with motion
compensation, ``CuboidList`` corners and ``Sweep``.
"""

from __future__ import annotations

import shutil
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("pyarrow")

from tests.data import argoverse2_log as av2log
from vadgs.data import load_argoverse2
from vadgs.data.argoverse2_tables import (
    Argoverse2Poses,
    argoverse2_sync,
    interpolate_city_SE3_ego,
    read_argoverse2_poses,
    read_feather_columns,
)
from vadgs.geometry import project_points

#: av2's cuboid vertex order (``Cuboid.vertices_m``), in half extents
AV2_UNIT_VERTICES = np.array(
    [[1, 1, 1], [1, -1, 1], [1, -1, -1], [1, 1, -1], [-1, 1, 1], [-1, -1, 1], [-1, -1, -1], [-1, 1, -1]],
    float,
)


@pytest.fixture(scope="module")
def log(tmp_path_factory) -> av2log.Truth:
    return av2log.write_log(tmp_path_factory.mktemp("av2") / "val")


@pytest.fixture(scope="module")
def scene(log):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a complete log: nothing to report
        return load_argoverse2(log.log_dir)


def _offset(log) -> np.ndarray:
    """The recentring offset: the true ego position at the first sweep."""
    return av2log.city_SE3_ego((log.sweeps_ns[0] - av2log.T0) * 1e-9)[:3, 3]


def _copy(log, tmp_path) -> Path:
    dst = tmp_path / "split" / log.log_dir.name
    shutil.copytree(log.log_dir, dst)
    return dst


class TestAgainstTruth:
    def test_frames_views_and_sync(self, scene, log):
        assert len(scene.frames) == 8 and scene.camera_names == list(av2log.CAMERAS)
        assert scene.num_views == 24 and scene.test_frames == [2, 6]
        sync = argoverse2_sync(log.log_dir)
        assert list(sync.sweeps_ns) == log.sweeps_ns
        assert {c: list(v) for c, v in sync.images_ns.items()} == log.images_ns
        for c, (_, phase) in av2log.CAMERAS.items():  # the phase of each camera, up to the 0.5 µs jitter
            np.testing.assert_allclose(sync.offsets_ms[c], phase / 1e6, atol=0.002)
        for v in scene.views:
            ts = log.images_ns[v.camera][v.frame]
            assert v.image == log.log_dir / "sensors" / "cameras" / v.camera / f"{ts}.jpg"
            assert v.timestamp == pytest.approx((ts - log.sweeps_ns[0]) * 1e-9, abs=1e-9)
        assert scene.frames[3].timestamp == pytest.approx(0.3 + 3 * 137e-9, abs=1e-9)

    def test_poses_interpolated_to_image_times(self, scene, log):
        """Constant velocity and yaw rate: slerp + linear interpolation is exact."""
        offset = _offset(log)
        for v in scene.views:
            true = av2log.city_SE3_ego((log.images_ns[v.camera][v.frame] - av2log.T0) * 1e-9)
            true = true @ av2log.camera_to_ego(av2log.CAMERAS[v.camera][0])
            true[:3, 3] -= offset
            np.testing.assert_allclose(v.cam_to_world.double().numpy(), true, atol=2e-5)
        for f in scene.frames:
            true = av2log.city_SE3_ego((log.sweeps_ns[f.index] - av2log.T0) * 1e-9)
            true[:3, 3] -= offset
            np.testing.assert_allclose(f.ego_to_world.double().numpy(), true, atol=2e-5)

    def test_interpolation_float64_exact(self, log):
        poses = read_argoverse2_poses(log.log_dir)
        q = np.array([log.images_ns["ring_front_left"][4], int(poses.timestamps_ns[5])])
        got = interpolate_city_SE3_ego(poses, q)
        np.testing.assert_allclose(got[0], av2log.city_SE3_ego((q[0] - av2log.T0) * 1e-9), atol=1e-9)
        np.testing.assert_array_equal(got[1], poses.city_SE3_ego[5])  # a recorded time: that pose
        with pytest.raises(ValueError, match=r"query_ns: timestamp \d+ is outside the recorded poses"):
            interpolate_city_SE3_ego(poses, [int(poses.timestamps_ns[-1]) + 1])

    def test_intrinsics_ignore_distortion_by_default(self, scene):
        K = scene.cameras_info["ring_front_left"].K
        torch.testing.assert_close(
            K, torch.tensor([[24.0, 0, 19.3], [0, 24.24, 14.8], [0, 0, 1]]), atol=1e-5, rtol=0
        )
        c2e = scene.cameras_info["ring_front_left"].cam_to_ego.double().numpy()
        np.testing.assert_allclose(c2e, av2log.camera_to_ego(0.8), atol=1e-6)

    def test_lidar_in_world_and_labelled(self, scene, log):
        """Sweep points (float16 in the ego frame) land on the true city points; boxes label them."""
        offset = _offset(log)
        f = 5
        lf = scene.lidar(f)
        static = av2log.static_points() - offset
        n = len(static)
        # float16 of ego coordinates up to ~60 m: 0.03 m steps
        np.testing.assert_allclose(lf.points[:n].double().numpy(), static, atol=0.04)
        by_name = {i.name: i.id for i in scene.instances.values()}
        ids = lf.instance.numpy()
        assert (ids[n : n + 200] == by_name["9a1f0c22-2d6e-4b3f-9a55-6f0f1e2d3c4b"]).all()
        assert (ids[n + 200 :] == by_name["1b2c3d4e-0000-4a4a-8b8b-000000000001"]).all()
        origin = av2log.city_SE3_ego((log.sweeps_ns[f] - av2log.T0) * 1e-9) @ av2log.UP_LIDAR[:, 3]
        np.testing.assert_allclose(lf.origin.double().numpy(), origin[:3] - offset, atol=1e-4)

    def test_lidar_choice(self, log):
        up = load_argoverse2(log.log_dir, lidars=["up_lidar"], cameras=["ring_front_center"])
        down = load_argoverse2(log.log_dir, lidars=["down_lidar"], cameras=["ring_front_center"])
        both = load_argoverse2(log.log_dir, cameras=["ring_front_center"])
        cols = read_feather_columns(
            log.log_dir / "sensors" / "lidar" / f"{log.sweeps_ns[2]}.feather", {"laser_number": "int"}
        )
        n_up = int((cols["laser_number"] < 32).sum())
        assert (
            len(up.lidar(2).points) == n_up and len(down.lidar(2).points) == len(cols["laser_number"]) - n_up
        )
        assert len(both.lidar(2).points) == len(cols["laser_number"])
        o = av2log.city_SE3_ego((log.sweeps_ns[2] - av2log.T0) * 1e-9)
        delta = (o @ av2log.DOWN_LIDAR[:, 3] - o @ av2log.UP_LIDAR[:, 3])[:3]
        np.testing.assert_allclose((down.lidar(2).origin - up.lidar(2).origin).numpy(), delta, atol=1e-4)
        none = load_argoverse2(log.log_dir, lidars=None, cameras=["ring_front_center"])
        assert none.lidar_loader is None
        with pytest.raises(ValueError, match=r"lidars: expected names of \['up_lidar', 'down_lidar'\]"):
            load_argoverse2(log.log_dir, lidars=["top"])

    def test_tracks_moving_vs_parked(self, scene, log):
        """The parked car's labels jitter by 3 cm: an instance, not a track; the walker is not rigid."""
        by_name = {i.name: i for i in scene.instances.values()}
        moving = by_name["9a1f0c22-2d6e-4b3f-9a55-6f0f1e2d3c4b"]
        parked = by_name["1b2c3d4e-0000-4a4a-8b8b-000000000001"]
        walker = by_name["77777777-aaaa-4bbb-8ccc-dddddddddddd"]
        assert (moving.class_name, moving.dynamic) == ("regular_vehicle", True)
        assert (parked.class_name, parked.dynamic) == ("regular_vehicle", False)
        assert (walker.class_name, walker.dynamic) == ("pedestrian", True)
        assert sorted(scene.tracks) == [moving.id]
        track = scene.tracks[moving.id]
        torch.testing.assert_close(track.size_lwh, torch.tensor(av2log.CAR_LWH, dtype=torch.float32))
        offset = _offset(log)
        for f in range(len(scene.frames)):
            true = av2log.moving_box((log.sweeps_ns[f] - av2log.T0) * 1e-9)
            true[:3, 3] -= offset
            np.testing.assert_allclose(track.object_to_world[f].double().numpy(), true, atol=2e-5)
        everything = load_argoverse2(log.log_dir, min_motion_m=None, cameras=["ring_front_center"])
        assert sorted(everything.tracks) == sorted([moving.id, parked.id])

    def test_scale_and_subsets(self, log):
        s = load_argoverse2(log.log_dir, cameras=["ring_side_right"], frames=range(2, 6), scale=0.5)
        assert len(s.frames) == 4 and s.num_views == 4 and s.image_size(0) == (15, 20)
        torch.testing.assert_close(s.cameras_info["ring_side_right"].K[0], torch.tensor([12.0, 0.0, 9.4]))
        assert s.load_images([1]).shape == (1, 3, 15, 20)
        assert s.views[0].image.stem == str(log.images_ns["ring_side_right"][2])
        with pytest.raises(ValueError, match=r"cameras: unknown camera 'ring_rear_left', have \["):
            load_argoverse2(log.log_dir, cameras=["ring_rear_left"])  # calibrated nowhere, no images
        with pytest.raises(ValueError, match=r"cameras: unknown camera 'stereo_front_left'"):
            load_argoverse2(log.log_dir, cameras=["stereo_front_left"])  # calibrated, but no images
        with pytest.raises(ValueError, match=r"frames: expected sweep positions in \[0, 8\), got \[9\]"):
            load_argoverse2(log.log_dir, frames=[9])

    def test_undistort(self, log, tmp_path):
        """``undistort=True``: k1, k2, k3 as the radial terms 1 + k1 r² + k2 r⁴ + k3 r⁶; K the pinhole one."""
        from vadgs.data.undistort import undistortion_map

        k = (-0.1, 0.02, 0.004)
        log_dir = av2log.write_log(tmp_path / "split", num_sweeps=2, k123=k).log_dir
        s = load_argoverse2(log_dir, cameras=["ring_front_center"], frames=[0], undistort=True)
        K = s.cameras_info["ring_front_center"].K.double()
        assert float(K[0, 0]) != 24.0 and float(K[0, 2]) == pytest.approx(19.3)
        raw_K = torch.tensor([[24.0, 0, 19.3], [0, 24.24, 14.8], [0, 0, 1]], dtype=torch.float64)
        coeffs = torch.zeros(12, dtype=torch.float64)
        coeffs[[0, 1, 4]] = torch.tensor(k, dtype=torch.float64)
        raw = undistortion_map(raw_K, coeffs, (30, 40), K)
        for x, y in ((0, 0), (39, 29), (5, 20)):  # by hand: the radial model at the undistorted pixel's ray
            xy = np.array([(x - float(K[0, 2])) / float(K[0, 0]), (y - float(K[1, 2])) / float(K[1, 1])])
            r2 = float(xy @ xy)
            d = xy * (1 + k[0] * r2 + k[1] * r2**2 + k[2] * r2**3)
            expected = [24.0 * d[0] + 19.3, 24.24 * d[1] + 14.8]
            np.testing.assert_allclose(raw[y, x].numpy(), expected, atol=1e-6)
        img = s.load_images([0])
        assert img.shape == (1, 3, 30, 40)
        plain = load_argoverse2(log_dir, cameras=["ring_front_center"], frames=[0]).load_images([0])
        assert float((img - plain).abs().max()) > 0.05  # the pixels moved

    def test_export_round_trip(self, scene, tmp_path):
        from vadgs.data import export_scene, load_scene

        again = load_scene(export_scene(scene, tmp_path / "out"))
        assert again.num_views == 24 and again.camera_names == scene.camera_names
        torch.testing.assert_close(again.load_images([4]), scene.load_images([4]), atol=1 / 255, rtol=0)
        torch.testing.assert_close(again.lidar(3).points, scene.lidar(3).points)
        torch.testing.assert_close(again.lidar(3).instance, scene.lidar(3).instance)
        assert sorted(again.tracks) == sorted(scene.tracks) and again.test_frames == [2, 6]


class TestReported:
    def test_missing_image_drops_the_sweep(self, log, tmp_path):
        log_dir = _copy(log, tmp_path)
        (
            log_dir / "sensors" / "cameras" / "ring_front_left" / f"{log.images_ns['ring_front_left'][3]}.jpg"
        ).unlink()
        with pytest.warns(UserWarning, match=r"dropped sweep \d+: no ring_front_left image within 25 ms"):
            s = load_argoverse2(log_dir)
        assert len(s.frames) == 7 and s.frames[3].timestamp == pytest.approx(0.4, abs=1e-5)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert len(load_argoverse2(log_dir, cameras=["ring_side_right"]).frames) == 8

    def test_annotated_sweep_without_file_reported(self, log, tmp_path):
        log_dir = _copy(log, tmp_path)
        (log_dir / "sensors" / "lidar" / f"{log.sweeps_ns[7]}.feather").unlink()
        with pytest.warns(UserWarning, match=r"1 annotated timestamp\(s\) without a sweep file"):
            s = load_argoverse2(log_dir)
        assert len(s.frames) == 7
        assert argoverse2_sync(log_dir).missing_sweeps == (log.sweeps_ns[7],)

    def test_sweep_without_pose_dropped(self, log, tmp_path):
        log_dir = _copy(log, tmp_path)
        import pyarrow.feather as feather

        path = log_dir / "city_SE3_egovehicle.feather"
        table = feather.read_table(path)
        keep = np.asarray(table.column("timestamp_ns")) < log.sweeps_ns[5] + 10_000_000
        feather.write_feather(table.filter(keep), path)
        with pytest.warns(UserWarning, match=r"no ego pose at the ring_front_left image's time") as rec:
            assert len(load_argoverse2(log_dir).frames) == 5  # sweep 5's left image is after the last pose
        assert str(rec[0].message).count("no ego pose at the sweep's time") == 2  # sweeps 6 and 7


class TestRefused:
    @pytest.mark.parametrize(
        ("rel", "damage", "message"),
        [
            ("city_SE3_egovehicle.feather", "truncate", "not a readable Feather file"),
            ("calibration/intrinsics.feather", "drop:fx_px", r"missing column\(s\) \['fx_px'\]"),
            ("calibration/egovehicle_SE3_sensor.feather", "dtype:tx_m", "column 'tx_m': expected a float"),
            ("annotations.feather", "dtype:timestamp_ns", "column 'timestamp_ns': expected an integer"),
            ("annotations.feather", "truncate", "not a readable Feather file"),
        ],
    )
    def test_bad_table(self, log, tmp_path, rel, damage, message):
        import pyarrow as pa
        import pyarrow.feather as feather

        log_dir = _copy(log, tmp_path)
        path = log_dir / rel
        if damage == "truncate":
            path.write_bytes(path.read_bytes()[:200])
        else:
            kind, col = damage.split(":")
            table = feather.read_table(path)
            if kind == "drop":
                table = table.drop_columns([col])
            else:
                i = table.column_names.index(col)
                table = table.set_column(i, col, pa.array([str(v) for v in table.column(col).to_pylist()]))
            feather.write_feather(table, path)
        with pytest.raises(ValueError, match=message) as err:
            load_argoverse2(log_dir)
        assert str(path) in str(err.value)

    @pytest.mark.parametrize("sensor", ["ring_front_center", "down_lidar"])
    def test_sensor_without_extrinsics(self, log, tmp_path, sensor):
        """A selected camera or LiDAR without a row of the extrinsics: one line naming both."""
        import pyarrow.compute as pc
        import pyarrow.feather as feather

        log_dir = _copy(log, tmp_path)
        path = log_dir / "calibration" / "egovehicle_SE3_sensor.feather"
        table = feather.read_table(path)
        feather.write_feather(table.filter(pc.not_equal(table.column("sensor_name"), sensor)), path)
        with pytest.raises(ValueError, match=f"no row of sensor_name '{sensor}', have ") as err:
            load_argoverse2(log_dir)
        assert str(path) in str(err.value)
        if sensor == "down_lidar":  # without that LiDAR's points the log loads
            frames = load_argoverse2(log.log_dir).frames
            assert len(load_argoverse2(log_dir, lidars=["up_lidar"]).frames) == len(frames)

    def test_bad_sweep_named_when_read(self, log, tmp_path):
        import pyarrow.feather as feather

        log_dir = _copy(log, tmp_path)
        path = log_dir / "sensors" / "lidar" / f"{log.sweeps_ns[1]}.feather"
        feather.write_feather(feather.read_table(path).drop_columns(["laser_number"]), path)
        s = load_argoverse2(log_dir)
        with pytest.raises(ValueError, match=r"missing column\(s\) \['laser_number'\]") as err:
            s.lidar(1)
        assert str(path) in str(err.value)
        path.write_bytes(b"")
        with pytest.raises(ValueError, match="not a readable Feather file"):
            s.lidar(1)

    def test_missing_files(self, log, tmp_path):
        log_dir = _copy(log, tmp_path)
        with pytest.raises(FileNotFoundError, match="log_dir: no such folder"):
            load_argoverse2(tmp_path / "nowhere")
        (log_dir / "calibration" / "intrinsics.feather").unlink()
        with pytest.raises(FileNotFoundError, match=r"missing file .*intrinsics\.feather"):
            load_argoverse2(log_dir)
        with pytest.raises(FileNotFoundError, match="not an Argoverse 2 sensor-dataset log"):
            load_argoverse2(log_dir.parent)

    def test_image_of_the_wrong_size(self, log, tmp_path):
        from PIL import Image

        log_dir = _copy(log, tmp_path)
        path = (
            log_dir
            / "sensors"
            / "cameras"
            / "ring_front_center"
            / f"{log.images_ns['ring_front_center'][0]}.jpg"
        )
        Image.new("RGB", (20, 20)).save(path, format="JPEG")
        s = load_argoverse2(log_dir)
        with pytest.raises(
            ValueError, match=r"size 20x20 differs from calibration/intrinsics.feather's 40x30"
        ):
            s.load_images([0])
        path.write_bytes(path.read_bytes()[:50])  # a truncated JPEG
        with pytest.raises(ValueError, match="not a decodable image") as err:
            s.load_images([0])
        assert str(path) in str(err.value)

    def test_no_pyarrow(self, log, monkeypatch):
        monkeypatch.setitem(sys.modules, "pyarrow.feather", None)
        with pytest.raises(ImportError, match=r"pip install 'vadgs\[argoverse2\]'"):
            load_argoverse2(log.log_dir)


class TestAgainstDevkit:
    """The av2 devkit's own readers on the same log (skipped without ``av2``)."""

    @pytest.fixture
    def av2(self):
        pytest.importorskip("av2.datasets.sensor.av2_sensor_dataloader")
        from av2.datasets.sensor.av2_sensor_dataloader import AV2SensorDataLoader

        return AV2SensorDataLoader

    def _city_pose(self, log, ts: int):
        """av2's pose at ``ts``: its interpolate_pose between the two recorded poses around it."""
        from av2.geometry.interpolate import interpolate_pose
        from av2.utils.io import read_city_SE3_ego

        poses = read_city_SE3_ego(log.log_dir)
        stamps = np.array(sorted(poses))
        i = int(np.searchsorted(stamps, ts))
        t0, t1 = int(stamps[i - 1]), int(stamps[i])
        return interpolate_pose((t0, t1), (poses[t0], poses[t1]), ts)

    def test_images_matched_as_the_devkit(self, av2, log, scene):
        loader = av2(log.log_dir.parent, log.log_dir.parent)
        for v in scene.views:
            sweep = log.sweeps_ns[v.frame]
            assert loader.get_closest_img_fpath(log.log_dir.name, v.camera, sweep) == v.image
        assert loader.get_ordered_log_lidar_timestamps(log.log_dir.name) == log.sweeps_ns

    def test_poses_at_image_times(self, av2, log, scene):
        offset = _offset(log)
        for v in scene.views:
            ref = self._city_pose(log, log.images_ns[v.camera][v.frame]).transform_matrix
            ego = v.cam_to_world.double().numpy() @ np.linalg.inv(
                scene.cameras_info[v.camera].cam_to_ego.double().numpy()
            )
            ego[:3, 3] += offset
            np.testing.assert_allclose(ego, ref, atol=5e-5)

    def test_lidar_projections(self, av2, log, scene):
        """vadgs's world points and cameras against av2's motion-compensated projection, to 0.01 px."""
        from av2.geometry.camera.pinhole_camera import PinholeCamera
        from av2.structures.sweep import Sweep

        worst, compared = 0.0, 0
        for f in (1, 6):
            sweep = Sweep.from_feather(log.log_dir / "sensors" / "lidar" / f"{log.sweeps_ns[f]}.feather")
            lf = scene.lidar(f)
            assert len(lf.points) == len(sweep)
            lidar_pose = self._city_pose(log, log.sweeps_ns[f])
            for c in av2log.CAMERAS:
                cam = PinholeCamera.from_feather(log.log_dir, c)
                cam_pose = self._city_pose(log, log.images_ns[c][f])
                uv_ref, _, valid = cam.project_ego_to_img_motion_compensated(sweep.xyz, cam_pose, lidar_pose)
                v = scene.view_id(f, c)
                cams = scene.cameras([v])
                uv, depth = project_points(
                    lf.points[None].double(), cams.K.double(), cams.world_to_cam.double()
                )
                assert valid.sum() > 20
                assert (depth[0].numpy()[valid] > 0).all()
                err = np.abs(uv[0].numpy()[valid] - uv_ref[valid]).max()
                worst, compared = max(worst, float(err)), compared + int(valid.sum())
        print(f"worst |uv - av2 uv| {worst:.2e} px over {compared} projections")
        assert worst < 0.01, worst
        assert compared > 500

    def test_box_corners(self, av2, log, scene):
        from av2.structures.cuboid import CuboidList

        loader = av2(log.log_dir.parent, log.log_dir.parent)
        cuboids = CuboidList.from_feather(log.log_dir / "annotations.feather")
        offset = _offset(log)
        track_id = next(iter(scene.tracks))
        track = scene.tracks[track_id]
        for f in range(len(scene.frames)):
            ts = log.sweeps_ns[f]
            labels = loader.get_labels_at_lidar_timestamp(log.log_dir.name, ts)
            assert len(labels) == 3
            ours = [c for c in cuboids.cuboids if c.timestamp_ns == ts and c.length_m == av2log.CAR_LWH[0]]
            pose = self._city_pose(log, ts)
            ref = {
                tuple(np.round(c.transform(pose).xyz_center_m, 3)): c.transform(pose).vertices_m for c in ours
            }
            m = track.object_to_world[f].double().numpy()
            corners = (
                (AV2_UNIT_VERTICES * track.size_lwh.double().numpy() / 2) @ m[:3, :3].T + m[:3, 3] + offset
            )
            match = min(ref.values(), key=lambda r: np.abs(r - corners).max())
            np.testing.assert_allclose(corners, match, atol=1e-4)

    def test_undistort_not_done_by_devkit(self, av2, log):
        """The devkit's PinholeCamera has no distortion: its K is intrinsics.feather's, ours too."""
        from av2.geometry.camera.pinhole_camera import PinholeCamera

        cam = PinholeCamera.from_feather(log.log_dir, "ring_front_left")
        s = load_argoverse2(log.log_dir, cameras=["ring_front_left"], frames=[0])
        np.testing.assert_allclose(
            s.cameras_info["ring_front_left"].K.double().numpy(), cam.intrinsics.K, atol=1e-5
        )
        np.testing.assert_allclose(
            s.cameras_info["ring_front_left"].cam_to_ego.double().numpy(),
            cam.ego_SE3_cam.transform_matrix,
            atol=1e-6,
        )


def test_poses_type_doc():
    """:class:`Argoverse2Poses` holds numpy arrays in time order (what interpolate_city_SE3_ego takes)."""
    m = np.tile(np.eye(4), (3, 1, 1))
    m[:, 0, 3] = [0.0, 1.0, 3.0]
    out = interpolate_city_SE3_ego(Argoverse2Poses(np.array([0, 10, 20]), m), [5, 15, 20])
    assert out[:, 0, 3].tolist() == [0.5, 2.0, 3.0]


class TestCommandLine:
    def test_convert_options(self, log, tmp_path, capsys):
        from vadgs.cli import main
        from vadgs.data import load_scene

        out = tmp_path / "conv"
        args = ["convert", "argoverse2", str(log.log_dir), "--out", str(out), "--frames", "1:5"]
        args += ["--cameras", "ring_front_left,ring_side_right", "--lidars", "down_lidar", "--scale", "0.5"]
        assert main(args) == 0
        printed = capsys.readouterr().out
        assert "4 sweep(s) x 2 camera(s)" in printed and "ring_side_right: image - sweep offset" in printed
        assert "max 21.0 ms" in printed
        scene = load_scene(out)
        assert scene.camera_names == ["ring_front_left", "ring_side_right"] and scene.num_views == 8
        assert scene.image_size(0) == (15, 20)
        cols = read_feather_columns(
            log.log_dir / "sensors" / "lidar" / f"{log.sweeps_ns[2]}.feather", {"laser_number": "int"}
        )
        assert len(scene.lidar(1).points) == int((cols["laser_number"] >= 32).sum())
        assert (
            main(["convert", "argoverse2", str(log.log_dir), "--out", str(tmp_path / "x"), "--lidars", "top"])
            == 2
        )
        assert "lidars: expected names of ['up_lidar', 'down_lidar']" in capsys.readouterr().err

    def test_end_to_end(self, log, tmp_path, capsys):
        """convert → check --full → visibility → train --vad → eval → render --video → export."""
        import json

        from vadgs.cli import main

        scene_dir, run = tmp_path / "scene", tmp_path / "run"
        assert main(["convert", "argoverse2", str(log.log_dir), "--out", str(scene_dir)]) == 0
        assert main(["check", str(scene_dir), "--full"]) == 0
        assert "every file decoded" in capsys.readouterr().out
        vis = tmp_path / "vis"
        assert main(["visibility", str(scene_dir), "--out", str(vis), "--voxel-size", "0.5"]) == 0
        metrics = json.loads((vis / "visibility.json").read_text())
        assert metrics["lidar_points"] >= 6 * len(
            av2log.static_points()
        )  # at least the 6 training sweeps' static
        assert metrics["visible_voxels_in_view"] > 50
        args = [
            "train",
            str(scene_dir),
            "--out",
            str(run),
            "--iterations",
            "20",
            "--vad",
            "--vad.every-cycles",
            "1",
        ]
        assert main([*args, "--no-progress", "--init.max-points", "800", "--init.sh-degree", "0"]) == 0
        m = json.loads((run / "metrics.json").read_text())
        assert m["steps"] == 20 and m["test"]["num_views"] == 6 and len(m["vad_events"]) == 1
        assert main(["eval", str(run), "--no-progress"]) == 0
        assert json.loads((run / "eval.json").read_text())["psnr"] > 5
        video = tmp_path / "v.mp4"
        assert main(["render", str(run), "--video", str(video), "--no-progress"]) == 0
        assert "8 frames" in capsys.readouterr().out and video.stat().st_size > 1000
        assert main(["export", str(run), "--out", str(tmp_path / "export")]) == 0
        assert (tmp_path / "export" / "world_frame000.ply").stat().st_size > 1000
