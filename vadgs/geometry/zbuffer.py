r"""Voxel z-buffer: rasterise voxels into views as solid boxes, with classical z-buffering.

Each voxel is an axis-aligned box of edge ``voxel_size`` around its centre. For every view, each
box covers its full projected footprint: every pixel whose ray enters the box gets the box's
**entry z-depth** (exact ray–box intersection, slab method), and the nearest box wins. The result
is a dense depth map and a pixel → voxel index map per view (paper, Fig. 3c): occluded voxels
behind foreground geometry are excluded.

Depth modes. ``"box"`` returns the exact entry depth (what a ray caster of the boxes returns;
checked against Embree). Its error is *not* bounded by the voxel size: a ray skimming a road at a
shallow angle enters a road voxel through its top face, metres before it meets the road.
``"plane"`` (the default for a :class:`VoxelGrid`) intersects the
ray with the plane fitted to the voxel's neighbourhood and keeps the hit only inside the box, so a
ray that crosses a box above its surface falls through to the voxel behind; then the error is of
the order of the voxel size where a plane exists (the measured accuracy of both modes is in
docs/benchmarks.md).

The ray tests work in inverse depth, where every box face is an affine function of the pixel
(see ``_raster_one``): boxes are bucketed by the size of their projected pixel rectangle and
each bucket is evaluated as one padded ``(n, ph, pw)`` block by broadcasting a row term against a
column term per face, with no per-pixel gathers. The z-test is one ``scatter_reduce(amin)`` per
block on packed 64-bit keys ``(float32 depth bits << 32) | voxel id``: positive float32 values
order like their bit patterns, so the minimum key carries the nearest depth and, for exact ties,
the smallest voxel id. Pure torch, no compiled code, chunked over (voxel, pixel) pairs to bound
memory, with a Hi-Z test between chunks.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch

from vadgs.checks import (
    Checked,
    bool_field,
    check_finite,
    check_shape,
    checked,
    choice_field,
    float_field,
    int_field,
)
from vadgs.geometry.camera import Cameras
from vadgs.geometry.voxel import VoxelGrid

__all__ = ["VoxelRaster", "VoxelRasterizer", "ZBufferConfig", "rasterize_voxels"]

_EMPTY = 0x7F800000 << 32  # the key of depth +inf: misses (+inf | voxel id) never beat it


class VoxelRaster(NamedTuple):
    """Result of :func:`rasterize_voxels`.

    Attributes:
        depth: ``(B, 1, H, W)`` z-depth of the nearest voxel surface, ``0`` where no voxel.
        index: ``(B, H, W)`` int64 id of the nearest voxel, ``-1`` where no voxel.
        visible: ``B`` sorted int64 tensors: the voxels that own at least one pixel of each view.
    """

    depth: torch.Tensor
    # the field shadows tuple.index (the method); the public name stays
    index: torch.Tensor  # type: ignore[assignment]
    visible: list[torch.Tensor]


@dataclass(frozen=True)
class ZBufferConfig(Checked):
    """Settings of the voxel z-buffer.

    Attributes:
        near: voxels with a corner closer than this (z-depth) are skipped; they would cover the
            whole image from inside the camera.
        far: voxels farther than this are skipped.
        only_observed: rasterise into a view only the voxels whose visibility set contains it
            (needs ``view_ids``); otherwise all voxels in the frustum.
        depth_mode: ``"auto"`` (default): ``"plane"`` for a :class:`VoxelGrid`, ``"box"`` for bare
            centres. ``"box"``: the exact entry depth of the ray into the box (what a ray caster of
            the boxes returns). ``"plane"``: the ray's intersection with the plane fitted to the
            voxel's points (``VoxelGrid.normals``), kept only where it lies inside the box (with
            ``plane_tolerance`` voxel sizes of slack) — a ray that crosses a box above its
            surface falls through to the voxels behind, which removes the grazing-angle error of
            boxes on roads and walls. Voxels without a plane use the z-depth of their mean
            point, clamped into the box. Needs a :class:`VoxelGrid`.
        plane_tolerance: slack of the ``"plane"`` test, in voxel sizes.
        max_pairs: bound on the padded (voxel, pixel) pairs processed per chunk (memory ~ 40 B each).
    """

    near: float = checked(0.1, float_field(0, lo_open=True))
    far: float = checked(float("inf"), float_field(0, lo_open=True, finite=False))
    only_observed: bool = checked(False, bool_field())
    depth_mode: str = checked("auto", choice_field(("auto", "box", "plane")))
    plane_tolerance: float = checked(0.25, float_field(0))
    max_pairs: int = checked(4_000_000, int_field(1))

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.near < self.far:
            raise ValueError(f"near, far: expected near < far, got near={self.near}, far={self.far}")


def _boxes_in_view(
    centers: torch.Tensor, half: float, K: torch.Tensor, w2c: torch.Tensor, size: tuple[int, int], cfg
) -> tuple[torch.Tensor, ...]:
    """Cull boxes against one view; return ids and the integer pixel rectangles they may cover."""
    h, w = size
    corners = torch.tensor(
        [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)],
        dtype=centers.dtype,
        device=centers.device,
    )
    # corner z-depths: c_z + half * (± r_2x ± r_2y ± r_2z); extremes by the sign of each term
    rot, t = w2c[:3, :3], w2c[:3, 3]
    cam = centers @ rot.T + t  # (M, 3)
    zr = half * rot[2].abs().sum()
    keep = (cam[:, 2] - zr > cfg.near) & (cam[:, 2] - zr < cfg.far)
    # conservative frustum test of the bounding spheres before projecting any corner: the sphere
    # meets the half-space x >= a z iff (x - a z) / sqrt(1 + a^2) >= -radius
    radius = half * 3**0.5
    for axis, extent in ((0, w), (1, h)):
        f, c0 = K[axis, axis], K[axis, 2]
        for a, sign in (((-0.5 - c0) / f, 1.0), ((extent - 0.5 - c0) / f, -1.0)):
            keep &= sign * (cam[:, axis] - a * cam[:, 2]) >= -radius * torch.sqrt(1 + a * a)
    ids = keep.nonzero().squeeze(1)
    cam = cam[ids]
    zmin = cam[:, 2] - zr
    pc = cam[:, None, :] + half * (corners @ rot.T)[None]  # (M', 8, 3)
    uv = pc[..., :2] / pc[..., 2:3] * K[[0, 1], [0, 1]] + K[:2, 2]
    lo = torch.ceil(uv.amin(1) - 1e-6).clamp(min=0)
    hi = torch.floor(uv.amax(1) + 1e-6)
    hi = torch.minimum(hi, torch.tensor([w - 1, h - 1], dtype=hi.dtype, device=hi.device))
    ok = (hi >= lo).all(1)
    ids, lo, hi = ids[ok], lo[ok].long(), hi[ok].long()
    return ids, lo[:, 0], lo[:, 1], hi[:, 0] - lo[:, 0] + 1, hi[:, 1] - lo[:, 1] + 1, zmin[ok]


def _hiz_pyramid(keys: torch.Tensor, size: tuple[int, int]) -> list[torch.Tensor]:
    """Max-depth pyramid of the current z-buffer: level k holds the max over 2^k × 2^k tiles."""
    h, w = size
    depth = (keys >> 32).to(torch.int32).view(torch.float32).reshape(1, 1, h, w)
    levels = [depth[0, 0]]
    while max(levels[-1].shape) > 1:
        depth = torch.nn.functional.max_pool2d(depth, 2, ceil_mode=True)
        levels.append(depth[0, 0])
    return levels


def _occluded(
    levels: list[torch.Tensor], u0: torch.Tensor, v0: torch.Tensor, bw: torch.Tensor, bh: torch.Tensor, zmin
) -> torch.Tensor:
    """Boxes whose nearest possible depth is behind every pixel of their rectangle (Hi-Z test)."""
    ext = torch.maximum(bw, bh).clamp(min=1)
    level = torch.ceil(torch.log2(ext.to(torch.float32))).long().clamp(max=len(levels) - 1)
    out = torch.zeros_like(zmin, dtype=torch.bool)
    for k in torch.unique(level).tolist():
        sel = (level == k).nonzero().squeeze(1)
        lev = levels[k]
        x0, y0 = u0[sel] >> k, v0[sel] >> k
        x1, y1 = (u0[sel] + bw[sel] - 1) >> k, (v0[sel] + bh[sel] - 1) >> k
        far = torch.maximum(torch.maximum(lev[y0, x0], lev[y0, x1]), torch.maximum(lev[y1, x0], lev[y1, x1]))
        out[sel] = zmin[sel].float() > far
    return out


def _bucket_table(limit: int) -> list[int]:
    """Block sizes 1, 2, 3, 4, 6, 8, 12, 16, 24, ...: at most 1.5x padding per dimension."""
    out, p = [1, 2, 3], 4
    while out[-1] < limit:
        out += [p, 3 * p // 2]
        p *= 2
    return out


def _slab_offsets(
    c: torch.Tensor, half: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Signed offsets ``(n, 3)`` of each box's entry and exit planes from the camera, per world axis.

    Returns ``(enter, exit1, exit2, inside)``: for an axis whose slab does not contain the camera
    the ray enters through the near plane and leaves through the far one (``exit1 == exit2``);
    where the slab contains the camera (``inside``) there is no entry plane and the ray leaves
    through either plane depending on its direction (``exit1``, ``exit2``).
    """
    tiny = 1e-12
    lo, hi = c - half, c + half
    lo = torch.where(lo == 0, torch.full_like(lo, -tiny), lo)
    hi = torch.where(hi == 0, torch.full_like(hi, tiny), hi)
    below, above = lo > 0, hi < 0
    inside = ~(below | above)
    return torch.where(below, lo, hi), torch.where(above, lo, hi), torch.where(below, hi, lo), inside


