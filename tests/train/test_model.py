from __future__ import annotations

import pytest
import torch

from vadgs.geometry.rotation import quaternion_to_rotation
from vadgs.train.init import InitConfig, init_gaussians
from vadgs.train.model import PER_GAUSSIAN, GaussianModel, gaussians_at, make_optimizer


def _random_rotations(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    q = torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=torch.float64), dim=-1)
    return q, quaternion_to_rotation(q)


def _model(n_static=3, n_obj=2, frames=3):
    means = torch.randn(n_static + n_obj, 3)
    nodes = torch.tensor([-1] * n_static + [0] * n_obj)
    o2w = torch.eye(4).repeat(1, frames, 1, 1)
    _, R = _random_rotations(frames, 3)
    o2w[0, :, :3, :3] = R.float()
    o2w[0, :, :3, 3] = torch.arange(frames, dtype=torch.float32)[:, None] * torch.tensor([2.0, 0.0, 0.0])
    valid = torch.ones(1, frames, dtype=torch.bool)
    valid[0, 1] = False
    return GaussianModel(
        means,
        torch.rand(len(nodes), 3),
        torch.full((len(nodes), 3), -2.0),
        nodes,
        o2w,
        valid,
        [7],
        sh_degree=1,
    )


class TestGaussiansAt:
    def test_smoke(self):
        g = _model().gaussians_at(0)
        assert g.means.shape == (5, 3) and g.sh.shape == (5, 4, 3) and g.ids.tolist() == [0, 1, 2, 3, 4]

    def test_static_untouched_and_track_posed(self):
        m = _model()
        for f in (0, 2):
            g = m.gaussians_at(f)
            o2w = m.object_to_world[0, f]
            local = m.params["means"][3:]
            assert torch.allclose(g.means[:3], m.params["means"][:3])
            assert torch.allclose(g.means[3:], local @ o2w[:3, :3].T + o2w[:3, 3], atol=1e-6)
            Rg = quaternion_to_rotation(g.quats[3:])
            Rl = quaternion_to_rotation(m.params["quats"][3:])
            assert torch.allclose(Rg, o2w[:3, :3] @ Rl, atol=1e-5)

    def test_invalid_frame_drops_node(self):
        g = _model().gaussians_at(1)
        assert g.ids.tolist() == [0, 1, 2]

    def test_gradient_reaches_local_params(self):
        m = _model()
        g = m.gaussians_at(2)
        g.means.sum().backward()
        assert m.params["means"].grad[3:].abs().sum() > 0

    def test_bad_node_ids(self):
        with pytest.raises(ValueError, match="node_ids"):
            GaussianModel(
                torch.zeros(2, 3),
                torch.zeros(2, 3),
                torch.zeros(2, 3),
                torch.tensor([-1, 3]),
                torch.zeros(1, 2, 4, 4),
                torch.ones(1, 2, dtype=torch.bool),
                [1],
            )

    def test_functional_equals_module(self):
        m = _model()
        a = m.gaussians_at(2)
        b = gaussians_at(dict(m.params), m.node_ids, m.object_to_world, m.track_valid, 2)
        assert all(torch.equal(x, y) for x, y in zip(a, b))

    def test_state_roundtrip(self):
        m = _model()
        m.active_sh_degree = 1
        m2 = GaussianModel.from_state(m.state_dict(), m.extra_state())
        assert all(torch.equal(m.state_dict()[k], m2.state_dict()[k]) for k in m.state_dict())
        assert m2.active_sh_degree == 1 and m2.track_ids == [7]


class TestMakeOptimizer:
    def test_one_named_group_per_parameter(self):
        m = _model()
        lrs = {k: 0.1 * (i + 1) for i, k in enumerate([*PER_GAUSSIAN, "sky"])}
        opt = make_optimizer(m, lrs, eps=1e-12)
        assert [g["name"] for g in opt.param_groups] == [*PER_GAUSSIAN, "sky"]
        for g in opt.param_groups:
            held = m.sky if g["name"] == "sky" else m.params[g["name"]]
            assert g["params"] == [held] and g["lr"] == lrs[g["name"]] and g["eps"] == 1e-12
        # the integer entries (node_ids, provenance) are not optimised
        assert not any(g["name"] in ("node_ids", "provenance") for g in opt.param_groups)

    def test_missing_rate(self):
        with pytest.raises(ValueError, match=r"lrs: missing learning rates for \['sky'\]"):
            make_optimizer(_model(), dict.fromkeys(PER_GAUSSIAN, 1e-3))


class TestRenderDepth:
    def test_equals_the_full_render_with_its_gradients(self):
        torch.manual_seed(0)
        m = _model(n_static=40, n_obj=0)
        with torch.no_grad():
            m.params["means"].copy_(
                torch.randn(40, 3) * torch.tensor([1.0, 1.0, 0.3]) + torch.tensor([0, 0, 5.0])
            )
        K = torch.tensor([[[40.0, 0, 16.0], [0, 40.0, 12.0], [0, 0, 1]]])
        w2c = torch.eye(4)[None]
        outs = []
        for depth_only in (False, True):
            for p in m.params.values():
                p.grad = None
            if depth_only:
                r = m.render_depth(w2c, K, (24, 32), 0, opacity_override=1.0)
            else:
                r = m.render(w2c, K, (24, 32), 0, opacity_override=1.0).raster
            (r.depth * torch.linspace(0, 1, 32)).sum().backward()
            outs.append((r, {k: p.grad.clone() for k, p in m.params.items() if p.grad is not None}))
        (full, g_full), (geo, g_geo) = outs
        assert geo.color.shape == (1, 0, 24, 32) and bool((full.alpha > 0.5).any())
        for name in ("depth", "alpha", "normals", "median_depth"):
            assert torch.equal(getattr(full, name), getattr(geo, name)), name
        assert set(g_geo) == {"means", "quats", "log_scales"}  # opacities fixed, no colour
        for k, g in g_geo.items():
            assert torch.allclose(g, g_full[k], rtol=1e-5, atol=1e-7), k


class TestInit:
    def test_init_nodes(self, tiny_scene):
        model = init_gaussians(
            tiny_scene, InitConfig(voxel_size=0.6, max_points=800, max_object_points=100, sh_degree=0)
        )
        counts = model.node_counts()
        assert counts["static"] <= 800 and len(model.track_ids) == len(tiny_scene.tracks)
        assert sum(counts.values()) == model.num_gaussians
        assert counts[f"track_{model.track_ids[0]}"] > 0
        # object points are in the object frame: close to the origin of that frame
        obj = model.params["means"][model.node_ids == 0]
        lwh = tiny_scene.tracks[model.track_ids[0]].size_lwh
        assert bool((obj.abs().max(0).values <= lwh.max()).all())

    def test_no_lidar_no_colmap_raises(self, tiny_scene):
        with pytest.raises(ValueError, match="nothing to initialise") as e:
            init_gaussians(tiny_scene, InitConfig(use_lidar=False))
        assert "`vadgs train SCENE --colmap MODEL`" in str(e.value)  # says what to pass
