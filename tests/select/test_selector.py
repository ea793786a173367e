from __future__ import annotations

import itertools
import math

import pytest
import torch

from vadgs.select import (
    Covisibility,
    ViewSelection,
    ViewSelectionConfig,
    ViewSelector,
    diversity_scores,
    select_views,
)

from .select_helpers import random_scene, yaw_pose


def _ring(num_views=8, num_voxels=30, step_deg=12.0, radius=10.0, seed=0):
    """Cameras on an arc around voxels near the origin, every view sees every voxel."""
    g = torch.Generator().manual_seed(seed)
    w2c = torch.stack(
        [
            yaw_pose(
                step_deg * v,
                (
                    -radius * math.sin(math.radians(step_deg * v)),
                    0.0,
                    -radius * math.cos(math.radians(step_deg * v)),
                ),
            )
            for v in range(num_views)
        ]
    )
    centers = torch.randn(num_voxels, 3, generator=g) * 0.5
    return Covisibility.from_visible([torch.arange(num_voxels)] * num_views, centers, w2c)


def _ref_scores(covis, ref, count_exponent=ViewSelectionConfig.count_exponent):
    """Pair scores on the voxels the reference sees (what select_views optimises)."""
    return diversity_scores(covis.restrict(covis.seen_by(ref)), count_exponent=count_exponent)


def _objective(covis, ref, views, lam, scores=None):
    """Noiseless objective of a set of supporting views."""
    s = (scores or _ref_scores(covis, ref)).score
    pair = (s + s.T) / 2
    views = list(views)
    return float(
        sum(s[ref, i] for i in views) + lam * sum(pair[i, j] for i, j in itertools.combinations(views, 2))
    )


class TestViewSelectionConfig:
    @pytest.mark.parametrize(
        "kwargs",
        [
            dict(k=0),
            dict(method="random"),
            dict(noise_std=-1.0),
            dict(k=5, max_candidates=4),
            dict(eps=0.0),
            dict(min_angle=-1.0),
            dict(min_angle=90.0),
            dict(min_parallax=-1.0),
        ],
    )
    def test_exception(self, kwargs):
        with pytest.raises(ValueError):
            ViewSelectionConfig(**kwargs)


