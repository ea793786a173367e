"""Tests of pinhole cameras and poses (vadgs.geometry.camera)."""

from __future__ import annotations

import pytest
import torch
from torch.autograd import gradcheck

from vadgs.geometry import (
    Cameras,
    backproject_depth,
    camera_centers,
    cameras_in_object_frame,
    invert_rigid,
    observing_views,
    pixel_grid,
    project_points,
    relative_pose,
    scale_intrinsics,
    shift_K,
)


def random_rigid(n: int, seed: int = 0, dtype=torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q, _ = torch.linalg.qr(torch.randn(n, 3, 3, generator=g, dtype=dtype))
    q = q * torch.linalg.det(q)[:, None, None].sign()  # proper rotations
    T = torch.eye(4, dtype=dtype).repeat(n, 1, 1)
    T[:, :3, :3] = q
    T[:, :3, 3] = torch.randn(n, 3, generator=g, dtype=dtype)
    return T


def intrinsics(n: int = 1, f=(50.0, 55.0), c=(15.5, 11.5), dtype=torch.float64) -> torch.Tensor:
    K = torch.tensor([[f[0], 0, c[0]], [0, f[1], c[1]], [0, 0, 1]], dtype=dtype)
    return K.expand(n, 3, 3).clone()


class TestInvertRigid:
    def test_feature(self):
        T = random_rigid(5)
        eye = torch.eye(4, dtype=torch.float64).expand(5, 4, 4)
        torch.testing.assert_close(T @ invert_rigid(T), eye)
        torch.testing.assert_close(invert_rigid(T), torch.linalg.inv(T))

    def test_cardinality(self):
        assert invert_rigid(random_rigid(6).reshape(2, 3, 4, 4)).shape == (2, 3, 4, 4)

    def test_gradcheck(self):
        T = random_rigid(2).requires_grad_()
        assert gradcheck(invert_rigid, (T,))

    def test_exception(self):
        with pytest.raises(ValueError, match="transform"):
            invert_rigid(torch.eye(3))


class TestRelativePose:
    def test_maps_ref_camera_points_to_src(self):
        w2r, w2s = random_rigid(3, 1), random_rigid(3, 2)
        p_world = torch.randn(3, 4, 1, dtype=torch.float64)
        p_world = torch.cat([p_world.expand(3, 4, 5).transpose(1, 2)[..., :3], torch.ones(3, 5, 1)], -1)
        p_ref = p_world @ w2r.transpose(1, 2)
        p_src = p_world @ w2s.transpose(1, 2)
        torch.testing.assert_close(p_ref @ relative_pose(w2r, w2s).transpose(1, 2), p_src)

    def test_identity(self):
        T = random_rigid(2)
        torch.testing.assert_close(relative_pose(T, T), torch.eye(4, dtype=torch.float64).expand(2, 4, 4))

    def test_exception(self):
        with pytest.raises(ValueError, match="world_to_src"):
            relative_pose(random_rigid(1), torch.eye(3))


class TestProjectBackproject:
    def test_smoke(self):
        uv, z = project_points(torch.tensor([[[0.0, 0.0, 2.0]]]), intrinsics(dtype=torch.float32))
        assert uv.tolist() == [[[15.5, 11.5]]] and z.tolist() == [[2.0]]

    def test_round_trip(self):
        """backproject(depth) then project lands on the pixel centres with the same depth."""
        g = torch.Generator().manual_seed(3)
        depth = 1.0 + 5 * torch.rand(2, 1, 24, 32, generator=g, dtype=torch.float64)
        K = intrinsics(2)
        c2w = random_rigid(2, 4)
        pts = backproject_depth(depth, K, c2w)  # (B, 3, H, W) world
        assert pts.shape == (2, 3, 24, 32)
        uv, z = project_points(pts.flatten(2).transpose(1, 2), K, invert_rigid(c2w))
        grid = pixel_grid((24, 32), dtype=torch.float64).reshape(1, -1, 2).expand(2, -1, -1)
        torch.testing.assert_close(uv, grid)
        torch.testing.assert_close(z, depth.flatten(1))

    def test_camera_frame_without_pose(self):
        depth = torch.full((1, 1, 4, 6), 3.0, dtype=torch.float64)
        pts = backproject_depth(depth, intrinsics())
        torch.testing.assert_close(pts[:, 2], depth[:, 0])
        torch.testing.assert_close(
            pts[0, :, 2, 3],
            torch.tensor([(3 - 15.5) * 3 / 50, (2 - 11.5) * 3 / 55, 3.0], dtype=torch.float64),
        )

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_methods_agree(self, dtype):
        """The two arithmetics of backproject_depth: the same points to float rounding."""
        g = torch.Generator().manual_seed(7)
        depth = (1.0 + 40 * torch.rand(3, 1, 24, 32, generator=g, dtype=torch.float64)).to(dtype)
        K, c2w = intrinsics(3, dtype=dtype), random_rigid(3, 8, dtype=dtype)
        for pose in (None, c2w):
            a = backproject_depth(depth, K, pose)
            b = backproject_depth(depth, K, pose, method="inverse")
            assert b.shape == a.shape and b.dtype == dtype
            tol = 1e-5 if dtype == torch.float32 else 1e-12
            torch.testing.assert_close(b, a, rtol=tol, atol=tol)

    def test_inverse_reads_the_skew(self):
        """K^-1 (u, v, 1): with a skewed K the round trip through project_points (which reads the
        skew) lands on the pixel centres; kornia's rays ignore the skew."""
        depth = 1.0 + torch.rand(2, 1, 6, 8, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
        K = intrinsics(2)
        K[:, 0, 1] = 4.0
        c2w = random_rigid(2, 10)
        grid = pixel_grid((6, 8), dtype=torch.float64).reshape(1, -1, 2).expand(2, -1, -1)
        pts = backproject_depth(depth, K, c2w, method="inverse")
        uv, z = project_points(pts.flatten(2).transpose(1, 2), K, invert_rigid(c2w))
        torch.testing.assert_close(uv, grid)
        torch.testing.assert_close(z, depth.flatten(1))
        uv, _ = project_points(
            backproject_depth(depth, K, c2w).flatten(2).transpose(1, 2), K, invert_rigid(c2w)
        )
        assert float((uv - grid).abs().max()) > 0.1

    def test_inverse_against_a_loop(self):
        """Each pixel by hand: z K^-1 (u, v, 1)^T, then R X + t."""
        depth = 1.0 + torch.rand(1, 1, 3, 4, generator=torch.Generator().manual_seed(11), dtype=torch.float64)
        K, T = intrinsics(), random_rigid(1, 12)
        Kinv = torch.linalg.inv(K[0])
        got = backproject_depth(depth, K, T, method="inverse")[0]
        for v in range(3):
            for u in range(4):
                cam = depth[0, 0, v, u] * (Kinv @ torch.tensor([u, v, 1.0], dtype=torch.float64))
                torch.testing.assert_close(got[:, v, u], T[0, :3, :3] @ cam + T[0, :3, 3], rtol=0, atol=1e-12)

    def test_pixel_grid(self):
        grid = pixel_grid((2, 3))
        assert grid.shape == (2, 3, 2) and grid[1, 2].tolist() == [2.0, 1.0]

    def test_camera_centers(self):
        T = random_rigid(3, 5)
        c = camera_centers(T)
        torch.testing.assert_close(c, invert_rigid(T)[:, :3, 3])
        _, z = project_points(c[:, None], intrinsics(3), T)
        torch.testing.assert_close(z, torch.zeros(3, 1, dtype=torch.float64))

    def test_gradcheck(self):
        pts = (torch.randn(1, 4, 3, dtype=torch.float64) + torch.tensor([0, 0, 5.0])).requires_grad_()
        K = intrinsics().requires_grad_()
        T = random_rigid(1, 6)
        T[:, :3, 3] = torch.tensor([0.1, 0.2, 0.3])
        T.requires_grad_()
        assert gradcheck(lambda p, k, t: project_points(p, k, t), (pts, K, T))
        depth = (1 + torch.rand(1, 1, 3, 4, dtype=torch.float64)).requires_grad_()
        assert gradcheck(lambda d, k, t: backproject_depth(d, k, t), (depth, K, T))
        assert gradcheck(lambda d, k, t: backproject_depth(d, k, t, method="inverse"), (depth, K, T))

    def test_exception(self):
        with pytest.raises(ValueError, match="points"):
            project_points(torch.zeros(1, 4, 2), intrinsics())
        with pytest.raises(ValueError, match="K"):
            project_points(torch.zeros(2, 4, 3), intrinsics(1))
        with pytest.raises(ValueError, match="world_to_cam"):
            project_points(torch.zeros(1, 4, 3), intrinsics(1), torch.eye(4))
        with pytest.raises(ValueError, match="depth"):
            backproject_depth(torch.zeros(1, 4, 4), intrinsics())
        with pytest.raises(ValueError, match="cam_to_world"):
            backproject_depth(torch.zeros(1, 1, 4, 4), intrinsics(), torch.eye(4)[None, :3])
        with pytest.raises(ValueError, match="method: expected 'kornia' or 'inverse', got 'inv'"):
            backproject_depth(torch.zeros(1, 1, 4, 4), intrinsics(), method="inv")


class TestScaleIntrinsics:
    def test_pixel_centre_convention(self):
        """A 3D point's pixel x maps to s (x + 0.5) - 0.5 under a resize by s."""
        K = intrinsics()
        p = torch.tensor([[[0.3, -0.2, 2.0], [-1.0, 0.5, 4.0]]], dtype=torch.float64)
        uv, _ = project_points(p, K)
        for s in (0.5, 2.0, 0.25):
            uv_s, _ = project_points(p, scale_intrinsics(K, s))
            torch.testing.assert_close(uv_s, s * (uv + 0.5) - 0.5)

    def test_image_centre_stays_centre(self):
        h, w = 288, 480
        K = intrinsics(c=((w - 1) / 2, (h - 1) / 2))
        Ks = scale_intrinsics(K, 0.5)
        assert Ks[0, 0, 2].item() == (w / 2 - 1) / 2 and Ks[0, 1, 2].item() == (h / 2 - 1) / 2
        assert Ks[0, 0, 0].item() == 25.0 and Ks[0, 2].tolist() == [0.0, 0.0, 1.0]

    def test_unbatched(self):
        assert scale_intrinsics(intrinsics()[0], 2.0).shape == (3, 3)

    def test_exception(self):
        with pytest.raises(ValueError, match="K"):
            scale_intrinsics(torch.eye(4), 2.0)


class TestCamerasInObjectFrame:
    def test_feature(self):
        """A point fixed in the object frame has the same camera coordinates either way."""
        w2c, o2w = random_rigid(4, 7), random_rigid(4, 8)
        p_obj = torch.tensor([0.3, -1.0, 2.0, 1.0], dtype=torch.float64)
        p_world = o2w @ p_obj
        torch.testing.assert_close(
            cameras_in_object_frame(w2c, o2w) @ p_obj, (w2c @ p_world[..., None])[..., 0]
        )

    def test_exception(self):
        with pytest.raises(ValueError, match="object_to_world"):
            cameras_in_object_frame(random_rigid(2), random_rigid(3))


class TestCameras:
    def test_smoke(self):
        cams = Cameras(intrinsics(2), random_rigid(2), (24, 32))
        assert len(cams) == 2 and cams.image_size == (24, 32)
        assert cams.device == torch.device("cpu")

    def test_properties_and_indexing(self):
        T = random_rigid(3, 9)
        cams = Cameras(intrinsics(3), T, [24, 32])
        assert cams.image_size == (24, 32)
        torch.testing.assert_close(cams.cam_to_world, torch.linalg.inv(T))
        torch.testing.assert_close(cams.centers, camera_centers(T))
        assert len(cams[1]) == 1 and len(cams[[0, 2]]) == 2 and len(cams[torch.tensor([1])]) == 1
        torch.testing.assert_close(cams[2].world_to_cam[0], T[2])
        back = Cameras.from_cam_to_world(intrinsics(3), cams.cam_to_world, (24, 32))
        torch.testing.assert_close(back.world_to_cam, T)
        half = cams.rescale(0.5)
        assert half.image_size == (12, 16)
        torch.testing.assert_close(half.K, scale_intrinsics(cams.K, 0.5))
        assert cams.to(dtype=torch.float32).K.dtype == torch.float32
        o2w = random_rigid(3, 10)
        torch.testing.assert_close(cams.in_object_frame(o2w).world_to_cam, T @ o2w)

    def test_exception(self):
        T = random_rigid(2)
        bad = T.clone()
        bad[0, 0, 3] = float("nan")
        with pytest.raises(ValueError, match="world_to_cam: expected finite"):
            Cameras(intrinsics(2), bad, (4, 4))
        badK = intrinsics(2)
        badK[1, 0, 0] = float("inf")
        with pytest.raises(ValueError, match="K: expected finite"):
            Cameras(badK, T, (4, 4))
        with pytest.raises(ValueError, match="world_to_cam"):
            Cameras(intrinsics(3), T, (4, 4))
        with pytest.raises(ValueError, match="image_size"):
            Cameras(intrinsics(2), T, (0, 4))
        with pytest.raises(ValueError, match="image_size"):
            Cameras(intrinsics(2), T, "big")


class TestShiftK:
    def test_a_point_lands_at_its_pixel_in_the_crop(self):
        K = torch.tensor([[[50.0, 0, 31.5], [0, 40.0, 23.5], [0, 0, 1]]], dtype=torch.float64)
        w2c = random_rigid(1)
        pts = torch.tensor([[[0.3, -0.2, 4.0], [1.0, 0.5, 6.0]]], dtype=torch.float64)
        pts = (pts - w2c[:, None, :3, 3]) @ w2c[0, :3, :3]  # in front of the camera
        uv, _ = project_points(pts, K, w2c)
        uv_crop, _ = project_points(pts, shift_K(K, 7, 5), w2c)
        assert torch.allclose(uv_crop, uv - torch.tensor([7.0, 5.0], dtype=torch.float64))
        assert K[0, 0, 2] == 31.5  # a copy: K is unchanged


def _cams(n=3, size=(10, 12)):
    g = torch.Generator().manual_seed(5)
    K = torch.tensor([[8.0, 0, 5.5], [0, 8.0, 4.5], [0, 0, 1]]).expand(n, 3, 3).clone()
    T = torch.eye(4).repeat(n, 1, 1)
    T[:, :3, 3] = torch.rand(n, 3, generator=g) - 0.5
    return Cameras(K, T, size)


class TestObservingViews:
    def test_equals_naive_loop(self):
        g = torch.Generator().manual_seed(6)
        pts = (torch.rand(200, 3, generator=g) - 0.5) * torch.tensor([6.0, 6.0, 8.0])
        cams = _cams(4)
        pi, vi = observing_views(pts, cams, view_ids=[10, 11, 12, 13])
        ref = []
        for p in range(200):
            for b in range(4):
                x = cams.world_to_cam[b, :3, :3] @ pts[p] + cams.world_to_cam[b, :3, 3]
                u = 8.0 * x[0] / x[2] + 5.5
                v = 8.0 * x[1] / x[2] + 4.5
                if x[2] > 0.1 and -0.5 <= u < 11.5 and -0.5 <= v < 9.5:
                    ref.append((p, 10 + b))
        assert list(zip(pi.tolist(), vi.tolist())) == ref
        assert len(ref) > 20

    def test_groups(self):
        g = torch.Generator().manual_seed(7)
        pts = (torch.rand(100, 3, generator=g) - 0.5) * torch.tensor([2.0, 2.0, 4.0]) + torch.tensor(
            [0, 0, 3.0]
        )
        cams = _cams(4)
        pg = torch.randint(0, 2, (100,), generator=g)
        cg = torch.tensor([0, 0, 1, 1])
        pi, vi = observing_views(pts, cams, groups=(pg, cg))
        full = set(zip(*observing_views(pts, cams)))
        full = {(int(p), int(v)) for p, v in full}
        want = {(p, v) for p, v in full if int(pg[p]) == int(cg[v])}
        assert set(zip(pi.tolist(), vi.tolist())) == want
        assert (pi.diff() >= 0).all()

    def test_exception(self):
        cams = _cams(2)
        with pytest.raises(ValueError, match="points"):
            observing_views(torch.rand(5, 2), cams)
        with pytest.raises(ValueError, match="view_ids"):
            observing_views(torch.rand(5, 3), cams, view_ids=[0])
        with pytest.raises(ValueError, match=r"groups\[0\]"):
            observing_views(torch.rand(5, 3), cams, groups=(torch.zeros(4), torch.zeros(2)))
