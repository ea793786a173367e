r"""Planar completion of textureless parts of a region (an ACMP-style planar prior).

Photometric PatchMatch cannot match a window without texture (a uniformly painted sign board, a
plain wall): those pixels stay empty after the consistency check even when the rest of the same
flat surface is reconstructed. When the consistent pixels of a region are well explained by one
plane, that plane is the natural hypothesis for the region's empty pixels (ACMP triangulates
credible points into planar priors for the same reason). :func:`complete_planar`

1. fits a plane :math:`\mathbf{n}^\top \mathbf{X} + d = 0` to the region's consistent pixels
   (camera frame) with RANSAC (:func:`fit_plane_ransac`) and gives up unless at least
   ``min_inlier_ratio`` of them are inliers;
2. intersects the rays of the region's empty pixels within ``max_gap`` pixels of an inlier with
   that plane;
3. keeps a candidate only where its colour agrees (mean absolute RGB difference below
   ``color_tolerance``) with the colour its 3D point projects to in at least ``min_views`` other
   views, inside their regions — a colour test that, unlike NCC, works on flat patches.

Not differentiable (a search with boolean outputs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch

from vadgs.checks import check_finite, check_shape, checks_enabled
from vadgs.geometry import backproject_depth, project_points

__all__ = ["PlanarCompletionConfig", "PlaneFit", "complete_planar", "fit_plane_ransac"]


class PlaneFit(NamedTuple):
    """A plane ``n . X + d = 0`` and its inliers.

    Attributes:
        normal: ``(3,)`` unit normal.
        offset: ``()`` the plane's ``d``.
        inliers: ``(N,)`` bool.
    """

    normal: torch.Tensor
    offset: torch.Tensor
    inliers: torch.Tensor


def fit_plane_ransac(
    points: torch.Tensor,
    threshold: float | torch.Tensor,
    iterations: int = 200,
    generator: torch.Generator | None = None,
    normals: torch.Tensor | None = None,
    max_angle: float = 30.0,
) -> PlaneFit | None:
    """Dominant plane of a point set by RANSAC, refined by least squares on its inliers.

    Args:
        points: ``(N, 3)`` points.
        threshold: inlier distance, a number or ``(N,)`` per point (e.g. relative to depth).
        iterations: random triples tried (all at once, vectorised).
        generator: seeds the triples.
        normals: optional ``(N, 3)`` unit normals of the points (e.g. PatchMatch's): an inlier
            must then also have its normal within ``max_angle`` degrees of the plane's (either
            orientation), which keeps a plane through a thin pole from beating the board on it.
        max_angle: see ``normals``.

    Returns:
        A :class:`PlaneFit`, or None with fewer than 3 points or only degenerate triples.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> xy = torch.rand(200, 2, generator=g)
        >>> pts = torch.cat([xy, 0.5 * xy[:, :1] + 2], dim=1)  # the plane z = 0.5 x + 2
        >>> fit = fit_plane_ransac(pts, 0.01, generator=g)
        >>> bool(fit.inliers.all()), round(float(fit.normal[2] / fit.normal[0]), 3)
        (True, -2.0)
    """
    check_shape(points, "points", ("N", 3))
    normals_in = normals
    if normals_in is not None:
        check_shape(normals_in, "normals", ("N", 3))
    if int(iterations) < 1:
        raise ValueError(f"iterations: expected >= 1, got {iterations}")
    thr_in = torch.as_tensor(threshold)
    check_finite(thr_in, "threshold")
    if checks_enabled() and bool((thr_in <= 0).any()):
        raise ValueError(f"threshold: expected positive inlier distances, got min {float(thr_in.min()):g}")
    return _fit_plane(points, threshold, iterations, generator, normals_in, max_angle)


def _fit_plane(
    points: torch.Tensor,
    threshold: float | torch.Tensor,
    iterations: int,
    generator: torch.Generator | None,
    normals_in: torch.Tensor | None,
    max_angle: float,
) -> PlaneFit | None:
    """:func:`fit_plane_ransac` without its input checks (inputs its caller built): two host reads."""
    n = points.shape[0]
    if n < 3:
        return None
    gdev = generator.device if generator is not None else points.device  # a CPU generator for CUDA points
    idx = torch.randint(0, n, (iterations, 3), generator=generator, device=gdev).to(points.device)
    a, b, c = points[idx[:, 0]], points[idx[:, 1]], points[idx[:, 2]]
    normals = torch.cross(b - a, c - a, dim=-1)
    norm = normals.norm(dim=-1)
    ok = torch.nonzero(norm > 1e-9).squeeze(1)  # one read: the non-degenerate triples
    if ok.numel() == 0:
        return None
    normals = normals[ok] / norm[ok, None]
    offsets = -(normals * a[ok]).sum(-1)
    thr = torch.as_tensor(threshold, dtype=points.dtype, device=points.device)
    thr = thr[:, None] if thr.ndim == 1 else thr
    cos_min = math.cos(math.radians(max_angle))

    def inliers_of(plane_normals: torch.Tensor, plane_offsets: torch.Tensor) -> torch.Tensor:
        """``(N, T)`` inlier masks of ``T`` planes ``(T, 3)``, ``(T,)``."""
        inl = (points @ plane_normals.T + plane_offsets).abs() <= thr
        if normals_in is not None:
            inl &= (normals_in @ plane_normals.T).abs() >= cos_min
        return inl

    agree = inliers_of(normals, offsets)
    best = agree.sum(0).argmax()[None]  # stays on the device: a (1,) index reads nothing
    normal, offset, inliers = normals[best][0], offsets[best][0], agree[:, best][:, 0]
    # least-squares refinement on the inliers (smallest singular vector of the centred points)
    p = points[inliers]  # one read
    if p.shape[0] >= 3:
        centre = p.mean(0)
        normal = torch.linalg.svd(p - centre, full_matrices=False).Vh[-1]
        offset = -(normal * centre).sum()
        inliers = inliers_of(normal[None], offset[None])[:, 0]
    return PlaneFit(normal, offset, inliers)


def _near(mask: torch.Tensor, max_gap: float) -> torch.Tensor:
    """``(H, W)`` bool: pixels within Euclidean distance ``max_gap`` of a set pixel of ``mask``.

    ``distance_transform_edt(~mask) <= max_gap`` on the mask's device: a dilation by the disk of
    integer offsets ``dy^2 + dx^2 <= max_gap^2`` (one convolution, no host read).
    """
    r = max(0, math.floor(max_gap))
    off = torch.arange(-r, r + 1, device=mask.device, dtype=torch.float64)
    disk = (off[:, None] ** 2 + off[None, :] ** 2 <= max_gap * max_gap).to(torch.float32)
    hits = torch.nn.functional.conv2d(mask[None, None].to(torch.float32), disk[None, None], padding=r)
    return hits[0, 0] > 0.5


@dataclass(frozen=True)
class PlanarCompletionConfig:
    """Settings of :func:`complete_planar`.

    Attributes:
        min_pixels: consistent pixels a region needs before a plane is fitted.
        min_inlier_ratio: share of them the plane must explain.
        rel_threshold: inlier distance relative to the point's depth.
        max_gap: empty pixels farther than this (pixels) from an inlier are not filled.
        color_tolerance: mean absolute RGB difference (on [0, 1]) of an agreeing view.
        min_views: other views that must agree.
        iterations: RANSAC triples.
        max_normal_angle: if set and a normal map is given, inliers' normals must lie within this
            angle (degrees) of the plane's. Off by default: PatchMatch's normals on a small board
            are too noisy for it (the measurement: ``docs/results.md``).
    """

    min_pixels: int = 30
    min_inlier_ratio: float = 0.6
    rel_threshold: float = 0.02
    max_gap: float = 8.0
    color_tolerance: float = 0.06
    min_views: int = 1
    iterations: int = 200
    max_normal_angle: float | None = None


def complete_planar(
    depth: torch.Tensor,
    valid: torch.Tensor,
    region: torch.Tensor,
    image: torch.Tensor,
    K: torch.Tensor,
    cam_to_world: torch.Tensor,
    src_images: torch.Tensor,
    src_regions: torch.Tensor,
    src_K: torch.Tensor,
    src_world_to_cam: torch.Tensor,
    config: PlanarCompletionConfig | None = None,
    generator: torch.Generator | None = None,
    normal: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Fill the empty pixels of a planar region of one view from the plane of its valid pixels.

    Args:
        depth: ``(1, H, W)`` depth of the view (valid where ``valid``).
        valid: ``(1, H, W)`` bool, consistent pixels.
        region: ``(1, H, W)`` bool, the region (an instance's mask).
        image: ``(3, H, W)`` the view's colours.
        K: ``(3, 3)`` its intrinsics.
        cam_to_world: ``(4, 4)`` its pose.
        src_images: ``(V, 3, Hs, Ws)`` other views.
        src_regions: ``(V, 1, Hs, Ws)`` bool, the region in them (a colour match outside does
            not count: occluders).
        src_K: ``(V, 3, 3)`` their intrinsics.
        src_world_to_cam: ``(V, 4, 4)`` their poses.
        config: :class:`PlanarCompletionConfig`.
        generator: seeds RANSAC.
        normal: optional ``(3, H, W)`` camera-frame normals of the valid pixels: inliers must
            agree with the plane's normal within ``config.max_normal_angle`` (when set).

    Returns:
        ``(depth, normal, added)``: the completed depth ``(1, H, W)``, the plane's camera-frame
        normal ``(3,)`` facing the camera (zeros when no plane was accepted), and ``(1, H, W)``
        bool, the pixels filled.
    """
    cfg = config or PlanarCompletionConfig()
    dims = check_shape(depth, "depth", (1, "H", "W"))
    check_shape(valid, "valid", (1, "H", "W"), dims)
    check_shape(region, "region", (1, "H", "W"), dims)
    check_shape(image, "image", (3, "H", "W"), dims)
    sd = check_shape(src_images, "src_images", ("V", 3, "Hs", "Ws"))
    check_shape(src_regions, "src_regions", ("V", 1, "Hs", "Ws"), sd)
    none = torch.zeros_like(valid)
    zero_n = torch.zeros(3, dtype=depth.dtype, device=depth.device)
    if sd["V"] == 0:
        return depth, zero_n, none
    good = valid & region & (depth > 0)
    gy, gx = torch.nonzero(good[0], as_tuple=True)  # one read: the consistent pixels, row-major
    if gy.numel() < cfg.min_pixels:
        return depth, zero_n, none
    pts = backproject_depth(depth[None], K[None])[0]  # (3, H, W) camera frame
    p = pts[:, gy, gx].T
    nrm, angle = None, 90.0  # the angle is unused without normals
    if normal is not None and cfg.max_normal_angle is not None:
        nrm = torch.nn.functional.normalize(normal[:, gy, gx].T, dim=-1)
        angle = cfg.max_normal_angle
    fit = _fit_plane(p, cfg.rel_threshold * p[:, 2], cfg.iterations, generator, nrm, angle)
    if fit is None:
        return depth, zero_n, none
    inf = torch.full_like(p[:, 2], math.inf)
    ratio, off, z_min, z_max = torch.stack(
        [
            fit.inliers.float().mean().double(),
            fit.offset.double(),
            torch.where(fit.inliers, p[:, 2], inf).min().double(),
            torch.where(fit.inliers, p[:, 2], -inf).max().double(),
        ]
    ).tolist()  # one read (float64 holds each value exactly)
    if ratio < cfg.min_inlier_ratio:
        return depth, zero_n, none
    normal, offset = fit.normal, fit.offset
    if off < 0:  # the camera (origin) on the positive side: the normal faces it
        normal, offset = -normal, -offset
    # candidates: empty region pixels near an inlier
    inl = torch.zeros_like(good[0])
    inl[gy, gx] = fit.inliers
    cand = region & ~good & _near(inl, cfg.max_gap)[None]
    ys, xs = torch.nonzero(cand[0], as_tuple=True)  # one read
    if ys.numel() == 0:
        return depth, normal, none
    pix = torch.stack([xs, ys, torch.ones_like(xs)], -1).to(depth)
    rays = pix @ torch.linalg.inv(K).T
    den = rays @ normal
    z = -offset / torch.where(den.abs() > 1e-9, den, torch.full_like(den, 1e-9))
    ok = (z > 0.5 * z_min) & (z < 2.0 * z_max)
    cam = rays * z[:, None]
    world = cam @ cam_to_world[:3, :3].T + cam_to_world[:3, 3]
    colour = image[:, ys, xs].T  # (P, 3)
    v = sd["V"]
    uv, zs = project_points(world[None].expand(v, -1, -1), src_K, src_world_to_cam)
    qx, qy = uv[..., 0].round().long(), uv[..., 1].round().long()
    inside = (zs > 0) & (qx >= 0) & (qx < sd["Ws"]) & (qy >= 0) & (qy < sd["Hs"])
    qx, qy = qx.clamp(0, sd["Ws"] - 1), qy.clamp(0, sd["Hs"] - 1)
    views = torch.arange(v, device=qx.device)[:, None]
    sc = src_images.permute(0, 2, 3, 1)[views, qy, qx]  # (V, P, 3): each view's colour there
    match = (sc - colour).abs().mean(-1) <= cfg.color_tolerance
    agree = (inside & src_regions[views, 0, qy, qx] & match).long().sum(0)
    keep = ok & (agree >= cfg.min_views)
    out = depth.clone()
    added = torch.zeros_like(valid)
    out[0, ys, xs] = torch.where(keep, z, out[0, ys, xs])
    added[0, ys, xs] = keep
    return out, normal, added
