from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from vadgs.select import (
    Covisibility,
    diversity_score,
    diversity_scores,
    pose_terms,
    shared_voxel_stats,
    triangulation_angles,
    view_voxel_incidence,
)

from .select_helpers import random_scene, yaw_pose


def _naive_scores(centers, visible, w2c, eps, count_exponent=1.0):
    """Obviously-correct reference: a Python loop over ordered pairs, numpy float64."""
    V = w2c.shape[0]
    pts = centers.double().numpy()
    poses = w2c.double().numpy()
    cam = [np.linalg.inv(p)[:3, 3] for p in poses]
    sets = [set(v.tolist()) for v in visible]
    score = np.zeros((V, V))
    shared = np.zeros((V, V))
    for r in range(V):
        for s in range(V):
            common = sorted(sets[r] & sets[s])
            shared[r, s] = len(common)
            if r == s or not common:
                continue
            d_r = np.linalg.norm(pts[common] - cam[r], axis=1)
            d_s = np.linalg.norm(pts[common] - cam[s], axis=1)
            t = poses[r][:3, :3] @ (cam[s] - cam[r])
            rel = poses[r][:3, :3] @ poses[s][:3, :3].T
            vee = np.array([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]])
            theta = math.atan2(np.linalg.norm(vee) / 2, (np.trace(rel) - 1) / 2)
            score[r, s] = (
                len(common) ** count_exponent / (d_r @ d_s) * math.hypot(t[0], t[1]) / (abs(t[2]) + eps)
            ) * math.sin(theta)
    return score, shared


def _covis(centers, visible, w2c):
    return Covisibility.from_visible(visible, centers, w2c)


def _pair(shared, dist_dot, yaw_deg, center, eps=0.1):
    return float(
        diversity_score(
            torch.tensor(float(shared)), torch.tensor(dist_dot), torch.eye(4), yaw_pose(yaw_deg, center), eps
        )
    )


class TestDiversityScore:
    def test_smoke(self):
        s = diversity_score(torch.tensor(5.0), torch.tensor(20.0), torch.eye(4), yaw_pose(30.0, (1.0, 0, 0)))
        assert s.shape == () and float(s) > 0

    def test_exception(self):
        with pytest.raises(ValueError, match="world_to_ref"):
            diversity_score(torch.tensor(1.0), torch.tensor(1.0), torch.eye(3), torch.eye(4))

    def test_cardinality(self):
        ref = torch.eye(4).expand(5, 1, 4, 4)
        src = torch.stack([yaw_pose(10.0 * i, (i, 0, 0)) for i in range(7)])[None]
        out = diversity_score(torch.ones(5, 7), torch.ones(5, 7), ref, src)
        assert out.shape == (5, 7)

    def test_no_shared_voxel_scores_zero(self):
        assert _pair(0, 0.0, 30.0, (1.0, 0, 0)) == 0.0

    def test_known_value(self):
        # 90° turn, centre 2 m to the right, 10 voxels with d_R^T d_S = 40: 10/40 * 2/0.5 * 1
        assert _pair(10, 40.0, 90.0, (2.0, 0, 0), eps=0.5) == pytest.approx(1.0, rel=1e-5)

    # the terms each move the right way
    def test_closer_voxels_score_higher(self):
        assert _pair(10, 100.0, 20.0, (1.0, 0, 0)) > _pair(10, 400.0, 20.0, (1.0, 0, 0))

    def test_more_lateral_baseline_scores_higher(self):
        assert _pair(10, 100.0, 20.0, (2.0, 0, 0)) > _pair(10, 100.0, 20.0, (1.0, 0, 0))
        assert _pair(10, 100.0, 20.0, (0, 2.0, 0)) > _pair(10, 100.0, 20.0, (0, 1.0, 0))

    def test_more_longitudinal_motion_scores_lower(self):
        assert _pair(10, 100.0, 20.0, (1.0, 0, 0.5)) < _pair(10, 100.0, 20.0, (1.0, 0, 0))

    def test_larger_angle_scores_higher(self):
        scores = [_pair(10, 100.0, yaw, (1.0, 0, 0)) for yaw in (0.0, 10.0, 30.0, 60.0, 90.0)]
        assert scores[0] == 0.0
        assert all(a < b for a, b in itertools.pairwise(scores))

    def test_more_shared_voxels_scores_higher(self):
        """With equally distant voxels the printed equation is count-neutral (N / d^T d = 1 / mean);
        count_exponent=2 makes more shared voxels score higher; closer extra voxels raise both."""
        pose = yaw_pose(20.0, (1.0, 0, 0))

        def score(n, dist_dot, p):
            return float(
                diversity_score(torch.tensor(float(n)), torch.tensor(dist_dot), torch.eye(4), pose, 0.1, p)
            )

        # 10 voxels at d_R = d_S = 5, then 10 more at the same distances
        assert score(20, 500.0, 1.0) == pytest.approx(score(10, 250.0, 1.0))
        assert score(20, 500.0, 2.0) > score(10, 250.0, 2.0)
        # 10 more voxels, closer (d = 4): both versions rise
        assert score(20, 250.0 + 160.0, 1.0) > score(10, 250.0, 1.0)
        assert score(20, 250.0 + 160.0, 2.0) > score(10, 250.0, 2.0)

    def test_pose_terms(self):
        ratio, sin = pose_terms(torch.eye(4), yaw_pose(30.0, (3.0, 4.0, 0.0)), eps=1.0)
        assert float(ratio) == pytest.approx(5.0, rel=1e-5)
        assert float(sin) == pytest.approx(0.5, rel=1e-5)

    def test_gradcheck(self):
        ref = torch.eye(4, dtype=torch.float64)
        src = yaw_pose(20.0, (1.0, 0.5, 0.2)).double()
        dist_dot = torch.tensor(30.0, dtype=torch.float64, requires_grad=True)
        torch.autograd.gradcheck(
            lambda d: diversity_score(torch.tensor(6.0, dtype=torch.float64), d, ref, src), (dist_dot,)
        )


