"""PandaSet as a :class:`~vadgs.data.scene.Scene`, read from a sequence folder as PandaSet ships it.

A sequence folder (e.g. ``pandaset/002``) holds, for frames ``00`` to ``79`` (10 Hz):

- ``camera/<name>/NN.jpg`` with ``intrinsics.json`` (``fx, fy, cx, cy``), ``poses.json`` (one
  pose per frame) and ``timestamps.json`` (seconds), for the six cameras;
- ``lidar/NN.pkl.gz``: a gzip'd pickled pandas DataFrame with columns ``x, y, z, i, t, d``, the
  points **in world coordinates**, ``d`` the sensor (0: the Pandar64 360° LiDAR, 1: the forward
  PandarGT), with ``lidar/poses.json`` (the Pandar64's pose per frame) and ``timestamps.json``;
- ``annotations/cuboids/NN.pkl.gz``: a DataFrame of 3D boxes (``uuid``, ``label``, ``yaw``,
  ``position.{x,y,z}``, ``dimensions.{x,y,z}``, ``cuboids.sensor_id``, ``cuboids.sibling_id``,
  ...), in world coordinates;
- ``meta/gps.json``, ``meta/timestamps.json`` (not read), ``annotations/semseg`` (not read).

Pickles are read by :func:`~vadgs.data.pickles.read_pickled_dataframe`, which refuses any class a
DataFrame does not need (a pickle can run code while it loads). pandas is an optional dependency:
``pip install 'vadgs[pandaset]'``; the ``pandaset`` devkit is not needed.

How PandaSet maps to vadgs (conventions of the devkit, ``pandaset/geometry.py``):

- **Poses.** Every ``poses.json`` entry is a sensor → world pose, ``position`` ``{x, y, z}`` and
  ``heading`` a quaternion ``{w, x, y, z}`` (the devkit's ``_heading_position_to_mat``).
- **Cameras.** The camera frame is OpenCV (the devkit projects with ``inv(camera_pose)`` then
  ``K``), so ``cam_to_world`` = the camera's pose at the frame; ``K`` = ``fx, fy, cx, cy``
  (images are undistorted; no pixel offset). ``cam_to_ego`` = the inverse LiDAR pose times the
  camera pose at the first selected frame.
- **Frames.** Frame ``i`` is the ``i``-th selected file number; ``ego_to_world`` = the LiDAR pose
  (PandaSet has no separate vehicle frame); timestamps are seconds since the first selected
  LiDAR timestamp.
- **LiDAR.** ``lidar="pandar64"`` keeps the points with ``d == 0``, ``"pandargt"`` those with
  ``d == 1``, ``"both"`` all; the returns off the car's own roof (:data:`PANDASET_EGO_BOX`) are
  dropped. ``LidarFrame.origin`` is the position in ``lidar/poses.json`` (for the PandarGT's points
  too: its pose is not in the sequence); in sequence 002 that position lies 1.8 m below the
  cameras and the roof returns 1.3-1.7 m above it, so it is not where the Pandar64 sits (vadgs
  uses the origin nowhere but in the exported ``lidar/*.npz``). A missing sweep gives an empty
  sweep and a warning.
- **Boxes.** A cuboid's centre is ``position``; ``yaw`` turns it about the world z axis, with 0
  facing ``(0, 1, 0)``; ``dimensions.x`` is the width, ``dimensions.y`` the length (the devkit's
  ``center_box_to_corners``). In vadgs' box frame (x along the length) that is
  ``object_to_world = [Rz(yaw + pi/2) | position]`` and ``size_lwh = (dim.y, dim.x, dim.z)``.
- **Duplicated boxes.** A moving object in the overlap of the two LiDARs has two cuboids of
  different uuids (``cuboids.sensor_id`` 0 and 1) linked by ``cuboids.sibling_id``: siblings are one
  instance, and at each frame it takes the box of the loaded LiDAR's sensor (the Pandar64's for
  ``"both"``), the other when that one is absent.
- **Instances and tracks.** Each object (uuid, siblings joined) gets an id 1, 2, ... in order of
  first appearance; ``class_name`` is the ``label`` lower-cased with ``_`` for separators
  (``Pickup Truck`` → ``pickup_truck``); an instance is dynamic when its box centre moves more than
  ``min_motion_m`` (:func:`~vadgs.data._tracks.build_instances`; the ``stationary`` column is not
  used), and the dynamic vehicles (:data:`PANDASET_VEHICLES`) become tracks.
- **World.** PandaSet's world lies near the first LiDAR pose already; with ``recenter=True`` the
  first selected frame's LiDAR position is subtracted all the same (no rotation).
"""

