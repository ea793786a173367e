"""nuScenes as a :class:`~vadgs.data.scene.Scene`, read from the official JSON tables.

vadgs reads the tables of a nuScenes release directly (``<dataroot>/<version>/*.json``, the
layout that ``nuscenes-devkit`` reads) and needs no ``nuscenes-devkit`` installed. The tables used:

- ``scene.json`` (``name``, ``first_sample_token``), ``sample.json`` (keyframes, linked by
  ``next``, ``timestamp`` in µs). Without ``first_sample_token`` (a hand-trimmed extract) the
  keyframes are the samples whose ``scene_token`` is the scene's, in time order;
- ``sample_data.json`` (one file per sensor reading: ``sample_token``, ``is_key_frame``,
  ``ego_pose_token``, ``calibrated_sensor_token``, ``filename``, ``width``, ``height``,
  ``timestamp``), ``calibrated_sensor.json`` (sensor → ego: ``translation``, ``rotation`` as
  ``w, x, y, z``, ``camera_intrinsic``), ``sensor.json`` (``channel``, ``modality``),
  ``ego_pose.json`` (ego → global at the reading's own timestamp);
- ``sample_annotation.json`` (3D boxes in global coordinates: ``translation`` of the centre,
  ``size`` as **width, length, height**, ``rotation`` ``w, x, y, z``, ``instance_token``),
  ``instance.json`` (``category_token``) and ``category.json`` (``name``, e.g. ``vehicle.car``).
  These three are optional: without ``sample_annotation.json`` (or with an empty one, as in the
  test split) the scene has no instances and no tracks; ``instance.json`` and ``category.json``
  are needed only when there are annotations. ``log.json`` and ``map.json`` are not read.

How nuScenes maps to vadgs:

- **Frames** are the scene's keyframes (samples) in order; frame ``i`` is the ``i``-th selected
  sample. Views are frame-major in the order of ``cameras``.
- **Cameras.** nuScenes camera frames are OpenCV (x right, y down, z forward), so
  ``cam_to_world = ego_to_world(camera reading) @ camera_to_ego``, each camera with the ego pose
  at *its own* timestamp (as ``nuscenes-devkit`` does). ``K`` is ``camera_intrinsic`` as is
  (no pixel offset is applied): nuScenes images are already undistorted and rectified, and its
  ``calibrated_sensor`` has no distortion coefficients (nuscenes-devkit issue 120). Tables that
  carry a ``camera_distortion`` list (the nuImages layout: OpenCV order ``k1, k2, p1, p2, k3``)
  with non-zero values get their images undistorted when loaded (:mod:`vadgs.data.undistort`)
  and ``K`` is then the pinhole ``K`` of the undistorted images.
- **LiDAR.** ``LIDAR_TOP`` keyframe sweeps (``.pcd.bin``: float32 ``x, y, z, intensity, ring``
  in the LiDAR frame) are moved to the world with their own ego pose and calibration.
- **Boxes → tracks.** Annotations are grouped by ``instance_token``; each instance gets a
  persistent integer id (1, 2, ... in order of first appearance in the scene). Every instance is
  in ``Scene.instances``; *moving vehicles* (category ``vehicle.*`` whose box centre moves more
  than ``min_motion_m`` over the scene) become :class:`~vadgs.data.scene.Track` objects.
- **World.** nuScenes' global frame (z up, metres) lies far from its origin; with
  ``recenter=True`` vadgs subtracts the translation of the first keyframe's ego pose (no
  rotation), as :func:`~vadgs.data.load_dgp` does.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from vadgs.data._json import DatasetFiles, read_json, require_key
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
from vadgs.data.assemble import assemble_scene, check_scale, file_image_loader
from vadgs.data.checks import check_lidar_points
from vadgs.data.scene import CameraInfo, FrameInfo, LidarFrame, Scene, ViewInfo
from vadgs.data.undistort import ImageUndistorter
from vadgs.geometry.camera import scale_intrinsics

__all__ = ["NUSCENES_CAMERAS", "load_nuscenes", "nuscenes_class_name", "nuscenes_pose_to_matrix"]

#: the six cameras of the nuScenes rig, in the default order of the views.
NUSCENES_CAMERAS = (
    "CAM_FRONT_LEFT",
    "CAM_FRONT",
    "CAM_FRONT_RIGHT",
    "CAM_BACK_RIGHT",
    "CAM_BACK",
    "CAM_BACK_LEFT",
)

#: the tables every scene needs.
_TABLES = ("scene", "sample", "sample_data", "calibrated_sensor", "sensor", "ego_pose")
#: the annotation tables: a release without annotations (the test split, a trimmed extract) may
#: lack them; ``instance`` and ``category`` are then needed only if ``sample_annotation`` has rows.
_ANNOTATION_TABLES = ("sample_annotation", "instance", "category")


def nuscenes_pose_to_matrix(rotation: Sequence[float], translation: Sequence[float]) -> np.ndarray:
    """A nuScenes ``rotation`` (``w, x, y, z``) and ``translation`` as a 4×4 float64 matrix.

    Raises:
        ValueError: if the rotation is not a non-zero quaternion or the translation not 3 numbers.

    Example:
        >>> nuscenes_pose_to_matrix([0.0, 0.0, 0.0, 1.0], [1.0, 2.0, 3.0]).round(6).tolist()
        [[-1.0, 0.0, 0.0, 1.0], [0.0, -1.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0], [0.0, 0.0, 0.0, 1.0]]
    """
    out = np.eye(4)
    out[:3, :3] = quat_wxyz_to_matrix(rotation)
    try:
        t = np.asarray(translation, dtype=np.float64)
    except (TypeError, ValueError):
        t = np.zeros(0)
    if t.shape != (3,) or not np.isfinite(t).all():
        raise ValueError(f"translation: expected 3 finite numbers, got {translation!r}")
    out[:3, 3] = t
    return out


def nuscenes_class_name(category: str) -> str:
    """The vadgs class name of a nuScenes category: drop the top-level group, join the rest with ``_``.

    Example:
        >>> names = ("vehicle.car", "vehicle.bus.rigid", "human.pedestrian.adult", "animal")
        >>> [nuscenes_class_name(c) for c in names]
        ['car', 'bus_rigid', 'pedestrian_adult', 'animal']
    """
    parts = category.split(".")
    return "_".join(parts[1:] if len(parts) > 1 else parts)


def _read_table(meta_dir: Path, name: str) -> list[dict]:
    return read_json(meta_dir / f"{name}.json", f"nuScenes table {name}.json", top=list)


def _by_token(rows: list[dict], table: str) -> dict[str, dict]:
    out = {}
    for i, r in enumerate(rows):
        out[str(_key(r, "token", f"{table}.json[{i}]"))] = r
    return out


def _key(d: object, key: str, what: str) -> Any:
    return require_key(d, key, f"nuScenes {what}")


def _ref(table: dict[str, dict], token: object, table_name: str, what: str) -> dict:
    if token not in table:
        raise ValueError(f"nuScenes {what}: token {token!r} not in {table_name}.json")
    return table[token]


def load_nuscenes(
    dataroot: str | Path,
    scene_name: str,
    version: str = "v1.0-mini",
    cameras: Sequence[str] | None = None,
    scale: float = 1.0,
    frames: Sequence[int] | None = None,
    test_frames: Sequence[int] | None = None,
    min_motion_m: float | None = 0.5,
    lidar: str | None = "LIDAR_TOP",
    recenter: bool = True,
    check_files: bool = True,
) -> Scene:
    """Load one nuScenes scene (keyframes, cameras, LiDAR, 3D boxes) as a :class:`Scene`.

    Reads the official JSON tables directly (no ``nuscenes-devkit`` needed). See the module
    docstring for how each table maps to vadgs.

    What the scene holds:

    - ``cameras_info``: ``K`` = ``camera_intrinsic`` (or the pinhole ``K`` of the undistorted
      images when the table has a non-zero ``camera_distortion``; rescaled by ``scale``), the
      image size from ``sample_data``, ``cam_to_ego`` from ``calibrated_sensor``.
    - ``views``: ``cam_to_world`` from each camera reading's own ego pose; ``timestamp`` in
      seconds since the first keyframe; the JPEG path (read lazily, resized by ``scale``).
    - ``frames``: ``ego_to_world`` = the ego pose of the ``LIDAR_TOP`` keyframe reading,
      ``lidar`` its ``.pcd.bin``. ``Scene.lidar(f)`` gives the sweep in world coordinates, each
      point's ``instance`` the id of the annotated box it falls in (0 outside), ``origin`` the
      LiDAR position.
    - ``instances``: every annotated instance: id (persistent, 1-based, in order of first
      appearance), ``name`` = the instance token, ``class_name`` from
      :func:`nuscenes_class_name`, ``dynamic`` if its centre moves more than ``min_motion_m``.
    - ``tracks``: the dynamic ``vehicle.*`` instances (with ``min_motion_m=None``: every
      ``vehicle.*`` instance, parked ones too), ``object_to_world`` per annotated frame,
      ``size_lwh`` the median of the annotated sizes (nuScenes stores width, length, height).
    - ``test_frames``: frames 2, 6, 10, ... (every fourth, the benchmark's protocol) unless
      given; ``train_frames`` the rest.

    Args:
        dataroot: the nuScenes root (holding ``samples/``, ``sweeps/`` and ``<version>/``).
        scene_name: e.g. ``"scene-0061"``.
        version: the table folder, e.g. ``"v1.0-mini"`` or ``"v1.0-trainval"``.
        cameras: camera channels (default :data:`NUSCENES_CAMERAS`).
        scale: resolution factor for images and intrinsics.
        frames: keyframe positions to keep (default all), e.g. ``range(0, 20)``; they are
            renumbered 0, 1, ... in the scene.
        test_frames: frame indices to hold out (default every fourth from 2; ``()`` for none).
        min_motion_m: a vehicle whose box centre moves more than this (metres) is a track;
            None makes every vehicle a track.
        lidar: the LiDAR channel, or None for no LiDAR (``ego_to_world`` then comes from the
            first camera's reading).
        recenter: translate the world so that the ego at frame 0 sits at the origin.
        check_files: verify that every image and LiDAR file exists.

    Returns:
        The :class:`Scene`.

    Raises:
        FileNotFoundError: if ``dataroot``, a table or a referenced file is missing.
        ValueError: if the scene, a camera or the LiDAR channel is unknown (the message lists
            what there is), a table lacks a key or token, or an argument is invalid.

    Example:
        >>> scene = load_nuscenes("/data/sets/nuscenes", "scene-0061", scale=0.25)  # doctest: +SKIP
        >>> scene.num_views, scene.image_size(0)  # doctest: +SKIP
        (234, (225, 400))
    """
    dataroot = Path(dataroot)
    files = DatasetFiles(dataroot, what=f"nuScenes {version}")
    if not dataroot.is_dir():
        raise FileNotFoundError(f"dataroot: no such folder {dataroot}")
    meta_dir = dataroot / version
    if not meta_dir.is_dir():
        have = sorted(p.name for p in dataroot.iterdir() if p.is_dir() and p.name.startswith("v"))
        raise FileNotFoundError(f"version: no table folder {meta_dir} (have {have})")
    check_scale(scale)
    check_min_motion(min_motion_m)
    raw = {name: _read_table(meta_dir, name) for name in _TABLES}
    if (meta_dir / "sample_annotation.json").is_file():
        raw["sample_annotation"] = _read_table(meta_dir, "sample_annotation")
    else:
        raw["sample_annotation"] = []  # no annotations (e.g. a trimmed test keyframe): no tracks
    for name in _ANNOTATION_TABLES[1:]:
        needed = bool(raw["sample_annotation"]) or (meta_dir / f"{name}.json").is_file()
        raw[name] = _read_table(meta_dir, name) if needed else []
    t = {name: _by_token(rows, name) for name, rows in raw.items()}

    # -- the scene and its keyframes ------------------------------------------------------------------
    scenes = {str(_key(s, "name", "scene.json")): s for s in raw["scene"]}
    if scene_name not in scenes:
        raise ValueError(f"scene_name: unknown scene {scene_name!r} in {version}, have {sorted(scenes)[:20]}")
    scene_rec = scenes[scene_name]
    samples = []
    token = scene_rec.get("first_sample_token")
    while token:
        s = _ref(t["sample"], token, "sample", f"scene {scene_name}: sample chain")
        samples.append(s)
        token = s.get("next", "")
        if len(samples) > len(t["sample"]):
            raise ValueError(f"nuScenes scene {scene_name}: the sample chain loops")
    if "first_sample_token" not in scene_rec:
        # a trimmed table without the links: the scene's samples by scene_token, in time order
        scene_token = _key(scene_rec, "token", f"scene {scene_name}")
        mine = [s for s in raw["sample"] if s.get("scene_token") == scene_token]
        if not mine:
            raise ValueError(
                f"nuScenes scene {scene_name}: scene.json has no first_sample_token and sample.json "
                f"no sample with scene_token {scene_token!r}"
            )
        samples = sorted(mine, key=lambda s: int(_key(s, "timestamp", f"sample {s.get('token')}")))
    samples = [samples[f] for f in select_positions(frames, len(samples), "keyframe")]
    num_frames = len(samples)
    test = held_out_frames(test_frames, num_frames)

    # -- keyframe readings of each channel --------------------------------------------------------------
    def channel_of(sd: dict, what: str) -> tuple[str, str]:
        cs = _ref(
            t["calibrated_sensor"], _key(sd, "calibrated_sensor_token", what), "calibrated_sensor", what
        )
        sensor = _ref(t["sensor"], _key(cs, "sensor_token", what), "sensor", what)
        return str(_key(sensor, "channel", "sensor.json")), str(sensor.get("modality", ""))

    wanted: dict[str | None, int] = {str(s["token"]): i for i, s in enumerate(samples)}
    readings: dict[tuple[int, str], dict] = {}
    modality: dict[str, str] = {}
    for i, sd in enumerate(raw["sample_data"]):
        fi = wanted.get(sd.get("sample_token"))
        if fi is None or not sd.get("is_key_frame", False):
            continue
        channel, mod = channel_of(sd, f"sample_data.json[{i}]")
        readings[(fi, channel)] = sd
        modality[channel] = mod
    cam_channels = [c for c in NUSCENES_CAMERAS if modality.get(c) == "camera"] + sorted(
        c for c, m in modality.items() if m == "camera" and c not in NUSCENES_CAMERAS
    )
    cam_names = select_cameras(
        cameras,
        cam_channels,
        f"nuScenes scene {scene_name}: no camera keyframes (channels: {sorted(modality)})",
    )
    if lidar is not None and modality.get(lidar) != "lidar":
        have = sorted(c for c, m in modality.items() if m == "lidar")
        raise ValueError(f"lidar: unknown LiDAR channel {lidar!r}, have {have}")

    def reading(fi: int, channel: str) -> dict:
        sd = readings.get((fi, channel))
        if sd is None:
            raise ValueError(
                f"nuScenes scene {scene_name}: keyframe {fi} (sample {samples[fi]['token']}) "
                f"has no {channel} reading"
            )
        return sd

    def sensor_to_ego(sd: dict, what: str) -> tuple[np.ndarray, dict]:
        cs = t["calibrated_sensor"][sd["calibrated_sensor_token"]]
        m = nuscenes_pose_to_matrix(_key(cs, "rotation", what), _key(cs, "translation", what))
        return m, cs

    def ego_pose(sd: dict, what: str) -> np.ndarray:
        ep = _ref(t["ego_pose"], _key(sd, "ego_pose_token", what), "ego_pose", what)
        return nuscenes_pose_to_matrix(_key(ep, "rotation", what), _key(ep, "translation", what))

    ref = lidar if lidar is not None else cam_names[0]
    offset = ego_pose(reading(0, ref), f"{ref} at frame 0")[:3, 3].copy() if recenter else np.zeros(3)

    def to_world(m: np.ndarray) -> np.ndarray:
        return recentred(m, offset)

    # -- cameras ---------------------------------------------------------------------------------------
    cams: dict[str, CameraInfo] = {}
    full_size: dict[str, tuple[int, int]] = {}
    undistort: dict[str, ImageUndistorter] = {}  # cameras with a non-zero camera_distortion
    for c in cam_names:
        sd = reading(0, c)
        what = f"{c} calibrated_sensor"
        c2e, cs = sensor_to_ego(sd, what)
        K = np.asarray(_key(cs, "camera_intrinsic", what), dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"nuScenes {what}.camera_intrinsic: expected a 3x3 matrix, got shape {K.shape}")
        w, h = int(_key(sd, "width", f"{c} sample_data")), int(_key(sd, "height", f"{c} sample_data"))
        full_size[c] = (w, h)
        dist = cs.get("camera_distortion")
        if dist:
            try:
                und = ImageUndistorter(torch.from_numpy(K), dist, (h, w))
            except ValueError as e:
                raise ValueError(f"nuScenes {what}.camera_distortion: {e}") from None
            if und.distorted:
                undistort[c], K = und, und.K.numpy()
        size = (round(h * scale), round(w * scale))
        Kt = as_tensor(K, f"{what}.camera_intrinsic")
        if scale != 1.0:
            Kt = scale_intrinsics(Kt, size[1] / w)
        cams[c] = CameraInfo(c, Kt, size, as_tensor(c2e, what))

    # -- frames, views, LiDAR ---------------------------------------------------------------------------
    t0 = int(_key(samples[0], "timestamp", "sample"))
    frame_infos: list[FrameInfo] = []
    views: list[ViewInfo] = []
    lidar_to_world: dict[int, np.ndarray] = {}  # the LiDAR's sensor-to-world per frame
    for fi, s in enumerate(samples):
        ids = []
        for c in cam_names:
            sd = reading(fi, c)
            what = f"{c} at frame {fi}"
            if (sd.get("width"), sd.get("height")) != full_size[c]:
                raise ValueError(
                    f"nuScenes {what}: image size {sd.get('width')}x{sd.get('height')} differs from "
                    f"the camera's {full_size[c][0]}x{full_size[c][1]}"
                )
            c2w = to_world(ego_pose(sd, what)) @ sensor_to_ego(sd, what)[0]
            ts = (int(_key(sd, "timestamp", what)) - t0) * 1e-6
            path = files(str(_key(sd, "filename", what)), f"{what}.filename")
            views.append(ViewInfo(len(views), fi, c, ts, as_tensor(c2w, f"{what} pose"), path))
            ids.append(len(views) - 1)
        sd = reading(fi, ref)
        e2w = to_world(ego_pose(sd, f"{ref} at frame {fi}"))
        lidar_path = None
        if lidar is not None:
            lidar_path = files(str(_key(sd, "filename", f"{lidar} at frame {fi}")), f"{lidar} at frame {fi}")
            lidar_to_world[fi] = e2w @ sensor_to_ego(sd, f"{lidar} at frame {fi}")[0]
        ts = (int(_key(s, "timestamp", "sample")) - t0) * 1e-6
        frame_infos.append(
            FrameInfo(fi, ts, as_tensor(e2w, f"ego pose at frame {fi}"), tuple(ids), lidar_path)
        )

    # -- boxes → instances and tracks ------------------------------------------------------------------
    boxes: dict[int, dict[int, BoxObservation]] = {}
    id_of: dict[str, int] = {}
    names: dict[int, str] = {}
    anns_by_sample: dict[str | None, list[dict]] = {}
    for a in raw["sample_annotation"]:
        anns_by_sample.setdefault(a.get("sample_token"), []).append(a)
    for fi, s in enumerate(samples):
        for a in anns_by_sample.get(s["token"], []):
            what = f"sample_annotation {a.get('token')}"
            inst_token = str(_key(a, "instance_token", what))
            inst = _ref(t["instance"], inst_token, "instance", what)
            cat = _ref(
                t["category"], _key(inst, "category_token", f"instance {inst_token}"), "category", what
            )
            if inst_token not in id_of:
                id_of[inst_token] = len(id_of) + 1
                names[id_of[inst_token]] = inst_token
            wlh = np.asarray(_key(a, "size", what), dtype=np.float64)
            if wlh.shape != (3,):
                raise ValueError(f"nuScenes {what}.size: expected 3 numbers (w, l, h), got {a['size']!r}")
            pose = to_world(nuscenes_pose_to_matrix(_key(a, "rotation", what), _key(a, "translation", what)))
            cls = nuscenes_class_name(str(_key(cat, "name", "category.json")))
            boxes.setdefault(id_of[inst_token], {})[fi] = BoxObservation(pose, wlh[[1, 0, 2]], cls)
    vehicle_classes = {
        nuscenes_class_name(str(c["name"]))
        for c in raw["category"]
        if str(c.get("name", "")).startswith("vehicle.")
    }
    instances, tracks = build_instances(
        boxes, names, num_frames, lambda cls: cls in vehicle_classes, min_motion_m
    )

    def read_lidar(frame: int, path: Path) -> LidarFrame:
        sensor_to_world = lidar_to_world[frame]
        data = np.fromfile(path, dtype=np.float32)
        if data.size == 0 or data.size % 5:
            got = "an empty file (0 bytes)" if data.size == 0 else f"{path.stat().st_size} bytes"
            raise ValueError(
                f"nuScenes LiDAR {path}: expected float32 x, y, z, intensity, ring (5 per point, "
                f"20 bytes), got {got}: truncated or not a sweep"
            )
        local = data.reshape(-1, 5)[:, :3].astype(np.float64)
        check_lidar_points(
            torch.from_numpy(local), torch.zeros(3, dtype=torch.float64), f"nuScenes LiDAR {path}"
        )
        world = local @ sensor_to_world[:3, :3].T + sensor_to_world[:3, 3]
        return labelled_lidar(world, sensor_to_world[:3, 3], boxes, frame)

    files.warn()
    return assemble_scene(
        f"nuScenes scene {scene_name}",
        name=scene_name,
        root=dataroot,
        cameras_info=cams,
        frames=frame_infos,
        views=views,
        instances=instances,
        tracks=tracks,
        test_frames=test,
        scale=scale,
        read_lidar=read_lidar,
        image_loader=file_image_loader(undistort, "nuScenes"),
        check_files=check_files,
    )
