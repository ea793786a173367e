"""Real spherical harmonics up to degree 3, in the basis of 3DGS and gsplat.

A Gaussian's view-dependent colour is ``c(d) = max(0, sum_k Y_k(d) f_k + 0.5)`` with
``Y_k`` the real SH basis below, ``f_k`` its ``(K, 3)`` coefficients (``K = (degree + 1)^2``)
and ``d`` the unit direction from the camera centre to the Gaussian's mean, in world
coordinates. The ``+0.5`` offset and the clamp at zero are those of 3DGS and gsplat, so
coefficients move between vadgs and those codebases unchanged (``f_0 = (rgb - 0.5) / C0``).

:func:`rotate_sh` turns a Gaussian's coefficients with its frame (:func:`sh_rotation`: the exact
rotation of each degree's coefficients), e.g. to export a moving object's Gaussians in the world.
"""

from __future__ import annotations

import math

import torch

from vadgs.checks import check_shape

__all__ = [
    "SH_C0",
    "eval_sh",
    "num_sh_bases",
    "rgb_to_sh",
    "rotate_sh",
    "sh_basis",
    "sh_rotation",
    "sh_to_rgb",
]

SH_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients of a degree, ``(degree + 1)^2``.

    Example:
        >>> [num_sh_bases(d) for d in range(4)]
        [1, 4, 9, 16]
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"degree: expected 0 to 3, got {degree}")
    return (degree + 1) ** 2


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Evaluate the real SH basis of 3DGS / gsplat at unit directions.

    Differentiable w.r.t. ``dirs``.

    Args:
        dirs: ``(*, 3)`` unit directions.
        degree: 0 to 3.

    Returns:
        ``(*, (degree + 1)^2)`` basis values.

    Example:
        >>> [round(v, 4) for v in sh_basis(torch.tensor([0.0, 1.0, 0.0]), 1).abs().tolist()]
        [0.2821, 0.4886, 0.0, 0.0]
    """
    num_sh_bases(degree)
    check_shape(dirs, "dirs", ("*", 3))
    # Each basis function is the same float32 expression as written out term by term (3DGS's
    # order of operations: e.g. C * y * (3 xx - yy) is (C y)(3 xx - yy)), evaluated for many terms
    # at once: gathers of columns and column-wise products with constant rows.
    out = [torch.full_like(dirs[..., :1], SH_C0)]
    if degree > 0:
        out.append(_cols(dirs, (1, 2, 0)) * _row(dirs, (-_C1, _C1, -_C1)))
    if degree > 1:
        # D: x y z xx yy zz xy yz xz (columns 0 to 8)
        d = torch.cat([dirs, _cols(dirs, (0, 1, 2, 0, 1, 0)) * _cols(dirs, (0, 1, 2, 1, 2, 2))], -1)
        r = _cols(d, (5, 3)) * _row(d, (2.0, 1.0)) - _cols(d, (3, 4))  # 2 zz - xx, xx - yy
        a = r[..., :1] - d[..., 4:5]  # (2 zz - xx) - yy
        out.append(torch.cat([d[..., 6:8], a, d[..., 8:9], r[..., 1:]], -1) * _row(d, _C2))
    if degree > 2:
        # S: 3 xx, 4 zz, 2 zz, 3 yy (columns 9 to 12 of E)
        e = torch.cat([d, _cols(d, (3, 5, 5, 4)) * _row(d, (3.0, 4.0, 2.0, 3.0))], -1)
        m = _cols(e, (9, 10, 11, 3)) - _cols(e, (4, 3, 9, 12))  # 3xx - yy, 4zz - xx, 2zz - 3xx, xx - 3yy
        n = m[..., 1:3] - _cols(e, (4, 12))  # (4zz - xx) - yy, (2zz - 3xx) - 3yy
        right = torch.cat([m[..., :1], d[..., 2:3], n, n[..., :1], r[..., 1:], m[..., 3:]], -1)
        left = _cols(d, (1, 6, 1, 2, 0, 2, 0)) * _row(d, _C3)  # C y, C xy, C y, C z, C x, C z, C x
        out.append(left * right)
    return torch.cat(out, -1)


def _cols(x: torch.Tensor, idx: tuple[int, ...]) -> torch.Tensor:
    """Columns ``idx`` of ``x``'s last axis (a gather)."""
    return x[..., list(idx)]


_ROWS: dict[tuple[tuple[float, ...], torch.device, torch.dtype], torch.Tensor] = {}


def _row(x: torch.Tensor, values: tuple[float, ...]) -> torch.Tensor:
    """The constants ``values`` as a row on ``x``'s device and dtype, made once (no copy a call)."""
    key = (tuple(values), x.device, x.dtype)
    row = _ROWS.get(key)
    if row is None:
        row = _ROWS[key] = torch.tensor(values, device=x.device, dtype=x.dtype)
    return row


