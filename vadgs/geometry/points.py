"""Point clouds on a grid: averaged per voxel, thinned to one per cell, and their spacing.

:func:`voxel_downsample` averages points and colours per voxel (:class:`VoxelAccumulator`: the
same for points given in chunks, memory following the voxels); :func:`thin_points` keeps the first
point of each cell and none in cells other points occupy; :func:`knn_scales` is the root-mean-square
distance to the ``k`` nearest neighbours (3DGS's initial scale). Used by the trainer's
initialisation (:func:`vadgs.train.init.init_gaussians`) and by VAD-GS's fusion of new points.
"""

from __future__ import annotations

import numpy as np
import torch

from vadgs.geometry.voxel import check_voxel_size, unique_cells

__all__ = ["VoxelAccumulator", "knn_scales", "thin_points", "voxel_downsample"]


def voxel_downsample(
    points: torch.Tensor, colors: torch.Tensor, voxel_size: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Average points and colours per voxel.

    Args:
        points: ``(N, 3)``.
        colors: ``(N, C)``.
        voxel_size: edge length; ``0`` keeps every point.

    Returns:
        ``(M, 3)`` points and ``(M, C)`` colours, ``M <= N``.

    Example:
        >>> p = torch.tensor([[0.01, 0.0, 0.0], [0.03, 0.0, 0.0], [1.0, 0.0, 0.0]])
        >>> voxel_downsample(p, torch.ones(3, 1), 0.1)[0][:, 0].tolist()
        [0.019999999552965164, 1.0]
    """
    if voxel_size <= 0 or points.shape[0] == 0:
        return points, colors
    check_voxel_size(points, voxel_size)
    keys = torch.floor(points / voxel_size).long()
    _, inv = unique_cells(keys)
    m = int(inv.max()) + 1
    cnt = torch.zeros(m, dtype=points.dtype, device=points.device).index_add_(
        0, inv, torch.ones_like(points[:, 0])
    )
    p = torch.zeros(m, 3, dtype=points.dtype, device=points.device).index_add_(0, inv, points) / cnt[:, None]
    c = torch.zeros(m, colors.shape[1], dtype=colors.dtype, device=colors.device).index_add_(0, inv, colors)
    return p, c / cnt[:, None].to(colors.dtype)


class VoxelAccumulator:
    """:func:`voxel_downsample` of points given in chunks: memory follows the voxels, not the points.

    Each chunk's points and colours are summed into the voxels met so far, so the result of
    :meth:`add` for every chunk then :meth:`result` equals ``voxel_downsample`` of all chunks
    concatenated in order (the same additions, voxel by voxel, in the same order: bit for bit on
    one thread), while only the occupied voxels are held: initialising from a 200-frame segment's
    30 million LiDAR points holds their voxels, not the points.

    Example:
        >>> p = torch.tensor([[0.01, 0.0, 0.0], [0.03, 0.0, 0.0], [1.0, 0.0, 0.0]])
        >>> acc = VoxelAccumulator(0.1)
        >>> acc.add(p[:1], torch.ones(1, 1)); acc.add(p[1:], torch.ones(2, 1))
        >>> all(torch.equal(a, b) for a, b in zip(acc.result(), voxel_downsample(p, torch.ones(3, 1), 0.1)))
        True
    """

    def __init__(self, voxel_size: float) -> None:
        self.voxel_size = voxel_size
        self._keys: torch.Tensor | None = None  # (M, 3) sorted voxel keys
        self._sums: torch.Tensor | None = None  # (M, 3 + C): points, colours
        self._count: torch.Tensor | None = None  # (M,)
        self._kept: list[torch.Tensor] = []  # voxel_size <= 0: every point

    def add(self, points: torch.Tensor, colors: torch.Tensor) -> None:
        """Add ``(N, 3)`` points and their ``(N, C)`` colours."""
        if points.shape[0] == 0:
            return
        both = torch.cat([points, colors.to(points.dtype)], 1)
        if self.voxel_size <= 0:
            self._kept.append(both)
            return
        check_voxel_size(points, self.voxel_size)
        keys = torch.floor(points / self.voxel_size).long()
        ones = torch.ones_like(points[:, 0])
        if self._keys is not None:  # the voxels so far first: their sums are added before the new points
            assert self._sums is not None and self._count is not None  # set with _keys
            keys = torch.cat([self._keys, keys])
            both = torch.cat([self._sums, both])
            ones = torch.cat([self._count, ones])
        self._keys, inv = unique_cells(keys)
        m = self._keys.shape[0]
        self._count = torch.zeros(m, dtype=points.dtype, device=points.device).index_add_(0, inv, ones)
        self._sums = torch.zeros(m, both.shape[1], dtype=points.dtype, device=points.device).index_add_(
            0, inv, both
        )

    def result(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The ``(M, 3)`` points and ``(M, C)`` colours (each voxel's mean)."""
        if self.voxel_size <= 0:
            both = torch.cat(self._kept) if self._kept else torch.zeros(0, 6)
            return both[:, :3], both[:, 3:]
        if self._keys is None:
            return torch.zeros(0, 3), torch.zeros(0, 3)
        assert self._sums is not None and self._count is not None  # set with _keys
        cnt = self._count[:, None]
        return self._sums[:, :3] / cnt, self._sums[:, 3:] / cnt


def thin_points(
    points: torch.Tensor, cell: float | torch.Tensor, existing: torch.Tensor | None = None
) -> torch.Tensor:
    """Keep one point per ``cell``-sized voxel, and none in a voxel that ``existing`` points occupy.

    Args:
        points: ``(P, 3)``, in their priority order (the first point of a voxel is kept).
        cell: voxel edge.
        existing: optional ``(Q, 3)`` points (same frame) whose voxels are taken.

    Returns:
        ``(P,)`` bool: the points kept. On the device of ``points``.

    Example:
        >>> p = torch.tensor([[0.01, 0.0, 0.0], [0.02, 0.0, 0.0], [0.31, 0.0, 0.0]])
        >>> thin_points(p, 0.1).tolist()
        [True, False, True]
        >>> thin_points(p, 0.1, existing=torch.tensor([[0.35, 0.05, 0.05]])).tolist()
        [True, False, False]
    """
    if points.shape[0] == 0:
        return torch.zeros(0, dtype=torch.bool, device=points.device)
    cell = torch.as_tensor(cell, dtype=points.dtype, device=points.device).clamp_min(1e-6)
    every = points if existing is None else torch.cat([existing.to(points), points])
    q = torch.floor(every / cell).long()
    q = q - q.min(0).values
    span = q.max(0).values + 1
    keys = (q[:, 0] * span[1] + q[:, 1]) * span[2] + q[:, 2]
    # the first point of each voxel: a stable sort keeps each voxel's points in their order
    order = torch.argsort(keys, stable=True)
    ordered = keys[order]
    first = torch.ones_like(ordered, dtype=torch.bool)
    first[1:] = ordered[1:] != ordered[:-1]
    keep = torch.zeros_like(first).scatter_(0, order, first)
    return keep[every.shape[0] - points.shape[0] :]


def knn_scales(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """Root-mean-square distance of every point to its ``k`` nearest neighbours (3DGS's initial scale).

    Uses SciPy's ``cKDTree``. Not differentiable.

    Args:
        points: ``(N, 3)``.
        k: neighbours.

    Returns:
        ``(N,)`` distances (``1.0`` for a lone point).

    Example:
        >>> knn_scales(torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0]]), k=1).tolist()
        [1.0, 1.0, 2.0]
    """
    n = points.shape[0]
    if n < 2:
        return torch.ones(n, dtype=points.dtype, device=points.device)
    from scipy.spatial import cKDTree

    pts = points.detach().cpu().double().numpy()
    kk = min(k, n - 1)
    d, _ = cKDTree(pts).query(pts, k=kk + 1)
    rms = np.sqrt((d[:, 1:] ** 2).mean(1))
    return torch.from_numpy(rms).to(points)
