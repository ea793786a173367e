"""COLMAP sparse model folders: find and read one, its cameras as vadgs intrinsics, its images' poses.

:func:`find_colmap_model` recognises a model or project folder, :func:`distorted_cameras` lists the
cameras that need undistortion, :func:`colmap_camera_to_K` converts a camera (pixel centres at
integers: :data:`COLMAP_PIXEL_OFFSET`) and :func:`match_colmap_views` checks that a model belongs to
another scene's views. The loader itself is :func:`vadgs.data.colmap.load_colmap`.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from vadgs.data.colmap_files import check_reconstruction, diagnose_model_files, diagnose_references
from vadgs.data.scene import Scene
from vadgs.geometry.camera import invert_rigid

if TYPE_CHECKING:  # imported where used: pycolmap is slow to import
    import pycolmap

__all__ = [
    "COLMAP_PIXEL_OFFSET",
    "colmap_camera_to_K",
    "colmap_world_to_cam",
    "distorted_cameras",
    "find_colmap_model",
    "has_colmap_model",
    "match_colmap_views",
    "read_colmap_model",
]

#: vadgs pixel coordinates = COLMAP pixel coordinates + this offset (pixel centres at integers).
COLMAP_PIXEL_OFFSET = -0.5


_PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
_DISTORTED_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV")


def colmap_camera_to_K(camera: pycolmap.Camera) -> tuple[torch.Tensor, tuple[int, int]]:
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


def colmap_world_to_cam(image: pycolmap.Image) -> np.ndarray:
    """A pycolmap image's ``cam_from_world`` as a ``(4, 4)`` float64 ``world_to_cam`` (pycolmap 3 and 4)."""
    cfw: Any = image.cam_from_world  # Any: the stubs know only the pycolmap installed
    cfw = cfw() if callable(cfw) else cfw  # a method in pycolmap 4, a property before
    out = np.eye(4)
    out[:3, :4] = np.asarray(cfw.matrix(), dtype=np.float64)
    return out


def _model_file(folder: Path, name: str) -> bool:
    return any((folder / f"{name}.{e}").is_file() for e in ("bin", "txt"))


def has_colmap_model(folder: Path) -> bool:
    """Whether ``folder`` holds a COLMAP model (``cameras``, ``images``, ``points3D``: ``.bin``, ``.txt``)."""
    return all(_model_file(folder, n) for n in ("cameras", "images", "points3D"))


def find_colmap_model(path: str | Path) -> Path | None:
    """The COLMAP sparse model a folder is or holds: ``path``, ``path/sparse/0``, ``sparse`` or ``0``.

    A model folder has ``cameras``, ``images`` and ``points3D`` as ``.bin`` or ``.txt``.

    Returns:
        The model folder, or None when there is none.

    Example:
        >>> import tempfile
        >>> find_colmap_model(tempfile.mkdtemp()) is None
        True
    """
    path = Path(path)
    for cand in (path, path / "sparse" / "0", path / "sparse", path / "0"):
        if cand.is_dir() and has_colmap_model(cand):
            return cand
    return None


def read_colmap_model(sparse_dir: Path, what: str) -> pycolmap.Reconstruction:
    """The COLMAP model in ``sparse_dir``, its files checked first (errors name ``what`` and the file).

    Raises:
        FileNotFoundError: when a model file is missing.
        ValueError: when a file is corrupt or the model inconsistent.
    """
    import pycolmap

    if not has_colmap_model(sparse_dir):
        missing = [n for n in ("cameras", "images", "points3D") if not _model_file(sparse_dir, n)]
        raise FileNotFoundError(
            f"{what} {sparse_dir}: no COLMAP model (cameras, images, points3D as .bin or .txt; "
            f"missing {', '.join(missing)})"
        )
    found = diagnose_model_files(sparse_dir)  # pycolmap may loop for minutes on a truncated file
    if found is not None:
        raise ValueError(f"{what} {sparse_dir}: cannot read the COLMAP model: {found}")
    try:
        rec = pycolmap.Reconstruction(str(sparse_dir))
    except Exception as e:  # pycolmap raises a bare RuntimeError / ValueError on corrupt files
        raise ValueError(
            f"{what} {sparse_dir}: cannot read the COLMAP model: {_pycolmap_error(sparse_dir, e)}"
        ) from None
    check_reconstruction(rec, sparse_dir)
    return rec


