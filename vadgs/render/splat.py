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

import torch
import torch.nn.functional as F
from torch import nn

from vadgs.checks import check_size, checks_enabled
from vadgs.geometry.camera import Cameras, camera_centers
from vadgs.render.common import RasterConfig, RenderOutput, check_no_sh_degree, check_raster_inputs
from vadgs.render.composite import CompositeOutput, composite_gaussians
from vadgs.render.projection import project_gaussians
from vadgs.render.sh import eval_sh
from vadgs.render.tiles import bin_gaussians

__all__ = ["GaussianRasterizer", "rasterize_gaussians"]


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
    hard_depth: bool = False,
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
        hard_depth: also composite the *hard* depth (every opacity fixed to 1, no gradient to the
            opacities; ``hard_depth`` of the output) in the same pass: the same projection, and
            each camera's tiles walked a second time as a camera of their own (boxes at opacity
            1) in the same chunk loop, forward and backward. Equals a second render with
            ``opacities`` of ones (up to rounding), whose ``means2d`` gradient it leaves out of
            ``means2d.grad`` (the densification statistic). Torch backend, no antialiasing.

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
        if hard_depth:
            raise ValueError("hard_depth: expected RasterConfig(backend='torch'), got backend='gsplat'")
        from vadgs.render.gsplat_backend import rasterize_gaussians_gsplat

        return rasterize_gaussians_gsplat(
            means, quats, scales, opacities, colors, world_to_cam, K, image_size, background, sh_degree, cfg
        )
    h, w = check_size(image_size)
    dims = check_raster_inputs(means, quats, scales, opacities, colors, world_to_cam, K, background)
    b, n, d = dims["B"], dims["N"], dims["D"]
    if hard_depth and cfg.antialiased:
        raise ValueError("hard_depth: expected RasterConfig(antialiased=False), got antialiased=True")

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
        opaque=hard_depth,
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
        check_no_sh_degree(colors, sh_degree)
        rgb = colors.expand(b, n, d)
    features = torch.cat([rgb, proj.depths[..., None], proj.normals], dim=-1)
    means2d = proj.means2d
    opac = torch.clamp_min(proj.opacities, torch.finfo(means.dtype).tiny)
    conics, depths, radii = proj.conics, proj.depths, proj.radii
    absgrad = torch.zeros_like(means2d.detach()) if cfg.absgrad else None
    composited = means2d
    if hard_depth:
        # the hard pass: cameras B..2B-1, the same screen Gaussians at opacity 1 (only depth is
        # read); means2d is a node of its own so that its gradient is the colour pass's only
        means2d = means2d.clone()
        composited = torch.cat([means2d, proj.means2d])
        opac = torch.cat([opac, torch.ones_like(opac)])
        conics, depths = conics.repeat(2, 1, 1), depths.repeat(2, 1)
        assert proj.opaque_radii is not None  # projected with opaque=hard_depth
        radii = torch.cat([radii, proj.opaque_radii])
        features = features.repeat(2, 1, 1)
        absgrad = None if absgrad is None else absgrad.repeat(2, 1, 1)
    if means2d.requires_grad:
        means2d.retain_grad()

    bins = bin_gaussians(
        composited.detach(),
        radii,
        depths.detach(),
        (h, w),
        cfg.tile_size,
        conics=conics.detach(),
        opacities=opac.detach(),
        alpha_min=cfg.alpha_min,
    )
    comp = composite_gaussians(
        composited,
        conics,
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
    hard = None
    if hard_depth:
        t_hard = comp.transmittance[b:]
        hard = comp.features[b:, d : d + 1] / torch.clamp_min(1.0 - t_hard, 1e-10)
        comp = CompositeOutput(comp.features[:b], comp.transmittance[:b], comp.median_ids[:b])
        absgrad = None if absgrad is None else absgrad[:b]
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
        color, alpha, depth, median, normals, ids, means2d, absgrad, proj.radii, visible, proj.depths, hard
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
