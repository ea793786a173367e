"""Tests of plane-induced homographies and warps (vadgs.geometry.homography)."""

from __future__ import annotations

import pytest
import torch
from kornia.geometry.transform import warp_perspective
from torch.autograd import gradcheck

from vadgs.geometry import (
    apply_homography,
    homography_warp,
    invert_rigid,
    pixel_grid,
    plane_distance,
    plane_homography,
    project_points,
    relative_pose,
    warp_patches,
)

DT = torch.float64


def _K(n=1, f=40.0, size=(30, 40)):
    h, w = size
    return torch.tensor([[f, 0, (w - 1) / 2], [0, f * 1.05, (h - 1) / 2], [0, 0, 1]], dtype=DT).expand(
        n, 3, 3
    )


def _small_motion(n, seed=0, angle=0.08, shift=0.3) -> torch.Tensor:
    """Rigid src_from_ref transforms: small rotations (Rodrigues) and translations."""
    g = torch.Generator().manual_seed(seed)
    T = torch.eye(4, dtype=DT).repeat(n, 1, 1)
    for i in range(n):
        axis = torch.randn(3, generator=g, dtype=DT)
        axis = axis / axis.norm()
        a = angle * torch.rand(1, generator=g, dtype=DT)
        k = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], dtype=DT)
        T[i, :3, :3] = torch.eye(3, dtype=DT) + torch.sin(a) * k + (1 - torch.cos(a)) * k @ k
        T[i, :3, 3] = shift * torch.randn(3, generator=g, dtype=DT)
    return T


def _plane_points(normal, d, K, pix):
    """3D points (reference camera frame) of the plane n.X + d = 0 seen at pixels ``pix (N, 2)``."""
    rays = torch.cat([pix, torch.ones_like(pix[:, :1])], 1) @ torch.linalg.inv(K).T  # z = 1
    z = -d / (rays @ normal)
    return rays * z[:, None]


class TestPlaneHomography:
    def test_smoke(self):
        H = plane_homography(
            _K(), _K(), _small_motion(1), torch.tensor([[0.0, 0, -1]], dtype=DT), torch.ones(1, dtype=DT)
        )
        assert H.shape == (1, 3, 3)

    @pytest.mark.parametrize(
        "normal", [(0.0, 0.0, -1.0), (0.3, -0.2, -1.0), (-0.5, 0.6, -0.7)], ids=["fronto", "slant", "steep"]
    )
    def test_equals_projected_plane_points(self, normal):
        """H maps reference pixels to where the actual plane points project in the source views."""
        n_views = 4
        K_ref, K_src = _K(n_views), _K(n_views, f=45.0)
        T = _small_motion(n_views, seed=1)
        normal = torch.tensor(normal, dtype=DT)
        normal = normal / normal.norm()
        d = torch.tensor(4.0, dtype=DT)  # plane n.X + d = 0, 4 m from the reference camera
        pix = pixel_grid((30, 40), dtype=DT).reshape(-1, 2)[::7]
        X = _plane_points(normal, d, K_ref[0], pix)
        assert (X[:, 2] > 0).all()
        H = plane_homography(K_ref, K_src, T, normal.expand(n_views, 3), d.expand(n_views))
        for b in range(n_views):
            X_src = X @ T[b, :3, :3].T + T[b, :3, 3]
            uv, _ = project_points(X_src[None], K_src[b : b + 1])
            torch.testing.assert_close(apply_homography(H[b], pix), uv[0])

    def test_per_pixel_planes_from_depth(self):
        """Per-pixel planes (B, H, W) built with plane_distance from depth and normals."""
        K = _K(2, size=(6, 8))
        T = _small_motion(2, seed=2)
        g = torch.Generator().manual_seed(3)
        depth = 2 + 3 * torch.rand(2, 6, 8, generator=g, dtype=DT)
        normals = torch.nn.functional.normalize(
            torch.randn(2, 6, 8, 3, generator=g, dtype=DT) * 0.3 + torch.tensor([0, 0, -1.0], dtype=DT),
            dim=-1,
        )
        pix = pixel_grid((6, 8), dtype=DT)
        rays = torch.cat([pix, torch.ones(6, 8, 1, dtype=DT)], -1) @ torch.linalg.inv(K[0]).T
        d = plane_distance(depth, normals, rays)
        X = rays * depth[..., None]  # the pixel's own 3D point lies on its plane
        torch.testing.assert_close((normals * X).sum(-1) + d, torch.zeros_like(d))
        H = plane_homography(K, K, T, normals, d)
        assert H.shape == (2, 6, 8, 3, 3)
        X_src = X @ T[:, None, :3, :3].transpose(-1, -2) + T[:, None, None, :3, 3]
        uv, _ = project_points(X_src.reshape(2, -1, 3), K)
        torch.testing.assert_close(apply_homography(H, pix).reshape(2, -1, 2), uv)

    def test_relative_pose_of_two_cameras(self):
        """The homography of a world plane between two world cameras, through relative_pose."""
        w2r, w2s = torch.eye(4, dtype=DT)[None], _small_motion(1, seed=4) @ torch.eye(4, dtype=DT)
        src_from_ref = relative_pose(w2r, w2s)
        normal, d = torch.tensor([[0.0, 0.2, -1.0]], dtype=DT), torch.tensor([5.0], dtype=DT)
        normal = normal / normal.norm()
        pix = torch.tensor([[3.0, 4.0], [20.0, 10.0]], dtype=DT)
        X = _plane_points(normal[0], d[0], _K()[0], pix)
        uv, _ = project_points(X[None], _K(), w2s @ invert_rigid(w2r))
        H = plane_homography(_K(), _K(), src_from_ref, normal, d)
        torch.testing.assert_close(apply_homography(H[0], pix), uv[0])

    def test_gradcheck(self):
        K = _K(1)
        T = _small_motion(1, seed=5).requires_grad_()
        normals = torch.tensor([[[0.1, -0.1, -1.0], [0.0, 0.3, -0.9]]], dtype=DT, requires_grad=True)
        dist = torch.tensor([[3.0, 4.5]], dtype=DT, requires_grad=True)
        assert gradcheck(lambda t, n, d: plane_homography(K, K, t, n, d), (T, normals, dist))

    def test_exception(self):
        K, T = _K(2), _small_motion(2)
        n, d = torch.tensor([[0.0, 0, -1]] * 2, dtype=DT), torch.ones(2, dtype=DT)
        with pytest.raises(ValueError, match="K_src"):
            plane_homography(K, _K(3), T, n, d)
        with pytest.raises(ValueError, match="src_from_ref"):
            plane_homography(K, K, T[:, :3], n, d)
        with pytest.raises(ValueError, match="normals"):
            plane_homography(K, K, T, n[:, :2], d)
        with pytest.raises(ValueError, match="distances"):
            plane_homography(K, K, T, n, d[:, None])


