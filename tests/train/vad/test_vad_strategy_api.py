"""VisibilityAwareDensification as gsplat strategies are: a dataclass holding its settings, fed by
:class:`VisibilityInputs` (a vadgs scene or gsplat's ``Parser``), with ``check_sanity``, an explicit
``prepare``, and gsplat's ``DefaultStrategy`` (packed or not) and ``MCMCStrategy`` as its base."""

from __future__ import annotations

import copy
import dataclasses
import inspect

import pytest
import torch

from vadgs.data import load_colmap
from vadgs.train.strategy import ConfiguredStrategy, DefaultStrategy, DefaultStrategyConfig, ops
from vadgs.train.vad import (
    ReconstructConfig,
    StrategyContext,
    ViewRender,
    VisibilityAwareDensification,
    VisibilityDensifyConfig,
    VisibilityInputs,
    build_visibility_index,
)

from ..gsplat_parser import facade_splats

gsplat_strategy = pytest.importorskip("gsplat.strategy")


@pytest.fixture(scope="module")
def project(colmap_sample):
    return colmap_sample


@pytest.fixture(scope="module")
def parser(colmap_sample_parser):
    return colmap_sample_parser


class TestDataclass:
    def test_gsplat_shape(self):
        assert dataclasses.is_dataclass(VisibilityAwareDensification)
        params = inspect.signature(VisibilityAwareDensification).parameters
        assert "scene" not in params and "context" not in params
        assert not any("Scene" in str(p.annotation) for p in params.values())
        assert list(params) == ["config", "base", "on_addition", "on_progress", "log_size", "settings"]
        assert params["settings"].kind is inspect.Parameter.VAR_KEYWORD


SHAPES = [
    (DefaultStrategy, DefaultStrategyConfig, "refine_every", 50, 0),
    (VisibilityAwareDensification, VisibilityDensifyConfig, "every_cycles", 3, 0),
]


@pytest.mark.parametrize(("cls", "config_cls", "name", "good", "bad"), SHAPES, ids=["default", "vad"])
class TestOneShape:
    """Both strategies hold a frozen config; settings as keywords and as checked attributes."""

    def test_keywords_config_and_attributes(self, cls, config_cls, name, good, bad):
        assert issubclass(cls, ConfiguredStrategy) and cls.config_type is config_cls
        assert dataclasses.is_dataclass(cls) and config_cls.__dataclass_params__.frozen
        s = cls(**{name: good})
        assert s.config == config_cls(**{name: good}) and getattr(s, name) == good
        assert cls(config_cls(**{name: good})).config == s.config
        for f in dataclasses.fields(config_cls):  # every setting reads through
            assert getattr(s, f.name) == getattr(s.config, f.name), f.name
        # a keyword replaces that field of a given config, the others stay
        other = next(f.name for f in dataclasses.fields(config_cls) if f.name != name)
        base = config_cls(**{name: good})
        assert cls(base, **{other: getattr(base, other)}).config == base

    def test_assignment_is_checked_and_replaces_the_config(self, cls, config_cls, name, good, bad):
        s = cls()
        before = s.config
        setattr(s, name, good)
        assert getattr(s.config, name) == good and before == config_cls()  # a new config, not edited
        with pytest.raises(ValueError, match=f"{name}: expected an integer >= 1, got {bad}"):
            setattr(s, name, bad)
        assert getattr(s, name) == good  # unchanged by the failed assignment
        with pytest.raises(ValueError, match=f"config: expected a {config_cls.__name__}, got dict"):
            s.config = {}
        with pytest.raises(ValueError, match=f"config: expected a {config_cls.__name__}, got int"):
            cls(3)

    def test_unknown_setting_and_attribute(self, cls, config_cls, name, good, bad):
        with pytest.raises(TypeError, match=r"unexpected keyword argument\(s\) \['refine_evry'\]"):
            cls(refine_evry=1)
        with pytest.raises(AttributeError, match="has no attribute 'no_such_setting'"):
            _ = cls().no_such_setting

    def test_copies(self, cls, config_cls, name, good, bad):
        s = cls(**{name: good})
        for t in (copy.copy(s), copy.deepcopy(s)):
            assert t.config == s.config and getattr(t, name) == good


