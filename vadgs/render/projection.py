r"""EWA projection of 3D Gaussians to screen-space 2D Gaussians (gsplat's conventions).

A Gaussian with mean ``mu``, rotation ``R`` (from a ``wxyz`` quaternion) and scales ``s`` has
world covariance ``Sigma = R diag(s)^2 R^T``. With the camera rotation ``W`` and the Jacobian
``J`` of the pinhole projection at the mean (camera frame), its screen covariance is

.. math::

    \Sigma' = J W \Sigma W^T J^T + \epsilon_{2d} I, \qquad
    J = \begin{pmatrix} f_x / z & 0 & -f_x t_x / z^2 \\ 0 & f_y / z & -f_y t_y / z^2 \end{pmatrix}

where ``eps2d = 0.3`` px² is the low-pass filter of 3DGS and ``(t_x, t_y)`` is the camera-frame
mean with ``x / z`` and ``y / z`` clamped to 1.3 times the half field of view (gsplat's guard
against exploding Jacobians at the image border). In *antialiased* mode (Mip-Splatting) the
opacity is multiplied by ``sqrt(det(Sigma'_raw) / det(Sigma'))`` so that the low-pass filter
does not brighten small Gaussians.

The screen extent is gsplat's opacity-aware "3σ" box: a pixel can only receive
``alpha >= alpha_min`` (1/255) where ``0.5 d^T Sigma'^{-1} d <= log(opacity / alpha_min)``, so the
box half-sizes are ``ceil(e * sqrt(Sigma'_xx))`` and ``ceil(e * sqrt(Sigma'_yy))`` with
``e = sqrt(2 log(opacity / alpha_min))`` (≤ 3.33 for opacity ≤ 1). The box is exact, not a
truncation: every pixel outside it would have been skipped by the compositor anyway.

Pixel coordinates follow ``docs/conventions.md``: integer coordinates are pixel centres, so
``u = fx x / z + cx`` with the project's ``K`` (gsplat puts centres at ``i + 0.5``; its ``cx`` is
ours plus 0.5).
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from vadgs.checks import check_shape, check_size
from vadgs.geometry.rotation import quaternion_to_rotation

__all__ = ["ProjectedGaussians", "project_gaussians"]


class ProjectedGaussians(NamedTuple):
    """Screen-space Gaussians, one row per camera.

    Attributes:
        means2d: ``(B, N, 2)`` projected means ``(x, y)`` in pixels (pixel centres at integers).
        conics: ``(B, N, 3)`` inverse screen covariance ``(a, b, c)``: the Gaussian falls off as
            ``exp(-0.5 (a dx^2 + c dy^2) - b dx dy)``.
        depths: ``(B, N)`` camera-frame z of the means.
        opacities: ``(B, N)`` opacities, times the antialiasing compensation when enabled.
        normals: ``(B, N, 3)`` unit shortest axis in the camera frame, oriented towards the
            camera (``n · mean_cam <= 0``).
        radii: ``(B, N, 2)`` int32 half sizes (x, y) in pixels of the screen box; ``0`` where
            culled (behind the near plane, beyond the far plane, too transparent, off screen).
        opaque_radii: with ``opaque=True``, the ``radii`` every Gaussian would have at opacity 1
            (the box of a render with every opacity fixed to 1, e.g. the hard depth); else None.
    """

    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    opacities: torch.Tensor
    normals: torch.Tensor
    radii: torch.Tensor
    opaque_radii: torch.Tensor | None = None


def project_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    world_to_cam: torch.Tensor,
    K: torch.Tensor,
    image_size: tuple[int, int],
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    antialiased: bool = False,
    alpha_min: float = 1.0 / 255.0,
    opaque: bool = False,
) -> ProjectedGaussians:
    """Project 3D Gaussians into each camera (EWA splatting, see the module docstring).

    Differentiable w.r.t. means, quats, scales, opacities, ``world_to_cam`` and ``K``; the radii
    are not. Culled Gaussians keep finite (meaningless) values and get zero gradient.

    Args:
        means: ``(N, 3)`` world means.
        quats: ``(N, 4)`` ``wxyz`` rotations, any non-zero norm.
        scales: ``(N, 3)`` activated (positive) standard deviations along the local axes.
        opacities: ``(N,)`` activated opacities in ``[0, 1]``.
        world_to_cam: ``(B, 4, 4)``.
        K: ``(B, 3, 3)``.
        image_size: ``(H, W)``.
        near: Gaussians with ``z <= near`` are culled.
        far: Gaussians with ``z >= far`` are culled.
        eps2d: screen-space low-pass variance added to the covariance, px².
        antialiased: Mip-Splatting opacity compensation.
        alpha_min: the compositor's alpha threshold; sets the screen box.
        opaque: also return ``opaque_radii``, the boxes at opacity 1 (no antialiasing).

    Returns:
        The :class:`ProjectedGaussians`.

    Example:
        >>> K = torch.tensor([[[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]]])
        >>> p = project_gaussians(torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[1.0, 0, 0, 0]]),
        ...                       torch.full((1, 3), 0.02), torch.tensor([0.9]), torch.eye(4)[None], K,
        ...                       (48, 64))
        >>> p.means2d, p.radii
        (tensor([[[31.5000, 23.5000]]]), tensor([[[4, 4]]], dtype=torch.int32))
    """
    dims = check_shape(means, "means", ("N", 3))
    check_shape(quats, "quats", ("N", 4), dims)
    check_shape(scales, "scales", ("N", 3), dims)
    check_shape(opacities, "opacities", ("N",), dims)
    check_shape(world_to_cam, "world_to_cam", ("B", 4, 4), dims)
    check_shape(K, "K", ("B", 3, 3), dims)
    h, w = check_size(image_size)

    rot_w2c = world_to_cam[:, None, :3, :3]  # (B, 1, 3, 3)
    p_cam = (rot_w2c @ means[None, :, :, None]).squeeze(-1) + world_to_cam[:, None, :3, 3]  # (B, N, 3)
    x, y, z = p_cam.unbind(-1)
    in_depth = (z > near) & (z < far)
    z = torch.where(in_depth, z, torch.ones_like(z))  # guard divisions for culled Gaussians

    fx, fy = K[:, 0, 0, None], K[:, 1, 1, None]
    cx, cy = K[:, 0, 2, None], K[:, 1, 2, None]
    rz = 1.0 / z
    u = fx * x * rz + cx
    v = fy * y * rz + cy

    # Jacobian with gsplat's clamp of the view ray to 1.3x the half field of view. Our pixel
    # centres are at integers, so the image spans [-0.5, W - 0.5] and the bounds use cx + 0.5.
    tan_x, tan_y = 0.5 * w / fx, 0.5 * h / fy
    lim_xp, lim_xn = (w - (cx + 0.5)) / fx + 0.3 * tan_x, (cx + 0.5) / fx + 0.3 * tan_x
    lim_yp, lim_yn = (h - (cy + 0.5)) / fy + 0.3 * tan_y, (cy + 0.5) / fy + 0.3 * tan_y
    tx = torch.minimum(torch.maximum(x * rz, -lim_xn), lim_xp)
    ty = torch.minimum(torch.maximum(y * rz, -lim_yn), lim_yp)

    # A = J W R diag(s): screen covariance = A A^T.
    rot = quaternion_to_rotation(quats)  # (N, 3, 3)
    m = (rot_w2c @ (rot * scales[:, None, :])[None]).unbind(-2)  # rows (B, N, 3) of W R S
    a0 = (fx * rz)[..., None] * m[0] - (fx * tx * rz)[..., None] * m[2]
    a1 = (fy * rz)[..., None] * m[1] - (fy * ty * rz)[..., None] * m[2]
    cov_xx = (a0 * a0).sum(-1)
    cov_xy = (a0 * a1).sum(-1)
    cov_yy = (a1 * a1).sum(-1)
    det_raw = cov_xx * cov_yy - cov_xy * cov_xy
    cov_xx = cov_xx + eps2d
    cov_yy = cov_yy + eps2d
    det = cov_xx * cov_yy - cov_xy * cov_xy
    ok = in_depth & (det > 0)
    det = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([cov_yy / det, -cov_xy / det, cov_xx / det], dim=-1)

    opac = opacities.expand_as(det)
    if antialiased:
        opac = opac * torch.sqrt(torch.clamp_min(det_raw / det, 0.0))

    # Shortest axis of each Gaussian, in the camera frame, facing the camera.
    idx = scales.detach().argmin(-1)
    axis = torch.gather(rot, 2, idx[:, None, None].expand(-1, 3, 1)).squeeze(-1)  # (N, 3)
    normals = (rot_w2c @ axis[None, :, :, None]).squeeze(-1)
    facing = (normals * p_cam).sum(-1, keepdim=True) > 0
    normals = torch.where(facing, -normals, normals)

    with torch.no_grad():

        def box(o: torch.Tensor) -> torch.Tensor:
            keep = ok & (o >= alpha_min)
            extend = torch.sqrt(2.0 * torch.log(torch.clamp_min(o / alpha_min, 1.0)))
            rx = torch.ceil(extend * torch.sqrt(torch.clamp_min(cov_xx, 0.0)))
            ry = torch.ceil(extend * torch.sqrt(torch.clamp_min(cov_yy, 0.0)))
            keep = keep & (u + rx >= 0) & (u - rx <= w - 1) & (v + ry >= 0) & (v - ry <= h - 1)
            keep = keep & (rx > 0) & (ry > 0) & torch.isfinite(u) & torch.isfinite(v)
            radii = torch.stack([rx.clamp_max(2.0**30), ry.clamp_max(2.0**30)], dim=-1)
            return torch.where(keep[..., None], radii, torch.zeros_like(radii)).to(torch.int32)

        radii = box(opac)
        opaque_radii = box(torch.ones_like(opac)) if opaque else None

    means2d = torch.stack([u, v], dim=-1)
    return ProjectedGaussians(means2d, conics, p_cam[..., 2], opac, normals, radii, opaque_radii)
