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

The tables are read and the sweeps matched with their images in :mod:`vadgs.data.argoverse2_tables`;
this module assembles them into the scene.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from vadgs.data._tracks import (
    BoxObservation,
    as_tensor,
    build_instances,
    check_min_motion,
    held_out_frames,
    labelled_lidar,
    recentred,
)
from vadgs.data.argoverse2_tables import (
    ARGOVERSE2_INTRINSICS,
    ARGOVERSE2_MAX_IMAGE_OFFSET_MS,
    ARGOVERSE2_POSES,
    argoverse2_sync,
    interpolate_city_SE3_ego,
    read_argoverse2_boxes,
    read_argoverse2_intrinsics,
    read_argoverse2_poses,
    read_argoverse2_sensor_to_ego,
    read_feather_columns,
)
from vadgs.data.assemble import assemble_scene, check_scale, pinhole_camera
from vadgs.data.scene import CameraInfo, FrameInfo, LidarFrame, Scene, ViewInfo, read_rgb
from vadgs.data.undistort import ImageUndistorter

__all__ = [
    "ARGOVERSE2_LIDARS",
    "ARGOVERSE2_VEHICLES",
    "load_argoverse2",
]

#: the two VLP-32 LiDARs merged in each sweep file: ``laser_number`` 0-31 and 32-63.
ARGOVERSE2_LIDARS = ("up_lidar", "down_lidar")
_LASERS = {"up_lidar": (0, 32), "down_lidar": (32, 64)}
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
    intr = read_argoverse2_intrinsics(log_dir)
    sensor_to_ego = read_argoverse2_sensor_to_ego(log_dir, [*sync.cameras, *(lidars or ())])
    row_of = {str(n): i for i, n in enumerate(intr["sensor_name"])}
    cams: dict[str, CameraInfo] = {}
    undistorters: dict[str, ImageUndistorter] = {}
    for n in sync.cameras:
        r = row_of[n]
        what = f"Argoverse 2 {ARGOVERSE2_INTRINSICS}[{n}]"
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
                as_tensor(ego_to_world[fi], f"{ARGOVERSE2_POSES} at sweep {sweep}"),
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
                f"{ARGOVERSE2_INTRINSICS}'s {und.image_size[1]}x{und.image_size[0]}"
            )
        return und(img[None])[0].clamp_(0.0, 1.0) if und.distorted else img

    # -- boxes → instances and tracks ----------------------------------------------------------------
    boxes: dict[int, dict[int, BoxObservation]] = {}
    box_names: dict[int, str] = {}
    rigid: set[str] = set()
    ann = read_argoverse2_boxes(log_dir)
    if ann is not None:
        frame_of = {ts: fi for fi, ts in enumerate(sync.sweeps_ns)}
        id_of: dict[str, int] = {}
        rows = sorted(
            range(len(ann.timestamps_ns)), key=lambda i: (int(ann.timestamps_ns[i]), ann.track_uuid[i])
        )
        for i in rows:
            pos = frame_of.get(int(ann.timestamps_ns[i]))
            if pos is None:
                continue
            uuid = str(ann.track_uuid[i])
            if uuid not in id_of:
                id_of[uuid] = len(id_of) + 1
                box_names[id_of[uuid]] = uuid
            category = str(ann.category[i])
            if category in ARGOVERSE2_VEHICLES:
                rigid.add(category.lower())
            boxes.setdefault(id_of[uuid], {})[pos] = BoxObservation(
                ego_to_world[pos] @ ann.box_to_ego[i], ann.size[i].copy(), category.lower()
            )
    instances, tracks = build_instances(boxes, box_names, num_frames, lambda cls: cls in rigid, min_motion_m)

    # -- LiDAR ---------------------------------------------------------------------------------------
    read_lidar = None
    if lidars is not None:
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
