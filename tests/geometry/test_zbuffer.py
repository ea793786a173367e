"""Tests of the voxel z-buffer (vadgs.geometry.zbuffer) against naive and Embree references."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch

from vadgs.geometry import (
    Cameras,
    VoxelGrid,
    VoxelRaster,
    VoxelRasterizer,
    ZBufferConfig,
    backproject_depth,
    rasterize_voxels,
    voxelize,
)

from .geometry_reference import box_mesh, embree_zbuffer, naive_zbuffer, slab_entry

BOX = ZBufferConfig(depth_mode="box")
PLANE = ZBufferConfig(depth_mode="plane")
has_embree = importlib.util.find_spec("embreex") is not None


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """Small-tensor kernels: on a loaded shared machine one intra-op thread is much faster."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _look_at(eye, target, dtype=torch.float64) -> torch.Tensor:
    """world_to_cam of an OpenCV camera at ``eye`` looking at ``target`` with world z up."""
    eye, target = torch.as_tensor(eye, dtype=dtype), torch.as_tensor(target, dtype=dtype)
    z = target - eye
    z = z / z.norm()
    x = torch.linalg.cross(z, torch.tensor([0.0, 0.0, 1.0], dtype=dtype))
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    rot = torch.stack([x, y, z])
    T = torch.eye(4, dtype=dtype)
    T[:3, :3] = rot
    T[:3, 3] = -rot @ eye
    return T


def _cameras(size=(16, 24), f=18.0, eyes=((0.3, -0.2, 0.4),), target=(0.0, 6.0, 0.0), dtype=torch.float64):
    h, w = size
    K = torch.tensor([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]], dtype=dtype)
    T = torch.stack([_look_at(e, target, dtype) for e in eyes])
    return Cameras(K.expand(len(eyes), 3, 3).clone(), T, size)


