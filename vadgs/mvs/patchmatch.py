r"""Batched multi-view PatchMatch stereo with per-pixel view selection (ACMH-style).

Every reference pixel :math:`\mathbf{p}` carries a plane hypothesis, a depth :math:`z` and a
normal :math:`\mathbf{n}` in the reference camera frame, i.e. the plane
:math:`\mathbf{n}^\top \mathbf{X} + d = 0` with :math:`d = -z\,\mathbf{n}^\top K^{-1}\tilde{\mathbf{p}}`.
A window around :math:`\mathbf{p}` maps into source view :math:`v` by the plane-induced homography
(paper, "MVS Reconstruction from Selected Views")

.. math::

    \tilde{\mathbf{p}}' \simeq K_v \left(R_v - \frac{\mathbf{t}_v \mathbf{n}^\top}{d}\right)
    K^{-1} \tilde{\mathbf{p}},

and is scored by the bilateral NCC cost :math:`c_v \in [0, 2]` (:mod:`vadgs.mvs.cost`). Views are
aggregated per pixel with ACMH's weights: over the current hypothesis and the propagated
candidates, a view is *selected* when at least two hypotheses score below ``good_threshold`` and
at most three above ``bad_threshold``; its weight is the mean confidence
:math:`\exp(-c^2 / 2\beta^2)` of its good hypotheses, and

.. math::

    c(\mathbf{p}) = \frac{\sum_v w_v c_v}{\sum_v w_v},

so one occluded view cannot ruin a pixel. Pixels where no view is selected fall back to the mean
of the ``top_k`` best views (COLMAP-like).

The search alternates red/black checkerboard half-sweeps (ACMH): each pixel of one colour takes
the best-cost neighbour of each of 8 sampled regions of the other colour (4 V-shaped near regions,
4 long far strips), re-intersects its plane with the pixel's ray, and keeps the best of those and
its own hypothesis; then random refinement tries perturbed depths and normals whose spread halves
at every iteration. Initialisation is random (inverse depth uniform in ``depth_range``, normals
uniform on the hemisphere facing the camera) or taken from given depth / normal maps.

The plane homographies are those of :func:`vadgs.geometry.plane_homography`, composed here with
the pixel normalisation of :func:`torch.nn.functional.grid_sample` so that a window's samples
come out of one small matrix product (``tests/mvs`` checks both against each other).
Everything runs under :func:`torch.no_grad` and on the device of its inputs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import NamedTuple

import torch
import torch.nn.functional as F
from kornia.color import rgb_to_grayscale
from torch import nn

from vadgs.checks import check_finite, check_shape
from vadgs.geometry import relative_pose, scale_intrinsics
from vadgs.mvs.cost import (
    MAX_COST,
    ReferencePatchStats,
    bilateral_weights,
    ncc_cost_from_stats,
    patch_offsets,
    reference_patch_stats,
    reference_patches,
)

__all__ = ["PatchMatch", "PatchMatchConfig", "PatchMatchResult", "patchmatch", "propagation_regions"]


@dataclass(frozen=True)
class PatchMatchConfig:
    """Settings of :func:`patchmatch`.

    Attributes:
        iterations: red/black sweeps (each: propagation + refinement of both colours).
        window_radius: half-size of the matching window in pixels (COLMAP, ACMP: 5).
        window_step: sample every ``window_step`` pixels of the window (ACMP: 2 → 36 samples).
        sigma_spatial: spatial sigma of the bilateral weights; ``None`` = ``window_radius``.
        sigma_color: intensity sigma of the bilateral weights, on [0, 1] grey levels.
        min_variance: weighted patch variance under which a patch is flat (cost 2).
        propagation: ``"acmh"`` (8 sampled regions, best-cost neighbour of each) or ``"cross"``
            (the 4 adjacent pixels: half the cost evaluations).
        num_refine: random-refinement hypotheses per pixel and half-sweep (1 to 6), from the
            list (perturbed depth & normal, perturbed depth, perturbed normal, random depth &
            normal, random depth, random normal).
        depth_perturbation: relative depth perturbation of the first iteration (halved at each).
        normal_perturbation: normal perturbation of the first iteration (halved at each).
        view_selection: ``"acmh"`` (weighted good views, see the module docstring),
            ``"topk"`` (mean of the ``top_k`` lowest costs) or ``"mean"`` (plain mean: for tests).
        top_k: views kept by ``"topk"`` and by the fallback of ``"acmh"``.
        good_threshold: cost under which a view's score counts as good (ACMH: 0.8).
        bad_threshold: cost over which it counts as bad (ACMH: 1.2).
        beta: confidence width of the view weights (ACMH: 0.3).
        max_cost: pixels with a final aggregated cost above it are invalid in the result mask.
        seed: seed of the random hypotheses (``None``: torch's global generator).
        chunk_size: pixel-views scored at once; ``None``: 4096 on CPU (temporaries stay in
            cache, about 3x faster than one pass), everything at once on other devices.
        pyramid_levels: coarse-to-fine levels (ACMM-style; default 2). ``1``: a single scale. ``L > 1``: the
            ``iterations`` run on images downsampled ``2^(L-1)`` times, then at each finer level
            the upsampled hypotheses are refined by ``fine_iterations`` more sweeps (with the
            perturbation spread continuing to shrink). Most of the search happens on a quarter
            (or less) of the pixels, and the larger effective window helps on weak texture.
        fine_iterations: sweeps at each level finer than the coarsest (``pyramid_levels > 1``).
        fine_propagation: propagation pattern of the finer levels (``None``: ``propagation``);
            ``"cross"`` halves their cost once the coarse level has spread good planes.
    """

    iterations: int = 3
    window_radius: int = 5
    window_step: int = 2
    sigma_spatial: float | None = None
    sigma_color: float = 0.2
    min_variance: float = 1e-5
    propagation: str = "acmh"
    num_refine: int = 3
    depth_perturbation: float = 0.05
    normal_perturbation: float = 0.5
    view_selection: str = "acmh"
    top_k: int = 2
    good_threshold: float = 0.8
    bad_threshold: float = 1.2
    beta: float = 0.3
    max_cost: float = 0.6
    seed: int | None = 0
    chunk_size: int | None = None
    pyramid_levels: int = 2
    fine_iterations: int = 1
    fine_propagation: str | None = None

    def __post_init__(self) -> None:
        if self.pyramid_levels < 1 or self.fine_iterations < 0:
            raise ValueError(
                f"pyramid_levels, fine_iterations: expected >= 1 and >= 0, got {self.pyramid_levels}, "
                f"{self.fine_iterations}"
            )
        if self.iterations < 0:
            raise ValueError(f"iterations: expected >= 0, got {self.iterations}")
        if self.window_radius < 1 or self.window_step < 1:
            raise ValueError(
                f"window_radius, window_step: expected >= 1, got {self.window_radius}, {self.window_step}"
            )
        for name in ("propagation", "fine_propagation"):
            value = getattr(self, name)
            if value not in ("acmh", "cross") and not (name == "fine_propagation" and value is None):
                raise ValueError(f"{name}: expected 'acmh' or 'cross', got {value!r}")
        if self.view_selection not in ("acmh", "topk", "mean"):
            raise ValueError(
                f"view_selection: expected 'acmh', 'topk' or 'mean', got {self.view_selection!r}"
            )
        if not 0 <= self.num_refine <= 6:
            raise ValueError(f"num_refine: expected 0 to 6, got {self.num_refine}")
        if self.top_k < 1:
            raise ValueError(f"top_k: expected >= 1, got {self.top_k}")


class PatchMatchResult(NamedTuple):
    """Output of :func:`patchmatch`.

    Attributes:
        depth: ``(B, 1, H, W)`` z-depth; ``0`` where ``mask`` is False.
        normal: ``(B, 3, H, W)`` unit normals in the reference camera frame, facing the camera;
            zeros where ``mask`` is False.
        cost: ``(B, 1, H, W)`` aggregated photometric cost in ``[0, 2]`` (2 where nothing matched).
        view_costs: ``(B, V, H, W)`` per-source-view cost of the final hypothesis.
        mask: ``(B, 1, H, W)`` bool, pixels with a valid estimate (in the region, textured,
            cost below ``max_cost``).
        raw_depth: ``(B, 1, H, W)`` the final hypotheses' depth everywhere (before masking), for
            callers that fill or filter differently.
        raw_normal: ``(B, 3, H, W)`` the final hypotheses' normals everywhere.
    """

    depth: torch.Tensor
    normal: torch.Tensor
    cost: torch.Tensor
    view_costs: torch.Tensor
    mask: torch.Tensor
    raw_depth: torch.Tensor
    raw_normal: torch.Tensor


def propagation_regions(kind: str = "acmh") -> list[list[tuple[int, int]]]:
    """Neighbour offsets ``(dx, dy)`` of each propagation region.

    ``"acmh"``: ACMH's 8 regions, 4 V-shaped near regions of 7 pixels and 4 far strips of 11
    pixels (every other pixel from 3 to 23 away). ``"cross"``: the 4 adjacent pixels. All offsets
    have odd ``dx + dy``: they point to the other colour of the checkerboard.

    Example:
        >>> [len(r) for r in propagation_regions()]
        [7, 7, 7, 7, 11, 11, 11, 11]
    """
    if kind == "cross":
        return [[(0, -1)], [(0, 1)], [(-1, 0)], [(1, 0)]]
    if kind != "acmh":
        raise ValueError(f"kind: expected 'acmh' or 'cross', got {kind!r}")
    up = [(0, -1), (-1, -2), (1, -2), (-2, -3), (2, -3), (-3, -4), (3, -4)]
    far_up = [(0, -k) for k in range(3, 24, 2)]
    regions = []
    for base in (up, far_up):
        regions.append(base)
        regions.append([(x, -y) for x, y in base])
        regions.append([(y, x) for x, y in base])
        regions.append([(-y, x) for x, y in base])
    return regions


def _to_gray(x: torch.Tensor) -> torch.Tensor:
    return rgb_to_grayscale(x) if x.shape[-3] == 3 else x.mean(-3, keepdim=True)


def _random_normals(rays: torch.Tensor, gen: torch.Generator | None) -> torch.Tensor:
    n = torch.randn(rays.shape, generator=gen, device=rays.device, dtype=rays.dtype)
    n = F.normalize(n, dim=-1)
    return _face_camera(n, rays)


def _face_camera(n: torch.Tensor, rays: torch.Tensor) -> torch.Tensor:
    sign = torch.where((n * rays).sum(-1, keepdim=True) > 0, -1.0, 1.0).to(n)
    return n * sign


def _random_depth(shape, lo, hi, gen, like) -> torch.Tensor:
    u = torch.rand(shape, generator=gen, device=like.device, dtype=like.dtype)
    inv = 1 / hi + u * (1 / lo - 1 / hi)
    return 1 / inv


class _Colour(NamedTuple):
    """Per-checkerboard-colour precomputation (pixels of one colour)."""

    idx: torch.Tensor  # (P,) flat pixel indices
    pix: torch.Tensor  # (P, 3) homogeneous pixel coordinates
    rays: torch.Tensor  # (B, P, 3) K^-1 p
    stats: ReferencePatchStats  # (B, P, S)
    nbr: torch.Tensor  # (P, N) flat neighbour indices (clamped), a pixel's neighbours contiguous
    nbr_ok: torch.Tensor  # (P, N) neighbour inside the image
    region_sizes: list[int]


class _Sources(NamedTuple):
    gray: torch.Tensor  # (B*V, 1, Hs, Ws)
    masks: torch.Tensor | None  # (B*V, 1, Hs, Ws) float or None
    A: torch.Tensor  # (B, V, 3, 3) N K_s R K_r^-1
    b: torch.Tensor  # (B, V, 3) N K_s t
    Kinv: torch.Tensor  # (B, 3, 3)
    usable: torch.Tensor  # (B, V) bool: non-degenerate baseline
    axis: torch.Tensor  # (n,) window offsets along x and along y (the window is an n x n grid)


def _pixel_homographies(
    src: _Sources, col: _Colour, depth: torch.Tensor, normal: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel plane homographies in grid_sample coordinates, ``(B, V, 3, P, 3)``, and validity ``(B, P)``.

    ``C[:, :, 0] = H e_x``, ``C[:, :, 1] = H e_y`` and ``C[:, :, 2] = H p~`` (rows as vectors), so
    the window sample at offset ``o`` maps to ``(o_x, o_y, 1) @ C`` (homogeneous coordinates,
    normalised to [-1, 1] for :func:`torch.nn.functional.grid_sample`). Algebraically
    ``N K_s (R - t n^T / d) K_r^-1`` of :func:`vadgs.geometry.plane_homography`, with
    ``H p~ = N K_s (R K_r^-1 p~ + t / z)`` because ``n^T K_r^-1 p~ / d = -1 / z``.
    """
    rays = col.rays
    dist = -depth * (normal * rays).sum(-1)  # plane_distance, (B, P)
    ok = dist > 1e-6 * depth
    dist = torch.where(ok, dist, torch.ones_like(dist))
    n_k = normal @ src.Kinv  # (B, P, 3): n^T K^-1
    A, b = src.A, src.b  # (B, V, 3, 3), (B, V, 3)
    bb = b[:, :, None, :]
    c0 = torch.einsum("bvij,pj->bvpi", A, col.pix) + bb / depth[:, None, :, None]
    scale = (n_k[..., :2] / dist[..., None])[:, None]  # (B, 1, P, 2)
    c1 = A[:, :, None, :, 0] - bb * scale[..., 0:1]
    c2 = A[:, :, None, :, 1] - bb * scale[..., 1:2]
    return torch.stack([c1, c2, c0], dim=2), ok


def _chunk_size(cfg_chunk: int | None, device: torch.device, views: int) -> int:
    if cfg_chunk is None:
        cfg_chunk = 4096 if device.type == "cpu" else 1 << 30
    return max(1, cfg_chunk // views)


def _view_costs(
    src: _Sources, col: _Colour, depth: torch.Tensor, normal: torch.Tensor, min_variance: float, chunk: int
) -> torch.Tensor:
    """Per-view costs ``(B, V, P)`` of the hypotheses ``depth (B, P)``, ``normal (B, P, 3)``.

    Scored ``chunk`` pixels at a time so that the ``(V, S, chunk)`` temporaries stay in cache.
    """
    C, ok = _pixel_homographies(src, col, depth, normal)
    b, v, _, p, _ = C.shape
    n = src.axis.shape[0]
    ax = src.axis.view(1, n, 1)
    out = []
    for p0 in range(0, p, chunk):
        cc = C[:, :, :, p0 : p0 + chunk].reshape(b * v, 3, -1, 3)
        pc = cc.shape[2]
        # The window is a grid: sample (ix, iy) maps to o_x[ix] C1 + o_y[iy] C2 + C0, a broadcast
        # add of a per-column and a per-row term, one contiguous plane per coordinate.
        planes = []
        for k in range(3):
            c1, c2, c0 = (cc[:, j, None, :, k] for j in range(3))  # (BV, 1, pc)
            row = torch.addcmul(c0, ax, c2)  # (BV, n_y, pc)
            planes.append(row[:, :, None] + ax[:, None] * c1[:, None])  # (BV, n_y, n_x, pc)
        inv_z = planes[2].clamp_min_(1e-9).reciprocal_()  # behind the camera: far outside
        grid = torch.empty(b * v, n, n, pc, 2, device=inv_z.device, dtype=inv_z.dtype)
        torch.mul(planes[0], inv_z, out=grid[..., 0])
        torch.mul(planes[1], inv_z, out=grid[..., 1])
        grid = grid.view(b * v, n * n, pc, 2)
        samples = F.grid_sample(src.gray, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
        stats = ReferencePatchStats(
            col.stats.weights[..., p0 : p0 + chunk],
            col.stats.normalized[..., p0 : p0 + chunk],
            col.stats.valid[..., p0 : p0 + chunk],
        )
        out.append(ncc_cost_from_stats(samples.view(b, v, n * n, pc), stats, min_variance))
    cost = torch.cat(out, dim=-1) if len(out) > 1 else out[0]
    # The window centre must land in front of the source camera, inside its image (and mask).
    c0 = C[:, :, 2]  # (B, V, P, 3)
    cz = c0[..., 2]
    cxy = c0[..., :2] / cz.clamp_min(1e-9)[..., None]
    good = (cz > 1e-9) & (cxy.abs() <= 1).all(-1) & ok[:, None] & src.usable[..., None]
    if src.masks is not None:
        m = F.grid_sample(
            src.masks, cxy.reshape(b * v, p, 1, 2), mode="nearest", padding_mode="zeros", align_corners=True
        ).reshape(b, v, p)
        good = good & (m > 0.5)
    return torch.where(good, cost, torch.full_like(cost, MAX_COST))


def _view_weights(costs: torch.Tensor, cfg: PatchMatchConfig) -> torch.Tensor:
    """ACMH view weights ``(B, V, P)`` from the costs ``(N, B, V, P)`` of N hypotheses."""
    good = costs < cfg.good_threshold
    bad = costs > cfg.bad_threshold
    n_good = good.sum(0)
    selected = (n_good >= 2) & (bad.sum(0) <= 3)
    conf = torch.exp(-(costs**2) / (2 * cfg.beta**2)) * good
    return conf.sum(0) / n_good.clamp_min(1) * selected


def _aggregate(costs: torch.Tensor, weights: torch.Tensor | None, cfg: PatchMatchConfig) -> torch.Tensor:
    """Aggregated costs ``(N, B, P)`` of per-view costs ``(N, B, V, P)``."""
    v = costs.shape[-2]
    if cfg.view_selection == "mean":
        return costs.mean(-2)
    k = min(cfg.top_k, v)
    topk = costs.topk(k, dim=-2, largest=False).values.mean(-2) if k < v else costs.mean(-2)
    if cfg.view_selection == "topk" or weights is None:
        return topk
    wsum = weights.sum(-2)  # (B, P)
    weighted = (costs * weights).sum(-2) / wsum.clamp_min(1e-12)
    return torch.where(wsum > 0, weighted, topk)


def _propagate_depth(z_q, n, rays_q, rays_p, lo, hi):
    """Depth at ``p`` of the plane through neighbour ``q`` (re-intersected with p's ray)."""
    num = (n * rays_q).sum(-1)
    den = (n * rays_p).sum(-1)
    z = z_q * num / torch.where(den < -1e-6, den, torch.full_like(den, -1.0))
    z = torch.where((den < -1e-6) & torch.isfinite(z), z, z_q)
    return z.clamp(lo, hi)


def _perturb_normals(n, rays, scale, gen):
    noise = (torch.rand(n.shape, generator=gen, device=n.device, dtype=n.dtype) * 2 - 1) * scale
    m = F.normalize(n + noise, dim=-1)
    return torch.where(((m * rays).sum(-1, keepdim=True) < -1e-3), m, n)


def _apply_init(depth, normal, init_depth, init_normal, rays, lo, hi):
    """Hypotheses ``(B, P)``, ``(B, P, 3)`` overridden by the known pixels of init maps."""
    bsz, p = depth.shape
    if init_depth is not None:
        d0 = init_depth.reshape(bsz, p)
        known = torch.isfinite(d0) & (d0 > 0)
        depth = torch.where(known, d0.clamp(lo, hi), depth)
    if init_normal is not None:
        n0 = init_normal.reshape(bsz, 3, p).transpose(1, 2)
        nn_ = n0.norm(dim=-1, keepdim=True)
        known = torch.isfinite(nn_) & (nn_ > 1e-6)
        n0 = _face_camera(n0 / nn_.clamp_min(1e-6), rays)
        ok = known & ((n0 * rays).sum(-1, keepdim=True) < -1e-3)
        normal = torch.where(ok, n0, normal)
    return depth, normal


def _check_inputs(
    image, src_images, K, src_K, world_to_cam, src_world_to_cam, depth_range, init, mask, src_masks
):
    dims = check_shape(image, "image", ("B", "C", "H", "W"))
    if src_images.ndim != 5:
        raise ValueError(f"src_images: expected shape (B, V, C, Hs, Ws), got {tuple(src_images.shape)}")
    check_shape(src_images, "src_images", ("B", "V", "C", "Hs", "Ws"), dims)
    if dims["V"] < 1:
        raise ValueError(f"src_images: expected at least one source view (V >= 1), got V={dims['V']}")
    check_shape(K, "K", ("B", 3, 3), dims)
    check_shape(src_K, "src_K", ("B", "V", 3, 3), dims)
    check_shape(world_to_cam, "world_to_cam", ("B", 4, 4), dims)
    check_shape(src_world_to_cam, "src_world_to_cam", ("B", "V", 4, 4), dims)
    for name, t in (("K", K), ("src_K", src_K), ("world_to_cam", world_to_cam)):
        check_finite(t, name)
    check_finite(src_world_to_cam, "src_world_to_cam")
    init_depth, init_normal = init
    if init_depth is not None:
        check_shape(init_depth, "init_depth", ("B", 1, "H", "W"), dims)
    if init_normal is not None:
        check_shape(init_normal, "init_normal", ("B", 3, "H", "W"), dims)
    if mask is not None:
        check_shape(mask, "mask", ("B", 1, "H", "W"), dims)
    if src_masks is not None:
        check_shape(src_masks, "src_masks", ("B", "V", 1, "Hs", "Ws"), dims)
    floats = {
        name: t.dtype
        for name, t in (
            ("image", image),
            ("src_images", src_images),
            ("K", K),
            ("src_K", src_K),
            ("world_to_cam", world_to_cam),
            ("src_world_to_cam", src_world_to_cam),
            ("init_depth", init_depth),
            ("init_normal", init_normal),
        )
        if t is not None and t.is_floating_point()
    }
    if len(set(floats.values())) > 1:
        raise ValueError(
            f"expected one floating dtype for the images, cameras and initial values, got {floats}; "
            "convert with .float() (or .double() for all)"
        )
    lo, hi = (float(x) for x in depth_range)
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo < hi):
        raise ValueError(f"depth_range: expected finite 0 < near < far, got {tuple(depth_range)}")
    return dims, lo, hi


def _check_images(image: torch.Tensor, src_images: torch.Tensor, cfg: PatchMatchConfig) -> None:
    """Float images at least ``window_radius + 1`` pixels per side, finite (a value check)."""
    for name, t in (("image", image), ("src_images", src_images)):
        if not t.is_floating_point():
            raise ValueError(
                f"{name}: expected a floating dtype (intensities in [0, 1]), got {t.dtype}; "
                "convert with x.float() / 255"
            )
    need = cfg.window_radius + 1
    for name, size in (("image", tuple(image.shape[-2:])), ("src_images", tuple(src_images.shape[-2:]))):
        if min(size) < need:
            raise ValueError(
                f"{name}: expected (H, W) of at least ({need}, {need}) pixels (window_radius + 1, so "
                f"that every matching window holds image pixels), got {size}"
            )
    check_finite(image, "image")
    check_finite(src_images, "src_images")


@torch.no_grad()
def patchmatch(
    image: torch.Tensor,
    src_images: torch.Tensor,
    K: torch.Tensor,
    src_K: torch.Tensor,
    world_to_cam: torch.Tensor,
    src_world_to_cam: torch.Tensor,
    depth_range: tuple[float, float],
    config: PatchMatchConfig | None = None,
    init_depth: torch.Tensor | None = None,
    init_normal: torch.Tensor | None = None,
    mask: torch.Tensor | None = None,
    src_masks: torch.Tensor | None = None,
) -> PatchMatchResult:
    r"""Estimate depth and normal maps of reference views by multi-view PatchMatch.

    Not differentiable (a search; runs under :func:`torch.no_grad`).

    Args:
        image: ``(B, C, H, W)`` reference images in [0, 1] (``C = 3`` RGB or any grey channels).
        src_images: ``(B, V, C, Hs, Ws)`` the ``V`` source images of each reference.
        K: ``(B, 3, 3)`` reference intrinsics.
        src_K: ``(B, V, 3, 3)`` source intrinsics.
        world_to_cam: ``(B, 4, 4)`` reference poses. For a rigid moving object pass the poses in
            its frame (:func:`vadgs.geometry.cameras_in_object_frame`) and restrict ``mask``.
        src_world_to_cam: ``(B, V, 4, 4)`` source poses, in the same frame.
        depth_range: ``(near, far)`` bounds of random depths (sampled uniformly in inverse depth).
        config: a :class:`PatchMatchConfig` (defaults if ``None``).
        init_depth: optional ``(B, 1, H, W)`` initial depth (e.g. rendered by the Gaussians);
            ``0`` where unknown (those pixels start random).
        init_normal: optional ``(B, 3, H, W)`` initial camera-frame normals (flipped to face the
            camera; zero where unknown: random).
        mask: optional ``(B, 1, H, W)`` bool region of the reference to reconstruct (static
            region, or one object); pixels outside get no estimate and do not weigh in windows.
        src_masks: optional ``(B, V, 1, Hs, Ws)`` bool regions of the sources; a window whose
            centre falls outside scores the worst cost in that view.

    Returns:
        A :class:`PatchMatchResult`.

    Raises:
        ValueError: on bad shapes, non-floating images, images smaller than
            ``window_radius + 1`` pixels per side, non-finite images (a value check, see
            :mod:`vadgs.checks`), fewer than one source view, a bad depth range, or when every
            source of a reference coincides with it (zero baseline: depth is unobservable).
            Individual sources with a zero baseline are ignored (worst cost).

    Shape:
        ``B`` references, each with ``V`` sources of size ``(Hs, Ws)`` (may differ from the
        reference's ``(H, W)``).

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> tex = torch.rand(1, 1, 40, 64, generator=g)  # a textured fronto-parallel plane at z = 2
        >>> K = torch.tensor([[[50.0, 0, 31.5], [0, 50.0, 19.5], [0, 0, 1]]])
        >>> src = torch.roll(tex, shifts=-5, dims=-1)  # baseline 0.2: disparity 50 * 0.2 / 2 = 5 px
        >>> w2c = torch.eye(4)[None]; s2c = torch.eye(4)[None, None].clone(); s2c[0, 0, 0, 3] = -0.2
        >>> res = patchmatch(tex, src[:, None], K, K[:, None], w2c, s2c, (1.0, 10.0))
        >>> err = (res.depth[0, 0, 8:-8, 8:-12] - 2).abs()
        >>> bool(err.median() < 0.01), bool((err < 0.02).float().mean() > 0.9)
        (True, True)
    """
    cfg = config or PatchMatchConfig()
    _, lo, hi = _check_inputs(
        image, src_images, K, src_K, world_to_cam, src_world_to_cam, depth_range,
        (init_depth, init_normal), mask, src_masks,
    )  # fmt: skip
    _check_images(image, src_images, cfg)
    return _pyramid(
        image, src_images, K, src_K, world_to_cam, src_world_to_cam, (lo, hi), cfg,
        init_depth, init_normal, mask, src_masks, cfg.pyramid_levels,
    )  # fmt: skip


def _downsample(x: torch.Tensor, size: tuple[int, int], mode: str) -> torch.Tensor:
    lead = x.shape[:-3]
    flat = x.reshape(-1, *x.shape[-3:])
    if mode == "area":
        out = F.interpolate(flat, size=size, mode="bilinear", antialias=True, align_corners=False)
    else:
        out = F.interpolate(flat.float(), size=size, mode="nearest").to(x.dtype)
    return out.reshape(*lead, *out.shape[-3:])


def _pyramid(
    image, src_images, K, src_K, world_to_cam, src_world_to_cam, depth_range, cfg, init_depth,
    init_normal, mask, src_masks, levels: int, start_iteration: int = 0,
) -> PatchMatchResult:  # fmt: skip
    """Coarse-to-fine: solve at half resolution, upsample the hypotheses, refine at this one."""
    h, w = image.shape[-2:]
    hs, ws = src_images.shape[-2:]
    if levels <= 1 or cfg.iterations == 0 or min(h, w, hs, ws) < 8:
        return _patchmatch_level(
            image, src_images, K, src_K, world_to_cam, src_world_to_cam, depth_range, cfg,
            init_depth, init_normal, mask, src_masks, start_iteration, cfg.iterations,
        )  # fmt: skip
    hc, wc, hsc, wsc = (h + 1) // 2, (w + 1) // 2, (hs + 1) // 2, (ws + 1) // 2
    coarse = _pyramid(
        _downsample(image, (hc, wc), "area"),
        _downsample(src_images, (hsc, wsc), "area"),
        scale_intrinsics(K, (wc / w, hc / h)),
        scale_intrinsics(src_K, (wsc / ws, hsc / hs)),
        world_to_cam,
        src_world_to_cam,
        depth_range,
        cfg,
        None if init_depth is None else _downsample(init_depth, (hc, wc), "nearest"),
        None if init_normal is None else _downsample(init_normal, (hc, wc), "nearest"),
        None if mask is None else _downsample(mask, (hc, wc), "nearest"),
        None if src_masks is None else _downsample(src_masks, (hsc, wsc), "nearest"),
        levels - 1,
    )
    up_depth = _downsample(coarse.raw_depth, (h, w), "nearest")
    up_normal = _downsample(coarse.raw_normal, (h, w), "nearest")
    done = cfg.iterations + (levels - 2) * cfg.fine_iterations
    fine = cfg if cfg.fine_propagation is None else replace(cfg, propagation=cfg.fine_propagation)
    return _patchmatch_level(
        image, src_images, K, src_K, world_to_cam, src_world_to_cam, depth_range, fine,
        up_depth, up_normal, mask, src_masks, done, cfg.fine_iterations,
        None if init_depth is None and init_normal is None else (init_depth, init_normal),
    )  # fmt: skip


def _patchmatch_level(
    image, src_images, K, src_K, world_to_cam, src_world_to_cam, depth_range, cfg, init_depth,
    init_normal, mask, src_masks, start_iteration: int, iterations: int,
    alt_init: tuple[torch.Tensor | None, torch.Tensor | None] | None = None,
) -> PatchMatchResult:  # fmt: skip
    """PatchMatch at one resolution (inputs already checked)."""
    lo, hi = depth_range
    dims = {"B": image.shape[0], "V": src_images.shape[1], "H": image.shape[-2], "W": image.shape[-1]}
    dims["Hs"], dims["Ws"] = src_images.shape[-2:]
    bsz, nv, h, w = dims["B"], dims["V"], dims["H"], dims["W"]
    hs, ws = dims["Hs"], dims["Ws"]
    dev, dt = image.device, image.dtype
    gen = None
    if cfg.seed is not None:
        gen = torch.Generator(device=dev)
        gen.manual_seed(cfg.seed)

    # Sources: grey images, normalised homography parts, degenerate views.
    src_from_ref = relative_pose(world_to_cam[:, None], src_world_to_cam)  # (B, V, 4, 4)
    baseline = src_from_ref[..., :3, 3].norm(dim=-1)
    usable = baseline > 1e-6 * lo
    if not bool(usable.any(-1).all()):
        bad = [int(i) for i in torch.nonzero(~usable.any(-1)).flatten()]
        raise ValueError(
            f"src_world_to_cam: every source of reference(s) {bad} has the reference's camera centre "
            "(zero baseline): depth is unobservable"
        )
    norm = torch.tensor(
        [[2 / max(ws - 1, 1), 0, -1], [0, 2 / max(hs - 1, 1), -1], [0, 0, 1]], device=dev, dtype=dt
    )
    Kinv = torch.linalg.inv(K)
    A = norm @ src_K @ src_from_ref[..., :3, :3] @ Kinv[:, None]
    bvec = (norm @ src_K @ src_from_ref[..., :3, 3:]).squeeze(-1)
    offsets = patch_offsets(cfg.window_radius, cfg.window_step, device=dev, dtype=dt)
    n_axis = math.isqrt(offsets.shape[0])
    axis = offsets[:n_axis, 0]  # row-major grid: the first row holds the x offsets (= the y offsets)
    src_gray = _to_gray(src_images.reshape(bsz * nv, -1, hs, ws))
    smasks = None if src_masks is None else src_masks.reshape(bsz * nv, 1, hs, ws).to(dt)
    src = _Sources(src_gray, smasks, A, bvec, Kinv, usable, axis)
    chunk = _chunk_size(cfg.chunk_size, dev, nv)

    # Reference: windows, bilateral weights (zero outside the region), statistics per colour.
    gray = _to_gray(image)
    patches = reference_patches(gray, offsets)  # (B, S, HW)
    sigma_s = cfg.sigma_spatial if cfg.sigma_spatial is not None else float(cfg.window_radius)
    weights = bilateral_weights(patches, offsets, sigma_s, cfg.sigma_color, dim=1)
    region = torch.ones(bsz, 1, h, w, dtype=torch.bool, device=dev) if mask is None else mask.bool()
    if mask is not None:
        inside = reference_patches(region.to(dt), offsets) > 0.5
        weights = weights * inside
        weights = weights / weights.sum(1, keepdim=True).clamp_min(1e-12)
    region_flat = region.reshape(bsz, h * w)

    ys, xs = torch.meshgrid(torch.arange(h, device=dev), torch.arange(w, device=dev), indexing="ij")
    xs, ys = xs.reshape(-1), ys.reshape(-1)
    pix_all = torch.stack([xs, ys, torch.ones_like(xs)], dim=-1).to(dt)  # (HW, 3)
    rays_all = pix_all @ Kinv.transpose(-1, -2)  # (B, HW, 3)
    regions = propagation_regions(cfg.propagation)
    flat_off = [o for r in regions for o in r]
    # Only the pixels of the region (of any batch element) are scored: with a small object in a
    # large crop, the cost follows the object, not the crop. Pixels outside keep the worst cost, so
    # they never win a propagation (as when they were scored: the region zeroes their statistics).
    active = region_flat.any(0)
    colours = []
    for c in (0, 1):
        sel = ((xs + ys) % 2 == c) & active
        idx = torch.nonzero(sel).flatten()
        px, py = xs[idx], ys[idx]
        nbr, nbr_ok = [], []
        for dx, dy in flat_off:
            qx, qy = px + dx, py + dy
            ok = (qx >= 0) & (qx < w) & (qy >= 0) & (qy < h)
            nbr.append(qy.clamp(0, h - 1) * w + qx.clamp(0, w - 1))
            nbr_ok.append(ok)
        st = reference_patch_stats(patches[:, :, idx], weights[:, :, idx], cfg.min_variance)
        st = ReferencePatchStats(st.weights, st.normalized, st.valid & region_flat[:, idx])
        colours.append(
            _Colour(
                idx,
                pix_all[idx],
                rays_all[:, idx],
                st,
                torch.stack(nbr, dim=1),
                torch.stack(nbr_ok, dim=1),
                [len(r) for r in regions],
            )
        )
    del patches, weights
    colours = [col for col in colours if col.idx.numel()]  # an empty region scores nothing

    # Initial hypotheses: random, overridden where an init is given; with an alternative
    # (coarse-to-fine: the caller's full-resolution init), the better-scoring of the two.
    depth = _random_depth((bsz, h * w), lo, hi, gen, rays_all)
    normal = _random_normals(rays_all, gen)
    depth, normal = _apply_init(depth, normal, init_depth, init_normal, rays_all, lo, hi)
    view_cost = torch.full((bsz, nv, h * w), MAX_COST, device=dev, dtype=dt)
    agg = torch.full((bsz, h * w), MAX_COST, device=dev, dtype=dt)
    for col in colours:
        vc = _view_costs(src, col, depth[:, col.idx], normal[:, col.idx], cfg.min_variance, chunk)
        view_cost[:, :, col.idx] = vc
        agg[:, col.idx] = _aggregate(vc[None], None, cfg)[0]
    if alt_init is not None:
        alt_d, alt_n = _apply_init(depth, normal, *alt_init, rays_all, lo, hi)
        for col in colours:
            vc = _view_costs(src, col, alt_d[:, col.idx], alt_n[:, col.idx], cfg.min_variance, chunk)
            a = _aggregate(vc[None], None, cfg)[0]
            better = a < agg[:, col.idx]
            idx = col.idx
            depth[:, idx] = torch.where(better, alt_d[:, idx], depth[:, idx])
            normal[:, idx] = torch.where(better[..., None], alt_n[:, idx], normal[:, idx])
            view_cost[:, :, idx] = torch.where(better[:, None], vc, view_cost[:, :, idx])
            agg[:, idx] = torch.where(better, a, agg[:, idx])

    refine_kinds = [("p", "p"), ("p", "c"), ("c", "p"), ("r", "r"), ("r", "c"), ("c", "r")][: cfg.num_refine]
    for it in range(start_iteration, start_iteration + iterations):
        dscale = cfg.depth_perturbation * 0.5**it
        nscale = cfg.normal_perturbation * 0.5**it
        for col in colours:
            idx, rays = col.idx, col.rays
            cur_d, cur_n = depth[:, idx], normal[:, idx]
            # Propagation: best-cost neighbour of each region, its plane re-intersected.
            nbr_t = col.nbr  # (P, N): the regions' neighbours of a pixel are contiguous
            nb_cost = agg[:, nbr_t]  # (B, P, N)
            nb_cost = torch.where(col.nbr_ok, nb_cost, torch.full_like(nb_cost, float("inf")))
            cands_d, cands_n = [], []
            start = 0
            for size in col.region_sizes:
                best = nb_cost[..., start : start + size].argmin(-1)  # (B, P)
                q = torch.gather(nbr_t[:, start : start + size].expand(bsz, -1, -1), 2, best[..., None])[
                    ..., 0
                ]
                start += size
                zq = torch.gather(depth, 1, q)
                nq = torch.gather(normal, 1, q[..., None].expand(-1, -1, 3))
                rq = torch.gather(rays_all, 1, q[..., None].expand(-1, -1, 3))
                cands_d.append(_propagate_depth(zq, nq, rq, rays, lo, hi))
                cands_n.append(nq)
            cand_costs = torch.stack(
                [_view_costs(src, col, d, n, cfg.min_variance, chunk) for d, n in zip(cands_d, cands_n)]
            )  # (N, B, V, P)
            all_costs = torch.cat([view_cost[None, :, :, idx], cand_costs])
            vw = _view_weights(all_costs, cfg) if cfg.view_selection == "acmh" else None
            all_agg = _aggregate(all_costs, vw, cfg)  # (N+1, B, P)
            all_d = torch.stack([cur_d, *cands_d])
            all_n = torch.stack([cur_n, *cands_n])
            best_agg, best = all_agg.min(0)
            cur_d = torch.gather(all_d, 0, best[None])[0]
            cur_n = torch.gather(all_n, 0, best[None, ..., None].expand(1, -1, -1, 3))[0]
            cur_vc = torch.gather(all_costs, 0, best[None, :, None].expand(1, -1, nv, -1))[0]
            # Random refinement around the winner, scored with the same view weights.
            if refine_kinds:
                rd = [
                    cur_d
                    * torch.exp(
                        (torch.rand(cur_d.shape, generator=gen, device=dev, dtype=dt) * 2 - 1) * dscale
                    )
                    for _ in range(2)
                ]
                rn = [_perturb_normals(cur_n, rays, nscale, gen) for _ in range(2)]
                rand_d = _random_depth(cur_d.shape, lo, hi, gen, cur_d)
                rand_n = _random_normals(rays, gen)
                ref_d, ref_n = [], []
                for i, (kd, kn) in enumerate(refine_kinds):
                    ref_d.append({"p": rd[i % 2].clamp(lo, hi), "c": cur_d, "r": rand_d}[kd])
                    ref_n.append({"p": rn[i % 2], "c": cur_n, "r": rand_n}[kn])
                ref_costs = torch.stack(
                    [_view_costs(src, col, d, n, cfg.min_variance, chunk) for d, n in zip(ref_d, ref_n)]
                )
                ref_agg = _aggregate(ref_costs, vw, cfg)
                r_best_agg, r_best = ref_agg.min(0)
                better = r_best_agg < best_agg
                new_d = torch.gather(torch.stack(ref_d), 0, r_best[None])[0]
                new_n = torch.gather(torch.stack(ref_n), 0, r_best[None, ..., None].expand(1, -1, -1, 3))[0]
                new_vc = torch.gather(ref_costs, 0, r_best[None, :, None].expand(1, -1, nv, -1))[0]
                cur_d = torch.where(better, new_d, cur_d)
                cur_n = torch.where(better[..., None], new_n, cur_n)
                cur_vc = torch.where(better[:, None], new_vc, cur_vc)
                best_agg = torch.where(better, r_best_agg, best_agg)
            depth[:, idx] = cur_d
            normal[:, idx] = cur_n
            view_cost[:, :, idx] = cur_vc
            agg[:, idx] = best_agg

    valid = region_flat & (agg <= cfg.max_cost) & torch.isfinite(depth) & (depth > 0)
    for col in colours:
        valid[:, col.idx] &= col.stats.valid
    raw = depth.reshape(bsz, 1, h, w)
    valid = valid.reshape(bsz, 1, h, w)
    normal_map = normal.transpose(1, 2).reshape(bsz, 3, h, w)
    return PatchMatchResult(
        depth=torch.where(valid, raw, torch.zeros_like(raw)),
        normal=torch.where(valid, normal_map, torch.zeros_like(normal_map)),
        cost=agg.reshape(bsz, 1, h, w),
        view_costs=view_cost.reshape(bsz, nv, h, w),
        mask=valid,
        raw_depth=raw,
        raw_normal=normal_map,
    )


class PatchMatch(nn.Module):
    """Multi-view PatchMatch stereo as a module holding its :class:`PatchMatchConfig`.

    See :func:`patchmatch`.

    Example:
        >>> PatchMatch(PatchMatchConfig(iterations=2)).config.iterations
        2
    """

    def __init__(self, config: PatchMatchConfig | None = None) -> None:
        super().__init__()
        self.config = config or PatchMatchConfig()

    def forward(
        self,
        image: torch.Tensor,
        src_images: torch.Tensor,
        K: torch.Tensor,
        src_K: torch.Tensor,
        world_to_cam: torch.Tensor,
        src_world_to_cam: torch.Tensor,
        depth_range: tuple[float, float],
        init_depth: torch.Tensor | None = None,
        init_normal: torch.Tensor | None = None,
        mask: torch.Tensor | None = None,
        src_masks: torch.Tensor | None = None,
    ) -> PatchMatchResult:
        """Run :func:`patchmatch` with the stored config."""
        return patchmatch(
            image, src_images, K, src_K, world_to_cam, src_world_to_cam, depth_range, self.config,
            init_depth, init_normal, mask, src_masks,
        )  # fmt: skip