class TestSettings:
    def test_init_does_not_rewrite_its_settings(self):
        s = VisibilityAwareDensification(view_selection=False)
        assert s.reconstruct == ReconstructConfig()  # as given
        assert s.reconstruct.selection.method != "consecutive"
        assert s.config.effective_reconstruct().selection.method == "consecutive"  # what the event uses
        assert s.config == VisibilityDensifyConfig(view_selection=False)

    def test_from_config_round_trip_and_checks(self):
        cfg = VisibilityDensifyConfig(every_cycles=3, references=2, skip_classes=("road", "sky"))
        s = VisibilityAwareDensification.from_config(cfg)
        assert s.config == cfg and s.every_cycles == 3 and s.index is None and s.inputs is None
        with pytest.raises(ValueError, match="every_cycles: expected an integer >= 1, got 0"):
            VisibilityAwareDensification(every_cycles=0)
        with pytest.raises(ValueError, match="log_size: expected an integer >= 1, got 0"):
            VisibilityAwareDensification(log_size=0)

    def test_needs_prepare(self):
        s = VisibilityAwareDensification()
        with pytest.raises(RuntimeError, match=r"call prepare\(inputs, context\)"):
            s.prepare()
        with pytest.raises(ValueError, match="inputs: expected VisibilityInputs, got dict"):
            s.prepare({})


class _Recording:
    """A base strategy that records every call (and checks nothing)."""

    def __init__(self) -> None:
        self.calls: list = []

    def check_sanity(self, *args, **kwargs) -> None:
        self.calls.append(("check_sanity", args, kwargs))

    def initialize_state(self, *args, **kwargs) -> dict:
        self.calls.append(("initialize_state", args, kwargs))
        return {"from_base": args[0]}

    def step_pre_backward(self, *args, **kwargs) -> None:
        self.calls.append(("step_pre_backward", args, kwargs))

    def step_post_backward(self, *args, **kwargs) -> None:
        self.calls.append(("step_post_backward", args, kwargs))


