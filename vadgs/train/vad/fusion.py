"""From an instance's matched crops to points and priors: steps 4–6 of reconstructing it by MVS.

After PatchMatch (:func:`~vadgs.train.vad.reconstruct.reconstruct_instance`, paper Sec. 4.3):

4. :func:`consistent_depth` keeps the pixels whose depth at least ``min_consistent_views`` other
   members confirm (:func:`~vadgs.mvs.geometric_consistency`: forward–backward reprojection,
   relative depth) and completes the textureless parts of static planar instances
   (:func:`~vadgs.mvs.complete_planar`: all members at once);
5. :func:`lidar_check` drops the consistent pixels of an instance that the members' own
   LiDAR contradicts (all of them when most of those it can check are); :func:`explained_pixels`
   finds the consistent pixels an opaque rendered surface already explains; :func:`fuse_points`
   makes a point of every other one (:func:`~vadgs.mvs.fuse_depth_maps`, in the instance's
   frame), thinned to one per cell of the point spacing (:func:`~vadgs.geometry.points.thin_points`);
6. :func:`depth_priors` gives each member's consistent depth and normals at the scene's
   resolution, the geometric losses' priors.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import torch
import torch.nn.functional as F

from vadgs.geometry.camera import invert_rigid
from vadgs.geometry.points import thin_points
from vadgs.geometry.resample import pool_valid, repeat
from vadgs.mvs.consistency import geometric_consistency
from vadgs.mvs.fusion import FusionConfig, fuse_depth_maps
from vadgs.mvs.planar import complete_planar
from vadgs.train.vad.crops import Crops, MatchedCrops, render_maps, to_scale
from vadgs.train.vad.reconstruct_config import ReconstructConfig
from vadgs.train.vad.visibility import VisibilityIndex

__all__ = [
    "ConsistentDepth",
    "LidarCheck",
    "consistent_depth",
    "depth_priors",
    "explained_pixels",
    "fuse_points",
    "lidar_check",
]


class ConsistentDepth(NamedTuple):
    """Step 4's result, per member crop."""

    depth: torch.Tensor  # (b, 1, ch, cw)
    normal: torch.Tensor  # (b, 3, ch, cw) camera frame
    keep: torch.Tensor  # (b, 1, ch, cw) bool: consistent (or planar-completed)


def consistent_depth(
    matched: MatchedCrops,
    crops: Crops,
    group: list[int],
    world_to_cam: torch.Tensor,
    planar: bool,
    cfg: ReconstructConfig,
    generator: torch.Generator | None,
) -> ConsistentDepth:
    """Step 4: keep the pixels that other members confirm; planar completion of static instances."""
    res, w2c = matched.result, matched.world_to_cam
    depth = torch.where(res.mask, res.depth, torch.zeros_like(res.depth))
    b = len(crops.members)
    src = torch.tensor([[j for j in range(b) if j != i] for i in range(b)], device=depth.device)
    cons = geometric_consistency(
        depth,
        matched.K,
        w2c,
        depth[src],
        matched.K[src],
        w2c[src],
        cfg.max_reproj_error,
        cfg.max_rel_depth,
        min(cfg.min_consistent_views, b - 1),
    )
    keep = cons.mask & res.mask
    normal = res.normal
    if planar:  # every member at once: one host read
        dev = depth.device
        others = torch.tensor([[j for j in range(len(group)) if j != m] for m in crops.members], device=dev)
        depth, plane_n, add = complete_planar(
            depth, keep, matched.masks, matched.images, matched.K, invert_rigid(w2c),
            crops.images[others], torch.stack(crops.masks)[others][:, :, None], crops.K[others],
            world_to_cam[others], cfg.planar, generator, res.normal,
        )  # fmt: skip
        keep = keep | add
        normal = torch.where(add, plane_n[:, :, None, None].expand_as(normal), normal)
    return ConsistentDepth(depth, normal, keep)