def _pycolmap_error(sparse_dir: Path, error: Exception) -> str:
    """The error of pycolmap as one line naming the file at fault (found by :func:`diagnose_model_files`)."""
    first = " ".join(str(error).split())
    first = first.split("] ", 1)[-1] if first.startswith("[") else first  # "[file.cc:123] Check failed"
    found = diagnose_model_files(sparse_dir) or diagnose_references(sparse_dir)
    return f"{found} (pycolmap: {first[:200]})" if found else f"pycolmap: {first[:200]}"


def distorted_cameras(sparse_dir: str | Path) -> list[str]:
    """The cameras of a COLMAP model that are not pinhole (PINHOLE / SIMPLE_PINHOLE), as ``"id MODEL"``.

    A model counts, whatever its parameters: undistorting a SIMPLE_RADIAL camera with ``k = 0``
    only rewrites it as PINHOLE.

    Raises:
        FileNotFoundError: if ``sparse_dir`` holds no model.
        ValueError: if the model cannot be read.
    """
    rec = read_colmap_model(Path(sparse_dir), "sparse_dir")
    return [
        f"{cid} {cam.model.name}"
        for cid, cam in sorted(rec.cameras.items())
        if cam.model.name not in _PINHOLE_MODELS
    ]


def match_colmap_views(scene: Scene, sparse_dir: str | Path, what: str = "colmap") -> torch.Tensor:
    """Which view of ``scene`` each registered image of a COLMAP model is; raises unless all match.

    A COLMAP image name matches a view whose image path ends with it (``front/000.png`` matches
    ``.../images/front/000.png``). The model must also be in the scene's world frame: the median
    distance between matched camera centres must be below 5 % of the scene's camera extent
    (the largest distance of a camera from the cameras' mean, at least 1e-3).

    Args:
        scene: the scene the model's points are for.
        sparse_dir: the COLMAP model folder.
        what: the argument's name in messages (e.g. ``"--colmap"``).

    Returns:
        ``(N,)`` int64 index into ``scene.views`` of each registered image, in name order.

    Raises:
        FileNotFoundError: if ``sparse_dir`` holds no model.
        ValueError: naming ``what``, the expected and the found names (or the centres' distance).
    """
    rec = read_colmap_model(Path(sparse_dir), what)
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    by_suffix: dict[tuple[str, ...], int] = {}
    for v in scene.views:
        if v.image is not None and v.group is None:
            parts = Path(v.image).parts
            for k in range(1, len(parts) + 1):
                by_suffix.setdefault(parts[-k:], v.index)
    idx = [by_suffix.get(Path(im.name).parts, -1) for im in images]
    bad = [im.name for im, i in zip(images, idx) if i < 0]
    if bad or not images:
        firsts = [scene.views[v].image for v in scene.train_views[:2]]
        expected = [str(Path(*Path(im).parts[-2:])) for im in firsts if im is not None]
        raise ValueError(
            f"{what} {sparse_dir}: the COLMAP model's images are not the views of scene {scene.name!r}: "
            f"{len(bad)} of {len(images)} registered image names match none (expected names like "
            f"{expected}, found {bad[:3]})"
        )
    theirs = torch.stack([invert_rigid(torch.tensor(colmap_world_to_cam(im)))[:3, 3] for im in images])
    mine = torch.stack([scene.views[i].cam_to_world[:3, 3] for i in idx]).double()
    allc = torch.stack([v.cam_to_world[:3, 3] for v in scene.views]).double()
    extent = max(float((allc - allc.mean(0)).norm(dim=-1).max()), 1e-3)
    off = float((mine - theirs).norm(dim=-1).median())
    if off > 0.05 * extent:
        raise ValueError(
            f"{what} {sparse_dir}: the COLMAP model is not in the world frame of scene {scene.name!r}: "
            f"its camera centres are a median {off:.3g} from the scene's (expected below "
            f"{0.05 * extent:.3g}, 5 % of the cameras' extent); align it first (colmap model_aligner)"
        )
    return torch.tensor(idx, dtype=torch.int64)
