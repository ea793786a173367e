"""The VAD-GS strategy as a whole (:class:`VisibilityAwareDensification`).

As gsplat strategies are: a dataclass holding its settings (checked when set, at construction and
later), fed by :class:`VisibilityInputs` (a vadgs scene or gsplat's ``Parser``), with
``check_sanity``, an explicit ``prepare``, and gsplat's ``DefaultStrategy`` (packed or not) and
``MCMCStrategy`` as its base. The priors :meth:`VisibilityAwareDensification.geometry_targets` gives
a view, against a naive pixel-by-pixel reference: the MVS depth of the events where it exists, else
the voxel depth only where the voxel belongs to the pixel's own instance (elsewhere the z-buffer sees
through missing geometry, e.g. to the facade behind a sign), cut to the view's own size; and its
errors before ``prepare`` or on a state it did not make."""

from __future__ import annotations

import copy
import dataclasses
import inspect
import itertools
import math
import typing
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from tests.train.vad.config_cases import INF, NAN, bad_values
from vadgs.train.strategy import ConfiguredStrategy, DefaultStrategy, DefaultStrategyConfig, ops
from vadgs.train.vad import (
    ReconstructConfig,
    StrategyContext,
    ViewRender,
    VisibilityAwareDensification,
    VisibilityDensifyConfig,
    VisibilityInputs,
)
from vadgs.train.vad.visibility import own_instance_depth

from ..gsplat_parser import facade_splats

try:
    import gsplat.strategy as gsplat_strategy
except ImportError:  # the tests with gsplat's strategies as the base skip
    gsplat_strategy = None
needs_gsplat = pytest.mark.skipif(gsplat_strategy is None, reason="needs gsplat")


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
        own_voxel_depth=lambda view, tracks=True: own_instance_depth(  # the index's, uncached
            vd, vlabel if tracks else vlabel.masked_fill(vlabel == TRACK, -1), ins
        ),
        size=lambda view: (H, W),
    )
    return s, s.initialize_state()


TRACK = 2  # the stand-in index's moving object


def _naive(vd, vlabel, ins, mvs=None, voxel_prior=True, tracks=False):
    out = torch.zeros(1, 1, H, W)
    for y, x in itertools.product(range(H), range(W)):
        if mvs is not None and mvs[0, y, x] > 0:
            out[0, 0, y, x] = mvs[0, y, x]
        elif voxel_prior and vlabel[y, x] == ins[y, x] and (tracks or vlabel[y, x] != TRACK):
            # the pixel's own instance's voxel only; a moving object's with voxel_prior_tracks
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
        own = (vlabel == ins)[:H, :W] & (vd[0, :H, :W] > 0) & (vlabel[:H, :W] != TRACK)
        assert 0 < int(own.sum()) < H * W and bool((t.depth[0, 0][~own] == 0).all())

    def test_voxel_prior_tracks(self):
        vd, vlabel, ins, _, _ = _maps(1)
        s, state = _strategy(vd, vlabel, ins, voxel_prior_tracks=True)
        expect = _naive(vd, vlabel, ins, tracks=True)
        assert torch.equal(s.geometry_targets(state, 1).depth, expect)
        assert not torch.equal(expect, _naive(vd, vlabel, ins))  # the moving object's pixels added

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


class TestGeometryTargetsErrors:
    def test_before_prepare(self):
        s = VisibilityAwareDensification()
        with pytest.raises(ValueError, match=r"^geometry_targets: .* call prepare\(inputs, context\)"):
            s.geometry_targets({}, 0)

    def test_state_not_from_initialize_state_and_view_out_of_range(self, tiny_inputs, tiny_index):
        s = VisibilityAwareDensification(voxel_size=1.0, cell_size=20.0)
        s.prepare(tiny_inputs, index=tiny_index)
        with pytest.raises(
            ValueError, match=r"^state: expected the strategy's state .*'vad_priors'.*, got keys \[\]"
        ):
            s.geometry_targets({}, 0)
        state = s.initialize_state(1.0)
        n = tiny_inputs.num_views
        with pytest.raises(
            ValueError,
            match=rf"^view: expected an integer in \[0, {n - 1}\] \(a view of the inputs' {n}\), got {n}$",
        ):
            s.geometry_targets(state, n)
        v = tiny_inputs.train_views[0]
        targets = s.geometry_targets(state, v)
        assert targets is None or not math.isnan(float(targets.depth.sum()))


# -- its settings -----------------------------------------------------------------------------------


def _strategy_cases():
    hints = typing.get_type_hints(VisibilityDensifyConfig)
    for f in dataclasses.fields(VisibilityDensifyConfig):
        for bad in bad_values(hints[f.name]):
            yield pytest.param(f.name, bad, id=f"{f.name}={bad!r}")


class TestEverySetting:
    @pytest.mark.parametrize(("name", "bad"), list(_strategy_cases()))
    def test_bad_value_set_on_the_strategy_after_construction(self, name, bad):
        s = VisibilityAwareDensification()
        before = getattr(s, name)
        with pytest.raises(ValueError) as e:
            setattr(s, name, bad)
        assert str(e.value).startswith(name), str(e.value)
        assert getattr(s, name) == before and s.config == VisibilityDensifyConfig()  # unchanged

    @pytest.mark.parametrize(("name", "bad"), list(_strategy_cases()))
    def test_bad_value_given_to_the_strategy(self, name, bad):
        with pytest.raises(ValueError, match=f"^{name}"):
            VisibilityAwareDensification(**{name: bad})

    def test_strategy_field_set_later_no_zero_division(self):
        s = VisibilityAwareDensification()
        with pytest.raises(ValueError, match=r"^every_cycles: expected an integer >= 1, got 0$"):
            s.every_cycles = 0
        with pytest.raises(ValueError, match=r"^log_size: expected an integer >= 1, got 0$"):
            s.log_size = 0
        assert s.every_cycles == 5 and s.log_size >= 1

    def test_strategy_setting_set_later_is_in_its_config(self):
        s = VisibilityAwareDensification()
        s.every_cycles = np.int64(2)
        s.skip_classes = ["road", "car"]
        assert s.every_cycles == 2 and s.skip_classes == ("road", "car")
        assert s.config == VisibilityDensifyConfig(every_cycles=2, skip_classes=("road", "car"))
        s.config = VisibilityDensifyConfig(references=1)
        assert s.every_cycles == 5 and s.config.references == 1


class TestInitializeState:
    @pytest.mark.parametrize("scale", [NAN, -1.0, 0.0, INF, "1", None])
    def test_initialize_state_scene_scale(self, scale):
        with pytest.raises(ValueError, match=r"^scene_scale: expected a finite number > 0, got"):
            VisibilityAwareDensification().initialize_state(scene_scale=scale)
        with pytest.raises(ValueError, match=r"^scene_scale: expected a finite number > 0, got"):
            DefaultStrategy().initialize_state(scale)

    def test_initialize_state_valid(self):
        state = VisibilityAwareDensification().initialize_state(np.float64(2.5))
        assert state["scene_scale"] == 2.5 and state["vad_priors"] == {}


# -- as gsplat's strategies are ---------------------------------------------------------------------


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


if gsplat_strategy is not None:

    class _RecordingGsplat(gsplat_strategy.DefaultStrategy):
        """gsplat's DefaultStrategy, its ``check_sanity`` recorded (and run)."""

        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            self.calls = []

        def check_sanity(self, *args, **kwargs) -> None:
            self.calls.append(("check_sanity", args, kwargs))
            super().check_sanity(*args, **kwargs)


@needs_gsplat
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


@needs_gsplat
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