def explained_pixels(
    index: VisibilityIndex,
    cons: ConsistentDepth,
    crops: Crops,
    group: list[int],
    cfg: ReconstructConfig,
    render_prior: Callable[[int], Any] | None,
) -> torch.Tensor:
    """Step 5a: ``(b, 1, ch, cw)`` consistent pixels that an opaque rendered surface already explains.

    Each member's MVS depth is compared with that member's own render (``render_prior``, ``view ->``
    :class:`~vadgs.train.vad.reconstruct.ViewRender`, at the matching scale): explained where the
    render has opacity ``>= explained_alpha`` and a depth in front of, or within
    ``explained_tolerance`` of, the MVS depth. Those pixels give priors but no new point.
    """
    out = torch.zeros_like(cons.keep)
    if render_prior is None:
        return out
    ch, cw = crops.size
    dev = cons.depth.device
    for k, (i, (y0, x0)) in enumerate(zip(crops.members, crops.corners)):
        d, a, _ = render_maps(render_prior, group[i], index)
        if a is None:
            continue
        d, a = d.to(dev), a.to(dev)
        if crops.scale.up > 1:
            d, a = repeat(d, crops.scale.up), repeat(a, crops.scale.up)
        elif crops.scale.down > 1:
            d = pool_valid(d, d > 0, crops.scale.down)
            a = F.avg_pool2d(a[None], crops.scale.down)[0]
        d, a = d[:, y0 : y0 + ch, x0 : x0 + cw], a[:, y0 : y0 + ch, x0 : x0 + cw]
        mvs = cons.depth[k]
        out[k] = (a >= cfg.explained_alpha) & (d > 0) & (d <= mvs * (1 + cfg.explained_tolerance))
    return out & cons.keep


class LidarCheck(NamedTuple):
    """Step 5a's LiDAR check (:func:`lidar_check`), per member crop ``(b, 1, ch, cw)`` bool.

    Attributes:
        checked: consistent pixels where the member's own sweep measured a depth.
        contradicted: those of ``checked`` whose MVS depth is more than ``max_lidar_error`` off it.
    """

    checked: torch.Tensor
    contradicted: torch.Tensor


def lidar_check(
    index: VisibilityIndex,
    cons: ConsistentDepth,
    crops: Crops,
    group: list[int],
    cfg: ReconstructConfig,
    track: int | None = None,
) -> LidarCheck:
    """Step 5a: the consistent pixels of an instance that the members' own LiDAR contradicts.

    Each member's MVS depth is compared with the depth its own sweep measured
    (:meth:`VisibilityIndex.observed_depth`, resampled to the matching scale and cropped as the
    member's crop): contradicted where that depth exists and the MVS depth is more than
    ``cfg.max_lidar_error`` (relative) off it. Everything False when ``max_lidar_error`` is None.
    ``track``: a moving object's, against the voxels of its grid the member's sweep observed
    (posed at the member's time; a camera's depth is the same in the object's frame).
    """
    checked = torch.zeros_like(cons.keep)
    contradicted = torch.zeros_like(cons.keep)
    if cfg.max_lidar_error is None:
        return LidarCheck(checked, contradicted)
    ch, cw = crops.size
    dev = cons.depth.device
    for k, (i, (y0, x0)) in enumerate(zip(crops.members, crops.corners)):
        d = index.observed_depth(group[i], track).to(dev, cons.depth.dtype)
        d = to_scale(d, d > 0, crops.scale)[:, y0 : y0 + ch, x0 : x0 + cw]
        checked[k] = cons.keep[k] & (d > 0)
        contradicted[k] = checked[k] & ((cons.depth[k] - d).abs() > cfg.max_lidar_error * d)
    return LidarCheck(checked, contradicted)


