from __future__ import annotations

import pytest

from vadgs.train.sampler import ViewSampler


class TestViewSampler:
    def test_every_view_once_per_cycle(self):
        views = list(range(3, 20, 2))
        s = ViewSampler(views, seed=1)
        orders = []
        for cycle in range(4):
            drawn = [s.next() for _ in views]
            assert sorted(drawn) == views
            assert s.cycle == cycle + 1
            orders.append(drawn)
        assert len({tuple(o) for o in orders}) > 1  # reshuffled between cycles

    def test_seeded_and_resumable(self):
        a = ViewSampler(range(10), seed=5)
        first = [a.next() for _ in range(13)]
        state = a.state_dict()
        rest = [a.next() for _ in range(20)]
        b = ViewSampler(range(10), seed=0)
        b.load_state_dict(state)
        assert [b.next() for _ in range(20)] == rest
        assert [ViewSampler(range(10), seed=5).next() for _ in range(1)] == first[:1]

    def test_empty_and_mismatch(self):
        with pytest.raises(ValueError, match="view_ids"):
            ViewSampler([])
        with pytest.raises(ValueError, match="differ"):
            ViewSampler([1, 2]).load_state_dict(ViewSampler([1, 3]).state_dict())