class _RecordingGsplat(gsplat_strategy.DefaultStrategy):
    """gsplat's DefaultStrategy, its ``check_sanity`` recorded (and run)."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.calls = []

    def check_sanity(self, *args, **kwargs) -> None:
        self.calls.append(("check_sanity", args, kwargs))
        super().check_sanity(*args, **kwargs)


class TestCheckSanity:
    def _splats(self, n=5):
        keys = {"means": 3, "quats": 4, "scales": 3, "opacities": None, "sh0": (1, 3), "shN": (0, 3)}
        splats = torch.nn.ParameterDict()
        for k, tail in keys.items():
            shape = (n,) if tail is None else (n, *tail) if isinstance(tail, tuple) else (n, tail)
            splats[k] = torch.nn.Parameter(torch.zeros(shape))
        return splats, {k: torch.optim.Adam([splats[k]], lr=1e-3) for k in splats}

    def test_passes_and_calls_the_base(self):
        """Its own check, then the base's, with the same ``params`` and ``optimizers``."""
        splats, opts = self._splats()
        for base in (_Recording(), _RecordingGsplat()):
            VisibilityAwareDensification(base=base).check_sanity(splats, opts)
            assert base.calls == [("check_sanity", (splats, opts), {})]
        splats2 = {k: v for k, v in splats.items() if k not in ("sh0", "shN")}  # gsplat's appearance
        splats2["colors"] = torch.nn.Parameter(torch.zeros(5, 3))
        opts2 = {k: torch.optim.Adam([splats2[k]], lr=1e-3) for k in splats2}
        base = _RecordingGsplat()
        VisibilityAwareDensification(base=base).check_sanity(splats2, opts2)
        assert [c[0] for c in base.calls] == ["check_sanity"]
        # the base's own verdict stands: gsplat's wants an optimizer for trainable params only
        extra = {**opts, "sky": torch.optim.Adam([torch.nn.Parameter(torch.zeros(1))], lr=1e-3)}
        ops.check_params(splats, extra)  # vadgs's own check lets an extra optimizer pass
        base = _RecordingGsplat()
        with pytest.raises(
            AssertionError, match="trainable parameters and optimizers must have the same keys"
        ):
            VisibilityAwareDensification(base=base).check_sanity(splats, extra)
        assert [c[0] for c in base.calls] == ["check_sanity"]
        VisibilityAwareDensification(base=object()).check_sanity(splats, opts)  # a base without one

    def test_forwards_every_call_to_the_base(self):
        """``initialize_state`` (with ``scene_scale``), ``step_pre_backward`` and
        ``step_post_backward`` reach the base with the loop's arguments and keyword arguments."""
        base = _Recording()
        vad = VisibilityAwareDensification(base=base)
        vad.context = StrategyContext(lambda v: None, total_steps=10, steps_per_cycle=100)  # no event
        state = vad.initialize_state(2.5)
        assert state["from_base"] == 2.5 and "vad_events" in state
        splats, opts = self._splats()
        info = {"width": 8}
        vad.step_pre_backward(splats, opts, state, 3, info)
        vad.step_post_backward(
            params=splats, optimizers=opts, state=state, step=3, info=info, packed=True, lr=0.1
        )
        assert base.calls == [
            ("initialize_state", (2.5,), {}),
            ("step_pre_backward", (splats, opts, state, 3, info), {}),
            ("step_post_backward", (splats, opts, state, 3, info), {"packed": True, "lr": 0.1}),
        ]

    def test_clear_errors(self):
        s = VisibilityAwareDensification()
        splats, opts = self._splats()
        splats["scales"] = torch.nn.Parameter(torch.zeros(4, 3))
        with pytest.raises(
            ValueError, match=r"params\['scales'\]: expected a tensor of 5 rows .*got \(4, 3\)"
        ):
            s.check_sanity(splats, opts)
        splats, opts = self._splats()
        del opts["shN"]
        with pytest.raises(ValueError, match=r"optimizers: expected a key 'shN', got keys \["):
            s.check_sanity(splats, opts)
        splats, opts = self._splats()
        opts["sh0"] = torch.optim.Adam([torch.nn.Parameter(torch.zeros(5, 1, 3))], lr=1e-3)  # another tensor
        with pytest.raises(ValueError, match=r"optimizers\['sh0'\]: expected one param group holding"):
            s.check_sanity(splats, opts)
        splats, _ = self._splats()
        one = torch.optim.Adam([{"params": [splats[k]], "name": k} for k in splats if k != "quats"])
        with pytest.raises(ValueError, match="expected a param group named 'quats'"):
            s.check_sanity(splats, one)
        del splats["quats"]
        with pytest.raises(ValueError, match=r"params: expected vadgs names .* got \["):
            s.check_sanity(splats, None)


class TestInputsFromParser:
    def test_same_index_as_the_vadgs_colmap_scene(self, project, parser):
        """``from_gsplat_parser`` of the Parser-like namespace and ``from_scene`` of vadgs's own
        COLMAP reader (same model, resolution and split) give the same cameras, images, TRACK
        visibility and derived instances."""
        scene, _ = load_colmap(project / "sparse" / "0", scale=0.5, test_every=8)
        ours = VisibilityInputs.from_gsplat_parser(parser)
        theirs = VisibilityInputs.from_scene(scene)
        root = str(project / "images") + "/"
        order = [parser.image_names.index(str(v.image).split(root)[-1]) for v in scene.views]
        assert sorted(order) == list(range(24))
        assert [order[v] for v in theirs.train_views] == list(ours.train_views)  # same split
        torch.testing.assert_close(ours.cameras.K[order], theirs.cameras.K, atol=1e-4, rtol=0)
        torch.testing.assert_close(
            ours.cameras.world_to_cam[order], theirs.cameras.world_to_cam, atol=1e-4, rtol=0
        )
        assert ours.cameras.image_size == theirs.cameras.image_size == (72, 120)
        torch.testing.assert_close(ours.load_image(order[5], None), theirs.load_image(5, None))
        assert ours.sfm.points.shape == theirs.sfm.points.shape
        # the same lengths (a vadgs scene is in its units, depth 10; the parser's depth is measured)
        assert theirs.scene_depth == 10.0 and ours.scene_depth == pytest.approx(11.27, abs=0.01)
        a, b = build_visibility_index(ours, 0.5, scene_depth=10.0), build_visibility_index(theirs, 0.5)
        torch.testing.assert_close(a.grid.centers, b.grid.centers)
        for m in range(len(a.grid)):
            assert {order.index(v) for v in a.grid.views_of(m).tolist()} == set(b.grid.views_of(m).tolist())
        assert a.derives_instances and b.derives_instances
        for v in (0, 7, 13):
            assert torch.equal(a.instances(order[v]), b.instances(v)), v

    def test_errors(self, parser):
        bad = copy.copy(parser)
        bad.camtoworlds = parser.camtoworlds[:3]
        with pytest.raises(ValueError, match=r"parser.camtoworlds: expected \(24, 4, 4\), got \(3, 4, 4\)"):
            VisibilityInputs.from_gsplat_parser(bad)


