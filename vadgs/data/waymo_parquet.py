"""Reading a Waymo Open Dataset v2 segment's parquet components with ``pyarrow``.

Each component of a segment is a parquet file, ``<dataset_dir>/<component>/<segment>.parquet``
(see :mod:`vadgs.data.waymo`, which assembles them into a scene). Here: the column names (the
key columns, :data:`WAYMO_SEGMENT_KEY` ..., the components' prefixes,
:data:`WAYMO_CAMERA_CALIBRATION` ..., :func:`component_columns`), a component file read column
by column or row group by row group with its checksums verified and its errors naming it
(:class:`WaymoComponent`, :func:`parquet_error`), its range images, the transforms
(:func:`waymo_matrix`), the camera names (:func:`waymo_camera_name`) and the vehicle poses
(:func:`read_waymo_poses`).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

__all__ = [
    "WAYMO_CAMERAS",
    "WAYMO_CAMERA_CALIBRATION",
    "WAYMO_CAMERA_IMAGE",
    "WAYMO_CAMERA_KEY",
    "WAYMO_LASERS",
    "WAYMO_LASER_KEY",
    "WAYMO_LIDAR",
    "WAYMO_LIDAR_BOX",
    "WAYMO_LIDAR_CALIBRATION",
    "WAYMO_LIDAR_POSE",
    "WAYMO_OBJECT_KEY",
    "WAYMO_SEGMENT_KEY",
    "WAYMO_TIMESTAMP_KEY",
    "WAYMO_VEHICLE_POSE",
    "WaymoComponent",
    "WaymoPoses",
    "component_columns",
    "parquet_error",
    "pyarrow_parquet",
    "read_waymo_poses",
    "waymo_camera_name",
    "waymo_matrix",
]

#: ``key.camera_name`` → name (``camera_image.CameraName``).
WAYMO_CAMERAS = {1: "FRONT", 2: "FRONT_LEFT", 3: "FRONT_RIGHT", 4: "SIDE_LEFT", 5: "SIDE_RIGHT"}
#: ``key.laser_name`` → name (``lidar.LaserName``).
WAYMO_LASERS = {1: "TOP", 2: "FRONT", 3: "SIDE_LEFT", 4: "SIDE_RIGHT", 5: "REAR"}

#: The key columns of the components' rows: segment, frame timestamp, camera, laser, object.
WAYMO_SEGMENT_KEY = "key.segment_context_name"
WAYMO_TIMESTAMP_KEY = "key.frame_timestamp_micros"
WAYMO_CAMERA_KEY = "key.camera_name"
WAYMO_LASER_KEY = "key.laser_name"
WAYMO_OBJECT_KEY = "key.laser_object_id"
_SEG, _TS, _LASER = WAYMO_SEGMENT_KEY, WAYMO_TIMESTAMP_KEY, WAYMO_LASER_KEY
#: The components' column prefixes (``<component>.<field>``), read here and written by
#: :func:`vadgs.data.waymo_writer.write_waymo_segment`.
WAYMO_CAMERA_CALIBRATION = "[CameraCalibrationComponent]"
WAYMO_CAMERA_IMAGE = "[CameraImageComponent]"
WAYMO_LIDAR_CALIBRATION = "[LiDARCalibrationComponent]"
WAYMO_LIDAR = "[LiDARComponent]"
WAYMO_LIDAR_POSE = "[LiDARPoseComponent]"
WAYMO_LIDAR_BOX = "[LiDARBoxComponent]"
WAYMO_VEHICLE_POSE = "[VehiclePoseComponent]"
_RANGE_IMAGE = ("range_image_return1.values", "range_image_return1.shape")  # fields of lidar, lidar_pose


def pyarrow_parquet():
    """``pyarrow.parquet``, or an ``ImportError`` saying how to install it (the ``waymo`` extra)."""
    try:
        import pyarrow.parquet as pq
    except ImportError:
        raise ImportError(
            "load_waymo needs pyarrow to read Waymo v2 parquet files: pip install 'vadgs[waymo]' "
            "(or pip install pyarrow)"
        ) from None
    return pq


def component_columns(component: str, *fields: str) -> list[str]:
    """The column names ``<component>.<field>`` of a component's fields, in order."""
    return [f"{component}.{f}" for f in fields]


