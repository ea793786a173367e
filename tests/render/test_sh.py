"""Tests of the rotation of spherical-harmonics coefficients (vadgs.render.sh).

The reference: rotating the coefficients by ``R`` and evaluating at ``d`` equals evaluating the
original coefficients at ``R^T d`` (the basis evaluated one Gaussian at a time); degree 1 against
its hand-computed matrix.
"""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from torch.autograd import gradcheck

from vadgs.geometry import quaternion_to_rotation
from vadgs.render import SH_C0, eval_sh, rotate_sh, sh_basis, sh_rotation

#: (x, y, z) -> (-y, z, -x): the degree-1 basis of 3DGS is C1 times this (sh_basis).
S1 = torch.tensor([[0.0, -1, 0], [0, 0, 1], [-1, 0, 0]], dtype=torch.float64)


def random_rotation(gen: torch.Generator) -> torch.Tensor:
    return quaternion_to_rotation(torch.randn(4, generator=gen, dtype=torch.float64))


class TestShRotation:
    def test_identity_and_group_structure(self):
        gen = torch.Generator().manual_seed(1)
        R1, R2 = random_rotation(gen), random_rotation(gen)
        torch.testing.assert_close(sh_rotation(torch.eye(3), 3), torch.eye(16, dtype=torch.float64))
        torch.testing.assert_close(sh_rotation(R1 @ R2, 3), sh_rotation(R1, 3) @ sh_rotation(R2, 3))
        M = sh_rotation(R1, 3)
        torch.testing.assert_close(M @ M.T, torch.eye(16, dtype=torch.float64))  # orthogonal

    def test_block_diagonal_by_degree(self):
        M = sh_rotation(random_rotation(torch.Generator().manual_seed(2)), 3)
        degree = torch.tensor([0] + [1] * 3 + [2] * 5 + [3] * 7)
        across = degree[:, None] != degree[None, :]
        assert float(M[across].abs().max()) < 1e-12
        assert abs(float(M[0, 0]) - 1.0) < 1e-12  # the constant term does not turn

    def test_degree_one_hand_computed(self):
        # f' . Y(d) = f . Y(R^T d) with Y = C1 S1 d for degree 1: f' = S1 R S1^T f
        R = random_rotation(torch.Generator().manual_seed(3))
        M = sh_rotation(R, 1)
        torch.testing.assert_close(M[1:, 1:], S1 @ R @ S1.T, rtol=0, atol=1e-12)

    def test_float32_rotation(self):
        R = random_rotation(torch.Generator().manual_seed(4))
        M = sh_rotation(R.float(), 2)
        assert M.dtype == torch.float64 and M.shape == (9, 9)
        torch.testing.assert_close(M, sh_rotation(R.float().double(), 2))

    def test_exception(self):
        with pytest.raises(ValueError, match=r"R: expected shape \(3, 3\), got \(4, 4\)"):
            sh_rotation(torch.eye(4), 1)
        with pytest.raises(ValueError, match="degree: expected 0 to 3, got 4"):
            sh_rotation(torch.eye(3), 4)


