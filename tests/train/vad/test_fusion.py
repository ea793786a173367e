"""The fusion of an event's depth maps into points (:mod:`vadgs.train.vad.fusion`): the thinning of
new points to one per cell, against a naive first-come reference."""

from __future__ import annotations

import torch

from vadgs.train.vad.fusion import thin_points


class TestThinPoints:
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