def _texture(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """A smooth texture on plane coordinates (metres)."""
    return 0.5 + 0.25 * torch.sin(3.0 * a) * torch.cos(2.0 * b) + 0.2 * torch.sin(1.3 * a + 0.7 * b)


def _render_plane(K, cam_from_plane, size):
    """Analytic render of the textured plane z = 0 (plane frame) into a camera: (1, 1, H, W)."""
    h, w = size
    pix = pixel_grid(size, dtype=DT).reshape(-1, 2)
    rays = torch.cat([pix, torch.ones(h * w, 1, dtype=DT)], 1) @ torch.linalg.inv(K).T
    R, t = cam_from_plane[:3, :3], cam_from_plane[:3, 3]
    o, dirs = -R.T @ t, rays @ R  # camera centre and ray directions in the plane frame
    s = -o[2] / dirs[:, 2]
    p = o + s[:, None] * dirs
    return _texture(p[:, 0], p[:, 1]).reshape(1, 1, h, w)


class TestHomographyWarp:
    def test_smoke(self):
        out = homography_warp(torch.rand(1, 3, 5, 6), torch.eye(3)[None], (4, 7))
        assert out.shape == (1, 3, 4, 7)

    def test_identity_and_shift(self):
        img = torch.rand(2, 3, 8, 10, dtype=DT)
        torch.testing.assert_close(homography_warp(img, torch.eye(3, dtype=DT).expand(2, 3, 3), (8, 10)), img)
        H = torch.eye(3, dtype=DT).repeat(2, 1, 1)
        H[:, 0, 2] = 2.0  # out[v, u] = src[v, u + 2]
        out = homography_warp(img, H, (8, 10))
        torch.testing.assert_close(out[..., :8], img[..., 2:])

    def test_equals_kornia(self):
        g = torch.Generator().manual_seed(6)
        img = torch.rand(1, 1, 12, 14, generator=g, dtype=DT)
        H = torch.eye(3, dtype=DT)[None] + 0.01 * torch.randn(1, 3, 3, generator=g, dtype=DT)
        ref = warp_perspective(img, torch.linalg.inv(H), (12, 14), align_corners=True)
        torch.testing.assert_close(homography_warp(img, H, (12, 14)), ref)

    def test_rendered_plane(self):
        """Warp a rendered source view of a textured plane into the reference: equals its render."""
        size = (48, 64)
        K = _K(1, f=60.0, size=size)[0]
        ref_from_plane = torch.eye(4, dtype=DT)
        a = 0.35  # the plane is slanted w.r.t. the reference camera
        ref_from_plane[:3, :3] = torch.tensor(
            [
                [1, 0, 0],
                [0, torch.cos(torch.tensor(a)), -torch.sin(torch.tensor(a))],
                [0, torch.sin(torch.tensor(a)), torch.cos(torch.tensor(a))],
            ],
            dtype=DT,
        )
        ref_from_plane[:3, 3] = torch.tensor([-0.5, 0.2, 4.0], dtype=DT)
        src_from_ref = _small_motion(1, seed=7, angle=0.05, shift=0.25)[0]
        ref_img = _render_plane(K, ref_from_plane, size)
        src_img = _render_plane(K, src_from_ref @ ref_from_plane, size)
        # the plane in the reference frame: normal = R e_z, through the point t
        normal = ref_from_plane[:3, 2]
        d = -(normal @ ref_from_plane[:3, 3])
        if d < 0:
            normal, d = -normal, -d
        H = plane_homography(K[None], K[None], src_from_ref[None], normal[None], d[None])
        warped = homography_warp(src_img, H, size)
        # compare where the source sample lies well inside the source image
        xy = apply_homography(H[0], pixel_grid(size, dtype=DT))
        inner = (xy[..., 0] > 1) & (xy[..., 0] < size[1] - 2) & (xy[..., 1] > 1) & (xy[..., 1] < size[0] - 2)
        assert inner.float().mean() > 0.6
        err = (warped[0, 0] - ref_img[0, 0]).abs()[inner]
        assert err.max() < 0.03  # bilinear interpolation of a smooth texture
        assert err.mean() < 0.005
        # a wrong plane warps visibly worse
        wrong = homography_warp(
            src_img, plane_homography(K[None], K[None], src_from_ref[None], normal[None], 2 * d[None]), size
        )
        assert (wrong[0, 0] - ref_img[0, 0]).abs()[inner].mean() > 5 * err.mean()

    def test_gradcheck(self):
        img = torch.rand(1, 1, 5, 6, dtype=DT, requires_grad=True)
        H = (torch.eye(3, dtype=DT)[None] + 0.02 * torch.rand(1, 3, 3, dtype=DT)).requires_grad_()
        assert gradcheck(lambda i, h: homography_warp(i, h, (4, 5)), (img, H))

    def test_exception(self):
        with pytest.raises(ValueError, match="src"):
            homography_warp(torch.rand(3, 5, 6), torch.eye(3)[None], (4, 4))
        with pytest.raises(ValueError, match="H_ref_to_src"):
            homography_warp(torch.rand(2, 1, 5, 6), torch.eye(3)[None], (4, 4))


class TestWarpPatches:
    def test_cardinality(self):
        patches, inside = warp_patches(
            torch.rand(2, 3, 8, 9), torch.eye(3).expand(2, 5, 3, 3), torch.rand(5, 2) * 8, torch.zeros(4, 2)
        )
        assert patches.shape == (2, 3, 5, 4) and inside.shape == (2, 5, 4) and inside.dtype == torch.bool

    def test_equals_homography_warp(self):
        """Per-patch samples through the same H equal the whole-image warp at centre + offset."""
        g = torch.Generator().manual_seed(8)
        src = torch.rand(1, 2, 20, 24, generator=g, dtype=DT)
        H = torch.eye(3, dtype=DT)[None] + torch.tensor(
            [[0.02, 0.01, 1.5], [-0.01, 0.03, -0.7], [1e-4, 2e-4, 0]], dtype=DT
        )
        warped = homography_warp(src, H, (20, 24))
        centers = torch.tensor([[5.0, 6.0], [12.0, 9.0], [17.0, 14.0]], dtype=DT)
        offsets = torch.tensor([[-1.0, -1.0], [0.0, 0.0], [1.0, 0.0], [2.0, 1.0]], dtype=DT)
        patches, inside = warp_patches(src, H[:, None].expand(1, 3, 3, 3), centers, offsets)
        assert inside.all()
        for p in range(3):
            for s in range(4):
                u, v = (centers[p] + offsets[s]).long().tolist()
                torch.testing.assert_close(patches[0, :, p, s], warped[0, :, v, u])

    def test_inside_mask(self):
        src = torch.rand(1, 1, 4, 4)
        _, inside = warp_patches(
            src,
            torch.eye(3).expand(1, 1, 3, 3),
            torch.tensor([[3.0, 3.0]]),
            torch.tensor([[0.0, 0.0], [0.6, 0.0]]),
        )
        assert inside.tolist() == [[[True, False]]]

    def test_gradcheck(self):
        src = torch.rand(1, 1, 6, 7, dtype=DT, requires_grad=True)
        H = (
            (torch.eye(3, dtype=DT) + 0.01 * torch.rand(3, 3, dtype=DT))
            .expand(1, 2, 3, 3)
            .clone()
            .requires_grad_()
        )
        centers = torch.tensor([[2.3, 2.6], [3.4, 1.7]], dtype=DT)
        offsets = torch.tensor([[0.0, 0.0], [1.0, 0.5]], dtype=DT)
        assert gradcheck(lambda s, h: warp_patches(s, h, centers, offsets)[0], (src, H))

    def test_exception(self):
        src, H = torch.rand(1, 1, 6, 7), torch.eye(3).expand(1, 2, 3, 3)
        with pytest.raises(ValueError, match="H"):
            warp_patches(src, torch.eye(3).expand(2, 2, 3, 3), torch.zeros(2, 2), torch.zeros(1, 2))
        with pytest.raises(ValueError, match="centers"):
            warp_patches(src, H, torch.zeros(3, 2), torch.zeros(1, 2))
        with pytest.raises(ValueError, match="offsets"):
            warp_patches(src, H, torch.zeros(2, 2), torch.zeros(1, 3))
