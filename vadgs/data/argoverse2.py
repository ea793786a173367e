"""An Argoverse 2 *sensor dataset* log as a :class:`~vadgs.data.scene.Scene`.

A log folder ``<split>/<log_id>/`` of the Argoverse 2 (AV2) sensor dataset holds Apache Feather
tables and JPEG images (the layout the ``av2`` devkit's ``AV2SensorDataLoader`` reads). vadgs
reads them with ``pyarrow`` (an optional dependency: ``pip install 'vadgs[argoverse2]'``); the
``av2`` devkit is not needed. Files read:

- ``city_SE3_egovehicle.feather``: ``timestamp_ns``, ``qw, qx, qy, qz``, ``tx_m, ty_m, tz_m``
  (ego → city, at a higher rate than the sweeps);
- ``calibration/egovehicle_SE3_sensor.feather``: ``sensor_name``, ``qw..qz``, ``tx_m..tz_m``
  (sensor → ego, for the cameras and the ``up_lidar`` / ``down_lidar``);
- ``calibration/intrinsics.feather``: ``sensor_name``, ``fx_px, fy_px, cx_px, cy_px``,
  ``k1, k2, k3``, ``width_px, height_px``;
- ``sensors/lidar/<timestamp_ns>.feather``: ``x, y, z`` (float16 in the release: the *ego* frame
  at the sweep's timestamp, motion compensated by AV2), ``laser_number`` (0-31 the up VLP-32,
  32-63 the down one; av2-api issue 77); ``intensity`` and ``offset_ns`` are not read;
- ``sensors/cameras/<camera>/<timestamp_ns>.jpg``: the images (ring cameras at 20 Hz, stereo at
  20 Hz);
- ``annotations.feather`` (optional: the test split has none): ``timestamp_ns`` (a sweep's),
  ``track_uuid``, ``category``, ``length_m, width_m, height_m``, ``qw..qz``, ``tx_m..tz_m`` (the box
  in the ego frame at that sweep's timestamp). ``num_interior_pts`` is not read.

The vector map (``map/``) is not read.

How AV2 maps to vadgs:

- **Frames** are the LiDAR sweeps (10 Hz), the files of ``sensors/lidar`` in time order; ``frames``
  selects positions among them. Each camera's view of a frame is its image *nearest in time* to
  the sweep, if within ``max_image_offset_ms`` (25 ms, half the cameras' 50 ms period, as the
  devkit's ``SynchronizationDB``); :func:`argoverse2_sync` reports every offset. A sweep without
  an image of every selected camera within that window, or without a pose at its own or an
  image's timestamp, is dropped with a warning (not an error), as are annotated timestamps without
  a sweep file.
- **Poses.** ``ego_to_world`` of a frame is ``city_SE3_egovehicle`` at the sweep's timestamp and a
  view's ``cam_to_world`` is ``city_SE3_egovehicle`` at *its image's* timestamp times the camera's
  ``egovehicle_SE3_sensor``, both interpolated between the two nearest poses
  (:func:`interpolate_city_SE3_ego`: slerp of the rotation, linear translation, as the devkit's
  ``av2.geometry.interpolate.interpolate_pose``). AV2 camera frames are OpenCV's (x right, y
  down, z forward), so ``cam_to_ego`` is ``egovehicle_SE3_sensor`` as is.
- **Intrinsics.** ``K`` is ``fx_px, fy_px, cx_px, cy_px`` as is (the devkit's ``PinholeCamera``:
  pixel centres at integers, as vadgs). **Lens distortion:** the devkit's ``PinholeCamera``
  ignores ``k1, k2, k3`` (it projects with ``K`` alone), and so does vadgs by default, so that a
  converted log projects exactly as the devkit projects it. With ``undistort=True`` the images
  are undistorted instead with the radial model ``1 + k1 r² + k2 r⁴ + k3 r⁶`` (OpenCV's with
  ``p1 = p2 = 0``; :mod:`vadgs.data.undistort`, as for Waymo) and ``K`` is that pinhole ``K``.
- **LiDAR.** A sweep's points of the selected LiDARs (``laser_number`` < 32: ``up_lidar``, ≥ 32:
  ``down_lidar``) go to the world with the ego pose at the sweep's timestamp; ``origin`` is the
  first selected LiDAR's position.
- **Boxes → tracks.** Boxes are grouped by ``track_uuid``; each gets an integer id 1, 2, ... in
  order of first appearance. Every track is in ``Scene.instances`` (class: the category
  lower-cased, e.g. ``regular_vehicle``); the vehicles (:data:`ARGOVERSE2_VEHICLES`) whose box
  centre moves more than ``min_motion_m`` in the world (the labels jitter by centimetres: a parked
  car stays an instance, not a track) become :class:`~vadgs.data.scene.Track` objects, as in
  :func:`~vadgs.data.load_nuscenes`.
- **World.** AV2's city frame, translated (``recenter=True``) so that the ego at the first frame
  sits at the origin (no rotation).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from vadgs.data._tracks import (
    BoxObservation,
    as_tensor,
    build_instances,
    check_min_motion,
    held_out_frames,
    labelled_lidar,
    recentred,
    select_cameras,
    select_positions,
)
from vadgs.data.assemble import assemble_scene, check_scale, pinhole_camera
from vadgs.data.scene import CameraInfo, FrameInfo, LidarFrame, Scene, ViewInfo, read_rgb
from vadgs.data.undistort import ImageUndistorter

__all__ = [
    "ARGOVERSE2_CAMERAS",
    "ARGOVERSE2_LIDARS",
    "ARGOVERSE2_MAX_IMAGE_OFFSET_MS",
    "ARGOVERSE2_VEHICLES",
    "Argoverse2Poses",
    "Argoverse2Sync",
    "argoverse2_sync",
    "interpolate_city_SE3_ego",
    "load_argoverse2",
    "read_argoverse2_poses",
    "read_feather_columns",
]

#: the cameras of the rig, in the default order of the views: seven ring cameras, two stereo.
ARGOVERSE2_CAMERAS = (
    "ring_front_center",
    "ring_front_left",
    "ring_front_right",
    "ring_side_left",
    "ring_side_right",
    "ring_rear_left",
    "ring_rear_right",
    "stereo_front_left",
    "stereo_front_right",
)
#: the two VLP-32 LiDARs merged in each sweep file: ``laser_number`` 0-31 and 32-63.
ARGOVERSE2_LIDARS = ("up_lidar", "down_lidar")
_LASERS = {"up_lidar": (0, 32), "down_lidar": (32, 64)}
#: an image farther than this from a sweep is not that sweep's (half the cameras' 50 ms period).
ARGOVERSE2_MAX_IMAGE_OFFSET_MS = 25.0
#: the categories whose moving boxes become tracks (rigid vehicles).
ARGOVERSE2_VEHICLES = frozenset(
    {
        "REGULAR_VEHICLE",
        "LARGE_VEHICLE",
        "BUS",
        "ARTICULATED_BUS",
        "SCHOOL_BUS",
        "BOX_TRUCK",
        "TRUCK",
        "TRUCK_CAB",
        "VEHICULAR_TRAILER",
        "MESSAGE_BOARD_TRAILER",
        "TRAFFIC_LIGHT_TRAILER",
        "RAILED_VEHICLE",
        "MOTORCYCLE",
        "BICYCLE",
    }
)

_QUAT, _TRANS = ("qw", "qx", "qy", "qz"), ("tx_m", "ty_m", "tz_m")
_POSE_COLUMNS = {**dict.fromkeys(_QUAT, "float"), **dict.fromkeys(_TRANS, "float")}
_POSES = "city_SE3_egovehicle.feather"
_EXTRINSICS = "calibration/egovehicle_SE3_sensor.feather"
_INTRINSICS = "calibration/intrinsics.feather"
_ANNOTATIONS = "annotations.feather"


def _pyarrow():
    """``(pyarrow, pyarrow.feather)``, or an ``ImportError`` saying how to install them."""
    try:
        import pyarrow as pa
        import pyarrow.feather as feather
    except ImportError:
        raise ImportError(
            "load_argoverse2 needs pyarrow to read Argoverse 2 feather files: "
            "pip install 'vadgs[argoverse2]' (or pip install pyarrow)"
        ) from None
    return pa, feather


def read_feather_columns(path: str | Path, columns: Mapping[str, str]) -> dict[str, np.ndarray]:
    """Read and check columns of a Feather file: ``name → kind`` (``"float"``, ``"int"``, ``"str"``).

    ``"float"`` columns may be any floating or integer type (AV2 stores LiDAR points as float16)
    and are returned as finite float64; ``"int"`` columns int64; ``"str"`` columns (plain or
    dictionary-encoded strings) an object array of ``str``. Other columns are not converted.

    Raises:
        ImportError: if ``pyarrow`` is not installed.
        FileNotFoundError: if ``path`` is not a file.
        ValueError: naming the file: not a readable Feather file (empty, truncated, another
            format); a missing column (and those there are); a column of the wrong type (expected
            and actual); a null or non-finite value.

    Example:
        >>> import tempfile, pyarrow as pa, pyarrow.feather as feather
        >>> with tempfile.TemporaryDirectory() as d:
        ...     feather.write_feather(pa.table({"a": [1.5, 2.0], "n": ["x", "y"]}), f"{d}/t.feather")
        ...     cols = read_feather_columns(f"{d}/t.feather", {"a": "float", "n": "str"})
        >>> cols["a"].tolist(), cols["n"].tolist()
        ([1.5, 2.0], ['x', 'y'])
    """
    pa, feather = _pyarrow()
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"Argoverse 2: missing file {path}")
    try:
        table = feather.read_table(path, memory_map=False)
    except (pa.ArrowException, OSError, ValueError) as e:
        raise ValueError(f"{path}: not a readable Feather file ({type(e).__name__}: {e})") from None
    missing = [c for c in columns if c not in table.column_names]
    if missing:
        raise ValueError(f"{path}: missing column(s) {missing}, have {table.column_names}")
    out: dict[str, np.ndarray] = {}
    for name, kind in columns.items():
        col = table.column(name)
        typ = col.type
        if pa.types.is_dictionary(typ):
            col, typ = col.cast(typ.value_type), typ.value_type
        ok = {
            "float": pa.types.is_floating(typ) or pa.types.is_integer(typ),
            "int": pa.types.is_integer(typ),
            "str": pa.types.is_string(typ) or pa.types.is_large_string(typ),
        }[kind]
        if not ok:
            expected = {"float": "a float or integer", "int": "an integer", "str": "a string"}[kind]
            raise ValueError(f"{path}: column {name!r}: expected {expected} type, got {typ}")
        if col.null_count:
            raise ValueError(f"{path}: column {name!r}: {col.null_count} null value(s)")
        if kind == "str":
            out[name] = np.array([str(v) for v in col.to_pylist()], dtype=object)
        elif kind == "int":
            out[name] = col.to_numpy().astype(np.int64)
        else:
            values = col.to_numpy().astype(np.float64)
            if not np.isfinite(values).all():
                raise ValueError(f"{path}: column {name!r}: non-finite value(s)")
            out[name] = values
    return out


def _se3(cols: dict[str, np.ndarray], path: Path) -> np.ndarray:
    """The ``(N, 4, 4)`` float64 transforms of rows ``qw..qz, tx_m..tz_m`` (quaternions normalised)."""
    q = np.stack([cols[c] for c in _QUAT], axis=-1)
    norm = np.linalg.norm(q, axis=-1)
    if (norm < 1e-6).any():
        raise ValueError(f"{path}: row {int(np.argmax(norm < 1e-6))}: quaternion qw..qz has zero norm")
    out = np.tile(np.eye(4), (len(q), 1, 1))
    if len(q):
        out[:, :3, :3] = Rotation.from_quat(q / norm[:, None], scalar_first=True).as_matrix()
    out[:, :3, 3] = np.stack([cols[c] for c in _TRANS], axis=-1)
    return out


class Argoverse2Poses(NamedTuple):
    """The ego poses of a log (``city_SE3_egovehicle.feather``), in time order.

    Attributes:
        timestamps_ns: ``(P,)`` int64.
        city_SE3_ego: ``(P, 4, 4)`` float64 ego → city (not recentred).
    """

    timestamps_ns: np.ndarray
    city_SE3_ego: np.ndarray


def read_argoverse2_poses(log_dir: str | Path) -> Argoverse2Poses:
    """Read a log's ``city_SE3_egovehicle.feather``, sorted by timestamp.

    Raises:
        FileNotFoundError: if the file is missing.
        ValueError: as :func:`read_feather_columns`; if it has no rows or two rows of one timestamp.
    """
    path = Path(log_dir) / _POSES
    cols = read_feather_columns(path, {"timestamp_ns": "int", **_POSE_COLUMNS})
    ts = cols["timestamp_ns"]
    if not len(ts):
        raise ValueError(f"{path}: no rows")
    order = np.argsort(ts, kind="stable")
    ts = ts[order]
    dup = ts[1:][np.diff(ts) == 0]
    if len(dup):
        raise ValueError(f"{path}: timestamp_ns {int(dup[0])} appears more than once")
    return Argoverse2Poses(ts, _se3(cols, path)[order])


def interpolate_city_SE3_ego(poses: Argoverse2Poses, query_ns: Sequence[int] | np.ndarray) -> np.ndarray:
    """The ego poses at ``query_ns``, interpolated between the two nearest recorded poses.

    The rotation is slerped and the translation interpolated linearly, as
    ``av2.geometry.interpolate.interpolate_pose`` does; a query at a recorded timestamp gets that
    pose exactly. The fraction between the two poses is computed from integer nanoseconds (no loss
    of precision at AV2's 1.6e18 ns timestamps).

    Args:
        poses: from :func:`read_argoverse2_poses`.
        query_ns: ``(Q,)`` integer timestamps in ``[poses.timestamps_ns[0], poses.timestamps_ns[-1]]``.

    Returns:
        ``(Q, 4, 4)`` float64 ego → city.

    Raises:
        ValueError: if a query lies outside the recorded poses (naming it and the range).

    Example:
        >>> rz = lambda a: Rotation.from_euler("z", a).as_matrix()
        >>> m = np.tile(np.eye(4), (2, 1, 1)); m[1, :3, :3] = rz(0.4); m[1, 0, 3] = 2.0
        >>> out = interpolate_city_SE3_ego(Argoverse2Poses(np.array([10, 20]), m), [15])
        >>> round(float(out[0, 0, 3]), 6), np.allclose(out[0, :3, :3], rz(0.2))
        (1.0, True)
    """
    ts = poses.timestamps_ns
    q = np.asarray(query_ns, dtype=np.int64).reshape(-1)
    outside = q[(q < ts[0]) | (q > ts[-1])]
    if len(outside):
        raise ValueError(
            f"query_ns: timestamp {int(outside[0])} is outside the recorded poses "
            f"[{int(ts[0])}, {int(ts[-1])}]"
        )
    out = poses.city_SE3_ego[np.clip(np.searchsorted(ts, q), 0, len(ts) - 1)].copy()
    between = ts[np.clip(np.searchsorted(ts, q), 0, len(ts) - 1)] != q
    if between.any():
        i1 = np.searchsorted(ts, q[between])
        i0 = i1 - 1
        frac = (q[between] - ts[i0]).astype(np.float64) / (ts[i1] - ts[i0]).astype(np.float64)
        m0, m1 = poses.city_SE3_ego[i0], poses.city_SE3_ego[i1]
        r0 = Rotation.from_matrix(m0[:, :3, :3])
        delta = (r0.inv() * Rotation.from_matrix(m1[:, :3, :3])).as_rotvec()
        rot = r0 * Rotation.from_rotvec(frac[:, None] * delta)
        mid = np.tile(np.eye(4), (len(frac), 1, 1))
        mid[:, :3, :3] = rot.as_matrix()
        mid[:, :3, 3] = m0[:, :3, 3] + frac[:, None] * (m1[:, :3, 3] - m0[:, :3, 3])
        out[between] = mid
    return out


def _timestamps(folder: Path, suffix: str) -> np.ndarray:
    """The sorted int64 timestamps of the ``<timestamp_ns><suffix>`` files of ``folder``."""
    stamps = [
        int(p.name[: -len(suffix)]) for p in folder.glob(f"*{suffix}") if p.name[: -len(suffix)].isdigit()
    ]
    return np.array(sorted(stamps), dtype=np.int64)


class Argoverse2Sync(NamedTuple):
    """Which image of each camera goes with which sweep, and what was left out.

    Attributes:
        cameras: the cameras, in view order.
        sweeps_ns: the kept sweeps' timestamps, in frame order.
        images_ns: camera → the timestamp of its image at each kept sweep.
        offsets_ms: camera → image minus sweep time at each kept sweep, in milliseconds.
        dropped: ``(sweep timestamp, why)`` of each selected sweep left out (no image within the
            window, no pose).
        missing_sweeps: the timestamps that ``annotations.feather`` annotates but
            ``sensors/lidar`` has no file of.
    """

    cameras: tuple[str, ...]
    sweeps_ns: tuple[int, ...]
    images_ns: dict[str, tuple[int, ...]]
    offsets_ms: dict[str, tuple[float, ...]]
    dropped: tuple[tuple[int, str], ...]
    missing_sweeps: tuple[int, ...]

    def summary(self) -> str:
        """A few lines for a person: frames, the largest offset per camera, what was left out."""
        lines = [f"{len(self.sweeps_ns)} sweep(s) x {len(self.cameras)} camera(s)"]
        for c in self.cameras:
            off = np.abs(np.array(self.offsets_ms[c]))
            if len(off):
                lines.append(
                    f"  {c}: image - sweep offset |mean| {off.mean():.1f} ms, max {off.max():.1f} ms"
                )
        for ts, why in self.dropped:
            lines.append(f"  dropped sweep {ts}: {why}")
        if self.missing_sweeps:
            lines.append(
                f"  {len(self.missing_sweeps)} annotated timestamp(s) without a sweep file, e.g. "
                f"{list(self.missing_sweeps[:3])}"
            )
        return "\n".join(lines)


def _camera_names(log_dir: Path, intrinsics: dict[str, np.ndarray]) -> list[str]:
    """The cameras of the intrinsics that have an image folder, in :data:`ARGOVERSE2_CAMERAS` order."""
    have = [str(n) for n in intrinsics["sensor_name"]]
    known = [c for c in ARGOVERSE2_CAMERAS if c in have] + sorted(
        c for c in have if c not in ARGOVERSE2_CAMERAS
    )
    return [c for c in known if (log_dir / "sensors" / "cameras" / c).is_dir()]


def _read_intrinsics(log_dir: Path) -> dict[str, np.ndarray]:
    cols = dict.fromkeys(("fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "k3"), "float")
    return read_feather_columns(
        log_dir / _INTRINSICS, {"sensor_name": "str", **cols, "width_px": "int", "height_px": "int"}
    )


def _check_log_dir(log_dir: str | Path) -> Path:
    log_dir = Path(log_dir)
    if not log_dir.is_dir():
        raise FileNotFoundError(f"log_dir: no such folder {log_dir}")
    if not (log_dir / "sensors" / "lidar").is_dir():
        raise FileNotFoundError(
            f"log_dir: {log_dir} is not an Argoverse 2 sensor-dataset log: no folder "
            f"{log_dir / 'sensors' / 'lidar'}"
        )
    return log_dir


def argoverse2_sync(
    log_dir: str | Path,
    cameras: Sequence[str] | None = None,
    frames: Sequence[int] | None = None,
    max_image_offset_ms: float = ARGOVERSE2_MAX_IMAGE_OFFSET_MS,
) -> Argoverse2Sync:
    """Match each selected sweep with each camera's nearest image (see the module docstring).

    Reads the file names of ``sensors/``, the pose table and the timestamps of the annotations;
    no image or point is decoded.

    Args:
        log_dir: the log folder.
        cameras: camera names (default: every camera of ``intrinsics.feather`` with an image folder).
        frames: sweep positions among the log's sweep files (default all).
        max_image_offset_ms: the largest image - sweep time difference of a frame's image.

    Returns:
        :class:`Argoverse2Sync`.

    Raises:
        FileNotFoundError: if the log folder, ``sensors/lidar`` or a table is missing.
        ValueError: if a camera or frame is unknown, a table is unreadable or wrong, or no sweep
            is left.
    """
    log_dir = _check_log_dir(log_dir)
    if not max_image_offset_ms > 0:
        raise ValueError(f"max_image_offset_ms: expected a positive number, got {max_image_offset_ms!r}")
    poses = read_argoverse2_poses(log_dir)
    names = select_cameras(
        cameras,
        _camera_names(log_dir, _read_intrinsics(log_dir)),
        f"Argoverse 2 log {log_dir}: no camera of {_INTRINSICS} has a folder in sensors/cameras",
    )
    all_sweeps = _timestamps(log_dir / "sensors" / "lidar", ".feather")
    if not len(all_sweeps):
        raise ValueError(f"Argoverse 2 log {log_dir}: no sweep (<timestamp_ns>.feather) in sensors/lidar")
    positions = select_positions(frames, len(all_sweeps), "sweep")
    images = {c: _timestamps(log_dir / "sensors" / "cameras" / c, ".jpg") for c in names}
    window = round(max_image_offset_ms * 1e6)
    lo, hi = int(poses.timestamps_ns[0]), int(poses.timestamps_ns[-1])
    kept: list[int] = []
    chosen: dict[str, list[int]] = {c: [] for c in names}
    dropped: list[tuple[int, str]] = []
    for p in positions:
        sweep = int(all_sweeps[p])
        if not lo <= sweep <= hi:
            dropped.append((sweep, f"no ego pose at the sweep's time (poses {lo}..{hi})"))
            continue
        pick: dict[str, int] = {}
        why = ""
        for c in names:
            ts = images[c]
            if not len(ts):
                why = f"no {c} image"
                break
            j = int(np.argmin(np.abs(ts - sweep)))
            if abs(int(ts[j]) - sweep) > window:
                near = (int(ts[j]) - sweep) / 1e6
                why = f"no {c} image within {max_image_offset_ms:g} ms (nearest {near:+.1f} ms)"
                break
            if not lo <= int(ts[j]) <= hi:
                why = f"no ego pose at the {c} image's time {int(ts[j])}"
                break
            pick[c] = int(ts[j])
        if why:
            dropped.append((sweep, why))
            continue
        kept.append(sweep)
        for c in names:
            chosen[c].append(pick[c])
    if not kept:
        raise ValueError(
            f"Argoverse 2 log {log_dir}: no selected sweep has an image of every camera {names} "
            f"within {max_image_offset_ms:g} ms and an ego pose, e.g. {dropped[:3]}"
        )
    missing: tuple[int, ...] = ()
    if (log_dir / _ANNOTATIONS).is_file():
        annotated = np.unique(
            read_feather_columns(log_dir / _ANNOTATIONS, {"timestamp_ns": "int"})["timestamp_ns"]
        )
        missing = tuple(int(t) for t in np.setdiff1d(annotated, all_sweeps))
    return Argoverse2Sync(
        tuple(names),
        tuple(kept),
        {c: tuple(v) for c, v in chosen.items()},
        {c: tuple((t - s) / 1e6 for t, s in zip(v, kept)) for c, v in chosen.items()},
        tuple(dropped),
        missing,
    )


def load_argoverse2(
    log_dir: str | Path,
    cameras: Sequence[str] | None = None,
    scale: float = 1.0,
    frames: Sequence[int] | None = None,
    test_frames: Sequence[int] | None = None,
    min_motion_m: float | None = 0.5,
    lidars: Sequence[str] | None = ARGOVERSE2_LIDARS,
    recenter: bool = True,
    undistort: bool = False,
    max_image_offset_ms: float = ARGOVERSE2_MAX_IMAGE_OFFSET_MS,
) -> Scene:
    """Load one Argoverse 2 sensor-dataset log as a :class:`Scene`.

    See the module docstring for the files read and how they map to vadgs.

    What the scene holds:

    - ``cameras_info``: ``K`` from ``intrinsics.feather`` (rescaled by ``scale``; with
      ``undistort`` the undistorted images'), the calibrated image size, ``cam_to_ego``.
    - ``views``: the JPEG files (``ViewInfo.image``; each decoded image's size is checked against
      the calibration), ``cam_to_world`` with the ego pose interpolated to the image's timestamp,
      ``timestamp`` = the image's, in seconds since the first frame's sweep.
    - ``frames``: the kept sweeps (:func:`argoverse2_sync`), ``ego_to_world`` at the sweep's
      timestamp, ``lidar`` the sweep file; ``Scene.lidar(f)`` returns its points of ``lidars`` in
      the world, each point's ``instance`` the id of the box it falls in (0 outside).
    - ``instances`` / ``tracks``: from ``annotations.feather`` (``name`` = ``track_uuid``); tracks
      are the :data:`ARGOVERSE2_VEHICLES` boxes moving more than ``min_motion_m`` (every vehicle
      with None). No annotation file: no instances.
    - ``test_frames``: 2, 6, 10, ... of the kept frames unless given; ``train_frames`` the rest.

    Args:
        log_dir: the log folder (``.../sensor/train/<log_id>``).
        cameras: camera names (default: every camera with calibration and images, in
            :data:`ARGOVERSE2_CAMERAS` order).
        scale: resolution factor for images and intrinsics.
        frames: sweep positions to keep (default all), renumbered 0, 1, ... (dropped sweeps removed).
        test_frames: frame indices to hold out (default every fourth from 2; ``()`` for none).
        min_motion_m: motion threshold (metres) for a vehicle to be a track; None: every vehicle.
        lidars: the LiDARs whose points form each frame's LiDAR (:data:`ARGOVERSE2_LIDARS`), or
            None for no LiDAR.
        recenter: translate the world so that the ego at the first frame sits at the origin.
        undistort: undistort the images with ``k1, k2, k3`` (default: ignore them, as the
            devkit's ``PinholeCamera`` does).
        max_image_offset_ms: the largest image - sweep time difference of a frame's image.

    Returns:
        The :class:`Scene`. Dropped sweeps and annotated timestamps without a sweep file are
        reported with a :class:`UserWarning`.

    Raises:
        ImportError: if ``pyarrow`` is not installed.
        FileNotFoundError: if the log folder, ``sensors/lidar`` or a required table is missing.
        ValueError: naming the file, for a table that is unreadable (truncated), lacks a column
            or has one of the wrong type; for an unknown camera, LiDAR or frame; for an argument
            out of range.

    Example:
        >>> log = "/data/av2/sensor/val/02678d04-cc9f-3148-9f95-1ba66347dff9"
        >>> scene = load_argoverse2(log, cameras=["ring_front_center"], scale=0.25)  # doctest: +SKIP
        >>> scene.num_frames  # doctest: +SKIP
        157
    """
    check_scale(scale)
    check_min_motion(min_motion_m)
    if lidars is not None:
        bad = [n for n in lidars if n not in ARGOVERSE2_LIDARS]
        if bad or not lidars:
            raise ValueError(
                f"lidars: expected names of {list(ARGOVERSE2_LIDARS)} or None, got {list(lidars)}"
            )
    sync = argoverse2_sync(log_dir, cameras, frames, max_image_offset_ms)
    log_dir = Path(log_dir)
    if sync.dropped or sync.missing_sweeps:
        warnings.warn(f"Argoverse 2 log {log_dir.name}: {sync.summary()}", stacklevel=2)
    poses = read_argoverse2_poses(log_dir)
    num_frames = len(sync.sweeps_ns)
    test = held_out_frames(test_frames, num_frames)
    ego_to_city = interpolate_city_SE3_ego(poses, sync.sweeps_ns)
    offset = ego_to_city[0, :3, 3].copy() if recenter else np.zeros(3)
    ego_to_world = recentred(ego_to_city, offset)
    t0 = sync.sweeps_ns[0]

    # -- cameras -------------------------------------------------------------------------------------
    intr = _read_intrinsics(log_dir)
    extr_path = log_dir / _EXTRINSICS
    extr = read_feather_columns(extr_path, {"sensor_name": "str", **_POSE_COLUMNS})
    sensor_to_ego = dict(zip((str(n) for n in extr["sensor_name"]), _se3(extr, extr_path)))
    row_of = {str(n): i for i, n in enumerate(intr["sensor_name"])}
    cams: dict[str, CameraInfo] = {}
    undistorters: dict[str, ImageUndistorter] = {}
    for n in sync.cameras:
        if n not in sensor_to_ego:
            raise ValueError(f"{extr_path}: no row of sensor_name {n!r}, have {sorted(sensor_to_ego)}")
        r = row_of[n]
        what = f"Argoverse 2 {_INTRINSICS}[{n}]"
        w, h = int(intr["width_px"][r]), int(intr["height_px"][r])
        if w < 1 or h < 1:
            raise ValueError(f"{what}: expected a positive width_px and height_px, got {w}x{h}")
        raw_K = torch.tensor(
            [
                [intr["fx_px"][r], 0.0, intr["cx_px"][r]],
                [0.0, intr["fy_px"][r], intr["cy_px"][r]],
                [0.0, 0.0, 1.0],
            ],
            dtype=torch.float64,
        )
        k1, k2, k3 = (float(intr[k][r]) for k in ("k1", "k2", "k3"))
        dist = torch.tensor([k1, k2, 0.0, 0.0, k3] if undistort else [0.0] * 4, dtype=torch.float64)
        cams[n], undistorters[n] = pinhole_camera(n, raw_K, dist, (h, w), scale, sensor_to_ego[n], what)

    # -- frames and views ------------------------------------------------------------------------------
    cam_root = log_dir / "sensors" / "cameras"
    lidar_root = log_dir / "sensors" / "lidar"
    image_poses = {c: interpolate_city_SE3_ego(poses, sync.images_ns[c]) for c in sync.cameras}
    views: list[ViewInfo] = []
    frame_infos: list[FrameInfo] = []
    for fi, sweep in enumerate(sync.sweeps_ns):
        ids = []
        for c in sync.cameras:
            ts = sync.images_ns[c][fi]
            c2w = recentred(image_poses[c][fi], offset) @ sensor_to_ego[c]
            views.append(
                ViewInfo(
                    len(views),
                    fi,
                    c,
                    (ts - t0) * 1e-9,
                    as_tensor(c2w, f"{c} at image {ts}"),
                    image=cam_root / c / f"{ts}.jpg",
                )
            )
            ids.append(len(views) - 1)
        frame_infos.append(
            FrameInfo(
                fi,
                (sweep - t0) * 1e-9,
                as_tensor(ego_to_world[fi], f"{_POSES} at sweep {sweep}"),
                tuple(ids),
                lidar=lidar_root / f"{sweep}.feather" if lidars is not None else None,
            )
        )

    def image_loader(view: ViewInfo) -> torch.Tensor:
        assert view.image is not None  # every view above has its JPEG
        img = read_rgb(view.image)
        und = undistorters[view.camera]
        if tuple(img.shape[-2:]) != und.image_size:
            raise ValueError(
                f"Argoverse 2 image {view.image}: size {img.shape[-1]}x{img.shape[-2]} differs from "
                f"{_INTRINSICS}'s {und.image_size[1]}x{und.image_size[0]}"
            )
        return und(img[None])[0].clamp_(0.0, 1.0) if und.distorted else img

    # -- boxes → instances and tracks ----------------------------------------------------------------
    boxes: dict[int, dict[int, BoxObservation]] = {}
    box_names: dict[int, str] = {}
    rigid: set[str] = set()
    ann_path = log_dir / _ANNOTATIONS
    if ann_path.is_file():
        sizes = ("length_m", "width_m", "height_m")
        ann = read_feather_columns(
            ann_path,
            {
                "timestamp_ns": "int",
                "track_uuid": "str",
                "category": "str",
                **dict.fromkeys(sizes, "float"),
                **_POSE_COLUMNS,
            },
        )
        box_to_ego = _se3(ann, ann_path)
        frame_of = {ts: fi for fi, ts in enumerate(sync.sweeps_ns)}
        id_of: dict[str, int] = {}
        rows = sorted(
            range(len(ann["timestamp_ns"])), key=lambda i: (int(ann["timestamp_ns"][i]), ann["track_uuid"][i])
        )
        for i in rows:
            pos = frame_of.get(int(ann["timestamp_ns"][i]))
            if pos is None:
                continue
            uuid = str(ann["track_uuid"][i])
            if uuid not in id_of:
                id_of[uuid] = len(id_of) + 1
                box_names[id_of[uuid]] = uuid
            category = str(ann["category"][i])
            if category in ARGOVERSE2_VEHICLES:
                rigid.add(category.lower())
            size = np.array([ann[s][i] for s in sizes])
            boxes.setdefault(id_of[uuid], {})[pos] = BoxObservation(
                ego_to_world[pos] @ box_to_ego[i], size, category.lower()
            )
    instances, tracks = build_instances(boxes, box_names, num_frames, lambda cls: cls in rigid, min_motion_m)

    # -- LiDAR ---------------------------------------------------------------------------------------
    read_lidar = None
    if lidars is not None:
        missing = [n for n in lidars if n not in sensor_to_ego]
        if missing:
            raise ValueError(
                f"{extr_path}: no row of sensor_name {missing[0]!r}, have {sorted(sensor_to_ego)}"
            )
        lidar_names = tuple(lidars)

        def read_lidar(frame: int, path: Path) -> LidarFrame:
            cols = read_feather_columns(
                path, {"x": "float", "y": "float", "z": "float", "laser_number": "int"}
            )
            laser = cols["laser_number"]
            keep = np.zeros(len(laser), dtype=bool)
            for n in lidar_names:
                a, b = _LASERS[n]
                keep |= (laser >= a) & (laser < b)
            ego = np.stack([cols["x"], cols["y"], cols["z"]], axis=-1)[keep]
            e2w = ego_to_world[frame]
            world = ego @ e2w[:3, :3].T + e2w[:3, 3]
            origin = e2w @ sensor_to_ego[lidar_names[0]][:, 3]
            return labelled_lidar(world, origin[:3], boxes, frame)

    return assemble_scene(
        f"Argoverse 2 log {log_dir}",
        name=log_dir.name,
        root=log_dir,
        cameras_info=cams,
        frames=frame_infos,
        views=views,
        instances=instances,
        tracks=tracks,
        test_frames=test,
        scale=scale,
        read_lidar=read_lidar,
        image_loader=image_loader,
    )