from __future__ import annotations

import math
import re
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image

from vadgs.data._json import read_json, require_key
from vadgs.data._tracks import (
    BoxObservation,
    as_tensor,
    build_instances,
    check_min_motion,
    held_out_frames,
    labelled_lidar,
    quat_wxyz_to_matrix,
    recentred,
    select_cameras,
    select_positions,
)
from vadgs.data.assemble import assemble_scene, check_scale
from vadgs.data.pickles import read_pickled_dataframe, require_pandas
from vadgs.data.scene import CameraInfo, FrameInfo, LidarFrame, Scene, ViewInfo
from vadgs.geometry.camera import scale_intrinsics

__all__ = [
    "PANDASET_CAMERAS",
    "PANDASET_EGO_BOX",
    "PANDASET_LIDARS",
    "PANDASET_VEHICLES",
    "load_pandaset",
    "pandaset_box_to_matrix",
    "pandaset_class_name",
    "pandaset_pose_to_matrix",
]

#: the six cameras, in the default order of the views (left to right, then round the back).
PANDASET_CAMERAS = (
    "front_left_camera",
    "front_camera",
    "front_right_camera",
    "right_camera",
    "back_camera",
    "left_camera",
)

#: ``lidar=`` name → the values of the ``d`` column kept (0: Pandar64 360°, 1: forward PandarGT).
PANDASET_LIDARS = {"pandar64": (0,), "pandargt": (1,), "both": (0, 1)}

#: the labels that are vehicles (the classes the devkit gives ``attributes.object_motion``):
#: their moving instances become tracks.
PANDASET_VEHICLES = frozenset(
    {
        "Car",
        "Pickup Truck",
        "Medium-sized Truck",
        "Semi-truck",
        "Towed Object",
        "Motorcycle",
        "Other Vehicle - Construction Vehicle",
        "Other Vehicle - Uncommon",
        "Other Vehicle - Pedicab",
        "Emergency Vehicle",
        "Bus",
        "Personal Mobility Device",
        "Motorized Scooter",
        "Bicycle",
        "Train",
        "Trolley",
        "Tram / Subway",
    }
)

#: the returns off the recording car's own roof (the sensor rack), in the frame of ``lidar/poses.json``
#: (x right, y forward, z up): ``((x_min, x_max), (y_min, y_max), (z_min, z_max))`` in metres. In
#: sequence 002 they lie within x -1..0.75, y -1..2, z 1.3..1.7 and nothing else comes within 0.2 m
#: of this box; ``drop_ego=True`` removes them (they would sit right in front of the cameras).
PANDASET_EGO_BOX = ((-1.2, 1.2), (-1.5, 2.5), (-1.0, 2.5))

_LIDAR_COLUMNS = ("x", "y", "z", "d")
_CUBOID_COLUMNS = (
    "uuid",
    "label",
    "yaw",
    "position.x",
    "position.y",
    "position.z",
    "dimensions.x",
    "dimensions.y",
    "dimensions.z",
)


def pandaset_class_name(label: str) -> str:
    """The vadgs class name of a PandaSet ``label``: lower case, runs of other characters as ``_``.

    Example:
        >>> [pandaset_class_name(x) for x in ("Car", "Pickup Truck", "Other Vehicle - Construction Vehicle")]
        ['car', 'pickup_truck', 'other_vehicle_construction_vehicle']
    """
    return re.sub(r"[^0-9a-z]+", "_", label.lower()).strip("_") or "unknown"


