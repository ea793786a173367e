"""The tables and timing of an Argoverse 2 sensor-dataset log, read with ``pyarrow``.

What :func:`vadgs.data.argoverse2.load_argoverse2` assembles into a scene (the files and how they
map to vadgs: :mod:`vadgs.data.argoverse2`): checked Feather columns (:func:`read_feather_columns`),
the ego poses and their interpolation (:func:`read_argoverse2_poses`,
:func:`interpolate_city_SE3_ego`), the calibration (:func:`read_argoverse2_intrinsics`,
:func:`read_argoverse2_sensor_to_ego`), the boxes (:func:`read_argoverse2_boxes`) and which
image of each camera goes with which sweep (:func:`argoverse2_sync`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from vadgs.data._tracks import select_cameras, select_positions

__all__ = [
    "ARGOVERSE2_CAMERAS",
    "ARGOVERSE2_INTRINSICS",
    "ARGOVERSE2_MAX_IMAGE_OFFSET_MS",
    "ARGOVERSE2_POSES",
    "Argoverse2Boxes",
    "Argoverse2Poses",
    "Argoverse2Sync",
    "argoverse2_sync",
    "check_log_dir",
    "interpolate_city_SE3_ego",
    "read_argoverse2_boxes",
    "read_argoverse2_intrinsics",
    "read_argoverse2_poses",
    "read_argoverse2_sensor_to_ego",
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
#: an image farther than this from a sweep is not that sweep's (half the cameras' 50 ms period).
ARGOVERSE2_MAX_IMAGE_OFFSET_MS = 25.0

_QUAT, _TRANS = ("qw", "qx", "qy", "qz"), ("tx_m", "ty_m", "tz_m")
_POSE_COLUMNS = {**dict.fromkeys(_QUAT, "float"), **dict.fromkeys(_TRANS, "float")}
#: The ego poses' table of a log.
ARGOVERSE2_POSES = "city_SE3_egovehicle.feather"
_EXTRINSICS = "calibration/egovehicle_SE3_sensor.feather"
#: The cameras' intrinsics table of a log.
ARGOVERSE2_INTRINSICS = "calibration/intrinsics.feather"
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
    path = Path(log_dir) / ARGOVERSE2_POSES
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


def read_argoverse2_intrinsics(log_dir: Path) -> dict[str, np.ndarray]:
    """The columns of a log's ``calibration/intrinsics.feather`` (a row per sensor), checked."""
    cols = dict.fromkeys(("fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "k3"), "float")
    return read_feather_columns(
        log_dir / ARGOVERSE2_INTRINSICS, {"sensor_name": "str", **cols, "width_px": "int", "height_px": "int"}
    )


def check_log_dir(log_dir: str | Path) -> Path:
    """``log_dir`` as a path to an Argoverse 2 sensor-dataset log folder, or a ``FileNotFoundError``."""
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
    log_dir = check_log_dir(log_dir)
    if not max_image_offset_ms > 0:
        raise ValueError(f"max_image_offset_ms: expected a positive number, got {max_image_offset_ms!r}")
    poses = read_argoverse2_poses(log_dir)
    names = select_cameras(
        cameras,
        _camera_names(log_dir, read_argoverse2_intrinsics(log_dir)),
        f"Argoverse 2 log {log_dir}: no camera of {ARGOVERSE2_INTRINSICS} has a folder in sensors/cameras",
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


def read_argoverse2_sensor_to_ego(log_dir: Path, sensors: Sequence[str]) -> dict[str, np.ndarray]:
    """``sensor → (4, 4)`` float64 sensor → ego of ``calibration/egovehicle_SE3_sensor.feather``.

    Raises:
        FileNotFoundError: if the table is missing.
        ValueError: as :func:`read_feather_columns`; a sensor of ``sensors`` without a row.
    """
    path = log_dir / _EXTRINSICS
    extr = read_feather_columns(path, {"sensor_name": "str", **_POSE_COLUMNS})
    sensor_to_ego = dict(zip((str(n) for n in extr["sensor_name"]), _se3(extr, path)))
    missing = [n for n in sensors if n not in sensor_to_ego]
    if missing:
        raise ValueError(f"{path}: no row of sensor_name {missing[0]!r}, have {sorted(sensor_to_ego)}")
    return sensor_to_ego


class Argoverse2Boxes(NamedTuple):
    """The rows of a log's ``annotations.feather``: a box of a track at a sweep.

    Attributes:
        timestamps_ns: ``(N,)`` int64, the sweep of each box.
        track_uuid: ``(N,)`` str.
        category: ``(N,)`` str (AV2's, upper case).
        size: ``(N, 3)`` float64 ``length_m, width_m, height_m``.
        box_to_ego: ``(N, 4, 4)`` float64, the box in the ego frame at its sweep.
    """

    timestamps_ns: np.ndarray
    track_uuid: np.ndarray
    category: np.ndarray
    size: np.ndarray
    box_to_ego: np.ndarray


def read_argoverse2_boxes(log_dir: Path) -> Argoverse2Boxes | None:
    """A log's ``annotations.feather`` (None without one: the test split has none).

    Raises:
        ValueError: as :func:`read_feather_columns`.
    """
    path = log_dir / _ANNOTATIONS
    if not path.is_file():
        return None
    sizes = ("length_m", "width_m", "height_m")
    columns = {"timestamp_ns": "int", "track_uuid": "str", "category": "str", **dict.fromkeys(sizes, "float")}
    ann = read_feather_columns(path, {**columns, **_POSE_COLUMNS})
    size = np.stack([ann[s] for s in sizes], axis=-1)
    return Argoverse2Boxes(ann["timestamp_ns"], ann["track_uuid"], ann["category"], size, _se3(ann, path))
