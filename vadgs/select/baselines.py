"""Baseline view selections for ablations and comparison, behind the same interface.

- :func:`consecutive_views`: the temporally nearest frames of the reference's own camera
  (GaussianPro; the paper's "w/o view selection" ablation).
- :func:`mvsnet_scores`: MVSNet's pair score (Yao et al. 2018, sec. 4.1),
  ``Σ_p G(θ_ij(p))`` over the shared points with the piecewise Gaussian
  ``G(θ) = exp(-(θ - θ0)² / (2σ1²))`` for ``θ ≤ θ0`` and ``exp(-(θ - θ0)² / (2σ2²))`` above,
  ``θ0 = 5°, σ1 = 1, σ2 = 10``; the top-k views are kept.
- :func:`colmap_scores`: COLMAP's source-image rule for patch-match stereo
  (``Model::GetMaxOverlappingImages``): the views sharing the most points with the reference,
  among those whose 75th-percentile triangulation angle over the shared points is at least
  ``min_triangulation_angle`` (1° by default).

``θ(p)`` is the angle at voxel centre ``p`` between the rays to the two camera centres. All
scores are vectorised over the non-zeros of the view × voxel incidence; no loop over views.
:func:`top_k_views` turns any score vector into a selection.
"""

from __future__ import annotations

import math

import torch

from vadgs.checks import check_finite, check_shape
from vadgs.select.covisibility import Covisibility
from vadgs.select.score import ray_angles, triangulation_angles

__all__ = ["colmap_scores", "consecutive_views", "mvsnet_scores", "top_k_views"]


def _check_ref(ref: int, num_views: int) -> int:
    if not 0 <= int(ref) < num_views:
        raise ValueError(f"ref: expected a view index in [0, {num_views}), got {ref}")
    return int(ref)


def mvsnet_scores(
    covis: Covisibility, ref: int, theta0: float = 5.0, sigma1: float = 1.0, sigma2: float = 10.0
) -> torch.Tensor:
    """MVSNet's view-selection score of every view as a source for ``ref``.

    Not differentiable (runs under ``torch.no_grad()``).

    Args:
        covis: the views, voxels and visibility.
        ref: the reference view.
        theta0: ``θ0`` in degrees.
        sigma1: ``σ1`` in degrees, below ``θ0``.
        sigma2: ``σ2`` in degrees, above ``θ0``.

    Returns:
        ``(V,)`` scores, ``0`` for ``ref`` itself and views sharing no voxel with it.

    Example:
        >>> w2c = torch.eye(4).repeat(2, 1, 1); w2c[1, 0, 3] = -math.tan(math.radians(5.0))
        >>> covis = Covisibility.from_visible(
        ...     [torch.tensor([0]), torch.tensor([0])], torch.tensor([[0.0, 0, 1]]), w2c)
        >>> mvsnet_scores(covis, 0)  # one voxel seen under exactly θ0
        tensor([0., 1.])
    """
    ref = _check_ref(ref, covis.num_views)
    with torch.no_grad():
        view, _, theta = ray_angles(covis, ref)
        sigma = torch.where(theta <= theta0, sigma1, sigma2)
        g = torch.exp(-((theta - theta0) ** 2) / (2 * sigma**2))
        out = torch.zeros(covis.num_views, dtype=covis.voxel_centers.dtype, device=g.device)
        return out.index_add_(0, view, g.to(out.dtype))