def fuse_points(
    index: VisibilityIndex,
    cons: ConsistentDepth,
    matched: MatchedCrops,
    crops: Crops,
    new: torch.Tensor,
    track: int | None,
    cfg: ReconstructConfig,
    occupied: torch.Tensor | None,
    generator: torch.Generator | None,
    device: torch.device,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, int]:
    """Step 5b: ``(points, normals, colors, spacing, consistent)``, the points of the ``new`` pixels.

    Points, normals, colours and spacing in the instance's frame.

    One point per pixel (:func:`~vadgs.mvs.fuse_depth_maps`), its spacing the pixel footprint at its
    depth; with ``cfg.thin_points``, one per cell of the spacing (times ``thin_factor`` for a
    coarsely matched instance; cells of the static grid's frame, or a moving object's own) and none
    in a cell of ``occupied``; at most ``cfg.max_points``, drawn with ``generator``. ``consistent``:
    the consistent pixels (``cons.keep``), counted in the thinning's read.
    """
    fused = fuse_depth_maps(  # one point per such pixel, in the instance's frame
        cons.depth, matched.images, matched.K, matched.world_to_cam, cons.normal, new,
        FusionConfig(min_views=0, deduplicate=False),
    )  # fmt: skip
    seed_w2c, seed_K = matched.world_to_cam[fused.view_index], matched.K[fused.view_index]
    z_seed = (seed_w2c[:, 2, :3] * fused.points).sum(-1) + seed_w2c[:, 2, 3]
    points, normals, colors, spacing = fused.points, fused.normals, fused.colors, z_seed / seed_K[:, 0, 0]
    consistent = cons.keep.sum()
    if cfg.thin_points and points.shape[0]:  # one per cell of the scene resolution's spacing, or coarser
        spacing = spacing * (crops.scale.up * (cfg.thin_factor if crops.scale.down > 1 else 1.0))
        local, taken = points, None if occupied is None else occupied.to(device)
        if track is None:  # cells of the static grid's frame (a moving object's: its own frame)
            local, taken = index.to_ground(local), None if taken is None else index.to_ground(taken)
        kept = thin_points(local, spacing.median(), taken)
        n, consistent = torch.stack([kept.sum(), consistent.to(kept.device)]).tolist()  # one read
        keep = torch.nonzero_static(kept, size=n).squeeze(1)
        points, normals, colors, spacing = points[keep], normals[keep], colors[keep], spacing[keep]
    if points.shape[0] > cfg.max_points:
        g = generator or torch.Generator().manual_seed(0)
        sub = torch.randperm(points.shape[0], generator=g)[: cfg.max_points].to(device)
        points, normals, colors, spacing = points[sub], normals[sub], colors[sub], spacing[sub]
    return points, normals, colors, spacing, int(consistent)


def depth_priors(cons: ConsistentDepth, crops: Crops, size: tuple[int, int]) -> tuple[list, list]:
    """Step 6: each member's consistent depth and normals in its full image at the scene's resolution."""
    h, w = size
    ch, cw = crops.size_lo
    full_depth, full_normal = [], []
    for k, (y0, x0) in enumerate(crops.corners_lo):
        fd = cons.depth.new_zeros(1, h, w)
        fn = cons.normal.new_zeros(3, h, w)
        if crops.scale.up > 1:
            f = crops.scale.up
            d = pool_valid(cons.depth[k], cons.keep[k], f)
            n = pool_valid(cons.normal[k], cons.keep[k], f, unit=True)
        else:
            f = crops.scale.down
            d = repeat(torch.where(cons.keep[k], cons.depth[k], torch.zeros_like(cons.depth[k])), f)
            n = repeat(torch.where(cons.keep[k], cons.normal[k], torch.zeros_like(cons.normal[k])), f)
        fd[:, y0 : y0 + ch, x0 : x0 + cw] = d
        fn[:, y0 : y0 + ch, x0 : x0 + cw] = n
        full_depth.append(fd)
        full_normal.append(fn)
    return full_depth, full_normal
