r"""Rotations as ``wxyz`` quaternions and 3×3 matrices: conversions and composition.

Conventions (``docs/conventions.md``): quaternions are ``(w, x, y, z)`` (scalar first, as kornia,
gsplat and 3DGS store them), of any non-zero norm where a rotation is read from one; matrices act
on column vectors. The quaternion :math:`q = (w, \mathbf{v})` rotates :math:`\mathbf{p}` to
:math:`q\,\mathbf{p}\,q^{-1}`, so :math:`R(q_1 \otimes q_2) = R(q_1)\,R(q_2)`.

:func:`rotation_to_quat` is kornia's
:func:`~kornia.geometry.conversions.rotation_matrix_to_quaternion` with the sign fixed;
:func:`quaternion_to_rotation` is written out by hand: it runs at every training step on every
Gaussian and is faster forward than kornia's ``quaternion_to_rotation_matrix`` (the same values to
float rounding; ``benchmarks/bench_quaternion.py``).
"""

from __future__ import annotations

import torch
from kornia.geometry.conversions import rotation_matrix_to_quaternion

from vadgs.checks import check_finite, check_shape, checks_enabled

__all__ = [
    "normals_to_quats",
    "quat_left_matrix",
    "quat_multiply",
    "quaternion_to_rotation",
    "rotation_to_quat",
]


def _check_quaternions(q: torch.Tensor, name: str = "quats") -> None:
    """Value check of ``(*, 4)`` quaternions: finite and of non-zero norm (a zero one has no rotation).

    Example:
        >>> _check_quaternions(torch.tensor([[1.0, 0, 0, 0], [0, 0, 0, 0]]))
        Traceback (most recent call last):
        ...
        ValueError: quats: expected non-zero quaternions, got 1 of norm 0 (first: row 1)
    """
    check_finite(q, name)
    if checks_enabled() and q.numel():
        zero = q.detach().norm(dim=-1) < 1e-12
        if bool(zero.any()):
            first = int(zero.flatten().nonzero()[0, 0])
            raise ValueError(
                f"{name}: expected non-zero quaternions, got {int(zero.sum())} of norm 0 (first: row {first})"
            )


def quaternion_to_rotation(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from ``wxyz`` quaternions of any non-zero norm (normalised here).

    Differentiable w.r.t. ``quats``.

    Args:
        quats: ``(*, 4)`` quaternions ``(w, x, y, z)``.

    Returns:
        ``(*, 3, 3)`` rotation matrices acting on column vectors.

    Raises:
        ValueError: for a shape other than ``(*, 4)``, or a zero or non-finite quaternion.

    Example:
        >>> quaternion_to_rotation(torch.tensor([[2.0, 0.0, 0.0, 0.0]]))
        tensor([[[1., 0., 0.],
                 [0., 1., 0.],
                 [0., 0., 1.]]])
    """
    check_shape(quats, "quats", ("*", 4))
    _check_quaternions(quats)
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, dim=-1).reshape(*q.shape[:-1], 3, 3)


def rotation_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Unit ``wxyz`` quaternion of rotation matrices, with ``w >= 0``.

    :func:`kornia.geometry.conversions.rotation_matrix_to_quaternion` (Shepperd's choice of the
    best conditioned component, branch-free), its sign fixed so that ``w >= 0``. Not meant to be
    differentiated (poses are fixed).

    Shape:
        ``(*, 3, 3)`` → ``(*, 4)``.

    Example:
        >>> rotation_to_quat(torch.eye(3))
        tensor([1., 0., 0., 0.])
        >>> Rz = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # 90° about z
        >>> [round(v, 4) for v in rotation_to_quat(Rz).tolist()]
        [0.7071, 0.0, 0.0, 0.7071]
    """
    q = rotation_matrix_to_quaternion(R)
    return q * torch.where(q[..., :1] < 0, -1.0, 1.0)


def quat_left_matrix(q: torch.Tensor) -> torch.Tensor:
    """The ``4 x 4`` matrix ``L(q)`` of left multiplication by ``q``: ``L(q1) @ q2 = q1 ⊗ q2`` (``wxyz``).

    For many products by a few quaternions (a node's pose applied to its Gaussians): the matrices
    of the few, gathered and applied in one batched product, instead of :func:`quat_multiply`'s
    sixteen products and twelve sums, each a kernel on a GPU (equal to rounding).

    Shape:
        ``(*, 4)`` → ``(*, 4, 4)``.

    Example:
        >>> q = torch.tensor([0.0, 1.0, 0.0, 0.0])  # 180° about x
        >>> quat_left_matrix(q) @ q
        tensor([-1.,  0.,  0.,  0.])
    """
    check_shape(q, "q", ("*", 4))
    w, x, y, z = q.unbind(-1)
    rows = [[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def quat_multiply(q1: torch.Tensor, q2: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``q1 ⊗ q2`` of ``wxyz`` quaternions (rotation ``q2`` first, then ``q1``).

    Differentiable w.r.t. both.

    Shape:
        ``(*, 4)`` and ``(*, 4)`` (broadcast) → ``(*, 4)``.

    Example:
        >>> q = torch.tensor([0.0, 1.0, 0.0, 0.0])  # 180° about x
        >>> quat_multiply(q, q)
        tensor([-1.,  0.,  0.,  0.])
    """
    check_shape(q1, "q1", ("*", 4))
    check_shape(q2, "q2", ("*", 4))
    w1, x1, y1, z1 = q1.unbind(-1)
    w2, x2, y2, z2 = q2.unbind(-1)
    return torch.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        -1,
    )


def normals_to_quats(normals: torch.Tensor) -> torch.Tensor:
    """``wxyz`` quaternions of rotations whose third axis is the given unit normal ``(N, 3)``.

    A Gaussian with scales ``(s, s, t)``, ``t << s``, and this rotation is a disc in the plane of
    the normal. On the device and in the dtype of ``normals``.

    Example:
        >>> n = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]])
        >>> torch.allclose(quaternion_to_rotation(normals_to_quats(n))[:, :, 2], n, atol=1e-6)
        True
    """
    check_shape(normals, "normals", ("N", 3))
    check_finite(normals, "normals")
    n = torch.nn.functional.normalize(normals, dim=-1)
    helper = torch.where(
        n[:, 2:3].abs() < 0.9,
        n.new_tensor([0.0, 0.0, 1.0]).expand_as(n),
        n.new_tensor([1.0, 0.0, 0.0]).expand_as(n),
    )
    a = torch.nn.functional.normalize(torch.cross(helper, n, dim=-1), dim=-1)
    b = torch.cross(n, a, dim=-1)
    R = torch.stack([a, b, n], dim=-1)  # columns: the Gaussian's axes in the world
    return rotation_to_quat(R)
