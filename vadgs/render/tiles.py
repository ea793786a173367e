"""Tile binning: which projected Gaussians touch which screen tile, in depth order.

The image is cut into ``tile_size × tile_size`` tiles (8 px by default; the last row and column
of tiles may hang over the image border). Every Gaussian with a non-zero screen box
(:func:`vadgs.render.projection.project_gaussians`) is listed in each tile that its box
overlaps, and the lists are sorted by camera, tile and then depth (nearest first), as gsplat's
``isect_tiles`` does with 64-bit keys; here a depth argsort per camera followed by a stable sort
by tile id does the same without packing keys.

A box covers the pixel centres ``ceil(u - r_x) .. floor(u + r_x)`` (integers are pixel centres),
so tile ranges are exact in the pixel-centre convention of ``docs/conventions.md``.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from vadgs.checks import check_shape, check_size

__all__ = ["TileBins", "bin_gaussians"]


class TileBins(NamedTuple):
    """Per-tile depth-sorted Gaussian lists of a batch of cameras.

    Attributes:
        gauss_ids: ``(M,)`` int64 flat Gaussian ids ``b * N + n``, grouped by tile (camera-major,
            then row-major tiles) and sorted by depth within a tile.
        tile_starts: ``(B * TH * TW,)`` int64 offset of each tile's list in ``gauss_ids``.
        tile_counts: ``(B * TH * TW,)`` int64 length of each tile's list.
        grid: ``(TH, TW)`` tiles per column and row.
        tile_size: tile side in pixels.
    """

    gauss_ids: torch.Tensor
    tile_starts: torch.Tensor
    tile_counts: torch.Tensor
    grid: tuple[int, int]
    tile_size: int


@torch.no_grad()
def bin_gaussians(
    means2d: torch.Tensor,
    radii: torch.Tensor,
    depths: torch.Tensor,
    image_size: tuple[int, int],
    tile_size: int = 8,
    conics: torch.Tensor | None = None,
    opacities: torch.Tensor | None = None,
    alpha_min: float = 1.0 / 255.0,
) -> TileBins:
    """Bin projected Gaussians into screen tiles, depth-sorted within each tile.

    Not differentiable (integer bookkeeping); runs under ``torch.no_grad()``.

    Args:
        means2d: ``(B, N, 2)`` screen means in pixels.
        radii: ``(B, N, 2)`` int half sizes of the screen boxes, ``0`` for culled Gaussians.
        depths: ``(B, N)`` sort keys (camera-frame z).
        image_size: ``(H, W)``.
        tile_size: tile side in pixels.
        conics: optional ``(B, N, 3)`` inverse screen covariances; with ``opacities`` it enables
            the exact ellipse test below.
        opacities: optional ``(B, N)`` opacities.
        alpha_min: the compositor's alpha threshold.

    With ``conics`` and ``opacities`` a tile is kept for a Gaussian only if the Gaussian can
    reach ``alpha_min`` somewhere on the rectangle spanned by the tile's pixel centres (the
    minimum of the quadratic form over a box, found on its edges). This drops the corner tiles
    of the box that the ellipse misses (about 20-40 % of the pairs) without changing the image.

    Returns:
        The :class:`TileBins`.

    Example:
        >>> bins = bin_gaussians(torch.tensor([[[3.0, 3.0], [9.0, 3.0]]]), torch.tensor([[[2, 2], [2, 2]]]),
        ...                      torch.tensor([[2.0, 1.0]]), (8, 16), tile_size=8)
        >>> bins.gauss_ids.tolist(), bins.tile_counts.tolist()
        ([1, 0, 1], [2, 1])
    """
    dims = check_shape(means2d, "means2d", ("B", "N", 2))
    check_shape(radii, "radii", ("B", "N", 2), dims)
    check_shape(depths, "depths", ("B", "N"), dims)
    h, w = check_size(image_size)
    if tile_size < 1:
        raise ValueError(f"tile_size: expected a positive int, got {tile_size}")
    b, n = dims["B"], dims["N"]
    th, tw = -(-h // tile_size), -(-w // tile_size)
    device = means2d.device

    r = radii.to(means2d.dtype)
    lo = torch.div(torch.ceil(means2d - r), tile_size, rounding_mode="floor")
    hi = torch.div(torch.floor(means2d + r), tile_size, rounding_mode="floor") + 1
    limit = torch.tensor([tw, th], device=device, dtype=means2d.dtype)
    lo = torch.minimum(lo.clamp_min(0), limit).long()
    hi = torch.minimum(hi.clamp_min(0), limit).long()
    ext = (hi - lo).clamp_min(0)
    counts = ext[..., 0] * ext[..., 1] * (radii > 0).all(-1)  # (B, N)

    # Visit Gaussians camera by camera in depth order; a stable sort by tile keeps that order.
    keyed = torch.where(counts > 0, depths, torch.full_like(depths, float("inf")))
    order = torch.argsort(keyed, dim=1)  # (B, N)
    flat = (order + torch.arange(b, device=device)[:, None] * n).reshape(-1)
    cnt = counts.reshape(-1)[flat]
    keep = cnt > 0
    flat, cnt = flat[keep], cnt[keep]
    num = int(cnt.sum())
    n_tiles = b * th * tw
    if num == 0:
        zeros = torch.zeros(n_tiles, dtype=torch.long, device=device)
        return TileBins(torch.zeros(0, dtype=torch.long, device=device), zeros, zeros, (th, tw), tile_size)

    which = torch.repeat_interleave(torch.arange(flat.numel(), device=device), cnt)  # (M,)
    first = torch.cumsum(cnt, 0) - cnt
    k = torch.arange(num, device=device) - first[which]
    lo_f, ext_f = lo.reshape(-1, 2)[flat], ext.reshape(-1, 2)[flat]
    width = ext_f[which, 0]
    tx = lo_f[which, 0] + k % width
    ty = lo_f[which, 1] + k // width
    if conics is not None and opacities is not None:
        check_shape(conics, "conics", ("B", "N", 3), dims)
        check_shape(opacities, "opacities", ("B", "N"), dims)
        g = flat[which]
        keep = _touches(
            means2d.reshape(-1, 2)[g],
            conics.reshape(-1, 3)[g],
            torch.log(opacities.reshape(-1)[g] / alpha_min),
            tx * tile_size,
            ty * tile_size,
            tile_size,
        )
        which, tx, ty = which[keep], tx[keep], ty[keep]
    cam = flat[which] // n
    tile = (cam * th + ty) * tw + tx
    key = tile.to(torch.int32) if n_tiles < 2**31 else tile
    perm = torch.sort(key, stable=True).indices
    gauss_ids = flat[which[perm]]
    tile_counts = torch.bincount(tile, minlength=n_tiles)
    tile_starts = torch.cumsum(tile_counts, 0) - tile_counts
    return TileBins(gauss_ids, tile_starts, tile_counts, (th, tw), tile_size)


def _touches(
    mean: torch.Tensor,
    conic: torch.Tensor,
    level: torch.Tensor,
    x0: torch.Tensor,
    y0: torch.Tensor,
    size: int,
) -> torch.Tensor:
    """Whether ``0.5 d^T conic d <= level`` somewhere on the pixel-centre box of a tile.

    The quadratic form is convex, so its minimum over the box is 0 when the mean is inside and
    otherwise lies on one of the four edges, where it is a clamped 1D parabola.
    """
    a, b, c = conic.unbind(-1)
    lo_x, lo_y = x0.to(mean.dtype) - mean[:, 0], y0.to(mean.dtype) - mean[:, 1]  # box relative to the mean
    hi_x, hi_y = lo_x + (size - 1), lo_y + (size - 1)
    best = torch.full_like(a, float("inf"))
    for dx in (lo_x, hi_x):  # vertical edges: minimise over dy
        dy = torch.minimum(torch.maximum(-b * dx / c, lo_y), hi_y)
        best = torch.minimum(best, 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy)
    for dy in (lo_y, hi_y):  # horizontal edges: minimise over dx
        dx = torch.minimum(torch.maximum(-b * dy / a, lo_x), hi_x)
        best = torch.minimum(best, 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy)
    inside = (lo_x <= 0) & (hi_x >= 0) & (lo_y <= 0) & (hi_y >= 0)
    # A little slack keeps pairs at the exact threshold (rounding can only add work, not lose it).
    return inside | (best <= level * (1 + 1e-5) + 1e-6)
