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

from vadgs.checks import Checked, check_finite, check_shape, checked, checks_enabled, float_field, int_field
from vadgs.geometry import backproject_depth, project_points

__all__ = [
    "PlanarCompletionConfig",
    "PlaneFit",
    "complete_planar",
    "fit_plane_ransac",
    "near_pixels",
]


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


def near_pixels(mask: torch.Tensor, max_gap: float) -> torch.Tensor:
    """``(B, H, W)`` bool: pixels within Euclidean distance ``max_gap`` of a set pixel of ``mask (B, H, W)``.

    ``distance_transform_edt(~mask) <= max_gap`` of each mask, on the mask's device: a dilation by
    the disk of integer offsets ``dy^2 + dx^2 <= max_gap^2`` (one convolution, no host read).
    """
    r = max(0, math.floor(max_gap))
    off = torch.arange(-r, r + 1, device=mask.device, dtype=torch.float64)
    disk = (off[:, None] ** 2 + off[None, :] ** 2 <= max_gap * max_gap).to(torch.float32)
    hits = torch.nn.functional.conv2d(mask[:, None].to(torch.float32), disk[None, None], padding=r)
    return hits[:, 0] > 0.5


@dataclass(frozen=True)
class PlanarCompletionConfig(Checked):
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

    min_pixels: int = checked(30, int_field(0))
    min_inlier_ratio: float = checked(0.6, float_field(0, 1))
    rel_threshold: float = checked(0.02, float_field(0, lo_open=True))
    max_gap: float = checked(8.0, float_field(0))
    color_tolerance: float = checked(0.06, float_field(0))
    min_views: int = checked(1, int_field(0))
    iterations: int = checked(200, int_field(1))
    max_normal_angle: float | None = checked(None, float_field(0, 180, optional=True))


