"""The geometric priors of the losses (:mod:`vadgs.train.vad.priors`): the MVS depth and normals an
event keeps (:func:`merge_priors`) against a pixel-by-pixel reference, read back from the state
(:func:`state_priors`) as a view's targets (:func:`view_targets`): the MVS depth where it exists,
else the voxel depth of the pixel's own instance, cut to the view's own size."""

from __future__ import annotations

import itertools
from types import SimpleNamespace

import pytest
import torch

from tests.train.vad.sample import sample_reconstruction
from vadgs.train.vad.priors import merge_priors, state_priors, view_targets

# -- merge_priors ------------------------------------------------------------------------------------


def _naive_merge(priors, views, depths, normals):
    """Pixel by pixel: a view's new depth (and normal) replaces the old one where it is > 0."""
    out = {v: (d.clone(), n.clone()) for v, (d, n) in priors.items()}
    for v, d, n in zip(views, depths, normals):
        if v not in out:
            out[v] = (d.clone(), n.clone())
            continue
        od, on = out[v]
        for y in range(d.shape[-2]):
            for x in range(d.shape[-1]):
                if d[0, y, x] > 0:
                    od[0, y, x] = d[0, y, x]
                    on[:, y, x] = n[:, y, x]
    return out


class TestMergePriors:
    def test_hand_values(self):
        old_d = torch.tensor([[[1.0, 2.0], [3.0, 0.0]]])
        old_n = torch.arange(12.0).reshape(3, 2, 2)
        priors = {4: (old_d, old_n)}
        new_d = torch.tensor([[[0.0, 5.0], [0.0, 6.0]]])
        new_n = -torch.ones(3, 2, 2)
        rec = sample_reconstruction(1, 0, 0)._replace(
            views=[4, 8], depth=[new_d, new_d * 2], normal=[new_n, new_n * 2]
        )
        merge_priors(priors, rec)
        assert priors[4][0].tolist() == [[[1.0, 5.0], [3.0, 6.0]]]
        assert priors[4][1][:, 0, 0].tolist() == [0.0, 4.0, 8.0]  # kept: no new depth there
        assert priors[4][1][:, 1, 1].tolist() == [-1.0, -1.0, -1.0]  # replaced
        assert priors[8][0] is rec.depth[1] and priors[8][1] is rec.normal[1]  # a new view: as is

    def test_against_naive(self):
        g = torch.Generator().manual_seed(0)

        def maps():
            d = torch.rand(1, 5, 6, generator=g)
            d[torch.rand(1, 5, 6, generator=g) < 0.5] = 0  # half the pixels without depth
            return d, torch.randn(3, 5, 6, generator=g)

        priors = {v: maps() for v in (0, 2)}
        for views in ([0, 1], [2, 0, 1], [1, 1]):
            new = [maps() for _ in views]
            rec = sample_reconstruction(1, 0, 0)._replace(
                views=views, depth=[d for d, _ in new], normal=[n for _, n in new]
            )
            expect = _naive_merge(priors, views, rec.depth, rec.normal)
            merge_priors(priors, rec)
            assert sorted(priors) == sorted(expect)
            for v in expect:
                assert torch.equal(priors[v][0], expect[v][0]) and torch.equal(priors[v][1], expect[v][1]), v

    def test_beyond_the_voxels_against_naive(self):
        """With ``beyond``, the new depth and normals only where the view's voxel z-buffer is empty;
        the old priors (kept, as cut when they came) elsewhere, pixel by pixel."""
        g = torch.Generator().manual_seed(3)
        vox = {v: torch.rand(1, 5, 6, generator=g) * 10 + 1 for v in (0, 1)}
        for d in vox.values():
            d[torch.rand(1, 5, 6, generator=g) < 0.5] = 0  # beyond the voxels
        index = SimpleNamespace(voxel_depth=lambda view: (vox[view], torch.zeros(5, 6, dtype=torch.long)))

        def maps():
            d = torch.rand(1, 5, 6, generator=g) + 1
            d[torch.rand(1, 5, 6, generator=g) < 0.3] = 0
            return d, torch.randn(3, 5, 6, generator=g)

        priors: dict = {}
        for views in ([0, 1], [1, 0]):
            new = [maps() for _ in views]
            cut = [(d * (vox[v] == 0), n * (vox[v] == 0)) for v, (d, n) in zip(views, new)]
            expect = _naive_merge(priors, views, [d for d, _ in cut], [n for _, n in cut])
            rec = sample_reconstruction(1, 0, 0)._replace(
                views=views, depth=[d for d, _ in new], normal=[n for _, n in new]
            )
            merge_priors(priors, rec, index)
            for v in expect:
                assert torch.equal(priors[v][0], expect[v][0]) and torch.equal(priors[v][1], expect[v][1]), v
        for v, (d, n) in priors.items():
            assert not (d[vox[v] > 0] != 0).any() and not (n[(vox[v] > 0).expand(3, 5, 6)] != 0).any()
            assert (d > 0).any()  # MVS pixels kept beyond the voxels
        everywhere: dict = {}
        merge_priors(everywhere, rec)
        assert any((d[vox[v] > 0] > 0).any() for v, (d, _) in everywhere.items())  # the default keeps all


