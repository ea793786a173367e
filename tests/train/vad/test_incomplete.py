"""Incompleteness of the instances of a view (:mod:`vadgs.train.vad.incomplete`): :func:`find_incomplete`
against a naive per-instance reference and the paper's rules, the voxel labels it reads, and the checks
of :class:`IncompleteConfig`."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import vadgs.geometry
from tests.train.vad.config_cases import check_bad_value, field_cases
from vadgs.geometry.voxel import voxel_labels
from vadgs.train.vad.incomplete import IncompleteConfig, find_incomplete


def _naive(ins, vox, ren, alpha, cfg, vindex=None, vlabels=None):
    rows = {}
    b = ins.shape[0]
    for v in range(b):
        for i in ins[v].unique().tolist():
            if i in cfg.ignore_ids:
                continue
            m = ins[v] == i
            n = int(m.sum())
            if n < cfg.min_pixels:
                continue
            a = alpha[v, 0][m]
            low = float((a < cfg.alpha_threshold).float().mean())
            ratios = []
            for d_v, d_r, al in zip(vox[v, 0][m].tolist(), ren[v, 0][m].tolist(), a.tolist()):
                if d_v > 0:
                    absent = al < cfg.min_alpha_for_depth or d_r <= 0
                    ratios.append(math.inf if absent else d_r / d_v)
            ratios.sort()
            med = ratios[(len(ratios) - 1) // 2] if ratios else math.nan
            foreign = math.nan
            if vlabels is not None:
                idx = vindex[v][m]
                idx = idx[idx >= 0]
                if idx.numel():
                    foreign = float((vlabels[idx] != i).float().mean())
            flagged = (med > cfg.depth_ratio) or (low > cfg.low_alpha_fraction)  # foreign: reported only
            rows[(v, i)] = (flagged, med, low, foreign, n)
    return rows


def _random_case(seed, b=3, h=24, w=32):
    g = torch.Generator().manual_seed(seed)
    ins = torch.randint(0, 6, (b, h, w), generator=g)
    vox = torch.rand(b, 1, h, w, generator=g) * 20 + 1
    vox[torch.rand(b, 1, h, w, generator=g) < 0.3] = 0
    ren = vox * (0.8 + 0.5 * torch.rand(b, 1, h, w, generator=g))
    alpha = torch.rand(b, 1, h, w, generator=g)
    return ins, vox, ren, alpha


class TestFindIncomplete:
    def test_smoke(self):
        ins, vox, ren, alpha = _random_case(0)
        out = find_incomplete(ins, vox, ren, alpha)
        assert out.flagged.dtype == torch.bool

    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_matches_naive_reference(self, seed):
        ins, vox, ren, alpha = _random_case(seed)
        cfg = IncompleteConfig(min_pixels=5)
        out = find_incomplete(ins, vox, ren, alpha, cfg)
        ref = _naive(ins, vox, ren, alpha, cfg)
        assert len(ref) == out.view.numel()
        for k in range(out.view.numel()):
            flagged, med, low, _, n = ref[(int(out.view[k]), int(out.instance[k]))]
            assert bool(out.flagged[k]) == flagged
            assert int(out.pixels[k]) == n
            assert float(out.low_alpha[k]) == pytest.approx(low, abs=1e-6)
            if math.isnan(med):
                assert math.isnan(float(out.depth_ratio[k]))
            else:
                assert float(out.depth_ratio[k]) == pytest.approx(med, rel=1e-5)

    def test_foreign_voxels_match_reference(self):
        """The share of pixels on other instances' voxels is reported; it flags nothing (the
        never-used ``foreign_fraction`` is gone): the same flags as without labels."""
        ins, vox, ren, alpha = _random_case(3)
        g = torch.Generator().manual_seed(3)
        vindex = torch.randint(-1, 50, ins.shape, generator=g)
        vlabels = torch.randint(0, 6, (50,), generator=g)
        cfg = IncompleteConfig(min_pixels=5)
        out = find_incomplete(ins, vox, ren, alpha, cfg, vindex, vlabels)
        ref = _naive(ins, vox, ren, alpha, cfg, vindex, vlabels)
        assert torch.equal(out.flagged, find_incomplete(ins, vox, ren, alpha, cfg).flagged)
        for k in range(out.view.numel()):
            flagged, _, _, foreign, _ = ref[(int(out.view[k]), int(out.instance[k]))]
            assert bool(out.flagged[k]) == flagged
            assert float(out.foreign[k]) == pytest.approx(foreign, abs=1e-6)
        assert 0 < float(out.foreign.nan_to_num(0).max()) and not hasattr(cfg, "foreign_fraction")

    def test_paper_rules(self):
        # four instances: complete; rendered behind voxels (ratio 1.2); transparent (alpha 0.5);
        # rendered in front of voxels (completed geometry, not flagged)
        ins = torch.zeros(1, 8, 32, dtype=torch.long)
        for k in range(4):
            ins[0, :, 8 * k : 8 * (k + 1)] = k + 1
        vox = torch.full((1, 1, 8, 32), 10.0)
        ren = vox.clone()
        ren[..., 8:16] = 12.0
        ren[..., 24:32] = 6.0
        alpha = torch.ones(1, 1, 8, 32)
        alpha[..., 16:24] = 0.5
        out = find_incomplete(ins, vox, ren, alpha)
        assert out.flagged.tolist() == [False, True, True, False]
        # no rendered depth at all counts as absent → flagged
        out = find_incomplete(ins, vox, torch.zeros_like(ren), torch.zeros_like(alpha))
        assert out.flagged.all()

    def test_exception(self):
        ins, vox, ren, alpha = _random_case(0)
        with pytest.raises(ValueError, match="voxel_depth"):
            find_incomplete(ins, vox[:, :, :4], ren, alpha)
        with pytest.raises(ValueError, match="give both"):
            find_incomplete(ins, vox, ren, alpha, voxel_labels=torch.zeros(3, dtype=torch.long))


class TestVoxelLabels:
    def test_majority_against_naive(self):
        g = torch.Generator().manual_seed(0)
        p2v = torch.randint(-1, 30, (500,), generator=g)
        lab = torch.randint(0, 5, (500,), generator=g)
        out = voxel_labels(p2v, lab, 32)
        for v in range(32):
            ls = lab[p2v == v].tolist()
            if not ls:
                assert out[v] == 0
                continue
            best = min(set(ls), key=lambda x: (-ls.count(x), x))
            assert out[v] == best

    def test_is_the_geometry_one(self):
        """Moved to :mod:`vadgs.geometry.voxel`; still importable from here."""
        assert voxel_labels is vadgs.geometry.voxel_labels


class TestIncompleteConfig:
    """Every field has one rule, next to it (:func:`vadgs.checks.checked`; ``tests/test_config_rules.py``
    checks every config), run at construction (issue 39, item 5); valid values normalised."""

    @pytest.mark.parametrize(("name", "bad"), field_cases(IncompleteConfig))
    def test_bad_value_at_construction(self, name, bad):
        check_bad_value(IncompleteConfig, name, bad)

    def test_messages_and_valid_values(self):
        with pytest.raises(ValueError, match=r"^min_pixels: expected an integer >= 0, got -1$"):
            IncompleteConfig(min_pixels=-1)
        inc = IncompleteConfig(alpha_threshold=0, low_alpha_fraction=1, ignore_ids=[0, np.int64(3)])
        assert inc.ignore_ids == (0, 3) and all(type(i) is int for i in inc.ignore_ids)
        assert IncompleteConfig() == IncompleteConfig()
