"""gsplat as a rendering backend: :func:`rasterize_gaussians` inputs in, :class:`RenderOutput` out.

:func:`rasterize_gaussians_gsplat` takes exactly the inputs of
:func:`~vadgs.render.rasterize_gaussians` (activated parameters, ``wxyz`` quaternions, OpenCV
cameras with pixel centres at integers) and renders them with gsplat. The conventions it converts
(``docs/render.md``, "gsplat backend"):

- ``K``: gsplat puts pixel centres at ``i + 0.5``, so its ``cx, cy`` are ours plus 0.5; screen
  means come back in our convention (``meta["means2d"] - 0.5``, same gradient);
- quaternions (``wxyz``, any norm), scales (activated), opacities (activated) and
  ``world_to_cam`` (gsplat's ``viewmats``) are passed through unchanged;
- SH coefficients ``(N, K, 3)`` are evaluated here with gsplat's SH code at the direction
  *camera centre → mean* and ``max(0, SH + 0.5)``, as ``gsplat.rasterization`` does, so that the
  colours, the camera-frame normals (each Gaussian's shortest axis facing the camera, as
  :func:`~vadgs.render.project_gaussians`) and the depth go through one ``"RGB+ED"`` pass;
- ``background`` applies to the colour channels only (normals and depth composite over 0).

Two implementations, chosen by ``impl``: ``"cuda"`` calls ``gsplat.rasterization`` (needs CUDA
tensors and gsplat's compiled extension); ``"torch"`` runs the same pipeline with gsplat's
pure-torch reference functions (``gsplat.cuda._torch_impl``: covariance, projection, tile
intersection) and a torch transcription of gsplat's ``rasterize_to_pixels`` forward kernel
(:func:`rasterize_to_pixels_torch`; gsplat's own ``_rasterize_to_pixels`` calls a CUDA kernel),
differentiable by autograd. ``"auto"`` picks ``"cuda"`` for CUDA tensors and ``"torch"`` otherwise.
The torch implementation is a CPU reference for tests (its tile intersection is a Python loop over
Gaussians), not a fast path: use :func:`~vadgs.render.rasterize_gaussians` on the CPU.

Not produced by gsplat: ``median_depth`` (zeros) and ``median_ids`` (``-1``).
"""

from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn.functional as F

from vadgs.checks import check_size
from vadgs.geometry.camera import camera_centers, invert_rigid
from vadgs.geometry.rotation import quaternion_to_rotation
from vadgs.render.common import RasterConfig, RenderOutput, check_no_sh_degree, check_raster_inputs

__all__ = ["GSPLAT_TILE_SIZE", "rasterize_gaussians_gsplat", "rasterize_to_pixels_torch"]

#: gsplat's tile size (its default; ``RasterConfig.tile_size`` is the pure-torch renderer's).
GSPLAT_TILE_SIZE = 16
_ALPHA_THRESHOLD = 1.0 / 255.0  # gsplat's ALPHA_THRESHOLD
_IMPLS = ("auto", "cuda", "torch")


def _import_gsplat() -> Any:
    try:
        import gsplat
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError(
            "the gsplat backend needs gsplat: pip install 'gsplat>=1.4' (or RasterConfig(backend='torch'))"
        ) from e
    return gsplat


def _check_config(cfg: RasterConfig, impl: str) -> None:
    fixed = {"alpha_max": 0.999, "alpha_min": _ALPHA_THRESHOLD, "transmittance_min": 1e-4}
    for name, value in fixed.items():
        if not math.isclose(getattr(cfg, name), value, rel_tol=1e-9):
            raise ValueError(
                f"config.{name}: gsplat hard-codes {value:.6g}, got {getattr(cfg, name)!r}; "
                f"use RasterConfig(backend='torch') for other values"
            )
    if cfg.absgrad and impl == "torch":
        raise ValueError("config.absgrad: not available with impl='torch' (gsplat computes it in CUDA)")


def _shortest_axis_normals(
    means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, world_to_cam: torch.Tensor
) -> torch.Tensor:
    """``(B, N, 3)`` camera-frame shortest axes facing the camera (as ``project_gaussians``)."""
    rot_w2c = world_to_cam[:, None, :3, :3]
    p_cam = (rot_w2c @ means[None, :, :, None]).squeeze(-1) + world_to_cam[:, None, :3, 3]
    rot = quaternion_to_rotation(quats)
    idx = scales.detach().argmin(-1)
    axis = torch.gather(rot, 2, idx[:, None, None].expand(-1, 3, 1)).squeeze(-1)
    normals = (rot_w2c @ axis[None, :, :, None]).squeeze(-1)
    facing = (normals * p_cam).sum(-1, keepdim=True) > 0
    return torch.where(facing, -normals, normals)


