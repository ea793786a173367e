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

- **Hold-out.** ``test_every=N`` puts every ``N``-th frame (position ``% N == 0`` in name order;
  one image per frame without rigs: the 3DGS / Mip-NeRF 360 convention "every 8th image") in
  ``test_frames``.
- **Normalisation.** ``normalize=True`` maps the reconstruction by the similarity of
  :func:`colmap_normalization` (cameras centred, mean camera up on ``+z``, median
  camera-to-point depth 10 units; :mod:`vadgs.data.normalize`), so that vadgs's settings in metres
  fit an SfM scene of arbitrary scale; a recorded ``(4, 4)`` transform re-applies it exactly.

There is no LiDAR, no instance table and no tracks of moving objects in a COLMAP model; the scene
carries the points as :attr:`Scene.sfm_points <vadgs.data.scene.Scene>` instead.

Around the loader: :func:`~vadgs.data.colmap_model.find_colmap_model` recognises a model or
project folder and :func:`~vadgs.data.colmap_model.distorted_cameras` names the cameras that are
not pinhole (the model folders and cameras: :mod:`vadgs.data.colmap_model`);
:func:`~vadgs.data.colmap_project.undistort_colmap` (pycolmap's undistorter) gives a pinhole model
and :func:`~vadgs.data.colmap_project.open_colmap_project` does all of it for ``vadgs train``
(:mod:`vadgs.data.colmap_project`).
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import torch

from vadgs.checks import check_finite
from vadgs.data.assemble import assemble_scene, check_scale, check_validate_level
from vadgs.data.colmap_model import (
    COLMAP_PIXEL_OFFSET,
    colmap_camera_to_K,
    colmap_world_to_cam,
    read_colmap_model,
)
from vadgs.data.images import exif_orientation
from vadgs.data.normalize import normalization_transform, transform_cam_to_world, transform_points
from vadgs.data.scene import CameraInfo, ColmapPoints, FrameInfo, Scene, ViewInfo
from vadgs.geometry.camera import invert_rigid, scale_intrinsics

if TYPE_CHECKING:  # imported where used: pycolmap is slow to import
    import pycolmap

__all__ = [
    "ColmapScene",
    "colmap_normalization",
    "colmap_project_name",
    "find_images_dir",
    "load_colmap",
    "transform_colmap",
    "warn_exif_rotated",
]


class ColmapScene(NamedTuple):
    """What :func:`load_colmap` returns: unpack as ``scene, points = load_colmap(...)``.

    Attributes:
        scene: the :class:`~vadgs.data.scene.Scene` (cameras, frames, views; no LiDAR).
        points: the sparse points and their TRACK table.
    """

    scene: Scene
    points: ColmapPoints


def find_images_dir(sparse_dir: Path) -> Path | None:
    """The ``images`` folder of a COLMAP project, looked for beside and above ``sparse_dir``; or None."""
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
    test_every: int = 0,
    normalize: bool | torch.Tensor = False,
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
        test_every: hold out every ``test_every``-th frame (positions ``0, N, 2N, ...`` in name
            order) as ``test_frames``; ``0`` (default): every frame trains.
        normalize: ``False`` (default): COLMAP's own frame and scale; ``True``: apply
            :func:`colmap_normalization` (centred, up on ``+z``, median depth 10); a ``(4, 4)``
            similarity (tensor or nested list, e.g. the one a run recorded): apply that one.

    Returns:
        A :class:`ColmapScene` ``(scene, points)``. The scene has every registered image as a
        view, no LiDAR, no instances, no tracks, the split of ``test_every``, and the points as
        ``scene.sfm_points``.

    Raises:
        FileNotFoundError: if ``sparse_dir`` holds no COLMAP model, ``images_dir`` is given but
            missing, or (with ``check_files``) a registered image is missing.
        ValueError: if ``scale`` is not positive, ``test_every`` negative, ``normalize`` not a
            ``(4, 4)`` similarity, the model has no registered image, a pose is not finite, or a
            camera model is unsupported.

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
    sparse_dir = Path(sparse_dir)
    check_scale(scale)
    check_validate_level(validate)
    if not (isinstance(test_every, int) and test_every >= 0):
        raise ValueError(f"test_every: expected an integer >= 0 (0 = no test split), got {test_every!r}")
    transform = None if isinstance(normalize, bool) else _check_similarity(normalize)
    if not any((sparse_dir / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
        raise FileNotFoundError(f"sparse_dir: no COLMAP model (cameras.bin or cameras.txt) in {sparse_dir}")
    rec = read_colmap_model(sparse_dir, "sparse_dir")

    if images_dir is not None:
        images_dir = Path(images_dir)
        if not images_dir.is_dir():
            raise FileNotFoundError(f"images_dir: no such folder {images_dir}")
    else:
        images_dir = find_images_dir(sparse_dir)

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
    groups: dict[int, list[pycolmap.Image]] = {}
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
            w2c = torch.tensor(colmap_world_to_cam(im))
            check_finite(w2c, f"{sparse_dir}: image {im.name!r} cam_from_world")
            path = images_dir / im.name if images_dir is not None else None
            view_of_image[int(im.image_id)] = len(views)
            views.append(
                ViewInfo(len(views), fi, cam_name[im.camera_id], float(fi), invert_rigid(w2c).float(), path)
            )
            ids.append(len(views) - 1)
        frames.append(FrameInfo(fi, float(fi), None, tuple(ids)))

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
    scene = assemble_scene(
        f"images_dir {images_dir}",
        name=colmap_project_name(sparse_dir),
        root=sparse_dir,
        cameras_info=cameras,
        frames=frames,
        views=views,
        test_frames=[f.index for f in frames if test_every and f.index % test_every == 0],
        scale=scale,
        sfm_points=points,
        check_files=check_files,
        missing_noun="registered image(s)",
        validate=validate,
    )
    if check_files and images_dir is not None:
        warn_exif_rotated(images_dir, [im.name for im in registered])
    out = ColmapScene(scene, points)
    if normalize is True:
        transform = colmap_normalization(out)
    return transform_colmap(out, transform) if transform is not None else out


def warn_exif_rotated(images_dir: str | Path, names: list[str], stacklevel: int = 3) -> int:
    """Warn when images of a COLMAP project carry an EXIF rotation (COLMAP ignores it); how many do.

    COLMAP fits each camera to the stored pixel grid, and vadgs reads that grid too
    (:func:`vadgs.data.images.read_image`), so such a project is consistent but sideways: the up
    direction, videos and exports are rolled. ``vadgs sfm`` writes its images upright, so its
    projects never warn.
    """
    turned = {}
    for name in names:
        path = Path(images_dir) / name
        if path.is_file() and (o := exif_orientation(path)) != 1:
            turned[name] = o
    if turned:
        first = next(iter(turned))
        warnings.warn(
            f"{images_dir}: {len(turned)} of {len(names)} image(s) carry an EXIF orientation tag that "
            f"COLMAP ignores (e.g. {first}: orientation {turned[first]}); vadgs reads them as stored, as "
            "their cameras were fitted, so the up direction, renders and exports follow the stored "
            "(sideways) pixels; for upright results rerun `vadgs sfm` on the original photos (it turns "
            "them upright), or rotate their pixels and drop the tags before running COLMAP",
            UserWarning,
            stacklevel=stacklevel,
        )
    return len(turned)


def colmap_project_name(sparse_dir: Path) -> str:
    """``project`` for ``project/sparse/0``: skip the folders COLMAP names itself."""
    path = sparse_dir.resolve()
    while path.parent != path and (path.name.isdigit() or path.name == "sparse"):
        path = path.parent
    return path.name


# ---------------------------------------------------------------------------------------------------
# normalisation


def _check_similarity(transform: object) -> torch.Tensor:
    """A ``(4, 4)`` similarity ``[[s R, t], [0, 1]]`` as float64, or a ``ValueError`` naming ``normalize``."""
    try:
        T = torch.as_tensor(transform, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"normalize: expected a bool or a (4, 4) similarity, got {transform!r}") from None
    if T.shape != (4, 4) or not bool(torch.isfinite(T).all()):
        raise ValueError(f"normalize: expected a finite (4, 4) similarity, got shape {tuple(T.shape)}")
    A = T[:3, :3]
    s = float(A.det().abs() ** (1 / 3))
    eye = torch.eye(3, dtype=torch.float64)
    if s <= 0 or not torch.allclose(A @ A.T / s**2, eye, atol=1e-6) or float(A.det()) < 0:
        raise ValueError(
            "normalize: the (4, 4) matrix is not a similarity [[s R, t], [0, 1]] with a rotation R"
        )
    if not torch.allclose(T[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)):
        raise ValueError(f"normalize: expected the last row (0, 0, 0, 1), got {T[3].tolist()}")
    return T


def colmap_normalization(colmap: ColmapScene, target_depth: float = 10.0) -> torch.Tensor:
    """The similarity that normalises a COLMAP scene (:func:`vadgs.data.normalize.normalization_transform`).

    Cameras centred on their mean, their mean up direction (``-y`` of OpenCV axes) rotated onto
    ``+z``, and the median camera-to-point depth of the TRACK table scaled to ``target_depth``.

    Args:
        colmap: what :func:`load_colmap` returned (in COLMAP's frame).
        target_depth: the median depth after the transform.

    Returns:
        ``(4, 4)`` float64 similarity (apply it with :func:`transform_colmap`, or pass it as
        ``load_colmap(..., normalize=T)``).
    """
    c2w = torch.stack([v.cam_to_world for v in colmap.scene.views])
    return normalization_transform(c2w, colmap.points.points, colmap.points.point_views, target_depth)


def transform_colmap(colmap: ColmapScene, transform: torch.Tensor) -> ColmapScene:
    """A COLMAP scene mapped by a similarity: poses and points move, intrinsics and pixels do not.

    Args:
        colmap: a :class:`ColmapScene`.
        transform: ``(4, 4)`` similarity ``[[s R, t], [0, 1]]``.

    Returns:
        A new :class:`ColmapScene` (its scene's ``sfm_points`` are the new points).
    """
    T = _check_similarity(transform)
    scene, points = colmap
    views = [
        dataclasses.replace(v, cam_to_world=transform_cam_to_world(T, v.cam_to_world)) for v in scene.views
    ]
    points = points._replace(points=transform_points(T, points.points))
    return ColmapScene(dataclasses.replace(scene, views=views, sfm_points=points), points)