def _inliers(
    pts: torch.Tensor,
    thr: torch.Tensor,
    normals: torch.Tensor,
    offsets: torch.Tensor,
    normals_in: torch.Tensor | None,
    cos_min: float,
) -> torch.Tensor:
    """``(b, N, T)`` inlier masks of the ``T`` planes ``(b, T, 3)``, ``(b, T)`` of each view's ``pts``."""
    inl = (torch.bmm(pts, normals.transpose(1, 2)) + offsets[:, None]).abs() <= thr[..., None]
    if normals_in is not None:
        inl &= torch.bmm(normals_in, normals.transpose(1, 2)).abs() >= cos_min
    return inl


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
    """Fill the empty pixels of a planar region of each of ``b`` views from the plane of its valid pixels.

    See the module docstring for the steps. The ``b`` views (the group members of a
    reconstruction) are done at once with one host read: each view's RANSAC triples are drawn
    uniformly among its own consistent pixels, the best plane refined by least squares on its
    inliers (the smallest eigenvector of their covariance, in float64), candidates and colour tests
    are masks of the whole view.

    Args:
        depth: ``(b, 1, H, W)`` depth of the views (valid where ``valid``).
        valid: ``(b, 1, H, W)`` bool, consistent pixels.
        region: ``(b, 1, H, W)`` bool, the region (an instance's mask).
        image: ``(b, 3, H, W)`` the views' colours.
        K: ``(b, 3, 3)`` their intrinsics.
        cam_to_world: ``(b, 4, 4)`` their poses.
        src_images: ``(b, V, 3, Hs, Ws)`` other views of each.
        src_regions: ``(b, V, 1, Hs, Ws)`` bool, the region in them (a colour match outside does
            not count: occluders).
        src_K: ``(b, V, 3, 3)`` their intrinsics.
        src_world_to_cam: ``(b, V, 4, 4)`` their poses.
        config: :class:`PlanarCompletionConfig`.
        generator: seeds RANSAC.
        normal: optional ``(b, 3, H, W)`` camera-frame normals of the valid pixels: inliers must
            agree with the plane's normal within ``config.max_normal_angle`` (when set).

    Returns:
        ``(depth, normal, added)``: the completed depth ``(b, 1, H, W)``, each plane's
        camera-frame normal ``(b, 3)`` facing the camera (zeros where no plane was accepted), and
        ``(b, 1, H, W)`` bool, the pixels filled.

    Example:
        >>> d = torch.full((2, 1, 8, 8), 2.0); K = torch.tensor([[8.0, 0, 3.5], [0, 8.0, 3.5], [0, 0, 1]])
        >>> ok = torch.ones(2, 1, 8, 8, dtype=torch.bool); img = torch.rand(2, 3, 8, 8)
        >>> src = img[:, None]; w2c = torch.eye(4).expand(2, 1, 4, 4)
        >>> Ks, c2w = K.expand(2, 3, 3), torch.eye(4).expand(2, 4, 4)
        >>> out, n, added = complete_planar(d, ok, ok, img, Ks, c2w, src, ok[:, None], Ks[:, None], w2c)
        >>> n[:, 2].tolist(), bool(added.any())  # planes found (facing the camera), nothing to fill
        ([-1.0, -1.0], False)
    """
    cfg = config or PlanarCompletionConfig()
    dims = check_shape(depth, "depth", ("b", 1, "H", "W"))
    check_shape(valid, "valid", ("b", 1, "H", "W"), dims)
    check_shape(region, "region", ("b", 1, "H", "W"), dims)
    check_shape(image, "image", ("b", 3, "H", "W"), dims)
    sd = check_shape(src_images, "src_images", ("b", "V", 3, "Hs", "Ws"), dims)
    check_shape(src_regions, "src_regions", ("b", "V", 1, "Hs", "Ws"), sd)
    b, h, w, v = dims["b"], dims["H"], dims["W"], sd["V"]
    hw, dev, dt = h * w, depth.device, depth.dtype
    none = torch.zeros_like(valid)
    zero_n = torch.zeros(b, 3, dtype=dt, device=dev)
    if v == 0 or b == 0:
        return depth, zero_n, none
    good = (valid & region & (depth > 0)).reshape(b, hw)
    count = good.sum(1)  # (b,)
    # each view's consistent pixels first, in row-major order (as nonzero), padded to the most
    real, order = good.sort(dim=1, descending=True, stable=True)
    most = int(count.max())  # the one host read
    if most < max(cfg.min_pixels, 3):
        return depth, zero_n, none
    idx, real = order[:, :most], real[:, :most]
    pts_all = backproject_depth(depth, K).reshape(b, 3, hw).transpose(1, 2)  # (b, HW, 3) camera frame
    pts = torch.gather(pts_all, 1, idx[..., None].expand(-1, -1, 3))  # (b, N, 3)
    nrm = None
    cos_min = 0.0
    if normal is not None and cfg.max_normal_angle is not None:
        nrm = torch.nn.functional.normalize(normal.reshape(b, 3, hw).transpose(1, 2), dim=-1)
        nrm = torch.gather(nrm, 1, idx[..., None].expand(-1, -1, 3))
        cos_min = math.cos(math.radians(cfg.max_normal_angle))
    thr = cfg.rel_threshold * pts[..., 2]
    # RANSAC: the same number of triples per view, each of its own pixels
    gdev = generator.device if generator is not None else dev
    u = torch.rand((b, cfg.iterations * 3), generator=generator, device=gdev, dtype=torch.float64).to(dev)
    pick = (u * count[:, None]).long().clamp_max((count - 1).clamp_min(0)[:, None])
    tri = torch.gather(pts, 1, pick[..., None].expand(-1, -1, 3)).view(b, cfg.iterations, 3, 3)
    a, bb, c = tri.unbind(2)
    normals = torch.cross(bb - a, c - a, dim=-1)
    norm = normals.norm(dim=-1)
    solid = norm > 1e-9  # (b, T) non-degenerate triples
    normals = normals / norm.clamp_min(1e-30)[..., None]
    offsets = -(normals * a).sum(-1)
    agree = _inliers(pts, thr, normals, offsets, nrm, cos_min) & real[..., None] & solid[:, None]
    best = agree.sum(1).argmax(1)  # (b,): the first triple of the most inliers, as argmax
    plane_n = torch.gather(normals, 1, best[:, None, None].expand(-1, 1, 3))[:, 0]  # (b, 3)
    plane_d = torch.gather(offsets, 1, best[:, None])[:, 0]
    inl = torch.gather(agree, 2, best[:, None, None].expand(-1, agree.shape[1], 1))[..., 0]  # (b, N)
    # least squares on the inliers (>= 3): the smallest eigenvector of their covariance
    wgt = inl.to(torch.float64)
    n_inl = wgt.sum(1)
    p64 = pts.to(torch.float64)
    centre = (p64 * wgt[..., None]).sum(1) / n_inl.clamp_min(1)[:, None]
    x = (p64 - centre[:, None]) * wgt[..., None]
    vec = torch.linalg.eigh(torch.bmm(x.transpose(1, 2), x)).eigenvectors[..., 0].to(dt)  # (b, 3)
    refine = n_inl >= 3
    plane_n = torch.where(refine[:, None], vec, plane_n)
    plane_d = torch.where(refine, -(plane_n * centre.to(dt)).sum(-1), plane_d)
    inl = (
        torch.where(
            refine[:, None], _inliers(pts, thr, plane_n[:, None], plane_d[:, None], nrm, cos_min)[..., 0], inl
        )
        & real
    )
    ratio = inl.sum(1) / count.clamp_min(1)
    z = pts[..., 2]
    z_min = torch.where(inl, z, math.inf).amin(1)
    z_max = torch.where(inl, z, -math.inf).amax(1)
    accept = (count >= cfg.min_pixels) & solid.any(1) & (ratio >= cfg.min_inlier_ratio)
    flip = torch.where(plane_d < 0, -1.0, 1.0).to(dt)  # the camera (origin) on the positive side
    plane_n, plane_d = plane_n * flip[:, None], plane_d * flip
    # candidates: empty region pixels near an inlier, of an accepted plane
    inl_map = torch.zeros(b, hw, dtype=torch.bool, device=dev).scatter_(
        1, idx, inl
    )  # padding: non-good pixels
    near = near_pixels(inl_map.view(b, h, w), cfg.max_gap).view(b, hw)
    cand = (region.reshape(b, hw) & ~good & near) & accept[:, None]
    # every pixel's depth on its view's plane, its colour against the sources'
    flat = torch.arange(hw, device=dev)
    pix = torch.stack([flat % w, flat // w, torch.ones_like(flat)], -1).to(dt)  # (HW, 3)
    rays = pix @ torch.linalg.inv(K).transpose(1, 2)  # (b, HW, 3)
    den = (rays * plane_n[:, None]).sum(-1)
    zp = -plane_d[:, None] / torch.where(den.abs() > 1e-9, den, torch.full_like(den, 1e-9))
    ok = (zp > 0.5 * z_min[:, None]) & (zp < 2.0 * z_max[:, None])
    world = (rays * zp[..., None]) @ cam_to_world[:, :3, :3].transpose(1, 2) + cam_to_world[:, None, :3, 3]
    uv, zs = project_points(
        world[:, None].expand(-1, v, -1, -1).reshape(b * v, hw, 3),
        src_K.reshape(b * v, 3, 3),
        src_world_to_cam.reshape(b * v, 4, 4),
    )
    hs, ws = sd["Hs"], sd["Ws"]
    qx, qy = uv[..., 0].round().long(), uv[..., 1].round().long()
    inside = (zs > 0) & (qx >= 0) & (qx < ws) & (qy >= 0) & (qy < hs)
    q = (qy.clamp(0, hs - 1) * ws + qx.clamp(0, ws - 1))[:, None]  # (b V, 1, HW)
    sc = torch.gather(src_images.reshape(b * v, 3, hs * ws), 2, q.expand(-1, 3, -1))  # (b V, 3, HW)
    colour = image.reshape(b, 1, 3, hw).expand(-1, v, -1, -1).reshape(b * v, 3, hw)
    match = (sc - colour).abs().mean(1) <= cfg.color_tolerance
    seen = torch.gather(src_regions.reshape(b * v, 1, hs * ws), 2, q)[:, 0]
    views = (inside & seen & match).view(b, v, hw).sum(1)
    keep = cand & ok & (views >= cfg.min_views)
    out = torch.where(keep, zp, depth.reshape(b, hw)).view_as(depth)
    return out, torch.where(accept[:, None], plane_n, zero_n), keep.view_as(valid)