def eval_sh(
    coeffs: torch.Tensor, dirs: torch.Tensor, degree: int | None = None, max_value: float | None = None
) -> torch.Tensor:
    r"""View-dependent colours from SH coefficients: ``max(0, sum_k Y_k(d) f_k + 0.5)``.

    Only the first ``(degree + 1)^2`` coefficients are used, so a model can raise its degree
    during training (as 3DGS does) without reallocating. Differentiable w.r.t. ``coeffs`` and
    ``dirs`` (the clamp at zero has zero gradient below it).

    .. math::

        c(\mathbf{d}) = \max\big(0, \tfrac12 + \textstyle\sum_k Y_k(\mathbf{d})\,\mathbf{f}_k\big)

    Args:
        coeffs: ``(N, K, C)`` coefficients, ``K`` a square number ≤ 16.
        dirs: ``(*, N, 3)`` unit viewing directions (camera centre to Gaussian, world frame).
        degree: SH degree to evaluate; ``None`` uses all of ``K``.
        max_value: also clamped from above at this value (in the same kernel), e.g. ``1.0``.

    Returns:
        ``(*, N, C)`` colours.

    Example:
        >>> coeffs = torch.zeros(1, 4, 3); coeffs[0, 0] = rgb_to_sh(torch.tensor([0.2, 0.4, 0.6]))
        >>> eval_sh(coeffs, torch.tensor([[1.0, 0.0, 0.0]]))
        tensor([[0.2000, 0.4000, 0.6000]])
    """
    dims = check_shape(coeffs, "coeffs", ("N", "K", "C"))
    check_shape(dirs, "dirs", ("*", "N", 3), dims)
    k = dims["K"]
    max_degree = math.isqrt(k) - 1
    if (max_degree + 1) ** 2 != k or k > 16:
        raise ValueError(f"coeffs: expected K = (degree + 1)^2 in (1, 4, 9, 16), got K={k}")
    degree = max_degree if degree is None else degree
    if not 0 <= degree <= max_degree:
        raise ValueError(f"degree: expected 0 to {max_degree} for K={k} coefficients, got {degree}")
    basis = sh_basis(dirs, degree)  # (*, N, K')
    colors = (basis.unsqueeze(-1) * coeffs[:, : basis.shape[-1]]).sum(-2)
    if max_value is not None:
        return torch.clamp(colors + 0.5, 0.0, max_value)
    return torch.clamp_min(colors + 0.5, 0.0)


def rgb_to_sh(rgb: torch.Tensor) -> torch.Tensor:
    """The degree-0 coefficient that renders a constant colour: ``(rgb - 0.5) / C0``.

    Example:
        >>> sh_to_rgb(rgb_to_sh(torch.tensor([0.25])))
        tensor([0.2500])
    """
    return (rgb - 0.5) / SH_C0


def sh_to_rgb(sh: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`rgb_to_sh`: ``sh * C0 + 0.5``."""
    return sh * SH_C0 + 0.5


# ---------------------------------------------------------------------------------------------------
# rotation


def _sphere_directions(n: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """``(n, 3)`` unit directions on a Fibonacci sphere (well spread, deterministic)."""
    i = torch.arange(n, dtype=dtype) + 0.5
    z = 1 - 2 * i / n
    r = torch.sqrt(1 - z * z)
    phi = math.pi * (3 - math.sqrt(5)) * i
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)


def sh_rotation(R: torch.Tensor, degree: int) -> torch.Tensor:
    r"""The ``(K, K)`` matrix ``M`` that rotates SH coefficients by ``R``: ``f' = M f``.

    ``f'`` evaluated at ``d`` equals ``f`` evaluated at ``R^\top d`` (an object's SH moved into the
    world by its rotation ``R``). The SH of degree ≤ 3 span a rotation-invariant space, so ``M`` is
    exactly the least-squares solution of :math:`B(D)\,M = B(D R)` on 64 directions ``D``
    (``B`` = :func:`sh_basis`), computed in float64: block diagonal by degree, the Wigner-D
    matrices in the real basis of 3DGS. Not differentiable (poses are fixed).

    .. math::

        \sum_k Y_k(\mathbf{d})\,(M \mathbf{f})_k = \sum_k Y_k(R^\top \mathbf{d})\,\mathbf{f}_k

    Args:
        R: ``(3, 3)`` rotation.
        degree: 0 to 3.

    Returns:
        ``(K, K)`` float64, ``K = (degree + 1)^2``.

    Raises:
        ValueError: for ``R`` not ``(3, 3)`` or a degree outside 0 to 3.

    Example:
        >>> Rz = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # 90° about z
        >>> sh_rotation(Rz, 1).round(decimals=6).abs().tolist()[1:]  # basis y, z, x: y -> x, x -> y
        [[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 0.0]]
    """
    if R.shape != (3, 3):
        raise ValueError(f"R: expected shape (3, 3), got {tuple(R.shape)}")
    dirs = _sphere_directions(64)
    B = sh_basis(dirs, degree)
    B_rot = sh_basis(dirs @ R.double(), degree)  # rows (R^T d)^T = d^T R
    return torch.linalg.lstsq(B, B_rot).solution


def rotate_sh(sh: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """SH coefficients ``(N, K, C)`` rotated by ``(3, 3)`` ``R`` (see :func:`sh_rotation`).

    Differentiable w.r.t. ``sh``; keeps its dtype and device.

    Raises:
        ValueError: for ``sh`` not ``(N, K, C)`` with ``K`` in 1, 4, 9, 16, or ``R`` not ``(3, 3)``.

    Example:
        >>> sh = torch.randn(5, 9, 3); R = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
        >>> d = torch.nn.functional.normalize(torch.randn(5, 3), dim=-1)
        >>> bool(torch.allclose(eval_sh(rotate_sh(sh, R), d), eval_sh(sh, d @ R), atol=1e-5))
        True
    """
    k = sh.shape[-2]
    degree = math.isqrt(k) - 1
    if (degree + 1) ** 2 != k or k > 16 or sh.dim() != 3:
        raise ValueError(f"sh: expected (N, K, C) with K in (1, 4, 9, 16), got {tuple(sh.shape)}")
    M = sh_rotation(R.detach().cpu(), degree).to(device=sh.device, dtype=sh.dtype)
    return torch.einsum("kj,njc->nkc", M, sh)
