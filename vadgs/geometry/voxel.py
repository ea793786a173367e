r"""Voxel grids with per-voxel visibility sets (paper, "Voxel-Based Visibility Reasoning").

The initial points (accumulated LiDAR, SfM) are voxelised to a uniform density. Each voxel keeps
its centre, the mean of its points, its point count and its **visibility set**: the union of the
views that observed its points. A LiDAR point is observed by the cameras of its own frame that
see it (:func:`observing_views`); an SfM point by the images of its COLMAP track. Visibility is
stored sparsely as CSR (voxel → sorted view ids), which scales to :math:`10^6` voxels ×
:math:`10^3` views: memory is linear in the number of (voxel, view) pairs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from vadgs.checks import check_finite, check_shape
from vadgs.geometry.camera import Cameras, project_points

__all__ = ["MAX_VOXEL_CELLS", "VoxelGrid", "check_voxel_size", "observing_views", "voxelize"]

#: Most cells per axis a voxel size may make of a point set (integer coordinates stay exact).
MAX_VOXEL_CELLS = 2**40


def check_voxel_size(offsets: torch.Tensor, voxel_size: float, name: str = "voxel_size") -> None:
    """Raise a :class:`ValueError` when ``voxel_size`` cuts ``offsets`` into too many cells per axis.

    ``offsets`` are the points relative to the grid's origin (or the points themselves for a grid
    at 0). Beyond :data:`MAX_VOXEL_CELLS` cells per axis the integer cell coordinates lose
    precision and then overflow int64 (``voxel_size=1e-30`` merged distant points silently).

    Example:
        >>> check_voxel_size(torch.tensor([[50.0, 0.0, 0.0]]), 1e-30)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        ValueError: voxel_size: 1e-30 makes 5e+31 cells along an axis (points up to 50 from the origin)...
    """
    if offsets.numel() == 0 or not voxel_size > 0:
        return
    reach = float(offsets.detach().abs().max())
    cells = reach / voxel_size
    if not cells <= MAX_VOXEL_CELLS:
        raise ValueError(
            f"{name}: {voxel_size:g} makes {cells:.3g} cells along an axis (points up to {reach:.3g} from "
            f"the origin); expected at most {MAX_VOXEL_CELLS:.3g} ({name} >= {reach / MAX_VOXEL_CELLS:.3g})"
        )


@dataclass(frozen=True)
class VoxelGrid:
    """A sparse voxel grid with visibility sets.

    Voxel ``m`` spans ``origin + coords[m] * voxel_size`` to ``origin + (coords[m] + 1) * voxel_size``.
    Visibility is CSR: the views that observed voxel ``m`` are
    ``vis_views[vis_indptr[m]:vis_indptr[m + 1]]`` (sorted, unique).

    Attributes:
        voxel_size: edge length in world units.
        origin: ``(3,)`` world position of the corner of voxel ``(0, 0, 0)``.
        coords: ``(M, 3)`` int64 integer voxel coordinates.
        means: ``(M, 3)`` mean of the points in each voxel.
        counts: ``(M,)`` int64 number of points in each voxel.
        vis_indptr: ``(M + 1,)`` int64 CSR row pointers.
        vis_views: ``(nnz,)`` int64 view ids.
        num_views: number of views the ids refer to.
        point_to_voxel: ``(N,)`` int64 voxel of each input point.
        normals: ``(M, 3)`` unit normal of the plane fitted to the points of each voxel and its
            26 neighbours (smallest principal axis, sign arbitrary), ``0`` where no clear plane.
    """

    voxel_size: float
    origin: torch.Tensor
    coords: torch.Tensor
    means: torch.Tensor
    counts: torch.Tensor
    vis_indptr: torch.Tensor
    vis_views: torch.Tensor
    num_views: int
    point_to_voxel: torch.Tensor
    normals: torch.Tensor

    def __len__(self) -> int:
        return self.coords.shape[0]

    @property
    def centers(self) -> torch.Tensor:
        """``(M, 3)`` voxel centres."""
        return self.origin + (self.coords.to(self.origin.dtype) + 0.5) * self.voxel_size

    @property
    def vis_voxels(self) -> torch.Tensor:
        """``(nnz,)`` the voxel of each CSR entry (row index expanded)."""
        return torch.repeat_interleave(
            torch.arange(len(self), device=self.coords.device), self.vis_indptr.diff()
        )

    def views_of(self, voxel: int) -> torch.Tensor:
        """Sorted view ids that observed ``voxel``."""
        return self.vis_views[self.vis_indptr[voxel] : self.vis_indptr[voxel + 1]]

    def seen_by(self, view: int) -> torch.Tensor:
        """``(M,)`` bool: voxels whose visibility set contains ``view``."""
        mask = torch.zeros(len(self), dtype=torch.bool, device=self.coords.device)
        mask[self.vis_voxels[self.vis_views == view]] = True
        return mask

    def candidate_views(self, voxels: torch.Tensor) -> torch.Tensor:
        """Union of the visibility sets of ``voxels`` (ids or a bool mask): sorted view ids."""
        if voxels.dtype == torch.bool:
            voxels = voxels.nonzero().squeeze(1)
        starts, ends = self.vis_indptr[voxels], self.vis_indptr[voxels + 1]
        lens = ends - starts
        if int(lens.sum()) == 0:
            return torch.zeros(0, dtype=torch.int64, device=self.coords.device)
        offs = torch.arange(int(lens.sum()), device=lens.device) - torch.repeat_interleave(
            lens.cumsum(0) - lens, lens
        )
        return torch.unique(self.vis_views[torch.repeat_interleave(starts, lens) + offs])

    def incidence(self) -> torch.Tensor:
        """Sparse ``(num_views, M)`` 0/1 COO matrix: ``[v, m] = 1`` if view ``v`` observed voxel ``m``."""
        idx = torch.stack([self.vis_views, self.vis_voxels])
        vals = torch.ones(idx.shape[1], dtype=self.means.dtype, device=idx.device)
        return torch.sparse_coo_tensor(idx, vals, (self.num_views, len(self)), is_coalesced=False).coalesce()

    def subset(self, keep: torch.Tensor) -> VoxelGrid:
        """The grid restricted to ``keep`` (ids or bool mask); voxels are renumbered in order.

        ``point_to_voxel`` maps dropped voxels' points to ``-1``.
        """
        if keep.dtype != torch.bool:
            mask = torch.zeros(len(self), dtype=torch.bool, device=keep.device)
            mask[keep] = True
            keep = mask
        new_id = torch.full((len(self),), -1, dtype=torch.int64, device=keep.device)
        new_id[keep] = torch.arange(int(keep.sum()), device=keep.device)
        entry_keep = keep[self.vis_voxels]
        lens = self.vis_indptr.diff()[keep]
        indptr = torch.zeros(len(lens) + 1, dtype=torch.int64, device=keep.device)
        indptr[1:] = lens.cumsum(0)
        p2v = self.point_to_voxel
        return VoxelGrid(
            self.voxel_size,
            self.origin,
            self.coords[keep],
            self.means[keep],
            self.counts[keep],
            indptr,
            self.vis_views[entry_keep],
            self.num_views,
            torch.where(p2v >= 0, new_id[p2v.clamp(min=0)], p2v),
            self.normals[keep],
        )

    def __repr__(self) -> str:
        return (
            f"VoxelGrid({len(self)} voxels of {self.voxel_size} m, {self.vis_views.numel()} "
            f"voxel-view pairs over {self.num_views} views)"
        )


def voxelize(
    points: torch.Tensor,
    voxel_size: float,
    point_views: tuple[torch.Tensor, torch.Tensor] | None = None,
    num_views: int | None = None,
    origin: torch.Tensor | None = None,
) -> VoxelGrid:
    """Voxelise points and build each voxel's visibility set.

    Not differentiable (the grid is a discrete structure; ``means`` are plain averages).

    Args:
        points: ``(N, 3)`` finite points, ``N >= 1``.
        voxel_size: voxel edge length (> 0).
        point_views: optional observation table as COO pairs ``(point_idx (P,), view_idx (P,))``:
            view ``view_idx[i]`` observed point ``point_idx[i]`` (a COLMAP TRACK table, or the
            output of :func:`observing_views` for LiDAR). Without it every visibility set is empty.
        num_views: the number of views the ids refer to (default: ``max(view_idx) + 1``).
        origin: ``(3,)`` grid origin (default: the points' minimum, floored to the voxel size),
            to align several grids.

    Returns:
        The :class:`VoxelGrid`, voxels sorted by their integer coordinates.

    Raises:
        ValueError: on an empty or non-finite point set, a non-positive voxel size, or an
            observation table that does not match the points.

    Example:
        >>> pts = torch.tensor([[0.05, 0.05, 0.05], [0.15, 0.02, 0.01], [0.31, 0.0, 0.0]])
        >>> grid = voxelize(pts, 0.2, (torch.tensor([0, 1, 2]), torch.tensor([0, 1, 1])), num_views=2)
        >>> len(grid), grid.counts.tolist(), grid.views_of(0).tolist(), grid.views_of(1).tolist()
        (2, [2, 1], [0, 1], [1])
    """
    check_shape(points, "points", ("N", 3))
    if points.shape[0] == 0:
        raise ValueError("points: expected at least one point, got an empty (0, 3) tensor")
    check_finite(points, "points")
    if not voxel_size > 0:
        raise ValueError(f"voxel_size: expected a positive number, got {voxel_size}")
    device = points.device
    check_voxel_size(points, voxel_size)  # the origin's cell first (points / voxel_size may overflow)
    if origin is None:
        origin = torch.floor(points.min(0).values / voxel_size) * voxel_size
    else:
        check_shape(origin, "origin", (3,))
        origin = origin.to(points)
    check_voxel_size(points - origin, voxel_size)
    coords = torch.floor((points - origin) / voxel_size).long()
    cmin = coords.min(0).values
    c = coords - cmin
    ext = c.max(0).values + 1
    key = (c[:, 0] * ext[1] + c[:, 1]) * ext[2] + c[:, 2]
    ukey, p2v = torch.unique(key, return_inverse=True)
    m = ukey.numel()
    counts = torch.bincount(p2v, minlength=m)
    means = torch.zeros(m, 3, dtype=points.dtype, device=device).index_add_(0, p2v, points)
    means = means / counts[:, None].to(points.dtype)
    ucoords = torch.stack([ukey // (ext[1] * ext[2]), (ukey // ext[2]) % ext[1], ukey % ext[2]], 1)
    normals = _voxel_normals(points, means, p2v, ukey, ucoords, ext)
    ucoords = ucoords + cmin

    if point_views is None:
        indptr = torch.zeros(m + 1, dtype=torch.int64, device=device)
        views = torch.zeros(0, dtype=torch.int64, device=device)
        num_views = int(num_views or 0)
    else:
        pidx, vidx = point_views
        check_shape(pidx, "point_views[0]", ("P",))
        check_shape(vidx, "point_views[1]", ("P",), {"P": pidx.shape[0]})
        if pidx.numel() and (int(pidx.min()) < 0 or int(pidx.max()) >= points.shape[0]):
            raise ValueError(
                f"point_views[0]: point ids must lie in [0, {points.shape[0]}), got out-of-range ids"
            )
        if vidx.numel() and int(vidx.min()) < 0:
            raise ValueError("point_views[1]: view ids must be non-negative")
        nv = int(vidx.max()) + 1 if vidx.numel() else 0
        num_views = nv if num_views is None else int(num_views)
        if nv > num_views:
            raise ValueError(f"point_views[1]: view id {nv - 1} >= num_views={num_views}")
        pair = torch.unique(p2v[pidx.long()] * max(num_views, 1) + vidx.long())
        vox, views = pair // max(num_views, 1), pair % max(num_views, 1)
        indptr = torch.zeros(m + 1, dtype=torch.int64, device=device)
        indptr[1:] = torch.bincount(vox, minlength=m).cumsum(0)
    return VoxelGrid(
        float(voxel_size), origin, ucoords, means, counts, indptr, views, num_views, p2v, normals
    )


def _voxel_normals(
    points: torch.Tensor,
    means: torch.Tensor,
    p2v: torch.Tensor,
    keys: torch.Tensor,
    coords: torch.Tensor,
    ext: torch.Tensor,
    flatness: float = 0.25,
) -> torch.Tensor:
    """Per-voxel plane normals by PCA of the points of the voxel and its 26 neighbours.

    Pooling the 3×3×3 neighbourhood makes planes estimable from sparse LiDAR (a few points per
    voxel). A voxel gets a normal when the pooled covariance has at least 3 points and its
    smallest eigenvalue is below ``flatness`` times the middle one; otherwise 0.
    """
    m = means.shape[0]
    dt = points.dtype
    # centred at the voxel means for numerical stability: sums of d and d d^T per voxel
    d = (points - means[p2v]).double()
    cnt = torch.bincount(p2v, minlength=m).double()
    s1 = torch.zeros(m, 3, dtype=torch.float64, device=points.device).index_add_(0, p2v, d)
    s2 = torch.zeros(m, 3, 3, dtype=torch.float64, device=points.device).index_add_(
        0, p2v, d[:, :, None] * d[:, None, :]
    )
    # each voxel's raw sums, once: sum p = s1 + n mu, sum p p^T = s2 + mu s1^T + s1 mu^T + n mu mu^T
    mu = means.double()
    raw1 = s1 + cnt[:, None] * mu
    raw2 = (
        s2
        + mu[:, :, None] * s1[:, None, :]
        + s1[:, :, None] * mu[:, None, :]
        + cnt[:, None, None] * mu[:, :, None] * mu[:, None, :]
    )
    n_tot = torch.zeros_like(cnt)
    p_tot = torch.zeros(m, 3, dtype=torch.float64, device=points.device)
    pp_tot = torch.zeros(m, 3, 3, dtype=torch.float64, device=points.device)
    offsets = torch.tensor(
        [[i, j, k] for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)], device=points.device
    )
    for off in offsets:
        c = coords + off
        inside = ((c >= 0) & (c < ext)).all(1)
        key = (c[:, 0] * ext[1] + c[:, 1]) * ext[2] + c[:, 2]
        pos = torch.searchsorted(keys, key).clamp(max=m - 1)
        i = (inside & (keys[pos] == key)).nonzero().squeeze(1)  # voxels whose neighbour exists
        j = pos[i]
        n_tot.index_add_(0, i, cnt[j])
        p_tot.index_add_(0, i, raw1[j])
        pp_tot.index_add_(0, i, raw2[j])
    mean = p_tot / n_tot.clamp(min=1)[:, None]
    cov = pp_tot / n_tot.clamp(min=1)[:, None, None] - mean[:, :, None] * mean[:, None, :]
    evals, evecs = torch.linalg.eigh(cov)
    normal = evecs[:, :, 0].to(dt)
    planar = (n_tot >= 3) & (evals[:, 0] <= flatness * evals[:, 1]) & (evals[:, 1] > 0)
    return torch.where(planar[:, None], normal, torch.zeros_like(normal))


def observing_views(
    points: torch.Tensor,
    cameras: Cameras,
    view_ids: Sequence[int] | torch.Tensor | None = None,
    groups: tuple[torch.Tensor, torch.Tensor] | None = None,
    near: float = 0.1,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Which cameras see which points: points in front of a camera that project inside its image.

    For LiDAR, a point is observed by the cameras *of its own frame* that see it: pass
    ``groups=(point_frame, camera_frame)`` so that each point is tested only against the cameras
    of the same group (processed group by group, so memory stays ``O(N_group × B_group)``).
    Occlusion is not tested here; the voxel z-buffer resolves it.

    Args:
        points: ``(N, 3)`` world points.
        cameras: ``B`` cameras.
        view_ids: ``(B,)`` the view id of each camera (default ``0..B-1``).
        groups: optional ``(point_group (N,), camera_group (B,))`` integer labels.
        near: minimum z-depth.

    Returns:
        COO pairs ``(point_idx, view_idx)``, each ``(P,)`` int64, sorted by point.

    Example:
        >>> K = torch.tensor([[[10.0, 0, 4.5], [0, 10.0, 4.5], [0, 0, 1]]])
        >>> cams = Cameras(K, torch.eye(4)[None], (10, 10))
        >>> observing_views(torch.tensor([[0.0, 0, 2], [0, 0, -2], [5, 0, 1]]), cams)
        (tensor([0]), tensor([0]))
    """
    check_shape(points, "points", ("N", 3))
    b = len(cameras)
    ids = torch.arange(b) if view_ids is None else torch.as_tensor(view_ids, dtype=torch.int64)
    if ids.shape != (b,):
        raise ValueError(f"view_ids: expected shape ({b},), got {tuple(ids.shape)}")
    ids = ids.to(points.device)
    if groups is None:
        point_sel = [torch.arange(points.shape[0], device=points.device)]
        cam_sel = [torch.arange(b, device=points.device)]
    else:
        pg, cg = groups
        check_shape(pg, "groups[0]", (points.shape[0],))
        check_shape(cg, "groups[1]", (b,))
        labels = torch.unique(cg)
        point_sel = [(pg == g).nonzero().squeeze(1) for g in labels]
        cam_sel = [(cg == g).nonzero().squeeze(1) for g in labels]
    h, w = cameras.image_size
    out_p, out_v = [], []
    for psel, csel in zip(point_sel, cam_sel):
        if psel.numel() == 0:
            continue
        sub = cameras[csel]
        uv, z = project_points(points[psel].expand(len(sub), -1, -1), sub.K, sub.world_to_cam)
        u, v = uv[..., 0], uv[..., 1]
        ok = (z > near) & (u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5)
        bi, pi = ok.nonzero(as_tuple=True)
        out_p.append(psel[pi])
        out_v.append(ids[csel[bi]])
    if not out_p:
        empty = torch.zeros(0, dtype=torch.int64, device=points.device)
        return empty, empty.clone()
    pidx, vidx = torch.cat(out_p), torch.cat(out_v)
    order = torch.argsort(pidx * (int(ids.max()) + 1) + vidx)
    return pidx[order], vidx[order]
