from __future__ import annotations

import pytest
import torch

from vadgs.mvs import FusedPoints, FusionConfig, fuse_depth_maps


def _views(b=3, h=10, w=12, z=2.0):
    K = torch.tensor([[12.0, 0, (w - 1) / 2], [0, 12.0, (h - 1) / 2], [0, 0, 1]]).repeat(b, 1, 1)
    w2c = torch.eye(4).repeat(b, 1, 1)
    w2c[:, 0, 3] = torch.arange(b) * -0.2 / 1.2  # 1 px disparity per view at z = 2
    depth = torch.full((b, 1, h, w), z)
    normal = torch.tensor([0.0, 0.0, -1.0]).reshape(1, 3, 1, 1).expand(b, 3, h, w)
    images = torch.rand(b, 3, h, w)
    return depth, images, K, w2c, normal


class TestFuseDepthMaps:
    def test_smoke_and_cardinality(self):
        d, img, K, w2c, n = _views()
        out = fuse_depth_maps(d, img, K, w2c, normal=n)
        assert isinstance(out, FusedPoints)
        m = out.points.shape[0]
        assert m > 0
        assert out.normals.shape == (m, 3) and out.colors.shape == (m, 3)
        assert out.view_index.shape == out.num_views.shape == (m,)

    def test_points_on_the_plane(self):
        d, img, K, w2c, n = _views()
        out = fuse_depth_maps(d, img, K, w2c, normal=n)
        assert torch.allclose(out.points[:, 2], torch.full_like(out.points[:, 2], 2.0), atol=1e-5)
        assert torch.allclose(out.normals, torch.tensor([0.0, 0, -1]).expand_as(out.normals), atol=1e-5)
        assert (out.num_views >= 3).all()
        assert ((out.colors >= 0) & (out.colors <= 1)).all()
        # each surface point once: no duplicates from the other views
        assert out.points.shape[0] <= d[0].numel()

    def test_inconsistent_views_fuse_nothing(self):
        d, img, K, w2c, n = _views()
        d = d.clone()
        d[1] *= 1.1
        d[2] *= 0.9
        assert fuse_depth_maps(d, img, K, w2c, normal=n).points.shape[0] == 0
        # normals that disagree are rejected too
        n2 = n.clone()
        n2[1:] = torch.tensor([1.0, 0.0, 0.0]).reshape(1, 3, 1, 1)
        d, img, K, w2c, _ = _views()
        assert fuse_depth_maps(d, img, K, w2c, normal=n2).points.shape[0] == 0

    def test_single_view_min_views_zero(self):
        d, img, K, w2c, n = _views(b=1)
        mask = torch.zeros_like(d, dtype=torch.bool)
        mask[..., 2:5, 3:7] = True
        out = fuse_depth_maps(d, img, K, w2c, normal=n, mask=mask, config=FusionConfig(min_views=0))
        assert out.points.shape[0] == 12
        assert torch.allclose(out.colors, img[0].reshape(3, -1)[:, mask[0, 0].reshape(-1)].T)

    def test_world_frame(self):
        d, img, K, w2c, n = _views()
        w2c = w2c.clone()
        w2c[:, 2, 3] = -1.0  # the world origin is 1 m behind the cameras
        out = fuse_depth_maps(d, img, K, w2c, normal=n)
        assert torch.allclose(out.points[:, 2], torch.full_like(out.points[:, 2], 3.0), atol=1e-5)

    def test_exceptions(self):
        d, img, K, w2c, n = _views()
        with pytest.raises(ValueError, match="images"):
            fuse_depth_maps(d, img[:2], K, w2c)
        with pytest.raises(ValueError, match="normal"):
            fuse_depth_maps(d, img, K, w2c, normal=n[:, :2])
        with pytest.raises(ValueError, match="min_views"):
            FusionConfig(min_views=-1)


def test_without_deduplication_every_valid_pixel_is_a_point():
    """``deduplicate=False``: each valid pixel's point, view by view in pixel order (a naive loop)."""
    g = torch.Generator().manual_seed(0)
    b, h, w = 3, 6, 8
    K = torch.tensor([[10.0, 0, 3.5], [0, 10.0, 2.5], [0, 0, 1]]).repeat(b, 1, 1)
    w2c = torch.eye(4).repeat(b, 1, 1)
    w2c[:, 0, 3] = torch.tensor([0.0, -0.1, 0.1])
    w2c[2, :3, :3] = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    depth = 1 + torch.rand(b, 1, h, w, generator=g)
    depth[0, 0, 0, :3] = 0
    mask = torch.rand(b, 1, h, w, generator=g) > 0.3
    normal = torch.randn(b, 3, h, w, generator=g)
    images = torch.rand(b, 3, h, w, generator=g) * 1.2
    fused = fuse_depth_maps(depth, images, K, w2c, normal, mask, FusionConfig(min_views=0, deduplicate=False))
    pts, nrm, col, view = [], [], [], []
    for i in range(b):
        c2w = torch.linalg.inv(w2c[i])
        for y in range(h):
            for x in range(w):
                z = depth[i, 0, y, x]
                if z > 0 and mask[i, 0, y, x]:
                    cam = z * torch.linalg.inv(K[i]) @ torch.tensor([float(x), float(y), 1.0])
                    pts.append(c2w[:3, :3] @ cam + c2w[:3, 3])
                    n = c2w[:3, :3] @ normal[i, :, y, x]
                    nrm.append(n / n.norm())
                    col.append(images[i, :, y, x].clamp(0, 1))
                    view.append(i)
    assert torch.allclose(fused.points, torch.stack(pts), atol=1e-5)
    assert torch.allclose(fused.normals, torch.stack(nrm), atol=1e-5)
    assert torch.equal(fused.colors, torch.stack(col))
    assert fused.view_index.tolist() == view and (fused.num_views == 1).all()
