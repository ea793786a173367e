"""TRI's DGP driving format (the DDAD family) as a :class:`~vadgs.data.scene.Scene`.

A DGP scene folder holds ``scene_<sha1>.json`` (``samples``: one per timestamp, each listing
the keys of its datums; ``data``: the datums: images and point clouds, each with a ``pose``),
``calibration/<key>.json`` (per sensor ``names``, ``intrinsics``, ``extrinsics``),
``ontology/<key>.json`` (class id → name), ``rgb/<camera>/<ts>.jpg``,
``point_cloud/<lidar>/<ts>.npz`` and ``bounding_box_3d/<sensor>/<ts>.json``.

How DGP's frames map to vadgs's (verified on ``dgp_test_scene/scene_02``, see ``docs/data.md``):

- **Poses** are quaternions ``(qw, qx, qy, qz)`` plus a translation. A datum's ``pose`` is
  *sensor-to-world* at the datum's own timestamp, so a camera datum's pose is its
  ``cam_to_world`` directly (cameras use OpenCV axes in DGP, as in vadgs). Calibration
  ``extrinsics`` are *sensor-to-vehicle* (``CameraInfo.cam_to_ego``); in the test scenes the
  LiDAR's extrinsic is the identity, so the vehicle frame is the LiDAR frame, and a camera's pose
  equals ``lidar_pose @ inv(lidar_extrinsic) @ camera_extrinsic`` to within 5 cm (the camera is
  triggered about 90 ms before the sweep ends).
- **Intrinsics** ``fx, fy, cx, cy, skew`` form ``K`` as in OpenCV, pixel centres at integers, so
  no offset is applied (unlike COLMAP). When a calibration has non-zero distortion coefficients
  (OpenCV's ``k1``-``k6``, ``p1``, ``p2``, ``s1``-``s4``, as DGP's ``CameraIntrinsics``) the images
  are undistorted when loaded (:mod:`vadgs.data.undistort`) and ``K`` is their pinhole ``K``; other
  camera models (``fisheye``, tilted sensor, UCM, double sphere, equirectangular) are refused
  with a :class:`ValueError`. The real test scenes have no distortion.
- **Point clouds** are stored in the *sensor frame* (``X, Y, Z, INTENSITY``, float64) and are
  moved to world coordinates with the LiDAR datum's pose when loaded.
- **3D boxes** are stored in the frame of the sensor they annotate, centred on the box, with x
  along the length, y along the width, z up. vadgs reads the LiDAR's boxes (a camera's when no
  LiDAR is loaded) and places them in the world: ``object_to_world = sensor_to_world @ box_pose``.
  Instance ids persist across samples, so every box instance becomes a :class:`Track`.
- **World.** DGP's world frame has z up (metres) but lies far from its origin (e.g. y = -2261 m),
  which float32 and Gaussian splatting handle poorly. With ``recenter=True`` (the default) vadgs's
  world is DGP's world translated so that the vehicle at the first sample sits at the origin
  (no rotation): ``p_vadgs = p_dgp - t0`` with ``t0`` the translation of that vehicle pose.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import torch

from vadgs.data._json import DatasetFiles, read_json, require_key
from vadgs.data._tracks import (
    BoxObservation,
    as_tensor,
    build_instances,
    labelled_lidar,
    quat_wxyz_to_matrix,
    recentred,
    select_cameras,
)
from vadgs.data.assemble import (
    assemble_scene,
    check_scale,
    check_validate_level,
    file_image_loader,
    pinhole_camera,
)
from vadgs.data.checks import check_lidar_points
from vadgs.data.scene import CameraInfo, FrameInfo, LidarFrame, Scene, ViewInfo, npz_headers
from vadgs.data.undistort import OPENCV_DISTORTION, ImageUndistorter

__all__ = ["dgp_pose_to_matrix", "load_dgp"]


#: the DGP annotation type id of 3D bounding boxes (keys of ``annotations`` and ``ontologies``).
_BOX3D = "1"
#: ``CameraIntrinsics`` fields of camera models other than OpenCV's (refused when non-zero).
_OTHER_CAMERA_MODELS = ("fisheye", "taux", "tauy", "alpha", "beta", "w", "xi", "equirectangular")


def dgp_pose_to_matrix(pose: dict) -> np.ndarray:
    """A DGP pose ``{"rotation": {qw, qx, qy, qz}, "translation": {x, y, z}}`` as a 4×4 float64 matrix.

    The quaternion is normalised (DGP writes it with a few ulps of error, sometimes with qw < 0).

    Args:
        pose: the pose as stored in DGP JSON.

    Returns:
        ``(4, 4)`` rigid transform (numpy, float64).

    Raises:
        ValueError: if a key is missing, a value is not a finite number, or the quaternion is zero.

    Example:
        >>> T = dgp_pose_to_matrix({"rotation": {"qw": 0.0, "qx": 0.0, "qy": 0.0, "qz": 1.0},
        ...                         "translation": {"x": 1.0, "y": 2.0, "z": 3.0}})
        >>> T.round(6).tolist()
        [[-1.0, 0.0, 0.0, 1.0], [0.0, -1.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0], [0.0, 0.0, 0.0, 1.0]]
    """
    try:
        rot, tr = pose["rotation"], pose["translation"]
        q = np.array([float(rot[k]) for k in ("qw", "qx", "qy", "qz")])
        t = np.array([float(tr[k]) for k in ("x", "y", "z")])
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(
            "DGP pose: expected rotation {qw, qx, qy, qz} and translation {x, y, z}, "
            f"got {pose!r} ({e!r})"
        ) from None
    n = np.linalg.norm(q)
    if not (np.isfinite(n) and n > 0 and np.isfinite(t).all()):
        raise ValueError(f"DGP pose: expected a finite non-zero quaternion and translation, got {pose!r}")
    out = np.eye(4)
    out[:3, :3] = quat_wxyz_to_matrix(q)
    out[:3, 3] = t
    return out


def _read_json(path: Path, what: str) -> dict:
    return read_json(path, f"DGP {what}")


def _key(d: object, key: str, what: str) -> Any:
    return require_key(d, key, f"DGP {what}")


def _time(stamp: str, what: str) -> datetime:
    try:
        return datetime.fromisoformat(stamp.replace("Z", "+00:00"))
    except (AttributeError, ValueError):
        raise ValueError(f"DGP {what}: expected an ISO 8601 timestamp, got {stamp!r}") from None


def _class_slug(name: str) -> str:
    """``"Bus/RV/Caravan"`` → ``"bus_rv_caravan"`` (vadgs class names are lower-case words)."""
    return "_".join("".join(c if c.isalnum() else " " for c in name.lower()).split())


def _find_scene_json(scene_dir: Path) -> tuple[Path, Path]:
    if scene_dir.is_file():
        return scene_dir.parent, scene_dir
    if not scene_dir.is_dir():
        raise FileNotFoundError(f"scene_dir: no such folder {scene_dir}")
    cands = sorted(scene_dir.glob("scene*.json"))
    if not cands:
        raise FileNotFoundError(f"scene_dir: no scene*.json in {scene_dir}")
    if len(cands) > 1:
        raise ValueError(
            f"scene_dir: several scene JSON files in {scene_dir}: {[c.name for c in cands]}; pass one"
        )
    return scene_dir, cands[0]


def load_dgp(
    scene_dir: str | Path,
    cameras: Sequence[str] | None = None,
    scale: float = 1.0,
    lidar: str | None = "LIDAR",
    test_frames: Sequence[int] = (),
    recenter: bool = True,
    check_files: bool = True,
    validate: str = "headers",
) -> Scene:
    """Load one DGP scene (cameras, LiDAR, 3D boxes) as a :class:`Scene`.

    Frames are DGP samples in order (frame ``i`` is sample ``i``); views are frame-major in the
    order of ``cameras``. See the module docstring for the frame conventions.

    What the scene holds:

    - ``cameras_info``: ``K`` (with skew) from the calibration (the pinhole ``K`` of the
      undistorted images for a camera with distortion), rescaled by ``scale``; the image
      size from the datums; ``cam_to_ego`` = the sensor-to-vehicle extrinsic.
    - ``views``: ``cam_to_world`` = the camera datum's pose, timestamp in seconds since the first
      sample, the JPEG path (loaded lazily, undistorted if distorted, resized by ``scale``). No
      depth or instance maps (DGP has none here: ``ViewInfo.depth`` and ``ViewInfo.instances``
      are None).
    - ``frames``: ``ego_to_world`` = vehicle pose (LiDAR pose ``@ inv(lidar_extrinsic)``), and
      the LiDAR path. ``Scene.lidar(frame)`` returns the sweep in world coordinates (float32),
      its ``instance`` the id of the 3D box (as annotated at that sample) each point falls in
      (0 outside every box), its
      ``origin`` the LiDAR position.
    - ``tracks``: one per box instance id: ``object_to_world`` per frame where annotated
      (``valid``), ``size_lwh`` the median over frames, class from the ontology
      (lower-cased, e.g. ``"car"``, ``"truck"``, ``"bus_rv_caravan"``). ``instances`` lists the
      same ids, ``dynamic`` when the box centre moves more than 0.5 m in the world.
    - ``train_frames`` every frame not in ``test_frames`` (by default no frame is held out).

    Args:
        scene_dir: the scene folder holding ``scene_*.json`` (or that JSON file itself).
        cameras: camera datum names to load (default: every camera of the calibration that has
            image datums, in calibration order, e.g. ``CAMERA_01, CAMERA_05, ...``).
        scale: resolution factor for images and intrinsics.
        lidar: the LiDAR datum name, or None to load no LiDAR (boxes then come from the first
            camera's annotations).
        test_frames: frame indices (sample positions) to hold out.
        recenter: translate the world so that the vehicle at frame 0 sits at the origin.
        check_files: verify that every referenced image and point cloud exists.
        validate: content checks (:func:`~vadgs.data.validate_scene`): ``"headers"`` (default:
            ``K``, rigid poses, image sizes from the file headers, point-cloud array headers),
            ``"full"`` (decode every file) or ``"none"``; a failure raises a :class:`ValueError`
            naming the file.

    Returns:
        The :class:`Scene`.

    Raises:
        FileNotFoundError: if the scene JSON, calibration, ontology or a referenced file is missing.
        ValueError: if a JSON file is malformed or lacks a key (named in the message), a pose is
            not finite, a camera or LiDAR name is unknown, a sample lacks a requested datum, a
            camera is not an OpenCV (pinhole + distortion) camera, or ``scale`` / ``test_frames``
            are invalid.

    Example:
        >>> from pathlib import Path
        >>> root = Path("../shared/data/real/dgp_test_scene/scene_02")
        >>> if root.is_dir():  # doctest: +SKIP
        ...     scene = load_dgp(root, scale=0.25)
        ...     scene.num_views, scene.image_size(0)
        (18, (304, 484))
    """
    scene_dir, scene_json = _find_scene_json(Path(scene_dir))
    check_scale(scale)
    check_validate_level(validate)
    meta = _read_json(scene_json, "scene")
    files = DatasetFiles(scene_dir, what=f"DGP {scene_json.name}")
    samples = _key(meta, "samples", scene_json.name)
    data = _key(meta, "data", scene_json.name)
    if not isinstance(samples, list) or not samples:
        raise ValueError(f"DGP {scene_json.name}: samples: expected a non-empty list")
    if not isinstance(data, list):
        raise ValueError(f"DGP {scene_json.name}: data: expected a list")
    datum_by_key = {str(_key(d, "key", f"{scene_json.name}: data[{i}]")): d for i, d in enumerate(data)}

    calib_key = str(_key(samples[0], "calibration_key", f"{scene_json.name}: samples[0]"))
    if any(s.get("calibration_key") != calib_key for s in samples):
        raise ValueError(
            f"DGP {scene_json.name}: samples use several calibrations; vadgs supports one per scene"
        )
    calib = _read_json(files(f"calibration/{calib_key}.json", "calibration_key"), "calibration")
    names = [str(n) for n in _key(calib, "names", "calibration")]
    intr = _key(calib, "intrinsics", "calibration")
    extr = _key(calib, "extrinsics", "calibration")
    if not (len(intr) == len(extr) == len(names)):
        raise ValueError(
            "DGP calibration: names, intrinsics, extrinsics differ in length "
            f"({len(names)}, {len(intr)}, {len(extr)})"
        )
    sensor_to_ego = {n: dgp_pose_to_matrix(e) for n, e in zip(names, extr)}
    intrinsics = dict(zip(names, intr))

    # the datums of each sample, by sensor name
    per_sample: list[dict[str, dict]] = []
    for si, s in enumerate(samples):
        row = {}
        for k in _key(s, "datum_keys", f"{scene_json.name}: samples[{si}]"):
            if k not in datum_by_key:
                raise ValueError(f"DGP {scene_json.name}: samples[{si}]: datum key {k!r} not in data")
            d = datum_by_key[k]
            row[str(_key(_key(d, "id", f"datum {k}"), "name", f"datum {k}.id"))] = d
        per_sample.append(row)
    image_names = [n for n in names if any("image" in r.get(n, {}).get("datum", {}) for r in per_sample)]
    cam_names = select_cameras(
        cameras, image_names, f"DGP {scene_json.name}: no camera to load (image datums: {image_names})"
    )
    if lidar is not None and lidar not in names:
        raise ValueError(f"lidar: unknown sensor {lidar!r}, have {names}")
    frame_ids = list(range(len(samples)))
    bad = [f for f in test_frames if f not in frame_ids]
    if bad:
        raise ValueError(f"test_frames: unknown frame(s) {bad}, have {frame_ids}")

    def datum(si: int, name: str, kind: str) -> dict:
        d = per_sample[si].get(name)
        if d is None or kind not in d.get("datum", {}):
            raise ValueError(f"DGP {scene_json.name}: samples[{si}] has no {kind} datum {name!r}")
        return d["datum"][kind]

    # -- world origin ---------------------------------------------------------------------------------
    ref = lidar if lidar is not None else cam_names[0]
    ref_kind = "point_cloud" if lidar is not None else "image"
    ego0 = dgp_pose_to_matrix(_key(datum(0, ref, ref_kind), "pose", f"samples[0].{ref}")) @ np.linalg.inv(
        sensor_to_ego[ref]
    )
    offset = ego0[:3, 3].copy() if recenter else np.zeros(3)

    def to_world(sensor_to_dgp_world: np.ndarray) -> np.ndarray:
        return recentred(sensor_to_dgp_world, offset)

    # -- cameras --------------------------------------------------------------------------------------
    cams: dict[str, CameraInfo] = {}
    full_size: dict[str, tuple[object, object]] = {}
    undistort: dict[str, ImageUndistorter] = {}
    for n in cam_names:
        c = intrinsics[n]
        what = f"calibration.intrinsics[{n}]"
        raw = [_key(c, k, what) for k in ("fx", "fy", "cx", "cy")]
        try:
            fx, fy, cx, cy = (float(v) for v in raw)
            skew = float(c.get("skew", 0.0))
        except (TypeError, ValueError):
            raise ValueError(f"DGP {what}: expected numbers, got {c!r}") from None
        other = {k: c[k] for k in _OTHER_CAMERA_MODELS if c.get(k) not in (None, 0, 0.0, False)}
        if other:
            raise ValueError(
                f"DGP {what}: camera model parameters {other} are not supported (vadgs undistorts "
                f"OpenCV's {', '.join(OPENCV_DISTORTION)} only)"
            )
        try:
            coeffs = [float(c.get(k) or 0.0) for k in OPENCV_DISTORTION]
        except (TypeError, ValueError):
            raise ValueError(f"DGP {what}: expected numeric distortion coefficients, got {c!r}") from None
        K = torch.tensor([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)
        first = datum(0, n, "image")
        w, h = int(_key(first, "width", f"{n} image datum")), int(_key(first, "height", f"{n} image datum"))
        full_size[n] = (first["width"], first["height"])
        dist = torch.tensor(coeffs, dtype=torch.float64)
        cams[n], undistort[n] = pinhole_camera(n, K, dist, (h, w), scale, sensor_to_ego[n], f"DGP {what}")

    # -- frames, views, LiDAR, boxes ------------------------------------------------------------------
    t0 = _time(
        _key(_key(samples[0], "id", "samples[0]"), "timestamp", "samples[0].id"), "samples[0].id.timestamp"
    )
    frames: list[FrameInfo] = []
    views: list[ViewInfo] = []
    lidar_to_world: dict[int, np.ndarray] = {}  # the LiDAR datum's pose per frame
    raw_boxes: dict[
        int, dict[int, tuple[np.ndarray, list[float], int]]
    ] = {}  # id -> frame -> (pose, lwh, class)
    for fi in frame_ids:
        stamp = _key(_key(samples[fi], "id", f"samples[{fi}]"), "timestamp", f"samples[{fi}].id")
        ts = (_time(stamp, f"samples[{fi}].id.timestamp") - t0).total_seconds()
        ids = []
        for n in cam_names:
            im = datum(fi, n, "image")
            what = f"samples[{fi}].{n}"
            if (im.get("width"), im.get("height")) != full_size[n]:
                raise ValueError(
                    f"DGP {what}: image size {im.get('width')}x{im.get('height')} differs from the "
                    f"camera's {full_size[n][0]}x{full_size[n][1]}"
                )
            c2w = as_tensor(to_world(dgp_pose_to_matrix(_key(im, "pose", what))), f"{what}.pose")
            vts = (
                _time(per_sample[fi][n]["id"].get("timestamp", stamp), f"{what}.id.timestamp") - t0
            ).total_seconds()
            path = files(str(_key(im, "filename", what)), f"{what}.filename")
            views.append(ViewInfo(len(views), fi, n, vts, c2w, path))
            ids.append(len(views) - 1)
        ref_datum = datum(fi, ref, ref_kind)
        ref_pose = to_world(dgp_pose_to_matrix(_key(ref_datum, "pose", f"samples[{fi}].{ref}")))
        e2w = as_tensor(ref_pose @ np.linalg.inv(sensor_to_ego[ref]), f"samples[{fi}].{ref}.pose")
        lidar_path = None
        if lidar is not None:
            lidar_path = files(
                str(_key(ref_datum, "filename", f"samples[{fi}].{lidar}")), f"samples[{fi}].{lidar}"
            )
            lidar_to_world[fi] = ref_pose
        frames.append(FrameInfo(fi, ts, e2w, tuple(ids), lidar_path))

        ann = ref_datum.get("annotations", {}).get(_BOX3D)
        if ann:
            for ai, a in enumerate(
                _key(
                    _read_json(files(str(ann), f"samples[{fi}] annotations"), "3D boxes"), "annotations", ann
                )
            ):
                what = f"{ann}: annotations[{ai}]"
                box = _key(a, "box", what)
                iid = int(_key(a, "instance_id", what))
                lwh = [float(_key(box, k, f"{what}.box")) for k in ("length", "width", "height")]
                pose = ref_pose @ dgp_pose_to_matrix(_key(box, "pose", f"{what}.box"))
                raw_boxes.setdefault(iid, {})[fi] = (pose, lwh, int(_key(a, "class_id", what)))

    # -- instances and tracks: every box instance is a track ------------------------------------------
    classes: dict[int, str] = {}
    onto_key = meta.get("ontologies", {}).get(_BOX3D)
    if raw_boxes:
        if onto_key is None:
            raise ValueError(f"DGP {scene_json.name}: ontologies: missing key {_BOX3D!r} (3D boxes)")
        onto = _read_json(files(f"ontology/{onto_key}.json", "ontologies"), "ontology")
        classes = {
            int(_key(it, "id", "ontology item")): _class_slug(str(_key(it, "name", "ontology item")))
            for it in _key(onto, "items", "ontology")
        }
    boxes = {
        iid: {
            fi: BoxObservation(pose, np.asarray(lwh), classes.get(cid, "unknown"))
            for fi, (pose, lwh, cid) in per_frame.items()
        }
        for iid, per_frame in raw_boxes.items()
    }
    track_names = {iid: f"{next(iter(b.values())).class_name}_{iid}" for iid, b in boxes.items()}
    instances, tracks = build_instances(
        boxes, track_names, len(frames), rigid=lambda _: True, min_motion_m=None
    )

    def read_lidar(frame: int, path: Path) -> LidarFrame:
        sensor_to_world = lidar_to_world[frame]
        npz_headers(path)  # a clear error for a file that is not an .npz (0 bytes, truncated)
        try:
            with np.load(path) as z:
                if "data" not in z:
                    raise ValueError(f"DGP point cloud {path}: missing key 'data'")
                raw = np.asarray(z["data"], dtype=np.float64)
        except ValueError as e:
            if str(path) in str(e):
                raise
            raise ValueError(f"DGP point cloud {path}: corrupt archive ({type(e).__name__}: {e})") from None
        except Exception as e:  # zlib.error, BadZipFile (a CRC-32 mismatch), EOFError on a corrupt member
            raise ValueError(f"DGP point cloud {path}: corrupt archive ({type(e).__name__}: {e})") from None
        if raw.ndim != 2 or raw.shape[1] < 3:
            raise ValueError(f"DGP point cloud {path}: expected (N, >=3) X, Y, Z, ..., got {raw.shape}")
        check_lidar_points(
            torch.from_numpy(raw[:, :3]), torch.zeros(3, dtype=torch.float64), f"DGP point cloud {path}"
        )
        world = raw[:, :3] @ sensor_to_world[:3, :3].T + sensor_to_world[:3, 3]
        return labelled_lidar(world, sensor_to_world[:3, 3], boxes, frame)

    files.warn()
    return assemble_scene(
        f"DGP scene {scene_dir}",
        name=scene_dir.name,
        root=scene_dir,
        cameras_info=cams,
        frames=frames,
        views=views,
        instances=instances,
        tracks=tracks,
        test_frames=sorted(int(f) for f in test_frames),
        scale=scale,
        read_lidar=read_lidar,
        image_loader=file_image_loader(undistort, "DGP"),
        check_files=check_files,
        validate=validate,
    )
