"""The priors :meth:`VisibilityAwareDensification.geometry_targets` gives a view, against a naive
pixel-by-pixel reference: the MVS depth of the events where it exists, else the voxel depth only
where the voxel belongs to the pixel's own instance (elsewhere the z-buffer sees through missing
geometry, e.g. to the facade behind a sign), cut to the view's own size."""

from __future__ import annotations

import itertools
from types import SimpleNamespace

import pytest
import torch

from vadgs.train.vad import VisibilityAwareDensification
from vadgs.train.vad.visibility import own_instance_depth

PH, PW = 5, 7  # the index's (padded) maps
H, W = 4, 6  # the view's own size


def _maps(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    vd = torch.rand(1, PH, PW, generator=g) * 10 + 1
    vd[0, 0, :3] = 0  # no voxel there
    ins = torch.randint(1, 4, (PH, PW), generator=g)
    vlabel = torch.where(
        torch.rand(PH, PW, generator=g) < 0.6, ins, torch.randint(1, 4, (PH, PW), generator=g)
    )
    vlabel[0, :3] = 0
    mvs = torch.rand(1, PH, PW, generator=g) * 10 + 1
    mvs[torch.rand(1, PH, PW, generator=g) < 0.5] = 0  # half the pixels without MVS depth
    normal = torch.randn(3, PH, PW, generator=g)
    return vd, vlabel, ins, mvs, normal


def _strategy(vd, vlabel, ins, **settings):
    """A strategy prepared with a stand-in of the index (two views of size ``(H, W)``)."""
    s = VisibilityAwareDensification(**settings)
    s.index = SimpleNamespace(
        inputs=SimpleNamespace(num_views=2),
        voxel_depth=lambda view: (vd, vlabel),
        instances=lambda view: ins,
        own_voxel_depth=lambda view: own_instance_depth(vd, vlabel, ins),  # the index's, uncached
        size=lambda view: (H, W),
    )
    return s, s.initialize_state()


def _naive(vd, vlabel, ins, mvs=None, voxel_prior=True):
    out = torch.zeros(1, 1, H, W)
    for y, x in itertools.product(range(H), range(W)):
        if mvs is not None and mvs[0, y, x] > 0:
            out[0, 0, y, x] = mvs[0, y, x]
        elif voxel_prior and vlabel[y, x] == ins[y, x]:  # the pixel's own instance's voxel only
            out[0, 0, y, x] = vd[0, y, x]
    return out


class TestGeometryTargets:
    @pytest.mark.parametrize("seed", [0, 1])
    def test_voxel_depth_of_the_own_instance_only(self, seed):
        vd, vlabel, ins, _, _ = _maps(seed)
        s, state = _strategy(vd, vlabel, ins)
        t = s.geometry_targets(state, 1)
        assert t.normal is None and t.depth.shape == (1, 1, H, W)
        expect = _naive(vd, vlabel, ins)
        assert torch.equal(t.depth, expect)
        own = (vlabel == ins)[:H, :W] & (vd[0, :H, :W] > 0)
        assert 0 < int(own.sum()) < H * W and bool((t.depth[0, 0][~own] == 0).all())

    def test_mvs_depth_first(self):
        vd, vlabel, ins, mvs, normal = _maps(2)
        s, state = _strategy(vd, vlabel, ins)
        state["vad_priors"][1] = (mvs, normal)
        t = s.geometry_targets(state, 1)
        assert torch.equal(t.depth, _naive(vd, vlabel, ins, mvs))
        assert torch.equal(t.normal, normal[None, :, :H, :W])
        assert torch.equal(s.geometry_targets(state, 0).depth, _naive(vd, vlabel, ins))  # no MVS there

    def test_switches(self):
        vd, vlabel, ins, mvs, normal = _maps(3)
        s, state = _strategy(vd, vlabel, ins, voxel_depth_prior=False)
        state["vad_priors"][1] = (mvs, normal)
        assert torch.equal(
            s.geometry_targets(state, 1).depth, _naive(vd, vlabel, ins, mvs, voxel_prior=False)
        )
        assert s.geometry_targets(state, 0) is None  # neither MVS nor voxel depth
        s, state = _strategy(vd, vlabel, ins, geometric_losses=False)
        state["vad_priors"][1] = (mvs, normal)
        assert s.geometry_targets(state, 1) is None
