"""Corrupt inputs are refused, naming the file: Waymo parquet, nuScenes, DGP, COLMAP, scene folders.

Each reader is given files cut short, emptied, zeroed or overwritten with random bytes at several
offsets, and files whose *decoded* values were corrupted on purpose (so that the test does not
depend on where random bytes land): the reader raises a ``ValueError`` naming the file, or (for
random bytes that land where nothing is read) gives back exactly what the intact file gives.
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")

from tests.data.test_waymo import N_FRAMES, RI_W, SEG, T0_US, write_waymo  # noqa: E402
from vadgs.data import load_waymo, validate_scene  # noqa: E402
from vadgs.data.waymo_lidar import (  # noqa: E402
    WAYMO_MAX_RANGE_M,
    waymo_check_pixel_pose,
    waymo_check_range_image,
)


def _rewrite(path: Path, **kw) -> bytes:
    """Rewrite a parquet file with ``kw`` (e.g. uncompressed, PLAIN), range images as Waymo's
    ``list<float>``, and return its bytes."""
    table = pq.read_table(path)
    fields = [
        pa.field(f.name, pa.list_(pa.float32())) if f.name.endswith("range_image_return1.values") else f
        for f in table.schema
    ]
    pq.write_table(table.cast(pa.schema(fields)), path, **kw)
    return path.read_bytes()


def _named(path: Path) -> str:
    """How the Waymo reader names a component file in its errors, as a regex."""
    return re.escape(f"Waymo component {path.parent.name!r} ({path})")


def _all_lidar(root: Path) -> list[torch.Tensor]:
    scene = load_waymo(root, SEG)
    return [scene.lidar(f).points for f in range(N_FRAMES)]


@pytest.fixture
def wod(tmp_path):
    """The test segment of ``test_waymo`` (7 frames, one return per frame)."""
    root = tmp_path / "training"
    write_waymo(root)
    return root


@pytest.fixture
def wod_pose(tmp_path):
    """The test segment with a ``lidar_pose`` component (per-pixel vehicle poses)."""
    root = tmp_path / "training"
    write_waymo(root, lidar_pose_shift=0.3)
    return root


class TestWaymoRangeImageChecks:
    def test_range_image(self):
        ok = np.full((2, 3, 4), -1.0, np.float32)
        ok[0, 1, 0], ok[1, 2, 0] = 75.0, 0.0
        waymo_check_range_image(ok, WAYMO_MAX_RANGE_M["TOP"], "x")
        for bad, match in (
            (
                -5.0,
                r"1 of 6 ranges are neither a return in \(0, 82.5\] m nor -1 / 0 \(no return\), "
                r"e.g. \[-5.0\]",
            ),
            (83.0, r"1 of 6 ranges.*\[83.0\]"),
            (3e38, r"1 of 6 ranges"),
            (np.nan, r"1 of 24 values are not finite"),
        ):
            img = ok.copy()
            img[1, 1, 0] = bad
            with pytest.raises(ValueError, match=r"^frame 3: " + match):
                waymo_check_range_image(img, 82.5, "frame 3")
        img = ok.copy()
        img[0, 0, 2] = np.inf  # elongation: not read, but a sign of a corrupt file
        with pytest.raises(ValueError, match="not finite"):
            waymo_check_range_image(img, 82.5, "x")
        with pytest.raises(ValueError, match=r"\(H, W, C >= 1\)"):
            waymo_check_range_image(ok[..., 0], 82.5, "x")
        short = ok.copy()
        short[0, 1, 0] = 23.0
        with pytest.raises(ValueError, match=r"\(0, 22\]"):  # a short-range laser
            waymo_check_range_image(short, WAYMO_MAX_RANGE_M["REAR"], "x")

    def test_pixel_pose(self):
        ranges = np.array([[10.0, -1.0, 5.0]])
        frame = np.eye(4)
        frame[:3, 3] = [1000.0, -200.0, 30.0]
        pose = np.zeros((1, 3, 6))
        pose[..., 3:] = frame[:3, 3]
        pose[0, 1] = np.nan  # no return there: not read
        waymo_check_pixel_pose(pose, ranges, frame, "x")
        for col, value, match in ((2, (0.0, 0.0, 0.0, 1000.0, -221.0, 30.0), r"up to 21 m"),
                                  (0, (0.0, 0.0, 0.6, 1000.0, -200.0, 30.0), r"0.6 rad"),
                                  (0, (np.nan,) * 6, "not finite")):  # fmt: skip
            bad = pose.copy()
            bad[0, col] = value
            with pytest.raises(ValueError, match=match):
                waymo_check_pixel_pose(bad, ranges, frame, "x")
        with pytest.raises(ValueError, match=r"expected per-pixel poses of shape \(1, 3, 6\)"):
            waymo_check_pixel_pose(pose[..., :5], ranges, frame, "x")


class TestCorruptWaymo:
    """The issue's case: bytes of ``lidar/*.parquet`` changed; the frame is refused, naming the file."""

    @pytest.mark.parametrize("value", [-5.0, 3e38, np.nan, 200.0, 82.6])
    def test_decoded_range_corrupted(self, wod, value):
        # uncompressed PLAIN values: frame 1's only return (20 m) is four known bytes of the file
        path = wod / "lidar" / f"{SEG}.parquet"
        data = bytearray(_rewrite(path, compression="none", use_dictionary=False))
        good = np.float32(20.0).tobytes()
        assert data.count(good) == 1
        at = data.find(good)
        data[at : at + 4] = np.float32(value).tobytes()
        path.write_bytes(bytes(data))
        scene = load_waymo(wod, SEG)  # the frames' metadata is intact
        assert len(scene.lidar(0).points) == 1  # other frames read
        want = (
            rf"^{_named(path)}, row group 0, row 1 \(frame 1, timestamp {T0_US + 100_000} µs, laser TOP\): "
        )
        with pytest.raises(ValueError, match=want):
            scene.lidar(1)

    def test_decoded_pixel_pose_corrupted(self, wod_pose):
        path = wod_pose / "lidar_pose" / f"{SEG}.parquet"
        data = bytearray(_rewrite(path, compression="none", use_dictionary=False))
        ref = load_waymo(wod_pose, SEG)
        # frame 1's per-pixel pose: the vehicle pose's x, repeated at every pixel; change the one
        # at the return's pixel (row 1, column 4 of the (3, RI_W, 6) image)
        values = pq.read_table(path).column("[LiDARPoseComponent].range_image_return1.values")[1].as_py()
        pix = np.asarray(values, np.float32).reshape(3, RI_W, 6)[1, 4]
        start = data.find(np.asarray(values, np.float32).tobytes())  # frame 1's image, one PLAIN run
        assert start >= 0
        at = start + (1 * RI_W + 4) * 6 * 4 + 3 * 4  # its x
        data[at : at + 4] = np.float32(pix[3] + 100.0).tobytes()
        path.write_bytes(bytes(data))
        scene = load_waymo(wod_pose, SEG)
        torch.testing.assert_close(scene.lidar(0).points, ref.lidar(0).points)
        with pytest.raises(
            ValueError, match=rf"^{_named(path)}, row group 0, row 1 \(frame 1.*\): 1 of 1 per-pixel"
        ):
            scene.lidar(1)

    def test_cut_and_empty(self, wod):
        path = wod / "lidar" / f"{SEG}.parquet"
        data = path.read_bytes()
        for size in (0, 3, 100, len(data) // 2, len(data) - 9):
            path.write_bytes(data[:size])
            with pytest.raises(
                ValueError,
                match=rf"^{re.escape(str(path))}: not a readable parquet file, truncated or corrupt",
            ):
                _all_lidar(wod)
        path.write_bytes(b"")
        with pytest.raises(ValueError, match=r"an empty file \(0 bytes\)"):
            _all_lidar(wod)
        for comp in ("vehicle_pose", "camera_calibration", "camera_image", "lidar_calibration", "lidar_box"):
            root = wod.parent / f"t_{comp}"
            write_waymo(root)
            other = root / comp / f"{SEG}.parquet"
            other.write_bytes(other.read_bytes()[: len(other.read_bytes()) // 2])
            with pytest.raises(ValueError, match=rf"^{re.escape(str(other))}: not a readable parquet file"):
                load_waymo(root, SEG)
            other.write_bytes(b"")
            with pytest.raises(ValueError, match=rf"^{re.escape(str(other))}: .*empty file"):
                load_waymo(root, SEG)

    @pytest.mark.parametrize("component", ["lidar", "lidar_pose"])
    def test_random_bytes_with_checksums(self, wod_pose, component):
        """Random bytes anywhere in a file with page checksums (as write_waymo_segment writes them):
        refused naming the file, or (bytes where nothing is read) exactly the intact result."""
        path = wod_pose / component / f"{SEG}.parquet"
        data = _rewrite(path, write_page_checksum=True)
        ref = _all_lidar(wod_pose)
        rng = np.random.default_rng(49)
        outcomes = {"refused": 0, "same": 0}
        for frac in np.linspace(0.0, 0.98, 25):
            for n in (1, 16, 200):
                at = int(frac * (len(data) - n))
                bad = bytearray(data)
                bad[at : at + n] = rng.bytes(n)
                if bad == data:
                    continue
                path.write_bytes(bytes(bad))
                try:
                    got = _all_lidar(wod_pose)
                except ValueError as e:
                    assert str(path) in str(e), str(e)
                    outcomes["refused"] += 1
                    continue
                for g, r in zip(got, ref):
                    torch.testing.assert_close(g, r, atol=0, rtol=0)
                outcomes["same"] += 1
        assert outcomes["refused"] >= 60  # of 75 (most bytes are pages, each checked)

    @pytest.mark.parametrize("offset", [0.3, 0.5, 0.7])
    def test_zeroed_range_image(self, wod, offset):
        """Zeroed bytes in a plain range image: a zero range is "no return", so a frame may lose
        points; the file's row group is refused only where the values decode implausibly. With a
        checksum, any change is refused."""
        path = wod / "lidar" / f"{SEG}.parquet"
        data = bytearray(_rewrite(path, write_page_checksum=True))
        at = int(offset * len(data))
        data[at : at + 64] = bytes(64)
        path.write_bytes(bytes(data))
        with pytest.raises(ValueError, match=re.escape(str(path))):
            _all_lidar(wod)

    def test_decoded_image_corrupted(self, wod):
        """A JPEG cut short inside its parquet row: the image's error names the file, row group and frame."""
        path = wod / "camera_image" / f"{SEG}.parquet"
        table = pq.read_table(path)
        col = "[CameraImageComponent].image"
        images = table.column(col).to_pylist()
        images[3] = images[3][
            : len(images[3]) // 3
        ]  # row 3: frame 1's FRONT (rows: SIDE_LEFT, FRONT per frame)
        pq.write_table(
            table.set_column(table.schema.get_field_index(col), col, pa.array(images, pa.binary())), path
        )
        scene = load_waymo(wod, SEG)
        scene.load_images([scene.view_id(0, "FRONT")])  # the others decode
        want = rf"^{_named(path)}, row group 0, row 3: Waymo FRONT image at frame 1: not a decodable image"
        with pytest.raises(ValueError, match=want):
            scene.load_images([scene.view_id(1, "FRONT")])

    def test_cli_convert_refuses(self, wod, tmp_path, capsys):
        from vadgs.cli import main

        path = wod / "lidar" / f"{SEG}.parquet"
        data = bytearray(_rewrite(path, compression="none", use_dictionary=False))
        assert data.count(np.float32(20.0).tobytes()) == 1  # frame 1's return (30 m is also a statistic)
        at = data.find(np.float32(20.0).tobytes())
        data[at : at + 4] = np.float32(2.5e38).tobytes()
        path.write_bytes(bytes(data))
        out = tmp_path / "conv"
        assert main(["convert", "waymo", str(wod), "--scene", SEG, "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert str(path) in err and "row group 0, row 1 (frame 1" in err and "the file is corrupt" in err
        assert not (out / "scene.json").exists()


class TestCheckFullLidar:
    """``vadgs check --full`` flags LiDAR points that are non-finite or beyond any plausible range."""

    def _scene(self, tmp_path):
        from vadgs.data import sample_scene_path

        dst = tmp_path / "scene"
        shutil.copytree(sample_scene_path(), dst)
        return dst

    def test_far_point(self, tmp_path):
        root = self._scene(tmp_path)
        assert validate_scene(root, full=True).ok
        lidar = sorted((root / "lidar").glob("*.npz"))[1]
        with np.load(lidar) as z:
            arrays = dict(z)
        arrays["points"] = arrays["points"].copy()
        arrays["points"][3] = [2.5e38, 0.0, 1.0]
        np.savez(lidar, **arrays)
        report = validate_scene(root, full=True)
        bad = [r for r in report.rows if r.status == "error"]
        assert len(bad) == 1 and bad[0].file == str(lidar)
        assert "1 of" in bad[0].message and "more than 1000 m from the sensor" in bad[0].message
        assert validate_scene(root).ok  # the headers level does not decode the sweeps

    def test_without_origin_only_finiteness(self, tmp_path):
        """A sweep without ``origin`` reads as seen from (0, 0, 0): far points are not flagged, NaN is."""
        root = self._scene(tmp_path)
        lidar = sorted((root / "lidar").glob("*.npz"))[0]
        with np.load(lidar) as z:
            pts = z["points"] + np.float32(5000.0)  # a world far from its origin
        np.savez(lidar, points=pts)
        assert validate_scene(root, full=True).ok
        pts[0, 0] = np.nan
        np.savez(lidar, points=pts)
        bad = [r for r in validate_scene(root, full=True).rows if r.status == "error"]
        assert len(bad) == 1 and "non-finite" in bad[0].message

    def test_loader_lidar_decoded(self, tmp_path):
        """A loaded Waymo scene (LiDAR read from the parquet files): ``full`` decodes it."""
        root = tmp_path / "training"
        write_waymo(root)
        scene = load_waymo(root, SEG)
        report = validate_scene(scene, full=True)
        assert report.ok and sum(r.item.startswith("lidar (frame") for r in report.rows) == 0
        assert [r.message for r in report.rows if r.item == "lidar"] == [
            f"{N_FRAMES} files, {N_FRAMES} points"
        ]
        assert not any(r.item == "lidar" for r in validate_scene(scene).rows)  # headers: not read


def test_writer_refuses_ranges_beyond_the_top_laser(tmp_path):
    """write_waymo_segment does not write ranges that load_waymo would refuse."""
    pytest.importorskip("embreex")
    from vadgs.data import SegmentConfig, make_segment
    from vadgs.data.waymo_writer import write_waymo_segment

    src = make_segment(
        tmp_path / "src", SegmentConfig(frames=1, cameras=1, lidar_range=150.0), progress=False
    )
    with pytest.raises(
        ValueError, match=r"scene: frame 0 has LiDAR points \d+\.\d m from the sensor; .* 82.5 m"
    ):
        write_waymo_segment(src, tmp_path / "training", "far")


# -- nuScenes, DGP, COLMAP ----------------------------------------------------------------------------


def _first(root: Path, pattern: str) -> Path:
    return sorted(root.rglob(pattern))[0]


class TestCorruptNuScenes:
    """A ``.pcd.bin`` sweep is raw float32 without a checksum: cut, empty and implausible values are
    refused naming the file (bytes that still decode as plausible coordinates cannot be told)."""

    @pytest.fixture
    def nus(self, tmp_path):
        from tests.data.test_nuscenes import write_nuscenes

        write_nuscenes(tmp_path / "nuscenes")
        return tmp_path / "nuscenes"

    def _lidar(self, root: Path):
        from vadgs.data import load_nuscenes

        scene = load_nuscenes(root, "scene-0061")
        return [scene.lidar(f.index) for f in scene.frames]

    def test_cut_empty_and_implausible(self, nus):
        path = _first(nus, "*.pcd.bin")
        data = path.read_bytes()
        assert len(self._lidar(nus)) > 1
        for size, match in (
            (0, r"an empty file \(0 bytes\)"),
            (len(data) - 7, rf"got {len(data) - 7} bytes"),
        ):
            path.write_bytes(data[:size])
            with pytest.raises(ValueError, match=rf"^nuScenes LiDAR {re.escape(str(path))}: .*{match}"):
                self._lidar(nus)
        for value, match in ((np.nan, "1 non-finite points"), (2.5e38, "more than 1000 m from the sensor")):
            arr = np.frombuffer(data, np.float32).copy()
            arr[5] = value  # point 1's x
            path.write_bytes(arr.tobytes())
            with pytest.raises(ValueError, match=rf"^nuScenes LiDAR {re.escape(str(path))}: .*{match}"):
                self._lidar(nus)

    def test_cut_table(self, nus):
        from vadgs.data import load_nuscenes

        table = nus / "v1.0-mini" / "sample_data.json"
        table.write_text(table.read_text()[:-30])
        with pytest.raises(ValueError, match=rf"{re.escape(str(table))} is not valid JSON"):
            load_nuscenes(nus, "scene-0061")


class TestCorruptDgp:
    """DGP sweeps are ``.npz`` archives: zip CRC-32 checks every member, so bytes anywhere are found."""

    @pytest.fixture
    def dgp(self, tmp_path):
        from tests.data.test_dgp import write_dgp

        write_dgp(tmp_path / "dgp")
        return tmp_path / "dgp"

    def _lidar(self, root: Path):
        from vadgs.data import load_dgp

        scene = load_dgp(root)
        return [scene.lidar(f.index).points for f in scene.frames]

    def test_cut_empty_random(self, dgp):
        path = _first(dgp, "point_cloud/LIDAR/*.npz")
        data = path.read_bytes()
        ref = self._lidar(dgp)
        for size in (0, 10, len(data) // 2, len(data) - 5):
            path.write_bytes(data[:size])
            with pytest.raises(ValueError, match=re.escape(str(path))):
                self._lidar(dgp)
        rng = np.random.default_rng(3)
        refused = 0
        for frac in np.linspace(0.0, 0.98, 20):
            for n in (1, 8, 0):  # 0: 16 zeroed bytes
                at = int(frac * (len(data) - max(n, 16)))
                bad = bytearray(data)
                bad[at : at + max(n, 16)] = rng.bytes(n) if n else bytes(16)
                if bad == data:
                    continue
                path.write_bytes(bytes(bad))
                try:
                    got = self._lidar(dgp)
                except ValueError as e:
                    assert str(path) in str(e), str(e)
                    refused += 1
                    continue
                for g, r in zip(got, ref):
                    torch.testing.assert_close(g, r, atol=0, rtol=0)
        assert refused >= 45  # of 60

    def test_implausible_values(self, dgp):
        path = _first(dgp, "point_cloud/LIDAR/*.npz")
        with np.load(path) as z:
            pts = z["data"].copy()
        for value, match in ((np.inf, "non-finite"), (-3e38, "more than 1000 m")):
            bad = pts.copy()
            bad[0, 1] = value
            np.savez(path, data=bad)
            with pytest.raises(ValueError, match=rf"^DGP point cloud {re.escape(str(path))}: .*{match}"):
                self._lidar(dgp)

    def test_cut_scene_json(self, dgp):
        from vadgs.data import load_dgp

        scene_json = _first(dgp, "scene*.json")
        scene_json.write_text(scene_json.read_text()[:-50])
        with pytest.raises(ValueError, match=rf"{re.escape(str(scene_json))} is not valid JSON"):
            load_dgp(dgp)


class TestCorruptColmap:
    def test_non_finite_point(self, tmp_path):
        pytest.importorskip("pycolmap")
        from tests.data.test_colmap import synthetic_model
        from vadgs.data import load_colmap

        synthetic_model(tmp_path / "m")
        path = tmp_path / "m" / "points3D.bin"
        data = bytearray(path.read_bytes())
        # uint64 count, then the first point: uint64 id, 3 float64 x y z
        (pid,) = np.frombuffer(bytes(data[8:16]), np.uint64)
        data[16:24] = np.float64(np.nan).tobytes()
        path.write_bytes(bytes(data))
        with pytest.raises(
            ValueError, match=rf"^{re.escape(str(path))}: point {pid}: expected finite coordinates"
        ):
            load_colmap(tmp_path / "m")

    @pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin"])
    def test_empty_file(self, tmp_path, name):
        pytest.importorskip("pycolmap")
        from tests.data.test_colmap import synthetic_model
        from vadgs.data import load_colmap

        synthetic_model(tmp_path / "m")
        (tmp_path / "m" / name).write_bytes(b"")
        with pytest.raises(ValueError, match=re.escape(str(tmp_path / "m" / name))):
            load_colmap(tmp_path / "m")