class TestSelectViews:
    def test_smoke(self):
        sel = select_views(0, _ring(), ViewSelectionConfig(noise_std=0.0))
        assert isinstance(sel, ViewSelection) and sel.reason == "ok" and sel.complete

    def test_exception(self):
        covis = _ring()
        with pytest.raises(ValueError, match="ref"):
            select_views(8, covis)
        with pytest.raises(ValueError, match="allowed"):
            select_views(0, covis, allowed=torch.ones(3, dtype=torch.bool))
        with pytest.raises(ValueError, match="camera_ids"):
            select_views(0, covis, ViewSelectionConfig(method="consecutive"))

    @pytest.mark.parametrize("method", ["diversity", "consecutive", "mvsnet", "colmap"])
    def test_cardinality(self, method):
        covis = _ring(num_views=10)
        covis = Covisibility(
            covis.voxel_centers,
            covis.incidence,
            covis.world_to_cam,
            torch.zeros(10, dtype=torch.long),
            torch.arange(10),
        )
        sel = select_views(
            4, covis, ViewSelectionConfig(k=3, method=method), torch.Generator().manual_seed(0)
        )
        assert sel.views.shape == (3,) and sel.views.dtype == torch.int64
        assert 4 not in sel.views.tolist() and len(set(sel.views.tolist())) == 3
        assert set(sel.views.tolist()) <= set(sel.candidates.tolist())

    def test_one_read_of_the_device_and_host_ids(self):
        """The diversity selection reads the device once; its views are host data (``ids``).

        Value checks off, as an event runs it: those of the clique search's host inputs count too.
        """
        from vadgs.checks import checking

        from ..launch_count import LaunchCounter

        centers, visible, w2c = random_scene(num_views=10, seed=11, p=0.6)
        covis = Covisibility.from_visible(visible, centers, w2c)
        cfg = ViewSelectionConfig(k=3, min_shared=1)
        for ref in (0, 4):
            with LaunchCounter() as counter, checking(False):
                sel = select_views(ref, covis, cfg, torch.Generator().manual_seed(ref))
            assert counter.host_reads == 1 and sel.complete
            assert sel.views.device.type == "cpu" and sel.ids == sel.views.tolist() and len(sel.ids) == 3
            # the same choice as a selection on the restriction to the voxels ref sees
            sub = covis.restrict(covis.voxels_of(ref))
            again = select_views(ref, sub, cfg, torch.Generator().manual_seed(ref))
            assert again.ids == sel.ids and again.score == sel.score

    def test_exact_against_brute_force(self):
        centers, visible, w2c = random_scene(num_views=10, seed=11, p=0.6)
        covis = Covisibility.from_visible(visible, centers, w2c)
        cfg = ViewSelectionConfig(k=3, lam=0.7, noise_std=0.0, min_shared=1)
        for ref in range(10):
            scores = _ref_scores(covis, ref)
            sel = select_views(ref, covis, cfg)
            cand = sel.candidates.tolist()
            adj = scores.shared >= cfg.min_shared
            best = max(
                (_objective(covis, ref, c, cfg.lam, scores), c)
                for c in itertools.combinations(cand, 3)
                if all(adj[i, j] for i, j in itertools.combinations(c, 2))
            )
            assert sel.score == pytest.approx(best[0], rel=1e-5)

    def test_prefers_other_camera_over_forward_motion(self):
        # views 1, 2: the reference camera driven forward (no rotation, no lateral baseline): s = 0;
        # views 3, 4: a side camera turned 40° and shifted sideways: chosen
        w2c = torch.stack(
            [
                yaw_pose(0.0, (0.0, 0.0, 0.0)),
                yaw_pose(0.0, (0.0, 0.0, 1.0)),
                yaw_pose(0.0, (0.0, 0.0, 2.0)),
                yaw_pose(40.0, (1.0, 0.0, 0.5)),
                yaw_pose(-40.0, (-1.0, 0.0, 1.0)),
            ]
        )
        centers = torch.randn(20, 3) + torch.tensor([0.0, 0.0, 10.0])
        covis = Covisibility.from_visible([torch.arange(20)] * 5, centers, w2c)
        sel = select_views(0, covis, ViewSelectionConfig(k=2, min_shared=5))
        assert sel.views.tolist() == [3, 4] and sel.candidates.tolist() == [3, 4]

    def test_short_baselines_left_out(self):
        # a car waiting at a light: views 1, 2 are the reference camera 2 cm and 4 cm aside, turned
        # 1°, so they score > 0 but their rays meet the reference's at 0.02° and 0.05° at 50 m;
        # view 3 is a side camera 2 m aside (2.3°)
        w2c = torch.stack(
            [
                yaw_pose(0.0, (0.0, 0.0, 0.0)),
                yaw_pose(1.0, (0.02, 0.0, 0.0)),
                yaw_pose(-1.0, (0.04, 0.0, 0.0)),
                yaw_pose(5.0, (2.0, 0.0, 0.0)),
            ]
        )
        centers = torch.randn(20, 3, generator=torch.Generator().manual_seed(0)) + torch.tensor(
            [0.0, 0.0, 50.0]
        )
        covis = Covisibility.from_visible([torch.arange(20)] * 4, centers, w2c)
        config = ViewSelectionConfig(k=1, min_shared=5, noise_std=0.0)
        assert (diversity_scores(covis).score[0, 1:] > 0).all()
        sel = select_views(0, covis, config)
        assert sel.views.tolist() == [3] and sel.candidates.tolist() == [3]
        assert select_views(
            0, covis, ViewSelectionConfig(k=3, min_shared=5, min_angle=0.0)
        ).views.tolist() == [1, 2, 3]
        none = select_views(0, covis, config, allowed=torch.tensor([True, True, True, False]))
        assert none.views.tolist() == [] and not none.complete
        assert (
            none.reason
            == "narrow_baselines: 2 views share >= 5 voxels with it, all at a triangulation angle < 1°"
        )

    def test_min_parallax_in_pixels_of_the_reference(self):
        # view 1 is 1 m aside of the reference at 20 m: 2.9°; 10 px of parallax need 5.7° at a
        # focal length of 100 px, 0.57° at 1000 px (then min_angle's 1° rules)
        w2c = torch.stack([yaw_pose(0.0, (0.0, 0.0, 0.0)), yaw_pose(3.0, (1.0, 0.0, 0.0))])
        centers = torch.randn(20, 3, generator=torch.Generator().manual_seed(1)) * 0.1 + torch.tensor(
            [0, 0, 20.0]
        )
        covis = Covisibility.from_visible([torch.arange(20)] * 2, centers, w2c)
        config = ViewSelectionConfig(k=1, min_shared=5, noise_std=0.0, min_parallax=10.0)
        assert config.least_angle(100.0) == pytest.approx(math.degrees(0.1))
        assert config.least_angle(1000.0) == 1.0
        assert select_views(0, covis, config, focal=1000.0).views.tolist() == [1]
        narrow = select_views(0, covis, config, focal=100.0)
        assert narrow.views.tolist() == [] and narrow.reason.endswith("triangulation angle < 5.73°")
        with pytest.raises(ValueError, match="focal: expected the reference's focal length"):
            select_views(0, covis, config)

    # graceful results
    def test_no_voxels(self):
        covis = Covisibility.from_visible(
            [torch.tensor([], dtype=torch.long), torch.tensor([0, 1])],
            torch.rand(2, 3) + 5,
            torch.eye(4).repeat(2, 1, 1),
        )
        sel = select_views(0, covis)
        assert len(sel.views) == 0 and sel.reason.startswith("no_voxels") and not sel.complete

    def test_empty_candidate_set(self):
        covis = _ring(num_views=4)
        sel = select_views(0, covis, allowed=torch.tensor([True, False, False, False]))
        assert len(sel.views) == 0 and sel.reason.startswith("no_candidates") and sel.score == 0.0

    def test_fewer_candidates_than_k(self):
        sel = select_views(0, _ring(num_views=3), ViewSelectionConfig(k=4))
        assert sel.views.tolist() == [1, 2] and sel.reason.startswith("few_candidates")

    def test_disconnected_graph(self):
        # views 1, 2 see voxels 0..9, views 3, 4 see voxels 10..19; the reference sees all
        w2c = torch.stack([yaw_pose(10.0 * v, (float(v), 0.0, 0.0)) for v in range(5)])
        centers = torch.randn(20, 3) + torch.tensor([0.0, 0.0, 10.0])
        a, b = torch.arange(10), torch.arange(10, 20)
        covis = Covisibility.from_visible([torch.arange(20), a, a, b, b], centers, w2c)
        sel = select_views(0, covis, ViewSelectionConfig(k=3, min_shared=5))
        assert len(sel.views) == 2 and sel.reason.startswith("no_k_clique")
        assert sel.views.tolist() in ([1, 2], [3, 4])

    def test_allowed_mask(self):
        allowed = torch.tensor([True, True, False, True, False, True, True, True])
        sel = select_views(0, _ring(), allowed=allowed)
        assert all(allowed[sel.views])

    def test_candidate_cap(self):
        covis = _ring(num_views=12)
        sel = select_views(0, covis, ViewSelectionConfig(k=2, max_candidates=4, noise_std=0.0))
        assert len(sel.candidates) == 4 and "capped to 4 of 11" in sel.reason and sel.complete

    def test_cap_keeps_optimum_when_large_enough(self):
        centers, visible, w2c = random_scene(num_views=14, seed=21, p=0.8)
        covis = Covisibility.from_visible(visible, centers, w2c)
        full = ViewSelectionConfig(k=3, noise_std=0.0, min_shared=1, max_candidates=13)
        capped = ViewSelectionConfig(k=3, noise_std=0.0, min_shared=1, max_candidates=8)
        same = sum(
            select_views(r, covis, full).views.tolist() == select_views(r, covis, capped).views.tolist()
            for r in range(14)
        )
        assert same >= 12

    # the noise
    def test_seed_reproducible(self):
        centers, visible, w2c = random_scene(num_views=16, seed=3)
        covis = Covisibility.from_visible(visible, centers, w2c)
        cfg = ViewSelectionConfig(noise_std=0.5, min_shared=1)
        a = [s.views.tolist() for s in ViewSelector(cfg, seed=7).select_all(covis)]
        b = [s.views.tolist() for s in ViewSelector(cfg, seed=7).select_all(covis)]
        c = [s.views.tolist() for s in ViewSelector(cfg, seed=8).select_all(covis)]
        assert a == b
        assert a != c  # large noise does change picks

    def test_small_noise_changes_picks_only_among_near_ties(self):
        eps = 1e-3
        for seed in range(3):
            centers, visible, w2c = random_scene(num_views=12, seed=seed, p=0.7)
            covis = Covisibility.from_visible(visible, centers, w2c)
            exact = ViewSelectionConfig(noise_std=0.0, min_shared=1)
            noisy = ViewSelectionConfig(noise_std=eps, min_shared=1)
            g = torch.Generator().manual_seed(seed)
            for ref in range(12):
                scores = _ref_scores(covis, ref)
                best = select_views(ref, covis, exact)
                opt = _objective(covis, ref, best.views.tolist(), exact.lam, scores)
                pick = select_views(ref, covis, noisy, g)
                got = _objective(covis, ref, pick.views.tolist(), exact.lam, scores)
                # |ξ - 1| < 6ε with overwhelming probability: the pick is within 12ε of the optimum
                assert got >= opt * (1 - 12 * eps) - 1e-12
                if pick.views.tolist() != best.views.tolist():
                    assert got >= opt * (1 - 12 * eps)  # a different pick is a near-tie

    def test_noise_breaks_exact_ties_both_ways(self):
        # views 1 and 2 are mirror images w.r.t. the reference: an exact tie for k=1
        w2c = torch.stack(
            [
                yaw_pose(0.0, (0.0, 0.0, 0.0)),
                yaw_pose(20.0, (2.0, 0.0, 0.0)),
                yaw_pose(-20.0, (-2.0, 0.0, 0.0)),
            ]
        )
        centers = torch.tensor([[0.0, 0.0, 10.0], [0.0, 1.0, 10.0], [0.0, -1.0, 10.0]])
        covis = Covisibility.from_visible([torch.arange(3)] * 3, centers, w2c)
        cfg = ViewSelectionConfig(k=1, noise_std=1e-3, min_shared=1, max_candidates=2)
        picks = {
            select_views(0, covis, cfg, torch.Generator().manual_seed(s)).views.item() for s in range(20)
        }
        assert picks == {1, 2}


class TestViewSelector:
    def test_module_equals_function(self):
        centers, visible, w2c = random_scene(num_views=10, seed=5)
        covis = Covisibility.from_visible(visible, centers, w2c)
        cfg = ViewSelectionConfig(noise_std=0.1, min_shared=1)
        selector = ViewSelector(cfg, seed=3)
        g = torch.Generator().manual_seed(3)
        for ref in range(10):
            a = selector(ref, covis)
            b = select_views(ref, covis, cfg, g)
            assert (
                torch.equal(a.views, b.views) and a.score == pytest.approx(b.score) and a.reason == b.reason
            )

    def test_select_all_equals_loop(self):
        centers, visible, w2c = random_scene(num_views=10, seed=6)
        covis = Covisibility.from_visible(visible, centers, w2c)
        cfg = ViewSelectionConfig(min_shared=1)
        batch = ViewSelector(cfg, seed=1).select_all(covis, refs=[2, 5, 7])
        one = ViewSelector(cfg, seed=1)
        assert [s.views.tolist() for s in batch] == [one(r, covis).views.tolist() for r in (2, 5, 7)]

    def test_repr(self):
        assert "seed=4" in repr(ViewSelector(seed=4))
