"""write_waymo_segment: a generated segment as Waymo v2 parquet, through `vadgs convert waymo`."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")
pytest.importorskip("embreex")  # make_segment's ray caster

from scipy.spatial import cKDTree  # noqa: E402

from tests.data.test_waymo import rigid  # noqa: E402  (pyarrow is required by both)
from vadgs.data import SegmentConfig, load_scene, load_waymo, make_segment  # noqa: E402
from vadgs.data.waymo_lidar import (  # noqa: E402
    waymo_beam_inclinations,
    waymo_points_to_range_image,
    waymo_range_image_to_points,
)
from vadgs.data.waymo_writer import write_waymo_segment  # noqa: E402

SEG = "synthetic_0001"
# five cameras (the side ones shorter, as Waymo's) and the generated segment's 150k-point scan
CONFIG = SegmentConfig(frames=4, cameras=5, width=64, height=48, side_height=32, lidar_points=150_000)
REAL = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real" / "waymo_one_frame"


@pytest.fixture(scope="module")
def converted(tmp_path_factory):
    """``(source scene folder, Waymo split folder, summary, converted scene folder)``."""
    from vadgs.cli import main

    tmp = tmp_path_factory.mktemp("waymo_segment")
    src = make_segment(tmp / "src", CONFIG, progress=False)
    info = write_waymo_segment(src, tmp / "training", SEG)
    out = tmp / "converted"
    assert main(["convert", "waymo", str(tmp / "training"), "--scene", SEG, "--out", str(out)]) == 0
    return src, tmp / "training", info, out


class TestWriteWaymoSegment:
    def test_smoke(self, converted):
        _, root, info, _ = converted
        assert info.dataset_dir == root and info.segment == SEG
        for comp in (
            "vehicle_pose",
            "camera_calibration",
            "camera_image",
            "lidar_calibration",
            "lidar",
            "lidar_box",
        ):
            assert (root / comp / f"{SEG}.parquet").is_file()
        assert not list(root.glob("*/*.tmp"))

    def test_cardinality(self, converted):
        src, root, info, _ = converted
        scene = load_scene(src)
        assert (info.frames, info.views) == (CONFIG.frames, CONFIG.frames * CONFIG.cameras)
        assert info.points == sum(len(scene.lidar(f).points) for f in range(CONFIG.frames))
        assert info.boxes == CONFIG.frames * CONFIG.moving_cars
        assert info.range_image_shape[0] == CONFIG.lidar_beams
        # one row group per frame in the two large components, as they are written frame by frame
        for comp, rows in (("camera_image", CONFIG.cameras), ("lidar", 1)):
            f = pq.ParquetFile(root / comp / f"{SEG}.parquet")
            assert f.num_row_groups == CONFIG.frames
            assert [f.metadata.row_group(i).num_rows for i in range(CONFIG.frames)] == [rows] * CONFIG.frames

    def test_schema_is_waymos(self, converted):
        _, root, _, _ = converted
        lidar = pq.read_schema(root / "lidar" / f"{SEG}.parquet")
        assert lidar.field("[LiDARComponent].range_image_return1.values").type == pa.list_(pa.float32())
        assert lidar.field("[LiDARComponent].range_image_return1.shape").type == pa.list_(pa.int32(), 3)
        assert lidar.field("key.laser_name").type == pa.int8()
        real = REAL / "v2_from_v1_pvps"
        if not real.is_dir():
            pytest.skip("../shared is absent: no real Waymo file to compare the schema with")
        for comp in ("vehicle_pose", "camera_calibration", "camera_image", "lidar_calibration", "lidar_box"):
            ours = pq.read_schema(root / comp / f"{SEG}.parquet")
            theirs = pq.read_schema(next((real / comp).glob("*.parquet")))
            assert set(ours.names) <= set(theirs.names), comp
            for name in ours.names:  # every column we write has the type of the real file's
                assert ours.field(name).type == theirs.field(name).type, (comp, name)

    def test_cameras(self, converted):
        src, _, _, out = converted
        scene, again = load_scene(src), load_scene(out)
        names = {"front": "FRONT", "front_left": "FRONT_LEFT", "front_right": "FRONT_RIGHT"}
        names |= {"side_left": "SIDE_LEFT", "side_right": "SIDE_RIGHT"}
        assert again.camera_names == [names[c] for c in scene.camera_names]
        for c, info in scene.cameras_info.items():
            got = again.cameras_info[names[c]]
            assert got.image_size == info.image_size
            torch.testing.assert_close(got.K, info.K, atol=1e-5, rtol=0)
            torch.testing.assert_close(got.cam_to_ego, info.cam_to_ego, atol=1e-6, rtol=0)
        # the reader recentres the world on the vehicle at frame 0
        offset = scene.frames[0].ego_to_world[:3, 3]
        assert again.num_views == scene.num_views
        err = 0.0
        for a, b in zip(again.views, scene.views):
            assert (a.frame, a.camera) == (b.frame, names[b.camera])
            want = b.cam_to_world.clone()
            want[:3, 3] -= offset
            err = max(err, float((a.cam_to_world - want).abs().max()))
        assert err < 1e-5
        for a, b in zip(again.frames, scene.frames):
            want = b.ego_to_world.clone()
            want[:3, 3] -= offset
            torch.testing.assert_close(a.ego_to_world, want, atol=1e-5, rtol=0)
            assert a.timestamp == pytest.approx(b.timestamp, abs=1e-6)
        assert (again.train_frames, again.test_frames) == (scene.train_frames, scene.test_frames)

    def test_images(self, converted):
        src, _, _, out = converted
        scene, again = load_scene(src), load_scene(out)
        assert again.num_views == scene.num_views
        for vid in range(scene.num_views):  # two image sizes: one view at a time
            got, want = again.load_images([vid]), scene.load_images([vid])
            assert got.shape == want.shape
            # the JPEG files are stored as they are: the converted PNG is the same decode, to rounding
            assert float((got - want).abs().max()) <= 1.5 / 255

    def test_lidar(self, converted):
        src, _, info, out = converted
        scene, again = load_scene(src), load_scene(out)
        offset = scene.frames[0].ego_to_world[:3, 3].double().numpy()
        width = info.range_image_shape[1]
        for f in range(CONFIG.frames):
            want = scene.lidar(f)
            got = again.lidar(f)
            assert len(got.points) == len(want.points)  # a cell per point: none lost
            pts = got.points.double().numpy() + offset
            dist, _ = cKDTree(want.points.double().numpy()).query(pts)
            # a point keeps its range and beam and moves to its column's centre: at most half a column
            rng = np.linalg.norm(pts - want.origin.double().numpy(), axis=-1)
            assert (dist <= rng * math.pi / width + 1e-4).all()
            assert np.median(dist) < 0.01 and dist.max() < 0.04
            torch.testing.assert_close(
                got.origin.double() + torch.from_numpy(offset), want.origin.double(), atol=1e-5, rtol=0
            )

    def test_tracks(self, converted):
        src, _, _, out = converted
        scene, again = load_scene(src), load_scene(out)
        offset = scene.frames[0].ego_to_world[:3, 3]
        by_name = {scene.instances[i].name: t for i, t in scene.tracks.items()}
        assert len(again.tracks) == len(scene.tracks) == CONFIG.moving_cars
        for i, track in again.tracks.items():
            assert again.instances[i].class_name == "vehicle" and again.instances[i].dynamic
            source = by_name[again.instances[i].name]
            torch.testing.assert_close(track.size_lwh, source.size_lwh)
            assert bool(track.valid.all())
            # Waymo's box centre is the middle of the box, the benchmark object's origin its bottom
            lift = torch.eye(4)
            lift[2, 3] = float(source.size_lwh[2]) / 2
            want = source.object_to_world @ lift
            want[:, :3, 3] -= offset
            torch.testing.assert_close(track.object_to_world, want, atol=1e-5, rtol=0)

    def test_png_source_and_center_boxes(self, tmp_path):
        cfg = SegmentConfig(frames=2, cameras=1, width=48, height=32, lidar_points=1000, image_format="png")
        src = make_segment(tmp_path / "src", cfg, progress=False)
        write_waymo_segment(src, tmp_path / "training", "png_seg", box_origin="center", columns=2650)
        scene, again = load_scene(src), load_waymo(tmp_path / "training", "png_seg")
        got, want = again.load_images(), scene.load_images()
        assert float((got - want).abs().mean()) < 0.02  # encoded as JPEG (quality 95)
        t = next(iter(again.tracks.values()))
        source = next(
            s for i, s in scene.tracks.items() if scene.instances[i].name == again.instances[t.id].name
        )
        torch.testing.assert_close(
            t.object_to_world[:, :3, 3] + scene.frames[0].ego_to_world[:3, 3],
            source.object_to_world[:, :3, 3],
            atol=1e-5,
            rtol=0,
        )
        assert pq.read_metadata(tmp_path / "training" / "lidar" / "png_seg.parquet").num_rows == 2
        assert again.lidar(0).points.shape[0] <= cfg.lidar_points

    def test_exception(self, converted, tmp_path):
        src, _, _, _ = converted
        with pytest.raises(ValueError, match="box_origin: expected 'bottom' or 'center', got 'top'"):
            write_waymo_segment(src, tmp_path, box_origin="top")
        with pytest.raises(ValueError, match="columns: expected a positive integer"):
            write_waymo_segment(src, tmp_path, columns=0)
        with pytest.raises(ValueError, match="segment: expected a safe file name"):
            write_waymo_segment(src, tmp_path, "../up")
        with pytest.raises(ValueError, match="beam_inclinations: expected finite, strictly increasing"):
            write_waymo_segment(src, tmp_path, beam_inclinations=[0.1, -0.1])
        write_waymo_segment(src, tmp_path, "again", columns=64)
        with pytest.raises(ValueError, match="out_dir: segment 'again' exists"):
            write_waymo_segment(src, tmp_path, "again")
        assert write_waymo_segment(src, tmp_path, "again", columns=32, overwrite=True).range_image_shape == (
            64,
            32,
        )
        # a camera that Waymo has no name for
        odd = tmp_path / "odd"
        shutil.copytree(src, odd)
        meta = json.loads((odd / "scene.json").read_text())
        meta["cameras"]["rear"] = meta["cameras"].pop("side_right")
        for fm in meta["frames"]:
            for v in fm["views"]:
                v["camera"] = "rear" if v["camera"] == "side_right" else v["camera"]
        (odd / "scene.json").write_text(json.dumps(meta))
        with pytest.raises(ValueError, match=r"camera 'rear' has no Waymo name; expected one of \['front'"):
            write_waymo_segment(odd, tmp_path / "odd_out")
        del meta["lidar"]
        (odd / "scene.json").write_text(json.dumps(meta).replace('"rear"', '"side_right"'))
        with pytest.raises(ValueError, match=r"beam_inclinations: .* has no 'lidar' profile"):
            write_waymo_segment(odd, tmp_path / "odd_out")


def _points_to_range_image_naive(points, extrinsic, row_inclination, width):
    """Point by point: the nearest beam's row, the column whose azimuth interval holds it; nearest wins."""
    out = np.full((len(row_inclination), width), -1.0)
    inv = np.linalg.inv(extrinsic)
    yaw = math.atan2(extrinsic[1, 0], extrinsic[0, 0])
    for p in points:
        x, y, z = inv[:3, :3] @ p + inv[:3, 3]
        r = math.sqrt(x * x + y * y + z * z)
        if r == 0:
            continue
        row = int(np.argmin(np.abs(np.asarray(row_inclination) - math.asin(z / r))))
        az = math.atan2(y, x) + yaw
        col = math.floor((math.pi - az) / (2 * math.pi) * width) % width
        if out[row, col] < 0 or r < out[row, col]:
            out[row, col] = r
    return out


