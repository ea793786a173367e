r"""Multi-view geometric consistency of depth maps (forward–backward reprojection).

A reference pixel :math:`\mathbf{p}` with depth :math:`z` is back-projected, transformed into a
source view and projected to :math:`\mathbf{p}_s` (nearest pixel). The source depth there is
back-projected in turn and brought back into the reference, landing at :math:`\mathbf{p}'` with
depth :math:`z'`. The view agrees with the pixel when

.. math::

    \lVert \mathbf{p}' - \mathbf{p} \rVert \le \tau_\mathrm{px}
    \quad\text{and}\quad
    \frac{|z' - z|}{z} \le \tau_\mathrm{rel},

(ACMP / COLMAP fusion use about 1–2 px and 1 %), and the pixel is kept when at least
``min_views`` source views agree. Not differentiable (boolean output); the error maps are
differentiable w.r.t. the reference depth almost everywhere, but nothing relies on it.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from vadgs.checks import check_shape
from vadgs.geometry import backproject_depth, invert_rigid, pixel_grid, relative_pose

__all__ = ["ConsistencyResult", "geometric_consistency", "reproject_depth"]


class ConsistencyResult(NamedTuple):
    """Output of :func:`geometric_consistency`.

    Attributes:
        mask: ``(B, 1, H, W)`` bool, pixels with a depth that at least ``min_views`` views agree
            with.
        num_consistent: ``(B, 1, H, W)`` int64, the number of agreeing views.
        view_consistent: ``(B, V, H, W)`` bool, the per-view verdicts.
        reproj_error: ``(B, V, H, W)`` forward–backward reprojection error in pixels (``inf``
            where the pixel has no depth, leaves the source image or meets no source depth).
        rel_depth_error: ``(B, V, H, W)`` relative depth difference ``|z' - z| / z`` (``inf``
            likewise).
    """

    mask: torch.Tensor
    num_consistent: torch.Tensor
    view_consistent: torch.Tensor
    reproj_error: torch.Tensor
    rel_depth_error: torch.Tensor


def _project(points: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera points ``(N, 3, P)`` → pixels ``(N, 2, P)`` and depth ``(N, P)``."""
    z = points[:, 2]
    zs = torch.where(z > 1e-9, z, torch.ones_like(z))
    uv = K[:, :2, :2] @ (points[:, :2] / zs[:, None]) + K[:, :2, 2:]
    return uv, z


