"""Quaternion conversions: vadgs's hand-written ones against kornia's (pytest-benchmark; issue 24).

Run (the numbers in docs/benchmarks.md come from exactly this, one thread, CPU time):

    VADGS_BENCH_THREADS=1 pytest benchmarks/bench_quaternion.py --benchmark-enable -p no:cacheprovider \
        --benchmark-columns=min,median,max,rounds --benchmark-sort=name --benchmark-timer=time.process_time

- ``quaternion_to_rotation`` (:mod:`vadgs.geometry.rotation`) runs at every training step on
  every Gaussian, forward and backward: 150k seeded ``wxyz`` quaternions of random norm (a
  street_a initialisation), float32, against
  :func:`kornia.geometry.conversions.quaternion_to_rotation_matrix`.
- rotation → quaternion (:func:`vadgs.geometry.rotation_to_quat`) runs on track poses and the
  normals of a VAD-GS event's new points (thousands, no gradient): 10k seeded rotations, float64,
  the hand-written Shepperd's method vadgs had until issue 24 (kept here as the reference)
  against :func:`kornia.geometry.conversions.rotation_matrix_to_quaternion` with vadgs's
  ``w >= 0`` sign, which ``rotation_to_quat`` now is.

Each comparison also asserts that the two agree to float round-off.
"""

from __future__ import annotations

import os

import pytest
import torch
from kornia.geometry.conversions import quaternion_to_rotation_matrix, rotation_matrix_to_quaternion

from vadgs.geometry.rotation import quaternion_to_rotation, rotation_to_quat

if os.environ.get("VADGS_BENCH_THREADS"):  # e.g. 1 on a loaded shared machine, see the docs
    torch.set_num_threads(int(os.environ["VADGS_BENCH_THREADS"]))

N_GAUSSIANS = 150_000
N_ROTATIONS = 10_000


def _quats(n: int = N_GAUSSIANS, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    return (torch.randn(n, 4, generator=g, dtype=torch.float64) * 3).to(dtype)


def _kornia_rotation_to_quat(R: torch.Tensor) -> torch.Tensor:
    q = rotation_matrix_to_quaternion(R)
    return q * torch.where(q[..., :1] < 0, -1.0, 1.0)


def _shepperd_rotation_to_quat(R: torch.Tensor) -> torch.Tensor:
    """vadgs's hand-written ``rotation_to_quat`` before issue 24 (Shepperd's method, branch-free)."""
    (a, b, c), (d, e, f), (g, h, k) = (row.unbind(-1) for row in R.unbind(-2))
    rows = [
        [1 + a + e + k, h - f, c - g, d - b],
        [h - f, 1 + a - e - k, b + d, c + g],
        [c - g, b + d, 1 - a + e - k, f + h],
        [d - b, c + g, f + h, 1 - a - e + k],
    ]
    cands = torch.stack([torch.stack(r, -1) for r in rows], -2)  # row i is 4 q_i q
    best = torch.diagonal(cands, dim1=-2, dim2=-1).argmax(-1)
    q = torch.gather(cands, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    q = torch.nn.functional.normalize(q, dim=-1)
    return q * torch.where(q[..., :1] < 0, -1.0, 1.0)


def _forward_backward(fn, q: torch.Tensor) -> None:
    q = q.detach().requires_grad_(True)
    fn(q).sum().backward()


@pytest.mark.parametrize("impl", ["handwritten", "kornia"])
def test_quat_to_rotation_forward_backward(benchmark, impl):
    fn = quaternion_to_rotation if impl == "handwritten" else quaternion_to_rotation_matrix
    q = _quats()
    benchmark(_forward_backward, fn, q)


@pytest.mark.parametrize("impl", ["handwritten", "kornia"])
def test_quat_to_rotation_forward(benchmark, impl):
    fn = quaternion_to_rotation if impl == "handwritten" else quaternion_to_rotation_matrix
    q = _quats()
    with torch.no_grad():
        benchmark(fn, q)


@pytest.mark.parametrize("impl", ["handwritten", "kornia"])
def test_rotation_to_quat(benchmark, impl):
    fn = _shepperd_rotation_to_quat if impl == "handwritten" else rotation_to_quat
    R = quaternion_to_rotation(_quats(N_ROTATIONS, torch.float64))
    benchmark(fn, R)


def test_same_numbers():
    """Both pairs agree to float round-off (and the gradients too)."""
    q = _quats(10_000).requires_grad_(True)
    a, b = quaternion_to_rotation(q), quaternion_to_rotation_matrix(q)
    torch.testing.assert_close(a, b, rtol=0, atol=1e-6)
    ga, gb = (torch.autograd.grad(m.sum(), q)[0] for m in (a, b))
    torch.testing.assert_close(ga, gb, rtol=1e-5, atol=1e-6)
    R = quaternion_to_rotation(_quats(N_ROTATIONS, torch.float64))
    torch.testing.assert_close(rotation_to_quat(R), _kornia_rotation_to_quat(R), rtol=0, atol=0)
    torch.testing.assert_close(rotation_to_quat(R), _shepperd_rotation_to_quat(R), rtol=0, atol=1e-14)