def _cloud(n=40, seed=0, dtype=torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    pts = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * torch.tensor([4.0, 3.0, 2.0], dtype=dtype)
    return pts + torch.tensor([0.0, 6.0, 0.0], dtype=dtype)


class TestRasterizeVoxels:
    def test_smoke(self):
        cams = _cameras()
        out = rasterize_voxels((_cloud(), 0.5), cams, config=BOX)
        assert isinstance(out, VoxelRaster)

    def test_cardinality(self):
        cams = _cameras(eyes=((0.3, -0.2, 0.4), (-0.5, 0.0, 0.2), (0.0, 1.0, 0.5)))
        grid = voxelize(_cloud(200).float(), 0.3)
        out = rasterize_voxels(grid, cams.to(dtype=torch.float32))
        assert out.depth.shape == (3, 1, 16, 24) and out.depth.dtype == torch.float32
        assert out.index.shape == (3, 16, 24) and out.index.dtype == torch.int64
        assert len(out.visible) == 3
        for b in range(3):
            assert torch.equal(out.visible[b], torch.unique(out.index[b][out.index[b] >= 0]))
            assert torch.equal(out.depth[b, 0] > 0, out.index[b] >= 0)

    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_box_mode_equals_naive_reference(self, seed):
        """Exact ray-box entry depth: same index map, depth up to the float32 packing."""
        centers = _cloud(30, seed)
        cams = _cameras(eyes=((0.3, -0.2, 0.4), (1.5, 2.0, 1.8)))
        out = rasterize_voxels((centers, 0.8), cams, config=BOX)
        for b in range(len(cams)):
            depth, index = naive_zbuffer(centers, 0.8, cams.K[b], cams.world_to_cam[b], cams.image_size)
            assert (index >= 0).mean() > 0.2  # the scene covers a good part of the image
            np.testing.assert_array_equal(out.index[b].numpy(), index)
            np.testing.assert_allclose(out.depth[b, 0].numpy(), depth, rtol=1e-6)

    def test_occlusion(self):
        cams = _cameras(target=(0.0, 6.0, 0.4), eyes=((0.0, 0.0, 0.4),))
        centers = torch.tensor([[0.0, 5.0, 0.4], [0.0, 9.0, 0.4]], dtype=torch.float64)
        out = rasterize_voxels((centers, 1.0), cams, config=BOX)
        assert out.visible[0].tolist() == [0]  # the far voxel is entirely hidden
        assert out.depth[0, 0, 7, 11].item() == pytest.approx(4.5)
        alone = rasterize_voxels((centers[1:], 1.0), cams, config=BOX)
        assert alone.visible[0].tolist() == [0] and alone.depth[0, 0, 7, 11].item() == pytest.approx(8.5)

    def test_footprint_covers_every_hit_pixel(self):
        """A lone voxel owns exactly the pixels whose rays hit it (no more, no fewer)."""
        cams = _cameras(size=(40, 60), f=50.0, eyes=((0.7, 0.0, 1.3),))
        center = torch.tensor([[0.2, 4.0, 0.1]], dtype=torch.float64)
        out = rasterize_voxels((center, 0.8), cams, config=BOX)
        T, K = cams.world_to_cam[0].numpy(), cams.K[0].numpy()
        o = -T[:3, :3].T @ T[:3, 3]
        hit = np.zeros((40, 60), dtype=bool)
        for v in range(40):
            for u in range(60):
                d = T[:3, :3].T @ np.linalg.inv(K) @ np.array([u, v, 1.0])
                hit[v, u] = slab_entry(o, d, center[0].numpy() - 0.4, center[0].numpy() + 0.4) is not None
        assert hit.sum() > 50
        np.testing.assert_array_equal(out.index[0].numpy() == 0, hit)

    def test_near_and_far(self):
        cams = _cameras(target=(0.0, 6.0, 0.0), eyes=((0.0, 0.0, 0.0),))
        centers = torch.tensor([[0.0, 0.3, 0.0], [0.0, 20.0, 0.0]], dtype=torch.float64)
        out = rasterize_voxels((centers, 0.5), cams, config=ZBufferConfig(depth_mode="box", far=10.0))
        assert out.visible[0].numel() == 0  # the first has a corner behind near, the second is past far

    def test_only_observed(self):
        """A voxel whose visibility set lacks the view is not drawn: the one behind shows through."""
        pts = torch.tensor([[0.0, 5.0, 0.0], [0.0, 8.0, 0.0]])
        grid = voxelize(pts, 1.0, (torch.tensor([0, 1, 1]), torch.tensor([1, 0, 1])), num_views=2)
        cams = _cameras(eyes=((0.0, 0.0, 0.0),) * 2, target=(0.0, 6.0, 0.0)).to(dtype=torch.float32)
        full = rasterize_voxels(grid, cams, [0, 1], BOX)
        obs = rasterize_voxels(grid, cams, [0, 1], ZBufferConfig(depth_mode="box", only_observed=True))
        near_voxel = int(grid.point_to_voxel[0])
        far_voxel = int(grid.point_to_voxel[1])
        assert full.visible[0].tolist() == [near_voxel]
        assert obs.visible[0].tolist() == [far_voxel]  # view 0 saw only the far point
        assert obs.visible[1].tolist() == [near_voxel]  # view 1 saw both; the near one hides the far

    def test_plane_mode_on_tilted_plane(self):
        """Plane-in-box depth on a slanted surface: error far below the voxel size."""
        g = torch.Generator().manual_seed(3)
        ab = torch.rand(20000, 2, generator=g, dtype=torch.float64) * torch.tensor([6.0, 8.0]) - torch.tensor(
            [3.0, -2.0]
        )
        normal = torch.tensor([0.0, -0.3, 1.0], dtype=torch.float64)
        normal = normal / normal.norm()
        # the plane n . X = 0 through the origin, a road-like ramp seen at a grazing angle
        x, y = ab[:, 0], ab[:, 1]
        z = -(normal[0] * x + normal[1] * y) / normal[2]
        grid = voxelize(torch.stack([x, y, z], 1), 0.25)
        cams = _cameras(size=(48, 64), f=40.0, eyes=((0.0, -1.0, 1.6),), target=(0.0, 6.0, 1.0))
        box = rasterize_voxels(grid, cams, config=BOX)
        plane = rasterize_voxels(grid, cams, config=PLANE)
        # ground truth: ray / plane intersection
        T, K = cams.world_to_cam[0], cams.K[0]
        o = -T[:3, :3].T @ T[:3, 3]
        vs, us = torch.meshgrid(torch.arange(48.0), torch.arange(64.0), indexing="ij")
        d = torch.stack([us, vs, torch.ones_like(us)], -1).double() @ (T[:3, :3].T @ torch.linalg.inv(K)).T
        gt = -(normal @ o) / (d @ normal)
        # pixels well inside the sampled patch (its 3D point back-projected from GT depth)
        p = backproject_depth(gt[None, None].float(), K[None].float(), torch.linalg.inv(T)[None].float())[0]
        inner = (p[0].abs() < 2.5) & (p[1] > 2.5) & (p[1] < 9.5) & (gt > 0)
        m = inner & (plane.depth[0, 0] > 0)
        assert m.float().sum() > 0.95 * inner.float().sum()  # the plane mode covers the surface
        err_plane = (plane.depth[0, 0] - gt).abs()[m]
        assert err_plane.max() < 0.05 * 0.25
        err_box = (box.depth[0, 0] - gt).abs()[inner & (box.depth[0, 0] > 0)]
        assert err_box.median() > 5 * err_plane.median()  # boxes at grazing angles are far worse

    def test_plane_mode_falls_back_to_box_without_planes(self):
        pts = torch.tensor([[0.0, 5.0, 0.0]], dtype=torch.float64)  # one point: no normal
        grid = voxelize(pts, 0.5)
        cams = _cameras(eyes=((0.0, 0.0, 0.0),), target=(0.0, 6.0, 0.0))
        out = rasterize_voxels(grid, cams, config=PLANE)
        hit = out.index[0] >= 0
        assert hit.any()
        # z-depth of the mean point (clamped into the box, with slack)
        assert torch.allclose(out.depth[0, 0][hit], torch.full_like(out.depth[0, 0][hit], 5.0))

    @pytest.mark.skipif(not has_embree, reason="needs embreex")
    def test_agrees_with_embree(self):
        """Exact reference: Embree ray cast of the same boxes, pixel by pixel."""
        g = torch.Generator().manual_seed(7)
        pts = torch.rand(3000, 3, generator=g, dtype=torch.float64) * torch.tensor([8.0, 12.0, 3.0])
        pts = pts + torch.tensor([-4.0, 3.0, -1.0])
        grid = voxelize(pts, 0.4)
        eyes = ((0.0, 0.0, 1.0), (2.0, -1.0, 2.5), (-3.0, 1.0, 0.5))
        cams = _cameras(size=(60, 80), f=60.0, eyes=eyes, target=(0.0, 9.0, 0.5))
        out = rasterize_voxels(grid, cams, config=BOX)
        mesh = box_mesh(grid.centers.numpy(), 0.4)
        for b in range(len(cams)):
            depth, index = embree_zbuffer(mesh, cams.K[b], cams.world_to_cam[b], cams.image_size)
            same = out.index[b].numpy() == index
            assert same.mean() >= 0.99
            both = (index >= 0) & same
            np.testing.assert_allclose(out.depth[b, 0].numpy()[both], depth[both], rtol=1e-4, atol=1e-4)

    def test_float32_equals_float64(self):
        centers = _cloud(60, 5)
        cams = _cameras(eyes=((0.3, -0.2, 0.4), (1.0, 1.0, 1.0)))
        a = rasterize_voxels((centers, 0.4), cams, config=BOX)
        b = rasterize_voxels((centers.float(), 0.4), cams.to(dtype=torch.float32), config=BOX)
        assert b.depth.dtype == torch.float32 and a.depth.dtype == torch.float64
        assert (a.index == b.index).float().mean() > 0.995

    def test_sample_scene_accuracy(self, sample_grid):
        """Bundled street_a cut: plane mode within one voxel (0.2 m) of GT on most covered pixels."""
        scene, grid = sample_grid
        views = scene.test_views[:3]
        gt = scene.load_depths(views)
        out = rasterize_voxels(grid, scene.cameras(views), views)
        covered = (out.depth > 0) & (gt > 0)
        err = (out.depth - gt).abs()[covered]
        # measured 0.894 over all 24 views (0.2 m voxels); box mode only 0.17 (grazing road)
        assert (err <= 0.2).float().mean() > 0.85
        assert covered.float().sum() > 0.5 * (gt > 0).float().sum()

    def test_exception(self):
        cams = _cameras()
        centers = _cloud(5)
        with pytest.raises(ValueError, match="centers"):
            rasterize_voxels((centers[:, :2], 0.5), cams)
        with pytest.raises(ValueError, match="centers: expected finite"):
            rasterize_voxels((torch.full((2, 3), float("nan")), 0.5), cams)
        with pytest.raises(ValueError, match="voxel_size"):
            rasterize_voxels((centers, 0.0), cams)
        with pytest.raises(ValueError, match="cameras"):
            rasterize_voxels((centers, 0.5), cams.K)
        with pytest.raises(ValueError, match="view_ids"):
            rasterize_voxels((centers, 0.5), cams, view_ids=[0, 1])
        with pytest.raises(ValueError, match="only_observed"):
            rasterize_voxels((centers, 0.5), cams, [0], ZBufferConfig(only_observed=True))
        with pytest.raises(ValueError, match="depth_mode"):
            rasterize_voxels((centers, 0.5), cams, config=ZBufferConfig(depth_mode="sphere"))
        with pytest.raises(ValueError, match="plane"):
            rasterize_voxels((centers, 0.5), cams, config=PLANE)


class TestVoxelRasterizer:
    def test_module_equals_function(self):
        grid = voxelize(_cloud(100).float(), 0.3)
        cams = _cameras(eyes=((0.3, -0.2, 0.4), (1.0, 1.0, 1.0))).to(dtype=torch.float32)
        cfg = ZBufferConfig(near=0.2, depth_mode="plane")
        a = VoxelRasterizer(cfg)(grid, cams)
        b = rasterize_voxels(grid, cams, config=cfg)
        assert torch.equal(a.depth, b.depth) and torch.equal(a.index, b.index)
        assert all(torch.equal(x, y) for x, y in zip(a.visible, b.visible))


@pytest.fixture(scope="module")
def sample_grid() -> tuple:
    from vadgs.data import load_scene, sample_scene_path
    from vadgs.data.lidar import accumulate_lidar

    scene = load_scene(sample_scene_path())
    acc = accumulate_lidar(scene)
    grid = voxelize(acc.points, 0.2, acc.point_views, num_views=scene.num_views)
    assert isinstance(grid, VoxelGrid)
    return scene, grid
