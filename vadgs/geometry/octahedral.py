"""Octahedral encoding of unit normals: two signed bytes per normal.

The unit sphere is projected onto the octahedron ``|x| + |y| + |z| = 1`` and unfolded onto the
square ``[-1, 1]²`` (the hemisphere ``z ≥ 0`` is the inner diamond, the other one folded over its
corners; Cigolle et al., "A Survey of Efficient Representations for Independent Unit Vectors",
JCGT 2014). Quantised to ``int8`` (``round(127 u)``) a normal comes back within 0.95° (0.34° on
average over the sphere, ``tests/geometry/test_octahedral.py``). The zero vector (a pixel no
Gaussian covers) is kept as ``(-128, -128)`` and decoded to zero.

:func:`octahedral_encode` / :func:`octahedral_decode`, used for the renders the VAD-GS strategy
keeps between its events (:mod:`vadgs.train.vad.state`).
"""

from __future__ import annotations

import torch

__all__ = ["octahedral_decode", "octahedral_encode"]

_ZERO = -128  # the code of the zero vector (never produced by a unit normal: codes are in [-127, 127])


def _check_components(x: torch.Tensor, name: str, n: int, dim: int) -> None:
    """ValueError unless ``x`` has ``n`` components along ``dim``."""
    if not -x.dim() <= dim < x.dim() or x.shape[dim] != n:
        raise ValueError(f"{name}: expected {n} components along dim {dim}, got shape {tuple(x.shape)}")


def _sign(x: torch.Tensor) -> torch.Tensor:
    """``+1`` where ``x >= 0`` (zero included), else ``-1``, in ``x``'s dtype."""
    return torch.where(x >= 0, 1.0, -1.0).to(x)


def octahedral_encode(normals: torch.Tensor, dim: int = -3) -> torch.Tensor:
    """Unit normals → ``int8`` octahedral codes (two per normal, along ``dim``).

    Args:
        normals: unit vectors (or zero vectors) with 3 components along ``dim``; other lengths
            are projected to the sphere first.
        dim: the component axis (``-3``: the channel axis of ``(C, H, W)`` / ``(B, C, H, W)`` maps).

    Returns:
        ``int8`` codes in ``[-127, 127]`` with 2 components along ``dim``, on ``normals``' device;
        a zero vector gives ``(-128, -128)``. Not differentiable.

    Raises:
        ValueError: when ``normals`` has no 3 components along ``dim``.

    Example:
        >>> n = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, -0.8], [0.0, 0.0, 0.0]])
        >>> octahedral_encode(n, dim=-1).tolist()
        [[0, 0], [127, 73], [-128, -128]]
        >>> back = octahedral_decode(octahedral_encode(n, dim=-1), dim=-1)
        >>> back[1], back[2]  # within 0.4° of (0.6, 0, -0.8); the zero vector stays zero
        (tensor([ 0.5947,  0.0000, -0.8039]), tensor([0., 0., 0.]))
    """
    _check_components(normals, "normals", 3, dim)
    n = normals.detach().float()
    a = n.abs()
    s = a.narrow(dim, 0, 1) + a.narrow(dim, 1, 1) + a.narrow(dim, 2, 1)  # |x| + |y| + |z|, in that order
    zero = s == 0
    uv = n.narrow(dim, 0, 2) / s.masked_fill(zero, 1.0)
    back = n.narrow(dim, 2, 1) < 0  # folded over the square's corners
    # (1 - |v|, 1 - |u|) with the signs of (u, v), a zero's sign +1 (+ 0.0 turns -0.0 into +0.0)
    folded = torch.copysign(1 - uv.abs().flip(dim), uv + 0.0)
    codes = torch.where(back, folded, uv).mul_(127).round_().to(torch.int8)  # |u|, |v| <= 1: within ±127
    return codes.masked_fill_(zero, _ZERO)


def octahedral_decode(codes: torch.Tensor, dim: int = -3, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """``int8`` octahedral codes → unit normals (zero where the code is ``(-128, -128)``).

    Args:
        codes: ``int8``, 2 components along ``dim`` (from :func:`octahedral_encode`).
        dim: the component axis.
        dtype: the normals' floating dtype.

    Returns:
        Unit normals with 3 components along ``dim``, ``dtype``, on ``codes``' device (see
        :func:`octahedral_encode`, with an example of both).

    Raises:
        ValueError: when ``codes`` is not ``int8`` with 2 components along ``dim``.
    """
    if codes.dtype != torch.int8:
        raise ValueError(f"octahedral_decode: codes must be int8, got {codes.dtype}")
    _check_components(codes, "codes", 2, dim)
    cu, cv = codes.unbind(dim)
    u, v = cu.to(dtype) / 127, cv.to(dtype) / 127
    z = 1 - u.abs() - v.abs()
    t = (-z).clamp(min=0)  # the folded hemisphere: back to the octahedron's lower half
    x, y = u - t * _sign(u), v - t * _sign(v)
    r = (x * x + y * y + z * z).rsqrt()  # |x| + |y| + |z| = 1: the length is at least 1/sqrt(3)
    n = torch.stack([x * r, y * r, z * r], dim)
    return n.masked_fill(((cu == _ZERO) & (cv == _ZERO)).unsqueeze(dim), 0.0)  # +0, not -0