class TestRotateSh:
    def test_smoke(self, device, dtype):
        sh = torch.randn(7, 9, 3, device=device, dtype=dtype)
        out = rotate_sh(sh, torch.eye(3, device=device))
        assert out.shape == sh.shape and out.device == sh.device and out.dtype == dtype
        torch.testing.assert_close(out, sh)

    @pytest.mark.parametrize("degree", [0, 1, 2, 3])
    def test_against_evaluation_at_rotated_directions(self, degree):
        gen = torch.Generator().manual_seed(degree)
        R = random_rotation(gen)
        sh = torch.randn(50, (degree + 1) ** 2, 3, generator=gen, dtype=torch.float64)
        d = F.normalize(torch.randn(50, 3, generator=gen, dtype=torch.float64), dim=-1)
        # the reference: evaluate the basis at R^T d directly, one Gaussian at a time
        expect = torch.stack([sh_basis(R.T @ d[i], degree) @ sh[i] for i in range(50)])
        got = torch.einsum("nk,nkc->nc", sh_basis(d, degree), rotate_sh(sh, R))
        torch.testing.assert_close(got, expect, atol=1e-9, rtol=1e-9)

    def test_colours_follow_the_frame(self):
        # an object's colours seen from the world: eval_sh of the rotated SH at d = the object's at R^T d
        gen = torch.Generator().manual_seed(5)
        R = random_rotation(gen)
        sh = torch.randn(20, 16, 3, generator=gen, dtype=torch.float64)
        d = F.normalize(torch.randn(20, 3, generator=gen, dtype=torch.float64), dim=-1)
        torch.testing.assert_close(eval_sh(rotate_sh(sh, R), d), eval_sh(sh, d @ R))

    def test_inverse(self):
        gen = torch.Generator().manual_seed(6)
        R = random_rotation(gen)
        sh = torch.randn(10, 16, 3, generator=gen, dtype=torch.float64)
        torch.testing.assert_close(rotate_sh(rotate_sh(sh, R), R.T), sh)

    def test_exception(self):
        with pytest.raises(
            ValueError, match=r"sh: expected \(N, K, C\) with K in \(1, 4, 9, 16\), got \(2, 5, 3\)"
        ):
            rotate_sh(torch.zeros(2, 5, 3), torch.eye(3))
        with pytest.raises(ValueError, match="sh: expected"):
            rotate_sh(torch.zeros(4, 3), torch.eye(3))
        with pytest.raises(ValueError, match="R: expected shape"):
            rotate_sh(torch.zeros(2, 4, 3), torch.eye(2))

    def test_gradcheck(self):
        R = random_rotation(torch.Generator().manual_seed(7))
        sh = torch.randn(2, 9, 3, dtype=torch.float64, requires_grad=True)
        assert gradcheck(lambda s: rotate_sh(s, R), (sh,))


# 3DGS's constants of the real SH basis (``utils/sh_utils.py``), as its code writes them
C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def test_the_constants_are_the_closed_forms():
    pi = math.pi
    closed = [1 / (2 * math.sqrt(pi)), math.sqrt(3 / (4 * pi))]
    closed += [x * math.sqrt(15 / pi) for x in (1 / 2, -1 / 2)] + [math.sqrt(5 / pi) / 4]
    closed += [-math.sqrt(15 / pi) / 2, math.sqrt(15 / pi) / 4]
    a, b, c, d = (
        math.sqrt(35 / (2 * pi)) / 4,
        math.sqrt(105 / pi),
        math.sqrt(21 / (2 * pi)) / 4,
        math.sqrt(7 / pi) / 4,
    )
    closed += [-a, b / 2, -c, d, -c, b / 4, -a]
    assert [C0, C1, *C2, *C3] == pytest.approx(closed, rel=1e-15)
    assert SH_C0 == C0


def _basis_term_by_term(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """3DGS's real SH basis written out one term at a time (its order of operations and constants)."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree > 0:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree > 1:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [C2[0] * xy, C2[1] * yz, C2[2] * (2.0 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
    if degree > 2:
        out += [
            C3[0] * y * (3.0 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4.0 * zz - xx - yy),
            C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            C3[4] * x * (4.0 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, -1)


class TestShBasis:
    @pytest.mark.parametrize("degree", [0, 1, 2, 3])
    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_equals_the_term_by_term_basis_bit_for_bit(self, degree, dtype):
        """Gathered columns (fewer kernels: 27 instead of 50 at degree 3) give the same values."""
        g = torch.Generator().manual_seed(degree)
        d = F.normalize(torch.randn(4, 5000, 3, generator=g, dtype=dtype), dim=-1)
        d[0, :4] = torch.tensor([[0.0, 0, 1], [-0.0, 0.0, -1.0], [0.6, 0.0, -0.8], [1.0, 0, 0]], dtype=dtype)
        assert torch.equal(sh_basis(d, degree), _basis_term_by_term(d, degree))

    def test_gradient_to_rounding(self):
        d = F.normalize(torch.randn(300, 3, generator=torch.Generator().manual_seed(1)), dim=-1)
        a, b = d.clone().requires_grad_(), d.clone().requires_grad_()
        w = torch.randn(300, 16, generator=torch.Generator().manual_seed(2))
        (sh_basis(a, 3) * w).sum().backward()
        (_basis_term_by_term(b, 3) * w).sum().backward()
        torch.testing.assert_close(a.grad, b.grad, rtol=1e-5, atol=1e-5)
