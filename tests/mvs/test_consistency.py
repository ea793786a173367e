from __future__ import annotations

import pytest
import torch

from vadgs.mvs import ConsistencyResult, geometric_consistency, reproject_depth


def _setup(v=3, h=12, w=16, z=2.0):
    K = torch.tensor([[[12.0, 0, (w - 1) / 2], [0, 12.0, (h - 1) / 2], [0, 0, 1]]])
    w2c = torch.eye(4)[None]
    src = torch.eye(4).repeat(1, v, 1, 1)
    src[0, :, 0, 3] = torch.tensor([-1.0, 1.0, 2.0])[:v] * z / 12  # disparities f b / z of -1, 1, 2 px
    depth = torch.full((1, 1, h, w), z)
    return depth, K, w2c, depth[:, None].repeat(1, v, 1, 1, 1), K[:, None].repeat(1, v, 1, 1), src


class TestGeometricConsistency:
    def test_smoke_and_cardinality(self):
        d, K, w2c, sd, sK, sw = _setup()
        res = geometric_consistency(d, K, w2c, sd, sK, sw)
        assert isinstance(res, ConsistencyResult)
        assert res.mask.shape == (1, 1, 12, 16) and res.mask.dtype == torch.bool
        assert res.view_consistent.shape == (1, 3, 12, 16)
        assert res.reproj_error.shape == res.rel_depth_error.shape == (1, 3, 12, 16)

    def test_consistent_plane(self):
        d, K, w2c, sd, sK, sw = _setup()
        res = geometric_consistency(d, K, w2c, sd, sK, sw, min_views=3)
        assert res.mask[..., 2:-2].all()
        assert (res.reproj_error[..., 2:-2] < 1e-4).all()

    def test_rejects_corrupted_source_depth(self):
        d, K, w2c, sd, sK, sw = _setup()
        sd = sd.clone()
        sd[:, 0] *= 1.05  # one source is 5 % off: its relative depth check fails
        sd[:, 1, :, :, :8] = 0  # half of another has no depth
        res = geometric_consistency(d, K, w2c, sd, sK, sw, min_views=2)
        assert not res.view_consistent[:, 0].any()
        assert not res.view_consistent[:, 1, :, :7].any()
        assert not res.mask[..., :7].any()  # only view 2 left there
        assert res.mask[..., 9:-2].all()  # views 1 and 2 agree there
        res1 = geometric_consistency(d, K, w2c, sd, sK, sw, min_views=1)
        assert res1.mask[..., 2:-2].all()

    def test_rejects_corrupted_reference(self):
        d, K, w2c, sd, sK, sw = _setup()
        d = d.clone()
        d[..., 5, 5] = 2.5
        d[..., 6, 6] = 0.0
        res = geometric_consistency(d, K, w2c, sd, sK, sw, min_views=1)
        assert not res.mask[0, 0, 5, 5] and not res.mask[0, 0, 6, 6]
        assert torch.isinf(res.reproj_error[0, :, 6, 6]).all()

    def test_non_finite_reference_depth_is_inconsistent_not_a_crash(self):
        """An inf / NaN reference depth (a render with no surface) projects nowhere: it used to give
        NaN pixel coordinates cast to an out-of-range index (RuntimeError)."""
        d, K, w2c, sd, sK, sw = _setup()
        ref = geometric_consistency(d, K, w2c, sd, sK, sw, min_views=1)
        d = d.clone()
        d[..., 3, 4], d[..., 7, 9], d[..., 8, 2] = float("inf"), float("nan"), float("-inf")
        res = geometric_consistency(d, K, w2c, sd, sK, sw, min_views=1)
        bad = torch.zeros(12, 16, dtype=torch.bool)
        bad[3, 4] = bad[7, 9] = bad[8, 2] = True
        assert not res.mask[0, 0][bad].any() and torch.isinf(res.reproj_error[0][:, bad]).all()
        assert torch.equal(res.mask[0, 0][~bad], ref.mask[0, 0][~bad])
        assert torch.equal(res.reproj_error[0][:, ~bad], ref.reproj_error[0][:, ~bad])

    def test_exceptions(self):
        d, K, w2c, sd, sK, sw = _setup()
        with pytest.raises(ValueError, match="src_depth"):
            geometric_consistency(d, K, w2c, torch.cat([sd, sd], 2), sK, sw)
        with pytest.raises(ValueError, match="src_depth"):
            geometric_consistency(d, K, w2c, sd[:, 0], sK, sw)
        with pytest.raises(ValueError, match="min_views"):
            geometric_consistency(d, K, w2c, sd, sK, sw, min_views=4)

    def test_reproject_identity_pose_is_exact(self):
        d, K, *_ = _setup()
        err, rel = reproject_depth(d, K, d, K, torch.eye(4)[None])
        assert err.max() < 1e-4 and rel.max() < 1e-6
