"""Tests of voxel grids with CSR visibility sets (vadgs.geometry.voxel) against naive references."""

from __future__ import annotations

import math
import time
from collections import defaultdict

import pytest
import torch

from vadgs.geometry import (
    PointChunk,
    VoxelGrid,
    unique_cells,
    voxel_labels,
    voxelize,
    voxelize_chunks,
)


def _naive_voxelize(points, voxel_size, pidx, vidx, origin):
    """coord tuple -> (point ids, set of views), with plain Python loops."""
    vox: dict = defaultdict(lambda: ([], set()))
    for i, p in enumerate(points.tolist()):
        key = tuple(math.floor((p[k] - float(origin[k])) / voxel_size) for k in range(3))
        vox[key][0].append(i)
    point_key = {i: k for k, (ids, _) in vox.items() for i in ids}
    for p, v in zip(pidx.tolist(), vidx.tolist()):
        vox[point_key[p]][1].add(v)
    return dict(vox)


def _random_table(n_points=300, n_views=7, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(n_points, 3, generator=g, dtype=dtype) * torch.tensor([3.0, 2.0, 1.0], dtype=dtype) - 1.0
    pairs = torch.randint(0, n_points, (900,), generator=g), torch.randint(0, n_views, (900,), generator=g)
    return pts, pairs


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """On a loaded shared machine one intra-op thread is much faster for these small kernels."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


class TestVoxelize:
    def test_smoke(self):
        grid = voxelize(torch.rand(10, 3), 0.5)
        assert isinstance(grid, VoxelGrid) and len(grid) >= 1
        assert "VoxelGrid(" in repr(grid)

    def test_cardinality(self):
        pts, (pi, vi) = _random_table()
        grid = voxelize(pts, 0.3, (pi, vi), num_views=9)
        m = len(grid)
        assert grid.coords.shape == (m, 3) and grid.coords.dtype == torch.int64
        assert grid.means.shape == (m, 3) and grid.means.dtype == pts.dtype
        assert grid.counts.shape == (m,) and grid.normals.shape == (m, 3)
        assert grid.vis_indptr.shape == (m + 1,) and grid.point_to_voxel.shape == (300,)
        assert grid.num_views == 9 and grid.centers.shape == (m, 3)

    @pytest.mark.parametrize("seed", [0, 1])
    def test_equals_naive_reference(self, seed):
        pts, (pi, vi) = _random_table(seed=seed)
        grid = voxelize(pts, 0.3, (pi, vi))
        ref = _naive_voxelize(pts, 0.3, pi, vi, grid.origin)
        assert len(grid) == len(ref)
        coords = [tuple(c) for c in grid.coords.tolist()]
        assert coords == sorted(ref)  # voxels sorted by their integer coordinates
        for m, c in enumerate(coords):
            ids, views = ref[c]
            assert int(grid.counts[m]) == len(ids)
            torch.testing.assert_close(grid.means[m], pts[ids].mean(0))
            assert grid.views_of(m).tolist() == sorted(views)
            assert (grid.point_to_voxel[ids] == m).all()
        # centre of a voxel: origin + (coord + 1/2) * size, and every point lies in its voxel
        lo = grid.centers[grid.point_to_voxel] - 0.15
        assert ((pts >= lo - 1e-9) & (pts < lo + 0.3 + 1e-9)).all()

    def test_origin_aligns_grids(self):
        pts = torch.tensor([[0.05, 0.05, 0.05], [1.01, 0.0, 0.0]])
        grid = voxelize(pts, 0.5, origin=torch.tensor([-1.0, -1.0, -1.0]))
        assert grid.coords.tolist() == [[2, 2, 2], [4, 2, 2]]

    def test_csr_invariants(self):
        pts, (pi, vi) = _random_table(n_views=5)
        grid = voxelize(pts, 0.25, (pi, vi), num_views=5)
        ptr, views = grid.vis_indptr, grid.vis_views
        assert ptr[0] == 0 and ptr[-1] == views.numel() and (ptr.diff() >= 0).all()
        assert ((views >= 0) & (views < 5)).all()
        for m in range(len(grid)):
            row = grid.views_of(m)
            assert (row.diff() > 0).all()  # sorted and unique
        assert torch.equal(grid.vis_voxels, torch.repeat_interleave(torch.arange(len(grid)), ptr.diff()))

    @pytest.mark.filterwarnings("ignore:Sparse invariant checks")
    def test_seen_by_candidate_views_incidence(self):
        pts, (pi, vi) = _random_table(n_views=6, seed=2)
        grid = voxelize(pts, 0.3, (pi, vi), num_views=6)
        sets = [set(grid.views_of(m).tolist()) for m in range(len(grid))]
        for v in range(6):
            assert grid.seen_by(v).tolist() == [v in s for s in sets]
        pick = torch.tensor([0, 3, 5])
        assert grid.candidate_views(pick).tolist() == sorted(set().union(*(sets[i] for i in pick.tolist())))
        mask = torch.zeros(len(grid), dtype=torch.bool)
        mask[pick] = True
        assert torch.equal(grid.candidate_views(mask), grid.candidate_views(pick))
        assert grid.candidate_views(torch.zeros(0, dtype=torch.int64)).numel() == 0
        dense = grid.incidence().to_dense()
        assert dense.shape == (6, len(grid))
        for m, s in enumerate(sets):
            assert dense[:, m].tolist() == [float(v in s) for v in range(6)]

    def test_subset(self):
        pts, (pi, vi) = _random_table(seed=3)
        grid = voxelize(pts, 0.3, (pi, vi))
        keep = torch.arange(len(grid)) % 3 == 0
        sub = grid.subset(keep)
        old = keep.nonzero().squeeze(1)
        assert len(sub) == int(keep.sum())
        assert torch.equal(sub.coords, grid.coords[keep]) and torch.equal(sub.counts, grid.counts[keep])
        for new, m in enumerate(old.tolist()):
            assert torch.equal(sub.views_of(new), grid.views_of(m))
        p2v = grid.point_to_voxel
        new_id = torch.full((len(grid),), -1)
        new_id[old] = torch.arange(len(old))
        assert torch.equal(sub.point_to_voxel, new_id[p2v])
        assert torch.equal(grid.subset(old).coords, sub.coords)  # ids == mask

    def test_normals_of_points_on_a_plane(self):
        g = torch.Generator().manual_seed(4)
        n = torch.tensor([0.3, -0.2, 1.0], dtype=torch.float64)
        n = n / n.norm()
        u = torch.linalg.cross(n, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
        u = u / u.norm()
        w = torch.linalg.cross(n, u)
        ab = torch.rand(5000, 2, generator=g, dtype=torch.float64) * 4 - 2
        pts = (
            ab[:, :1] * u + ab[:, 1:] * w + 0.001 * torch.randn(5000, 1, generator=g, dtype=torch.float64) * n
        )
        grid = voxelize(pts, 0.5)
        has = grid.normals.norm(dim=1) > 0
        assert has.float().mean() > 0.9
        cos = (grid.normals[has] @ n).abs()
        assert cos.min() > 0.999
        # an isotropic blob has no plane
        blob = voxelize(torch.randn(3000, 3, generator=g, dtype=torch.float64) * 0.05, 1.0)
        assert (blob.normals == 0).all()

    def test_no_observations(self):
        grid = voxelize(torch.rand(20, 3), 0.5)
        assert grid.vis_views.numel() == 0 and (grid.vis_indptr == 0).all() and grid.num_views == 0

    def test_scaling_1e5_voxels_1e3_views(self):
        """10^5 voxels × 10^6 observations over 10^3 views (the 10^6-voxel case is in benchmarks/)."""
        g = torch.Generator().manual_seed(0)
        n, per_point, views = 100_000, 10, 1000
        side = 50
        idx = torch.randperm(side**3, generator=g)[:n]
        coords = torch.stack([idx // side**2, (idx // side) % side, idx % side], 1).float()
        pts = (coords + 0.01 + 0.98 * torch.rand(n, 3, generator=g)) * 0.2
        pidx = torch.arange(n).repeat_interleave(per_point)
        vidx = torch.randint(0, views, (n * per_point,), generator=g)
        t0 = time.process_time()
        grid = voxelize(pts, 0.2, (pidx, vidx), views)
        cpu = time.process_time() - t0
        assert len(grid) == n
        assert grid.vis_indptr[-1] == grid.vis_views.numel() == torch.unique(pidx * views + vidx).numel()
        assert cpu < 30.0  # measured ~1 s of CPU time on the 2-core dev machine

    def test_exception(self):
        with pytest.raises(ValueError, match="points"):
            voxelize(torch.rand(5, 2), 0.5)
        with pytest.raises(ValueError, match="at least one point"):
            voxelize(torch.zeros(0, 3), 0.5)
        with pytest.raises(ValueError, match="points: expected finite"):
            voxelize(torch.tensor([[0.0, float("inf"), 0.0]]), 0.5)
        with pytest.raises(ValueError, match="voxel_size"):
            voxelize(torch.rand(5, 3), -1.0)
        with pytest.raises(ValueError, match="origin"):
            voxelize(torch.rand(5, 3), 0.5, origin=torch.zeros(2))
        with pytest.raises(ValueError, match=r"point_views\[0\]"):
            voxelize(torch.rand(5, 3), 0.5, (torch.tensor([0, 5]), torch.tensor([0, 0])))
        with pytest.raises(ValueError, match=r"point_views\[1\]"):
            voxelize(torch.rand(5, 3), 0.5, (torch.tensor([0, 1]), torch.tensor([0])))
        with pytest.raises(ValueError, match=r"point_views\[1\]"):
            voxelize(torch.rand(5, 3), 0.5, (torch.tensor([0]), torch.tensor([-1])))
        with pytest.raises(ValueError, match="num_views"):
            voxelize(torch.rand(5, 3), 0.5, (torch.tensor([0]), torch.tensor([3])), num_views=2)


class TestVoxelizeChunks:
    """``voxelize_chunks``: the grid of points given chunk by chunk (a segment's sweeps) equals
    ``voxelize`` of them all, bit for bit, while only the voxels are held."""

    @staticmethod
    def _chunks(n_chunks, seed=0):
        g = torch.Generator().manual_seed(seed)
        out = []
        for _ in range(n_chunks):
            n = int(torch.randint(50, 400, (1,), generator=g))
            pts = torch.rand(n, 3, generator=g) * torch.tensor([4.0, 3.0, 1.0]) - 1.0
            pv = torch.randint(0, n, (2 * n,), generator=g), torch.randint(0, 9, (2 * n,), generator=g)
            out.append(PointChunk(pts, pv, torch.randint(0, 4, (n,), generator=g)))
        return out

    @pytest.mark.parametrize("n_chunks", [1, 3, 8])
    def test_equals_voxelize_of_the_concatenation(self, n_chunks):
        chunks = self._chunks(n_chunks)
        calls = []

        def source():
            calls.append(1)
            return iter(chunks)

        points = torch.cat([c.points for c in chunks])
        offsets = torch.tensor([0] + [c.points.shape[0] for c in chunks]).cumsum(0)
        pidx = torch.cat([c.point_views[0] + o for c, o in zip(chunks, offsets)])
        vidx = torch.cat([c.point_views[1] for c in chunks])
        ref = voxelize(points, 0.3, (pidx, vidx), num_views=9)
        got = voxelize_chunks(source, 0.3, num_views=9)
        assert len(calls) == 3  # origin, sums, spread
        for name in ("origin", "coords", "means", "counts", "vis_indptr", "vis_views", "normals"):
            assert torch.equal(getattr(got.grid, name), getattr(ref, name)), name
        assert got.grid.point_to_voxel.numel() == 0 and got.grid.num_views == 9
        labels = torch.cat([c.labels for c in chunks])
        assert torch.equal(got.labels, voxel_labels(ref.point_to_voxel, labels, len(ref)))
        # and against plain counting: the most frequent label of each voxel, the smaller on ties
        for m in torch.randperm(len(ref))[:20].tolist():
            counts = torch.bincount(labels[ref.point_to_voxel == m], minlength=4)
            assert int(got.labels[m]) == int(torch.argmax(counts))  # argmax: the first maximum
        # with the origin given, two passes
        calls.clear()
        again = voxelize_chunks(source, 0.3, num_views=9, origin=ref.origin)
        assert len(calls) == 2 and torch.equal(again.grid.means, ref.means)

    def test_points_on_both_sides_of_the_origin(self):
        chunks = self._chunks(2)
        got = voxelize_chunks(lambda: chunks, 0.25, origin=torch.tensor([0.5, 0.5, 0.0]))
        points = torch.cat([c.points for c in chunks])
        ref = voxelize(points, 0.25, origin=torch.tensor([0.5, 0.5, 0.0]))
        assert int(got.grid.coords.min()) < 0
        assert torch.equal(got.grid.coords, ref.coords) and torch.equal(got.grid.means, ref.means)
        assert got.grid.num_views == 9 and torch.equal(got.labels.unique(), torch.arange(4))

    def test_exception(self):
        with pytest.raises(ValueError, match="chunks: expected at least one point, got none"):
            voxelize_chunks(lambda: [PointChunk(torch.zeros(0, 3))], 0.5)
        with pytest.raises(ValueError, match="chunks: expected at least one point"):
            voxelize_chunks(lambda: [], 0.5, origin=torch.zeros(3))
        with pytest.raises(ValueError, match="voxel_size"):
            voxelize_chunks(lambda: [], 0.0)
        far = PointChunk(torch.tensor([[0.0, 0, 0], [3e6, 0, 0]]))  # 3e6 voxels of 1 m along x
        with pytest.raises(ValueError, match="span more than 2097152 voxels of 1 along an axis"):
            voxelize_chunks(lambda: [far], 1.0)
        with pytest.raises(ValueError, match="span more than"):
            voxelize(far.points, 1.0)
        three = torch.rand(3, 3)
        with pytest.raises(ValueError, match="labels"):
            voxelize_chunks(lambda: [PointChunk(three, labels=torch.tensor([0, -1, 2]))], 0.5)
        with pytest.raises(ValueError, match="must give the same chunks in the same order"):
            voxelize_chunks(lambda: [PointChunk(torch.rand(50, 3) * 10)], 0.5, origin=torch.zeros(3))
        with pytest.raises(ValueError, match="num_views"):
            voxelize_chunks(lambda: [PointChunk(three, (torch.tensor([0]), torch.tensor([4])))], 0.5, 3)


@pytest.mark.parametrize("span", [5, 2**21 - 1, 2**21, 2**40])
def test_unique_cells_equals_unique_over_rows(span):
    g = torch.Generator().manual_seed(span % 1000)
    coords = torch.randint(-50, 50, (5000, 3), generator=g)
    coords[0, 1] = -7 + span  # one coordinate far away: packed below 2**21 cells, rows beyond
    coords[1:40] = coords[0]  # repeated rows
    got, inv = unique_cells(coords)
    ref, ref_inv = torch.unique(coords, dim=0, return_inverse=True)
    assert torch.equal(got, ref) and torch.equal(inv, ref_inv)
    empty = unique_cells(torch.zeros(0, 3, dtype=torch.int64))
    assert empty[0].shape == (0, 3) and empty[1].shape == (0,)
