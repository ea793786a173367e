"""Tests of camera paths (vadgs.geometry.camera_path).

References: scipy's ``Slerp`` for the rotation of :func:`interpolate_rigid`, the closed form of a
uniform Catmull-Rom spline (``alpha = 0``), and hand-made camera rings for the orbit.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation, Slerp

from vadgs.geometry import (
    CameraPath,
    catmull_rom,
    focus_point,
    interpolate_rigid,
    keyframe_path,
    look_at,
    orbit_path,
    quaternion_to_rotation,
    spline_path,
)

UP = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)


def _rot(axis: torch.Tensor, angle: float) -> torch.Tensor:
    q = torch.cat([torch.tensor([np.cos(angle / 2)]), np.sin(angle / 2) * axis / axis.norm()])
    return quaternion_to_rotation(q.double())


def random_rigid(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    T = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    T[:, :3, :3] = quaternion_to_rotation(torch.randn(n, 4, generator=g, dtype=torch.float64))
    T[:, :3, 3] = torch.randn(n, 3, generator=g, dtype=torch.float64) * 5
    return T


def ring(n: int, radius: float = 4.0, height: float = 1.0, turn: float = 1.0) -> torch.Tensor:
    """``(n, 4, 4)`` cameras on a circle about the z axis at ``height``, looking at the origin."""
    a = turn * torch.arange(n, dtype=torch.float64) * 2 * math.pi / n
    pos = torch.stack([radius * a.cos(), radius * a.sin(), torch.full_like(a, height)], -1)
    return look_at(pos, torch.zeros_like(pos), UP)


class TestInterpolateRigid:
    def test_endpoints_and_midpoint(self):
        a, b = torch.eye(4, dtype=torch.float64), torch.eye(4, dtype=torch.float64)
        axis = torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64)
        a[:3, :3], b[:3, :3] = _rot(axis, 0.3), _rot(axis, 1.1)
        a[:3, 3], b[:3, 3] = torch.tensor([1.0, 2, 3]), torch.tensor([3.0, 0, 3])
        torch.testing.assert_close(interpolate_rigid(a, b, 0.0), a)
        torch.testing.assert_close(interpolate_rigid(a, b, 1.0), b)
        mid = interpolate_rigid(a, b, 0.25)
        torch.testing.assert_close(mid[:3, :3], _rot(axis, 0.5))  # constant angular speed
        torch.testing.assert_close(mid[:3, 3], torch.tensor([1.5, 1.5, 3.0], dtype=torch.float64))

    @pytest.mark.parametrize("t", [0.1, 0.5, 0.9])
    def test_feature_against_scipy_slerp(self, t):
        a, b = random_rigid(20, 0), random_rigid(20, 1)
        got = interpolate_rigid(a, b, t)
        for i in range(20):
            rots = Rotation.from_matrix(np.stack([a[i, :3, :3].numpy(), b[i, :3, :3].numpy()]))
            want = Slerp([0.0, 1.0], rots)([t]).as_matrix()[0]  # the shortest arc, as here
            np.testing.assert_allclose(got[i, :3, :3].numpy(), want, rtol=0, atol=1e-12)
        torch.testing.assert_close(got[:, :3, 3], (1 - t) * a[:, :3, 3] + t * b[:, :3, 3])

    def test_same_rotation_and_dtype(self):
        a = random_rigid(3, 2).float()
        b = a.clone()
        b[:, :3, 3] += 1.0
        got = interpolate_rigid(a, b, 0.5)
        assert got.dtype == torch.float32
        torch.testing.assert_close(got[:, :3, :3], a[:, :3, :3])

    def test_exception(self):
        with pytest.raises(ValueError, match=r"b: expected shape \(\*, 4, 4\)"):
            interpolate_rigid(torch.eye(4), torch.eye(3), 0.5)


class TestKeyframePath:
    def test_through_the_keys(self):
        keys = random_rigid(4, 3)
        path = keyframe_path(keys, frames_between=2)
        assert isinstance(path, CameraPath) and path.cam_to_world.shape == (10, 4, 4)
        assert torch.equal(path.cam_to_world[::3], keys)  # the keys themselves, bit for bit
        torch.testing.assert_close(path.t, torch.arange(10, dtype=torch.float64) / 3)
        torch.testing.assert_close(path.cam_to_world[4], interpolate_rigid(keys[1], keys[2], 1 / 3))

    def test_no_frames_between_and_one_key(self):
        keys = random_rigid(3, 4)
        assert torch.equal(keyframe_path(keys).cam_to_world, keys)
        assert keyframe_path(keys[:1], 5).t.tolist() == [0.0]

    def test_exception(self):
        with pytest.raises(ValueError, match="frames_between: expected >= 0, got -1"):
            keyframe_path(random_rigid(2, 5), -1)
        with pytest.raises(ValueError, match="keys: expected at least one pose"):
            keyframe_path(torch.zeros(0, 4, 4))


class TestLookAt:
    def test_look_at(self):
        pos, target = torch.tensor([[1.0, 2.0, 3.0]]), torch.tensor([[4.0, -2.0, 3.5]])
        c2w = look_at(pos, target, UP.float())[0]
        torch.testing.assert_close(c2w[:3, 2], (target - pos)[0] / (target - pos).norm())
        assert abs(float(c2w[:3, 0] @ UP.float())) < 1e-6 and float(c2w[:3, 1] @ UP.float()) < 0  # y down
        assert float(torch.linalg.det(c2w[:3, :3])) == pytest.approx(1.0)
        down = look_at(torch.zeros(3), torch.tensor([0.0, 0.0, -1.0]), UP.float())  # along up: still a pose
        assert float(torch.linalg.det(down[:3, :3])) == pytest.approx(1.0)

    def test_exception(self):
        with pytest.raises(ValueError, match=r"up: expected shape \(3\), got \(2, 3\)"):
            look_at(torch.zeros(3), torch.ones(3), torch.ones(2, 3))


class TestCatmullRom:
    def test_through_the_points_and_smooth(self):
        pts = torch.tensor([[0.0, 0.0], [1.0, 2.0], [4.0, 2.5], [5.0, 0.0]], dtype=torch.float64)
        torch.testing.assert_close(catmull_rom(pts, torch.arange(4.0, dtype=torch.float64)), pts)
        h = 1e-5  # smooth at the inner points: the tangents from both sides point the same way
        for k in (1.0, 2.0):
            t = torch.tensor([k - h, k, k + h], dtype=torch.float64)
            a, b, c = catmull_rom(pts, t)
            cos = torch.nn.functional.cosine_similarity(b - a, c - b, dim=0)
            assert float(cos) > 1 - 1e-6, (k, float(cos))
        # a straight run of uneven steps: no overshoot, monotone
        line = torch.tensor([[0.0], [0.1], [3.0], [3.2]], dtype=torch.float64)
        x = catmull_rom(line, torch.linspace(0, 3, 301, dtype=torch.float64))[:, 0]
        assert bool((x.diff() >= 0).all()) and float(x.min()) == 0.0 and float(x.max()) == 3.2
        with pytest.raises(ValueError, match="t: expected parameters in"):
            catmull_rom(pts, torch.tensor([3.5]))

    def test_uniform_against_the_closed_form(self):
        # alpha = 0: the uniform spline, 0.5 * [2 p1 + (-p0 + p2) u + (2p0 - 5p1 + 4p2 - p3) u² + ...]
        g = torch.Generator().manual_seed(6)
        pts = torch.randn(5, 3, generator=g, dtype=torch.float64)
        t = torch.linspace(0, 4, 41, dtype=torch.float64)
        ext = torch.cat([2 * pts[:1] - pts[1:2], pts, 2 * pts[-1:] - pts[-2:-1]])
        want = []
        for tv in t.tolist():
            i = min(math.floor(tv), 3)
            u = tv - i
            p0, p1, p2, p3 = ext[i], ext[i + 1], ext[i + 2], ext[i + 3]
            want.append(
                0.5
                * (
                    2 * p1
                    + (-p0 + p2) * u
                    + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u**2
                    + (-p0 + 3 * p1 - 3 * p2 + p3) * u**3
                )
            )
        torch.testing.assert_close(catmull_rom(pts, t, alpha=0.0), torch.stack(want), rtol=0, atol=1e-12)

    def test_one_point(self):
        assert catmull_rom(torch.ones(1, 2), torch.zeros(3)).tolist() == [[1.0, 1.0]] * 3


class TestSplinePath:
    def test_through_the_cameras(self):
        keys = ring(6, turn=0.5)  # half a circle, cameras looking at the centre
        path = spline_path(keys, UP, 4.0, frames_between=3)
        assert path.cam_to_world.shape == (21, 4, 4)
        torch.testing.assert_close(path.t, torch.arange(21, dtype=torch.float64) / 4)
        # every 4th pose is a camera: its centre, its viewing direction, no roll (the keys have none)
        torch.testing.assert_close(path.cam_to_world[::4], keys, rtol=0, atol=1e-9)
        assert float((path.cam_to_world[:, :3, 0] @ UP).abs().max()) < 1e-12  # level: x normal to up

    def test_exception(self):
        with pytest.raises(ValueError, match="frames_between: expected >= 0"):
            spline_path(ring(3), UP, 4.0, frames_between=-2)


class TestFocusPoint:
    def test_ring(self):
        torch.testing.assert_close(
            focus_point(ring(5)[:, :3, 3], ring(5)[:, :3, 2]), torch.zeros(3, dtype=torch.float64)
        )

    def test_parallel_or_behind(self):
        c2w = torch.eye(4, dtype=torch.float64).repeat(4, 1, 1)
        c2w[:, 0, 3] = torch.arange(4.0)  # a street: all looking along +z
        assert focus_point(c2w[:, :3, 3], c2w[:, :3, 2]) is None
        ring_out = ring(5)
        assert focus_point(ring_out[:, :3, 3], -ring_out[:, :3, 2]) is None  # looking away from it

    def test_exception(self):
        with pytest.raises(ValueError, match="forward"):
            focus_point(torch.zeros(3, 3), torch.zeros(2, 3))


class TestOrbitPath:
    def test_ring_comes_back(self):
        keys = ring(8, radius=3.0, height=1.5)
        path = orbit_path(keys, UP, 8)
        # the circle through the ring's cameras, from the first, turning their way, looking at the centre
        torch.testing.assert_close(path.cam_to_world, keys, rtol=0, atol=1e-12)
        torch.testing.assert_close(path.t, torch.arange(8, dtype=torch.float64) / 8)

    def test_turns_the_way_the_cameras_do(self):
        keys = ring(8, turn=-1.0)  # clockwise seen from above
        path = orbit_path(keys, UP, 16)
        torch.testing.assert_close(path.cam_to_world[::2], keys, rtol=0, atol=1e-12)

    def test_street_fallback_centre(self):
        c2w = look_at(
            torch.tensor([[0.0, 0, 0], [2.0, 0, 0], [4.0, 0, 0]], dtype=torch.float64),
            torch.tensor([[0.0, 10, 0], [2.0, 10, 0], [4.0, 10, 0]], dtype=torch.float64),
            UP,
        )  # a street: parallel axes, so the middle of what they look at, 5 m ahead
        path = orbit_path(c2w, UP, 4, focus_depth=5.0)
        centre = torch.tensor([2.0, 5.0, 0.0], dtype=torch.float64)
        dist = (path.cam_to_world[:, :3, 3] - centre).norm(dim=-1)
        torch.testing.assert_close(dist, torch.full((4,), math.hypot(2.0, 5.0), dtype=torch.float64))
        ahead = centre - path.cam_to_world[:, :3, 3]
        torch.testing.assert_close(path.cam_to_world[:, :3, 2], ahead / ahead.norm(dim=-1, keepdim=True))

    def test_exception(self):
        with pytest.raises(ValueError, match="num_frames: expected >= 1, got 0"):
            orbit_path(ring(3), UP, 0)
