from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from vadgs.select import Covisibility, colmap_scores, consecutive_views, mvsnet_scores, top_k_views

from .select_helpers import random_scene


def _angles(covis, visible, ref, src):
    """Triangulation angles (deg) over the voxels both views see: a plain loop."""
    c2w = np.linalg.inv(covis.world_to_cam.double().numpy())
    c_r, c_s = c2w[ref][:3, 3], c2w[src][:3, 3]
    out = []
    for m in sorted(set(visible[ref].tolist()) & set(visible[src].tolist())):
        p = covis.voxel_centers[m].double().numpy()
        a, b = c_r - p, c_s - p
        cos = a @ b / np.linalg.norm(a) / np.linalg.norm(b)
        out.append(math.degrees(math.acos(max(-1.0, min(1.0, cos)))))
    return out


def _covis(seed=0):
    centers, visible, w2c = random_scene(num_views=10, seed=seed)
    return Covisibility.from_visible(visible, centers, w2c), visible


class TestMvsnetScores:
    def test_smoke(self):
        covis, _ = _covis()
        assert mvsnet_scores(covis, 0).shape == (10,)

    def test_exception(self):
        covis, _ = _covis()
        with pytest.raises(ValueError, match="ref"):
            mvsnet_scores(covis, 10)

    @pytest.mark.parametrize("seed", [0, 1])
    def test_matches_naive_loop(self, seed):
        covis, visible = _covis(seed)
        for ref in (0, 3):
            want = []
            for src in range(10):
                g = 0.0
                if src != ref:
                    for th in _angles(covis, visible, ref, src):
                        sigma = 1.0 if th <= 5.0 else 10.0
                        g += math.exp(-((th - 5.0) ** 2) / (2 * sigma**2))
                want.append(g)
            np.testing.assert_allclose(mvsnet_scores(covis, ref).numpy(), want, rtol=1e-4, atol=1e-6)


class TestColmapScores:
    @pytest.mark.parametrize("seed", [0, 1])
    @pytest.mark.parametrize("min_angle", [1.0, 8.0])
    def test_matches_naive_loop(self, seed, min_angle):
        covis, visible = _covis(seed)
        for ref in (0, 5):
            want = []
            for src in range(10):
                th = sorted(_angles(covis, visible, ref, src))
                if src == ref or not th:
                    want.append(0.0)
                    continue
                q = th[math.floor((len(th) - 1) * 0.75)]
                want.append(float(len(th)) if q >= min_angle else 0.0)
            got = colmap_scores(covis, ref, min_triangulation_angle=min_angle)
            np.testing.assert_allclose(got.numpy(), want)


class TestConsecutiveViews:
    def test_nearest_same_camera(self):
        cams = torch.tensor([0, 1, 2] * 6)
        frames = torch.arange(18) // 3
        # reference: camera 1 at frame 2 (view 7) -> frames 1, 3, 0, 4 of camera 1
        assert consecutive_views(7, cams, frames, k=4).tolist() == [4, 10, 1, 13]

    def test_allowed_and_few(self):
        cams = torch.tensor([0, 0, 0])
        frames = torch.tensor([0, 1, 2])
        assert consecutive_views(
            0, cams, frames, k=4, allowed=torch.tensor([True, False, True])
        ).tolist() == [2]

    def test_exception(self):
        with pytest.raises(ValueError, match="frame_ids"):
            consecutive_views(0, torch.zeros(3, dtype=torch.long), torch.zeros(4, dtype=torch.long))


class TestTopKViews:
    def test_excludes_ref_and_non_positive(self):
        assert top_k_views(torch.tensor([5.0, 0.0, -1.0, 2.0]), 0, 4).tolist() == [3]
        assert top_k_views(torch.tensor([5.0, 0.0]), 0, 4).shape == (0,)
