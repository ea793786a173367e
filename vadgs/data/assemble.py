"""The last step of every loader: check the referenced files, wire the LiDAR, build and check the Scene.

Each reader (:func:`~vadgs.data.load_scene`, :func:`~vadgs.data.load_dgp`,
:func:`~vadgs.data.load_nuscenes`, :func:`~vadgs.data.load_waymo`, :func:`~vadgs.data.load_colmap`)
parses its format into cameras, frames and views and hands them to :func:`assemble_scene`, so
that a missing file, a frame without LiDAR and a failed content check read the same whatever the
format.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import torch

from vadgs.data.checks import check_scene
from vadgs.data.scene import (
    CameraInfo,
    ColmapPoints,
    FrameInfo,
    InstanceInfo,
    LidarFrame,
    Scene,
    Track,
    ViewInfo,
)

__all__ = ["VALIDATE_LEVELS", "assemble_scene", "check_validate_level"]

#: the ``validate=`` levels of the loaders (see :func:`~vadgs.data.checks.check_scene`).
VALIDATE_LEVELS = ("none", "headers", "full")


def check_validate_level(validate: str) -> None:
    """Raise a :class:`ValueError` unless ``validate`` is one of :data:`VALIDATE_LEVELS`.

    Example:
        >>> check_validate_level("fast")
        Traceback (most recent call last):
        ...
        ValueError: validate: expected 'none', 'headers' or 'full', got 'fast'
    """
    if validate not in VALIDATE_LEVELS:
        raise ValueError(f"validate: expected 'none', 'headers' or 'full', got {validate!r}")


def _file_lidar_loader(
    frames: Sequence[FrameInfo], read: Callable[[int, Path], LidarFrame], what: str
) -> Callable[[int], LidarFrame] | None:
    """``Scene.lidar_loader`` over the frames' LiDAR files (None when no frame has one)."""
    paths = {f.index: f.lidar for f in frames if f.lidar is not None}
    if not paths:
        return None
    indices = [f.index for f in frames]

    def lidar_loader(frame: int) -> LidarFrame:
        if frame not in paths:
            why = ""
            if frame not in indices:
                why = f": the scene has no such frame (frames {min(indices)}..{max(indices)})"
            raise FileNotFoundError(f"{what}: no LiDAR for frame {frame}{why}")
        path = paths[frame]
        if not path.is_file():
            raise FileNotFoundError(f"{what}: missing file {path}")
        return read(frame, path)

    return lidar_loader


def assemble_scene(
    what: str,
    *,
    name: str,
    root: Path | None,
    cameras_info: dict[str, CameraInfo],
    frames: list[FrameInfo],
    views: list[ViewInfo],
    test_frames: Sequence[int],
    train_frames: Sequence[int] | None = None,
    scale: float = 1.0,
    instances: dict[int, InstanceInfo] | None = None,
    tracks: dict[int, Track] | None = None,
    read_lidar: Callable[[int, Path], LidarFrame] | None = None,
    lidar_loader: Callable[[int], LidarFrame] | None = None,
    image_loader: Callable[[ViewInfo], torch.Tensor] | None = None,
    sfm_points: ColmapPoints | None = None,
    check_files: bool = True,
    missing_noun: str = "referenced file(s)",
    validate: str = "none",
) -> Scene:
    """A :class:`~vadgs.data.scene.Scene` from a loader's parts, its files and content checked.

    In order: with ``check_files``, every image, depth and instance file of ``views`` and every
    LiDAR file of ``frames`` must exist; the LiDAR loader is ``read_lidar`` over the frames'
    ``lidar`` paths (or ``lidar_loader`` as given, for LiDAR that is not one file per frame); the
    scene is built; with ``check_files`` and ``validate`` other than ``"none"``,
    :func:`~vadgs.data.checks.check_scene` must find no problem.

    Args:
        what: the scene as the messages name it, e.g. ``"DGP scene /data/scene_02"``.
        name: :attr:`Scene.name <vadgs.data.scene.Scene>`.
        root: the folder it was loaded from (or None).
        cameras_info: camera name → :class:`~vadgs.data.scene.CameraInfo`.
        frames: the frames in order (``lidar`` the frame's LiDAR file, if any).
        views: the views, ``views[i].index == i``.
        test_frames: the held-out frame indices.
        train_frames: default: every frame not in ``test_frames``, in order.
        scale: the resolution factor applied at load time.
        instances: instance id → :class:`~vadgs.data.scene.InstanceInfo` (default none).
        tracks: instance id → :class:`~vadgs.data.scene.Track` (default none).
        read_lidar: ``(frame index, path) → LidarFrame``; called with existing files only.
        lidar_loader: ``frame index → LidarFrame``, when there are no per-frame files
            (exclusive with ``read_lidar``).
        check_files: verify that every referenced file exists (and run the content checks).
        image_loader: view → ``(3, H, W)`` image, for images that are not plain files.
        sfm_points: sparse SfM points (COLMAP scenes).
        missing_noun: what the missing files are called in the message.
        validate: ``"none"``, ``"headers"`` or ``"full"`` (see :mod:`vadgs.data.checks`).

    Returns:
        The scene.

    Raises:
        FileNotFoundError: ``"<what>: N referenced file(s) missing, e.g. [...]"``; from the LiDAR
            loader, ``"<what>: no LiDAR for frame F"`` or ``"<what>: missing file <path>"``.
        ValueError: if ``validate`` is unknown, both LiDAR arguments are given, or a content
            check fails (the message names the file).

    Example:
        >>> cams = {"cam": CameraInfo("cam", torch.eye(3), (2, 2))}
        >>> frames = [FrameInfo(i, float(i), None, (i,)) for i in range(3)]
        >>> views = [ViewInfo(i, i, "cam", float(i), torch.eye(4)) for i in range(3)]
        >>> s = assemble_scene("demo", name="demo", root=None, cameras_info=cams, frames=frames,
        ...                    views=views, test_frames=[1])
        >>> s.train_frames, s.test_frames, s.lidar_loader is None
        ([0, 2], [1], True)
    """
    check_validate_level(validate)
    if read_lidar is not None and lidar_loader is not None:
        raise ValueError("assemble_scene: pass read_lidar or lidar_loader, not both")
    if check_files:
        missing = [
            p for v in views for p in (v.image, v.depth, v.instances) if p is not None and not p.is_file()
        ] + [f.lidar for f in frames if f.lidar is not None and not f.lidar.is_file()]
        if missing:
            raise FileNotFoundError(
                f"{what}: {len(missing)} {missing_noun} missing, e.g. {[str(m) for m in missing[:3]]}"
            )
    if read_lidar is not None:
        lidar_loader = _file_lidar_loader(frames, read_lidar, what)
    test = list(test_frames)
    if train_frames is None:
        held = set(test)
        train_frames = [f.index for f in frames if f.index not in held]
    scene = Scene(
        name=name,
        root=root,
        cameras_info=cameras_info,
        frames=frames,
        views=views,
        instances=instances if instances is not None else {},
        tracks=tracks if tracks is not None else {},
        train_frames=list(train_frames),
        test_frames=test,
        scale=float(scale),
        lidar_loader=lidar_loader,
        image_loader=image_loader,
        sfm_points=sfm_points,
    )
    if check_files and validate != "none":
        check_scene(scene, full=validate == "full").raise_if_errors()
    return scene
