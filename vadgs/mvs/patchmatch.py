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

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from kornia.color import rgb_to_grayscale
from torch import nn

from vadgs.checks import (
    Checked,
    bool_field,
    check_finite,
    check_shape,
    checked,
    checks_enabled,
    choice_field,
    float_field,
    int_field,
)
from vadgs.mvs.cost import (
    MAX_COST,
    bilateral_weights,
    patch_center_indices,
    patch_offsets,
    reference_terms,
    spatial_log_weights,
    window_patches,
)

__all__ = [
    "MatchPixels",
    "MatchSources",
    "PatchMatch",
    "PatchMatchConfig",
    "PatchMatchResult",
    "map_tables",
    "match_costs",
    "patchmatch",
    "propagation_regions",
    "window_maps",
]


@dataclass(frozen=True)
class PatchMatchConfig(Checked):
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
        chunk_size: pixel-views (times hypotheses) scored at once, over all the references of a
            call; ``None``: 4096 on CPU (temporaries stay in cache, about 3x faster than one pass),
            everything at once on other devices.
        pyramid_levels: coarse-to-fine levels (ACMM-style; default 2). ``1``: a single scale. ``L > 1``: the
            ``iterations`` run on images downsampled ``2^(L-1)`` times, then at each finer level
            the upsampled hypotheses are refined by ``fine_iterations`` more sweeps (with the
            perturbation spread continuing to shrink). Most of the search happens on a quarter
            (or less) of the pixels, and the larger effective window helps on weak texture.
        fine_iterations: sweeps at each level finer than the coarsest (``pyramid_levels > 1``).
        fine_propagation: propagation pattern of the finer levels (``None``: ``propagation``);
            ``"cross"`` halves their cost once the coarse level has spread good planes.
        joint_scoring: score the random refinements together with the propagated planes, in one
            cost evaluation per half-sweep, around the likeliest winner known before scoring (the
            plane of lowest cost where it was last scored) instead of around the propagation's
            winner: about a quarter fewer kernel launches (744 instead of 984 for the defaults,
            ``docs/benchmarks.md``), less accurate (street_a frame 20: 29.6 % instead of 32.4 %
            of the raw depths within 1 %, mean of seeds 0-2).
        compile: run each half-sweep through one :func:`torch.compile` of :func:`_half_sweep`
            (``dynamic=True``, compiled once per process and reused: the pixel count and the depth
            bounds are symbolic, so another crop size or depth range compiles nothing new; a
            finer pyramid level adds one graph). Meant for CUDA, where the half-sweep's ~100 kernel
            launches become a few fused kernels; it works on the CPU too (that is how it is
            tested) but is no faster there. The first call compiles (seconds to a minute); the
            eager path (``False``) is the reference it is tested against (depths within 1e-4
            relative on >= 99 % of the pixels of ``tests/mvs/test_patchmatch_compile.py``).
    """

    iterations: int = checked(3, int_field(0))
    window_radius: int = checked(5, int_field(1))
    window_step: int = checked(2, int_field(1))
    sigma_spatial: float | None = checked(None, float_field(0, lo_open=True, optional=True))
    sigma_color: float = checked(0.2, float_field(0, lo_open=True))
    min_variance: float = checked(1e-5, float_field(0))
    propagation: str = checked("acmh", choice_field(("acmh", "cross")))
    num_refine: int = checked(3, int_field(0, 6))
    depth_perturbation: float = checked(0.05, float_field(0))
    normal_perturbation: float = checked(0.5, float_field(0))
    view_selection: str = checked("acmh", choice_field(("acmh", "topk", "mean")))
    top_k: int = checked(2, int_field(1))
    good_threshold: float = checked(0.8, float_field(0))
    bad_threshold: float = checked(1.2, float_field(0))
    beta: float = checked(0.3, float_field(0, lo_open=True))
    max_cost: float = checked(0.6, float_field(0))
    seed: int | None = checked(0, int_field(optional=True))
    chunk_size: int | None = checked(None, int_field(1, optional=True))
    pyramid_levels: int = checked(2, int_field(1))
    fine_iterations: int = checked(1, int_field(0))
    fine_propagation: str | None = checked(None, choice_field(("acmh", "cross", None)))
    joint_scoring: bool = checked(False, bool_field())
    compile: bool = checked(False, bool_field())


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
    """``(*, 1, H, W)`` grey levels of ``(*, C, H, W)`` images (RGB, or the mean of the channels).

    kornia's weights, given as a tensor made on the host (kornia fills its own on the device:
    four launches), round from the same numbers: the same grey levels.
    """
    if x.shape[-3] == 1:
        return x
    if x.shape[-3] != 3:
        return x.mean(-3, keepdim=True)
    return rgb_to_grayscale(x, torch.tensor([0.299, 0.587, 0.114], device=x.device, dtype=x.dtype))


def _random_normals(rays: torch.Tensor, gen: torch.Generator | None) -> torch.Tensor:
    n = torch.randn(rays.shape, generator=gen, device=rays.device, dtype=rays.dtype)
    return _face_camera(n / torch.linalg.vector_norm(n, dim=-1, keepdim=True), rays)


def _face_camera(n: torch.Tensor, rays: torch.Tensor) -> torch.Tensor:
    return torch.where((n * rays).sum(-1, keepdim=True) > 0, -n, n)


def _random_depth(shape, lo, hi, gen, like) -> torch.Tensor:
    """Depths of ``shape`` ``(B, ...)`` uniform in inverse depth between ``lo`` and ``hi``.

    ``lo``, ``hi``: numbers, or ``(B,)`` tensors (one range per reference).
    """
    u = torch.rand(shape, generator=gen, device=like.device, dtype=like.dtype)
    lo, hi = _per_reference(lo, len(shape) - 1), _per_reference(hi, len(shape) - 1)
    return u.mul_(1 / lo - 1 / hi).add_(1 / hi).reciprocal_()


def _per_reference(x: float | torch.Tensor, dims: int) -> float | torch.Tensor:
    """A depth bound broadcastable over ``(B, *dims)``: a number as it is, a ``(B,)`` tensor reshaped."""
    return x if not isinstance(x, torch.Tensor) else x.view(-1, *([1] * dims))


class MatchPixels(NamedTuple):
    """The scored reference pixels of one level, the first colour's then the second's.

    A colour is a slice (:meth:`part`), so that a half-sweep reads and writes contiguous runs.
    """

    idx: torch.Tensor  # (B, P) flat pixel indices
    rays: torch.Tensor  # (B, P, 3) K^-1 p~
    cols: torch.Tensor  # (B, 3, 3, P) [m, j]: m-th entry of K^-1 e_x, K^-1 e_y, K^-1 p~ (see window_maps)
    rows: torch.Tensor  # (B, V, 3, P, 3) A e_x, A e_y, A p~: the hypothesis-free part of the maps
    ref: torch.Tensor  # (B, 2, S, P) bilateral weights (zero where the reference window is flat or
    #   outside the region: such a pixel scores the worst cost) and w (r - mean) / std

    def part(self, sl: slice) -> MatchPixels:
        """The pixels of ``sl`` (a view of every field)."""
        return MatchPixels(
            self.idx[:, sl], self.rays[:, sl], self.cols[..., sl], self.rows[:, :, :, sl], self.ref[..., sl]
        )


class MatchSources(NamedTuple):
    """The source views of one level: grey images, masks and the hypothesis-free homography parts."""

    gray: torch.Tensor  # (B*V, 1, Hs, Ws), zero (flat: the worst cost) for a degenerate source
    masks: torch.Tensor | None  # (B*V, 1, Hs, Ws) float or None
    b: torch.Tensor  # (B, V, 3) N K_s t
    offsets: torch.Tensor  # (B*V, S, 3) window offsets (o_x, o_y, 1) (expanded)
    one: torch.Tensor  # () 1, for the fused 1 - ncc
    zero: torch.Tensor  # () 0
    worst: torch.Tensor  # () MAX_COST
    nan: torch.Tensor  # () NaN: the maps of a plane seen edge-on or from behind


def window_maps(src: MatchSources, px: MatchPixels, hyp: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Plane homographies of ``K`` hypotheses per pixel in grid_sample coordinates, and their validity.

    ``hyp`` is ``(B, K, P, 4)``: depth and normal. Returns ``C`` ``(B, V, 3, K, P, 3)`` with
    ``C[:, :, 0] = H e_x``, ``C[:, :, 1] = H e_y`` and ``C[:, :, 2] = H p~`` (rows as vectors), so
    the window sample at offset ``o`` maps to ``(o_x, o_y, 1) @ C`` (homogeneous coordinates,
    normalised to [-1, 1] for :func:`torch.nn.functional.grid_sample`), and ``nr`` ``(B, K, P)``,
    ``n^T K^-1 p~``. Where the plane is seen edge-on or from behind (``nr >= -1e-6``) the maps
    are NaN, so that the window centre's test of :func:`match_costs` fails (the worst cost).
    ``H = N K_s (R - t n^T / d) K_r^-1`` of :func:`vadgs.geometry.plane_homography` is
    ``A - b m^T`` with ``m = K_r^-T n / d`` and ``d = -z nr``, so ``C = rows + b u^T`` with
    ``u = (-m_x, -m_y, 1 / z) = (n^T K^-1 e_x, n^T K^-1 e_y, nr) / (z nr)`` (because
    ``m^T p~ = -1 / z``): a few fused multiply-adds over every view and hypothesis.
    """
    z, n = hyp[..., 0], hyp[..., 1:]
    cols = px.cols[:, :, :, None]  # (B, 3, 3, 1, P)
    t = n[:, None, ..., 0] * cols[:, 0]
    t = torch.addcmul(t, n[:, None, ..., 1], cols[:, 1])
    t = torch.addcmul(t, n[:, None, ..., 2], cols[:, 2])  # (B, 3, K, P): n^T K^-1 (e_x, e_y, p~)
    nr = t[:, 2]
    u = t / (z * torch.where(nr < -1e-6, nr, src.nan))[:, None]  # NaN where the plane is rejected
    C = torch.addcmul(px.rows[:, :, :, None], src.b[:, :, None, None, None], u[:, None, ..., None])
    return C, nr


