"""A benchmark-format scene written as a Waymo Open Dataset v2 segment that :func:`load_waymo` reads.

:func:`write_waymo_segment` turns a scene folder (``scene.json`` and its files, e.g. one written by
:func:`~vadgs.data.make_segment`) into the v2 parquet components, one file per component in
``<out_dir>/<component>/<segment>.parquet`` with the official column names and types:
``vehicle_pose``, ``camera_calibration``, ``camera_image``, ``lidar_calibration``, ``lidar``
and ``lidar_box``. It is the inverse of :func:`~vadgs.data.waymo.load_waymo` (see its module
docstring for the conventions), so that the reader and ``vadgs convert waymo`` can be tested
and measured on a segment of any size with known ground truth:

- **Frames**: ``vehicle_pose`` = ``ego_to_world``; ``key.frame_timestamp_micros`` =
  ``start_us`` + the frame's timestamp.
- **Cameras**: a scene camera named ``front``, ``front_left``, ... (any case) becomes Waymo's
  ``FRONT`` (1), ``FRONT_LEFT`` (2), ``FRONT_RIGHT`` (3), ``SIDE_LEFT`` (4) or ``SIDE_RIGHT`` (5).
  ``extrinsic = cam_to_ego @ WAYMO_CAMERA_TO_OPENCV⁻¹`` (Waymo camera axes), ``c_u, c_v`` =
  ``K``'s principal point + 0.5 (:data:`~vadgs.data.waymo.WAYMO_PIXEL_OFFSET`), no distortion.
  Each image's ``pose`` is ``cam_to_world @ cam_to_ego⁻¹``, so the reader gives back every
  view's ``cam_to_world``; JPEG files are stored as they are (other images are encoded as JPEG).
- **LiDAR**: the TOP laser, its extrinsic a translation to the sensor's position in the ego
  frame at frame 0 (LiDAR axes = vehicle axes), its rows the beams of the scene's LiDAR profile
  (``scene.json``'s ``lidar``: ``beams`` evenly over ``vfov``). Each frame's points become the
  first return of a range image (:func:`~vadgs.data.waymo_lidar.waymo_points_to_range_image`):
  read back, a point keeps its range and beam and moves to its column's centre azimuth, at
  most half a column sideways. No ``lidar_pose`` (one ego pose per sweep).
- **Tracks**: one ``lidar_box`` row per track and frame where it is valid, ``laser_object_id``
  = the instance's name, so that the reader's tracks are the scene's. A box's centre is the
  object's origin, or its origin + half the height with ``box_origin="bottom"`` (the benchmark
  format's object frame: the origin at the bottom centre); the heading is the box's yaw in the
  vehicle frame (Waymo boxes have no pitch or roll). Type: ``vehicle`` for ``car``, ``vehicle``,
  ``truck`` and ``bus``, ``pedestrian``, ``sign``, ``cyclist``, else ``unknown``.

Each of ``camera_image`` and ``lidar`` has one row group per frame and is written frame by frame
(``pyarrow.parquet.ParquetWriter``): one frame's images and LiDAR are in memory at a time.
``benchmarks/make_waymo_segment.py`` is the command line.
"""

from __future__ import annotations

import io
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from vadgs.data.scene import Scene
from vadgs.data.scene_json import load_scene
from vadgs.data.waymo import WAYMO_CAMERA_TO_OPENCV, WAYMO_PIXEL_OFFSET
from vadgs.data.waymo_lidar import WAYMO_MAX_RANGE_M, waymo_beam_inclinations, waymo_points_to_range_image
from vadgs.data.waymo_parquet import (
    WAYMO_CAMERA_CALIBRATION,
    WAYMO_CAMERA_IMAGE,
    WAYMO_CAMERAS,
    WAYMO_LIDAR,
    WAYMO_LIDAR_BOX,
    WAYMO_LIDAR_CALIBRATION,
    WAYMO_VEHICLE_POSE,
    pyarrow_parquet,
)
from vadgs.io import safe_filename

__all__ = ["BOX_TYPE_OF_CLASS", "MAX_COLUMNS", "WaymoSegmentSummary", "write_waymo_segment"]

