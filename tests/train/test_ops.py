from __future__ import annotations

import pytest
import torch

from vadgs.train.model import PER_GAUSSIAN, GaussianModel, make_optimizer
from vadgs.train.strategy import ops


def _setup(n=6, tracks=1):
    torch.manual_seed(0)
    nodes = torch.tensor([-1, -1, -1, 0, 0, -1][:n])
    m = GaussianModel(
        torch.randn(n, 3),
        torch.rand(n, 3),
        torch.randn(n, 3) * 0.1 - 2,
        nodes,
        torch.eye(4).repeat(tracks, 2, 1, 1),
        torch.ones(tracks, 2, dtype=torch.bool),
        list(range(tracks)),
        sh_degree=1,
    )
    opt = make_optimizer(m, dict.fromkeys([*PER_GAUSSIAN, "sky"], 1e-2))
    # one step so that the moments are non-zero and distinct per row
    loss = sum(
        (p * torch.arange(1, p.shape[0] + 1).reshape(-1, *[1] * (p.dim() - 1))).square().sum()
        for p in m.params.values()
    )
    loss.backward()
    opt.step()
    opt.zero_grad()
    state = {"grad2d": torch.arange(n, dtype=torch.float32), "count": torch.ones(n), "scene_scale": 1.0}
    return m, opt, state


def _moments(m, opt, name):
    st = opt.state[m.params[name]]
    return st["exp_avg"], st["exp_avg_sq"]


def _consistent(m, opt):
    for g in opt.param_groups:
        if g["name"] in PER_GAUSSIAN:
            p = g["params"][0]
            assert p is m.params[g["name"]]
            if p in opt.state:
                assert opt.state[p]["exp_avg"].shape == p.shape
                assert opt.state[p]["exp_avg_sq"].shape == p.shape
    assert m.node_ids.shape[0] == m.num_gaussians


def _step_ok(m, opt):
    sum(p.sum() for p in m.params.values()).backward()
    opt.step()
    opt.zero_grad()


class TestRemove:
    def test_naive(self):
        m, opt, st = _setup()
        old = {
            k: (m.params[k].detach().clone(), *[x.clone() for x in _moments(m, opt, k)]) for k in PER_GAUSSIAN
        }
        mask = torch.tensor([False, True, False, True, False, False])
        ops.remove_gaussians(m.params, opt, st, mask)
        keep = [0, 2, 4, 5]
        for k in PER_GAUSSIAN:
            p, ea, eas = old[k]
            assert torch.equal(m.params[k].data, p[keep])
            a, b = _moments(m, opt, k)
            assert torch.equal(a, ea[keep]) and torch.equal(b, eas[keep])
        assert st["grad2d"].tolist() == [0.0, 2.0, 4.0, 5.0] and m.node_ids.tolist() == [-1, -1, 0, -1]
        _consistent(m, opt)
        _step_ok(m, opt)

    def test_bad_mask(self):
        m, opt, st = _setup()
        with pytest.raises(ValueError, match="mask"):
            ops.remove_gaussians(m.params, opt, st, torch.zeros(3, dtype=torch.bool))


class TestDuplicate:
    def test_naive(self):
        m, opt, st = _setup()
        old_means = m.params["means"].detach().clone()
        old_m = _moments(m, opt, "means")[0].clone()
        mask = torch.tensor([False, False, False, True, False, True])
        ops.duplicate(m.params, opt, st, mask)
        assert m.num_gaussians == 8
        assert torch.equal(m.params["means"].data, torch.cat([old_means, old_means[[3, 5]]]))
        ea = _moments(m, opt, "means")[0]
        assert torch.equal(ea[:6], old_m) and bool((ea[6:] == 0).all())
        assert m.node_ids[6:].tolist() == [0, -1] and st["grad2d"][6:].tolist() == [0.0, 0.0]
        _consistent(m, opt)
        _step_ok(m, opt)


class TestSplit:
    def test_children(self):
        m, opt, st = _setup()
        p0 = {k: v.detach().clone() for k, v in m.params.items()}
        mask = torch.tensor([True, False, False, True, False, False])
        ops.split(m.params, opt, st, mask, torch.Generator().manual_seed(0))
        assert m.num_gaussians == 8
        assert torch.equal(m.params["means"].data[:4], p0["means"][[1, 2, 4, 5]])
        children = m.params["log_scales"].data[4:]
        parents = p0["log_scales"][[0, 3]].repeat(2, 1)
        assert torch.allclose(children, parents - torch.log(torch.tensor(1.6)))
        assert m.node_ids.tolist() == [-1, -1, 0, -1, -1, 0, -1, 0]
        assert bool((_moments(m, opt, "quats")[1][4:] == 0).all())
        # children stay within a few sigma of their parents
        d = (m.params["means"].data[4:] - p0["means"][[0, 3]].repeat(2, 1)).norm(dim=-1)
        assert bool((d < 5 * p0["log_scales"][[0, 3]].exp().amax(-1).repeat(2)).all())
        _consistent(m, opt)
        _step_ok(m, opt)


