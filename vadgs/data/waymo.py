"""Waymo Open Dataset v2 (parquet components) as a :class:`~vadgs.data.scene.Scene`.

The v2 release stores each *component* of a segment in its own parquet file,
``<dataset_dir>/<component>/<segment_context_name>.parquet``, with flat columns named
``key.segment_context_name``, ``key.frame_timestamp_micros``, ``key.camera_name``,
``key.laser_name``, ``key.laser_object_id`` and ``[<Component>].<field>.<subfield>``
(``key.camera_name`` is an int8 in the v2 schema; some release files hold the name, e.g.
``"FRONT"``: both are accepted, see :func:`~vadgs.data.waymo_parquet.waymo_camera_name`). vadgs reads
them with ``pyarrow`` (an optional dependency: ``pip install 'vadgs[waymo]'``); the
``waymo-open-dataset`` package (and TensorFlow) is not needed. Components read:

- ``vehicle_pose``: ``[VehiclePoseComponent].world_from_vehicle.transform`` (a row per frame;
  double in the v2 schema, float32 in some release files: both are read as float64);
- ``camera_calibration``: ``[CameraCalibrationComponent].intrinsic.{f_u, f_v, c_u, c_v, k1, k2,
  p1, p2, k3}``, ``.extrinsic.transform``, ``.width``, ``.height``;
- ``camera_image``: ``[CameraImageComponent].image`` (JPEG), ``.pose.transform``,
  ``.pose_timestamp``;
- ``lidar_calibration``: ``[LiDARCalibrationComponent].extrinsic.transform``,
  ``.beam_inclination.{min, max, values}``;
- ``lidar``: ``[LiDARComponent].range_image_return1.{values, shape}``;
- ``lidar_pose`` (optional): ``[LiDARPoseComponent].range_image_return1.{values, shape}``;
- ``lidar_box`` (optional): ``[LiDARBoxComponent].box.center.{x, y, z}``,
  ``.box.size.{x, y, z}``, ``.box.heading``, ``.type``.

How Waymo maps to vadgs:

- **Frames** are the rows of ``vehicle_pose`` in time order; frame ``i`` is the ``i``-th selected
  one; ``ego_to_world`` = ``world_from_vehicle`` (4×4 row-major). Views are frame-major.
- **Cameras.** Waymo camera frames have x forward, y left, z up; the calibration ``extrinsic``
  maps camera to vehicle. vadgs uses OpenCV axes:
  ``cam_to_ego = extrinsic @ WAYMO_CAMERA_TO_OPENCV`` (x_cv = -y, y_cv = -z, z_cv = x). Each
  image's own ``pose`` (the vehicle pose at ``pose_timestamp``) gives
  ``cam_to_world = pose @ cam_to_ego``. Waymo's image coordinates put 0 at the *left edge* of the
  first pixel (stated for the LiDAR camera projections), vadgs at its centre, so
  ``cx = c_u - 0.5``, ``cy = c_v - 0.5`` (:data:`WAYMO_PIXEL_OFFSET`). The lens distortion
  ``k1, k2, p1, p2, k3`` (OpenCV's model and order) is removed: each image is undistorted when
  loaded (:mod:`vadgs.data.undistort`: same size and principal point, focal lengths scaled by
  the smallest factor that leaves no pixel without a source: 0.9999-1.0025 for the real cameras)
  and ``K`` is that pinhole ``K``. The rolling shutter is ignored.
- **LiDAR.** The first return of each selected laser's range image becomes points with
  :func:`waymo_range_image_to_points` (:mod:`vadgs.data.waymo_lidar`; the
  official conversion: rows from the beam inclinations, top row = highest, columns from azimuth
  π to -π corrected by the extrinsic's yaw, then the extrinsic). With a ``lidar_pose`` component
  (the TOP laser's per-pixel vehicle pose) each point is moved to the world with its own pose
  (ego-motion compensated); otherwise with the frame's.
- **Boxes → tracks.** ``lidar_box`` boxes are in the vehicle frame of their frame (7-DOF:
  centre, length/width/height along x/y/z, heading about z). ``laser_object_id`` persists across
  frames; each gets an integer id 1, 2, ... in order of first appearance. Every object is in
  ``Scene.instances`` (class ``vehicle``, ``pedestrian``, ``sign``, ``cyclist`` or ``unknown``);
  *moving vehicles* (centre moving more than ``min_motion_m`` in the world) become tracks.
- **World.** With ``recenter=True`` the world is Waymo's global frame translated so that the
  vehicle at frame 0 sits at the origin (no rotation).

The component files are read in :mod:`vadgs.data.waymo_parquet`; this module assembles them
into the scene.
"""

