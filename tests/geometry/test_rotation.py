"""Tests of quaternion / rotation-matrix conversions (vadgs.geometry.rotation).

References: scipy's ``Rotation`` (an independent implementation, scalar-first ``wxyz``) and kornia's
conversions; the Hamilton product also against its definition written with Python floats.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from kornia.geometry.conversions import quaternion_to_rotation_matrix, rotation_matrix_to_quaternion
from kornia.geometry.quaternion import Quaternion
from scipy.spatial.transform import Rotation
from torch.autograd import gradcheck

from vadgs.checks import checking
from vadgs.geometry import normals_to_quats, quat_multiply, quaternion_to_rotation, rotation_to_quat


def random_quats(n: int, seed: int = 0, dtype=torch.float64, scale: float = 3.0) -> torch.Tensor:
    """``(n, 4)`` ``wxyz`` quaternions of random norm (as stored by a model), both signs of ``w``."""
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(n, 4, generator=g, dtype=torch.float64) * scale).to(dtype)


def scipy_matrix(q: torch.Tensor) -> torch.Tensor:
    return torch.from_numpy(Rotation.from_quat(q.double().numpy(), scalar_first=True).as_matrix())


def naive_hamilton(a: list[float], b: list[float]) -> list[float]:
    """``a ⊗ b`` from ``(w1 w2 - v1·v2, w1 v2 + w2 v1 + v1 × v2)``, one pair of Python floats."""
    w1, v1 = a[0], np.array(a[1:])
    w2, v2 = b[0], np.array(b[1:])
    v = w1 * v2 + w2 * v1 + np.cross(v1, v2)
    return [w1 * w2 - float(v1 @ v2), *v.tolist()]


class TestQuaternionToRotation:
    def test_smoke(self, device, dtype):
        R = quaternion_to_rotation(torch.tensor([1.0, 0, 0, 0], device=device, dtype=dtype))
        assert R.shape == (3, 3) and R.device.type == device.type and R.dtype == dtype

    @pytest.mark.parametrize("shape", [(4,), (7, 4), (2, 3, 4)])
    def test_cardinality(self, shape):
        q = random_quats(int(np.prod(shape[:-1])) if len(shape) > 1 else 1).reshape(shape)
        assert quaternion_to_rotation(q).shape == (*shape[:-1], 3, 3)

    def test_exception(self):
        with pytest.raises(ValueError, match=r"quats: expected shape \(\*, 4\)"):
            quaternion_to_rotation(torch.zeros(5, 3))
        with pytest.raises(ValueError, match="quats: expected non-zero quaternions"):
            quaternion_to_rotation(torch.tensor([[1.0, 0, 0, 0], [0.0, 0, 0, 0]]))
        with pytest.raises(ValueError, match="quats: expected finite values"):
            quaternion_to_rotation(torch.tensor([[float("nan"), 0, 0, 0]]))
        with checking(False):  # the caller vouches: no value check, NaN comes out
            assert quaternion_to_rotation(torch.zeros(1, 4)).isnan().all()

    def test_feature_against_scipy(self):
        q = random_quats(500)
        torch.testing.assert_close(quaternion_to_rotation(q), scipy_matrix(q), rtol=0, atol=1e-14)

    def test_feature_against_kornia(self, dtype):
        q = random_quats(500, seed=1, dtype=dtype)
        want = quaternion_to_rotation_matrix(q / q.norm(dim=-1, keepdim=True))
        torch.testing.assert_close(quaternion_to_rotation(q), want, rtol=0, atol=1e-6)

    def test_feature_hand_computed(self):
        # 90° about x: y -> z, z -> -y; the norm does not matter, nor the sign
        q = torch.tensor([[1.0, 1.0, 0.0, 0.0], [-2.0, -2.0, 0.0, 0.0]], dtype=torch.float64)
        want = torch.tensor([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=torch.float64)
        torch.testing.assert_close(quaternion_to_rotation(q), want.expand(2, 3, 3), rtol=0, atol=1e-15)

    def test_proper_rotations(self):
        R = quaternion_to_rotation(random_quats(200, seed=2))
        eye = torch.eye(3, dtype=torch.float64).expand_as(R)
        torch.testing.assert_close(R @ R.transpose(-1, -2), eye, rtol=0, atol=1e-14)
        torch.testing.assert_close(torch.linalg.det(R), torch.ones(200, dtype=torch.float64))

    def test_gradcheck(self):
        q = random_quats(3, seed=3).requires_grad_()
        assert gradcheck(quaternion_to_rotation, (q,))


class TestRotationToQuat:
    def test_smoke(self, device, dtype):
        q = rotation_to_quat(torch.eye(3, device=device, dtype=dtype))
        assert q.tolist() == [1.0, 0.0, 0.0, 0.0] and q.device.type == device.type and q.dtype == dtype

    def test_cardinality(self):
        R = quaternion_to_rotation(random_quats(6)).reshape(2, 3, 3, 3)
        assert rotation_to_quat(R).shape == (2, 3, 4)

    def test_feature_against_scipy(self):
        q = random_quats(500, seed=4)
        R = quaternion_to_rotation(q)
        want = torch.from_numpy(Rotation.from_matrix(R.numpy()).as_quat(canonical=True, scalar_first=True))
        torch.testing.assert_close(rotation_to_quat(R), want, rtol=0, atol=1e-12)

    def test_round_trip(self):
        q = random_quats(500, seed=5)
        unit = q / q.norm(dim=-1, keepdim=True)
        got = rotation_to_quat(quaternion_to_rotation(q))
        torch.testing.assert_close(got, unit * unit[:, :1].sign(), rtol=0, atol=1e-12)  # w >= 0
        assert bool((got[:, 0] >= 0).all())

    def test_half_turns(self):
        # w = 0: the conditioning branch Shepperd's method exists for; either sign of v is right
        q = torch.tensor(
            [[0.0, 1, 0, 0], [0.0, 0, 1, 0], [0.0, 0, 0, 1], [0.0, 1, 1, 0]], dtype=torch.float64
        )
        got = rotation_to_quat(quaternion_to_rotation(q))
        unit = q / q.norm(dim=-1, keepdim=True)
        torch.testing.assert_close(got.abs(), unit.abs(), rtol=0, atol=1e-12)

    def test_is_kornia_with_the_sign_fixed(self):
        R = quaternion_to_rotation(random_quats(100, seed=6))
        q = rotation_matrix_to_quaternion(R)
        assert torch.equal(rotation_to_quat(R), torch.where(q[:, :1] < 0, -q, q))


class TestQuatMultiply:
    def test_smoke(self, device, dtype):
        q = torch.tensor([1.0, 0, 0, 0], device=device, dtype=dtype)
        assert quat_multiply(q, q).tolist() == [1.0, 0.0, 0.0, 0.0]

    def test_cardinality_broadcast(self):
        assert quat_multiply(random_quats(1), random_quats(5)).shape == (5, 4)
        assert quat_multiply(random_quats(4).reshape(2, 2, 4), random_quats(2)).shape == (2, 2, 4)

    def test_exception(self):
        with pytest.raises(ValueError, match=r"q2: expected shape \(\*, 4\)"):
            quat_multiply(torch.zeros(2, 4), torch.zeros(2, 3))

    def test_feature_naive(self):
        a, b = random_quats(20, seed=7), random_quats(20, seed=8)
        want = torch.tensor(
            [naive_hamilton(x, y) for x, y in zip(a.tolist(), b.tolist())], dtype=torch.float64
        )
        torch.testing.assert_close(quat_multiply(a, b), want, rtol=1e-14, atol=1e-14)

    def test_feature_against_kornia(self):
        a, b = random_quats(20, seed=9), random_quats(20, seed=10)
        torch.testing.assert_close(quat_multiply(a, b), (Quaternion(a) * Quaternion(b)).data)

    def test_composes_rotations(self):
        a, b = random_quats(64, seed=11), random_quats(64, seed=12)
        R = quaternion_to_rotation(quat_multiply(a, b))
        torch.testing.assert_close(
            R, quaternion_to_rotation(a) @ quaternion_to_rotation(b), rtol=0, atol=1e-13
        )
        ra, rb = (Rotation.from_quat(x.numpy(), scalar_first=True) for x in (a, b))
        want = ra * rb
        torch.testing.assert_close(R, torch.from_numpy(want.as_matrix()), rtol=0, atol=1e-13)

    def test_gradcheck(self):
        a, b = random_quats(3, seed=13).requires_grad_(), random_quats(3, seed=14).requires_grad_()
        assert gradcheck(quat_multiply, (a, b))


class TestNormalsToQuats:
    def test_third_axis_is_the_normal(self):
        n = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
        R = quaternion_to_rotation(normals_to_quats(n))
        assert torch.allclose(R[:, :, 2], n, atol=1e-5)