class TestDiversityScores:
    def test_smoke(self):
        covis = _covis(*random_scene())
        out = diversity_scores(covis)
        assert out.score.shape == out.shared.shape == out.dist_dot.shape == (12, 12)

    @pytest.mark.parametrize("seed", [0, 1, 2])
    @pytest.mark.parametrize("count_exponent", [1.0, 2.0])
    def test_matches_naive_loop(self, seed, count_exponent):
        centers, visible, w2c = random_scene(seed=seed)
        covis = Covisibility.from_visible(visible, centers, w2c)
        out = diversity_scores(covis, eps=0.2, count_exponent=count_exponent)
        ref_score, ref_shared = _naive_scores(centers, visible, w2c, 0.2, count_exponent)
        np.testing.assert_allclose(out.shared.numpy(), ref_shared)
        np.testing.assert_allclose(out.score.numpy(), ref_score, rtol=1e-4, atol=1e-7)

    def test_float64(self):
        centers, visible, w2c = random_scene(seed=3)
        covis = Covisibility.from_visible(visible, centers.double(), w2c.double())
        out = diversity_scores(covis, eps=0.2)
        assert out.score.dtype == torch.float64
        np.testing.assert_allclose(out.score.numpy(), _naive_scores(centers, visible, w2c, 0.2)[0], rtol=1e-6)

    @pytest.mark.parametrize("seed", [0, 5])
    def test_voxel_mask_equals_restriction_bit_for_bit(self, seed):
        """Entries outside ``voxels`` weigh 0: the values of the restricted covisibility, exactly."""
        covis = _covis(*random_scene(seed=seed))
        mask = torch.rand(covis.num_voxels, generator=torch.Generator().manual_seed(seed)) < 0.3
        masked = diversity_scores(covis, 0.2, 2.0, voxels=mask)
        restricted = diversity_scores(covis.restrict(mask), 0.2, 2.0)
        for a, b in zip(masked, restricted):
            assert torch.equal(a, b)
        assert 0 < int(masked.shared.diagonal().max()) <= int(mask.sum())
        with pytest.raises(ValueError, match="voxels"):
            diversity_scores(covis, voxels=mask[:-1])

    def test_shared_stats_symmetric(self):
        covis = _covis(*random_scene(seed=4))
        shared, dist_dot = shared_voxel_stats(covis)
        assert torch.equal(shared, shared.T)
        torch.testing.assert_close(dist_dot, dist_dot.T)
        torch.testing.assert_close(shared.diagonal(), covis.visible_counts())