from __future__ import annotations

import functools
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
    select_cameras,
    select_positions,
)
from vadgs.data.assemble import assemble_scene, check_scale, pinhole_camera
from vadgs.data.images import decode_image
from vadgs.data.scene import CameraInfo, FrameInfo, LidarFrame, Scene, ViewInfo
from vadgs.data.undistort import ImageUndistorter
from vadgs.data.waymo_lidar import (
    WAYMO_MAX_RANGE_M,
    waymo_beam_inclinations,
    waymo_check_pixel_pose,
    waymo_check_range_image,
    waymo_range_image_to_points,
)
from vadgs.data.waymo_parquet import (
    WAYMO_CAMERA_CALIBRATION,
    WAYMO_CAMERA_IMAGE,
    WAYMO_CAMERA_KEY,
    WAYMO_CAMERAS,
    WAYMO_LASER_KEY,
    WAYMO_LASERS,
    WAYMO_LIDAR,
    WAYMO_LIDAR_BOX,
    WAYMO_LIDAR_CALIBRATION,
    WAYMO_LIDAR_POSE,
    WAYMO_OBJECT_KEY,
    WAYMO_SEGMENT_KEY,
    WAYMO_TIMESTAMP_KEY,
    WaymoComponent,
    component_columns,
    pyarrow_parquet,
    read_waymo_poses,
    waymo_camera_name,
    waymo_matrix,
)

__all__ = [
    "WAYMO_BOX_TYPES",
    "WAYMO_CAMERA_TO_OPENCV",
    "WAYMO_PIXEL_OFFSET",
    "load_waymo",
]