def waymo_matrix(value: object, what: str) -> np.ndarray:
    """A row-major 4x4 transform (16 finite numbers) as ``(4, 4)`` float64.

    Raises:
        ValueError: naming ``what``, for anything else.
    """
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"Waymo {what}: expected 16 numbers (a row-major 4x4), got {value!r}") from None
    if m.size != 16 or not np.isfinite(m).all():
        raise ValueError(f"Waymo {what}: expected 16 finite numbers (a row-major 4x4), got {m.size}")
    return m.reshape(4, 4)


def parquet_error(path: Path, e: BaseException, at: str = "") -> ValueError:
    """The error for a parquet file that pyarrow cannot read: names the file (and ``at``) and says why.

    Example:
        >>> str(parquet_error(Path("x.parquet"), OSError("Parquet magic bytes not found")))
        'x.parquet: not a readable parquet file, truncated or corrupt (OSError: Parquet magic bytes ...)'
    """
    try:
        empty = path.stat().st_size == 0
    except OSError:
        empty = False
    what = "an empty file (0 bytes)" if empty else f"{type(e).__name__}: {e}"
    return ValueError(f"{path}{at}: not a readable parquet file, truncated or corrupt ({what})")


@contextlib.contextmanager
def _reading(path: Path, at: str = "") -> Iterator[None]:
    """Turn pyarrow's errors while reading ``path`` into :func:`parquet_error` (naming the file)."""
    try:
        yield
    except Exception as e:
        import pyarrow as pa  # imported by pyarrow_parquet() before any read

        if isinstance(e, (pa.ArrowException, OSError, ValueError)):
            raise parquet_error(path, e, at) from e
        raise


