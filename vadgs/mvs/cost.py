r"""Bilateral-weighted normalised cross-correlation, the photometric cost of PatchMatch MVS.

A reference patch :math:`r_s` and a source patch :math:`s_s` (the reference window warped into
a source view through a plane homography) are compared by their weighted correlation

.. math::

    \mathrm{NCC} = \frac{\sum_s w_s (r_s - \bar r)(s_s - \bar s)}
                        {\sqrt{\sum_s w_s (r_s - \bar r)^2 \; \sum_s w_s (s_s - \bar s)^2}},
    \qquad \bar r = \sum_s w_s r_s, \quad \sum_s w_s = 1,

with COLMAP's bilateral weights, computed on the reference patch only,

.. math::

    w_s \propto \exp\left(-\frac{\lVert \mathbf{o}_s \rVert^2}{2\sigma_\mathrm{spatial}^2}
                          -\frac{(r_s - r_0)^2}{2\sigma_\mathrm{colour}^2}\right),

where :math:`\mathbf{o}_s` is the sample's offset from the centre and :math:`r_0` the centre
intensity. The cost is :math:`1 - \mathrm{NCC}` in :math:`[0, 2]`; a patch whose weighted variance
is below ``min_variance`` (textureless, sky, saturated) gets the worst cost 2.

Windows are sampled every ``step`` pixels (ACMP samples a radius-5 window every other pixel:
36 samples instead of 121), offsets are ``(x, y)`` as everywhere in vadgs.

The reference-side quantities (weights, mean, standard deviation) do not depend on the plane
hypothesis, so PatchMatch computes them once with :func:`reference_patch_stats`;
:func:`bilateral_ncc` is the plain, self-contained form of the same cost.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F

from vadgs.checks import check_shape

__all__ = [
    "MAX_COST",
    "ReferencePatchStats",
    "bilateral_ncc",
    "bilateral_weights",
    "ncc_cost_from_stats",
    "patch_center_indices",
    "patch_offsets",
    "reference_patch_stats",
    "reference_patches",
    "reference_terms",
    "spatial_log_weights",
    "window_patches",
]

#: The worst photometric cost (``1 - NCC`` for perfectly anti-correlated patches).
MAX_COST = 2.0


def patch_offsets(
    radius: int, step: int = 1, device: torch.device | None = None, dtype: torch.dtype | None = None
) -> torch.Tensor:
    """Sample offsets ``(x, y)`` of a square window, row by row.

    Offsets run from ``-radius`` to ``radius``; with ``step > 1`` they are symmetric about the
    centre (``radius=5, step=2`` gives ``-5, -3, -1, 1, 3, 5`` per axis, as ACMP).

    Args:
        radius: half-size of the window in pixels (>= 0).
        step: sampling step in pixels (>= 1).
        device: device of the result.
        dtype: dtype of the result (default float32).

    Returns:
        ``(S, 2)`` offsets.

    Example:
        >>> patch_offsets(1).shape, patch_offsets(5, 2)[:3, 0]
        (torch.Size([9, 2]), tensor([-5., -3., -1.]))
    """
    if radius < 0 or step < 1:
        raise ValueError(f"patch_offsets: expected radius >= 0 and step >= 1, got {radius=}, {step=}")
    n = radius * 2 // step + 1
    span = (n - 1) * step
    axis = [k * step - span / 2 for k in range(n)]  # whole or half numbers: exact in any float dtype
    return torch.tensor([[x, y] for y in axis for x in axis], device=device, dtype=dtype or torch.float32)


def patch_center_indices(radius: int, step: int = 1) -> list[int]:
    """Indices of the samples of :func:`patch_offsets` nearest to the window centre (no tensor read).

    One sample (the centre) when the window has an odd number of samples per axis, else the four
    around it, in increasing order: what :func:`bilateral_weights` finds from the offsets.

    Example:
        >>> patch_center_indices(1), patch_center_indices(5, 2)
        ([4], [14, 15, 20, 21])
    """
    if radius < 0 or step < 1:
        raise ValueError(f"patch_center_indices: expected radius >= 0 and step >= 1, got {radius=}, {step=}")
    n = radius * 2 // step + 1
    axis = [(n - 1) // 2] if n % 2 else [n // 2 - 1, n // 2]
    return [iy * n + ix for iy in axis for ix in axis]


def window_patches(gray: torch.Tensor, radius: int, step: int = 1) -> torch.Tensor:
    """:func:`reference_patches` of the window :func:`patch_offsets` ``(radius, step)``, as one unfold.

    The same values in the same order; two kernels (a replicate pad and an unfold) instead of one
    slice per sample. A window whose offsets are not whole pixels (an odd span: ``radius=4,
    step=3``) is gathered by :func:`reference_patches`.

    Args:
        gray: ``(B, 1, H, W)`` images.
        radius: half-size of the window in pixels (>= 0).
        step: sampling step in pixels (>= 1).

    Returns:
        ``(B, S, H * W)`` patch samples, sample-major.

    Example:
        >>> img = torch.rand(2, 1, 7, 9)
        >>> bool((window_patches(img, 3, 2) == reference_patches(img, patch_offsets(3, 2))).all())
        True
    """
    dims = check_shape(gray, "gray", ("B", 1, "H", "W"))
    if radius < 0 or step < 1:
        raise ValueError(f"window_patches: expected radius >= 0 and step >= 1, got {radius=}, {step=}")
    n = radius * 2 // step + 1
    span = (n - 1) * step
    if span % 2:
        return reference_patches(gray, patch_offsets(radius, step, gray.device, gray.dtype))
    pad = span // 2
    padded = F.pad(gray, (pad, pad, pad, pad), mode="replicate")
    return F.unfold(padded, n, dilation=step).view(dims["B"], n * n, dims["H"] * dims["W"])


def spatial_log_weights(offsets: torch.Tensor, sigma_spatial: float) -> torch.Tensor:
    """The spatial term of :func:`bilateral_weights`' log-weights, ``-|o|^2 / (2 sigma_spatial^2)``.

    Args:
        offsets: ``(S, 2)`` sample offsets.
        sigma_spatial: spatial standard deviation in pixels.

    Returns:
        ``(S,)`` log-weights.

    Example:
        >>> spatial_log_weights(torch.tensor([[0.0, 0.0], [1.0, 1.0]]), 1.0)
        tensor([-0., -1.])
    """
    check_shape(offsets, "offsets", ("S", 2))
    return -(offsets**2).sum(-1) / (2 * sigma_spatial**2)


def reference_patches(gray: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """Gather the window of every pixel of single-channel images (borders replicated).

    Args:
        gray: ``(B, 1, H, W)`` images.
        offsets: ``(S, 2)`` offsets ``(x, y)``; they are rounded to whole pixels.

    Returns:
        ``(B, S, H * W)`` patch samples, sample-major (pixels in row-major order on the last axis).

    Example:
        >>> img = torch.arange(9.0).reshape(1, 1, 3, 3)
        >>> reference_patches(img, torch.tensor([[0.0, 0.0], [1.0, 0.0]]))[0, :, 4]
        tensor([4., 5.])
    """
    dims = check_shape(gray, "gray", ("B", 1, "H", "W"))
    check_shape(offsets, "offsets", ("S", 2))
    off = offsets.round().long()
    pad = int(off.abs().max()) if off.numel() else 0
    padded = F.pad(gray, (pad, pad, pad, pad), mode="replicate")[:, 0]
    h, w = dims["H"], dims["W"]
    out = [padded[:, pad + dy : pad + dy + h, pad + dx : pad + dx + w] for dx, dy in off.tolist()]
    return torch.stack(out, dim=1).reshape(dims["B"], -1, h * w)


def bilateral_weights(
    ref_patches: torch.Tensor,
    offsets: torch.Tensor,
    sigma_spatial: float,
    sigma_color: float,
    center_index: int | list[int] | None = None,
    dim: int = -1,
    spatial: torch.Tensor | None = None,
) -> torch.Tensor:
    """COLMAP's bilateral weights of reference patches, normalised to sum to one.

    Args:
        ref_patches: ``(*, S)`` reference patch samples.
        offsets: ``(S, 2)`` their offsets from the patch centre.
        sigma_spatial: spatial standard deviation in pixels (COLMAP: the window radius).
        sigma_color: intensity standard deviation (COLMAP: 0.2 on [0, 1] intensities).
        center_index: index of the sample holding the centre intensity :math:`r_0`, or a list
            of indices whose mean is used; default the sample nearest to offset ``(0, 0)``. When
            the window has no centre sample (even number of samples per axis) the mean of the
            samples nearest the centre is used (:func:`patch_center_indices` lists them without
            reading the offsets back to the host).
        dim: the sample axis of ``ref_patches`` (``-2`` for the sample-major ``(B, S, P)``).
        spatial: the spatial log-weights :func:`spatial_log_weights` ``(offsets, sigma_spatial)``
            if already computed (PatchMatch computes them once per call).

    Returns:
        Non-negative weights shaped as ``ref_patches``, summing to one along ``dim``.

    Example:
        >>> off = patch_offsets(1)
        >>> w = bilateral_weights(torch.zeros(1, 9), off, 1.0, 0.2)
        >>> float(w.sum()), bool(w[0, 4] > w[0, 0])
        (1.0, True)
    """
    check_shape(offsets, "offsets", ("S", 2))
    x = ref_patches.movedim(dim, -1)
    check_shape(x, "ref_patches (sample axis last)", ("*", offsets.shape[0]))
    if spatial is None:
        spatial = spatial_log_weights(offsets.to(ref_patches), sigma_spatial)
    if center_index is None:
        off = offsets.to(ref_patches)
        dist2 = (off**2).sum(-1)
        nearest = torch.nonzero(dist2 <= dist2.min() + 1e-6).flatten()
        center = x[..., nearest].mean(-1, keepdim=True)
    elif isinstance(center_index, int):
        center = x[..., center_index : center_index + 1]
    elif len(center_index) == 1:
        center = x[..., center_index[0] : center_index[0] + 1]
    else:
        center = x[..., center_index].mean(-1, keepdim=True)
    d = x - center
    logw = torch.addcmul(spatial, d, d, value=-1 / (2 * sigma_color**2))
    return torch.softmax(logw, dim=-1).movedim(-1, dim)


def bilateral_ncc(
    ref_patches: torch.Tensor,
    src_patches: torch.Tensor,
    weights: torch.Tensor,
    min_variance: float = 1e-5,
) -> torch.Tensor:
    """Photometric cost ``1 - NCC`` of weighted patch pairs, in ``[0, 2]``.

    Not differentiable where the cost is clipped or a variance falls below ``min_variance``;
    PatchMatch uses it under ``torch.no_grad()``.

    Args:
        ref_patches: ``(*, S)`` reference patch samples.
        src_patches: ``(*, S)`` source patch samples (broadcast against ``ref_patches``).
        weights: ``(*, S)`` weights summing to one (see :func:`bilateral_weights`).
        min_variance: a patch (reference or source) with a smaller weighted variance gets the
            worst cost 2.

    Returns:
        ``(*)`` costs.

    Example:
        >>> r = torch.tensor([0.1, 0.5, 0.3, 0.9])
        >>> w = torch.full((4,), 0.25)
        >>> bilateral_ncc(r, r, w), bilateral_ncc(r, 2 * r + 0.1, w), bilateral_ncc(r, 1 - r, w)
        (tensor(0.), tensor(0.), tensor(2.))
        >>> bilateral_ncc(r, torch.full((4,), 0.5), w)  # a flat source patch
        tensor(2.)
    """
    r_mean = (weights * ref_patches).sum(-1, keepdim=True)
    s_mean = (weights * src_patches).sum(-1, keepdim=True)
    rc, sc = ref_patches - r_mean, src_patches - s_mean
    var_r = (weights * rc * rc).sum(-1)
    var_s = (weights * sc * sc).sum(-1)
    cov = (weights * rc * sc).sum(-1)
    ok = (var_r >= min_variance) & (var_s >= min_variance)
    ncc = cov / torch.sqrt((var_r * var_s).clamp_min(min_variance**2))
    cost = (1 - ncc).clamp(0, MAX_COST)
    return torch.where(ok, cost, torch.full_like(cost, MAX_COST))


class ReferencePatchStats(NamedTuple):
    r"""Hypothesis-independent reference-side terms of the bilateral NCC, sample-major.

    The layout is ``(B, S, P)`` (samples first) so that a run of pixels is a slice of the last
    axis: PatchMatch scores pixels in cache-sized chunks.

    Attributes:
        weights: ``(B, S, P)`` bilateral weights summing to one over ``S``.
        normalized: ``(B, S, P)`` :math:`w_s (r_s - \bar r) / \sigma_r` (zero where the
            reference patch is flat).
        valid: ``(B, P)`` bool, the reference patch variance reaches ``min_variance``.
    """

    weights: torch.Tensor
    normalized: torch.Tensor
    valid: torch.Tensor


def _weighted_moments(ref_patches: torch.Tensor, weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``w (r - mean)`` ``(B, S, P)`` and the weighted variance ``(B, 1, P)`` of checked patches."""
    dims = check_shape(ref_patches, "ref_patches", ("B", "S", "P"))
    check_shape(weights, "weights", ("B", "S", "P"), dims)
    # the patches first: the products take their layout, whatever the weights' (sums in one order)
    mean = (ref_patches * weights).sum(1, keepdim=True)
    centered = ref_patches - mean
    weighted = centered * weights
    return weighted, (weighted * centered).sum(1, keepdim=True)