def pandaset_pose_to_matrix(pose: object, what: str) -> np.ndarray:
    """A ``poses.json`` entry (``position`` ``{x, y, z}``, ``heading`` ``{w, x, y, z}``) as a 4×4 float64.

    Raises:
        ValueError: ``"<what>: ..."`` when a key is missing or a value is not a finite number.

    Example:
        >>> pose = {"position": {"x": 1, "y": 2, "z": 3}, "heading": {"w": 0, "x": 0, "y": 0, "z": 1}}
        >>> pandaset_pose_to_matrix(pose, "pose").round(6).tolist()
        [[-1.0, 0.0, 0.0, 1.0], [0.0, -1.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0], [0.0, 0.0, 0.0, 1.0]]
    """
    position = require_key(pose, "position", what)
    heading = require_key(pose, "heading", what)
    try:
        q = [float(require_key(heading, k, f"{what}.heading")) for k in "wxyz"]
        t = np.array([float(require_key(position, k, f"{what}.position")) for k in "xyz"])
    except (TypeError, ValueError) as e:
        raise ValueError(f"{what}: expected numbers ({e})") from None
    if not np.isfinite(t).all():
        raise ValueError(f"{what}.position: expected finite numbers, got {t.tolist()}")
    out = np.eye(4)
    try:
        out[:3, :3] = quat_wxyz_to_matrix(q)
    except ValueError as e:
        raise ValueError(f"{what}.heading: {e}") from None
    out[:3, 3] = t
    return out