class WaymoComponent:
    """One component file of one segment: its path, and columns read on demand.

    Every read verifies the pages' CRC checksums where the file has them
    (:func:`~vadgs.data.waymo_writer.write_waymo_segment` writes them), and a file pyarrow cannot
    read is a ``ValueError`` naming it.
    """

    def __init__(self, pq, dataset_dir: Path, name: str, segment: str, required: bool = True):
        self.pq, self.name, self.segment = pq, name, segment
        self.path = dataset_dir / name / f"{segment}.parquet"
        self.exists = self.path.is_file()
        self._file = None
        self._index: dict[tuple[int, int], tuple[int, int]] | None = None
        if required and not self.exists:
            raise FileNotFoundError(f"Waymo component {name!r}: missing file {self.path}")

    @property
    def where(self) -> str:
        """``Waymo component 'lidar' (<path>)``: how errors name the file."""
        return f"Waymo component {self.name!r} ({self.path})"

    def parquet_file(self):
        """The ``pyarrow.parquet.ParquetFile`` (opened once)."""
        if self._file is None:
            with _reading(self.path):
                self._file = self.pq.ParquetFile(self.path, page_checksum_verification=True)
        return self._file

    def names(self) -> set[str]:
        """The file's column names."""
        return set(self.parquet_file().schema_arrow.names)

    def read_row_group(self, rg: int, columns: Sequence[str], at: str = ""):
        """Row group ``rg``'s ``columns`` as a pyarrow table (``at``: more for the error, e.g. the frame)."""
        with _reading(self.path, f", row group {rg}{at}"):
            return self.parquet_file().read_row_group(rg, columns=list(columns))

    def read_table(self, columns: Sequence[str], optional: Sequence[str] = (), filters=None):
        """The pyarrow table of ``columns`` (each required) and those of ``optional`` the file has."""
        names = self.names()
        missing = [c for c in columns if c not in names]
        if missing:
            raise ValueError(f"Waymo component {self.name!r} ({self.path.name}): missing column(s) {missing}")
        cols = list(columns) + [c for c in optional if c in names]
        with _reading(self.path):
            return self.pq.read_table(
                self.path, columns=cols, filters=filters, page_checksum_verification=True
            )

    def read(self, columns: Sequence[str], optional: Sequence[str] = (), filters=None) -> dict[str, list]:
        """Column name → Python values (None for an absent optional column), as ``read_table``."""
        table = self.read_table(columns, optional, filters)
        with _reading(self.path):
            out = table.to_pydict()
        return {c: out.get(c, [None] * table.num_rows) for c in [*columns, *optional]}

    def range_image_rows(self) -> dict[tuple[int, int], tuple[int, int]]:
        """``(key.frame_timestamp_micros, key.laser_name)`` → ``(row group, row)`` of the segment's rows."""
        if self._index is None:
            names = self.names()
            missing = [c for c in (_SEG, _TS, _LASER) if c not in names]
            if missing:
                raise ValueError(f"{self.where}: missing column(s) {missing}")
            self._index = {}
            for rg in range(self.parquet_file().num_row_groups):
                d = self.read_row_group(rg, [_SEG, _TS, _LASER]).to_pydict()
                for r, (seg, ts, laser) in enumerate(zip(d[_SEG], d[_TS], d[_LASER])):
                    if seg == self.segment and ts is not None and laser is not None:
                        key = (int(ts), int(laser))
                        if key in self._index:
                            raise ValueError(
                                f"{self.where}: two range images of laser {laser} at timestamp {ts} µs "
                                f"(row group {self._index[key][0]} row {self._index[key][1]}, row group {rg} "
                                f"row {r}); the file is corrupt"
                            )
                        self._index[key] = (rg, r)
        return self._index

    def range_images(
        self, component: str, ts: int, frame: int, lasers: Sequence[int], channels: int | None = None
    ) -> dict[int, tuple[np.ndarray, str]]:
        """``key.laser_name`` → ``(image, where)``: a frame's range images of ``lasers`` the file has.

        ``image`` is the ``(H, W, C)`` float32 first-return range image of frame ``frame``
        (timestamp ``ts``), ``where`` names the file, row group, row, frame and laser for the
        errors about it.

        The values stay in numpy (a range image is ~700k floats: no Python list of them).

        Raises:
            ValueError: naming the file, row group, frame and laser: a shape that is not three
                positive sizes (``C == channels`` if given), or a value count that differs from it.
        """
        values, shape = component_columns(component, *_RANGE_IMAGE)
        names = self.names()
        missing = [c for c in (values, shape) if c not in names]
        if missing:
            raise ValueError(f"{self.where}: missing column(s) {missing}")
        rows = {k: self.range_image_rows().get((ts, k)) for k in lasers}
        out: dict[int, tuple[np.ndarray, str]] = {}
        for rg in sorted({v[0] for v in rows.values() if v is not None}):
            table = self.read_row_group(rg, [values, shape], f" (frame {frame}, timestamp {ts} µs)")
            for laser, at in rows.items():
                if at is None or at[0] != rg:
                    continue
                r = at[1]
                name = WAYMO_LASERS.get(laser, str(laser))
                where = (
                    f"{self.where}, row group {rg}, row {r} (frame {frame}, timestamp {ts} µs, laser {name})"
                )
                vals, shp = table.column(values)[r], table.column(shape)[r].as_py()
                if not vals.is_valid or shp is None:
                    raise ValueError(f"{where}: no range image (null values or shape)")
                if (
                    len(shp) != 3
                    or any(v is None or v <= 0 for v in shp)
                    or (channels is not None and shp[2] != channels)
                ):
                    want = f"(H, W, {channels})" if channels is not None else "(H, W, C)"
                    raise ValueError(
                        f"{where}: expected a range image shape {want} of positive sizes, got {shp}"
                    )
                with _reading(self.path):
                    flat = vals.values.to_numpy(zero_copy_only=False)
                if flat.size != int(np.prod(shp)):
                    raise ValueError(f"{where}: a range image of shape {shp} has {flat.size} values")
                out[laser] = (flat.reshape(shp), where)
        return out


