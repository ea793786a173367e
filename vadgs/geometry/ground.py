"""A scene's ground frame: the cameras' up, the points' principal ground axes, their median.

:func:`ground_frame` measures it (optionally turned onto the scene's walls); :func:`points_in_frame`
expresses points in it. Pure geometry: VAD-GS's visibility index cuts its derived instances
(:func:`ground_cells`) and thins new points in this frame, so that a
rotated, shifted or rescaled copy of a scene gets the same cells. :func:`sample_rows` bounds the
points it is measured on (a segment's LiDAR, read chunk by chunk).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import torch

from vadgs.geometry.camera import level_up

__all__ = [
    "ground_cells",
    "ground_frame",
    "points_in_frame",
    "sample_rows",
]


def points_in_frame(points: torch.Tensor, rotation: torch.Tensor, origin: torch.Tensor) -> torch.Tensor:
    """``(N, 3)`` points in the frame ``(rotation, origin)`` of :func:`ground_frame` (float64)."""
    return (points.double() - origin) @ rotation.T


def ground_frame(
    points: torch.Tensor, cam_to_world: torch.Tensor, walls: float | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """The scene's own ground frame: the cameras' up, the points' principal ground axes, their median.

    The up is :func:`~vadgs.geometry.camera.level_up` of the cameras (the world's ``z`` without
    cameras); the two ground axes are the principal axes of the points projected on the ground
    plane (the larger first); the origin is the points' median along each of the three axes (the
    middle two averaged). A rotated, shifted or uniformly scaled copy of the scene has the same
    frame, moved with it, up to the sign of each axis (an eigen-solver's choice): what is built on
    it (:func:`ground_cells`, the thinning of new points) is symmetric
    about the origin.

    With ``walls``, the ground axes are then turned about the up onto the scene's walls (a
    Manhattan alignment): the turn, searched over a quarter turn from the principal axes, that
    gives the points' coordinates the sharpest histogram at a bin of ``walls`` (walls are thin
    peaks along their normal). A street's principal axis can lie a degree or two off its facades;
    voxels on the facades' axes give their z-buffer flat faces.

    Args:
        points: ``(M, 3)`` points (voxel centres), world frame; ``M >= 1``.
        cam_to_world: ``(V, 4, 4)`` OpenCV camera-to-world of the views that saw them.
        walls: histogram bin of the wall alignment (a voxel edge), or None for the principal axes.

    Returns:
        ``(rotation, origin)``, float64 on the points' device: ``local = (x - origin) @ rotation.T``,
        the rows of ``rotation`` the major ground axis, the minor one and the up.

    Example:
        >>> pts = torch.tensor([[0.0, 0, 0], [4, 3, 0], [8, 6, 0], [12, 9, 1]])
        >>> rot, origin = ground_frame(pts, torch.empty(0, 4, 4))  # no cameras: z up
        >>> [round(abs(v), 3) for v in rot[0].tolist()], [round(v, 6) for v in origin.tolist()]
        ([0.8, 0.6, 0.0], [6.0, 4.5, 0.0])
    """
    p = points.double()
    up = level_up(cam_to_world.to(p.device)) if len(cam_to_world) else p.new_tensor([0.0, 0.0, 1.0])
    centred = p - (p @ up)[:, None] * up  # in the ground plane
    centred -= centred.mean(0)
    eye = torch.eye(3, dtype=p.dtype, device=p.device)
    scatter = centred.T @ centred / len(p) + 1e-9 * (eye - up[:, None] * up[None])
    del centred
    axes = torch.linalg.eigh(scatter).eigenvectors[:, 1:]  # the two ground axes (up's value is ~0)
    rotation = torch.stack([axes[:, 1], axes[:, 0], up])
    if walls is not None and len(p) > 1:
        rotation = _align_walls(p, rotation, walls)
    local = p @ rotation.T
    middle = torch.stack(  # the median, the middle two averaged (selection, not a sort: less memory)
        [
            0.5
            * (
                local[:, k].kthvalue((len(p) - 1) // 2 + 1).values
                + local[:, k].kthvalue(len(p) // 2 + 1).values
            )
            for k in range(3)
        ]
    )
    return rotation, middle @ rotation


def _align_walls(
    p: torch.Tensor, rotation: torch.Tensor, bin_size: float, max_points: int = 200_000
) -> torch.Tensor:
    """``rotation`` turned about its up (third row) onto the walls of ``p`` (:func:`ground_frame`).

    The candidates are turns from the principal axes (a quarter turn in 0.5° steps, then ±0.5°
    in 0.05° steps), so a rotated copy of the points meets the same candidates.
    """
    sub = p[:: max(1, len(p) // max_points)]
    uv0 = sub @ rotation[:2].T

    def score(angles: torch.Tensor) -> torch.Tensor:
        c, s = torch.cos(angles), torch.sin(angles)
        out = []
        for ci, si in zip(c.tolist(), s.tolist()):
            u = uv0[:, 0] * ci + uv0[:, 1] * si
            v = -uv0[:, 0] * si + uv0[:, 1] * ci
            total = 0.0
            for x in (u, v):
                q = torch.floor((x - x.min()) / bin_size).long()
                total += float(torch.bincount(q).double().pow(2).sum())
            out.append(total)
        return torch.tensor(out, dtype=torch.float64)

    coarse = torch.arange(180, dtype=torch.float64) * (math.pi / 360)
    best = float(coarse[int(score(coarse).argmax())])
    fine = best + torch.arange(-10, 11, dtype=torch.float64) * (math.pi / 3600)
    angle = float(fine[int(score(fine).argmax())])
    c, s = math.cos(angle), math.sin(angle)
    a, b = rotation[0], rotation[1]
    return torch.stack([c * a + s * b, -s * a + c * b, rotation[2]])


_GOLDEN = 2654435761  # 2**32 / golden ratio: Fibonacci hashing of a row's position


def sample_rows(chunks: Iterable[torch.Tensor], budget: int) -> torch.Tensor:
    """At most ``budget`` rows of the chunks concatenated, spread evenly, chosen by position only.

    Row ``i`` is kept when ``(i * 2654435761) mod 2**32 < 2**32 / s``, ``s`` the smallest power of
    two that keeps at most ``budget`` (every row when there are no more than that): Fibonacci
    hashing spreads the kept rows without a period (a stride of 8 would take one LiDAR beam in
    8). Only the sample is held (halving ``2**32 / s`` thins it); the rows chosen depend on their
    positions alone, so a moved copy of the points gives the moved sample.
    """
    sample: torch.Tensor | None = None
    keys = torch.zeros(0, dtype=torch.int64)
    limit, total = 1 << 32, 0
    for chunk in chunks:
        key = (torch.arange(total, total + chunk.shape[0]) * _GOLDEN) & 0xFFFFFFFF
        keep = key < limit
        sample = (
            chunk[keep.to(chunk.device)]
            if sample is None
            else torch.cat([sample, chunk[keep.to(chunk.device)]])
        )
        keys = torch.cat([keys, key[keep]])
        total += chunk.shape[0]
        while keys.shape[0] > budget:
            limit //= 2
            keep = keys < limit
            sample, keys = sample[keep.to(sample.device)], keys[keep]
    return sample if sample is not None else torch.zeros(0, 3)


def ground_cells(
    points: torch.Tensor,
    cam_to_world: torch.Tensor | None,
    cell_size: float,
    frame: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> torch.Tensor:
    """Cell index of each point in a grid of ``cell_size`` ground squares that moves with the scene.

    The squares lie in the ground plane of :func:`ground_frame`, along its axes, one centred on
    its origin (the points' median): a rotated, shifted or uniformly scaled copy of a scene
    (``cell_size`` scaled with it) is cut into the same cells, where square cells fixed to the
    world's axes would cut it elsewhere. Cells are numbered by their number of points, most first
    (ties: nearest to the origin, then lowest, first).

    Args:
        points: ``(M, 3)`` points (voxel centres), world frame.
        cam_to_world: ``(V, 4, 4)`` OpenCV camera-to-world of the views that saw them (unused
            when ``frame`` is given).
        cell_size: the squares' edge, in world units (> 0).
        frame: :func:`ground_frame` of these points and cameras, when already computed.

    Returns:
        ``(M,)`` int64 cell index in ``[0, number of cells)``, on the points' device.

    Example:
        >>> import math
        >>> pts = torch.rand(500, 3, generator=torch.Generator().manual_seed(0)) * torch.tensor([40.0, 8, 3])
        >>> c2w = torch.eye(4)[None].repeat(2, 1, 1)
        >>> c2w[:, :3, :3] = torch.tensor([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # level, z up
        >>> a = ground_cells(pts, c2w, 10.0)
        >>> c, s = math.cos(1.0), math.sin(1.0)
        >>> R = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        >>> moved = c2w.clone()
        >>> moved[:, :3, :3] = R @ c2w[:, :3, :3]
        >>> b = ground_cells(0.05 * (pts @ R.T) + 3.0, moved, 0.5)  # turned, shifted, 1/20
        >>> int(a.max()) + 1, bool((a == b).all())
        (5, True)
    """
    if not cell_size > 0:
        raise ValueError(f"cell_size: expected > 0, got {cell_size}")
    if len(points) == 0:
        return torch.zeros(0, dtype=torch.long, device=points.device)
    if frame is None:
        if cam_to_world is None:
            raise ValueError("cam_to_world: expected the cameras (N, 4, 4) when no frame is given, got None")
        frame = ground_frame(points, cam_to_world)
    local = points_in_frame(points, *frame)
    ij = torch.floor(local[:, :2] / cell_size + 0.5).long()  # the origin in a cell's centre
    _, cell, count = torch.unique(ij, dim=0, return_inverse=True, return_counts=True)
    centre = ij.double().norm(dim=1)  # a cell's distance from the origin, in cells
    dist = torch.zeros(len(count), dtype=local.dtype, device=local.device)
    dist = dist.scatter_reduce(0, cell, centre, "amax", include_self=False)
    height = torch.zeros_like(dist).index_add_(0, cell, local[:, 2] / cell_size) / count  # mean height
    key = [(-int(n), round(float(d), 6), round(float(h), 6)) for n, d, h in zip(count, dist, height)]
    order = sorted(range(len(count)), key=lambda c: (*key[c], c))
    rank = torch.empty_like(count)
    rank[torch.tensor(order, device=count.device)] = torch.arange(len(count), device=count.device)
    return rank[cell]