def _gsplat_run(parser, base, steps, post_kwargs, packed=False, monkeypatch=None):
    """A few steps on the facade scene with ``base`` under VAD-GS (4 steps a cycle: the event at step 3)."""
    torch.manual_seed(0)
    inputs = VisibilityInputs.from_gsplat_parser(parser)
    splats, optimizers, _ = facade_splats(parser, inputs)
    n0 = splats["means"].shape[0]
    vad = VisibilityAwareDensification(
        base=base,
        every_cycles=1,
        max_instances=1,
        time_budget=None,
        reconstruct=ReconstructConfig(max_crop=64),
        scene_depth=10.0,  # the sample's world is street metres: vadgs's lengths (10 m cells)
    )
    train = list(inputs.train_views)

    def rasterize(view):
        from vadgs.render import rasterize_gaussians

        s = splats
        out = rasterize_gaussians(
            s["means"], s["quats"], s["scales"].exp(), s["opacities"].sigmoid(),
            torch.cat([s["sh0"], s["shN"]], 1), inputs.cameras.world_to_cam[view : view + 1],
            inputs.cameras.K[view : view + 1], inputs.size(view),
        )  # fmt: skip
        h, w = inputs.size(view)
        return out, {"means2d": out.means2d, "radii": out.radii, "width": w, "height": h, "n_cameras": 1}

    @torch.no_grad()
    def render(view):
        out, _ = rasterize(view)
        return ViewRender(out.depth[0], out.alpha[0], out.normals[0])

    vad.check_sanity(splats, optimizers)
    vad.prepare(inputs, StrategyContext(render, total_steps=steps, steps_per_cycle=4))
    state = vad.initialize_state(scene_scale=1.0)
    for step in range(steps):
        view = train[(5 * step) % len(train)]
        out, info = rasterize(view)
        info["gaussian_ids"] = None
        vad.step_pre_backward(params=splats, optimizers=optimizers, state=state, step=step, info=info)
        (out.color[0] - inputs.load_image(view, None)).abs().mean().backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        if packed:  # gsplat's packed layout of the same render: [nnz, 2] rows and their ids
            ids = torch.nonzero((info["radii"][0] > 0).all(-1)).squeeze(1)
            m2d = torch.zeros(ids.numel(), 2, requires_grad=True)
            m2d.grad = info["means2d"].grad[0][ids]
            info = {**info, "means2d": m2d, "radii": info["radii"][0][ids], "gaussian_ids": ids}
        torch.manual_seed(100 + step)  # gsplat's split draws from the global generator
        # as gsplat's simple_trainer calls it: keywords, packed= (DefaultStrategy) or lr= (MCMC)
        vad.step_post_backward(
            params=splats, optimizers=optimizers, state=state, step=step, info=info, **post_kwargs
        )
    return splats, optimizers, state, n0


