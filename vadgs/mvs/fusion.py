r"""Fusion of consistent depth maps into an oriented, coloured point cloud.

Views are fused one after the other (ACMP / COLMAP style). For every pixel of view :math:`i` that
is valid and not yet claimed, each other view :math:`j` is checked: the 3D point
:math:`X = z\,T_i^{-1} K_i^{-1}\tilde{\mathbf{p}}` projects to pixel :math:`\mathbf{p}_j`
(nearest), whose own depth and normal must agree,

.. math::

    \lVert \pi_i(X_j) - \mathbf{p} \rVert \le \tau_\mathrm{px}, \qquad
    \frac{|z_j - \hat z_j|}{\hat z_j} \le \tau_\mathrm{rel}, \qquad
    \angle(\mathbf{n}, \mathbf{n}_j) \le \tau_\angle,

where :math:`X_j` is view :math:`j`'s point at :math:`\mathbf{p}_j` and :math:`\hat z_j` the depth
of :math:`X` in view :math:`j`. A pixel with at least ``min_views`` agreeing views yields one
point: the mean of the agreeing points, normals (re-normalised) and colours; the agreeing
pixels of the other views are claimed and do not produce duplicates later. The points are ready
to become new Gaussians (position, normal for the orientation, colour for the DC term).

With ``deduplicate=False`` (and ``min_views=0``) the cross-view test is skipped: every valid pixel
of every view becomes one point — for depth maps already filtered by
:func:`~vadgs.mvs.geometric_consistency`, when every observation should seed a Gaussian (the VAD-GS
pipeline, :func:`vadgs.train.vad.reconstruct.reconstruct_instance`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F

from vadgs.checks import Checked, bool_field, check_shape, checked, float_field, int_field
from vadgs.geometry import backproject_depth, invert_rigid, pixel_grid

__all__ = ["FusedPoints", "FusionConfig", "fuse_depth_maps"]


@dataclass(frozen=True)
class FusionConfig(Checked):
    """Thresholds of :func:`fuse_depth_maps`.

    Attributes:
        max_reproj_error: forward–backward reprojection threshold in pixels.
        max_rel_depth: relative depth difference threshold.
        max_normal_angle: normal angle threshold in degrees (``180`` disables the test).
        min_views: other views that must agree for a pixel to become a point (``0``: every
            valid pixel becomes a point, e.g. for a single view already filtered by
            :func:`~vadgs.mvs.geometric_consistency`).
        deduplicate: merge the agreeing pixels of other views into one point (False: no cross-view
            test at all, one point per valid pixel; needs ``min_views=0``).
    """

    max_reproj_error: float = checked(2.0, float_field(0))
    max_rel_depth: float = checked(0.01, float_field(0))
    max_normal_angle: float = checked(30.0, float_field(0, 180))
    min_views: int = checked(2, int_field(0))
    deduplicate: bool = checked(True, bool_field())

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.deduplicate and self.min_views != 0:
            raise ValueError(f"min_views: expected 0 with deduplicate=False, got {self.min_views}")


class FusedPoints(NamedTuple):
    """Output of :func:`fuse_depth_maps` (unbatched, world frame).

    Attributes:
        points: ``(N, 3)`` positions.
        normals: ``(N, 3)`` unit normals (zero where no input normal was given).
        colors: ``(N, C)`` colours in [0, 1].
        view_index: ``(N,)`` int64, the view whose pixel seeded the point.
        num_views: ``(N,)`` int64, the number of views that agreed (the seed included).
    """

    points: torch.Tensor
    normals: torch.Tensor
    colors: torch.Tensor
    view_index: torch.Tensor
    num_views: torch.Tensor


@torch.no_grad()
def fuse_depth_maps(
    depth: torch.Tensor,
    images: torch.Tensor,
    K: torch.Tensor,
    world_to_cam: torch.Tensor,
    normal: torch.Tensor | None = None,
    mask: torch.Tensor | None = None,
    config: FusionConfig | None = None,
) -> FusedPoints:
    """Fuse the depth (and normal) maps of ``B`` views of one scene into a point cloud.

    Not differentiable (runs under :func:`torch.no_grad`).

    Args:
        depth: ``(B, 1, H, W)`` z-depth, 0 where unknown.
        images: ``(B, C, H, W)`` colours in [0, 1].
        K: ``(B, 3, 3)`` intrinsics.
        world_to_cam: ``(B, 4, 4)`` poses (world, or a rigid object's frame).
        normal: optional ``(B, 3, H, W)`` camera-frame normals (zeros where unknown).
        mask: optional ``(B, 1, H, W)`` bool, the pixels allowed to fuse (e.g. the PatchMatch
            mask, or a consistency mask).
        config: a :class:`FusionConfig`.

    Returns:
        A :class:`FusedPoints`.

    Example:
        >>> K = torch.tensor([[10.0, 0, 4.5], [0, 10.0, 4.5], [0, 0, 1]]).repeat(3, 1, 1)
        >>> w2c = torch.eye(4).repeat(3, 1, 1); w2c[:, 0, 3] = torch.tensor([0.0, -0.1, 0.1])
        >>> d = torch.full((3, 1, 10, 10), 2.0)
        >>> fused = fuse_depth_maps(d, torch.rand(3, 3, 10, 10), K, w2c)
        >>> fused.points.shape[1], bool((fused.points[:, 2] - 2).abs().max() < 1e-5)
        (3, True)
    """
    cfg = config or FusionConfig()
    dims = check_shape(depth, "depth", ("B", 1, "H", "W"))
    check_shape(images, "images", ("B", "C", "H", "W"), dims)
    check_shape(K, "K", ("B", 3, 3), dims)
    check_shape(world_to_cam, "world_to_cam", ("B", 4, 4), dims)
    if normal is not None:
        check_shape(normal, "normal", ("B", 3, "H", "W"), dims)
    if mask is not None:
        check_shape(mask, "mask", ("B", 1, "H", "W"), dims)
    b, h, w, c = dims["B"], dims["H"], dims["W"], dims["C"]
    dev, dt = depth.device, depth.dtype
    p = h * w
    z = depth.reshape(b, p)
    valid = torch.isfinite(z) & (z > 0)
    if mask is not None:
        valid &= mask.reshape(b, p)
    pix = pixel_grid((h, w), device=dev, dtype=dt).reshape(p, 2).T  # (2, P)
    cam_to_world = invert_rigid(world_to_cam)
    zc = torch.where(valid, z, torch.zeros_like(z)).reshape(b, 1, h, w)
    pts_world = backproject_depth(zc, K, cam_to_world, method="inverse").reshape(b, 3, p)
    if normal is not None:
        nrm_world = cam_to_world[:, :3, :3] @ normal.reshape(b, 3, p)
    else:
        nrm_world = torch.zeros(b, 3, p, device=dev, dtype=dt)
    cols = images.reshape(b, c, p)
    if not cfg.deduplicate:  # every valid pixel a point of its own (min_views is 0): one read
        flat = valid.reshape(-1).nonzero().flatten()  # in view order, then pixel order
        view = flat // p
        return FusedPoints(
            pts_world.transpose(1, 2).reshape(b * p, 3)[flat],
            F.normalize(nrm_world.transpose(1, 2).reshape(b * p, 3)[flat], dim=1),
            cols.transpose(1, 2).reshape(b * p, c)[flat].clamp(0, 1),
            view,
            torch.ones_like(view),
        )
    cos_max = torch.cos(torch.deg2rad(torch.tensor(cfg.max_normal_angle, dtype=dt, device=dev)))
    used = ~valid
    out_p, out_n, out_c, out_v, out_k, out_keep = [], [], [], [], [], []
    for i in range(b):
        sel = torch.nonzero(~used[i]).flatten()  # the view's one read: its pixels not yet used
        if sel.numel() == 0:
            continue
        x = pts_world[i][:, sel]  # (3, M)
        sum_p, sum_n, sum_c = x.clone(), nrm_world[i][:, sel].clone(), cols[i][:, sel].clone()
        count = torch.ones(sel.shape[0], dtype=torch.long, device=dev)
        hits = []
        for j in range(b):
            if j == i or not cfg.deduplicate:
                continue
            xc = world_to_cam[j, :3, :3] @ x + world_to_cam[j, :3, 3:]
            zj = xc[2]
            uv = (
                K[j, :2, :2] @ (xc[:2] / torch.where(zj > 1e-9, zj, torch.ones_like(zj))) + K[j, :2, 2:]
            ).round()
            inside = (zj > 1e-9) & (uv[0] >= 0) & (uv[0] <= w - 1) & (uv[1] >= 0) & (uv[1] <= h - 1)
            lin = (uv[1].clamp(0, h - 1) * w + uv[0].clamp(0, w - 1)).long()
            ok = inside & valid[j, lin]
            xj = pts_world[j][:, lin]  # view j's own point at that pixel
            back = world_to_cam[i, :3, :3] @ xj + world_to_cam[i, :3, 3:]
            bz = back[2]
            buv = K[i, :2, :2] @ (back[:2] / torch.where(bz > 1e-9, bz, torch.ones_like(bz))) + K[i, :2, 2:]
            err = (buv - pix[:, sel]).norm(dim=0)
            rel = (z[j, lin] - zj).abs() / zj.clamp_min(1e-12)
            ok &= (bz > 1e-9) & (err <= cfg.max_reproj_error) & (rel <= cfg.max_rel_depth)
            if normal is not None:
                ok &= (
                    F.normalize(nrm_world[i][:, sel], dim=0) * F.normalize(nrm_world[j][:, lin], dim=0)
                ).sum(0) >= cos_max
            okf = ok.to(dt)
            sum_p += xj * okf
            sum_n += nrm_world[j][:, lin] * okf
            sum_c += cols[j][:, lin] * okf
            count += ok.long()
            hits.append((j, lin, ok))
        keep = count >= cfg.min_views + 1
        for j, lin, ok in hits:  # used[j, lin[ok & keep]] = True without reading the mask
            taken = torch.zeros(p, dtype=torch.int32, device=dev).index_add_(0, lin, (ok & keep).int())
            used[j] |= taken > 0
        used[i, sel] = True
        out_p.append(sum_p)
        out_n.append(sum_n)
        out_c.append(sum_c)
        out_v.append(torch.full((sel.shape[0],), i, dtype=torch.long, device=dev))
        out_k.append(count)
        out_keep.append(keep)
    if not out_p:
        empty = torch.zeros(0, 3, device=dev, dtype=dt)
        idx = torch.zeros(0, dtype=torch.long, device=dev)
        return FusedPoints(empty, empty.clone(), torch.zeros(0, c, device=dev, dtype=dt), idx, idx.clone())
    # the kept candidates of every view in one read, in view order
    k = torch.cat(out_keep).nonzero().flatten()
    counts = torch.cat(out_k)[k]
    n_k = counts.to(dt)
    return FusedPoints(
        (torch.cat(out_p, 1)[:, k] / n_k).T,
        F.normalize(torch.cat(out_n, 1)[:, k], dim=0).T,
        (torch.cat(out_c, 1)[:, k] / n_k).T.clamp(0, 1),
        torch.cat(out_v)[k],
        counts,
    )