def _raster_one(
    centers: torch.Tensor,
    half: float,
    K: torch.Tensor,
    w2c: torch.Tensor,
    size: tuple[int, int],
    candidates: torch.Tensor | None,
    cfg: ZBufferConfig,
    planes: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> torch.Tensor:
    r"""Packed z-buffer keys ``(H * W,)`` for one view.

    Works in inverse depth, where every plane is affine in the pixel: the ray
    :math:`o + t\,M (u, v, 1)^\top` (:math:`M = R^\top K^{-1}`, :math:`t` the z-depth) meets the
    world plane :math:`x_k = e` at :math:`1 / t = M_k (u, v, 1)^\top / (e - o_k)`. The ray hits a
    box iff its largest entry depth is at most its smallest exit depth (slab method), i.e. the
    smallest entry inverse depth is positive and at least the largest exit inverse depth. Each
    box's pixel rectangle is padded to a bucket size so that boxes of one bucket are evaluated as
    one ``(n, ph, pw)`` block by broadcasting a row term against a column term per plane.
    """
    h, w = size
    dev, dt = centers.device, centers.dtype
    keys = torch.full((h * w,), _EMPTY, dtype=torch.int64, device=dev)
    cen = centers if candidates is None else centers[candidates]
    ids, u0, v0, bw, bh, zmin = _boxes_in_view(cen, half, K, w2c, size, cfg)
    if ids.numel() == 0:
        return keys
    ids_g = ids if candidates is None else candidates[ids]
    rot_t = w2c[:3, :3].T
    origin = -(rot_t @ w2c[:3, 3])
    M = rot_t @ torch.linalg.inv(K)
    # per-box affine coefficients (n, P, 3) of the planes' inverse depth: rows 0-2 entry planes
    # (+inf where the slab contains the camera), 3-5 and 6-8 exit candidates, 9 the fitted plane
    enter, exit1, exit2, inside = _slab_offsets(cen[ids] - origin, half)
    coef = M.repeat(3, 1) / torch.cat([enter, exit1, exit2], 1)[:, :, None]
    no_entry = torch.tensor([0.0, 0.0, float("inf")], dtype=dt, device=dev)
    coef[:, :3] = torch.where(inside[:, :, None], no_entry, coef[:, :3])
    extra = None
    slack = 0.0
    if planes is not None:
        means, normals = planes[0][ids_g] - origin, planes[1][ids_g]
        coef = torch.cat([coef, (normals @ M)[:, None]], 1)
        has_normal = (normals.abs().sum(1) > 0).to(dt)
        extra = torch.stack([(means * normals).sum(1), means @ w2c[2, :3], has_normal], 1)
        slack = cfg.plane_tolerance * 2 * half
    # padded blocks: each rectangle rounded up to a bucket size and shifted to stay in the image
    table = torch.tensor(_bucket_table(max(h, w)), device=dev)
    ih, iw = torch.searchsorted(table, bh), torch.searchsorted(table, bw)
    ph, pw = table[ih].clamp(max=h), table[iw].clamp(max=w)
    u0, v0 = torch.minimum(u0, w - pw), torch.minimum(v0, h - ph)
    bucket = (ih * len(table) + iw) * 2 + inside.any(1).long()
    # front to back in chunks of at most max_pairs pairs; between chunks the Hi-Z pyramid of
    # what is drawn so far culls the boxes it hides
    zmin = zmin - slack
    todo = torch.argsort(zmin)
    first = True
    while todo.numel():
        if not first:
            levels = _hiz_pyramid(keys, size)
            todo = todo[~_occluded(levels, u0[todo], v0[todo], pw[todo], ph[todo], zmin[todo])]
            if todo.numel() == 0:
                break
        first = False
        end = max(int(torch.searchsorted((ph[todo] * pw[todo]).cumsum(0), cfg.max_pairs, right=True)), 1)
        chunk, todo = todo[:end], todo[end:]
        chunk = chunk[torch.argsort(bucket[chunk], stable=True)]
        _, counts = torch.unique_consecutive(bucket[chunk], return_counts=True)
        for sel in torch.split(chunk, counts.tolist()):
            i0 = int(sel[0])
            _raster_block(
                keys, coef[sel], None if extra is None else extra[sel], ids_g[sel], u0[sel], v0[sel],
                int(ph[i0]), int(pw[i0]), bool(bucket[i0] & 1), w, cfg.near, slack,
            )  # fmt: skip
    return keys


def _raster_block(keys, coef, extra, vox_ids, u0, v0, ph, pw, any_inside, w, near, slack) -> None:
    """Ray-box tests (and plane depths) of ``n`` boxes over ``(ph, pw)`` blocks; z-test into ``keys``."""
    dev, dt = coef.device, coef.dtype
    us = u0[:, None] + torch.arange(pw, device=dev)  # (n, pw) pixel columns
    vs = v0[:, None] + torch.arange(ph, device=dev)  # (n, ph) pixel rows
    cols = coef[:, :, 0:1] * us[:, None, :].to(dt)  # (n, P, pw)
    rows = coef[:, :, 1:2] * vs[:, None, :].to(dt) + coef[:, :, 2:3]  # (n, P, ph)

    def plane(k: int, out: torch.Tensor | None = None) -> torch.Tensor:
        return torch.add(rows[:, k, :, None], cols[:, k, None, :], out=out)  # (n, ph, pw)

    w_in = plane(0)
    tmp = torch.empty_like(w_in)  # one scratch block: fewer large allocations (page faults)
    torch.minimum(w_in, plane(1, tmp), out=w_in)
    torch.minimum(w_in, plane(2, tmp), out=w_in)
    w_out = plane(3)
    for k in (4, 5, 6, 7, 8) if any_inside else (4, 5):
        torch.maximum(w_out, plane(k, tmp), out=w_out)
    w_out.clamp_(min=1e-30)  # a hit needs a positive entry inverse depth
    hit = w_in >= w_out
    if extra is None:
        t = w_in.reciprocal_()
    else:  # the fitted plane, kept where it crosses the box (with slack); else fall through
        lo = w_in.reciprocal_().sub_(slack)  # entry depth minus the slack
        hi = w_out.reciprocal_().add_(slack)  # exit depth plus the slack
        nd = plane(9, tmp)
        num, t_mid, has_normal = (extra[:, j, None, None] for j in range(3))
        flat = nd.abs() >= 1e-9
        has_plane = flat & (has_normal > 0)
        t_plane = num / torch.where(flat, nd, 1.0)
        hit &= ((t_plane >= lo) & (t_plane <= hi)) | ~has_plane
        t = torch.maximum(torch.where(has_plane, t_plane, t_mid), lo).clamp_(min=near)
        torch.minimum(t, hi, out=t)
    t = torch.where(hit, t.float(), float("inf"))
    key = t.view(torch.int32).long()
    key <<= 32
    key |= vox_ids[:, None, None]
    pid = (vs * w)[:, :, None] + us[:, None, :]
    keys.scatter_reduce_(0, pid.reshape(-1), key.reshape(-1), reduce="amin")


def rasterize_voxels(
    grid: VoxelGrid | tuple[torch.Tensor, float],
    cameras: Cameras,
    view_ids: Sequence[int] | torch.Tensor | None = None,
    config: ZBufferConfig | None = None,
) -> VoxelRaster:
    """Rasterise voxels into views with z-buffering: dense depth and pixel → voxel index maps.

    Runs under ``torch.no_grad()``; nothing here is differentiable.

    Args:
        grid: a :class:`~vadgs.geometry.voxel.VoxelGrid`, or ``(centers (M, 3), voxel_size)``.
        cameras: ``B`` cameras (world frame of the grid).
        view_ids: ``(B,)`` the grid's view id of each camera; needed for
            ``config.only_observed``.
        config: :class:`ZBufferConfig`.

    Returns:
        :class:`VoxelRaster` with ``depth (B, 1, H, W)``, ``index (B, H, W)`` and ``visible``.

    Example:
        >>> K = torch.tensor([[[100.0, 0, 49.5], [0, 100.0, 49.5], [0, 0, 1]]])
        >>> cams = Cameras(K, torch.eye(4)[None], (100, 100))
        >>> centers = torch.tensor([[0.0, 0.0, 5.0], [0.0, 0.0, 10.0]])  # the far one is hidden
        >>> out = rasterize_voxels((centers, 1.0), cams)
        >>> out.depth[0, 0, 50, 50].item(), out.index[0, 50, 50].item(), out.visible[0].tolist()
        (4.5, 0, [0])
    """
    cfg = config or ZBufferConfig()
    if isinstance(grid, VoxelGrid):
        centers, size = grid.centers, grid.voxel_size
    else:
        centers, size = grid
    check_shape(centers, "centers", ("M", 3))
    check_finite(centers, "centers")
    if not size > 0:
        raise ValueError(f"voxel_size: expected a positive number, got {size}")
    if not isinstance(cameras, Cameras):
        raise ValueError(f"cameras: expected a vadgs.geometry.Cameras, got {type(cameras).__name__}")
    b = len(cameras)
    if view_ids is not None:
        view_ids = torch.as_tensor(view_ids, dtype=torch.int64)
        if view_ids.shape != (b,):
            raise ValueError(f"view_ids: expected shape ({b},), got {tuple(view_ids.shape)}")
    if cfg.only_observed and (view_ids is None or not isinstance(grid, VoxelGrid)):
        raise ValueError("config.only_observed needs a VoxelGrid with visibility and view_ids")
    if cfg.depth_mode not in ("auto", "box", "plane"):
        raise ValueError(f"config.depth_mode: expected 'auto', 'box' or 'plane', got {cfg.depth_mode!r}")
    planes = None
    if cfg.depth_mode == "plane" or (cfg.depth_mode == "auto" and isinstance(grid, VoxelGrid)):
        if not isinstance(grid, VoxelGrid):
            raise ValueError("config.depth_mode='plane' needs a VoxelGrid (its means and normals)")
        planes = (grid.means.to(centers), grid.normals.to(centers))
    h, w = cameras.image_size
    K = cameras.K.to(centers)
    w2c = cameras.world_to_cam.to(centers)
    with torch.no_grad():
        if cfg.only_observed:
            vis_voxels, vis_views = grid.vis_voxels, grid.vis_views  # type: ignore[union-attr]
        depth = torch.zeros(b, 1, h, w, dtype=centers.dtype, device=centers.device)
        index = torch.full((b, h, w), -1, dtype=torch.int64, device=centers.device)
        visible = []
        for i in range(b):
            cand = None
            if cfg.only_observed:
                cand = vis_voxels[vis_views == int(view_ids[i])].unique()  # type: ignore[index]
            keys = _raster_one(centers, size / 2, K[i], w2c[i], (h, w), cand, cfg, planes)
            filled = keys < _EMPTY
            d = (keys >> 32).to(torch.int32).view(torch.float32).to(depth.dtype)
            depth[i, 0] = torch.where(filled, d, 0).view(h, w)
            ids = torch.where(filled, keys & 0xFFFFFFFF, -1)
            index[i] = ids.view(h, w)
            seen = torch.zeros(centers.shape[0] + 1, dtype=torch.bool, device=centers.device)
            seen[ids] = True  # -1 (empty) lands in the extra last slot
            visible.append(seen[:-1].nonzero().squeeze(1))
    return VoxelRaster(depth, index, visible)


class VoxelRasterizer:
    """Holds a :class:`ZBufferConfig` and calls :func:`rasterize_voxels`. See :func:`rasterize_voxels`.

    Example:
        >>> zb = VoxelRasterizer(ZBufferConfig(near=0.2))
        >>> K = torch.tensor([[[10.0, 0, 4.5], [0, 10.0, 4.5], [0, 0, 1]]])
        >>> zb((torch.tensor([[0.0, 0, 3]]), 0.5), Cameras(K, torch.eye(4)[None], (10, 10))).index.shape
        torch.Size([1, 10, 10])
    """

    def __init__(self, config: ZBufferConfig | None = None) -> None:
        self.config = config or ZBufferConfig()

    def __call__(
        self,
        grid: VoxelGrid | tuple[torch.Tensor, float],
        cameras: Cameras,
        view_ids: Sequence[int] | torch.Tensor | None = None,
    ) -> VoxelRaster:
        """Rasterise ``grid`` into ``cameras`` (see :func:`rasterize_voxels`)."""
        return rasterize_voxels(grid, cameras, view_ids, self.config)