class TestAdd:
    def test_add_to_track_node(self):
        m, opt, st = _setup()
        new = {k: torch.ones(2, *v.shape[1:]) for k, v in m.params.items()}
        ops.add_gaussians(m.params, opt, st, new, torch.tensor([0, 0]))
        assert m.num_gaussians == 8 and m.node_ids[-2:].tolist() == [0, 0]
        assert bool((m.params["means"].data[-2:] == 1).all())
        assert bool((_moments(m, opt, "sh_dc")[0][-2:] == 0).all()) and st["count"][-2:].tolist() == [
            0.0,
            0.0,
        ]
        _consistent(m, opt)
        _step_ok(m, opt)

    def test_bad_input(self):
        m, opt, st = _setup()
        new = {k: torch.ones(2, *v.shape[1:]) for k, v in m.params.items()}
        with pytest.raises(ValueError, match="node_ids"):
            ops.add_gaussians(m.params, opt, st, new, torch.tensor([0, 5]), num_nodes=1)
        new["means"] = torch.ones(2, 2)
        with pytest.raises(ValueError, match="means"):
            ops.add_gaussians(m.params, opt, st, new, torch.tensor([0, 0]))


class TestModelFree:
    """The ops know params mappings only (gsplat's ``strategy/ops.py``), not vadgs's model."""

    def test_no_import_of_the_model(self):
        import networkx as nx

        from tests.test_imports import import_graph

        below = nx.descendants(import_graph(), "vadgs.train.strategy.ops")
        assert not any(m.startswith("vadgs.train") for m in below), sorted(below)

    def test_not_a_mapping(self):
        with pytest.raises(TypeError, match=r"params: expected a params mapping .* got list"):
            ops.reset_opacity([torch.zeros(3)], None, 0.01)
        m, opt, st = _setup()
        with pytest.raises(TypeError, match=r"model\.params\), got GaussianModel"):
            ops.remove_gaussians(m, opt, st, torch.tensor([True, False, False, False, False, False]))
        assert m.num_gaussians == 6  # nothing removed

    def test_node_ids_checked_without_num_nodes(self):
        m, opt, st = _setup()
        new = {k: torch.ones(2, *v.shape[1:]) for k, v in m.params.items()}
        ops.add_gaussians(m.params, opt, st, new, torch.tensor([0, 7]))  # no num_nodes: not bounded above
        assert m.node_ids[-2:].tolist() == [0, 7]
        with pytest.raises(ValueError, match=r"node_ids: expected values in \[-1, 1\), got \[-2, 0\]"):
            ops.add_gaussians(m.params, opt, st, new, torch.tensor([-2, 0]), num_nodes=1)


class TestResetOpacity:
    def test_reset(self):
        m, opt, _ = _setup()
        ops.reset_opacity(m.params, opt, 0.01)
        assert bool((torch.sigmoid(m.params["opacity_logits"]) <= 0.0100001).all())
        assert bool((_moments(m, opt, "opacity_logits")[0] == 0).all())
        _consistent(m, opt)


class TestProvenance:
    """Clones and splits keep the event that added their parent; additions default to 0."""

    def test_duplicate_split_add_follow_the_rows(self):
        m, opt, st = _setup()
        m.provenance = torch.tensor([0, 2, 0, 1, 0, 3])
        ops.duplicate(m.params, opt, st, torch.tensor([False, True, False, True, False, False]))
        assert m.provenance.tolist() == [0, 2, 0, 1, 0, 3, 2, 1]
        ops.split(m.params, opt, st, torch.tensor([False, False, False, False, False, True, True, False]))
        assert m.provenance.tolist() == [0, 2, 0, 1, 0, 1, 3, 2, 3, 2]
        ops.remove_gaussians(m.params, opt, st, m.provenance == 2)
        assert m.provenance.tolist() == [0, 0, 1, 0, 1, 3, 3]
        new = {k: torch.zeros(2, *m.params[k].shape[1:]) for k in PER_GAUSSIAN}
        ops.add_gaussians(m.params, opt, st, new)
        assert m.provenance.tolist()[-2:] == [0, 0]
        ops.add_gaussians(m.params, opt, st, {**new, "provenance": torch.tensor([4, 4])})
        assert m.provenance.tolist()[-2:] == [4, 4]
        assert not m.provenance.requires_grad and m.provenance.dtype == torch.int64
        _consistent(m, opt)
        _step_ok(m, opt)


