"""What both renderers share: :class:`RasterConfig`, :class:`RenderOutput` and the input checks.

:func:`vadgs.render.rasterize_gaussians` (pure torch, ``vadgs/render/splat.py``) and
:func:`vadgs.render.gsplat_backend.rasterize_gaussians_gsplat` take the same inputs and settings and
return the same :class:`RenderOutput`; both import them from here, so neither imports the other at
load time.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import NamedTuple

import torch

from vadgs.checks import (
    Checked,
    bool_field,
    check_finite,
    check_same_device,
    check_shape,
    checked,
    checks_enabled,
    choice_field,
    first_false,
    float_field,
    int_field,
)

__all__ = [
    "RasterConfig",
    "RenderOutput",
    "check_no_sh_degree",
    "check_raster_inputs",
]


@dataclass(frozen=True)
class RasterConfig(Checked):
    """Settings of the rasterizer (gsplat's defaults unless stated).

    Attributes:
        near: Gaussians with camera-frame ``z <= near`` are culled (metres).
        far: Gaussians with ``z >= far`` are culled.
        eps2d: screen-space low-pass variance added to every 2D covariance, px² (3DGS: 0.3).
        antialiased: Mip-Splatting opacity compensation ``sqrt(det(Σ) / det(Σ + eps2d I))``.
        alpha_max: alpha cap (gsplat 0.999; the original 3DGS uses 0.99). Must be < 1.
        alpha_min: a Gaussian with ``alpha < alpha_min`` at a pixel is skipped there (1/255).
        transmittance_min: a pixel stops before the Gaussian that would bring its transmittance
            to this or below (1e-4).
        tile_size: tile side in pixels (8 is fastest on CPU, see ``docs/render.md``).
        chunk_size: Gaussians per tile processed per step of the compositing loop.
        absgrad: also accumulate gsplat's ``absgrad`` (sum over pixels of the absolute
            per-pixel gradient of the 2D means) in :attr:`RenderOutput.means2d_absgrad` during
            backward; its cost was within the timing noise on benchmark case 1.
        backward: ``"manual"`` (hand-written backward, default) or ``"autograd"`` (the same loop
            differentiated by autograd; slower, more memory, for cross-checks).
        backend: ``"torch"`` (this pure-torch renderer, default) or ``"gsplat"``
            (:func:`~vadgs.render.gsplat_backend.rasterize_gaussians_gsplat`: gsplat's CUDA
            rasterizer for CUDA tensors, its pure-torch reference pipeline otherwise; no median
            depth; ``tile_size``, ``chunk_size`` and ``backward`` do not apply).
    """

    near: float = checked(0.01, float_field(0, lo_open=True))
    far: float = checked(1e10, float_field(0, lo_open=True))
    eps2d: float = checked(0.3, float_field(0))
    antialiased: bool = checked(False, bool_field())
    alpha_max: float = checked(0.999, float_field(0, 1, lo_open=True, hi_open=True))
    alpha_min: float = checked(1.0 / 255.0, float_field(0, 1, lo_open=True, hi_open=True))
    transmittance_min: float = checked(1e-4, float_field(0, 1, hi_open=True))
    tile_size: int = checked(8, int_field(1))
    chunk_size: int = checked(32, int_field(1))
    absgrad: bool = checked(False, bool_field())
    backward: str = checked("manual", choice_field(("manual", "autograd")))
    backend: str = checked("torch", choice_field(("torch", "gsplat")))

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.near < self.far:
            raise ValueError(f"near, far: expected 0 < near < far, got near={self.near}, far={self.far}")
        if not self.alpha_min < self.alpha_max:
            raise ValueError(
                f"alpha_min, alpha_max: expected 0 < alpha_min < alpha_max < 1, "
                f"got {self.alpha_min}, {self.alpha_max}"
            )


class RenderOutput(NamedTuple):
    """What :func:`rasterize_gaussians` returns.

    Attributes:
        color: ``(B, D, H, W)`` composited colour plus ``T * background`` (D = 3 for SH).
        alpha: ``(B, 1, H, W)`` accumulated opacity ``1 - T``.
        depth: ``(B, 1, H, W)`` expected z-depth ``sum_i w_i z_i / alpha``; 0 where alpha = 0.
        median_depth: ``(B, 1, H, W)`` z of the Gaussian at which the transmittance first drops
            to 0.5 or below; 0 where it never does.
        normals: ``(B, 3, H, W)`` normalised ``sum_i w_i n_i`` of the Gaussians' shortest axes,
            camera frame, facing the camera; zeros where nothing is rendered.
        median_ids: ``(B, H, W)`` int64 index of that median Gaussian, ``-1`` where none.
        means2d: ``(B, N, 2)`` screen means in pixels. When the inputs require grad it retains
            its gradient: after ``backward()``, ``means2d.grad`` is the densification statistic
            (gsplat's ``means2d`` gradient, in pixel units).
        means2d_absgrad: ``(B, N, 2)`` sum over pixels of the absolute per-pixel gradient of
            ``means2d`` (gsplat's ``absgrad``), filled during backward when
            ``RasterConfig.absgrad``; None otherwise.
        radii: ``(B, N, 2)`` int32 half sizes of the screen boxes, 0 where culled.
        visible: ``(B, N)`` bool, ``radii > 0``: in front of the camera, inside the near/far
            range, opaque enough and overlapping the image.
        depths: ``(B, N)`` camera-frame z of the means.
        hard_depth: ``(B, 1, H, W)`` with ``hard_depth=True``: the expected depth with every
            opacity fixed to 1 (the paper's hard depth), composited in the same tile pass as the
            rest; None otherwise.
    """

    color: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    median_depth: torch.Tensor
    normals: torch.Tensor
    median_ids: torch.Tensor
    means2d: torch.Tensor
    means2d_absgrad: torch.Tensor | None
    radii: torch.Tensor
    visible: torch.Tensor
    depths: torch.Tensor
    hard_depth: torch.Tensor | None = None


def check_raster_inputs(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    world_to_cam: torch.Tensor,
    K: torch.Tensor,
    background: torch.Tensor | None,
) -> dict[str, int]:
    """Check a rasterizer's inputs (shapes, dtypes, finite cameras); their dims (``N``, ``B``, ...).

    What both rasterizers (:mod:`vadgs.render.splat`, :mod:`vadgs.render.gsplat_backend`) check
    before rendering.
    """
    dims = check_shape(means, "means", ("N", 3))
    check_shape(quats, "quats", ("N", 4), dims)
    check_shape(scales, "scales", ("N", 3), dims)
    check_shape(opacities, "opacities", ("N",), dims)
    if not isinstance(colors, torch.Tensor) or colors.dim() not in (2, 3):
        shape = tuple(colors.shape) if isinstance(colors, torch.Tensor) else type(colors).__name__
        raise ValueError(f"colors: expected shape (N, D) or SH (N, K, 3), got {shape}")
    if colors.dim() == 2:
        check_shape(colors, "colors", ("N", "D"), dims)
    else:
        check_shape(colors, "colors", ("N", "K", 3), dims)
        dims["D"] = 3
    check_shape(world_to_cam, "world_to_cam", ("B", 4, 4), dims)
    check_shape(K, "K", ("B", 3, 3), dims)
    named = [
        ("means", means),
        ("quats", quats),
        ("scales", scales),
        ("opacities", opacities),
        ("colors", colors),
        ("world_to_cam", world_to_cam),
        ("K", K),
    ]
    if background is not None:
        if background.dim() == 1:
            check_shape(background, "background", ("D",), dims)
        else:
            check_shape(background, "background", ("B", "D"), dims)
        named.append(("background", background))
    check_same_device(*named)
    dtypes = {name: t.dtype for name, t in named}
    if len(set(dtypes.values())) > 1:
        raise ValueError(f"expected one floating dtype for all inputs, got {dtypes}")
    if not means.is_floating_point():
        raise ValueError(f"means: expected a floating dtype, got {means.dtype}")
    if checks_enabled():
        checks = _value_checks(named, K, quats, scales, opacities)
        failed = first_false([ok for ok, _ in checks])  # one read from the device for all of them
        if failed is not None:
            checks[failed][1]()
    return dims


def _value_checks(
    named: list[tuple[str, torch.Tensor]],
    K: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
) -> list[tuple[torch.Tensor, Callable[[], None]]]:
    """The value checks of :func:`check_raster_inputs`, in order: ``(holds, raise its error)`` each.

    Each condition is computed once; its error (with counts and values) only when it is raised.
    """
    with torch.no_grad():
        checks: list[tuple[torch.Tensor, Callable[[], None]]] = [
            (torch.isfinite(t).all(), partial(check_finite, t, name))
            for name, t in named
            if t.is_floating_point()
        ]
        focal = K[:, [0, 1], [0, 1]]

        def bad_focal() -> str:
            b = int((~(focal > 0).all(-1)).nonzero()[0, 0])
            return (
                f"K: expected positive focal lengths fx = K[b, 0, 0], fy = K[b, 1, 1] (an invertible "
                f"pinhole K), got fx={float(focal[b, 0]):.4g}, fy={float(focal[b, 1]):.4g} for camera b={b}"
            )

        checks.append(((focal > 0).all(), _raises(bad_focal)))
        if not quats.shape[0]:
            return checks
        zero = quats.norm(dim=-1) < 1e-12
        limit = math.sqrt(torch.finfo(scales.dtype).max) / 1e3  # larger overflows the covariance
        smax = scales.max()
        checks += [
            (
                ~zero.any(),
                _raises(lambda: f"quats: expected non-zero quaternions, got {int(zero.sum())} of norm 0"),
            ),
            (
                (scales >= 0).all(),
                _raises(
                    lambda: (
                        "scales: expected activated (non-negative) scales, got negative values; "
                        "pass exp(log_scales)"
                    )
                ),
            ),
            (
                ((opacities >= 0) & (opacities <= 1)).all(),
                _raises(
                    lambda: (
                        "opacities: expected activated opacities in [0, 1], got values outside; "
                        "pass sigmoid(logits)"
                    )
                ),
            ),
            (
                smax < limit,
                _raises(
                    lambda: (
                        f"scales: expected < {limit:.3g} (larger overflows the {scales.dtype} covariance), "
                        f"got max {float(smax):.3g}; pass exp(log_scales) of a sane model"
                    )
                ),
            ),
        ]
    return checks


def _raises(message: Callable[[], str]) -> Callable[[], None]:
    """A function that raises ``ValueError(message())``."""

    def raise_it() -> None:
        raise ValueError(message())

    return raise_it


def check_no_sh_degree(colors: torch.Tensor, sh_degree: int | None) -> None:
    """``sh_degree`` must be None when ``colors`` are not SH coefficients (``(N, D)`` colours)."""
    if sh_degree is not None:
        raise ValueError(f"sh_degree: given ({sh_degree}) but colors are not SH, shape {tuple(colors.shape)}")
