"""The benchmark scene format: ``scene.json`` beside ``images/``, ``depth/``, ``instances/``, ``lidar/``.

The format is described in ``../shared/data/README.md``; :func:`load_scene` reads it into a
:class:`~vadgs.data.scene.Scene`. Loading validates the whole ``scene.json`` and checks that every
referenced file exists before returning (and, by default, the files' headers: see
:mod:`vadgs.data.checks`), so a scene is never half-loaded silently.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from vadgs.checks import check_finite, check_intrinsics
from vadgs.data._json import DatasetFiles, read_json, require_key
from vadgs.data.assemble import assemble_scene, check_scale, check_validate_level
from vadgs.data.checks import check_rigid, check_split
from vadgs.data.scene import CameraInfo, FrameInfo, InstanceInfo, Scene, Track, ViewInfo, read_lidar_npz
from vadgs.geometry.camera import scale_intrinsics

__all__ = ["load_scene", "novel_view_group"]


def _int(value: object, what: str) -> int:
    """An integer field of scene.json (an int, or a float / string holding one)."""
    if isinstance(value, bool):
        raise ValueError(f"scene.json: {what}: expected an integer, got {value!r}")
    if isinstance(value, int):
        return value
    if isinstance(value, float) and value.is_integer():
        return int(value)
    if isinstance(value, str):
        try:
            return int(value)
        except ValueError:
            pass
    raise ValueError(f"scene.json: {what}: expected an integer, got {value!r}")


def _float(value: object, what: str) -> float:
    if isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value):
        return float(value)
    raise ValueError(f"scene.json: {what}: expected a finite number, got {value!r}")


def _str(value: object, what: str) -> str:
    if isinstance(value, str) and value:
        return value
    raise ValueError(f"scene.json: {what}: expected a non-empty string, got {value!r}")


def _bool(value: object, what: str) -> bool:
    if isinstance(value, bool):
        return value
    raise ValueError(f"scene.json: {what}: expected true or false, got {value!r}")


def _pose(value: object, what: str) -> torch.Tensor:
    """A rigid 4x4 transform of scene.json (see :func:`~vadgs.data.checks.check_rigid`)."""
    t = _matrix(value, (4, 4), what)
    check_rigid(t, f"scene.json: {what}")
    return t


def _frame_list(value: object, what: str) -> list[int]:
    if not isinstance(value, list):
        raise ValueError(f"scene.json: {what}: expected a list of frame indices, got {value!r}")
    return [_int(f, f"{what}[{i}]") for i, f in enumerate(value)]


def _matrix(value: object, shape: tuple[int, ...], what: str) -> torch.Tensor:
    try:
        t = torch.tensor(value, dtype=torch.float64)
    except (TypeError, ValueError):
        raise ValueError(f"scene.json: {what}: expected a {shape} matrix of numbers, got {value!r}") from None
    if tuple(t.shape) != shape:
        raise ValueError(f"scene.json: {what}: expected shape {shape}, got {tuple(t.shape)}")
    check_finite(t, f"scene.json: {what}")
    return t.float()


def _get(d: dict, key: str, what: str) -> Any:
    return require_key(d, key, f"scene.json: {what}")


def novel_view_group(shift_ego_m: Sequence[float]) -> str:
    """Group name of a novel view from its ego-frame shift: ``"shift+2.0"`` for a lateral ``(0, 2, 0)``.

    Any other shift is named by its three components, ``"shift+1.0,+0.0,+0.5"``.

    Example:
        >>> novel_view_group([0.0, -2.0, 0.0]), novel_view_group([1, 0, 0.5])
        ('shift-2.0', 'shift+1.0,+0.0,+0.5')
    """
    x, y, z = (float(c) for c in shift_ego_m)
    if x == 0.0 and z == 0.0:
        return f"shift{y:+.1f}"
    return f"shift{x:+.1f},{y:+.1f},{z:+.1f}"


def _novel_views(
    meta: dict, root: DatasetFiles, cameras: dict[str, CameraInfo], frames: dict[int, FrameInfo], start: int
) -> list[ViewInfo]:
    """The ``novel_views`` entries of ``scene.json`` as :class:`ViewInfo` (indices from ``start``)."""
    entries = meta.get("novel_views", [])
    if not isinstance(entries, list):
        raise ValueError("scene.json: novel_views: expected a list")
    views = []
    for ni, nm in enumerate(entries):
        what = f"novel_views[{ni}]"
        frame = int(_get(nm, "frame", what))
        if frame not in frames:
            raise ValueError(f"scene.json: {what}.frame: no frame {frame} in the scene")
        cam = str(_get(nm, "camera", what))
        if cam not in cameras:
            raise ValueError(f"scene.json: {what}.camera: unknown camera {cam!r}, have {list(cameras)}")
        c2w = _matrix(_get(nm, "cam_to_world", what), (4, 4), f"{what}.cam_to_world")
        if "group" in nm:
            group = str(nm["group"])
        else:
            shift = _get(nm, "shift_ego_m", what)
            if not (isinstance(shift, list) and len(shift) == 3):
                raise ValueError(f"scene.json: {what}.shift_ego_m: expected 3 numbers, got {shift!r}")
            group = novel_view_group(shift)
        files = {
            k: root(_str(nm[k], f"{what}.{k}"), f"{what}.{k}") if nm.get(k) else None
            for k in ("image", "depth", "instances")
        }
        if files["image"] is None:
            raise ValueError(f"scene.json: {what}: missing key 'image'")
        views.append(ViewInfo(start + ni, frame, cam, frames[frame].timestamp, c2w, **files, group=group))
    return views


def load_scene(
    path: str | Path,
    scale: float = 1.0,
    check_files: bool = True,
    validate: str = "headers",
    allow_outside: bool | None = None,
) -> Scene:
    """Load a scene in the benchmark format (``scene.json`` and its files).

    Args:
        path: the scene folder (or its ``scene.json``).
        scale: resolution factor; images are resized on load and intrinsics rescaled
            (e.g. ``0.5`` for 240×144 from 480×288).
        check_files: verify that every referenced file exists before returning.
        validate: content checks of the files (:func:`~vadgs.data.validate_scene`):
            ``"headers"`` (default: image sizes and decodable headers, ``.npz`` keys, shapes and
            dtypes, a non-empty LiDAR total, the test views' depth decoded), ``"full"`` (decode
            and check every file, as ``vadgs check --full``) or ``"none"``. The metadata
            (field types, ``K``, rigid poses, the split) is always checked.
        allow_outside: read files that ``scene.json`` names outside the scene folder (an
            absolute path or one with ``..``), which are refused otherwise; files that leave the
            folder only through a symlink are read with a warning naming them unless this is
            True. None (default): the environment variable ``VADGS_ALLOW_OUTSIDE_SCENE``.

    Returns:
        The :class:`Scene`, with per-view data loaded lazily. ``novel_views`` entries of
        ``scene.json`` become views after the recorded ones (:attr:`Scene.novel_views`).

    Raises:
        FileNotFoundError: if ``scene.json`` or a referenced file is missing.
        ValueError: if ``scene.json`` is malformed (the message names the entry: a field of the
            wrong type, a singular ``K``, a pose that is not rigid, a duplicate or unknown split
            frame) or a file's content is wrong (the message names the file, the expected and
            the actual: an image of another size, a corrupt PNG or ``.npz``, no LiDAR points).

    Example:
        >>> from vadgs.data import sample_scene_path
        >>> scene = load_scene(sample_scene_path())
        >>> scene.num_views, scene.camera_names
        (24, ['front', 'front_left', 'front_right'])
        >>> scene.load_images([0]).shape
        torch.Size([1, 3, 144, 240])
    """
    path = Path(path)
    root = path.parent if path.name == "scene.json" else path
    meta_path = root / "scene.json"
    if not meta_path.is_file():
        raise FileNotFoundError(f"no scene.json in {root}")
    meta = read_json(meta_path, "scene.json")
    files_of = DatasetFiles(root, allow_outside)
    check_scale(scale)
    check_validate_level(validate)

    cams_meta = _get(meta, "cameras", "top level")
    if not isinstance(cams_meta, dict) or not cams_meta:
        raise ValueError("scene.json: cameras: expected a non-empty object")
    cameras: dict[str, CameraInfo] = {}
    for name, c in cams_meta.items():
        w = _int(_get(c, "width", f"cameras.{name}"), f"cameras.{name}.width")
        h = _int(_get(c, "height", f"cameras.{name}"), f"cameras.{name}.height")
        if w <= 0 or h <= 0:
            raise ValueError(f"scene.json: cameras.{name}: expected positive width and height, got {w}x{h}")
        K = _matrix(_get(c, "K", f"cameras.{name}"), (3, 3), f"cameras.{name}.K")
        check_intrinsics(K, f"scene.json: cameras.{name}.K", pinhole=True)
        size = (round(h * scale), round(w * scale))
        if scale != 1.0:
            K = scale_intrinsics(K, size[1] / w)
        c2e = _pose(c["cam_to_ego"], f"cameras.{name}.cam_to_ego") if "cam_to_ego" in c else None
        cameras[name] = CameraInfo(name, K, size, c2e)

    frames: list[FrameInfo] = []
    views: list[ViewInfo] = []
    frames_meta = _get(meta, "frames", "top level")
    if not isinstance(frames_meta, list) or not frames_meta:
        raise ValueError("scene.json: frames: expected a non-empty list")
    for fi, fm in enumerate(frames_meta):
        what = f"frames[{fi}]"
        index = _int(_get(fm, "index", what), f"{what}.index")
        ts = _float(fm.get("timestamp", index), f"{what}.timestamp")
        e2w = _pose(fm["ego_to_world"], f"{what}.ego_to_world") if "ego_to_world" in fm else None
        ids = []
        vms = _get(fm, "views", what)
        if not isinstance(vms, list):
            raise ValueError(f"scene.json: {what}.views: expected a list")
        seen: dict[str, int] = {}
        for vi, vm in enumerate(vms):
            vwhat = f"{what}.views[{vi}]"
            cam = _str(_get(vm, "camera", vwhat), f"{vwhat}.camera")
            if cam not in cameras:
                raise ValueError(f"scene.json: {vwhat}.camera: unknown camera {cam!r}, have {list(cameras)}")
            if cam in seen:
                raise ValueError(
                    f"scene.json: {vwhat}.camera: camera {cam!r} already has a view in this frame "
                    f"({what}.views[{seen[cam]}]); expected one view per camera and frame"
                )
            seen[cam] = vi
            c2w = _pose(_get(vm, "cam_to_world", vwhat), f"{vwhat}.cam_to_world")
            files = {
                k: files_of(_str(vm[k], f"{vwhat}.{k}"), f"{vwhat}.{k}") if vm.get(k) else None
                for k in ("image", "depth", "instances")
            }
            if files["image"] is None:
                raise ValueError(f"scene.json: {vwhat}: missing key 'image'")
            views.append(
                ViewInfo(len(views), index, cam, ts, c2w, files["image"], files["depth"], files["instances"])
            )
            ids.append(len(views) - 1)
        lidar = files_of(_str(fm["lidar"], f"{what}.lidar"), f"{what}.lidar") if fm.get("lidar") else None
        frames.append(FrameInfo(index, ts, e2w, tuple(ids), lidar))

    views += _novel_views(meta, files_of, cameras, {f.index: f for f in frames}, len(views))

    instances = {}
    inst_meta = meta.get("instances", [])
    if not isinstance(inst_meta, list):
        raise ValueError(f"scene.json: instances: expected a list, got {type(inst_meta).__name__}")
    for ii, im in enumerate(inst_meta):
        iid = _int(_get(im, "id", f"instances[{ii}]"), f"instances[{ii}].id")
        instances[iid] = InstanceInfo(
            iid,
            str(im.get("name", iid)),
            _str(im.get("class", "unknown"), f"instances[{ii}].class"),
            _bool(im.get("dynamic", False), f"instances[{ii}].dynamic"),
        )

    frame_pos = {f.index: i for i, f in enumerate(frames)}
    tracks = {}
    for ti, tm in enumerate(meta.get("tracks", [])):
        what = f"tracks[{ti}]"
        tid = _int(_get(tm, "id", what), f"{what}.id")
        poses = torch.eye(4).repeat(len(frames), 1, 1)
        valid = torch.zeros(len(frames), dtype=torch.bool)
        o2w = _get(tm, "object_to_world", what)
        if not isinstance(o2w, dict):
            raise ValueError(
                f"scene.json: {what}.object_to_world: expected an object (frame -> 4x4), got {o2w!r}"
            )
        for key, mat in o2w.items():
            fk = _int(key, f"{what}.object_to_world key")
            if fk in frame_pos:
                poses[frame_pos[fk]] = _pose(mat, f"{what}.object_to_world[{key}]")
                valid[frame_pos[fk]] = True
        lwh = _matrix(tm.get("size_lwh", [0.0, 0.0, 0.0]), (3,), f"{what}.size_lwh")
        tracks[tid] = Track(
            tid,
            str(tm.get("class", "car")),
            lwh,
            poses,
            valid,
            files_of(_str(tm["mesh"], f"{what}.mesh"), f"{what}.mesh") if tm.get("mesh") else None,
        )

    split = meta.get("split", {})
    if not isinstance(split, dict):
        raise ValueError(f"scene.json: split: expected an object, got {split!r}")
    all_frames = [f.index for f in frames]
    if len(set(all_frames)) != len(all_frames):
        check_split(all_frames, all_frames, "scene.json: frames[].index")
    test_frames = _frame_list(split.get("test_frames", []), "split.test_frames")
    train_frames = _frame_list(
        split.get("train_frames", [f for f in all_frames if f not in test_frames]), "split.train_frames"
    )
    check_split(test_frames, all_frames, "scene.json: split.test_frames")
    check_split(train_frames, all_frames, "scene.json: split.train_frames")

    files_of.warn()
    return assemble_scene(
        f"scene {root}",
        name=str(meta.get("name", root.name)),
        root=root,
        cameras_info=cameras,
        frames=frames,
        views=views,
        instances=instances,
        tracks=tracks,
        train_frames=train_frames,
        test_frames=test_frames,
        scale=scale,
        read_lidar=lambda frame, path: read_lidar_npz(path),
        check_files=check_files,
        validate=validate,
    )