# -- state_priors and view_targets -------------------------------------------------------------------


class TestStatePriors:
    def test_reads_the_state_and_names_a_wrong_one(self):
        priors = {3: (torch.ones(1, 2, 2), torch.zeros(3, 2, 2))}
        assert state_priors({"vad_priors": priors, "scene_scale": 1.0}) is priors
        with pytest.raises(
            ValueError, match=r"^state: expected the strategy's state .*got keys \['scene_scale'\]$"
        ):
            state_priors({"scene_scale": 1.0})
        with pytest.raises(ValueError, match=r"^state: expected the strategy's state .*got list$"):
            state_priors([])


PH, PW = 5, 7  # the index's (padded) maps
H, W = 4, 6  # the view's own size


def _index(own_depth):
    """A stand-in of the index: every view of size ``(H, W)``, its own-instance voxel depth ``own_depth``."""
    return SimpleNamespace(own_voxel_depth=lambda view, tracks=True: own_depth, size=lambda view: (H, W))


class TestViewTargets:
    @pytest.mark.parametrize("seed", [0, 1])
    def test_mvs_depth_else_the_voxel_depth_cut_to_the_view(self, seed):
        g = torch.Generator().manual_seed(seed)
        own = torch.rand(1, PH, PW, generator=g) * 10 + 1
        own[torch.rand(1, PH, PW, generator=g) < 0.3] = 0  # no voxel of the pixel's own instance
        mvs = torch.rand(1, PH, PW, generator=g) * 10 + 1
        mvs[torch.rand(1, PH, PW, generator=g) < 0.5] = 0  # half the pixels without MVS depth
        normal = torch.randn(3, PH, PW, generator=g)
        t = view_targets({2: (mvs, normal)}, _index(own), 2)
        expect = torch.zeros(1, 1, H, W)
        for y, x in itertools.product(range(H), range(W)):  # pixel by pixel
            expect[0, 0, y, x] = mvs[0, y, x] if mvs[0, y, x] > 0 else own[0, y, x]
        assert torch.equal(t.depth, expect) and torch.equal(t.normal, normal[None, :, :H, :W])
        assert 0 < int((mvs[0, :H, :W] > 0).sum()) < H * W  # both sources are used

    def test_without_mvs_depth_or_voxel_prior(self):
        own = torch.arange(float(PH * PW)).reshape(1, PH, PW)
        t = view_targets({}, _index(own), 0)
        assert t.normal is None and torch.equal(t.depth, own[None, :, :H, :W])
        assert view_targets({}, _index(own), 0, voxel_depth_prior=False) is None
        mvs, normal = torch.ones(1, PH, PW), torch.ones(3, PH, PW)
        t = view_targets({0: (mvs, normal)}, _index(own), 0, voxel_depth_prior=False)
        assert torch.equal(t.depth, torch.ones(1, 1, H, W)) and t.normal.shape == (1, 3, H, W)