def pandaset_box_to_matrix(position: Sequence[float] | np.ndarray, yaw: float) -> np.ndarray:
    """A cuboid's ``object_to_world`` in vadgs' box frame (x along the length, y along the width, z up).

    PandaSet's yaw 0 faces ``(0, 1, 0)`` (the length along y, ``dimensions.y``), so the box's x
    axis is ``Rz(yaw) (0, 1, 0) = (-sin yaw, cos yaw, 0)``.

    Example:
        >>> pandaset_box_to_matrix([1.0, 2.0, 0.5], 0.0)[:3, 0].round(6).tolist()  # heading +y
        [0.0, 1.0, 0.0]
    """
    a = float(yaw) + math.pi / 2
    c, s = math.cos(a), math.sin(a)
    out = np.eye(4)
    out[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    out[:3, 3] = np.asarray(position, dtype=np.float64)
    return out


def _number_list(path: Path, what: str, n: int) -> list[float]:
    values = read_json(path, what, top=list)
    try:
        out = [float(v) for v in values]
    except (TypeError, ValueError):
        raise ValueError(f"{what}: {path}: expected a list of numbers") from None
    if len(out) < n:
        raise ValueError(f"{what}: {path}: expected at least {n} entries (one per frame), got {len(out)}")
    return out


def _poses(path: Path, what: str, n: int) -> list[object]:
    poses = read_json(path, what, top=list)
    if len(poses) < n:
        raise ValueError(f"{what}: {path}: expected at least {n} poses (one per frame), got {len(poses)}")
    return poses


class _Siblings:
    """Union-find over uuids: a cuboid and its ``cuboids.sibling_id`` are one object."""

    def __init__(self) -> None:
        self.parent: dict[str, str] = {}

    def find(self, u: str) -> str:
        root = u
        while self.parent.get(root, root) != root:
            root = self.parent[root]
        self.parent[u] = root
        return root

    def join(self, a: str, b: str) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self.parent[max(ra, rb)] = min(ra, rb)


def load_pandaset(
    sequence_dir: str | Path,
    cameras: Sequence[str] | None = None,
    scale: float = 1.0,
    frames: Sequence[int] | None = None,
    test_frames: Sequence[int] | None = None,
    min_motion_m: float | None = 0.5,
    lidar: str | None = "pandar64",
    recenter: bool = True,
    check_files: bool = True,
    drop_ego: bool = True,
) -> Scene:
    """Load one PandaSet sequence (cameras, LiDAR, cuboids) as a :class:`Scene`.

    See the module docstring for how each file maps to vadgs. Missing images (those views are
    left out), sweeps (an empty sweep) and cuboid files (no boxes at that frame) are listed in
    one :class:`UserWarning`, not fatal.

    Args:
        sequence_dir: the sequence folder (``camera/``, ``lidar/``, ``annotations/``).
        cameras: camera folder names (default :data:`PANDASET_CAMERAS`, those present).
        scale: resolution factor for images and intrinsics.
        frames: file numbers to keep (default all), e.g. ``range(0, 36)``; renumbered 0, 1, ...
        test_frames: frame indices to hold out (default every fourth from 2; ``()`` for none).
        min_motion_m: a vehicle whose box centre moves more than this (metres) is a track; None
            makes every vehicle a track.
        lidar: ``"pandar64"`` (360°), ``"pandargt"`` (forward), ``"both"``, or None for no LiDAR.
        recenter: translate the world so that the LiDAR at frame 0 sits at the origin.
        check_files: verify that every image exists.
        drop_ego: remove the LiDAR returns inside :data:`PANDASET_EGO_BOX` (the car's own roof).

    Returns:
        The :class:`Scene`.

    Raises:
        ImportError: without pandas (``pip install 'vadgs[pandaset]'``).
        FileNotFoundError: if the folder, a ``poses.json`` / ``timestamps.json`` /
            ``intrinsics.json`` is missing, or every image of a camera is.
        ValueError: naming the file, for bad JSON, a wrong or cut ``.pkl.gz``, a missing column;
            naming the argument for an unknown camera or LiDAR, a bad frame.

    Example:
        >>> scene = load_pandaset("pandaset/002", cameras=["front_camera"], scale=0.25)  # doctest: +SKIP
        >>> scene.num_views, scene.image_size(0)  # doctest: +SKIP
        (80, (270, 480))
    """
    root = Path(sequence_dir)
    what = f"PandaSet sequence {root}"
    require_pandas("load_pandaset")
    if not root.is_dir():
        raise FileNotFoundError(f"sequence_dir: no such folder {root}")
    check_scale(scale)
    check_min_motion(min_motion_m)
    if lidar is not None and lidar not in PANDASET_LIDARS:
        raise ValueError(f"lidar: expected one of {sorted(PANDASET_LIDARS)} or None, got {lidar!r}")

    # -- the LiDAR poses fix the frames -----------------------------------------------------------------
    lidar_poses = read_json(root / "lidar" / "poses.json", "PandaSet lidar/poses.json", top=list)
    num_files = len(lidar_poses)
    lidar_ts = _number_list(root / "lidar" / "timestamps.json", "PandaSet lidar/timestamps.json", num_files)
    sel = select_positions(frames, num_files, "frame")
    num_frames = len(sel)
    test = held_out_frames(test_frames, num_frames)
    lidar_to_world_raw = [
        pandaset_pose_to_matrix(lidar_poses[f], f"PandaSet lidar/poses.json[{f}]") for f in sel
    ]
    offset = lidar_to_world_raw[0][:3, 3].copy() if recenter else np.zeros(3)
    lidar_to_world = [recentred(m, offset) for m in lidar_to_world_raw]
    t0 = lidar_ts[sel[0]]

    # -- cameras ------------------------------------------------------------------------------------------
    cam_dir = root / "camera"
    present = (
        {p.name for p in cam_dir.iterdir() if p.is_dir() and (p / "intrinsics.json").is_file()}
        if cam_dir.is_dir()
        else set()
    )
    have = [c for c in PANDASET_CAMERAS if c in present] + sorted(present - set(PANDASET_CAMERAS))
    cam_names = select_cameras(
        cameras, have, f"{what}: no camera folder with an intrinsics.json in {cam_dir}"
    )
    missing: list[str] = []
    cams: dict[str, CameraInfo] = {}
    cam_to_world: dict[str, list[np.ndarray]] = {}
    cam_ts: dict[str, list[float]] = {}
    for c in cam_names:
        d = cam_dir / c
        intr = read_json(d / "intrinsics.json", f"PandaSet camera/{c}/intrinsics.json")
        try:
            fx, fy, cx, cy = (
                float(require_key(intr, k, f"PandaSet camera/{c}/intrinsics.json"))
                for k in ("fx", "fy", "cx", "cy")
            )
        except (TypeError, ValueError):
            raise ValueError(
                f"PandaSet camera/{c}/intrinsics.json: expected numbers fx, fy, cx, cy, got {intr!r}"
            ) from None
        poses = _poses(d / "poses.json", f"PandaSet camera/{c}/poses.json", num_files)
        cam_ts[c] = _number_list(d / "timestamps.json", f"PandaSet camera/{c}/timestamps.json", num_files)
        cam_to_world[c] = [
            recentred(pandaset_pose_to_matrix(poses[f], f"PandaSet camera/{c}/poses.json[{f}]"), offset)
            for f in sel
        ]
        first = next((d / f"{f:02d}.jpg" for f in sel if (d / f"{f:02d}.jpg").is_file()), None)
        if first is None:
            raise FileNotFoundError(
                f"{what}: camera {c} has none of its images, e.g. {d / f'{sel[0]:02d}.jpg'}"
            )
        try:
            with Image.open(first) as im:
                w, h = im.size
        except OSError as e:
            raise ValueError(f"PandaSet image {first}: not readable ({e})") from None
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        size = (round(h * scale), round(w * scale))
        Kt = as_tensor(K, f"PandaSet camera/{c}/intrinsics.json")
        if scale != 1.0:
            Kt = scale_intrinsics(Kt, size[1] / w)
        cam_to_ego = np.linalg.inv(lidar_to_world[0]) @ cam_to_world[c][0]
        cams[c] = CameraInfo(c, Kt, size, as_tensor(cam_to_ego, f"PandaSet camera {c} cam_to_ego"))

    # -- frames and views ---------------------------------------------------------------------------------
    views: list[ViewInfo] = []
    frame_infos: list[FrameInfo] = []
    for fi, f in enumerate(sel):
        ids = []
        for c in cam_names:
            path = cam_dir / c / f"{f:02d}.jpg"
            if not path.is_file():
                missing.append(f"camera/{c}/{f:02d}.jpg")
                continue
            c2w = as_tensor(cam_to_world[c][fi], f"PandaSet camera/{c}/poses.json[{f}]")
            views.append(ViewInfo(len(views), fi, c, cam_ts[c][f] - t0, c2w, path))
            ids.append(len(views) - 1)
        lidar_path = root / "lidar" / f"{f:02d}.pkl.gz"
        if lidar is not None and not lidar_path.is_file():
            missing.append(f"lidar/{f:02d}.pkl.gz")
        frame_infos.append(
            FrameInfo(
                fi,
                lidar_ts[f] - t0,
                as_tensor(lidar_to_world[fi], f"PandaSet lidar/poses.json[{f}]"),
                tuple(ids),
                lidar_path if lidar is not None and lidar_path.is_file() else None,
            )
        )

    # -- cuboids → instances and tracks -------------------------------------------------------------------
    want_sensor = 1 if lidar == "pandargt" else 0
    siblings = _Siblings()
    main_uuids: list[str] = []  # the uuids of boxes not of the PandarGT, in order of appearance
    rows: list[list[tuple[str, str, int, np.ndarray, np.ndarray]]] = []
    for f in sel:
        path = root / "annotations" / "cuboids" / f"{f:02d}.pkl.gz"
        if not path.is_file():
            missing.append(f"annotations/cuboids/{f:02d}.pkl.gz")
            rows.append([])
            continue
        df = read_pickled_dataframe(path, "PandaSet cuboids", _CUBOID_COLUMNS)
        try:
            pos = df[["position.x", "position.y", "position.z"]].to_numpy(dtype=np.float64, copy=True)
            dims = df[["dimensions.y", "dimensions.x", "dimensions.z"]].to_numpy(
                dtype=np.float64, copy=True
            )  # l, w, h
            yaw = df["yaw"].to_numpy(dtype=np.float64, copy=True)
        except (TypeError, ValueError) as e:
            raise ValueError(
                f"PandaSet cuboids {path}: position, dimensions, yaw: expected numbers ({e})"
            ) from None
        bad = ~(np.isfinite(pos).all(1) & np.isfinite(dims).all(1) & np.isfinite(yaw))
        if bad.any():
            raise ValueError(f"PandaSet cuboids {path}: row(s) {np.flatnonzero(bad)[:5].tolist()} not finite")
        uuids = [str(u) for u in df["uuid"]]
        labels = [str(x) for x in df["label"]]
        sensor = np.full(len(df), -1, dtype=np.int64)  # -1: a box of neither LiDAR alone
        if "cuboids.sensor_id" in df.columns:
            try:
                ids = df["cuboids.sensor_id"].to_numpy(dtype=np.float64)
            except (TypeError, ValueError) as e:
                raise ValueError(
                    f"PandaSet cuboids {path}: cuboids.sensor_id: expected numbers ({e})"
                ) from None
            sensor = np.where(np.isfinite(ids), ids, -1).astype(np.int64)
        if "cuboids.sibling_id" in df.columns:
            for u, s, sib in zip(uuids, sensor, df["cuboids.sibling_id"]):
                if s in (0, 1) and isinstance(sib, str) and sib not in ("", "-"):
                    siblings.join(u, sib)
        frame_rows = []
        for r in range(len(df)):
            if sensor[r] != 1:
                main_uuids.append(uuids[r])
            box = np.append(pos[r], yaw[r])
            frame_rows.append((uuids[r], labels[r], int(sensor[r]), box, dims[r]))
        rows.append(frame_rows)

    boxes: dict[int, dict[int, BoxObservation]] = {}
    id_of: dict[str, int] = {}
    names: dict[int, str] = {}
    for fi, frame_rows in enumerate(rows):
        chosen: dict[str, tuple[int, tuple[str, str, int, np.ndarray, np.ndarray]]] = {}
        for row in sorted(frame_rows, key=lambda r: r[0]):
            obj = siblings.find(row[0])
            rank = 0 if row[2] in (-1, want_sensor) else 1  # the loaded LiDAR's box first
            if obj not in chosen or rank < chosen[obj][0]:
                chosen[obj] = (rank, row)
        for obj in sorted(chosen):
            u, label, _, box, lwh = chosen[obj][1]
            if obj not in id_of:
                id_of[obj] = len(id_of) + 1
                names[id_of[obj]] = u
            pose = recentred(pandaset_box_to_matrix(box[:3], box[3]), offset)
            boxes.setdefault(id_of[obj], {})[fi] = BoxObservation(pose, lwh, pandaset_class_name(label))
    named: set[str] = set()
    for u in main_uuids:  # an object is named by its first Pandar64 (or sensor -1) uuid, whatever LiDAR
        obj = siblings.find(u)
        if obj in id_of and obj not in named:
            names[id_of[obj]] = u
            named.add(obj)
    vehicles = {pandaset_class_name(v) for v in PANDASET_VEHICLES}
    instances, tracks = build_instances(boxes, names, num_frames, lambda cls: cls in vehicles, min_motion_m)

    # -- LiDAR ----------------------------------------------------------------------------------------------
    lidar_loader = None
    if lidar is not None:
        keep = PANDASET_LIDARS[lidar]

        def lidar_loader(frame: int) -> LidarFrame:
            if not 0 <= frame < num_frames:
                raise FileNotFoundError(f"{what}: no LiDAR for frame {frame} (frames 0..{num_frames - 1})")
            origin = lidar_to_world[frame][:3, 3]
            path = frame_infos[frame].lidar
            if path is None:  # a missing sweep (warned about at load): no points
                return labelled_lidar(np.zeros((0, 3)), origin, boxes, frame)
            df = read_pickled_dataframe(path, "PandaSet LiDAR sweep", _LIDAR_COLUMNS)
            try:
                xyz = df[["x", "y", "z"]].to_numpy(dtype=np.float64, copy=True)
                d = df["d"].to_numpy().astype(np.int64)
            except (TypeError, ValueError) as e:
                raise ValueError(f"PandaSet LiDAR sweep {path}: x, y, z, d: expected numbers ({e})") from None
            xyz = xyz[np.isin(d, keep) & np.isfinite(xyz).all(1)] - offset
            if drop_ego:
                pose = lidar_to_world[frame]
                local = (xyz - pose[:3, 3]) @ pose[:3, :3]
                ego = np.ones(len(xyz), dtype=bool)
                for axis, (lo, hi) in enumerate(PANDASET_EGO_BOX):
                    ego &= (local[:, axis] > lo) & (local[:, axis] < hi)
                xyz = xyz[~ego]
            return labelled_lidar(xyz, origin, boxes, frame)

    if missing:
        warnings.warn(
            f"{what}: {len(missing)} file(s) missing, read without them: {', '.join(missing)}",
            UserWarning,
            stacklevel=2,
        )
    return assemble_scene(
        what,
        name=f"pandaset_{root.name}",
        root=root,
        cameras_info=cams,
        frames=frame_infos,
        views=views,
        instances=instances,
        tracks=tracks,
        test_frames=test,
        scale=scale,
        lidar_loader=lidar_loader,
        check_files=check_files,
    )