def rasterize_to_pixels_torch(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    colors: torch.Tensor,
    opacities: torch.Tensor,
    width: int,
    height: int,
    tile_size: int,
    isect_offsets: torch.Tensor,
    flatten_ids: torch.Tensor,
    backgrounds: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The forward kernel of gsplat's ``rasterize_to_pixels`` (``RasterizeToPixels3DGSFwd.cu``) in torch.

    Per pixel (centre ``(j + 0.5, i + 0.5)``), over its tile's Gaussians in depth order:
    ``sigma = 0.5 (a dx² + c dy²) + b dx dy`` with ``d = mean - pixel``; skip if ``sigma < 0`` or
    ``alpha = min(0.999, o exp(-sigma)) < 1/255``; stop (exclusive) at the first Gaussian whose
    ``T (1 - alpha) <= 1e-4``. Differentiable by autograd w.r.t. means2d, conics, colors, opacities.

    Shape:
        means2d ``(C, N, 2)``, conics ``(C, N, 3)``, colors ``(C, N, D)``, opacities ``(C, N)``,
        isect_offsets ``(C, TH, TW)``, flatten_ids ``(M,)`` (indices into ``C * N``),
        backgrounds ``(C, D)``; returns colours ``(C, H, W, D)`` and alphas ``(C, H, W, 1)``.
    """
    c, n, d = colors.shape
    th, tw = isect_offsets.shape[-2:]
    flat_means = means2d.reshape(c * n, 2)
    flat_conics = conics.reshape(c * n, 3)
    flat_colors = colors.reshape(c * n, d)
    flat_opac = opacities.reshape(c * n)
    ends = torch.cat([isect_offsets.flatten()[1:], isect_offsets.new_tensor([flatten_ids.numel()])]).tolist()
    starts = isect_offsets.flatten().tolist()
    ar = torch.arange(tile_size, device=means2d.device, dtype=means2d.dtype)
    out_rows = []
    t_rows = []
    for tile in range(c * th * tw):
        s, e = starts[tile], ends[tile]
        ty, tx = (tile // tw) % th, tile % tw
        py = (ty * tile_size + ar + 0.5)[:, None].expand(tile_size, tile_size).reshape(-1)
        px = (tx * tile_size + ar + 0.5)[None, :].expand(tile_size, tile_size).reshape(-1)
        if e <= s:
            out_rows.append(flat_colors.new_zeros(tile_size * tile_size, d))
            t_rows.append(flat_colors.new_ones(tile_size * tile_size))
            continue
        ids = flatten_ids[s:e].long()
        mu, con, op = flat_means[ids], flat_conics[ids], flat_opac[ids]
        dx = mu[None, :, 0] - px[:, None]  # (P, L)
        dy = mu[None, :, 1] - py[:, None]
        sigma = 0.5 * (con[:, 0] * dx * dx + con[:, 2] * dy * dy) + con[:, 1] * dx * dy
        alpha = torch.clamp_max(op * torch.exp(-sigma), 0.999)
        valid = (sigma >= 0) & (alpha >= _ALPHA_THRESHOLD)
        alpha = torch.where(valid, alpha, torch.zeros_like(alpha))
        one_minus = 1.0 - alpha
        trans = torch.cumprod(torch.cat([torch.ones_like(one_minus[:, :1]), one_minus[:, :-1]], 1), 1)
        stop = valid & (trans * one_minus <= 1e-4)
        done = torch.cummax(stop.to(torch.uint8), dim=1).values.bool()  # the stopping one is excluded
        weights = torch.where(done, torch.zeros_like(alpha), alpha * trans)
        out_rows.append(weights @ flat_colors[ids])
        t_rows.append(torch.where(done, torch.ones_like(one_minus), one_minus).prod(1))
    img = torch.stack(out_rows).reshape(c, th, tw, tile_size, tile_size, d)
    img = img.permute(0, 1, 3, 2, 4, 5).reshape(c, th * tile_size, tw * tile_size, d)[:, :height, :width]
    t = torch.stack(t_rows).reshape(c, th, tw, tile_size, tile_size)
    t = t.permute(0, 1, 3, 2, 4).reshape(c, th * tile_size, tw * tile_size)[:, :height, :width, None]
    if backgrounds is not None:
        img = img + t * backgrounds[:, None, None, :]
    return img, 1.0 - t


def _culled(
    means: torch.Tensor, viewmats: torch.Tensor, near_plane: float, far_plane: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Which Gaussians each camera culls, and where to project them instead.

    Returns ``(C, N)`` the Gaussians outside ``(near_plane, far_plane)`` of each camera, and
    ``(C, 3)`` a world point straight ahead of each camera at a depth between the two.
    """
    z = means @ viewmats[:, 2, :3].T + viewmats[:, 2, 3]  # (N, C)
    culled = ((z <= near_plane) | (z >= far_plane)).T
    cam_to_world = invert_rigid(viewmats)
    ahead = cam_to_world[:, :3, 3] + cam_to_world[:, :3, 2] * (0.5 * (near_plane + far_plane))
    return culled, ahead


def _gsplat_torch_rasterization(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    tile_size: int = GSPLAT_TILE_SIZE,
    backgrounds: torch.Tensor | None = None,
    rasterize_mode: str = "classic",
) -> tuple[torch.Tensor, torch.Tensor, dict[str, Any]]:
    """``gsplat.rasterization(..., packed=False, render_mode="RGB+ED", sh_degree=None)`` in pure torch.

    gsplat's pure-torch reference functions for the covariances, the projection and the tile
    intersection, :func:`rasterize_to_pixels_torch` for the compositing. The radii follow the CUDA
    projection (opacity-aware extent ``min(3.33, sqrt(2 log(o / (1/255))))`` and culling of
    ``o < 1/255``; the torch reference uses 3.33 for every Gaussian) so that ``meta["radii"]`` is
    CUDA's. Colours are per camera, ``(C, N, D)``, already activated; gsplat pixel convention.

    Returns:
        ``(render (C, H, W, D + 1), alphas (C, H, W, 1), meta)`` with the expected depth last and
        ``meta``'s ``means2d``, ``radii``, ``depths``, ``conics``, ``opacities``, ``width``,
        ``height``, ``n_cameras``, as gsplat's.
    """
    from gsplat.cuda._torch_impl import (
        _fully_fused_projection,
        _isect_offset_encode,
        _isect_tiles,
        _quat_scale_to_covar_preci,
    )

    c, n = viewmats.shape[0], means.shape[0]
    covars, _ = _quat_scale_to_covar_preci(quats, scales, compute_covar=True, compute_preci=False)
    # CUDA culls a Gaussian outside (near_plane, far_plane) before projecting it, so it gets no
    # gradient; the torch reference projects it all the same, and one exactly in a camera's plane
    # (z = 0) divides by zero: 0 * inf = NaN in the backward (seen on the bundled sample at step
    # 2). Such a Gaussian is projected, per camera, from a point straight ahead instead (no
    # gradient reaches it) and culled after, as CUDA does.
    culled, ahead = _culled(means.detach(), viewmats, near_plane, far_plane)
    safe_means = torch.where(culled[..., None], ahead[:, None], means[None])
    safe_covars = torch.where(culled[..., None, None], torch.eye(3).to(covars), covars[None])
    radii, means2d, depths, conics, comp = _fully_fused_projection(
        safe_means,
        safe_covars,
        viewmats[:, None],
        Ks[:, None],
        width,
        height,
        eps2d=eps2d,
        near_plane=near_plane,
        far_plane=far_plane,
        calc_compensations=rasterize_mode == "antialiased",
    )
    radii, means2d, depths, conics = (x.squeeze(1) for x in (radii, means2d, depths, conics))
    comp = comp.squeeze(1) if comp is not None else None
    radii = torch.where(culled[..., None], torch.zeros_like(radii), radii)
    opac = opacities[None].expand(c, n)
    if comp is not None:
        opac = opac * comp
    with torch.no_grad():  # CUDA's opacity-aware radii (ProjectionEWA3DGSFused.cu)
        a, b, cc = conics.unbind(-1)
        det_inv = a * cc - b * b
        cov_xx, cov_yy = cc / det_inv, a / det_inv
        extend = torch.sqrt(2.0 * torch.log(torch.clamp_min(opac / _ALPHA_THRESHOLD, 1.0))).clamp_max(3.33)
        rx, ry = torch.ceil(extend * cov_xx.sqrt()), torch.ceil(extend * cov_yy.sqrt())
        u, v = means2d.unbind(-1)
        ok = (radii > 0).all(-1) & (opac >= _ALPHA_THRESHOLD) & ((rx > 0) | (ry > 0))
        ok &= (u + rx > 0) & (u - rx < width) & (v + ry > 0) & (v - ry < height)
        radii = torch.where(ok[..., None], torch.stack([rx, ry], -1), torch.zeros_like(means2d)).int()
    feats = torch.cat([colors, depths[..., None]], -1)
    if backgrounds is not None:
        backgrounds = torch.cat([backgrounds, backgrounds.new_zeros(c, 1)], -1)
    tile_w, tile_h = math.ceil(width / tile_size), math.ceil(height / tile_size)
    _, isect_ids, flatten_ids = _isect_tiles(
        means2d.detach(), radii, depths.detach(), tile_size, tile_w, tile_h
    )
    offsets = _isect_offset_encode(isect_ids, c, tile_w, tile_h).reshape(c, tile_h, tile_w)
    render, alphas = rasterize_to_pixels_torch(
        means2d, conics, feats, opac, width, height, tile_size, offsets, flatten_ids, backgrounds
    )
    render = torch.cat([render[..., :-1], render[..., -1:] / alphas.clamp(min=1e-10)], -1)
    meta = {
        "means2d": means2d,
        "radii": radii,
        "depths": depths,
        "conics": conics,
        "opacities": opac,
        "width": width,
        "height": height,
        "tile_size": tile_size,
        "n_cameras": c,
    }
    return render, alphas, meta


def rasterize_gaussians_gsplat(
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
    impl: str = "auto",
) -> RenderOutput:
    """Render like :func:`~vadgs.render.rasterize_gaussians`, with gsplat (see the module docstring).

    Same arguments, conventions and outputs, except: ``median_depth`` is zeros and ``median_ids``
    is ``-1`` (gsplat has no median); ``config.tile_size``, ``chunk_size`` and ``backward`` are the
    pure-torch renderer's and are ignored (gsplat: 16-px tiles, its own backward); ``near``,
    ``far``, ``eps2d``, ``antialiased`` and ``absgrad`` (``impl="cuda"`` only) are passed on.
    Differentiable w.r.t. means, quats, scales, opacities, colours / SH, background and
    ``world_to_cam`` (gsplat is not differentiable w.r.t. ``K``). ``means2d`` is a leaf copy of
    gsplat's screen means in our pixel convention: after ``backward()`` its ``.grad`` is gsplat's
    ``means2d`` gradient in pixels (the densification statistic, as the pure-torch renderer's),
    but a loss on ``means2d`` itself does not reach the Gaussians.

    Args:
        means: ``(N, 3)`` world means.
        quats: ``(N, 4)`` ``wxyz``, any non-zero norm.
        scales: ``(N, 3)`` activated scales.
        opacities: ``(N,)`` activated opacities.
        colors: ``(N, D)`` colours or ``(N, K, 3)`` SH coefficients.
        world_to_cam: ``(B, 4, 4)`` (gsplat's ``viewmats``).
        K: ``(B, 3, 3)`` intrinsics, pixel centres at integers.
        image_size: ``(H, W)``.
        background: ``(D,)`` or ``(B, D)``; black when None.
        sh_degree: SH degree to use, ``None`` for all coefficients given.
        config: :class:`~vadgs.render.RasterConfig` (``backend`` is not read here).
        impl: ``"auto"`` (CUDA tensors: ``"cuda"``, else ``"torch"``), ``"cuda"``
            (``gsplat.rasterization``) or ``"torch"`` (the pure-torch reference pipeline).

    Returns:
        The :class:`~vadgs.render.RenderOutput`.

    Raises:
        ImportError: gsplat is not installed.
        ValueError: bad inputs (as :func:`~vadgs.render.rasterize_gaussians`), an unknown
            ``impl``, ``impl="cuda"`` with tensors not on CUDA, a non-float32 dtype with
            ``impl="cuda"``, or ``config`` values gsplat hard-codes set otherwise
            (``alpha_max`` 0.999, ``alpha_min`` 1/255, ``transmittance_min`` 1e-4).

    Example:
        >>> K = torch.tensor([[[50.0, 0, 16.0], [0, 50.0, 12.0], [0, 0, 1]]])
        >>> out = rasterize_gaussians_gsplat(
        ...     torch.tensor([[0.0, 0.0, 4.0]]), torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.1),
        ...     torch.tensor([0.5]), torch.tensor([[1.0, 0.5, 0.0]]), torch.eye(4)[None], K, (24, 32))
        >>> round(out.alpha.max().item(), 3), round(out.depth[0, 0, 12, 16].item(), 3)
        (0.5, 4.0)
        >>> out.means2d[0, 0].tolist()
        [16.0, 12.0]
    """
    cfg = config or RasterConfig()
    if impl not in _IMPLS:
        raise ValueError(f"impl: expected one of {_IMPLS}, got {impl!r}")
    h, w = check_size(image_size)
    dims = check_raster_inputs(means, quats, scales, opacities, colors, world_to_cam, K, background)
    b, n, d = dims["B"], dims["N"], dims["D"]
    if impl == "auto":
        impl = "cuda" if means.is_cuda else "torch"
    if impl == "cuda" and not means.is_cuda:
        raise ValueError(f"impl='cuda': expected CUDA tensors, got device {means.device}")
    if impl == "cuda" and means.dtype != torch.float32:
        raise ValueError(f"impl='cuda': gsplat's CUDA kernels take float32, got {means.dtype}")
    _check_config(cfg, impl)
    gsplat = _import_gsplat()

    # gsplat's pixel centres are at i + 0.5: shift the principal point by half a pixel.
    shift = torch.zeros_like(K)
    shift[:, 0, 2] = 0.5
    shift[:, 1, 2] = 0.5
    ks = K + shift
    if colors.dim() == 3:
        num = colors.shape[1]
        if math.isqrt(num) ** 2 != num:
            raise ValueError(f"colors: expected SH (N, K, 3) with K = (degree + 1)^2, got K = {num}")
        degree = math.isqrt(num) - 1 if sh_degree is None else int(sh_degree)
        if not 0 <= degree <= math.isqrt(num) - 1:
            raise ValueError(
                f"sh_degree: expected in [0, {math.isqrt(num) - 1}] for K = {num}, got {sh_degree}"
            )
        dirs = means[None] - camera_centers(world_to_cam)[:, None]  # (B, N, 3), normalised inside
        coeffs = colors[None].expand(b, -1, -1, -1)
        if impl == "cuda":
            sh = gsplat.spherical_harmonics(degree, dirs, coeffs)
        else:
            from gsplat.cuda._torch_impl import _spherical_harmonics

            sh = _spherical_harmonics(degree, dirs, coeffs)
        rgb = torch.clamp_min(sh + 0.5, 0.0)
    else:
        check_no_sh_degree(colors, sh_degree)
        rgb = colors[None].expand(b, n, d)
    normals = _shortest_axis_normals(means, quats, scales, world_to_cam)
    feats = torch.cat([rgb, normals], -1)  # (B, N, D + 3)
    bgs = None
    if background is not None:
        bg = background if background.dim() == 2 else background.expand(b, d)
        bgs = torch.cat([bg, bg.new_zeros(b, 3)], -1)
    mode = "antialiased" if cfg.antialiased else "classic"
    if impl == "cuda":
        render, alphas, meta = gsplat.rasterization(
            means,
            quats,
            scales,
            opacities,
            feats,
            world_to_cam,
            ks,
            w,
            h,
            near_plane=cfg.near,
            far_plane=cfg.far,
            eps2d=cfg.eps2d,
            packed=False,
            tile_size=GSPLAT_TILE_SIZE,
            backgrounds=bgs,
            render_mode="RGB+ED",
            absgrad=cfg.absgrad,
            rasterize_mode=mode,
        )
    else:
        render, alphas, meta = _gsplat_torch_rasterization(
            means, quats, scales, opacities, feats, world_to_cam, ks, w, h,
            near_plane=cfg.near, far_plane=cfg.far, eps2d=cfg.eps2d, backgrounds=bgs, rasterize_mode=mode,
        )  # fmt: skip
    render = render.permute(0, 3, 1, 2)
    alpha = alphas.permute(0, 3, 1, 2)
    # Our pixel centres: a leaf copy of gsplat's means2d, 0.5 px lower, whose .grad (and absgrad)
    # receive gsplat's means2d gradient during backward (gradients do not flow back through it).
    g_means2d = meta["means2d"]
    means2d = (g_means2d.detach() - 0.5).requires_grad_(g_means2d.requires_grad)
    absgrad = torch.zeros_like(means2d.detach()) if cfg.absgrad and g_means2d.requires_grad else None
    if g_means2d.requires_grad:

        def _collect(grad: torch.Tensor) -> None:
            means2d.grad = grad.detach().clone() if means2d.grad is None else means2d.grad + grad.detach()
            found = getattr(g_means2d, "absgrad", None)
            if absgrad is not None and found is not None:
                absgrad.add_(found)

        g_means2d.register_hook(_collect)
    radii = meta["radii"].to(torch.int32)
    return RenderOutput(
        color=render[:, :d],
        alpha=alpha,
        depth=render[:, d + 3 :],
        median_depth=torch.zeros_like(alpha.detach()),
        median_ids=torch.full((b, h, w), -1, dtype=torch.int64, device=means.device),
        normals=F.normalize(render[:, d : d + 3], dim=1),
        means2d=means2d,
        means2d_absgrad=absgrad,
        radii=radii,
        visible=(radii > 0).all(-1),
        depths=meta["depths"],
    )
