"""Point clouds on a grid (vadgs.geometry.points): against naive references."""

from __future__ import annotations

import pytest
import torch

from vadgs.geometry.points import VoxelAccumulator, knn_scales, thin_points, voxel_downsample


def _cells(points: torch.Tensor, cell: float) -> list[tuple[int, ...]]:
    return [tuple(int(v) for v in torch.floor(p / cell).tolist()) for p in points]


class TestVoxelDownsample:
    def test_against_a_dict_of_cells(self):
        g = torch.Generator().manual_seed(0)
        points = torch.rand(300, 3, generator=g, dtype=torch.float64) * 2
        colors = torch.rand(300, 2, generator=g, dtype=torch.float64)
        q, c = voxel_downsample(points, colors, 0.5)
        cells: dict[tuple[int, ...], list[int]] = {}
        for i, key in enumerate(_cells(points, 0.5)):
            cells.setdefault(key, []).append(i)
        naive = {k: (points[ix].mean(0), colors[ix].mean(0)) for k, ix in cells.items()}
        assert q.shape == (len(naive), 3) and c.shape == (len(naive), 2)
        for qi, ci, key in zip(q, c, _cells(q, 0.5)):  # a voxel's mean lies in its voxel
            assert torch.allclose(qi, naive[key][0]) and torch.allclose(ci, naive[key][1])

    def test_voxel_downsample_and_knn(self):
        p = torch.tensor([[0.0, 0, 0], [0.05, 0, 0], [1.0, 0, 0], [3.0, 0, 0]])
        q, c = voxel_downsample(p, torch.ones(4, 3), 0.1)
        assert q.shape == (3, 3) and torch.allclose(c, torch.ones(3, 3))
        naive = torch.stack([torch.cdist(x[None], p)[0].sort().values[1] for x in p])
        assert torch.allclose(knn_scales(p, 1), naive)

    def test_knn_against_cdist(self):
        p = torch.rand(50, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
        d = torch.cdist(p, p).sort(1).values[:, 1:4]  # the 3 nearest others
        assert torch.allclose(knn_scales(p, 3), d.pow(2).mean(1).sqrt())
        assert knn_scales(p[:1]).tolist() == [1.0]  # a lone point


class TestVoxelAccumulator:
    @pytest.mark.parametrize("chunks", [1, 2, 7])
    def test_chunks_equal_one_downsample_bit_for_bit(self, chunks):
        g = torch.Generator().manual_seed(0)
        points = torch.rand(5000, 3, generator=g) * 4 - 2
        colors = torch.rand(5000, 3, generator=g)
        acc = VoxelAccumulator(0.25)
        for p, c in zip(points.tensor_split(chunks), colors.tensor_split(chunks)):
            acc.add(p, c)
        p, c = acc.result()
        rp, rc = voxel_downsample(points, colors, 0.25)
        assert torch.equal(p, rp) and torch.equal(c, rc)
        assert p.shape[0] == int(torch.unique(torch.floor(points / 0.25), dim=0).shape[0])

    def test_holds_voxels_not_points(self):
        acc = VoxelAccumulator(1.0)
        g = torch.Generator().manual_seed(1)
        for _ in range(20):  # 20 "sweeps" of the same 27 voxels
            acc.add(torch.rand(10_000, 3, generator=g) * 3, torch.rand(10_000, 3, generator=g))
        p, c = acc.result()
        assert p.shape == (27, 3) and acc._sums.shape == (27, 6)  # 200,000 points, 27 rows held
        assert bool(((c > 0.45) & (c < 0.55)).all())  # the mean of uniform colours

    def test_no_voxels_keeps_every_point_and_empty(self):
        acc = VoxelAccumulator(0.0)
        acc.add(torch.ones(2, 3), torch.zeros(2, 3))
        acc.add(torch.zeros(1, 3), torch.ones(1, 3))
        p, c = acc.result()
        assert p.tolist() == [[1, 1, 1], [1, 1, 1], [0, 0, 0]] and c[:, 0].tolist() == [0, 0, 1]
        assert [t.shape for t in VoxelAccumulator(0.5).result()] == [(0, 3), (0, 3)]


class TestThinPoints:
    @pytest.mark.parametrize("cell", [0.1, 0.3])
    def test_first_point_of_each_free_cell(self, cell):
        g = torch.Generator().manual_seed(3)
        points = torch.rand(400, 3, generator=g, dtype=torch.float64)
        existing = torch.rand(30, 3, generator=g, dtype=torch.float64)
        keep = thin_points(points, cell, existing)
        taken = set(_cells(existing, cell))
        naive = []
        for key in _cells(points, cell):  # in order: the first point of a cell not yet taken
            naive.append(key not in taken)
            taken.add(key)
        assert keep.tolist() == naive and 0 < sum(naive) < len(naive)

    def test_one_point_per_cell_first_wins(self):
        g = torch.Generator().manual_seed(0)
        p = torch.rand(5000, 3, generator=g)
        keep = thin_points(p, 0.1)
        cells = torch.floor(p / 0.1).long()
        # naive reference: the first point of every occupied cell
        seen, ref = set(), []
        for c in cells.tolist():
            ref.append(tuple(c) not in seen)
            seen.add(tuple(c))
        assert keep.tolist() == ref
        assert int(keep.sum()) == len(seen) <= 1000

    def test_existing_points_take_their_cells(self):
        p = torch.tensor([[0.05, 0.05, 0.05], [0.15, 0.05, 0.05]])
        assert thin_points(p, 0.1, torch.tensor([[0.01, 0.01, 0.01]])).tolist() == [False, True]
        assert thin_points(torch.zeros(0, 3), 0.1).shape == (0,)