def map_tables(
    A: torch.Tensor, Kinv: torch.Tensor, pix: torch.Tensor, rays: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """The hypothesis-free tables of :func:`window_maps`, ``cols`` and ``rows``.

    ``A`` ``(B, V, 3, 3)`` is ``N K_s R K_r^-1``, ``pix`` ``(B, P, 3)`` (or ``(P, 3)``) the pixels, ``rays``
    ``(B, P, 3)`` their ``K_r^-1 p~``. Returns ``cols`` ``(B, 3, 3, P)`` and ``rows``
    ``(B, V, 3, P, 3)`` (see :class:`MatchPixels`).
    """
    p = pix.shape[-2]
    cols = torch.cat([Kinv[..., :2, None].expand(-1, -1, -1, p), rays.transpose(1, 2)[:, :, None]], 2)
    rows = torch.stack(
        [
            A[:, :, None, :, 0].expand(-1, -1, p, -1),
            A[:, :, None, :, 1].expand(-1, -1, p, -1),
            torch.einsum("bvij,pj->bvpi" if pix.ndim == 2 else "bvij,bpj->bvpi", A, pix),
        ],
        dim=2,
    )
    return cols, rows


def _chunk_size(cfg_chunk: int | None, device: torch.device, views: int) -> int:
    if cfg_chunk is None:
        cfg_chunk = 4096 if device.type == "cpu" else 1 << 30
    return max(1, cfg_chunk // views)


def match_costs(
    src: MatchSources, px: MatchPixels, hyp: torch.Tensor, min_variance: float, chunk: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-view costs ``(B, V, K, P)`` of ``K`` hypotheses per pixel, ``hyp`` ``(B, K, P, 4)``, and ``nr``.

    Every hypothesis of every pixel in every view is one sample grid of one
    :func:`torch.nn.functional.grid_sample` call (a handful of kernels whatever ``K``, ``V`` and
    ``P``), scored ``chunk`` pixel-hypotheses at a time so that the temporaries stay in cache on the
    CPU (one chunk on other devices). The cost is :func:`vadgs.mvs.ncc_cost_from_stats` (``tests/mvs``
    checks the two against each other) with every reason for the worst cost folded into one mask.
    ``nr`` ``(B, K, P)`` is ``n^T K^-1 p~`` of each hypothesis (see :func:`window_maps`).
    """
    C, nr = window_maps(src, px, hyp)
    bsz, v, _, k, p, _ = C.shape
    s = src.offsets.shape[1]
    step = max(1, chunk // k)
    # compiled (PatchMatchConfig.compile): one pass, so that the pixel count stays symbolic (a
    # loop over it would pin it: a recompile for every crop size)
    traced = torch.compiler.is_compiling()
    spans = [(0, p)] if traced else [(p0, min(step, p - p0)) for p0 in range(0, p, step)]
    costs, variances = [], []
    for p0, pc in spans:
        cc = C[..., p0 : p0 + pc, :].reshape(bsz * v, 3, k * pc * 3)
        xyz = torch.bmm(src.offsets, cc).view(bsz * v, s, k * pc, 3)  # (o_x, o_y, 1) @ C
        grid = xyz[..., :2] / xyz[..., 2:].clamp_min(1e-9)  # behind the camera: far outside
        x = F.grid_sample(src.gray, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
        x = x.view(bsz, v, 1, s, k, pc)
        prod = x * px.ref[:, None, :, :, None, p0 : p0 + pc]  # (B, V, 2, S, K, pc): w x, w x (r - mean) / std
        mean, cov = prod.sum(3).unbind(2)
        var = torch.addcmul((prod[:, :, 0] * x[:, :, 0]).sum(2), mean, mean, value=-1)
        # 1 - ncc, in [0, 2] up to rounding (clamped once, in the result); where var < min_variance
        # (NaN or infinite here) the mask below puts the worst cost
        costs.append(torch.addcmul(src.one, cov, var.rsqrt(), value=-1))
        variances.append(var)
    cost = torch.cat(costs, dim=-1) if len(costs) > 1 else costs[0]
    var = torch.cat(variances, dim=-1) if len(variances) > 1 else variances[0]
    # The worst cost where a window is flat, where the window centre does not land in front of the
    # source camera inside its image (and mask), where the plane is seen edge-on (NaN maps: the
    # comparisons are False).
    c0 = C[:, :, 2]  # (B, V, K, P, 3)
    cz = c0[..., 2]
    inside = torch.linalg.vector_norm(c0[..., :2], ord=math.inf, dim=-1) <= cz  # and in front
    good = (var >= min_variance) & inside
    if src.masks is not None:
        cxy = c0[..., :2] / cz.clamp_min(1e-9)[..., None]
        m = F.grid_sample(
            src.masks,
            cxy.reshape(bsz * v, k * p, 1, 2),
            mode="nearest",
            padding_mode="zeros",
            align_corners=True,
        )
        good = good & (m.view(bsz, v, k, p) >= 0.5)
    return torch.where(good, cost, src.worst), nr


def _drop_limits(cfg: PatchMatchConfig, device: torch.device, dtype: torch.dtype) -> torch.Tensor | None:
    """``(2, 1)``: the largest ``dtype`` value under ``good_threshold``, and ``bad_threshold``.

    A view is dropped where its second-lowest cost exceeds the first (fewer than two good costs)
    or its ``(N - 3)``-th lowest exceeds the second (more than three bad costs): one comparison
    of both order statistics (see :func:`_view_weights`). ``None`` for a dtype numpy lacks.
    """
    good = _adjacent(cfg.good_threshold, dtype, -math.inf)
    if good is None:
        return None
    return torch.tensor([[good], [cfg.bad_threshold]], device=device, dtype=dtype)


def _adjacent(x: float, dtype: torch.dtype, toward: float) -> float | None:
    """The ``dtype`` number next to ``x`` (as ``dtype`` rounds it) toward ``toward``.

    ``None`` for a dtype that numpy lacks (bfloat16).
    """
    np_dtype = {torch.float32: np.float32, torch.float64: np.float64, torch.float16: np.float16}.get(dtype)
    return None if np_dtype is None else float(np.nextafter(np_dtype(x), np_dtype(toward)))


def _view_weights(
    costs: torch.Tensor, cfg: PatchMatchConfig, zero: torch.Tensor, limits: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """ACMH view weights ``(B, V, P)`` of the costs ``(B, V, N, P)`` of N hypotheses, and where any is > 0.

    The weights are normalised to sum to one over the views (NaN where none is selected: the
    mask ``(B, 1, P)`` is False there), once for every :func:`_aggregate` call of a half-sweep.
    ``limits``: :func:`_drop_limits`'s.
    """
    good = costs < cfg.good_threshold
    n_good = good.sum(2)
    n = costs.shape[2]
    if n > 5 and limits is not None:  # the 2nd and the (N - 3)-th lowest costs, compared at once
        low = costs.topk(n - 3, dim=2, largest=False).values  # ascending
        dropped = (low[:, :, 1 : n - 3 : n - 5] > limits).any(2)
    else:
        dropped = n_good < 2
        if n > 3:  # more than three bad costs: the 4th largest is bad
            dropped = dropped | (costs.kthvalue(n - 3, dim=2).values > cfg.bad_threshold)
    conf = torch.addcmul(zero, costs, costs, value=-0.5 / cfg.beta**2).exp_().mul_(good)
    weights = (conf.sum(2) / n_good).masked_fill_(dropped, 0.0)
    wsum = weights.sum(1, keepdim=True)
    return weights / wsum, wsum > 0


def _aggregate(
    costs: torch.Tensor,
    weights: tuple[torch.Tensor, torch.Tensor] | None,
    cfg: PatchMatchConfig,
) -> torch.Tensor:
    """Aggregated costs ``(B, N, P)`` of per-view costs ``(B, V, N, P)``.

    ``weights``: :func:`_view_weights`'s (``None``: the mean of the ``top_k`` best views).
    """
    if cfg.view_selection == "mean":
        return costs.mean(1)
    topk = costs.topk(min(cfg.top_k, costs.shape[1]), dim=1, largest=False).values.mean(1)
    if cfg.view_selection == "topk" or weights is None:
        return topk
    w, has = weights
    return torch.where(has, (costs * w[:, :, None]).sum(1), topk)


def _scored_pixels(active: torch.Tensor, even: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Each reference's scored pixels ``(N, P)``, which are real ``(N, P)``, where the second colour starts.

    The pixels of ``active`` ``(N, HW)`` of the first colour (``even``), then of the second, in
    pixel order, each colour padded to the most pixels of any reference (``real`` False). One
    host read.
    """
    keys = torch.stack([active & even, active > even], 1)  # (N, 2, HW): each colour's pixels
    most = keys.sum(-1).amax(0).tolist()  # host read
    real, order = keys.sort(dim=-1, descending=True, stable=True)  # each colour's pixels first, in order
    idx = torch.cat([order[:, 0, : most[0]], order[:, 1, : most[1]]], 1)
    real = torch.cat([real[:, 0, : most[0]], real[:, 1, : most[1]]], 1)
    return idx, real, most[0]


def _take(x: torch.Tensor, idx: torch.Tensor, dim: int = 1) -> torch.Tensor:
    """``x`` ``(B, ..., HW, ...)`` at each reference's pixels ``idx`` ``(B, P)`` along ``dim``."""
    shape = [1] * x.ndim
    shape[0], shape[dim] = idx.shape
    return torch.gather(x, dim, idx.view(shape).expand(*x.shape[:dim], idx.shape[1], *x.shape[dim + 1 :]))


def _put(x: torch.Tensor, slot: torch.Tensor, values: torch.Tensor, padded: bool) -> torch.Tensor:
    """``x`` ``(B, HW, ...)`` with ``values`` ``(B, P, ...)`` at ``slot`` ``(B, P)``, in place.

    ``padded``: some slots are ``HW`` (padding, dropped), written to a spare slot (a copy).
    """
    index = slot.view(*slot.shape, *[1] * (x.ndim - 2)).expand_as(values)
    if not padded:
        return x.scatter_(1, index, values)
    return torch.cat([x, x[:, :1]], 1).scatter_(1, index, values)[:, : x.shape[1]]


def _neighbour_table(
    idx: torch.Tensor, h: int, w: int, lut: torch.Tensor, sentinel: int, kind: str
) -> torch.Tensor:
    """``(N, P, 1 + R, L)`` indices into the scored pixels: each pixel ``idx``, its regions' neighbours.

    ``idx`` ``(N, P)`` (flat pixel indices) and ``lut`` ``(N, HW + 1)`` (the scored pixel of each
    pixel) are of one reference each, or ``N = 1`` for all. Regions are padded to the longest;
    padding, neighbours outside the image and unscored neighbours point to ``sentinel`` (the
    index of a state row whose cost is infinite), a region with no other neighbour to the
    pixel itself. The neighbours are looked up in ``lut`` padded by the sentinel around the image,
    so that an offset is one addition: a handful of launches, once per level.
    """
    regions = [[(0, 0)], *propagation_regions(kind)]  # the pixel itself, then its R regions
    longest = max(len(r) for r in regions)
    pad = max(max(abs(dx), abs(dy)) for r in regions for dx, dy in r)
    wp = w + 2 * pad
    # (2, R, L): flat offsets in the padded table (from the pixel's padded index less pad * (wp + 1)),
    # and 1 for a neighbour, 0 for padding (then the offset is 0: a corner of the padding)
    rows = [[[(dy + pad) * wp + dx + pad for dx, dy in r] + [0] * (longest - len(r)) for r in regions]]
    rows.append([[1] * len(r) + [0] * (longest - len(r)) for r in regions])
    off, real = torch.tensor(rows, device=idx.device).unbind()
    padded = F.pad(lut[:, : h * w].view(-1, h, w), (pad, pad, pad, pad), value=sentinel)
    base = torch.add(idx, torch.div(idx, w, rounding_mode="floor"), alpha=wp - w)  # y wp + x
    q = torch.addcmul(off, base[..., None, None], real)
    table = torch.gather(padded.view(padded.shape[0], -1), 1, q.view(q.shape[0], -1)).view(q.shape)
    # A region wholly outside the image (or unscored) would offer only the sentinel, a plane of
    # fixed absolute depth: it offers the pixel's own plane instead (a tie with the current plane,
    # which argmin keeps), so that the search is equivariant to the scale of the world.
    empty = (table == sentinel).all(-1, keepdim=True)
    return torch.where(empty, table[..., :1, :1], table)


def _propagate(
    hyp: torch.Tensor,
    agg: torch.Tensor,
    nbr: torch.Tensor,
    rays: torch.Tensor,
    lo,
    hi,
    batch: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(B, 1 + R, P, 4)`` each pixel's plane, then the best-cost neighbour's plane of each region.

    The planes are re-intersected with the pixels' rays (a pixel's own: up to rounding, its depth).
    ``nbr`` ``(1 or B, P, 1 + R, L)`` is :func:`_neighbour_table`'s. ``hyp`` ``(B, N + 1, 5+)`` holds
    depth, normal and ``n^T K^-1 p~`` of every scored pixel and
    the sentinel, ``agg`` ``(B, N + 1)`` their costs. Also returns the costs ``(B, 1 + R, P)``
    where they were last scored. ``lo``, ``hi``: numbers or ``(B,)`` tensors. ``batch``: ``arange(B)``
    as ``(B, 1, 1, 1)`` when ``nbr`` is of each reference, None when it is one for all.
    """
    bsz = hyp.shape[0]
    p, r = nbr.shape[1:3]
    if batch is None:  # the same pixels for every reference
        nb_cost, best = agg[:, nbr[0]].min(-1, keepdim=True)  # (B, P, R, 1)
    else:
        nb_cost, best = agg[batch, nbr].min(-1, keepdim=True)
    q = torch.gather(nbr.expand(bsz, -1, -1, -1), 3, best)
    hq = torch.gather(hyp[..., :5], 1, q.view(bsz, p * r, 1).expand(-1, -1, 5)).view(bsz, p, r, 5)
    den = torch.bmm(hq[..., 1:4].reshape(bsz * p, r, 3), rays.reshape(bsz * p, 3, 1)).view(bsz, p, r)
    hq, den = hq.transpose(1, 2), den.transpose(1, 2)  # (B, 1 + R, P, 5), n_q^T K^-1 p~ (B, 1 + R, P)
    # z n^T K^-1 p~ is the plane's constant: z_p = z_q nr_q / den. Where the plane is seen edge-on
    # or from behind (den >= -1e-6) the depth is clamped to a bound, and the plane is rejected
    # when it is scored.
    lo, hi = _per_reference(lo, 2), _per_reference(hi, 2)
    z = (hq[..., 0] * hq[..., 4] / den).clamp_(lo, hi)
    return torch.cat([z[..., None], hq[..., 1:4]], -1), nb_cost[..., 0].transpose(1, 2)


def _refinements(
    cur: torch.Tensor, rays: torch.Tensor, noise: torch.Tensor, kinds: Sequence[tuple[str, str]], lo, hi,
    rand: tuple[torch.Tensor, torch.Tensor] | None,
) -> torch.Tensor:  # fmt: skip
    """``(B, len(kinds), P, 4)`` random refinements of the hypotheses ``cur`` ``(B, P, 4)``.

    Two perturbed depths (relative: ``z noise[..., i]``) and a perturbed normal (``n`` plus
    ``noise[..., 2:5]``, normalised, kept only when it faces the camera), the ``noise``
    ``(B, P, 8)`` uniform but for ``noise[..., :2]``, already exponentiated (the relative depth
    factors; ``noise[..., 5:]`` is drawn but unused), combined as ``kinds`` says:
    ``"p"`` perturbed (the ``i % 2``-th depth, the normal), ``"c"`` current, ``"r"`` random.
    ``kinds`` is a prefix of ACMH's list (see :func:`_patchmatch_level`): the result is the current
    plane repeated, with the perturbed and random parts written over it (a fixed handful of
    launches). ``lo``, ``hi``: numbers or ``(B,)`` tensors. ``rand``: the random depths ``(B, P)``
    and normals ``(B, P, 3)`` of the ``"r"`` kinds (:func:`_random_planes`, drawn by the caller),
    ``None`` when ``kinds`` has none.
    """
    k = len(kinds)  # a prefix of ("p", "p"), ("p", "c"), ("c", "p"), ("r", "r"), ("r", "c"), ("c", "r")
    z, n = cur[..., 0], cur[..., 1:4]
    lo, hi = _per_reference(lo, 2), _per_reference(hi, 2)
    out = cur[:, None, :, :4].repeat(1, k, 1, 1)  # (B, k, P, 4): "c" everywhere, then overwritten
    nd = min(k, 2)  # perturbed depths: kinds 0 and 1 (the i-th draw for kind i)
    # (torch.compile traces no non-contiguous ``out=``: there, the same numbers by assignment)
    traced = torch.compiler.is_compiling()
    pd = out[:, :nd, :, 0].transpose(1, 2)
    if traced:
        pd.copy_((z[..., None] * noise[..., :nd]).clamp(lo, hi))
    else:
        torch.mul(z[..., None], noise[..., :nd], out=pd).clamp_(lo, hi)
    # the perturbed normal: kinds 0 and 2 (both the first draw; the second is never used)
    m = n + noise[..., 2:5]  # |m| >= 1/2
    m = m / torch.linalg.vector_norm(m, dim=-1, keepdim=True)
    facing = torch.bmm(m.view(-1, 1, 3), rays.reshape(-1, 3, 1)).view(*m.shape[:-1], 1, 1) < -1e-3
    pn = out[:, 0:3:2, :, 1:4].transpose(1, 2)  # (B, P, 1 or 2, 3)
    if traced:
        pn.copy_(torch.where(facing, m[:, :, None], n[:, :, None]).expand_as(pn))
    else:
        torch.where(facing.expand_as(pn), m[:, :, None].expand_as(pn), n[:, :, None].expand_as(pn), out=pn)
    if k > 3:  # random hypotheses: depths for kinds 3 and 4, normals for kinds 3 and 5
        if rand is None:
            raise ValueError(f"rand: expected the random planes of kinds {list(kinds)}, got None")
        rd, rn = rand
        out[:, 3:5, :, 0] = rd[:, None]
        out[:, 3:6:2, :, 1:4] = rn[:, None]
    return out


#: ACMH's refinement kinds (see :func:`_refinements`); ``num_refine`` takes a prefix.
REFINE_KINDS = (("p", "p"), ("p", "c"), ("c", "p"), ("r", "r"), ("r", "c"), ("c", "r"))


def _random_planes(
    rays: torch.Tensor, cfg: PatchMatchConfig, lo, hi, gen: torch.Generator | None
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The random depths ``(B, P)`` and normals ``(B, P, 3)`` of a half-sweep's refinements.

    ``None`` when ``cfg.num_refine <= 3`` (no random kind). Drawn outside :func:`_half_sweep`
    (before it, in the order the refinements use them), so that the half-sweep draws nothing.
    """
    if cfg.num_refine <= 3:
        return None
    return _random_depth(rays.shape[:-1], lo, hi, gen, rays), _random_normals(rays, gen)


def _records(cands: torch.Tensor, nr: torch.Tensor, agg: torch.Tensor, costs: torch.Tensor) -> torch.Tensor:
    """``(B, N, P, 6 + V)`` state rows of ``cands`` ``(B, N, P, 4)`` (costs ``(B, V, N, P)``)."""
    return torch.cat([cands, nr[..., None], agg[..., None], costs.permute(0, 2, 3, 1)], -1)


def _half_sweep(
    state: torch.Tensor, nbr: torch.Tensor, px: MatchPixels, noise: torch.Tensor | None,
    rand: tuple[torch.Tensor, torch.Tensor] | None, src: MatchSources, cfg: PatchMatchConfig, lo, hi,
    batch: torch.Tensor | None, chunk: int, limits: torch.Tensor | None, out: torch.Tensor | None = None,
) -> torch.Tensor:  # fmt: skip
    """One red/black half-sweep: the new state rows ``(B, 1, P, 6 + V)`` of one colour's pixels.

    A pure function of its inputs (no random draw, no host read, no closure), so that it can be
    compiled as one unit (``PatchMatchConfig.compile``): propagation (the best-cost neighbour of
    each region, :func:`_propagate`), the candidates scored by :func:`match_costs`, ACMH's view
    weights and the aggregation, the random refinements of the winner (or, with ``joint_scoring``,
    of the likeliest winner, scored with the others), and the best of all.

    Args:
        state: ``(B, N + 1, 6 + V)`` depth, normal, ``n^T K^-1 p~``, aggregated and per-view
            costs of every scored pixel of the level and the sentinel (see :func:`_patchmatch_level`).
        nbr: ``(1 or B, P, 1 + R, L)`` this colour's rows of :func:`_neighbour_table`.
        px: this colour's :class:`MatchPixels`.
        noise: ``(B, P, 8)`` the refinements' noise (see :func:`_refinements`); ``None`` when
            ``cfg.num_refine`` is 0.
        rand: :func:`_random_planes`'s draws for these pixels.
        src: the level's :class:`MatchSources`.
        cfg: the settings.
        lo: the near bound (a number or a ``(B,)`` tensor).
        hi: the far bound.
        batch: ``arange(B)`` as ``(B, 1, 1, 1)`` when ``nbr`` is of each reference, else ``None``.
        chunk: :func:`match_costs`'s chunk.
        limits: :func:`_drop_limits`'s.
        out: where to write the rows (a view of the state: no copy), or ``None`` (a new tensor).

    Returns:
        The best-scoring row of each pixel, ``(B, 1, P, 6 + V)`` (``out`` when given).
    """
    kinds = REFINE_KINDS[: cfg.num_refine]
    cands, nb_cost = _propagate(state, state[..., 5], nbr, px.rays, lo, hi, batch)
    n_prop = cands.shape[1]  # current and propagated: what the view weights see
    if kinds and cfg.joint_scoring:
        assert noise is not None
        # Refine the likeliest winner: the plane of lowest cost where it was scored
        # (this pixel's, or a neighbour's), so that one scoring serves every candidate.
        likely = nb_cost.argmin(1)[:, None, :, None]  # (B, 1, P, 1)
        base = torch.gather(cands, 1, likely.expand(-1, -1, -1, 4))[:, 0]
        refined = _refinements(base, px.rays, noise, kinds, lo, hi, rand)
        cands = torch.cat([cands, refined], 1)  # (B, N, P, 4): current, propagated, refined
    # the pixel's own plane (re-intersected with its ray) scored with the others
    costs, nr = match_costs(src, px, cands, cfg.min_variance, chunk)  # (B, V, N, P)
    vw = _view_weights(costs[:, :, :n_prop], cfg, src.zero, limits) if cfg.view_selection == "acmh" else None
    agg = _aggregate(costs, vw, cfg)  # (B, N, P)
    if kinds and not cfg.joint_scoring:
        assert noise is not None
        # Refine the propagation's winner (ACMH), scored with the same view weights.
        win = agg.argmin(1)[:, None, :, None]
        base = torch.gather(cands, 1, win.expand(-1, -1, -1, 4))[:, 0]
        refined = _refinements(base, px.rays, noise, kinds, lo, hi, rand)
        c, r_nr = match_costs(src, px, refined, cfg.min_variance, chunk)
        record = torch.cat(  # current, propagated, refined
            [_records(cands, nr, agg, costs), _records(refined, r_nr, _aggregate(c, vw, cfg), c)], 1
        )
    else:
        record = _records(cands, nr, agg, costs)
    best = record[..., 5].argmin(1)[:, None, :, None]  # (B, 1, P, 1)
    return torch.gather(record, 1, best.expand(-1, -1, -1, record.shape[-1]), out=out)


@functools.cache
def _compiled_half_sweep() -> Callable[..., torch.Tensor]:
    """:func:`_half_sweep` through :func:`torch.compile` (``dynamic=True``), made once per process.

    ``PatchMatchConfig.compile``'s: one compiled function for every call, so that a call of the
    same batch, views and crop reuses the compiled code (``torch._dynamo`` caches by guards).
    """
    return torch.compile(_half_sweep, dynamic=True)


def _apply_init(depth, normal, init_depth, init_normal, rays, lo, hi):
    """Hypotheses ``(B, P)``, ``(B, P, 3)`` overridden by the known pixels of init maps."""
    bsz, p = depth.shape
    if init_depth is not None:
        d0 = init_depth.reshape(bsz, p)
        known = torch.isfinite(d0) & (d0 > 0)
        depth = torch.where(known, d0.clamp(_per_reference(lo, 1), _per_reference(hi, 1)), depth)
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
    lo, hi = _depth_bounds(depth_range, dims["B"], image.device, image.dtype)
    return dims, lo, hi


def _depth_bounds(
    depth_range, bsz: int, device: torch.device, dtype: torch.dtype
) -> tuple[float | torch.Tensor, float | torch.Tensor]:
    """``(near, far)``: two numbers, or two ``(B,)`` tensors when the references' ranges differ.

    ``depth_range`` is one ``(near, far)`` pair, or one pair per reference (a sequence of ``B``
    pairs or a ``(B, 2)`` tensor: one host read).
    """
    if isinstance(depth_range, torch.Tensor):
        depth_range = depth_range.tolist()
    pairs = list(depth_range)
    per_reference = bool(pairs) and all(isinstance(p, (tuple, list)) for p in pairs)
    if not per_reference:
        pairs = [tuple(pairs)]
    elif len(pairs) != bsz:
        raise ValueError(
            f"depth_range: expected one (near, far) pair or one per reference ({bsz}), got {len(pairs)} pairs"
        )
    bounds = []
    for pair in pairs:
        if len(pair) != 2:
            raise ValueError(f"depth_range: expected (near, far) pairs, got {tuple(pair)}")
        lo, hi = (float(x) for x in pair)
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo < hi):
            raise ValueError(f"depth_range: expected finite 0 < near < far, got {tuple(pair)}")
        bounds.append((lo, hi))
    if len(set(bounds)) == 1:  # one range for all: numbers (the path of a single range)
        return bounds[0]
    both = torch.tensor(bounds, device=device, dtype=dtype)
    return both[:, 0], both[:, 1]


def _check_images(
    image: torch.Tensor,
    src_images: torch.Tensor,
    K,
    src_K,
    world_to_cam,
    src_world_to_cam,
    cfg: PatchMatchConfig,
) -> None:
    """Float images at least ``window_radius + 1`` pixels per side; images, cameras finite (a value check)."""
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
    named = [
        ("K", K),
        ("src_K", src_K),
        ("world_to_cam", world_to_cam),
        ("src_world_to_cam", src_world_to_cam),
    ]
    _check_finite_together([*named, ("image", image), ("src_images", src_images)], world_to_cam)


def _check_finite_together(named: list[tuple[str, torch.Tensor]], world_to_cam: torch.Tensor) -> None:
    """:func:`vadgs.checks.check_finite` of every tensor, and ``world_to_cam``'s last rows, in one read.

    The sums of the tensors are finite when the tensors are (unless a sum overflows; then the
    tensors are checked one by one, which names the first non-finite one or passes). The last row
    of each ``world_to_cam`` is ``(0, 0, 0, 1)`` within 1e-5 (rigid transforms, as
    :func:`vadgs.geometry.invert_rigid` checks).
    """
    if not checks_enabled():
        return
    rows = world_to_cam[..., 3, :]
    off = (rows - torch.tensor([0.0, 0.0, 0.0, 1.0], device=rows.device, dtype=rows.dtype)).abs()
    sums = torch.stack([t.sum() for _, t in named] + [off.amax()])
    # |sum| < inf: finite (not NaN); the last row's largest offset <= 1e-5 (< the next number)
    tol = _adjacent(1e-5, rows.dtype, math.inf) or 1e-5
    limits = torch.tensor([math.inf] * len(named) + [tol], device=rows.device, dtype=rows.dtype)
    if bool((sums.abs() < limits).all()):
        return
    for name, t in named:
        check_finite(t, name)
    bad = (off > 1e-5).any(-1)
    if bool(bad.any()):
        got = rows[int(bad.nonzero()[0, 0])].tolist()
        raise ValueError(f"world_to_cam: expected a transform with last row (0, 0, 0, 1), got {got}")


@torch.no_grad()
def patchmatch(
    image: torch.Tensor,
    src_images: torch.Tensor,
    K: torch.Tensor,
    src_K: torch.Tensor,
    world_to_cam: torch.Tensor,
    src_world_to_cam: torch.Tensor,
    depth_range: tuple[float, float] | Sequence[tuple[float, float]] | torch.Tensor,
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
        depth_range: ``(near, far)`` bounds of random depths (sampled uniformly in inverse depth)
            and of every hypothesis, or one such pair per reference (a sequence of ``B`` pairs or a
            ``(B, 2)`` tensor), so that references of different depth ranges share one call.
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
    _check_images(image, src_images, K, src_K, world_to_cam, src_world_to_cam, cfg)
    bsz, nv = src_images.shape[:2]
    # [R^T | -R^T t] (vadgs.geometry.invert_rigid, whose checks _check_images made)
    rot_t = world_to_cam[:, :3, :3].transpose(-1, -2)
    last = torch.tensor([[[0.0, 0.0, 0.0, 1.0]]], device=image.device, dtype=world_to_cam.dtype)
    ref_to_world = torch.cat(
        [torch.cat([rot_t, -rot_t @ world_to_cam[:, :3, 3:]], -1), last.expand(bsz, -1, -1)], -2
    )
    src_from_ref = torch.bmm(src_world_to_cam.reshape(bsz, nv * 4, 4), ref_to_world).view(bsz, nv, 4, 4)
    usable = src_from_ref[..., :3, 3].norm(dim=-1) > 1e-6 * _per_reference(lo, 1)  # (B, V): baseline
    if not bool(usable.any(-1).all()):
        bad = [int(i) for i in torch.nonzero(~usable.any(-1)).flatten()]
        raise ValueError(
            f"src_world_to_cam: every source of reference(s) {bad} has the reference's camera centre "
            "(zero baseline): depth is unobservable"
        )
    # Grey levels, once for every level (flat for a degenerate source: the worst cost).
    gray, src_gray = _to_gray(image), _to_gray(src_images) * usable[..., None, None, None]
    # The window, the same at every level: offsets (o_x, o_y, 1), the bilateral weights' spatial
    # term and the samples nearest the centre.
    offsets = patch_offsets(cfg.window_radius, cfg.window_step, device=image.device, dtype=image.dtype)
    sigma_s = cfg.sigma_spatial if cfg.sigma_spatial is not None else float(cfg.window_radius)
    window = (
        F.pad(offsets, (0, 1), value=1.0),
        spatial_log_weights(offsets, sigma_s),
        patch_center_indices(cfg.window_radius, cfg.window_step),
    )
    level = _pyramid(
        gray, src_gray, K, src_K, (src_from_ref, window), (lo, hi), cfg, init_depth, init_normal,
        mask, src_masks, cfg.pyramid_levels,
    )  # fmt: skip
    return _result(level, cfg, bsz, nv, *image.shape[-2:])


class _Level(NamedTuple):
    """What one pyramid level hands on: full-image maps, flat (``HW`` last but for the planes)."""

    planes: torch.Tensor  # (B, HW, 4) raw depth and normal
    agg: torch.Tensor | None  # (B, HW) aggregated cost (finest level only)
    view_cost: torch.Tensor | None  # (B, V, HW) (finest level only)
    textured: torch.Tensor | None  # (B, HW) scored, in the region, textured (finest level only)


def _downsample(x: torch.Tensor, size: tuple[int, int], mode: str) -> torch.Tensor:
    lead = x.shape[:-3]
    flat = x.reshape(-1, *x.shape[-3:])
    if mode == "area":
        out = F.interpolate(flat, size=size, mode="bilinear", antialias=True, align_corners=False)
    else:
        out = F.interpolate(flat.float(), size=size, mode="nearest").to(x.dtype)
    return out.reshape(*lead, *out.shape[-3:])


def _scaled(K: torch.Tensor, sx: float, sy: float) -> torch.Tensor:
    """:func:`vadgs.geometry.scale_intrinsics` as one product (``K``'s last row is ``(0, 0, 1)``)."""
    m = torch.tensor(
        [[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1]], dtype=K.dtype, device=K.device
    )
    return m @ K


def _pyramid(
    image, src_images, K, src_K, shared, depth_range, cfg, init_depth, init_normal, mask, src_masks,
    levels: int,
) -> _Level:  # fmt: skip
    """Coarse-to-fine: solve at half resolution, upsample the hypotheses, refine at the next, up to this one.

    Every level's scored pixels are set up first, so that the reference windows' weights and
    statistics of all levels come out of one pass.
    """
    # The levels, finest first: images, cameras, init maps, regions.
    pyr = [(image, src_images, K, src_K, init_depth, init_normal, mask, src_masks)]
    while (
        len(pyr) < levels and cfg.iterations > 0 and min(*pyr[-1][0].shape[-2:], *pyr[-1][1].shape[-2:]) >= 8
    ):
        img, src, k, sk, d0, n0, m, sm = pyr[-1]
        h, w = img.shape[-2:]
        hs, ws = src.shape[-2:]
        hc, wc, hsc, wsc = (h + 1) // 2, (w + 1) // 2, (hs + 1) // 2, (ws + 1) // 2
        pyr.append(
            (
                _downsample(img, (hc, wc), "area"),
                _downsample(src, (hsc, wsc), "area"),
                _scaled(k, wc / w, hc / h),
                _scaled(sk, wsc / ws, hsc / hs),
                None if d0 is None else _downsample(d0, (hc, wc), "nearest"),
                None if n0 is None else _downsample(n0, (hc, wc), "nearest"),
                None if m is None else _downsample(m, (hc, wc), "nearest"),
                None if sm is None else _downsample(sm, (hsc, wsc), "nearest"),
            )
        )
    pixels = [_level_pixels(lv[0], lv[2], lv[6], i == 0) for i, lv in enumerate(pyr)]
    terms = _level_terms(pixels, cfg, shared[1])
    # The coarsest level from random (or given) hypotheses, then each finer one from the upsampled
    # planes of the coarser (with the caller's init maps at that level as an alternative).
    fine = cfg if cfg.fine_propagation is None else replace(cfg, propagation=cfg.fine_propagation)
    level = None
    for i in range(len(pyr) - 1, -1, -1):
        img, src, k, sk, d0, n0, m, sm = pyr[i]
        if level is None:
            level = _patchmatch_level(
                img, src, k, sk, shared, depth_range, cfg, d0, n0, sm, 0, cfg.iterations, None, i == 0,
                pixels[i], terms[i],
            )  # fmt: skip
            continue
        bsz, (h, w), (hc, wc) = img.shape[0], img.shape[-2:], pyr[i + 1][0].shape[-2:]
        # (B, 4, H, W) depth and normal in one, channels last (the finer level reads it as (B, HW, 4))
        up = _downsample(level.planes.view(bsz, hc, wc, 4).permute(0, 3, 1, 2), (h, w), "nearest")
        done = cfg.iterations + (len(pyr) - 2 - i) * cfg.fine_iterations
        level = _patchmatch_level(
            img, src, k, sk, shared, depth_range, fine, up, None, sm, done, cfg.fine_iterations, (d0, n0),
            i == 0, pixels[i], terms[i],
        )  # fmt: skip
    assert level is not None
    return level


class _Pixels(NamedTuple):
    """The scored pixels of one level (see :func:`_level_pixels`)."""

    Kinv: torch.Tensor  # (B, 3, 3)
    rays_all: torch.Tensor  # (B, HW, 3) K^-1 p~ of every pixel
    idx: torch.Tensor  # (B, P) the scored pixels, the first colour's then the second's
    slot: torch.Tensor  # (B, P) where their results go (HW for the padding)
    lut: torch.Tensor  # (1 or B, HW + 1) the scored pixel of each pixel (P: none, the sentinel)
    pix: torch.Tensor  # (B or 1, P, 3) p~
    keep: torch.Tensor | None  # (B, P) real and in the region (None: no region)
    region: torch.Tensor | None  # (B, HW) bool
    first: int  # where the second colour starts
    gray: torch.Tensor  # (B, 1, H, W) the reference images
    mask: torch.Tensor | None  # (B, 1, H, W) their regions


def _level_pixels(image: torch.Tensor, K: torch.Tensor, mask: torch.Tensor | None, final: bool) -> _Pixels:
    """The scored pixels of each reference and their windows at one level (``image`` grey).

    Those of its region (all without one), the first checkerboard colour then the second. With a
    small object in a large crop the cost follows the object, not the crop; pixels outside are
    never propagated from (as when they were scored with the worst cost). References of
    different regions are padded to the most pixels of each colour with pixels that score
    nothing, are never propagated from and whose results are dropped (``slot`` ``h * w``).
    """
    bsz = image.shape[0]
    h, w = image.shape[-2:]
    dev, dt = image.device, image.dtype
    # (inv_ex skips the check of a coarse level: K is singular there iff it is at the finest, checked)
    Kinv = torch.linalg.inv(K) if final else torch.linalg.inv_ex(K).inverse
    region = None if mask is None else mask.bool().reshape(bsz, h * w)
    exact = h * w <= 2 / torch.finfo(dt).eps  # pixel indices are whole numbers of dt (2^24 for float32)
    flat = torch.arange(h * w, device=dev, dtype=dt if exact else torch.long)
    xs, ys = flat % w, flat.div(w, rounding_mode="floor")
    odd = (xs + ys) % 2  # the checkerboard colour
    pix_all = torch.stack([xs, ys, torch.ones_like(xs)], dim=-1).to(dt)  # (HW, 3)
    rays_all = pix_all @ Kinv.transpose(-1, -2)  # (B, HW, 3)
    if region is None:  # the same pixels for all references
        shared = torch.argsort(odd, stable=True)  # the first colour's pixels, then the second's, in order
        n_act, first = h * w, (h * w + 1) // 2
        lut = F.pad(torch.argsort(shared), (0, 1), value=n_act)[None]  # the inverse permutation, the sentinel
        idx = slot = shared.expand(bsz, -1)
        pix = pix_all[shared]
        keep = None
    else:
        idx, real, first = _scored_pixels(region, odd == 0)  # one host read
        n_act = idx.shape[1]
        slot = torch.where(real, idx, h * w)  # where a pixel's results go (padding: a spare slot)
        lut = torch.full((bsz, h * w + 1), n_act, dtype=torch.long, device=dev)
        lut = lut.scatter_(1, slot, torch.arange(n_act, device=dev).expand_as(slot))
        lut[:, h * w] = n_act  # the sentinel
        pix = pix_all[idx]
        keep = real & _take(region, idx)
    return _Pixels(Kinv, rays_all, idx, slot, lut, pix, keep, region, first, image, mask)


def _level_terms(
    pixels: list[_Pixels], cfg: PatchMatchConfig, window
) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Each level's reference terms ``(B, 2, S, P)`` and textured pixels ``(B, P)``, in one pass.

    The windows of the scored pixels of every level side by side, their bilateral weights (zero
    outside the region) and :func:`vadgs.mvs.cost.reference_terms`; the pixels are independent,
    so that each level's are what a pass of its own gives, bit for bit.
    """
    off3, spatial, centre = window
    radius, wstep = cfg.window_radius, cfg.window_step

    def joined(parts: list[torch.Tensor], dim: int) -> torch.Tensor:
        return torch.cat(parts, dim) if len(parts) > 1 else parts[0]

    patches = joined([_take(window_patches(px.gray, radius, wstep), px.idx, 2) for px in pixels], 2)
    weights = bilateral_weights(patches, off3[:, :2], 0.0, cfg.sigma_color, centre, dim=1, spatial=spatial)
    keep = None
    masks = [px.mask for px in pixels if px.mask is not None]
    if masks:  # regions at every level
        dt = patches.dtype
        windows = [window_patches(m.bool().to(dt), radius, wstep) for m in masks]
        inside = joined([_take(x, px.idx, 2) for x, px in zip(windows, pixels)], 2) > 0.5
        weights = weights * inside
        weights = weights / weights.sum(1, keepdim=True).clamp_min(1e-12)
        keep = joined([px.keep for px in pixels if px.keep is not None], 1)
    ref, textured = reference_terms(patches, weights, cfg.min_variance, keep)
    out, p0 = [], 0
    for px in pixels:
        p = px.idx.shape[1]
        out.append((ref[..., p0 : p0 + p], textured[:, p0 : p0 + p]))
        p0 += p
    return out


def _patchmatch_level(
    image, src_images, K, src_K, shared, depth_range, cfg, init_depth, init_normal, src_masks,
    start_iteration: int, iterations: int, alt_init: tuple[torch.Tensor | None, torch.Tensor | None] | None,
    final: bool, scored: _Pixels, terms: tuple[torch.Tensor, torch.Tensor],
) -> _Level:  # fmt: skip
    """PatchMatch at one resolution (inputs already checked).

    Every half-sweep is a fixed handful of batched tensor operations whatever the batch, the views
    and the image size (``tests/mvs/test_patchmatch_launches.py`` counts them), and reads no tensor
    value back to the host: the neighbours' planes of all regions come out of one gather (with the
    pixel's own, whose costs are kept) and are scored in one :func:`match_costs` call, the winner is picked
    by one ``argmin``, its random refinements are scored in a second call (or, with
    ``joint_scoring``, with the propagated planes in the first, around the likeliest winner), and
    the best of all is kept by one ``gather``. The initial hypotheses are scored first, once.

    ``image`` ``(B, 1, H, W)`` and ``src_images`` ``(B, V, 1, Hs, Ws)`` are grey (zero for a
    degenerate source). ``alt_init`` is given at a finer pyramid level: ``init_depth`` is then the
    upsampled coarse planes ``(B, 4, H, W)`` (depth and normal, complete, channels last), and
    ``alt_init`` the caller's full-resolution init maps (or ``None``), scored against them.
    ``scored`` and ``terms``: the level's :func:`_level_pixels` and :func:`_level_terms`.
    """
    src_from_ref, (off3, _, _) = shared
    lo, hi = depth_range
    bsz, nv = src_images.shape[:2]
    h, w = image.shape[-2:]
    hs, ws = src_images.shape[-2:]
    dev, dt = image.device, image.dtype
    gen = None
    if cfg.seed is not None:
        gen = torch.Generator(device=dev)
        gen.manual_seed(cfg.seed)

    # Sources: grey images (flat for a degenerate source: the worst cost), homography parts.
    norm = torch.tensor(
        [[2 / max(ws - 1, 1), 0, -1], [0, 2 / max(hs - 1, 1), -1], [0, 0, 1]], device=dev, dtype=dt
    )
    Kinv, rays_all, idx, slot, lut, pix, _, region, first = scored[:9]
    NK = norm @ src_K  # (B, V, 3, 3)
    A = torch.bmm((NK @ src_from_ref[..., :3, :3]).view(bsz, nv * 3, 3), Kinv).view(bsz, nv, 3, 3)
    bvec = (NK @ src_from_ref[..., :3, 3:]).squeeze(-1)
    src_gray = src_images.reshape(bsz * nv, 1, hs, ws)  # grey, zero for a degenerate source
    smasks = None if src_masks is None else src_masks.reshape(bsz * nv, 1, hs, ws).to(dt)
    consts = torch.tensor([1.0, 0.0, MAX_COST, math.nan], device=dev, dtype=dt).unbind()
    src = MatchSources(src_gray, smasks, bvec, off3.expand(bsz * nv, -1, -1), *consts)
    chunk = _chunk_size(cfg.chunk_size, dev, nv * bsz)  # pixel-views of all references
    limits = _drop_limits(cfg, dev, dt)

    n_act = idx.shape[1]
    rays = _take(rays_all, idx)
    ref, textured = terms  # (B, 2, S, P), (B, P)
    cols, rows = map_tables(A, Kinv, pix, rays)
    pixels = MatchPixels(idx, rays, cols, rows, ref)
    na = lut.shape[0]  # 1: the same pixels for all
    nbr = _neighbour_table(idx[:na], h, w, lut, n_act, cfg.propagation)  # (1 or B, P, 1 + R, L)
    batch = None if region is None else torch.arange(bsz, device=dev).view(bsz, 1, 1, 1)
    colours = [sl for sl in (slice(0, first), slice(first, n_act)) if sl.stop > sl.start]
    parts = [pixels.part(sl)._replace(rays=rays[:, sl].clone()) for sl in colours]  # contiguous

    # Initial hypotheses: random, overridden where an init is given; with an alternative
    # (coarse-to-fine: the caller's full-resolution init), the better-scoring of the two.
    if alt_init is not None:  # a finer pyramid level: the upsampled coarse maps are complete
        planes = init_depth.permute(0, 2, 3, 1).reshape(bsz, h * w, 4)  # a view (channels last)
        depth, normal = planes[..., 0], planes[..., 1:]
    else:
        depth = _random_depth((bsz, h * w), lo, hi, gen, rays_all)
        normal = _random_normals(rays_all, gen)
        depth, normal = _apply_init(depth, normal, init_depth, init_normal, rays_all, lo, hi)
        planes = torch.cat([depth[..., None], normal], -1)  # (B, HW, 4)
    if n_act:
        init = [_take(planes, idx)]
        if alt_init is not None and (alt_init[0] is not None or alt_init[1] is not None):
            alt_d, alt_n = _apply_init(depth, normal, *alt_init, rays_all, lo, hi)
            init.append(_take(torch.cat([alt_d[..., None], alt_n], -1), idx))
        kinds = REFINE_KINDS[: cfg.num_refine]
        its = range(start_iteration, start_iteration + iterations)
        halves = [
            [cfg.depth_perturbation * 0.5**it] * 2 + [cfg.normal_perturbation * 0.5**it] * 6 for it in its
        ]
        # (2, iterations, 8): noise = -half + u * 2 half (the signs and doublings exact in any dtype)
        scale = torch.tensor(
            [[[-x for x in h] for h in halves], [[2 * x for x in h] for h in halves]], device=dev, dtype=dt
        )

        # State of the scored pixels and the sentinel (infinite cost, never chosen when another
        # neighbour exists): depth, normal, n^T K^-1 p~, aggregated cost, per-view costs; the
        # initial hypotheses' (the better-scoring one where there are two).
        first_hyp = torch.stack(init, 1) if len(init) > 1 else init[0][:, None]  # (B, K, P, 4)
        costs, nr = match_costs(src, pixels, first_hyp, cfg.min_variance, chunk)
        agg = _aggregate(costs, None, cfg)
        record = _records(first_hyp, nr, agg, costs)
        if len(init) > 1:
            best = agg.argmin(1)[:, None, :, None]
            record = torch.gather(record, 1, best.expand(-1, -1, -1, record.shape[-1]))
        sentinel = torch.tensor([1.0, 0.0, 0.0, -1.0, -1.0, math.inf] + [MAX_COST] * nv, device=dev, dtype=dt)
        state = torch.cat([record[:, 0], sentinel.expand(bsz, 1, -1)], 1)
        # The random numbers of the refinements of both colours: all the level's at once unless
        # random hypotheses are drawn between them (the same numbers either way on the CPU).
        upfront = bool(kinds) and iterations > 0 and not any("r" in kind for kind in kinds)
        if upfront:
            u = torch.rand((iterations, bsz, n_act, 8), generator=gen, device=dev, dtype=dt)
            noises = torch.addcmul(scale[0, :, None, None], u, scale[1, :, None, None])
            noises[..., :2].exp_()  # the relative depth factors (see _refinements)
        for i in range(iterations):
            noise = None
            if kinds:
                if upfront:
                    noise = noises[i]
                else:
                    u = torch.rand((bsz, n_act, 8), generator=gen, device=dev, dtype=dt)
                    noise = torch.addcmul(scale[0, i], u, scale[1, i])
                    noise[..., :2].exp_()
            for sl, px in zip(colours, parts):
                # the random draws stay outside the half-sweep (in the order its refinements use them)
                rand = _random_planes(px.rays, cfg, lo, hi, gen) if kinds else None
                nz = None if noise is None else noise[:, sl]
                args = (state, nbr[:, sl], px, nz, rand, src, cfg, lo, hi, batch, chunk, limits)
                if cfg.compile:  # depth bounds as tensors: a float would be a constant of the graph
                    bounds = [torch.as_tensor(x, device=dev, dtype=dt) for x in (lo, hi)]
                    args = (*args[:7], *bounds, *args[9:])
                    state[:, sl] = _compiled_half_sweep()(*args)[:, 0]
                else:
                    _half_sweep(*args, out=state[:, None, sl])  # written into the state: no copy
        padded = region is not None
        planes = _put(planes, slot, state[:, :n_act, :4], padded)
    if not final:
        return _Level(planes, None, None, None)
    if region is None:  # every pixel scored: its row of the state, at the inverse permutation
        inv = lut[0, : h * w]
        rows = state[:, inv, 5:]  # (B, HW, 1 + V): aggregated and per-view costs
        return _Level(planes, rows[..., 0], rows[..., 1:].transpose(1, 2), textured[:, inv])
    # with a spare slot for the padding's results (see _put)
    agg_full = torch.full((bsz, h * w + 1), MAX_COST, device=dev, dtype=dt)
    view_cost = torch.full((bsz, h * w + 1, nv), MAX_COST, device=dev, dtype=dt)
    valid = torch.zeros(bsz, h * w + 1, dtype=torch.bool, device=dev)
    if n_act:
        agg_full = _put(agg_full, slot, state[:, :n_act, 5], False)  # the spare slot is theirs
        view_cost = _put(view_cost, slot, state[:, :n_act, 6:], False)
        valid = _put(valid, slot, textured, False)
    agg_full, view_cost, valid = (
        agg_full[:, : h * w],
        view_cost[:, : h * w].transpose(1, 2),
        valid[:, : h * w],
    )
    return _Level(planes, agg_full, view_cost, valid)


def _result(level: _Level, cfg: PatchMatchConfig, bsz: int, nv: int, h: int, w: int) -> PatchMatchResult:
    assert level.agg is not None and level.view_cost is not None and level.textured is not None
    valid = level.textured & (level.agg <= cfg.max_cost)  # depths are in [near, far] by construction
    raw = level.planes[..., 0].reshape(bsz, 1, h, w)
    valid = valid.reshape(bsz, 1, h, w)
    normal_map = level.planes[..., 1:].transpose(1, 2).reshape(bsz, 3, h, w)
    return PatchMatchResult(
        depth=raw * valid,
        normal=normal_map * valid,
        cost=level.agg.reshape(bsz, 1, h, w).clamp(0, MAX_COST),
        view_costs=level.view_cost.reshape(bsz, nv, h, w).clamp(0, MAX_COST),
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
        depth_range: tuple[float, float] | Sequence[tuple[float, float]] | torch.Tensor,
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