_CC, _CI, _L, _LB, _LC, _VP = (  # short names for the columns below
    WAYMO_CAMERA_CALIBRATION,
    WAYMO_CAMERA_IMAGE,
    WAYMO_LIDAR,
    WAYMO_LIDAR_BOX,
    WAYMO_LIDAR_CALIBRATION,
    WAYMO_VEHICLE_POSE,
)

#: vadgs class name → ``[LiDARBoxComponent].type`` (``box.BoxType``); others are 0 (unknown).
BOX_TYPE_OF_CLASS = {"car": 1, "vehicle": 1, "truck": 1, "bus": 1, "pedestrian": 2, "sign": 3, "cyclist": 4}
#: the largest range-image width that ``columns=None`` picks.
MAX_COLUMNS = 16384
_TOP = 1  # key.laser_name of the TOP laser
_COMPONENTS = (
    "vehicle_pose",
    "camera_calibration",
    "camera_image",
    "lidar_calibration",
    "lidar",
    "lidar_box",
)


class WaymoSegmentSummary(NamedTuple):
    """What :func:`write_waymo_segment` wrote.

    Attributes:
        dataset_dir: the split folder holding one sub-folder per component.
        segment: the ``segment_context_name`` (each parquet file's stem).
        frames: frames written.
        views: camera images written.
        range_image_shape: ``(H, W)`` of the TOP laser's range images (``(0, 0)`` without LiDAR).
        points: the scene's LiDAR points over all frames.
        returns: range-image cells with a return over all frames (``points`` less those that
            shared a cell with a nearer point).
        boxes: ``lidar_box`` rows.
    """

    dataset_dir: Path
    segment: str
    frames: int
    views: int
    range_image_shape: tuple[int, int]
    points: int
    returns: int
    boxes: int


def _fixed_list(matrices: Sequence[np.ndarray], pa) -> object:
    """``fixed_size_list<double>[16]`` of 4x4 matrices, row-major (Waymo's transforms)."""
    flat = np.asarray(matrices, dtype=np.float64).reshape(-1)
    return pa.FixedSizeListArray.from_arrays(pa.array(flat, pa.float64()), 16)


def _waymo_camera_id(name: str) -> int:
    ids = {v: k for k, v in WAYMO_CAMERAS.items()}
    if name.upper() not in ids:
        raise ValueError(
            f"scene: camera {name!r} has no Waymo name; expected one of {[n.lower() for n in ids]} (any case)"
        )
    return ids[name.upper()]


def _jpeg_bytes(path: Path, quality: int) -> bytes:
    """The file's bytes if it is a JPEG, else the image encoded as JPEG."""
    if path.suffix.lower() in (".jpg", ".jpeg"):
        return path.read_bytes()
    from PIL import Image

    buf = io.BytesIO()
    with Image.open(path) as img:
        img.convert("RGB").save(buf, format="JPEG", quality=quality)
    return buf.getvalue()


def _scan_columns(local: np.ndarray, inclinations: np.ndarray) -> int:
    """Twice the azimuth samples of a spinning scan: ``2 round(2π / step)``, clipped to [8, MAX_COLUMNS].

    ``local`` are the sweep's points in the LiDAR frame, ``inclinations`` its beams (any order).
    ``step`` is the median over beams of the smallest azimuth difference between two returns of
    the beam; with half-step columns, no two returns of a beam share a cell.
    """
    inc = np.arcsin(np.clip(local[:, 2] / np.maximum(np.linalg.norm(local, axis=-1), 1e-12), -1.0, 1.0))
    rows = np.abs(inc[:, None] - np.asarray(inclinations)[None]).argmin(1)
    azimuth = np.arctan2(local[:, 1], local[:, 0])
    steps = []
    for r in np.unique(rows):
        d = np.diff(np.sort(azimuth[rows == r]))
        d = d[d > 1e-9]
        if len(d):
            steps.append(d.min())
    if not steps:
        return 2650  # Waymo's TOP laser
    return int(np.clip(2 * round(2 * math.pi / float(np.median(steps))), 8, MAX_COLUMNS))