def reference_patch_stats(
    ref_patches: torch.Tensor, weights: torch.Tensor, min_variance: float = 1e-5
) -> ReferencePatchStats:
    """Precompute the reference half of :func:`bilateral_ncc`.

    Args:
        ref_patches: ``(B, S, P)`` reference samples (as :func:`reference_patches` returns).
        weights: ``(B, S, P)`` bilateral weights summing to one over ``S``.
        min_variance: threshold below which the reference patch is flat.

    Returns:
        A :class:`ReferencePatchStats`.

    Example:
        >>> r = torch.tensor([[[0.1], [0.5], [0.3], [0.9]]])  # B = 1, S = 4, P = 1
        >>> st = reference_patch_stats(r, torch.full_like(r, 0.25))
        >>> ncc_cost_from_stats(r[:, None], st)
        tensor([[[0.]]])
    """
    weighted, var = _weighted_moments(ref_patches, weights)
    valid = var[:, 0] >= min_variance
    normalized = weighted * torch.rsqrt(var.clamp_min(min_variance)) * valid[:, None]  # zero where flat
    return ReferencePatchStats(weights, normalized, valid)


def reference_terms(
    ref_patches: torch.Tensor,
    weights: torch.Tensor,
    min_variance: float = 1e-5,
    keep: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    r"""The reference half of the NCC as PatchMatch scores it, stacked, and where it is usable.

    As :func:`reference_patch_stats` without the guards that a caller who masks flat patches
    does not need: where the patch is flat (or not kept) the weights are zero, so that the source
    side's weighted variance is zero and the cost is masked as the worst, and the normalised term
    is left undefined (NaN or infinite) there.

    Args:
        ref_patches: ``(B, S, P)`` reference samples.
        weights: ``(B, S, P)`` bilateral weights summing to one over ``S``.
        min_variance: threshold below which the reference patch is flat.
        keep: optional ``(B, P)`` bool, the pixels to score (others get zero weights too).

    Returns:
        ``(B, 2, S, P)`` the weights (zero where not usable) and :math:`w_s (r_s - \bar r) /
        \sigma_r`, and ``(B, P)`` bool where usable (textured and kept).

    Example:
        >>> r = torch.tensor([[[0.1], [0.5], [0.3], [0.9]]])  # B = 1, S = 4, P = 1
        >>> terms, usable = reference_terms(r, torch.full_like(r, 0.25))
        >>> st = reference_patch_stats(r, torch.full_like(r, 0.25))
        >>> bool(torch.equal(terms[:, 1], st.normalized)), usable
        (True, tensor([[True]]))
    """
    weighted, var = _weighted_moments(ref_patches, weights)
    usable = var[:, 0] >= min_variance
    if keep is not None:
        usable = usable & keep
    return torch.stack([weights * usable[:, None], weighted * var.rsqrt()], 1), usable


def ncc_cost_from_stats(
    src_patches: torch.Tensor, stats: ReferencePatchStats, min_variance: float = 1e-5
) -> torch.Tensor:
    """``1 - NCC`` of source patches against precomputed reference statistics (the hot path).

    Equal to :func:`bilateral_ncc` up to rounding (``tests/mvs`` checks it against a loop).

    Args:
        src_patches: ``(B, V, S, P)`` source samples of ``V`` views, sample-major.
        stats: reference statistics from :func:`reference_patch_stats`, ``(B, S, P)``.
        min_variance: threshold below which the source patch is flat (cost 2).

    Returns:
        ``(B, V, P)`` costs in ``[0, 2]``.
    """
    weighted = src_patches * stats.weights[:, None]
    mean = weighted.sum(2)
    sq = (weighted * src_patches).sum(2)
    cov = (src_patches * stats.normalized[:, None]).sum(2)
    var = sq - mean * mean
    ok = (var >= min_variance) & stats.valid[:, None]
    cost = (1 - cov * torch.rsqrt(var.clamp_min(min_variance))).clamp(0, MAX_COST)
    return torch.where(ok, cost, torch.full_like(cost, MAX_COST))
