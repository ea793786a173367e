r"""Training losses: the colour loss and the paper's geometric losses (Eq. "Loss Function").

.. math::

    \mathcal{L} = \mathcal{L}_\text{color} + \lambda_\text{normal}\mathcal{L}_\text{normal}
        + \lambda_\text{hard}\mathcal{L}_\text{hard} + \lambda_\text{soft}\mathcal{L}_\text{soft}

with :math:`\lambda_\text{normal} = 0.02`, :math:`\lambda_\text{hard} = \lambda_\text{soft} = 0.1`
and :math:`\lambda_\text{hard}` switched off after 80 % of the iterations (paper, "Implementation
Details"). These settings, and the ones that bound the hard loss's cost, are one
:class:`GeometricLossConfig` (``TrainConfig.geometry``); :func:`geometric_weights` gives its weights
at a step to any loop.

Our reading of the paper (it gives no formulas): both depth losses compare a rendered z-depth with
a target depth (voxel-rasterised / MVS depth in VAD-GS, projected LiDAR in the baseline) by the
relative L1 error on the target's valid pixels. They differ in the opacities the depth is rendered
with:

- *soft*: the ordinary expected depth, rendered with the learned opacities; its gradient also
  moves opacities.
- *hard*: the depth rendered with every opacity *fixed* to a constant (1 by default, no gradient
  to the opacity logits), so that each Gaussian counts as a solid surface and a semi-transparent
  floater in front of the true surface is pulled onto it (or out of the way) instead of being
  faded out. That constraint is too strong once the geometry has settled (thin and transparent
  structures), hence the switch-off after 80 %.

All losses are pure functions of tensors, differentiable w.r.t. the rendered inputs.
:func:`geometric_losses` is the one path from priors (:class:`GeometryTargets`, e.g. those of
:meth:`vadgs.train.vad.VisibilityAwareDensification.geometry_targets`) to weighted loss terms, used
by vadgs's trainer and by any other loop (``examples/gsplat_loop_vad.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from kornia.filters import get_gaussian_kernel1d

from vadgs.checks import Checked, bool_field, check_shape, checked, float_field, int_field

__all__ = [
    "GeometricLossConfig",
    "GeometryTargets",
    "color_loss",
    "depth_loss",
    "depth_loss_hard",
    "depth_loss_soft",
    "geometric_losses",
    "geometric_weights",
    "normal_loss",
    "ssim_map",
]


class GeometryTargets(NamedTuple):
    """Targets of the geometric losses for one view (any may be None).

    Attributes:
        depth: ``(1, 1, H, W)`` target z-depth, 0 where unknown (voxel / MVS depth).
        normal: ``(1, 3, H, W)`` target camera-frame normals, zeros where unknown.
        mask: ``(1, 1, H, W)`` bool, pixels the losses apply to (None: every pixel with a target).
    """

    depth: torch.Tensor | None = None
    normal: torch.Tensor | None = None
    mask: torch.Tensor | None = None

    def to(self, device: torch.device | str) -> GeometryTargets:
        """The same targets on ``device``."""
        return GeometryTargets(*(None if t is None else t.to(device) for t in self))


def _masked_mean(x: torch.Tensor, mask: torch.Tensor | None, min_share: float = 0.0) -> torch.Tensor:
    """The mean of ``x`` over ``mask``, or its sum over ``min_share`` of its elements if mask has fewer."""
    if mask is None:
        return x.mean()
    m = mask.to(x.dtype).expand_as(x)
    return (x * m).sum() / m.sum().clamp(min=max(1.0, min_share * m.numel()))


_SSIM_WINDOWS: dict[tuple[int, torch.device, torch.dtype], torch.Tensor] = {}  # ssim_map's


def ssim_map(img1: torch.Tensor, img2: torch.Tensor, window_size: int = 11) -> torch.Tensor:
    """Kornia's SSIM map with its five local moments filtered together.

    ``kornia.metrics.ssim``'s: a Gaussian window of sigma 1.5, reflected borders, ``max_val=1``,
    ``eps=1e-12``.
    The two images, their squares and their product are stacked and filtered by one separable
    depthwise convolution, instead of one filtering each: a third of the kernel launches of
    kornia's on a GPU (forward and backward), equal to it to rounding (within 1e-6 on ``[0, 1]``
    images, tested).

    Shape:
        ``(B, C, H, W)`` twice → ``(B, C, H, W)``.

    Example:
        >>> x = torch.rand(1, 3, 16, 16)
        >>> bool((ssim_map(x, x) - 1).abs().max() < 1e-5)
        True
    """
    dims = check_shape(img1, "img1", ("B", "C", "H", "W"))
    check_shape(img2, "img2", ("B", "C", "H", "W"), dims)
    c = dims["C"]
    key = (window_size, img1.device, img1.dtype)
    kernel = _SSIM_WINDOWS.get(key)
    if kernel is None:  # 20 launches to make: kept (a few dozen bytes a device and dtype)
        kernel = get_gaussian_kernel1d(window_size, 1.5, device=img1.device, dtype=img1.dtype).reshape(-1)
        _SSIM_WINDOWS[key] = kernel
    half = window_size // 2
    stacked = torch.cat([img1, img2, img1 * img1, img2 * img2, img1 * img2], 1)
    padded = F.pad(stacked, (half, half, half, half), mode="reflect")
    kx = kernel.reshape(1, 1, 1, -1).expand(5 * c, 1, 1, window_size)
    ky = kernel.reshape(1, 1, -1, 1).expand(5 * c, 1, window_size, 1)
    moments = F.conv2d(F.conv2d(padded, kx, groups=5 * c), ky, groups=5 * c)
    mu1, mu2, e11, e22, e12 = moments.split(c, 1)
    mu1_sq, mu2_sq, mu1_mu2 = mu1**2, mu2**2, mu1 * mu2
    c1, c2 = 0.01**2, 0.03**2
    num = (2.0 * mu1_mu2 + c1) * (2.0 * (e12 - mu1_mu2) + c2)
    den = (mu1_sq + mu2_sq + c1) * ((e11 - mu1_sq) + (e22 - mu2_sq) + c2)
    return num / (den + 1e-12)


def color_loss(
    pred: torch.Tensor, target: torch.Tensor, ssim_weight: float = 0.2, mask: torch.Tensor | None = None
) -> torch.Tensor:
    r"""3DGS colour loss :math:`(1 - \lambda)\,L_1 + \lambda\,(1 - \mathrm{SSIM})`, :math:`\lambda = 0.2`.

    SSIM is kornia's (11×11 Gaussian window), as :func:`ssim_map` computes it. With a mask, both
    terms are averaged over the masked pixels only (the SSIM map is computed on the full image).
    Differentiable w.r.t. ``pred``.

    Args:
        pred: ``(B, 3, H, W)`` rendered colours.
        target: ``(B, 3, H, W)`` observed colours in ``[0, 1]``.
        ssim_weight: :math:`\lambda`.
        mask: optional ``(B, 1, H, W)`` bool, pixels that count.

    Returns:
        Scalar loss.

    Example:
        >>> x = torch.rand(1, 3, 16, 16)
        >>> color_loss(x, x).item()
        0.0
    """
    dims = check_shape(pred, "pred", ("B", 3, "H", "W"))
    check_shape(target, "target", ("B", 3, "H", "W"), dims)
    l1 = _masked_mean((pred - target).abs(), mask)
    dssim = _masked_mean(1.0 - ssim_map(pred, target, 11), mask)
    return (1.0 - ssim_weight) * l1 + ssim_weight * dssim


def normal_loss(
    pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None, min_share: float = 0.0
) -> torch.Tensor:
    r"""Angular deviation :math:`\frac{1}{|M|}\sum_{p\in M} (1 - \mathbf{n}_p^\top \hat{\mathbf{n}}_p)`.

    Compares rendered normals with target normals (MVS in VAD-GS) on pixels where both are
    non-zero (and ``mask``). Differentiable w.r.t. ``pred``.

    Args:
        pred: ``(B, 3, H, W)`` rendered camera-frame normals (zeros where nothing is rendered).
        target: ``(B, 3, H, W)`` unit target normals, zeros where invalid.
        mask: optional ``(B, 1, H, W)`` bool.
        min_share: the sum is divided by ``max(|M|, min_share · B·H·W)``: a few pixels with a
            target weigh as their share of the image, not as the whole mean (0: the mean over M).

    Returns:
        Scalar loss in ``[0, 2]``.

    Example:
        >>> n = torch.zeros(1, 3, 2, 2); n[:, 2] = -1.0
        >>> normal_loss(n, n).item(), normal_loss(n, -n).item()
        (0.0, 2.0)
    """
    dims = check_shape(pred, "pred", ("B", 3, "H", "W"))
    check_shape(target, "target", ("B", 3, "H", "W"), dims)
    # a pixel whose normals both have a non-zero component (NaN counts: its loss is NaN either way)
    valid = (target != 0).any(1, keepdim=True) & (pred.detach() != 0).any(1, keepdim=True)
    if mask is not None:
        valid = valid & mask
    cos = (F.normalize(pred, dim=1) * F.normalize(target, dim=1)).sum(1, keepdim=True)
    return _masked_mean(1.0 - cos, valid, min_share)


def depth_loss(
    pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None, min_share: float = 0.0
) -> torch.Tensor:
    r"""Relative L1 depth error on the pixels with a target.

    .. math::

        \frac{1}{\max(|M|,\ \rho\,BHW)}\sum_{p\in M} |d_p - \hat d_p| / \hat d_p


    Pixels where the target is 0 (no value) are ignored; a rendered depth of 0 (nothing rendered)
    counts as a full error of 1. Differentiable w.r.t. ``pred``.

    Args:
        pred: ``(B, 1, H, W)`` rendered z-depth.
        target: ``(B, 1, H, W)`` target z-depth, 0 where unknown.
        mask: optional ``(B, 1, H, W)`` bool.
        min_share: :math:`\rho`: fewer pixels with a target than this share of the image weigh as
            their share, not as the whole mean (0: the mean over the pixels with a target).

    Returns:
        Scalar loss (0 when no pixel has a target).

    Example:
        >>> t = torch.full((1, 1, 2, 2), 10.0); t[0, 0, 0, 0] = 0
        >>> depth_loss(torch.full((1, 1, 2, 2), 11.0), t).item()
        0.10000000149011612
    """
    dims = check_shape(pred, "pred", ("B", 1, "H", "W"))
    check_shape(target, "target", ("B", 1, "H", "W"), dims)
    valid = target > 0
    if mask is not None:
        valid = valid & mask
    err = (pred - target).abs() / target.clamp(min=1e-6)
    return _masked_mean(err, valid, min_share)


def depth_loss_soft(
    depth: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None, min_share: float = 0.0
) -> torch.Tensor:
    r"""Soft depth loss: :func:`depth_loss` of the depth rendered with the *learned* opacities.

    Args:
        depth: ``(B, 1, H, W)`` expected depth of the ordinary render (``RenderOutput.depth``).
        target: ``(B, 1, H, W)`` target depth, 0 where unknown.
        mask: optional ``(B, 1, H, W)`` bool.
        min_share: see :func:`depth_loss`.

    Example:
        >>> t = torch.full((1, 1, 2, 2), 4.0)
        >>> depth_loss_soft(t, t).item()
        0.0
    """
    return depth_loss(depth, target, mask, min_share)


def depth_loss_hard(
    depth_hard: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None, min_share: float = 0.0
) -> torch.Tensor:
    r"""Hard depth loss: :func:`depth_loss` of the depth rendered with *fixed* opacities.

    ``depth_hard`` is the expected depth of a render in which every Gaussian has the same fixed
    opacity (1 by default) and no gradient flows to the opacities
    (``GaussianModel.render(..., opacity_override=1.0)``): only positions, scales and rotations
    move, so floaters cannot escape the loss by becoming transparent.

    Args:
        depth_hard: ``(B, 1, H, W)``.
        target: ``(B, 1, H, W)`` target depth, 0 where unknown.
        mask: optional ``(B, 1, H, W)`` bool.
        min_share: see :func:`depth_loss`.

    Example:
        >>> t = torch.full((1, 1, 2, 2), 4.0)
        >>> depth_loss_hard(t * 0.5, t).item()
        0.5
    """
    return depth_loss(depth_hard, target, mask, min_share)


@dataclass(frozen=True)
class GeometricLossConfig(Checked):
    r"""The paper's geometric loss: weights, the hard term's switch-off and cost (``TrainConfig.geometry``).

    The loss of a step (paper, Eq. "Loss Function" and "Implementation Details"):

    .. math::

        \mathcal{L} = \mathcal{L}_\text{color} + 0.02\,\mathcal{L}_\text{normal}
            + 0.1\,(\mathcal{L}_\text{hard} + \mathcal{L}_\text{soft})

    :math:`\mathcal{L}_\text{normal}` compares the rendered normals with the priors' normals
    (:func:`normal_loss`); :math:`\mathcal{L}_\text{soft}` and :math:`\mathcal{L}_\text{hard}` the
    rendered depth with the priors' depth (:func:`depth_loss_soft`: the learned opacities;
    :func:`depth_loss_hard`: every opacity fixed to 1, so a floater cannot escape by fading). The
    hard term is switched off after 80 % of the iterations (``hard_until``): too strong a
    constraint once the geometry has settled. :meth:`weights` gives the three weights at a step.

    The priors are VAD-GS's (:meth:`vadgs.train.vad.VisibilityAwareDensification.geometry_targets`:
    MVS depth and normals, voxel depth where MVS has none) or any
    :class:`GeometryTargets` provider's; a view without priors has no geometric term. The paper's
    "w/o geometric losses" ablation is the strategy's ``VisibilityDensifyConfig.geometric_losses =
    False`` (``--vad.geometric-losses False``): it gives no targets, which turns every geometric
    term off whatever the weights here.

    Each term is a mean over the pixels with a prior, or, where fewer than ``min_prior_share`` of
    the image's pixels have one, their sum over that share (:func:`depth_loss`'s ``min_share``): a
    documented deviation (the paper does not say how the terms are normalised). An event's priors
    cover its reconstructed crops: a sixth of a view on the rendered streets (median), but a few
    hundred pixels, 0.7 %, on PandaSet, where a mean over them gave those pixels 25 times the
    weight, pulled the geometric gradient up to the colour loss's, and grew the Gaussians the
    standard densification picks by that gradient (docs/results.md, "A real log"). ``0`` is the
    plain mean over the pixels with a prior.

    Three settings bound the hard term's cost: documented deviations from the paper (docs/train.md;
    measured in docs/results.md and docs/benchmarks.md). ``hard_every`` 1, ``hard_stride`` 1 is the
    paper's schedule:

    - ``hard_every``: the hard term (an extra depth-only render) on every ``hard_every``-th step
      only (:meth:`hard_applies`); the paper's: every step (1).
    - ``hard_stride``: its depth rendered on every ``hard_stride``-th pixel row and column (a
      camera with ``fx, fy, cx, cy`` divided by it) and compared with the targets there; the
      paper's: every pixel (1).
    - ``hard_fused``: composite the hard depth in the step's own render pass instead of a second
      render (the same loss and gradients, to float32 rounding, as the second render at
      ``hard_stride`` 1); a cost setting only, off by default. Both ways are
      :func:`~vadgs.train.objective.render_hard_depth`.

    Attributes:
        lambda_normal: weight of the normal term (0 disables it).
        lambda_hard: weight of the hard depth term before the switch-off (0 disables it).
        lambda_soft: weight of the soft depth term (0 disables it).
        hard_until: the hard term applies while ``step < hard_until * total_steps`` (in [0, 1]).
        hard_every: the hard term is applied on every ``hard_every``-th step only. 8 by default:
            a fraction of the cost of every step at the same quality (docs/results.md).
        hard_stride: the stride of the hard depth's pixels. 2 by default: the same quality as
            every pixel (docs/results.md).
        hard_fused: the hard depth composited in the step's own render pass (the same projection
            and tile lists, forward and backward: ``rasterize_gaussians(hard_depth=True)``). Needs
            ``hard_stride`` 1, the torch raster backend and no antialiasing (checked by
            ``TrainConfig``). Off by default (docs/benchmarks.md: the measured trade).
        min_prior_share: the share of a view's pixels below which the terms are sums over that
            share rather than means over the pixels with a prior (in [0, 1]; 0.1 by default).

    Example:
        >>> g = GeometricLossConfig()
        >>> g.weights(0, 1000)
        {'normal': 0.02, 'hard': 0.1, 'soft': 0.1}
        >>> g.weights(800, 1000)["hard"], g.hard_applies(8, 1000), g.hard_applies(9, 1000)
        (0.0, True, False)
        >>> GeometricLossConfig(hard_every=0)
        Traceback (most recent call last):
        ...
        ValueError: hard_every: expected an integer >= 1, got 0
    """

    lambda_normal: float = checked(0.02, float_field(0))
    lambda_hard: float = checked(0.1, float_field(0))
    lambda_soft: float = checked(0.1, float_field(0))
    hard_until: float = checked(0.8, float_field(0, 1))
    hard_every: int = checked(8, int_field(1))
    hard_stride: int = checked(2, int_field(1))
    hard_fused: bool = checked(False, bool_field())
    min_prior_share: float = checked(0.1, float_field(0, 1))

    def weights(self, step: int, total_steps: int) -> dict[str, float]:
        """The weights ``{"normal", "hard", "soft"}`` at ``step`` of ``total_steps``.

        ``hard`` is ``lambda_hard`` before ``hard_until * total_steps``, 0 from there on; the others
        are constant.
        """
        hard = self.lambda_hard if step < self.hard_until * total_steps else 0.0
        return {"normal": self.lambda_normal, "hard": hard, "soft": self.lambda_soft}

    def hard_applies(self, step: int, total_steps: int) -> bool:
        """Whether the hard depth term is computed at ``step``: its weight > 0 and ``step % hard_every == 0``.

        (It also needs the view's target depth: a loop asks only for a view with one.)
        """
        return self.weights(step, total_steps)["hard"] > 0 and step % self.hard_every == 0


def geometric_weights(
    step: int,
    total_steps: int,
    lambda_normal: float = GeometricLossConfig.lambda_normal,
    lambda_hard: float = GeometricLossConfig.lambda_hard,
    lambda_soft: float = GeometricLossConfig.lambda_soft,
    hard_until: float = GeometricLossConfig.hard_until,
) -> dict[str, float]:
    """The weights of the geometric losses at a step: ``λ_hard`` is 0 from ``hard_until · total_steps`` on.

    :meth:`GeometricLossConfig.weights` of a config with these settings (checked; the defaults are
    the paper's), for a loop that holds the numbers rather than the config.

    Example:
        >>> geometric_weights(799, 1000)["hard"], geometric_weights(800, 1000)["hard"]
        (0.1, 0.0)
    """
    config = GeometricLossConfig(
        lambda_normal=lambda_normal, lambda_hard=lambda_hard, lambda_soft=lambda_soft, hard_until=hard_until
    )
    return config.weights(step, total_steps)


def geometric_losses(
    targets: GeometryTargets,
    depth: torch.Tensor,
    normals: torch.Tensor,
    weights: dict[str, float],
    hard_depth: torch.Tensor | None = None,
    hard_stride: int = 1,
    min_share: float = GeometricLossConfig.min_prior_share,
) -> dict[str, torch.Tensor]:
    r"""The paper's geometric loss terms of one view, already weighted: ``soft``, ``hard``, ``normal``.

    ``soft``: :func:`depth_loss_soft` of the rendered ``depth``; ``hard``: :func:`depth_loss_hard` of
    ``hard_depth`` (the depth rendered with opacities fixed to 1; no term when None, so a loop can
    render it only every few steps); ``normal``: :func:`normal_loss` where the target normals are
    non-zero. A term is left out when its weight is 0 or its target is None. Differentiable w.r.t.
    ``depth``, ``normals`` and ``hard_depth``. No host synchronisation.

    Args:
        targets: :class:`GeometryTargets` on the device of the renders.
        depth: ``(1, 1, H, W)`` rendered expected depth.
        normals: ``(1, 3, H, W)`` rendered camera-frame normals.
        weights: ``{"normal", "hard", "soft"}`` (:meth:`GeometricLossConfig.weights`,
            :func:`geometric_weights`).
        hard_depth: ``(1, 1, H, W)`` or None; with ``hard_stride`` s, ``(1, 1, ceil(H / s),
            ceil(W / s))``: the depth at every s-th pixel row and column, compared with the
            targets there.
        hard_stride: the stride of ``hard_depth``.
        min_share: each term's sum is divided by ``max(pixels with a prior, min_share · pixels)``
            (:attr:`GeometricLossConfig.min_prior_share`; 0: the mean over the pixels with a prior).

    Returns:
        ``{name: scalar}``.

    Example:
        >>> t = GeometryTargets(depth=torch.full((1, 1, 2, 2), 4.0))
        >>> terms = geometric_losses(t, torch.full((1, 1, 2, 2), 5.0), torch.zeros(1, 3, 2, 2),
        ...                          geometric_weights(0, 10), hard_depth=torch.full((1, 1, 2, 2), 2.0))
        >>> {k: round(v.item(), 4) for k, v in terms.items()}
        {'soft': 0.025, 'hard': 0.05}
    """
    terms: dict[str, torch.Tensor] = {}
    if targets.depth is not None:
        if weights["soft"] > 0:
            terms["soft"] = weights["soft"] * depth_loss_soft(depth, targets.depth, targets.mask, min_share)
        if hard_depth is not None and weights["hard"] > 0:
            target, mask = targets.depth, targets.mask
            if hard_stride > 1:
                target = target[..., ::hard_stride, ::hard_stride]
                mask = None if mask is None else mask[..., ::hard_stride, ::hard_stride]
            if hard_depth.shape[-2:] != target.shape[-2:]:
                raise ValueError(
                    f"hard_depth: expected spatial size {tuple(target.shape[-2:])} (stride {hard_stride}), "
                    f"got {tuple(hard_depth.shape[-2:])}"
                )
            terms["hard"] = weights["hard"] * depth_loss_hard(hard_depth, target, mask, min_share)
    if targets.normal is not None and weights["normal"] > 0:
        terms["normal"] = weights["normal"] * normal_loss(normals, targets.normal, targets.mask, min_share)
    return terms
