"""The steps every loader shares; the last one checks the files, wires the LiDAR, builds the Scene.

Each reader (:func:`~vadgs.data.load_scene`, :func:`~vadgs.data.load_dgp`,
:func:`~vadgs.data.load_nuscenes`, :func:`~vadgs.data.load_waymo`, :func:`~vadgs.data.load_colmap`)
checks its arguments (:func:`check_scale`, :func:`check_validate_level`), parses its format into
cameras (:func:`pinhole_camera` for a camera with lens distortion), frames and views, and hands
them to :func:`assemble_scene`, so that a bad argument, a missing file, a frame without LiDAR and
a failed content check read the same whatever the format.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from vadgs.checks import check_finite
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
    read_rgb,
)
from vadgs.data.undistort import ImageUndistorter
from vadgs.geometry.camera import scale_intrinsics

__all__ = [
    "MAX_IMAGE_PIXELS",
    "VALIDATE_LEVELS",
    "assemble_scene",
    "check_scale",
    "check_scaled_sizes",
    "check_validate_level",
    "file_image_loader",
    "pinhole_camera",
]

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


def check_scale(scale: float) -> None:
    """Raise a :class:`ValueError` unless ``scale`` (a loader's resolution factor) is a positive number.

    Example:
        >>> check_scale(0)
        Traceback (most recent call last):
        ...
        ValueError: scale: expected a positive number, got 0
    """
    if not (isinstance(scale, (int, float)) and scale > 0):
        raise ValueError(f"scale: expected a positive number, got {scale!r}")


#: Largest image a loader makes (pixels, after ``scale``): 64 Mpx, 768 MB as float32 RGB.
MAX_IMAGE_PIXELS = 1 << 26


def check_scaled_sizes(cameras_info: dict[str, CameraInfo], scale: float) -> None:
    """Raise a :class:`ValueError` naming ``scale`` when a camera's scaled image is empty or huge.

    Every camera's ``image_size`` (already scaled) must be at least 1x1 and at most
    :data:`MAX_IMAGE_PIXELS` pixels, so that ``scale=1e6`` fails at load with the sizes instead of
    an allocation error of petabytes later.

    Example:
        >>> check_scaled_sizes({"cam": CameraInfo("cam", torch.eye(3), (9000, 9000))}, 100)
        Traceback (most recent call last):
        ...
        ValueError: scale: 100 makes camera 'cam' 9000x9000 pixels; expected at most 67108864 pixels per image
    """
    for name, info in cameras_info.items():
        h, w = info.image_size
        if h < 1 or w < 1:
            raise ValueError(f"scale: {scale:g} makes camera {name!r} {w}x{h} pixels; expected at least 1x1")
        if h * w > MAX_IMAGE_PIXELS:
            raise ValueError(
                f"scale: {scale:g} makes camera {name!r} {w}x{h} pixels; expected at most "
                f"{MAX_IMAGE_PIXELS} pixels per image"
            )


def pinhole_camera(
    name: str,
    raw_K: torch.Tensor,
    distortion: torch.Tensor,
    image_size: tuple[int, int],
    scale: float,
    cam_to_ego: np.ndarray,
    what: str,
) -> tuple[CameraInfo, ImageUndistorter]:
    """A camera of raw images with OpenCV lens distortion, as the pinhole camera of its undistorted images.

    ``K`` is the undistorted images' (:class:`~vadgs.data.undistort.ImageUndistorter`; ``raw_K``
    itself without distortion), rescaled by ``scale`` in float64, then stored as float32.

    Args:
        name: the camera name.
        raw_K: ``(3, 3)`` float64 intrinsics of the raw images (pixel centres at integers).
        distortion: OpenCV coefficients (``k1, k2, p1, p2[, k3, ...]``).
        image_size: ``(H, W)`` of the raw images.
        scale: the loader's resolution factor.
        cam_to_ego: ``(4, 4)`` float64 camera-to-ego transform.
        what: the camera as the messages name it (e.g. ``"DGP calibration.intrinsics[CAMERA_01]"``).

    Returns:
        ``(camera, undistorter)``; ``undistorter.distorted`` says whether images need it.

    Raises:
        ValueError: ``"<what>: ..."`` if the coefficients or ``K`` are invalid or not finite.

    Example:
        >>> K = torch.tensor([[100.0, 0, 49.5], [0, 100.0, 29.5], [0, 0, 1]], dtype=torch.float64)
        >>> cam, und = pinhole_camera("c", K, torch.zeros(4), (60, 100), 0.5, np.eye(4), "c")
        >>> cam.image_size, cam.K[0].tolist(), und.distorted
        ((30, 50), [50.0, 0.0, 24.5], False)
    """
    h, w = image_size
    try:
        und = ImageUndistorter(raw_K, distortion, (h, w))
    except ValueError as e:
        raise ValueError(f"{what}: {e}") from None
    K = und.K
    size = (round(h * scale), round(w * scale))
    if scale != 1.0:
        K = scale_intrinsics(K, size[1] / w)
    K32, c2e = torch.from_numpy(K.numpy()), torch.from_numpy(np.asarray(cam_to_ego, dtype=np.float64))
    check_finite(K32, f"{what}: K")
    check_finite(c2e, f"{what}: cam_to_ego")
    return CameraInfo(name, K32.float(), size, c2e.float()), und


def file_image_loader(
    undistort: dict[str, ImageUndistorter], what: str
) -> Callable[[ViewInfo], torch.Tensor] | None:
    """``Scene.image_loader`` reading each view's image file, undistorted for the distorted cameras.

    Args:
        undistort: camera name → its undistorter; cameras not in it (or not distorted) are read
            as they are.
        what: the format as the messages name it (e.g. ``"DGP"``).

    Returns:
        The loader, or None when no camera is distorted (the scene then reads the files itself).

    Raises:
        ValueError: from the loader, ``"<what> image <path>: size WxH differs from the camera's
            wxh"``.
    """
    undistort = {n: u for n, u in undistort.items() if u.distorted}
    if not undistort:
        return None

    def image_loader(view: ViewInfo) -> torch.Tensor:
        if view.image is None:
            raise ValueError(f"view {view.index}: expected an image file, got None")
        img = read_rgb(view.image)
        und = undistort.get(view.camera)
        if und is None:
            return img
        if tuple(img.shape[-2:]) != und.image_size:
            raise ValueError(
                f"{what} image {view.image}: size {img.shape[-1]}x{img.shape[-2]} differs from the "
                f"camera's {und.image_size[1]}x{und.image_size[0]}"
            )
        return und(img[None])[0].clamp(0.0, 1.0)

    return image_loader


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
    check_scaled_sizes(cameras_info, scale)
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