def waymo_camera_name(value: object) -> str:
    """The camera name of a ``key.camera_name`` value: the v2 schema's int8 id or the name itself.

    Raises:
        ValueError: if the value is neither a known id (1-5) nor a known name; the message names
            ``key.camera_name`` and lists both.

    Example:
        >>> waymo_camera_name(1), waymo_camera_name("SIDE_LEFT"), waymo_camera_name(b"FRONT_RIGHT")
        ('FRONT', 'SIDE_LEFT', 'FRONT_RIGHT')
    """
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    if isinstance(value, str):
        name = value.strip().upper()
        if name in WAYMO_CAMERAS.values():
            return name
        if name.isdigit() and int(name) in WAYMO_CAMERAS:
            return WAYMO_CAMERAS[int(name)]
    elif isinstance(value, (int, np.integer)) and int(value) in WAYMO_CAMERAS:
        return WAYMO_CAMERAS[int(value)]
    raise ValueError(
        f"key.camera_name: expected a camera id {sorted(WAYMO_CAMERAS)} or name "
        f"{list(WAYMO_CAMERAS.values())}, got {value!r}"
    )


class WaymoPoses(NamedTuple):
    """The vehicle poses of a segment (``vehicle_pose``), in time order.

    Attributes:
        timestamps_us: ``(F,)`` int64 ``key.frame_timestamp_micros``.
        world_from_vehicle: ``(F, 4, 4)`` float64 vehicle → Waymo's global frame (not recentred).
    """

    timestamps_us: torch.Tensor
    world_from_vehicle: torch.Tensor


def read_waymo_poses(dataset_dir: str | Path, segment: str) -> WaymoPoses:
    """Read a segment's ``vehicle_pose`` component (float64 or float32 transforms).

    Args:
        dataset_dir: the split folder holding one sub-folder per component.
        segment: the ``segment_context_name`` (the parquet file's stem).

    Returns:
        :class:`WaymoPoses`, sorted by timestamp.

    Raises:
        ImportError: if ``pyarrow`` is not installed.
        FileNotFoundError: if ``dataset_dir`` or its ``vehicle_pose`` folder is missing.
        ValueError: if the segment is unknown, a column is missing, a transform is not 16
            finite numbers, or the segment has no rows.

    Example:
        >>> from pathlib import Path
        >>> root = Path("/data/waymo/v2/training")
        >>> if root.is_dir():  # doctest: +SKIP
        ...     poses = read_waymo_poses(root, "10023947602400723454_1120_000_1140_000")
        ...     poses.world_from_vehicle.shape
        torch.Size([199, 4, 4])
    """
    pq = pyarrow_parquet()
    dataset_dir = Path(dataset_dir)
    if not dataset_dir.is_dir():
        raise FileNotFoundError(f"dataset_dir: no such folder {dataset_dir}")
    pose_dir = dataset_dir / "vehicle_pose"
    if not pose_dir.is_dir():
        raise FileNotFoundError(f"Waymo component 'vehicle_pose': no folder {pose_dir}")
    if not (pose_dir / f"{segment}.parquet").is_file():
        have = sorted(p.stem for p in pose_dir.glob("*.parquet"))
        raise ValueError(f"segment: unknown segment {segment!r} in {dataset_dir}, have {have[:20]}")
    vp = WaymoComponent(pq, dataset_dir, "vehicle_pose", segment).read(
        [_TS, f"{WAYMO_VEHICLE_POSE}.world_from_vehicle.transform"], filters=[(_SEG, "=", segment)]
    )
    if not vp[_TS]:
        raise ValueError(f"Waymo segment {segment}: vehicle_pose has no rows")
    order = np.argsort(vp[_TS], kind="stable")
    transforms = vp[f"{WAYMO_VEHICLE_POSE}.world_from_vehicle.transform"]
    poses = [waymo_matrix(transforms[i], "vehicle_pose") for i in order]
    return WaymoPoses(
        torch.tensor([int(vp[_TS][i]) for i in order], dtype=torch.int64),
        torch.from_numpy(np.stack(poses)),
    )