def _appearance(n=5):
    """gsplat's appearance-optimisation layout: ``features`` and ``colors`` instead of SH, one Adam each."""
    g = torch.Generator().manual_seed(1)
    splats = torch.nn.ParameterDict(
        {
            "means": torch.nn.Parameter(torch.randn(n, 3, generator=g)),
            "scales": torch.nn.Parameter(torch.rand(n, 3, generator=g).log()),
            "quats": torch.nn.Parameter(torch.randn(n, 4, generator=g)),
            "opacities": torch.nn.Parameter(torch.randn(n, generator=g)),
            "features": torch.nn.Parameter(torch.randn(n, 32, generator=g)),
            "colors": torch.nn.Parameter(torch.randn(n, 3, generator=g)),
        }
    )
    opts = {k: torch.optim.Adam([splats[k]], lr=1e-2) for k in splats}
    sum(p.square().sum() for p in splats.values()).backward()
    for o in opts.values():
        o.step()
    return splats, opts


class TestUnknownKeys:
    """Keys outside the two layouts (gsplat's ``features`` / ``colors``) follow the rows, as in gsplat."""

    def test_layout(self):
        splats, _ = _appearance()
        names = ops.param_names(splats)
        assert names[:4] == ops.GSPLAT_NAMES[:4] and names.sh_dc is None and names.sh_rest is None

    def test_duplicate_split_remove(self):
        splats, opts = _appearance()
        feat, col = splats["features"].detach().clone(), splats["colors"].detach().clone()
        state = {"grad2d": torch.arange(5.0)}
        ops.duplicate(splats, opts, state, torch.tensor([False, True, False, False, True]))
        assert torch.equal(splats["features"][5:], feat[[1, 4]]) and torch.equal(
            splats["colors"][5:], col[[1, 4]]
        )
        assert torch.equal(opts["features"].state[splats["features"]]["exp_avg"][5:], torch.zeros(2, 32))
        mask = torch.zeros(7, dtype=torch.bool)
        mask[0] = True
        ops.split(splats, opts, state, mask, generator=torch.Generator().manual_seed(0))
        assert splats["features"].shape == (8, 32) and torch.equal(splats["features"][6:], feat[[0, 0]])
        ops.remove_gaussians(splats, opts, state, torch.arange(8) < 3)
        assert torch.equal(splats["features"][:3], feat[[4, 1, 4]])
        for k in splats:
            assert opts[k].state[splats[k]]["exp_avg"].shape == splats[k].shape, k
        assert state["grad2d"].shape == (5,)

    def test_vad_adds_with_defaults(self):
        """New VAD-GS Gaussians: ``colors`` = logit of the MVS colour, ``features`` (unknown) = 0."""
        from vadgs.train.vad import VisibilityAwareDensification, flat_gaussians
        from vadgs.train.vad.reconstruct import InstanceReconstruction

        splats, opts = _appearance()
        old = {k: v.detach().clone() for k, v in splats.items()}
        rgb = torch.tensor([[0.2, 0.5, 0.9], [0.7, 0.1, 0.3]])
        rec = InstanceReconstruction(
            torch.randn(2, 3), torch.tensor([[0.0, 0.0, 1.0]] * 2), rgb, torch.full((2,), 0.1),
            None, [0], [], [], "ok",
        )  # fmt: skip
        cfg = VisibilityAwareDensification().config
        ops.add_gaussians(
            splats, opts, None, flat_gaussians(splats, rec, None, cfg.new_opacity, cfg.flatness)
        )
        assert splats["means"].shape[0] == 7
        torch.testing.assert_close(splats["colors"][5:].detach(), torch.logit(rgb))
        assert torch.equal(splats["features"][5:], torch.zeros(2, 32))
        for k in splats:
            assert torch.equal(splats[k][:5].detach(), old[k]), k
            assert torch.equal(opts[k].state[splats[k]]["exp_avg"][5:], torch.zeros_like(splats[k][5:])), k