class TestPointsToRangeImage:
    EXT = rigid(0.3, (1.5, 0.2, 2.0))
    INCL = waymo_beam_inclinations(6, -0.3, 0.1)

    def _beam_points(self, n, seed=0):
        rng = np.random.default_rng(seed)
        r, row, az = rng.uniform(2, 50, n), rng.integers(0, len(self.INCL), n), rng.uniform(-np.pi, np.pi, n)
        inc = self.INCL[row]
        local = np.stack([np.cos(az) * np.cos(inc), np.sin(az) * np.cos(inc), np.sin(inc)], -1) * r[:, None]
        return local @ self.EXT[:3, :3].T + self.EXT[:3, 3], r

    def test_smoke(self):
        # 10 m straight ahead of the LiDAR (yaw 0.3, 1.5 m forward, 2 m up): column 4 of 9 looks ahead
        ext = rigid(0.3, (1.5, 0.0, 2.0))
        ranges = waymo_points_to_range_image(np.array([[11.5, 0.0, 2.0]]), ext, np.array([0.0]), 9)
        assert ranges.shape == (1, 9) and ranges[0, 4] == pytest.approx(10.0)
        assert (np.delete(ranges, 4) == -1).all()

    def test_matches_naive(self):
        pts, _ = self._beam_points(300)
        pts = np.concatenate([pts, pts[:20] * 1.5])  # farther points behind the first 20: the nearest stays
        got = waymo_points_to_range_image(pts, self.EXT, self.INCL, 97)
        want = _points_to_range_image_naive(pts, self.EXT, self.INCL, 97)
        np.testing.assert_array_equal(got < 0, want < 0)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=0)
        assert (got > 0).sum() < 300  # some points shared a cell

    def test_round_trip(self):
        width = 4000  # fine enough that the random points rarely share a cell
        pts, r = self._beam_points(500, seed=1)
        back = waymo_range_image_to_points(
            waymo_points_to_range_image(pts, self.EXT, self.INCL, width), self.EXT, self.INCL
        )
        dist, idx = cKDTree(pts).query(back)
        assert len(back) >= 495
        assert (dist <= r[idx] * math.pi / width + 1e-9).all()

    def test_exception(self):
        with pytest.raises(ValueError, match=r"points: expected shape \(N, 3\)"):
            waymo_points_to_range_image(np.zeros((4, 2)), self.EXT, self.INCL, 8)
        with pytest.raises(ValueError, match="row_inclination: expected a strictly decreasing"):
            waymo_points_to_range_image(np.zeros((4, 3)), self.EXT, self.INCL[::-1], 8)
        with pytest.raises(ValueError, match="width: expected a positive integer, got 0"):
            waymo_points_to_range_image(np.zeros((4, 3)), self.EXT, self.INCL, 0)
        with pytest.raises(ValueError, match=r"extrinsic: expected shape \(4, 4\)"):
            waymo_points_to_range_image(np.zeros((4, 3)), np.eye(3), self.INCL, 8)
