"""The public renderer: 3D Gaussians and cameras in, images and densification statistics out.

:func:`rasterize_gaussians` chains :func:`~vadgs.render.projection.project_gaussians` (EWA),
spherical-harmonics colours (:func:`~vadgs.render.sh.eval_sh`), tile binning
(:func:`~vadgs.render.tiles.bin_gaussians`) and front-to-back compositing
(:func:`~vadgs.render.composite.composite_gaussians`). Colour, depth and normals go through the
compositor together as one feature vector per Gaussian, so they cost one pass.
:class:`GaussianRasterizer` is the ``nn.Module`` that holds a :class:`RasterConfig`.

Conventions (gsplat's unless stated, see ``docs/render.md``): activated inputs (positive scales,
opacities in ``[0, 1]``), ``wxyz`` quaternions of any non-zero norm, OpenCV cameras with pixel
centres at integers, ``eps2d = 0.3``, alpha capped at 0.999, ``alpha < 1/255`` skipped, a pixel
stops before its transmittance would reach ``1e-4``, opacity-aware 3σ screen boxes, 8-px tiles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from vadgs.checks import check_finite, check_same_device, check_shape, check_size, checks_enabled
from vadgs.geometry.camera import Cameras, camera_centers
from vadgs.render.composite import composite_gaussians
from vadgs.render.projection import project_gaussians
from vadgs.render.sh import eval_sh
from vadgs.render.tiles import bin_gaussians

__all__ = ["GaussianRasterizer", "RasterConfig", "RenderOutput", "rasterize_gaussians"]


@dataclass(frozen=True)
class RasterConfig:
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

    near: float = 0.01
    far: float = 1e10
    eps2d: float = 0.3
    antialiased: bool = False
    alpha_max: float = 0.999
    alpha_min: float = 1.0 / 255.0
    transmittance_min: float = 1e-4
    tile_size: int = 8
    chunk_size: int = 32
    absgrad: bool = False
    backward: str = "manual"
    backend: str = "torch"

    def __post_init__(self) -> None:
        if not 0 < self.near < self.far:
            raise ValueError(f"near, far: expected 0 < near < far, got near={self.near}, far={self.far}")
        if self.eps2d < 0:
            raise ValueError(f"eps2d: expected >= 0, got {self.eps2d}")
        if not 0 < self.alpha_min < self.alpha_max < 1:
            raise ValueError(
                f"alpha_min, alpha_max: expected 0 < alpha_min < alpha_max < 1, "
                f"got {self.alpha_min}, {self.alpha_max}"
            )
        if not 0 <= self.transmittance_min < 1:
            raise ValueError(f"transmittance_min: expected in [0, 1), got {self.transmittance_min}")
        if self.tile_size < 1 or self.chunk_size < 1:
            raise ValueError(
                f"tile_size, chunk_size: expected positive ints, got {self.tile_size}, {self.chunk_size}"
            )
        if self.backward not in ("manual", "autograd"):
            raise ValueError(f"backward: expected 'manual' or 'autograd', got {self.backward!r}")
        if self.backend not in ("torch", "gsplat"):
            raise ValueError(f"backend: expected 'torch' or 'gsplat', got {self.backend!r}")


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


def _check_inputs(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    world_to_cam: torch.Tensor,
    K: torch.Tensor,
    background: torch.Tensor | None,
) -> dict[str, int]:
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
    for name, t in named:
        check_finite(t, name)
    if checks_enabled():
        f = K.detach()[:, [0, 1], [0, 1]]
        bad = ~(f > 0).all(-1)
        if bool(bad.any()):
            b = int(bad.nonzero()[0, 0])
            raise ValueError(
                f"K: expected positive focal lengths fx = K[b, 0, 0], fy = K[b, 1, 1] (an invertible "
                f"pinhole K), got fx={float(f[b, 0]):.4g}, fy={float(f[b, 1]):.4g} for camera b={b}"
            )
    if dims["N"] and checks_enabled():
        qn = quats.detach().norm(dim=-1)
        if bool((qn < 1e-12).any()):
            raise ValueError(f"quats: expected non-zero quaternions, got {int((qn < 1e-12).sum())} of norm 0")
        if bool((scales < 0).any()):
            raise ValueError(
                "scales: expected activated (non-negative) scales, got negative values; pass exp(log_scales)"
            )
        if bool(((opacities < 0) | (opacities > 1)).any()):
            raise ValueError(
                "opacities: expected activated opacities in [0, 1], got values outside; pass sigmoid(logits)"
            )
        limit = math.sqrt(torch.finfo(scales.dtype).max) / 1e3
        smax = float(scales.detach().max())
        if smax >= limit:
            raise ValueError(
                f"scales: expected < {limit:.3g} (larger overflows the {scales.dtype} covariance), "
                f"got max {smax:.3g}; pass exp(log_scales) of a sane model"
            )
    return dims


def rasterize_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    world_to_cam: torch.Tensor,
    K: torch.Tensor,
    image_size: tuple[int, int],
    background: torch.Tensor | None = None,
    sh_degree: int | None = None,
    config: RasterConfig | None = None,
) -> RenderOutput:
    """Render 3D Gaussians into a batch of pinhole cameras.

    With ``RasterConfig(backend="gsplat")`` the call goes to
    :func:`~vadgs.render.gsplat_backend.rasterize_gaussians_gsplat` (same inputs and outputs,
    gsplat's rasterizer; see ``docs/render.md``).

    Differentiable w.r.t. means, quats, scales, opacities, colors (RGB or SH), background,
    ``world_to_cam`` and ``K`` (through the projection). Radii, visibility and median ids are
    not; median depth is differentiable w.r.t. the depth of the median Gaussian.

    Args:
        means: ``(N, 3)`` world means.
        quats: ``(N, 4)`` ``wxyz`` rotations of any non-zero norm (normalised inside).
        scales: ``(N, 3)`` activated (positive) standard deviations; log-scales are the caller's
            business (``docs/conventions.md``).
        opacities: ``(N,)`` activated opacities in ``[0, 1]``.
        colors: ``(N, D)`` colours (any D, typically RGB in ``[0, 1]``) or ``(N, K, 3)``
            spherical-harmonics coefficients, ``K`` in 1, 4, 9, 16 (3DGS basis and +0.5 offset).
        world_to_cam: ``(B, 4, 4)`` world-to-camera transforms (OpenCV axes).
        K: ``(B, 3, 3)`` intrinsics (pixel centres at integers).
        image_size: ``(H, W)``.
        background: ``(D,)`` or ``(B, D)`` colour behind the Gaussians; black when None.
        sh_degree: SH degree to use, ``None`` for all coefficients given.
        config: :class:`RasterConfig`; defaults when None.

    Returns:
        The :class:`RenderOutput`. N = 0 renders the background (alpha and depth 0); Gaussians
        behind the cameras or outside the near/far range are culled (``visible`` False).

    Raises:
        ValueError: on mismatched shapes, devices or dtypes, non-finite values, zero
            quaternions, negative scales or opacities outside ``[0, 1]``, a ``K`` without
            positive focal lengths, or scales so large that the covariance overflows (the
            value checks; see :mod:`vadgs.checks` to switch them off).

    Shape:
        - means ``(N, 3)``, quats ``(N, 4)``, scales ``(N, 3)``, opacities ``(N,)``
        - colors ``(N, D)`` or ``(N, K, 3)``; world_to_cam ``(B, 4, 4)``; K ``(B, 3, 3)``
        - color ``(B, D, H, W)``, alpha / depth / median_depth ``(B, 1, H, W)``,
          normals ``(B, 3, H, W)``, radii ``(B, N, 2)``, visible ``(B, N)``

    Example:
        >>> means = torch.tensor([[0.0, 0.0, 4.0]])
        >>> K = torch.tensor([[[50.0, 0, 16.0], [0, 50.0, 12.0], [0, 0, 1]]])
        >>> out = rasterize_gaussians(means, torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.1),
        ...                           torch.tensor([0.5]), torch.tensor([[1.0, 0.5, 0.0]]),
        ...                           torch.eye(4)[None], K, (24, 32))
        >>> out.color.shape, round(out.alpha.max().item(), 3), round(out.depth[0, 0, 12, 16].item(), 3)
        (torch.Size([1, 3, 24, 32]), 0.5, 4.0)
    """
    cfg = config or RasterConfig()
    if cfg.backend == "gsplat":
        from vadgs.render.gsplat_backend import rasterize_gaussians_gsplat

        return rasterize_gaussians_gsplat(
            means, quats, scales, opacities, colors, world_to_cam, K, image_size, background, sh_degree, cfg
        )
    h, w = check_size(image_size)
    dims = _check_inputs(means, quats, scales, opacities, colors, world_to_cam, K, background)
    b, n, d = dims["B"], dims["N"], dims["D"]

    proj = project_gaussians(
        means,
        quats,
        scales,
        opacities,
        world_to_cam,
        K,
        (h, w),
        near=cfg.near,
        far=cfg.far,
        eps2d=cfg.eps2d,
        antialiased=cfg.antialiased,
        alpha_min=cfg.alpha_min,
    )
    if checks_enabled() and n:
        shown = proj.radii.detach().amax(-1) > 0
        bad = shown & ~(
            torch.isfinite(proj.conics.detach()).all(-1) & torch.isfinite(proj.means2d.detach()).all(-1)
        )
        if bool(bad.any()):
            raise ValueError(
                f"scales: {int(bad.sum())} Gaussian(s) project to a non-finite screen covariance "
                f"(overflow in {means.dtype}); e.g. index {int(bad.nonzero()[0, 1])}"
            )
    if colors.dim() == 3:
        dirs = F.normalize(means[None] - camera_centers(world_to_cam)[:, None], dim=-1)
        rgb = eval_sh(colors, dirs, sh_degree)
    else:
        if sh_degree is not None:
            raise ValueError(
                f"sh_degree: given ({sh_degree}) but colors are not SH, shape {tuple(colors.shape)}"
            )
        rgb = colors.expand(b, n, d)
    features = torch.cat([rgb, proj.depths[..., None], proj.normals], dim=-1)
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    absgrad = torch.zeros_like(means2d.detach()) if cfg.absgrad else None

    opac = torch.clamp_min(proj.opacities, torch.finfo(means.dtype).tiny)
    bins = bin_gaussians(
        means2d.detach(),
        proj.radii,
        proj.depths.detach(),
        (h, w),
        cfg.tile_size,
        conics=proj.conics.detach(),
        opacities=opac.detach(),
        alpha_min=cfg.alpha_min,
    )
    comp = composite_gaussians(
        means2d,
        proj.conics,
        opac,
        features,
        bins,
        (h, w),
        alpha_max=cfg.alpha_max,
        alpha_min=cfg.alpha_min,
        transmittance_min=cfg.transmittance_min,
        chunk_size=cfg.chunk_size,
        absgrad=absgrad,
        backward=cfg.backward,
    )
    t = comp.transmittance
    alpha = 1.0 - t
    color = comp.features[:, :d]
    if background is not None:
        bg = background if background.dim() == 2 else background.expand(b, d)
        color = color + t * bg[:, :, None, None]
    depth = comp.features[:, d : d + 1] / torch.clamp_min(alpha, 1e-10)
    normals = F.normalize(comp.features[:, d + 1 :], dim=1)
    ids = comp.median_ids
    # Index -1 (no median) picks the zero padded in front of the depths.
    median = torch.gather(F.pad(proj.depths, (1, 0)), 1, (ids + 1).reshape(b, h * w)).reshape(b, 1, h, w)
    visible = (proj.radii > 0).all(-1)
    return RenderOutput(
        color, alpha, depth, median, normals, ids, means2d, absgrad, proj.radii, visible, proj.depths
    )


class GaussianRasterizer(nn.Module):
    """Renders Gaussians into :class:`~vadgs.geometry.Cameras`. See :func:`rasterize_gaussians`.

    Args:
        config: the :class:`RasterConfig` (defaults when None).

    Example:
        >>> from vadgs.geometry.camera import Cameras
        >>> K = torch.tensor([[[50.0, 0, 15.5], [0, 50.0, 11.5], [0, 0, 1]]])
        >>> cams = Cameras(K, torch.eye(4)[None], (24, 32))
        >>> out = GaussianRasterizer()(torch.tensor([[0.0, 0.0, 4.0]]), torch.tensor([[1.0, 0, 0, 0]]),
        ...                            torch.full((1, 3), 0.1), torch.tensor([0.5]), torch.ones(1, 3), cams)
        >>> out.color.shape
        torch.Size([1, 3, 24, 32])
    """

    def __init__(self, config: RasterConfig | None = None) -> None:
        super().__init__()
        self.config = config or RasterConfig()

    def forward(
        self,
        means: torch.Tensor,
        quats: torch.Tensor,
        scales: torch.Tensor,
        opacities: torch.Tensor,
        colors: torch.Tensor,
        cameras: Cameras,
        background: torch.Tensor | None = None,
        sh_degree: int | None = None,
    ) -> RenderOutput:
        """Render into ``cameras`` (see :func:`rasterize_gaussians`)."""
        return rasterize_gaussians(
            means,
            quats,
            scales,
            opacities,
            colors,
            cameras.world_to_cam,
            cameras.K,
            cameras.image_size,
            background=background,
            sh_degree=sh_degree,
            config=self.config,
        )

    def extra_repr(self) -> str:
        """The config, shown by ``print(module)``."""
        return repr(self.config)