def _beam_inclinations(root: Path, given: Sequence[float] | None) -> np.ndarray:
    """The beam inclinations, lowest first: ``given``, or ``scene.json``'s ``lidar`` profile."""
    if given is not None:
        incl = np.asarray(given, dtype=np.float64)
        if incl.ndim != 1 or len(incl) == 0 or not (np.diff(incl) > 0).all() or not np.isfinite(incl).all():
            raise ValueError(
                f"beam_inclinations: expected finite, strictly increasing radians (lowest first), "
                f"got {given!r}"
            )
        return incl
    prof = json.loads((root / "scene.json").read_text()).get("lidar")
    try:
        lo, hi = (float(v) for v in prof["vfov"])
        beams = int(prof["beams"])
    except (TypeError, KeyError, ValueError):
        raise ValueError(
            f"beam_inclinations: {root / 'scene.json'} has no 'lidar' profile with 'beams' and 'vfov' "
            f"(got {prof!r}); pass the beam inclinations"
        ) from None
    if beams < 1 or not lo < hi:
        raise ValueError(f"scene.json lidar profile: expected beams >= 1 and vfov min < max, got {prof!r}")
    return np.radians(np.linspace(lo, hi, beams))


def _ranges_to_image(ranges: np.ndarray) -> np.ndarray:
    """``(H, W, 4)`` float32: range, intensity, elongation, no-label zone (0; -1 without a return)."""
    img = np.full((*ranges.shape, 4), -1.0, np.float32)
    ret = ranges > 0
    img[..., 0] = ranges
    img[ret, 1:] = 0.0
    return img