def colmap_scores(
    covis: Covisibility, ref: int, min_triangulation_angle: float = 1.0, percentile: float = 75.0
) -> torch.Tensor:
    """COLMAP's source-view score: shared voxel count, zeroed where triangulation is too weak.

    A view keeps its shared count with ``ref`` if the ``percentile``-th percentile (nearest rank,
    rounded down) of the triangulation angles over the shared voxels is at least
    ``min_triangulation_angle`` degrees, as COLMAP's ``GetMaxOverlappingImages``.
    Not differentiable.

    Args:
        covis: the views, voxels and visibility.
        ref: the reference view.
        min_triangulation_angle: degrees.
        percentile: in ``[0, 100]``.

    Returns:
        ``(V,)`` shared voxel counts (float), ``0`` where rejected and for ``ref``.

    Example:
        >>> w2c = torch.eye(4).repeat(3, 1, 1); w2c[1, 0, 3] = -0.5; w2c[2, 0, 3] = -0.001
        >>> covis = Covisibility.from_visible(
        ...     [torch.tensor([0, 1])] * 3, torch.tensor([[0.0, 0, 4], [1.0, 0, 4]]), w2c)
        >>> colmap_scores(covis, 0)  # view 2 has a baseline of 1 mm: rejected
        tensor([0., 2., 0.])
    """
    ref = _check_ref(ref, covis.num_views)
    with torch.no_grad():
        view, _, _ = ray_angles(covis, ref)
        dtype = covis.voxel_centers.dtype
        counts = torch.zeros(covis.num_views, dtype=dtype, device=view.device).index_add_(
            0, view, torch.ones_like(view, dtype=dtype)
        )
        keep = triangulation_angles(covis, ref, percentile) >= min_triangulation_angle
        return torch.where(keep & (counts > 0), counts, torch.zeros((), dtype=dtype, device=view.device))


def consecutive_views(
    ref: int,
    camera_ids: torch.Tensor,
    frame_ids: torch.Tensor,
    k: int = 4,
    allowed: torch.Tensor | None = None,
) -> torch.Tensor:
    """The ``k`` views of the reference's camera nearest in time (earlier first on ties).

    Args:
        ref: the reference view.
        camera_ids: ``(V,)`` the rig camera of each view.
        frame_ids: ``(V,)`` the frame index of each view.
        k: how many.
        allowed: optional ``(V,)`` bool, the views that may be chosen (e.g. training views).

    Returns:
        ``(s,)`` int64 view ids, ``s <= k``, nearest first.

    Example:
        >>> cams = torch.tensor([0, 0, 0, 0, 1]); frames = torch.tensor([0, 1, 2, 3, 1])
        >>> consecutive_views(1, cams, frames, k=3)
        tensor([0, 2, 3])
    """
    dims = check_shape(camera_ids, "camera_ids", ("V",))
    check_shape(frame_ids, "frame_ids", ("V",), dims)
    ref = _check_ref(ref, dims["V"])
    ok = (camera_ids == camera_ids[ref]) & (torch.arange(dims["V"], device=camera_ids.device) != ref)
    if allowed is not None:
        check_shape(allowed, "allowed", ("V",), dims)
        ok &= allowed.to(ok.device)
    cand = torch.nonzero(ok).squeeze(1)
    dt = frame_ids[cand] - frame_ids[ref]
    key = dt.abs() * 2 + (dt > 0).long()  # nearest first, earlier before later
    return cand[torch.argsort(key, stable=True)[:k]]


def top_k_views(
    scores: torch.Tensor, ref: int, k: int = 4, allowed: torch.Tensor | None = None
) -> torch.Tensor:
    """The ``k`` views with the highest positive scores, excluding ``ref``, best first.

    Example:
        >>> top_k_views(torch.tensor([9.0, 0.0, 3.0, 5.0]), ref=0, k=3)
        tensor([3, 2])
    """
    dims = check_shape(scores, "scores", ("V",))
    ref = _check_ref(ref, dims["V"])
    if int(k) < 0:
        raise ValueError(f"k: expected a number of views >= 0, got {k}")
    check_finite(scores, "scores")
    ok = scores > 0
    ok[ref] = False
    if allowed is not None:
        check_shape(allowed, "allowed", ("V",), dims)
        ok &= allowed.to(ok.device)
    masked = torch.where(ok, scores, torch.full_like(scores, -math.inf))
    k = min(int(k), int(ok.sum()))
    return torch.topk(masked, k).indices if k > 0 else torch.zeros(0, dtype=torch.long, device=scores.device)
