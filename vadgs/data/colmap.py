"""COLMAP reconstructions (through pycolmap) as a :class:`~vadgs.data.scene.Scene` plus sparse points.

:func:`load_colmap` reads a sparse model (``cameras``, ``images``, ``points3D``, and in COLMAP 4
``rigs`` / ``frames``; binary or text) with :mod:`pycolmap` and converts it to vadgs conventions:

- **Pixel centres.** COLMAP puts the top-left *corner* of the image at ``(0, 0)``, so the centre of
  pixel ``(u, v)`` is at ``(u + 0.5, v + 0.5)``. vadgs puts pixel centres at integers
  (``docs/conventions.md``). Hence ``cx = cx_colmap - 0.5``, ``cy = cy_colmap - 0.5``, and every
  recorded 2D observation is shifted by ``-0.5`` as well.
- **Poses.** COLMAP's ``cam_from_world`` is vadgs's ``world_to_cam``; both use OpenCV axes
  (x right, y down, z forward), so no axis flip is needed. ``ViewInfo.cam_to_world`` is its inverse.
- **Cameras.** PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL and OPENCV are read as their pinhole
  part ``K``. When a model has non-zero distortion a :class:`UserWarning` says that it is ignored:
  undistort first (``colmap image_undistorter`` or :func:`pycolmap.undistort_images`), which
  writes a PINHOLE model. Other models (fisheye, ...) raise a :class:`ValueError`.
- **Frames.** Views are grouped by COLMAP 4 frame (images of one rig snapshot); a reconstruction
  without rigs has one frame per image. Frames are ordered by their first image's name, views
  within a frame by camera id. Images without a pose (unregistered) are skipped with a warning.
- **Points and the TRACK table.** :class:`ColmapPoints` holds the 3D points, their colours and
  reprojection errors and the TRACK table as flat COO arrays ``(point_idx, view_idx)``: one
  entry per observation, with ``view_idx`` the index in ``Scene.views``. This is what voxel
  visibility reasoning consumes (supplement, "Visibility Reasoning").

There is no LiDAR, no instance table and no tracks of moving objects in a COLMAP model.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from vadgs.checks import check_finite
from vadgs.data.scene import CameraInfo, FrameInfo, Scene, ViewInfo
from vadgs.data.validate import validate_scene
from vadgs.geometry.camera import invert_rigid, scale_intrinsics

__all__ = ["COLMAP_PIXEL_OFFSET", "ColmapPoints", "ColmapScene", "colmap_camera_to_K", "load_colmap"]

#: vadgs pixel coordinates = COLMAP pixel coordinates + this offset (pixel centres at integers).
COLMAP_PIXEL_OFFSET = -0.5

_PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
_DISTORTED_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV")


class ColmapPoints(NamedTuple):
    """The sparse points of a COLMAP model and their TRACK table.

    The track table is in coordinate (COO) form: observation ``t`` says that point
    ``point_idx[t]`` is seen in view ``view_idx[t]`` (an index into ``Scene.views``) at pixel
    ``uv[t]`` (vadgs pixel convention, at the scene's scale).

    Attributes:
        points: ``(P, 3)`` float32 world coordinates.
        colors: ``(P, 3)`` float32 RGB in ``[0, 1]``.
        errors: ``(P,)`` float32 mean reprojection error in pixels at full resolution as stored
            by COLMAP (``-1`` where COLMAP has none).
        point_ids: ``(P,)`` int64 COLMAP ``point3D_id`` of each point.
        point_idx: ``(T,)`` int64 index into ``points`` of each observation.
        view_idx: ``(T,)`` int64 index into ``Scene.views`` of each observation.
        uv: ``(T, 2)`` float32 observed pixel ``(x, y)`` of each observation.
    """

    points: torch.Tensor
    colors: torch.Tensor
    errors: torch.Tensor
    point_ids: torch.Tensor
    point_idx: torch.Tensor
    view_idx: torch.Tensor
    uv: torch.Tensor

    @property
    def point_views(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(point_idx, view_idx)``, as ``vadgs.geometry.voxelize(..., point_views=...)`` takes it."""
        return self.point_idx, self.view_idx


class ColmapScene(NamedTuple):
    """What :func:`load_colmap` returns: unpack as ``scene, points = load_colmap(...)``.

    Attributes:
        scene: the :class:`~vadgs.data.scene.Scene` (cameras, frames, views; no LiDAR).
        points: the sparse points and their TRACK table.
    """

    scene: Scene
    points: ColmapPoints


def colmap_camera_to_K(camera: object) -> tuple[torch.Tensor, tuple[int, int]]:
    """The vadgs intrinsics of a :class:`pycolmap.Camera`: its pinhole part, pixel centres at integers.

    Warns (:class:`UserWarning`) when the model has non-zero distortion, which is ignored.

    Args:
        camera: a ``pycolmap.Camera``.

    Returns:
        ``(K, (H, W))``: ``K (3, 3)`` float64 with ``c = c_colmap - 0.5``, and the image size.

    Raises:
        ValueError: for a camera model other than PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL,
            OPENCV.

    Example:
        >>> import pycolmap
        >>> cam = pycolmap.Camera.create_from_model_name(1, "PINHOLE", 100.0, 64, 48)
        >>> K, size = colmap_camera_to_K(cam)  # COLMAP's default centre (W/2, H/2)
        >>> K[0, 2].item(), K[1, 2].item(), size  # is the vadgs image centre ((W-1)/2, (H-1)/2)
        (31.5, 23.5, (48, 64))
    """
    model = camera.model.name
    if model not in _PINHOLE_MODELS + _DISTORTED_MODELS:
        raise ValueError(
            f"camera {camera.camera_id}: unsupported COLMAP camera model {model}; supported are "
            f"{list(_PINHOLE_MODELS + _DISTORTED_MODELS)} (undistort the images first)"
        )
    params = np.asarray(camera.params, dtype=np.float64)
    extra = params[list(camera.extra_params_idxs())] if model in _DISTORTED_MODELS else params[:0]
    if np.any(extra != 0):
        warnings.warn(
            f"COLMAP camera {camera.camera_id} is {model} with distortion "
            f"{dict(zip(camera.params_info.split(', ')[-len(extra) :], extra.tolist()))}: vadgs uses "
            "only its pinhole part and IGNORES the distortion; undistort the images first "
            "(pycolmap.undistort_images) for exact geometry",
            UserWarning,
            stacklevel=3,
        )
    K = torch.tensor(np.asarray(camera.calibration_matrix(), dtype=np.float64))
    K[0, 2] += COLMAP_PIXEL_OFFSET
    K[1, 2] += COLMAP_PIXEL_OFFSET
    return K, (int(camera.height), int(camera.width))


def _cam_from_world(image: object) -> np.ndarray:
    cfw = image.cam_from_world
    cfw = cfw() if callable(cfw) else cfw  # a method in pycolmap 4, a property before
    out = np.eye(4)
    out[:3, :4] = np.asarray(cfw.matrix(), dtype=np.float64)
    return out


def _find_images_dir(sparse_dir: Path) -> Path | None:
    for cand in (sparse_dir.parent.parent / "images", sparse_dir.parent / "images", sparse_dir / "images"):
        if cand.is_dir():
            return cand
    return None


def load_colmap(
    sparse_dir: str | Path,
    images_dir: str | Path | None = None,
    scale: float = 1.0,
    check_files: bool = True,
    validate: str = "headers",
) -> ColmapScene:
    """Load a COLMAP sparse reconstruction as a :class:`Scene` and its points with their tracks.

    See the module docstring for how COLMAP's conventions map to vadgs's (pixel offset ``-0.5``,
    ``cam_from_world`` → ``world_to_cam``, frames, the TRACK table).

    Args:
        sparse_dir: the model folder (``cameras.bin`` / ``.txt``, ``images``, ``points3D``), e.g.
            ``project/sparse/0``.
        images_dir: the folder the image names are relative to. When None, ``images/`` is looked
            for two levels, one level and zero levels above ``sparse_dir``; if none exists the
            views have no image path (their ``load_images`` raises ``FileNotFoundError``).
        scale: resolution factor: images are resized on load, intrinsics and the observations
            ``uv`` are rescaled (points stay in world units).
        check_files: when an images folder is known, verify that every registered image exists.
        validate: content checks (:func:`~vadgs.data.validate_scene`): ``"headers"`` (default:
            ``K``, rigid poses, image sizes from the file headers), ``"full"`` (decode
            every file) or ``"none"``; a failure raises a :class:`ValueError` naming the file.

    Returns:
        A :class:`ColmapScene` ``(scene, points)``. The scene has every registered image as a
        view, no LiDAR, no instances, no tracks, and every frame in ``train_frames``.

    Raises:
        FileNotFoundError: if ``sparse_dir`` holds no COLMAP model, ``images_dir`` is given but
            missing, or (with ``check_files``) a registered image is missing.
        ValueError: if ``scale`` is not positive, the model has no registered image, a pose is not
            finite, or a camera model is unsupported.

    Example:
        >>> import tempfile, numpy as np, pycolmap
        >>> rec = pycolmap.Reconstruction()
        >>> cam = pycolmap.Camera.create_from_model_name(1, "PINHOLE", 50.0, 64, 48)
        >>> rec.add_camera_with_trivial_rig(cam)
        >>> xyz = np.array([0.0, 0.0, 4.0])
        >>> img = pycolmap.Image(name="a.png", keypoints=np.array([[32.0, 24.0]]), camera_id=1, image_id=1)
        >>> rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d())
        >>> track = pycolmap.Track(); track.add_element(1, 0)
        >>> _ = rec.add_point3D(xyz, track, np.array([255, 0, 0], dtype=np.uint8))
        >>> d = tempfile.mkdtemp(); rec.write(d)
        >>> scene, points = load_colmap(d)
        >>> scene.num_views, points.points.tolist(), points.uv.tolist()
        (1, [[0.0, 0.0, 4.0]], [[31.5, 23.5]])
        >>> points.point_views
        (tensor([0]), tensor([0]))
    """
    import pycolmap  # imported lazily: only this loader needs it

    sparse_dir = Path(sparse_dir)
    if not (isinstance(scale, (int, float)) and scale > 0):
        raise ValueError(f"scale: expected a positive number, got {scale!r}")
    if validate not in ("none", "headers", "full"):
        raise ValueError(f"validate: expected 'none', 'headers' or 'full', got {validate!r}")
    if not any((sparse_dir / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
        raise FileNotFoundError(f"sparse_dir: no COLMAP model (cameras.bin or cameras.txt) in {sparse_dir}")
    try:
        rec = pycolmap.Reconstruction(str(sparse_dir))
    except Exception as e:  # pycolmap raises a bare RuntimeError / ValueError on corrupt files
        raise ValueError(f"sparse_dir: cannot read the COLMAP model in {sparse_dir}: {e}") from None

    if images_dir is not None:
        images_dir = Path(images_dir)
        if not images_dir.is_dir():
            raise FileNotFoundError(f"images_dir: no such folder {images_dir}")
    else:
        images_dir = _find_images_dir(sparse_dir)

    # -- cameras --------------------------------------------------------------------------------------
    images = sorted(rec.images.values(), key=lambda im: im.name)
    registered = [im for im in images if im.has_pose]
    if len(registered) < len(images):
        warnings.warn(
            f"{sparse_dir}: skipping {len(images) - len(registered)} unregistered image(s) "
            f"without a pose, e.g. {[im.name for im in images if not im.has_pose][:3]}",
            UserWarning,
            stacklevel=2,
        )
    if not registered:
        raise ValueError(f"sparse_dir: the COLMAP model in {sparse_dir} has no registered image")
    cam_ids = sorted({im.camera_id for im in registered})
    cam_name = {cid: f"camera_{cid}" for cid in cam_ids}
    cameras: dict[str, CameraInfo] = {}
    full_width: dict[str, int] = {}
    for cid in cam_ids:
        K, (h, w) = colmap_camera_to_K(rec.cameras[cid])
        size = (round(h * scale), round(w * scale))
        if scale != 1.0:
            K = scale_intrinsics(K, size[1] / w)
        cameras[cam_name[cid]] = CameraInfo(cam_name[cid], K.float(), size, None)
        full_width[cam_name[cid]] = w

    # -- frames and views -----------------------------------------------------------------------------
    groups: dict[int, list[object]] = {}
    for im in registered:
        key = int(im.frame_id) if im.has_frame_id() else -int(im.image_id) - 1
        groups.setdefault(key, []).append(im)
    ordered = sorted(groups.values(), key=lambda g: min(im.name for im in g))
    frames: list[FrameInfo] = []
    views: list[ViewInfo] = []
    view_of_image: dict[int, int] = {}
    for fi, group in enumerate(ordered):
        ids = []
        for im in sorted(group, key=lambda im: (im.camera_id, im.name)):
            w2c = torch.tensor(_cam_from_world(im))
            check_finite(w2c, f"{sparse_dir}: image {im.name!r} cam_from_world")
            path = images_dir / im.name if images_dir is not None else None
            view_of_image[int(im.image_id)] = len(views)
            views.append(
                ViewInfo(len(views), fi, cam_name[im.camera_id], float(fi), invert_rigid(w2c).float(), path)
            )
            ids.append(len(views) - 1)
        frames.append(FrameInfo(fi, float(fi), None, tuple(ids)))

    if images_dir is not None and check_files:
        missing = [str(v.image) for v in views if not v.image.is_file()]
        if missing:
            raise FileNotFoundError(
                f"images_dir {images_dir}: {len(missing)} registered image(s) missing, e.g. {missing[:3]}"
            )

    # -- points and the TRACK table -------------------------------------------------------------------
    pids = sorted(rec.point3D_ids()) if hasattr(rec, "point3D_ids") else sorted(rec.points3D)
    xyz = np.zeros((len(pids), 3))
    rgb = np.zeros((len(pids), 3))
    err = np.zeros(len(pids))
    p_idx, v_idx, uv = [], [], []
    for i, pid in enumerate(pids):
        p = rec.points3D[pid]
        xyz[i], rgb[i], err[i] = p.xyz, p.color, p.error
        for el in p.track.elements:
            v = view_of_image.get(int(el.image_id))
            if v is None:
                continue
            p_idx.append(i)
            v_idx.append(v)
            uv.append(rec.images[el.image_id].points2D[el.point2D_idx].xy)
    uv_t = torch.tensor(np.asarray(uv, dtype=np.float64).reshape(-1, 2)) + COLMAP_PIXEL_OFFSET
    if scale != 1.0 and len(v_idx):
        # per observation: the view's width at the scene's scale over its full width
        ratio = torch.tensor(
            [cameras[views[v].camera].image_size[1] / full_width[views[v].camera] for v in v_idx]
        )
        uv_t = (uv_t + 0.5) * ratio[:, None].double() - 0.5
    points = ColmapPoints(
        points=torch.tensor(xyz, dtype=torch.float32),
        colors=torch.tensor(rgb / 255.0, dtype=torch.float32),
        errors=torch.tensor(err, dtype=torch.float32),
        point_ids=torch.tensor(pids, dtype=torch.int64),
        point_idx=torch.tensor(p_idx, dtype=torch.int64),
        view_idx=torch.tensor(v_idx, dtype=torch.int64),
        uv=uv_t.float(),
    )
    scene = Scene(
        name=_project_name(sparse_dir),
        root=sparse_dir,
        cameras_info=cameras,
        frames=frames,
        views=views,
        train_frames=[f.index for f in frames],
        test_frames=[],
        scale=float(scale),
    )
    if check_files and validate != "none":
        validate_scene(scene, full=validate == "full").raise_if_errors()
    return ColmapScene(scene, points)


def _project_name(sparse_dir: Path) -> str:
    """``project`` for ``project/sparse/0``: skip the folders COLMAP names itself."""
    path = sparse_dir.resolve()
    while path.parent != path and (path.name.isdigit() or path.name == "sparse"):
        path = path.parent
    return path.name