class TestCovisibility:
    def test_incidence_dedup(self):
        inc = view_voxel_incidence([torch.tensor([1, 1, 0]), torch.tensor([], dtype=torch.long)], 2)
        assert inc.to_dense().tolist() == [[1.0, 1.0], [0.0, 0.0]]

    def test_exception(self):
        with pytest.raises(ValueError, match="visible\\[0\\]"):
            view_voxel_incidence([torch.tensor([0.5])], 2)
        with pytest.raises(ValueError, match="voxel ids in \\[0, 2\\)"):
            view_voxel_incidence([torch.tensor([2])], 2)
        with pytest.raises(ValueError, match="one id tensor per view"):
            Covisibility.from_visible([torch.tensor([0])], torch.zeros(2, 3), torch.eye(4).repeat(2, 1, 1))
        with pytest.raises(ValueError, match="voxel_centers"):
            Covisibility.from_visible([torch.tensor([0])], torch.zeros(2, 2), torch.eye(4)[None])
        with pytest.raises(ValueError, match="camera_ids"):
            Covisibility.from_visible(
                [torch.tensor([0])], torch.zeros(2, 3), torch.eye(4)[None], camera_ids=torch.zeros(3)
            )

    def test_from_csr_equals_from_visible(self):
        centers, visible, w2c = random_scene(seed=5)
        a = Covisibility.from_visible(visible, centers, w2c)
        # per-voxel visibility sets in CSR form
        per_voxel = [
            [v for v, ids in enumerate(visible) if m in set(ids.tolist())] for m in range(len(centers))
        ]
        indptr = torch.tensor([0, *np.cumsum([len(p) for p in per_voxel]).tolist()])
        views = torch.tensor([v for p in per_voxel for v in p])
        b = Covisibility.from_csr(indptr, views, centers, w2c)
        assert torch.equal(a.incidence.to_dense(), b.incidence.to_dense())

    def test_restrict(self):
        centers, visible, w2c = random_scene(seed=6)
        covis = Covisibility.from_visible(visible, centers, w2c)
        mask = torch.arange(len(centers)) % 3 == 0
        sub = covis.restrict(mask)
        assert sub.num_voxels == int(mask.sum())
        assert torch.equal(sub.incidence.to_dense(), covis.incidence.to_dense()[:, mask])
        by_ids = covis.restrict(torch.nonzero(mask).squeeze(1))
        assert torch.equal(by_ids.incidence.to_dense(), sub.incidence.to_dense())

    def test_restrict_with_sizes_reads_nothing(self):
        """Given the sizes (read with other values), the restriction is the same, without a read.

        Value checks off (the new covisibility's finite-value checks read too), as an event runs it.
        """
        from vadgs.checks import checking

        from ..launch_count import LaunchCounter

        centers, visible, w2c = random_scene(seed=6)
        covis = Covisibility.from_visible(visible, centers, w2c)
        mask = torch.arange(len(centers)) % 3 == 0
        sizes = covis.restrict_sizes(mask).tolist()
        assert sizes == [int(mask.sum()), int(covis.incidence.to_dense()[:, mask].sum())]
        with LaunchCounter() as counter, checking(False):
            sub = covis.restrict(mask, sizes=(sizes[0], sizes[1]))
        assert counter.host_reads == 0
        expected = covis.restrict(mask)
        assert torch.equal(sub.incidence.indices(), expected.incidence.indices())
        assert torch.equal(sub.voxel_centers, expected.voxel_centers)


class TestTriangulationAngles:
    def test_against_naive_loop(self):
        centers, visible, w2c = random_scene(num_views=7, num_voxels=60, seed=3)
        covis = _covis(centers, visible, w2c)
        pts = centers.double().numpy()
        cam = [np.linalg.inv(p)[:3, 3] for p in w2c.double().numpy()]
        sets = [set(v.tolist()) for v in visible]
        for r in range(7):
            out = triangulation_angles(covis, r, percentile=75.0)
            for s in range(7):
                common = sorted(sets[r] & sets[s])
                if r == s or not common:
                    assert out[s] == 0
                    continue
                a, b = pts[common] - cam[r], pts[common] - cam[s]
                cos = (a * b).sum(1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
                theta = np.sort(np.degrees(np.arccos(np.clip(cos, -1, 1))))
                expected = theta[math.floor((len(theta) - 1) * 0.75)]
                assert out[s].item() == pytest.approx(expected, abs=1e-3)

    def test_seen_mask_and_seen_by_without_reads(self):
        """Given the reference's voxels as a mask, the angles need no read by the host."""
        from ..launch_count import LaunchCounter

        covis = _covis(*random_scene(num_views=7, num_voxels=60, seed=3))
        expected = triangulation_angles(covis, 2)
        with LaunchCounter() as counter:
            seen = covis.seen_by(2)
            got = triangulation_angles(covis, 2, seen=seen)
        assert counter.host_reads == 0
        assert torch.equal(got, expected)
        assert torch.nonzero(seen).squeeze(1).tolist() == covis.voxels_of(2).tolist()

    def test_short_baseline_far_voxels(self):
        # 1 cm apart at 50 m: 0.0115°; 2 m apart: 2.29° (atan(2 / 50))
        w2c = torch.stack(
            [yaw_pose(0.0, (0.0, 0.0, 0.0)), yaw_pose(0.0, (0.01, 0.0, 0.0)), yaw_pose(0.0, (2.0, 0, 0))]
        )
        covis = _covis(torch.tensor([[0.0, 0.0, 50.0]]), [torch.tensor([0])] * 3, w2c)
        angle = triangulation_angles(covis, 0)
        assert angle[0].item() == 0
        assert angle[1].item() == pytest.approx(math.degrees(math.atan(0.01 / 50)), rel=1e-3)
        assert angle[2].item() == pytest.approx(math.degrees(math.atan(2.0 / 50)), rel=1e-4)