class TestGsplatBases:
    STEPS = 7  # one event (step 3: 4 steps a cycle); the base refines at steps 4 and 6

    def _check(self, splats, optimizers, state, n0):
        (event,) = state["vad_events"]
        assert event["step"] == 3 and event["added"] > 300  # one instance of the deleted facade repaired
        n = splats["means"].shape[0]
        assert n >= n0 + event["added"]
        for name, opt in optimizers.items():
            assert opt.state[splats[name]]["exp_avg"].shape == splats[name].shape, name
        return event

    def test_default_strategy_packed_and_not(self, parser):
        """gsplat's DefaultStrategy refines at steps 4 and 6, after the event; ``packed=True``
        reaches it (a packed ``info`` read as unpacked would fail) and gives the same decisions."""
        runs = {}
        for packed in (False, True):
            base = gsplat_strategy.DefaultStrategy(refine_start_iter=3, refine_every=2)
            runs[packed] = _gsplat_run(parser, base, self.STEPS, {"packed": packed}, packed=packed)
        for splats, optimizers, state, n0 in runs.values():
            event = self._check(splats, optimizers, state, n0)
            n = splats["means"].shape[0]
            assert n > n0 + event["added"], "the base grew after the event"  # ADC on the new rows too
            assert state["grad2d"].shape == (n,) and state["count"].shape == (n,)
        (a, _, sa, _), (b, _, sb, _) = runs[False], runs[True]
        assert a["means"].shape == b["means"].shape
        torch.testing.assert_close(a["means"], b["means"], rtol=0, atol=1e-6)
        torch.testing.assert_close(sa["grad2d"], sb["grad2d"])

    def test_default_base_in_a_gsplat_loop(self, parser):
        """The class docstring's use: the default base (vadgs's ``DefaultStrategy``) called as
        gsplat's ``simple_trainer`` calls a strategy, ``step_post_backward(..., packed=...)`` (was:
        ``TypeError: unexpected keyword argument 'packed'``). Packed or not, the same decisions."""
        runs = {}
        for packed in (False, True):
            base = DefaultStrategy(DefaultStrategyConfig(refine_start_iter=3, refine_every=2))
            runs[packed] = _gsplat_run(parser, base, self.STEPS, {"packed": packed}, packed=packed)
        for splats, optimizers, state, n0 in runs.values():
            event = self._check(splats, optimizers, state, n0)
            n = splats["means"].shape[0]
            assert n > n0 + event["added"], "the base grew after the event"
            assert state["grad2d"].shape == (n,) and state["count"].shape == (n,)
        (a, _, sa, _), (b, _, sb, _) = runs[False], runs[True]
        assert a["means"].shape == b["means"].shape
        torch.testing.assert_close(a["means"], b["means"], rtol=0, atol=1e-6)
        torch.testing.assert_close(sa["grad2d"], sb["grad2d"])
        torch.testing.assert_close(sa["count"], sb["count"])
        # the other keyword arguments of gsplat's loops (MCMC's lr=) are accepted and ignored
        _gsplat_run(parser, DefaultStrategy(), 1, {"lr": 1e-3})

    def test_default_base_packed_without_ids(self, parser):
        with pytest.raises(
            ValueError, match=r"info\['gaussian_ids'\]: expected the ids of .*packed=True, got None"
        ):
            _gsplat_run(parser, DefaultStrategy(), 1, {"packed": True})

    def test_mcmc_strategy(self, parser, monkeypatch):
        """gsplat's MCMCStrategy: ``initialize_state()`` without arguments, ``lr=`` passed on.

        Its noise injection runs through gsplat's own pure-torch reference of its one CUDA op
        (``quat_scale_to_covar_preci``); relocation (CUDA only) is kept after the run.
        """
        import gsplat.strategy.ops as gops
        from gsplat.cuda._torch_impl import _quat_scale_to_covar_preci

        monkeypatch.setattr(gops, "quat_scale_to_covar_preci", _quat_scale_to_covar_preci)
        base = gsplat_strategy.MCMCStrategy(refine_start_iter=10**6)
        with pytest.raises(TypeError, match="lr"):  # MCMC needs lr: only given through kwargs
            _gsplat_run(parser, copy.deepcopy(base), 1, {})
        splats, optimizers, state, n0 = _gsplat_run(parser, base, self.STEPS, {"lr": 1e-3})
        event = self._check(splats, optimizers, state, n0)
        assert splats["means"].shape[0] == n0 + event["added"]
        assert state["binoms"].shape == (51, 51)