def reproject_depth(
    depth: torch.Tensor,
    K: torch.Tensor,
    src_depth: torch.Tensor,
    src_K: torch.Tensor,
    src_from_ref: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward–backward reprojection of reference depth maps through source depth maps.

    Args:
        depth: ``(N, 1, H, W)`` reference z-depth (0 = none).
        K: ``(N, 3, 3)`` reference intrinsics.
        src_depth: ``(N, 1, Hs, Ws)`` source z-depth (0 = none).
        src_K: ``(N, 3, 3)`` source intrinsics.
        src_from_ref: ``(N, 4, 4)`` reference-to-source camera transforms.

    Returns:
        ``(reproj_error, rel_depth_error)``, each ``(N, H, W)``; ``inf`` where undefined.

    Example:
        >>> K = torch.tensor([[[10.0, 0, 4.5], [0, 10.0, 4.5], [0, 0, 1]]])
        >>> T = torch.eye(4)[None]; T[0, 0, 3] = -0.2  # 1 px disparity
        >>> d = torch.full((1, 1, 10, 10), 2.0)
        >>> err, rel = reproject_depth(d, K, d, K, T)
        >>> float(err[0, 5, 5]), float(rel[0, 5, 5])
        (0.0, 0.0)
    """
    dims = check_shape(depth, "depth", ("N", 1, "H", "W"))
    check_shape(K, "K", ("N", 3, 3), dims)
    check_shape(src_depth, "src_depth", ("N", 1, "Hs", "Ws"), dims)
    check_shape(src_K, "src_K", ("N", 3, 3), dims)
    check_shape(src_from_ref, "src_from_ref", ("N", 4, 4), dims)
    n, h, w = dims["N"], dims["H"], dims["W"]
    hs, ws = dims["Hs"], dims["Ws"]
    pix = pixel_grid((h, w), device=depth.device, dtype=depth.dtype).reshape(1, h * w, 2).transpose(1, 2)
    z = depth.reshape(n, 1, h * w)
    pts = backproject_depth(depth, K, method="inverse").reshape(n, 3, h * w)  # reference camera
    rot, t = src_from_ref[:, :3, :3], src_from_ref[:, :3, 3:]
    uv_s, z_s = _project(rot @ pts + t, src_K)
    uv_r = torch.nan_to_num(uv_s.round(), nan=-1.0, posinf=-1.0, neginf=-1.0)  # inf/NaN depth: outside
    inside = (uv_r[:, 0] >= 0) & (uv_r[:, 0] <= ws - 1) & (uv_r[:, 1] >= 0) & (uv_r[:, 1] <= hs - 1)
    lin = (uv_r[:, 1].clamp(0, hs - 1) * ws + uv_r[:, 0].clamp(0, ws - 1)).long()
    d_s = torch.gather(src_depth.reshape(n, hs * ws), 1, lin)  # (N, P)
    # the source's points at those pixels (where inside, the pixel is uv_r)
    src_pts = backproject_depth(src_depth, src_K, method="inverse").reshape(n, 3, hs * ws)
    pts_s = torch.gather(src_pts, 2, lin[:, None].expand(-1, 3, -1))
    back = invert_rigid(src_from_ref)
    uv_b, z_b = _project(back[:, :3, :3] @ pts_s + back[:, :3, 3:], K)
    ok = (z[:, 0] > 0) & (z_s > 1e-9) & inside & (d_s > 0) & (z_b > 1e-9)
    err = (uv_b - pix).norm(dim=1)
    rel = (z_b - z[:, 0]).abs() / z[:, 0].clamp_min(1e-12)
    inf = torch.full_like(err, float("inf"))
    err = torch.where(ok & torch.isfinite(err), err, inf)
    rel = torch.where(ok & torch.isfinite(rel), rel, inf)
    return err.reshape(n, h, w), rel.reshape(n, h, w)


def geometric_consistency(
    depth: torch.Tensor,
    K: torch.Tensor,
    world_to_cam: torch.Tensor,
    src_depth: torch.Tensor,
    src_K: torch.Tensor,
    src_world_to_cam: torch.Tensor,
    max_reproj_error: float = 1.0,
    max_rel_depth: float = 0.01,
    min_views: int = 2,
) -> ConsistencyResult:
    """Keep the pixels of reference depth maps that source depth maps agree with.

    Runs under :func:`torch.no_grad`.

    Args:
        depth: ``(B, 1, H, W)`` reference z-depth, 0 where unknown.
        K: ``(B, 3, 3)`` reference intrinsics.
        world_to_cam: ``(B, 4, 4)`` reference poses.
        src_depth: ``(B, V, 1, Hs, Ws)`` depth maps of the ``V`` source views, 0 where unknown.
        src_K: ``(B, V, 3, 3)`` source intrinsics.
        src_world_to_cam: ``(B, V, 4, 4)`` source poses.
        max_reproj_error: forward–backward reprojection threshold in pixels.
        max_rel_depth: relative depth-difference threshold.
        min_views: number of agreeing views required (``<= V``).

    Returns:
        A :class:`ConsistencyResult`.

    Example:
        >>> K = torch.tensor([[[10.0, 0, 4.5], [0, 10.0, 4.5], [0, 0, 1]]])
        >>> w2c = torch.eye(4)[None]
        >>> src_w2c = torch.eye(4).repeat(1, 2, 1, 1); src_w2c[0, :, 0, 3] = torch.tensor([-0.2, 0.2])
        >>> d = torch.full((1, 1, 10, 10), 2.0)
        >>> src_d, src_K = d[:, None].repeat(1, 2, 1, 1, 1), K[:, None].repeat(1, 2, 1, 1)
        >>> res = geometric_consistency(d, K, w2c, src_d, src_K, src_w2c)
        >>> int(res.mask.sum())  # all but the columns that leave one of the sources
        80
    """
    dims = check_shape(depth, "depth", ("B", 1, "H", "W"))
    check_shape(K, "K", ("B", 3, 3), dims)
    check_shape(world_to_cam, "world_to_cam", ("B", 4, 4), dims)
    if src_depth.ndim != 5:
        raise ValueError(f"src_depth: expected shape (B, V, 1, Hs, Ws), got {tuple(src_depth.shape)}")
    check_shape(src_depth, "src_depth", ("B", "V", 1, "Hs", "Ws"), dims)
    check_shape(src_K, "src_K", ("B", "V", 3, 3), dims)
    check_shape(src_world_to_cam, "src_world_to_cam", ("B", "V", 4, 4), dims)
    if not 0 <= min_views <= dims["V"]:
        raise ValueError(f"min_views: expected 0 <= min_views <= V={dims['V']}, got {min_views}")
    b, v, h, w = dims["B"], dims["V"], dims["H"], dims["W"]
    with torch.no_grad():
        src_from_ref = relative_pose(world_to_cam[:, None], src_world_to_cam).reshape(b * v, 4, 4)
        err, rel = reproject_depth(
            depth.repeat_interleave(v, 0),
            K.repeat_interleave(v, 0),
            src_depth.reshape(b * v, 1, dims["Hs"], dims["Ws"]),
            src_K.reshape(b * v, 3, 3),
            src_from_ref,
        )
        err, rel = err.reshape(b, v, h, w), rel.reshape(b, v, h, w)
        agree = (err <= max_reproj_error) & (rel <= max_rel_depth)
        count = agree.sum(1, keepdim=True)
        has_depth = torch.isfinite(depth) & (depth > 0)
        mask = has_depth & (count >= min_views)
    return ConsistencyResult(mask, count, agree, err, rel)