def write_waymo_segment(
    scene: str | Path,
    out_dir: str | Path,
    segment: str | None = None,
    *,
    beam_inclinations: Sequence[float] | None = None,
    columns: int | None = None,
    box_origin: str = "bottom",
    start_us: int = 1_500_000_000_000_000,
    jpeg_quality: int = 95,
    overwrite: bool = False,
    progress: bool = False,
) -> WaymoSegmentSummary:
    """Write a benchmark-format scene as a Waymo v2 segment; see the module docstring.

    Args:
        scene: the scene folder (``scene.json``), e.g. from :func:`~vadgs.data.make_segment`.
        out_dir: the split folder to write the components into (created).
        segment: the ``segment_context_name`` (default: the scene's name); a safe file name.
        beam_inclinations: the LiDAR's beam inclinations in radians, lowest first (default:
            ``scene.json``'s ``lidar`` profile, ``beams`` evenly over ``vfov``).
        columns: range-image width (default: twice the azimuth samples of frame 0's scan, so
            that every point gets a cell of its own, at most :data:`MAX_COLUMNS`; Waymo's TOP
            laser has 2650).
        box_origin: where a track's ``object_to_world`` origin sits in its box: ``"bottom"``
            (the bottom centre, as in the benchmark format) or ``"center"``.
        start_us: ``key.frame_timestamp_micros`` of timestamp 0.
        jpeg_quality: quality of images that are not already JPEG files.
        overwrite: replace the segment's existing component files (refused otherwise).
        progress: show a progress bar over frames.

    Returns:
        :class:`WaymoSegmentSummary`.

    Raises:
        ImportError: if ``pyarrow`` is not installed.
        FileNotFoundError: if the scene or one of its files is missing.
        ValueError: on a bad argument (the message names it, the expected and the actual), a
            camera without a Waymo name, a frame without ``ego_to_world``, a view without an
            image file, or existing component files without ``overwrite``.

    Example:
        >>> import tempfile
        >>> from vadgs.data import load_waymo, make_segment
        >>> d = tempfile.mkdtemp()
        >>> seg = make_segment(d + "/seg", frames=2, width=32, height=24, lidar_points=500, progress=False)
        >>> info = write_waymo_segment(seg, d + "/waymo", "seg0")
        >>> info.frames, info.views, info.points == info.returns
        (2, 4, True)
        >>> load_waymo(d + "/waymo", "seg0").camera_names
        ['FRONT', 'FRONT_LEFT']
    """
    pq = pyarrow_parquet()
    import pyarrow as pa

    root = Path(scene)
    if root.name == "scene.json":
        root = root.parent
    if box_origin not in ("bottom", "center"):
        raise ValueError(f"box_origin: expected 'bottom' or 'center', got {box_origin!r}")
    if columns is not None and not (isinstance(columns, int) and columns > 0):
        raise ValueError(f"columns: expected a positive integer or None, got {columns!r}")
    if not (isinstance(jpeg_quality, int) and 1 <= jpeg_quality <= 100):
        raise ValueError(f"jpeg_quality: expected an integer in [1, 100], got {jpeg_quality!r}")
    sc: Scene = load_scene(root)
    segment = sc.name if segment is None else segment
    if not segment or safe_filename(segment) != segment:
        raise ValueError(f"segment: expected a safe file name (letters, digits, . _ + -), got {segment!r}")
    out = Path(out_dir)
    paths = {c: out / c / f"{segment}.parquet" for c in _COMPONENTS}
    existing = [str(p) for p in paths.values() if p.exists()]
    if existing and not overwrite:
        raise ValueError(
            f"out_dir: segment {segment!r} exists ({existing[0]}); pass overwrite=True to replace it"
        )
    cam_ids = {name: _waymo_camera_id(name) for name in sc.camera_names}
    order = sorted(sc.camera_names, key=lambda c: cam_ids[c])
    ego = []
    for f in sc.frames:
        if f.ego_to_world is None:
            raise ValueError(f"scene: frame {f.index} has no ego_to_world (Waymo's vehicle_pose needs one)")
        ego.append(f.ego_to_world.double().numpy())
    ts_us = [start_us + round(f.timestamp * 1e6) for f in sc.frames]
    if len(set(ts_us)) != len(ts_us):
        raise ValueError("scene: frame timestamps are not distinct to the microsecond")
    c2e = {}
    for c in order:
        info = sc.cameras_info[c]
        if float(info.K[0, 1]) != 0.0:
            raise ValueError(
                f"scene: camera {c!r} has a skewed K (K[0, 1] = {float(info.K[0, 1])}); Waymo has none"
            )
        if info.cam_to_ego is not None:
            c2e[c] = info.cam_to_ego.double().numpy()
        else:  # a rig without cam_to_ego: frame 0's view relative to the ego
            vid = next(v for v in sc.frames[0].view_ids if sc.views[v].camera == c)
            c2e[c] = np.linalg.inv(ego[0]) @ sc.views[vid].cam_to_world.double().numpy()
    lidar = sc.lidar_loader is not None
    incl = _beam_inclinations(root, beam_inclinations) if lidar else np.zeros(0)
    for path in paths.values():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.unlink(missing_ok=True)  # a stale component of an earlier run (e.g. lidar) must not stay

    def finish(component: str, write) -> None:
        """Write a component to a temporary file, then move it into place (whole or not at all)."""
        tmp = paths[component].with_suffix(".parquet.tmp")
        write(tmp)
        tmp.replace(paths[component])

    def small(component: str, table: dict) -> None:
        finish(
            component,
            lambda tmp: pq.write_table(pa.table(table), tmp, compression="zstd", write_page_checksum=True),
        )

    def keys(count: int, ts: Sequence[int] | None = None) -> dict:
        cols = {"key.segment_context_name": pa.array([segment] * count, pa.string())}
        if ts is not None:
            cols["key.frame_timestamp_micros"] = pa.array(list(ts), pa.int64())
        return cols

    # -- vehicle poses and cameras --------------------------------------------------------------------
    small(
        "vehicle_pose", {**keys(len(ego), ts_us), f"{_VP}.world_from_vehicle.transform": _fixed_list(ego, pa)}
    )
    cams = [sc.cameras_info[c] for c in order]
    small(
        "camera_calibration",
        {
            **keys(len(order)),
            "key.camera_name": pa.array([cam_ids[c] for c in order], pa.int8()),
            f"{_CC}.intrinsic.f_u": [float(k.K[0, 0]) for k in cams],
            f"{_CC}.intrinsic.f_v": [float(k.K[1, 1]) for k in cams],
            f"{_CC}.intrinsic.c_u": [float(k.K[0, 2]) + WAYMO_PIXEL_OFFSET for k in cams],
            f"{_CC}.intrinsic.c_v": [float(k.K[1, 2]) + WAYMO_PIXEL_OFFSET for k in cams],
            **{f"{_CC}.intrinsic.{d}": [0.0] * len(order) for d in ("k1", "k2", "p1", "p2", "k3")},
            f"{_CC}.extrinsic.transform": _fixed_list(
                [c2e[c] @ np.linalg.inv(WAYMO_CAMERA_TO_OPENCV) for c in order], pa
            ),
            f"{_CC}.width": pa.array([k.image_size[1] for k in cams], pa.int32()),
            f"{_CC}.height": pa.array([k.image_size[0] for k in cams], pa.int32()),
            f"{_CC}.rolling_shutter_direction": pa.array([0] * len(order), pa.int8()),
        },
    )

    # -- LiDAR calibration ---------------------------------------------------------------------------
    width = 0  # the range images' columns (with lidar)
    if lidar:
        rows_incl = waymo_beam_inclinations(len(incl), float(incl[0]), float(incl[-1]), incl)
        first = sc.lidar(sc.frames[0].index)
        extrinsic = np.eye(4)
        extrinsic[:3, 3] = (np.linalg.inv(ego[0]) @ np.append(first.origin.double().numpy(), 1.0))[:3]
        if columns is None:
            local = (first.points.double().numpy() - ego[0][:3, 3]) @ ego[0][:3, :3] - extrinsic[:3, 3]
            columns = _scan_columns(local, incl)
        width = columns
        small(
            "lidar_calibration",
            {
                **keys(1),
                "key.laser_name": pa.array([_TOP], pa.int8()),
                f"{_LC}.extrinsic.transform": _fixed_list([extrinsic], pa),
                f"{_LC}.beam_inclination.min": [float(incl[0])],
                f"{_LC}.beam_inclination.max": [float(incl[-1])],
                f"{_LC}.beam_inclination.values": pa.array([incl.tolist()], pa.list_(pa.float64())),
            },
        )

    # -- frame by frame: images and range images, one row group each ---------------------------------
    image_schema = pa.schema(
        [
            ("key.segment_context_name", pa.string()),
            ("key.frame_timestamp_micros", pa.int64()),
            ("key.camera_name", pa.int8()),
            (f"{_CI}.image", pa.binary()),
            (f"{_CI}.pose.transform", pa.list_(pa.float64(), 16)),
            (f"{_CI}.pose_timestamp", pa.float64()),
        ]
    )
    lidar_schema = pa.schema(
        [
            ("key.segment_context_name", pa.string()),
            ("key.frame_timestamp_micros", pa.int64()),
            ("key.laser_name", pa.int8()),
            (f"{_L}.range_image_return1.values", pa.list_(pa.float32())),
            (f"{_L}.range_image_return1.shape", pa.list_(pa.int32(), 3)),
        ]
    )
    tmp_images = paths["camera_image"].with_suffix(".parquet.tmp")
    tmp_lidar = paths["lidar"].with_suffix(".parquet.tmp")
    # JPEG bytes: no compression to gain; CRC checksums on every page, so that the reader refuses a
    # corrupt page of these files (load_waymo verifies them)
    image_writer = pq.ParquetWriter(tmp_images, image_schema, write_page_checksum=True)
    lidar_writer = (
        pq.ParquetWriter(tmp_lidar, lidar_schema, compression="zstd", write_page_checksum=True)
        if lidar
        else None
    )
    n_views = n_points = n_returns = 0
    frames = range(len(sc.frames))
    if progress:
        from tqdm.auto import tqdm

        frames = tqdm(frames, desc="waymo segment", unit="frame")
    try:
        for p in frames:
            f = sc.frames[p]
            views = sorted((sc.views[v] for v in f.view_ids), key=lambda v: cam_ids[v.camera])
            images, poses = [], []
            for v in views:
                if v.image is None:
                    raise ValueError(
                        f"scene: view {v.index} ({v.camera} at frame {f.index}) has no image file"
                    )
                images.append(_jpeg_bytes(Path(v.image), jpeg_quality))
                poses.append(v.cam_to_world.double().numpy() @ np.linalg.inv(c2e[v.camera]))
            base = start_us * 1e-6
            image_writer.write_table(
                pa.table(
                    {
                        **keys(len(views), [ts_us[p]] * len(views)),
                        "key.camera_name": pa.array([cam_ids[v.camera] for v in views], pa.int8()),
                        f"{_CI}.image": pa.array(images, pa.binary()),
                        f"{_CI}.pose.transform": _fixed_list(poses, pa),
                        f"{_CI}.pose_timestamp": pa.array([base + v.timestamp for v in views], pa.float64()),
                    },
                    schema=image_schema,
                )
            )
            n_views += len(views)
            del images
            if lidar_writer is not None:
                pts = sc.lidar(f.index).points.double().numpy()
                vehicle = (pts - ego[p][:3, 3]) @ ego[p][:3, :3]
                ranges = waymo_points_to_range_image(vehicle, extrinsic, rows_incl, width)
                if ranges.max(initial=0.0) > WAYMO_MAX_RANGE_M["TOP"]:
                    raise ValueError(
                        f"scene: frame {f.index} has LiDAR points {ranges.max():.1f} m from the sensor; "
                        f"Waymo's TOP laser reaches {WAYMO_MAX_RANGE_M['TOP']:g} m (load_waymo refuses more)"
                    )
                img = _ranges_to_image(ranges)
                n_points += len(pts)
                n_returns += int((ranges > 0).sum())
                values = pa.array(img.ravel(), pa.float32())
                lidar_writer.write_table(
                    pa.table(
                        {
                            **keys(1, [ts_us[p]]),
                            "key.laser_name": pa.array([_TOP], pa.int8()),
                            f"{_L}.range_image_return1.values": pa.ListArray.from_arrays(
                                pa.array([0, len(values)], pa.int32()), values
                            ),
                            f"{_L}.range_image_return1.shape": pa.FixedSizeListArray.from_arrays(
                                pa.array(img.shape, pa.int32()), 3
                            ),
                        },
                        schema=lidar_schema,
                    )
                )
    finally:
        image_writer.close()
        if lidar_writer is not None:
            lidar_writer.close()
    tmp_images.replace(paths["camera_image"])
    if lidar_writer is not None:
        tmp_lidar.replace(paths["lidar"])

    # -- tracks -> boxes ------------------------------------------------------------------------------
    box: dict[str, list[Any]] = {k: [] for k in ("ts", "obj", "center", "size", "heading", "type")}
    names: set[str] = set()
    for tid, track in sc.tracks.items():
        inst = sc.instances.get(tid)
        name = inst.name if inst is not None and inst.name else f"track_{tid}"
        if name in names:
            name = f"{name}_{tid}"
        names.add(name)
        lwh = track.size_lwh.double().numpy()
        lift = np.eye(4)
        if box_origin == "bottom":
            lift[2, 3] = lwh[2] / 2
        cls = track.class_name.lower()
        for p in range(len(sc.frames)):
            if not bool(track.valid[p]):
                continue
            local = np.linalg.inv(ego[p]) @ track.object_to_world[p].double().numpy() @ lift
            box["ts"].append(ts_us[p])
            box["obj"].append(name)
            box["center"].append(local[:3, 3])
            box["size"].append(lwh)
            box["heading"].append(math.atan2(local[1, 0], local[0, 0]))
            box["type"].append(BOX_TYPE_OF_CLASS.get(cls, 0))
    centre = np.asarray(box["center"], dtype=np.float64).reshape(-1, 3)
    size = np.asarray(box["size"], dtype=np.float64).reshape(-1, 3)
    small(
        "lidar_box",
        {
            **keys(len(box["ts"]), box["ts"]),
            "key.laser_object_id": pa.array(box["obj"], pa.string()),
            **{f"{_LB}.box.center.{a}": centre[:, i] for i, a in enumerate("xyz")},
            **{f"{_LB}.box.size.{a}": size[:, i] for i, a in enumerate("xyz")},
            f"{_LB}.box.heading": pa.array(box["heading"], pa.float64()),
            f"{_LB}.type": pa.array(box["type"], pa.int8()),
        },
    )
    shape = (len(incl), width) if lidar else (0, 0)
    return WaymoSegmentSummary(
        out, segment, len(sc.frames), n_views, shape, n_points, n_returns, len(box["ts"])
    )