#: ``[LiDARBoxComponent].type`` → vadgs class name (``box.BoxType``).
WAYMO_BOX_TYPES = {0: "unknown", 1: "vehicle", 2: "pedestrian", 3: "sign", 4: "cyclist"}
#: subtracted from ``c_u, c_v``: Waymo's pixel 0 is the left edge of the first pixel.
WAYMO_PIXEL_OFFSET = 0.5
#: OpenCV camera axes (x right, y down, z forward) expressed in Waymo's camera frame.
WAYMO_CAMERA_TO_OPENCV = np.array(
    [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)

_SEG, _TS, _CAM, _LASER, _OBJ = (
    WAYMO_SEGMENT_KEY,
    WAYMO_TIMESTAMP_KEY,
    WAYMO_CAMERA_KEY,
    WAYMO_LASER_KEY,
    WAYMO_OBJECT_KEY,
)
_CC, _CI, _LC, _L, _LP, _LB = (  # short names for the columns below
    WAYMO_CAMERA_CALIBRATION,
    WAYMO_CAMERA_IMAGE,
    WAYMO_LIDAR_CALIBRATION,
    WAYMO_LIDAR,
    WAYMO_LIDAR_POSE,
    WAYMO_LIDAR_BOX,
)


def load_waymo(
    dataset_dir: str | Path,
    segment: str,
    cameras: Sequence[str] | None = None,
    scale: float = 1.0,
    frames: Sequence[int] | None = None,
    test_frames: Sequence[int] | None = None,
    min_motion_m: float | None = 0.5,
    lasers: Sequence[str] | None = ("TOP",),
    recenter: bool = True,
) -> Scene:
    """Load one Waymo Open Dataset v2 segment (parquet components) as a :class:`Scene`.

    See the module docstring for the components read and how their frames map to vadgs.

    What the scene holds:

    - ``cameras_info``: ``K`` from the intrinsics (``c - 0.5``, rescaled by ``scale``), the
      calibrated image size, ``cam_to_ego`` in OpenCV axes.
    - ``views``: ``cam_to_world`` from each image's own vehicle pose, ``timestamp`` =
      ``pose_timestamp`` in seconds since frame 0. ``ViewInfo.image`` is None: the JPEG bytes
      stay in the parquet file and :meth:`Scene.load_images` decodes them on demand
      (``Scene.image_loader``), resized by ``scale``.
    - ``frames``: ``ego_to_world`` from ``vehicle_pose``. ``Scene.lidar(f)`` reads the frame's
      range images of ``lasers`` on demand and returns world points, each point's ``instance``
      the id of the box it falls in (0 outside), ``origin`` the first laser's position.
    - ``instances`` / ``tracks``: as :func:`~vadgs.data.load_nuscenes`, from ``lidar_box``
      (``name`` = ``laser_object_id``); tracks are the ``vehicle`` objects moving more than
      ``min_motion_m`` (every vehicle with None). No ``lidar_box`` file: no instances.
    - ``test_frames``: 2, 6, 10, ... unless given; ``train_frames`` the rest.

    Args:
        dataset_dir: the split folder holding one sub-folder per component (e.g.
            ``.../waymo_open_dataset_v_2_0_1/training``).
        segment: the ``segment_context_name`` (the parquet file's stem).
        cameras: camera names (default all five, in :data:`~vadgs.data.waymo_parquet.WAYMO_CAMERAS` order).
        scale: resolution factor for images and intrinsics.
        frames: frame positions to keep (default all ~199), renumbered 0, 1, ...
        test_frames: frame indices to hold out (default every fourth from 2; ``()`` for none).
        min_motion_m: motion threshold (metres) for a vehicle to be a track; None: every vehicle.
        lasers: laser names whose first return forms the LiDAR (default the TOP laser), or None
            (no LiDAR: a segment without the ``lidar`` component needs None).
        recenter: translate the world so that the vehicle at frame 0 sits at the origin.

    Returns:
        The :class:`Scene`.

    Raises:
        ImportError: if ``pyarrow`` is not installed.
        FileNotFoundError: if ``dataset_dir`` or a required component file is missing.
        ValueError: if the segment, a camera or a laser is unknown (the message lists what there
            is), a column is missing, a frame lacks an image, or an argument is invalid.

    Example:
        >>> segment = "10017090168044687777_6380_000_6400_000"
        >>> scene = load_waymo("/data/waymo/v2/training", segment, scale=0.25)  # doctest: +SKIP
        >>> scene.num_views, scene.image_size(0)  # doctest: +SKIP
        (995, (320, 480))
    """
    pq = pyarrow_parquet()
    dataset_dir = Path(dataset_dir)
    if not dataset_dir.is_dir():
        raise FileNotFoundError(f"dataset_dir: no such folder {dataset_dir}")
    check_scale(scale)
    check_min_motion(min_motion_m)
    seg_filter = [(_SEG, "=", segment)]

    # -- frames --------------------------------------------------------------------------------------
    vp = read_waymo_poses(dataset_dir, segment)
    all_ts = vp.timestamps_us.tolist()
    all_poses = list(vp.world_from_vehicle.numpy())
    positions = select_positions(frames, len(all_ts))
    frame_ts = [all_ts[f] for f in positions]
    frame_of = {ts: fi for fi, ts in enumerate(frame_ts)}
    num_frames = len(frame_ts)
    test = held_out_frames(test_frames, num_frames)
    offset = all_poses[positions[0]][:3, 3].copy() if recenter else np.zeros(3)

    ego_to_world = [recentred(all_poses[f], offset) for f in positions]
    t0 = frame_ts[0] * 1e-6

    # -- cameras -------------------------------------------------------------------------------------
    intr = ("f_u", "f_v", "c_u", "c_v", "k1", "k2", "p1", "p2", "k3")
    cam_id = {n: k for k, n in WAYMO_CAMERAS.items()}
    cc = WaymoComponent(pq, dataset_dir, "camera_calibration", segment).read(
        [
            _CAM,
            *component_columns(
                _CC, *(f"intrinsic.{k}" for k in intr), "extrinsic.transform", "width", "height"
            ),
        ],
        filters=seg_filter,
    )
    calib = {cam_id[waymo_camera_name(c)]: i for i, c in enumerate(cc[_CAM])}
    have_cams = [n for k, n in WAYMO_CAMERAS.items() if k in calib]
    cam_names = select_cameras(
        cameras, have_cams, f"Waymo segment {segment}: camera_calibration lists no known camera"
    )
    cams: dict[str, CameraInfo] = {}
    full_size: dict[str, tuple[int, int]] = {}
    undistort: dict[str, ImageUndistorter] = {}
    for n in cam_names:
        row = calib[cam_id[n]]
        what = f"camera_calibration[{n}]"
        fu, fv, cu, cv, *dist = (float(cc[f"{_CC}.intrinsic.{k}"][row] or 0.0) for k in intr)
        w, h = int(cc[f"{_CC}.width"][row]), int(cc[f"{_CC}.height"][row])
        full_size[n] = (w, h)
        raw_K = torch.tensor(
            [[fu, 0.0, cu - WAYMO_PIXEL_OFFSET], [0.0, fv, cv - WAYMO_PIXEL_OFFSET], [0.0, 0.0, 1.0]],
            dtype=torch.float64,
        )
        c2e = (
            waymo_matrix(cc[f"{_CC}.extrinsic.transform"][row], f"{what}.extrinsic") @ WAYMO_CAMERA_TO_OPENCV
        )
        dist_t = torch.tensor(dist, dtype=torch.float64)
        cams[n], undistort[n] = pinhole_camera(n, raw_K, dist_t, (h, w), scale, c2e, f"Waymo {what}")

    # -- views: image poses (the JPEG bytes stay in the file) ----------------------------------------
    ci = WaymoComponent(pq, dataset_dir, "camera_image", segment)
    cols = [_SEG, _TS, _CAM, f"{_CI}.pose.transform"]
    image_rows: dict[tuple[int, int], tuple[int, int]] = {}  # (frame, camera id) -> (row group, row)
    image_pose: dict[tuple[int, int], tuple[np.ndarray, float]] = {}
    names = ci.names()
    missing = [c for c in [*cols, f"{_CI}.image"] if c not in names]
    if missing:
        raise ValueError(f"Waymo component 'camera_image' ({ci.path.name}): missing column(s) {missing}")
    wanted_ids = {cam_id[n] for n in cam_names}
    has_pose_ts = f"{_CI}.pose_timestamp" in names
    for rg in range(ci.parquet_file().num_row_groups):
        d = ci.read_row_group(rg, cols + ([f"{_CI}.pose_timestamp"] if has_pose_ts else [])).to_pydict()
        for r, (seg, ts, cam_value) in enumerate(zip(d[_SEG], d[_TS], d[_CAM])):
            fi = frame_of.get(int(ts))
            if seg != segment or fi is None:
                continue
            cam = cam_id[waymo_camera_name(cam_value)]
            if cam not in wanted_ids:
                continue
            image_rows[(fi, cam)] = (rg, r)
            pose_ts = float(d[f"{_CI}.pose_timestamp"][r] or 0.0) if has_pose_ts else 0.0
            image_pose[(fi, cam)] = (
                waymo_matrix(
                    d[f"{_CI}.pose.transform"][r], f"camera_image pose ({WAYMO_CAMERAS[cam]} at {ts})"
                ),
                pose_ts if pose_ts > 0 else int(ts) * 1e-6,
            )
    views: list[ViewInfo] = []
    frame_infos: list[FrameInfo] = []
    for fi, ts in enumerate(frame_ts):
        ids = []
        for n in cam_names:
            if (fi, cam_id[n]) not in image_pose:
                raise ValueError(f"Waymo segment {segment}: frame {fi} (timestamp {ts} µs) has no {n} image")
            pose, pose_ts = image_pose[(fi, cam_id[n])]
            c2e = cams[n].cam_to_ego
            assert c2e is not None  # pinhole_camera above is given the calibration's extrinsic
            c2w = recentred(pose, offset) @ c2e.double().numpy()
            views.append(ViewInfo(len(views), fi, n, pose_ts - t0, as_tensor(c2w, f"{n} at frame {fi}")))
            ids.append(len(views) - 1)
        frame_infos.append(
            FrameInfo(fi, ts * 1e-6 - t0, as_tensor(ego_to_world[fi], f"vehicle_pose {ts}"), tuple(ids))
        )

    @functools.lru_cache(maxsize=2)
    def row_group_images(rg: int) -> list:
        return ci.read_row_group(rg, [f"{_CI}.image"]).column(0).to_pylist()

    def image_loader(view: ViewInfo) -> torch.Tensor:
        rg, r = image_rows[(view.frame, cam_id[view.camera])]
        data = row_group_images(rg)[r]
        where = f"{ci.where}, row group {rg}, row {r}: Waymo {view.camera} image at frame {view.frame}"
        if data is None:
            raise ValueError(f"{where}: no image (null)")
        arr = decode_image(data, where)
        w, h = full_size[view.camera]
        if arr.shape[:2] != (h, w):
            raise ValueError(
                f"Waymo {view.camera} image at frame {view.frame}: decoded size "
                f"{arr.shape[1]}x{arr.shape[0]} differs from the calibration's {w}x{h}"
            )
        img = torch.from_numpy(arr).permute(2, 0, 1)
        return undistort[view.camera](img[None])[0].clamp_(0.0, 1.0)  # img is fresh: clamped in place

    # -- boxes → instances and tracks ---------------------------------------------------------------
    boxes: dict[int, dict[int, BoxObservation]] = {}
    id_of: dict[str, int] = {}
    box_names: dict[int, str] = {}
    lb = WaymoComponent(pq, dataset_dir, "lidar_box", segment, required=False)
    if lb.exists:
        fields = component_columns(
            _LB, *(f"box.center.{a}" for a in "xyz"), *(f"box.size.{a}" for a in "xyz")
        )
        d = lb.read([_TS, _OBJ, *fields, *component_columns(_LB, "box.heading", "type")], filters=seg_filter)
        rows = sorted(range(len(d[_TS])), key=lambda i: (int(d[_TS][i]), str(d[_OBJ][i])))
        for i in rows:
            fi = frame_of.get(int(d[_TS][i]))
            if fi is None:
                continue
            obj = str(d[_OBJ][i])
            if obj not in id_of:
                id_of[obj] = len(id_of) + 1
                box_names[id_of[obj]] = obj
            vals = np.array([float(d[f][i]) for f in fields])
            heading = float(d[f"{_LB}.box.heading"][i])
            box = np.eye(4)
            c, s = np.cos(heading), np.sin(heading)
            box[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
            box[:3, 3] = vals[:3]
            cls = WAYMO_BOX_TYPES.get(int(d[f"{_LB}.type"][i]), "unknown")
            boxes.setdefault(id_of[obj], {})[fi] = BoxObservation(ego_to_world[fi] @ box, vals[3:], cls)
    instances, tracks = build_instances(
        boxes, box_names, num_frames, lambda cls: cls == "vehicle", min_motion_m
    )

    # -- LiDAR (range images read per frame on demand) -----------------------------------------------
    lidar_loader = None
    if lasers is not None:
        for comp in ("lidar_calibration", "lidar"):
            if not (dataset_dir / comp / f"{segment}.parquet").is_file():
                raise FileNotFoundError(
                    f"Waymo component {comp!r}: missing file {dataset_dir / comp / f'{segment}.parquet'}; "
                    "a segment without LiDAR loads with lasers=None (vadgs convert waymo --no-lidar)"
                )
        laser_id = {n: k for k, n in WAYMO_LASERS.items()}
        lc = WaymoComponent(pq, dataset_dir, "lidar_calibration", segment).read(
            [
                _LASER,
                *component_columns(
                    _LC, "extrinsic.transform", "beam_inclination.min", "beam_inclination.max"
                ),
            ],
            optional=component_columns(_LC, "beam_inclination.values"),
            filters=seg_filter,
        )
        lcal = {int(k): i for i, k in enumerate(lc[_LASER])}
        have_lasers = [n for k, n in WAYMO_LASERS.items() if k in lcal]
        for n in lasers:
            if n not in have_lasers:
                raise ValueError(f"lasers: unknown laser {n!r}, have {have_lasers}")
        lidar_comp = WaymoComponent(pq, dataset_dir, "lidar", segment)
        pose_comp = WaymoComponent(pq, dataset_dir, "lidar_pose", segment, required=False)
        extr = {
            n: waymo_matrix(lc[f"{_LC}.extrinsic.transform"][lcal[laser_id[n]]], f"lidar_calibration[{n}]")
            for n in lasers
        }

        def lidar_loader(frame: int) -> LidarFrame:
            if not 0 <= frame < num_frames:
                raise FileNotFoundError(f"Waymo segment {segment}: no LiDAR for frame {frame}")
            ts, ids = frame_ts[frame], [laser_id[n] for n in lasers]
            by_laser = lidar_comp.range_images(_L, ts, frame, ids)
            pix = pose_comp.range_images(_LP, ts, frame, ids, channels=6) if pose_comp.exists else {}
            out = []
            for n in lasers:
                if laser_id[n] not in by_laser:
                    raise ValueError(
                        f"{lidar_comp.where}: frame {frame} (timestamp {ts} µs) has no {n} range image"
                    )
                img, where = by_laser[laser_id[n]]
                row = lcal[laser_id[n]]
                try:
                    incl = waymo_beam_inclinations(
                        img.shape[0],
                        float(lc[f"{_LC}.beam_inclination.min"][row]),
                        float(lc[f"{_LC}.beam_inclination.max"][row]),
                        lc[f"{_LC}.beam_inclination.values"][row],
                    )
                except ValueError as e:
                    raise ValueError(f"{where}: {e} (lidar_calibration's beam inclinations)") from None
                waymo_check_range_image(img, WAYMO_MAX_RANGE_M[n], where)
                if laser_id[n] in pix:
                    pose_img, pose_where = pix[laser_id[n]]
                    waymo_check_pixel_pose(pose_img, img[..., 0], all_poses[positions[frame]], pose_where)
                    pts = waymo_range_image_to_points(img[..., 0], extr[n], incl, pose_img) - offset
                else:
                    e2w = ego_to_world[frame]
                    pts = waymo_range_image_to_points(img[..., 0], extr[n], incl) @ e2w[:3, :3].T + e2w[:3, 3]
                out.append(pts)
            origin = ego_to_world[frame] @ extr[lasers[0]][:, 3]
            return labelled_lidar(np.concatenate(out), origin[:3], boxes, frame)

    return assemble_scene(
        f"Waymo segment {segment}",
        name=segment,
        root=dataset_dir,
        cameras_info=cams,
        frames=frame_infos,
        views=views,
        instances=instances,
        tracks=tracks,
        test_frames=test,
        scale=scale,
        lidar_loader=lidar_loader,
        image_loader=image_loader,
        check_files=False,  # the images and LiDAR live in the parquet files read above
    )
