"""gsplat's COLMAP ``Parser`` read as data: its views' cameras, TRACK table and images.

gsplat's ``examples/datasets/colmap.py`` ``Parser`` is read duck-typed (gsplat is not imported):
:func:`read_gsplat_parser` gives every view's camera in vadgs's conventions, the training views,
the SfM points those views observed with their observations (the TRACK table), and an image
loader that undistorts as gsplat's ``Dataset`` does (:func:`parser_undistortion`). VAD-GS's inputs
(:meth:`vadgs.train.vad.VisibilityInputs.from_gsplat_parser`) are built from it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F

from vadgs.data.images import read_image
from vadgs.geometry.camera import Cameras, invert_rigid

__all__ = ["ParserData", "parser_undistortion", "read_gsplat_parser"]


class ParserData(NamedTuple):
    """What :func:`read_gsplat_parser` reads of gsplat's Parser.

    Attributes:
        cameras: every view's camera (vadgs's pixel centres), at the largest view size.
        sizes: per view ``(H, W)`` when the views differ in size, else None.
        train_views: the training views, sorted.
        view_cameras: each view's camera, an index into the parser's sorted camera ids.
        points: ``(P, 3)`` the SfM points a training view observed (world frame).
        point_idx: ``(T,)`` int64 point (into ``points``) of each observation by a training view.
        view_idx: ``(T,)`` int64 view of each observation.
        load_image: ``(view, (H, W) or None) -> (3, H, W)`` float image in [0, 1], undistorted as
            gsplat's ``Dataset`` does it, resized (area) to the size asked (default: the view's).
        name: the parser's ``data_dir``.
    """

    cameras: Cameras
    sizes: tuple[tuple[int, int], ...] | None
    train_views: tuple[int, ...]
    view_cameras: tuple[int, ...]
    points: torch.Tensor
    point_idx: torch.Tensor
    view_idx: torch.Tensor
    load_image: Callable[[int, tuple[int, int] | None], torch.Tensor]
    name: str


def read_gsplat_parser(
    parser: Any, train_views: Sequence[int] | None = None, test_every: int | None = None
) -> ParserData:
    """The views, cameras, TRACK table and image loader of gsplat's COLMAP ``Parser``, duck-typed.

    Reads ``image_names``, ``image_paths``, ``camtoworlds`` (``(N, 4, 4)`` OpenCV
    camera-to-world), ``camera_ids``, ``Ks_dict``, ``imsize_dict`` (camera id → ``(W, H)``),
    ``points`` and ``point_indices`` (image name → indices of the points it sees: the TRACK
    table). ``K`` is moved to vadgs's pixel convention (centres at integers: ``cx, cy`` minus
    0.5; gsplat's and COLMAP's centres are at ``i + 0.5``). Images are read on demand and resized
    (area) to the parser's size; distorted cameras' images are undistorted as gsplat's
    ``Dataset`` does it (:func:`parser_undistortion`). Only observations by training views count,
    and only the points they observed are kept (renumbered, in their order).

    Args:
        parser: the parser (or any object with those attributes).
        train_views: the training views (default: gsplat's ``Dataset(split="train")``, every
            view but each ``test_every``-th when ``test_every`` is given, else every view).
        test_every: gsplat's ``test_every`` (``parser.test_every`` when present).

    Returns:
        :class:`ParserData`.

    Raises:
        ValueError: ``parser.camtoworlds`` of another shape than ``(N, 4, 4)``; a fisheye camera, or
            distortion parameters without the Parser's maps (:func:`parser_undistortion`).
    """
    names = list(parser.image_names)
    n = len(names)
    if test_every is None:
        test_every = getattr(parser, "test_every", None)
    if train_views is None:
        train_views = [i for i in range(n) if not test_every or i % test_every != 0]
    cam_ids = [int(c) for c in parser.camera_ids]
    K = torch.stack([torch.as_tensor(np.asarray(parser.Ks_dict[c])) for c in cam_ids]).float()
    K[:, :2, 2] -= 0.5  # gsplat / COLMAP: pixel centres at i + 0.5; vadgs: at i
    c2w = torch.as_tensor(np.asarray(parser.camtoworlds), dtype=torch.float32)
    if tuple(c2w.shape) != (n, 4, 4):
        raise ValueError(f"parser.camtoworlds: expected ({n}, 4, 4), got {tuple(c2w.shape)}")
    hw = [(int(parser.imsize_dict[c][1]), int(parser.imsize_dict[c][0])) for c in cam_ids]  # (W, H) -> (H, W)
    big = (max(h for h, _ in hw), max(w for _, w in hw))
    sizes = None if len(set(hw)) == 1 else tuple(hw)
    cameras = Cameras(K, invert_rigid(c2w), big)
    train = set(int(t) for t in train_views)
    pi, vi = [], []
    for v, name in enumerate(names):
        idx = parser.point_indices.get(name)
        if v in train and idx is not None and len(idx):
            idx = torch.as_tensor(np.asarray(idx), dtype=torch.int64)
            pi.append(idx)
            vi.append(torch.full_like(idx, v))
    points = torch.as_tensor(np.asarray(parser.points), dtype=torch.float32)
    pi_t = torch.cat(pi) if pi else torch.zeros(0, dtype=torch.int64)
    vi_t = torch.cat(vi) if vi else torch.zeros(0, dtype=torch.int64)
    used = torch.zeros(points.shape[0], dtype=torch.bool)
    used[pi_t] = True
    new_id = torch.cumsum(used.long(), 0) - 1  # only the observed points, renumbered
    paths = list(parser.image_paths)
    unique_cams = sorted(set(cam_ids))
    undistort = {c: parser_undistortion(parser, c) for c in unique_cams}

    def load_image(view: int, size: tuple[int, int] | None = None) -> torch.Tensor:
        arr = read_image(paths[view])  # float [0, 1], as every vadgs loader decodes a photo
        remap = undistort[cam_ids[view]]
        if remap is not None:  # as gsplat's Dataset: remap, then the ROI
            import cv2

            mapx, mapy, (x, y, w, h) = remap
            u8 = np.round(arr * 255.0).astype(np.uint8)
            if np.array_equal(u8.astype(np.float32) / 255.0, arr):  # 8-bit: on uint8, as gsplat
                arr = cv2.remap(u8, mapx, mapy, cv2.INTER_LINEAR).astype(np.float32) / 255.0
            else:  # 16-bit and float images keep their precision
                arr = cv2.remap(arr, mapx, mapy, cv2.INTER_LINEAR)
            arr = arr[y : y + h, x : x + w]
        img = torch.from_numpy(np.ascontiguousarray(arr)).permute(2, 0, 1).float()
        h, w = size or (sizes[view] if sizes is not None else big)
        if img.shape[-2:] != (h, w):
            mode = "bilinear" if h > img.shape[-2] or w > img.shape[-1] else "area"
            kw = {"align_corners": False} if mode == "bilinear" else {}
            img = F.interpolate(img[None], size=(h, w), mode=mode, **kw)[0]
        return img

    return ParserData(
        cameras=cameras,
        sizes=sizes,
        train_views=tuple(sorted(train)),
        view_cameras=tuple(unique_cams.index(c) for c in cam_ids),
        points=points[used],
        point_idx=new_id[pi_t],
        view_idx=vi_t,
        load_image=load_image,
        name=str(getattr(parser, "data_dir", "gsplat parser")),
    )


def parser_undistortion(parser: Any, camera_id: int) -> tuple[Any, Any, tuple[int, int, int, int]] | None:
    """``(mapx, mapy, roi)`` of a distorted camera of gsplat's Parser, None for a pinhole one.

    Args:
        parser: gsplat's ``Parser`` (``params_dict``, ``mask_dict``, ``mapx_dict``, ``mapy_dict``,
            ``roi_undist_dict``; duck-typed).
        camera_id: the COLMAP camera id.

    Returns:
        The maps ``cv2.remap`` takes and the crop ``(x, y, w, h)`` of the undistorted image, as
        gsplat's ``Dataset`` applies them; None when the camera has no distortion parameters.

    Raises:
        ValueError: a fisheye camera, or distortion parameters without the Parser's maps.
    """
    params = getattr(parser, "params_dict", {}).get(camera_id)
    if params is None or len(params) == 0:
        return None
    if getattr(parser, "mask_dict", {}).get(camera_id) is not None:
        raise ValueError(f"parser camera {camera_id}: expected a perspective camera, got a fisheye one")
    try:
        maps = parser.mapx_dict[camera_id], parser.mapy_dict[camera_id], parser.roi_undist_dict[camera_id]
    except (AttributeError, KeyError):
        raise ValueError(
            f"parser camera {camera_id}: expected mapx_dict / mapy_dict / roi_undist_dict for its distortion "
            f"params {list(params)}, got none (undistort the images, or use gsplat's Parser)"
        ) from None
    x, y, w, h = (int(v) for v in maps[2])
    return maps[0], maps[1], (x, y, w, h)
