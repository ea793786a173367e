"""Tests of vadgs.config.config_from_dict on the real (nested) config classes."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from typing import ClassVar

import pytest

from vadgs.config import RemovedField, config_from_dict
from vadgs.mvs import PatchMatchConfig
from vadgs.train.config import TrainConfig
from vadgs.train.vad import ReconstructConfig, VisibilityDensifyConfig


@dataclass(frozen=True)
class _Inner:
    a: int = 1
    b: float | None = None


@dataclass(frozen=True)
class _Outer:
    names: tuple[str, ...] = ("x",)
    size: tuple[int, int] = (2, 3)
    inner: _Inner = field(default_factory=_Inner)
    maybe: _Inner | None = None
    flag: bool = False


class TestConfigFromDict:
    @pytest.mark.parametrize(
        "cls", [TrainConfig, VisibilityDensifyConfig, ReconstructConfig, PatchMatchConfig]
    )
    def test_round_trip_through_json(self, cls):
        c = cls()
        assert config_from_dict(cls, json.loads(json.dumps(dataclasses.asdict(c)))) == c

    def test_optional_nested_and_tuples(self):
        c = config_from_dict(_Outer, {"names": ["a", "b"], "size": [4, 5], "maybe": {"a": 2, "b": 1}})
        assert c.names == ("a", "b") and c.size == (4, 5) and c.maybe == _Inner(2, 1.0)
        assert config_from_dict(_Outer, {"maybe": None}).maybe is None
        assert config_from_dict(_Outer, {}) == _Outer()

    def test_reconstruct_optional_planar(self):
        d = dataclasses.asdict(ReconstructConfig())
        d["planar"] = None
        assert config_from_dict(ReconstructConfig, d).planar is None

    def test_int_is_a_float_bool_is_not_an_int(self):
        assert config_from_dict(TrainConfig, {"ssim_weight": 1}).ssim_weight == 1.0
        with pytest.raises(ValueError, match=r"config\.iterations: expected int, got bool True"):
            config_from_dict(TrainConfig, {"iterations": True})
        with pytest.raises(ValueError, match=r"config\.iterations: expected int, got float 2\.5"):
            config_from_dict(TrainConfig, {"iterations": 2.5})

    @pytest.mark.parametrize(
        ("data", "match"),
        [
            (
                {"strategy": {"refine_every": "abc"}},
                r"config.strategy.refine_every: expected int, got str 'abc'",
            ),
            ({"lr": {"means": "x"}}, r"config.lr.means: expected float, got str 'x'"),
            (
                {"strategy": 3},
                r"config.strategy: expected an object of DefaultStrategyConfig fields, got int 3",
            ),
            ({"bogus": 1}, r"config: unknown key\(s\) \['bogus'\]"),
            ({"raster": {"bogus": 1}}, r"config.raster: unknown key\(s\) \['bogus'\]"),
            ({"raster": {"near": -1.0}}, r"config.raster: near, far: expected 0 < near < far"),
        ],
    )
    def test_train_config_errors(self, data, match):
        with pytest.raises(ValueError, match=match):
            TrainConfig.from_dict(data)

    def test_nested_vad_errors(self):
        with pytest.raises(
            ValueError, match=r"vad.reconstruct.patchmatch.window_radius: expected int, got str"
        ):
            config_from_dict(
                VisibilityDensifyConfig, {"reconstruct": {"patchmatch": {"window_radius": "5"}}}, "vad"
            )
        with pytest.raises(ValueError, match=r"vad.incomplete.ignore_ids\[1\]: expected int, got str 'a'"):
            config_from_dict(VisibilityDensifyConfig, {"incomplete": {"ignore_ids": [0, "a"]}}, "vad")
        with pytest.raises(ValueError, match=r"c.size: expected 2 items"):
            config_from_dict(_Outer, {"size": [1, 2, 3]}, "c")
        with pytest.raises(ValueError, match=r"c.names\[0\]: expected str, got int 1"):
            config_from_dict(_Outer, {"names": [1]}, "c")
        with pytest.raises(ValueError, match=r"c.maybe.b: expected float, got str 'x'"):
            config_from_dict(_Outer, {"maybe": {"b": "x"}}, "c")


class TestRemovedSettings:
    """Settings removed from the configs (issue 41) are still in older runs' files (checkpoints,
    ``config.json``, ``--config`` files): ignored with a one-line warning naming them, or, where the
    run cannot do without them, an error naming the setting and what to do."""

    def test_dead_settings_ignored_with_a_warning(self):
        base = TrainConfig(vad=VisibilityDensifyConfig()).to_dict()
        old = json.loads(json.dumps(base))
        old["vad"]["explained_tolerance"] = 0.2  # never had an effect (reconstruct's is the live one)
        old["vad"]["incomplete"]["foreign_fraction"] = 0.5  # never wired into the strategy
        with pytest.warns(UserWarning) as caught:
            config = TrainConfig.from_dict(old)
        assert config == TrainConfig.from_dict(base)
        lines = sorted(str(w.message) for w in caught)
        assert lines == [
            "config.vad.explained_tolerance: a removed setting, ignored: it never had an effect; the "
            "tolerance in use is reconstruct.explained_tolerance",
            "config.vad.incomplete.foreign_fraction: a removed setting, ignored: it was never used by "
            "the strategy (find_incomplete still reports the share, as 'foreign')",
        ]
        assert all("\n" not in line for line in lines)
        assert "explained_tolerance" not in config.to_dict()["vad"]
        with pytest.raises(TypeError, match="explained_tolerance"):
            VisibilityDensifyConfig(explained_tolerance=0.1)

    def test_visibility_switch(self):
        """One way to train without VAD-GS: ``vad=None``. An older run's ``visibility: true`` (the
        only behaviour left) is ignored; ``false`` is refused, saying what to do instead."""
        with pytest.warns(UserWarning, match=r"^config\.vad\.visibility: a removed setting, ignored"):
            assert TrainConfig.from_dict({"vad": {"visibility": True}}).vad == VisibilityDensifyConfig()
        with pytest.raises(
            ValueError,
            match=r"^config\.vad\.visibility: a removed setting, False no longer possible: .*'w/o voxel "
            r"visibility reasoning' ablation \(visibility False\) is TrainConfig\.vad = None: vadgs "
            r"train without --vad$",
        ):
            TrainConfig.from_dict({"vad": {"visibility": False, "explained_tolerance": 0.1}})
        assert "visibility" not in {f.name for f in dataclasses.fields(VisibilityDensifyConfig)}

    def test_other_unknown_keys_still_refused(self):
        with pytest.raises(ValueError, match=r"config.vad: unknown key\(s\) \['explained_tolerence'\]"):
            TrainConfig.from_dict({"vad": {"explained_tolerence": 0.1}})

    def test_removed_field_of_a_dataclass(self):
        @dataclass(frozen=True)
        class _Cfg:
            a: int = 1
            REMOVED_FIELDS: ClassVar[dict] = {
                "b": RemovedField("use a", same=(True,)),
                "c": RemovedField("gone"),
            }

        with pytest.warns(UserWarning, match=r"^x\.b: a removed setting, ignored: use a$"):
            assert config_from_dict(_Cfg, {"a": 2, "b": True}, "x") == _Cfg(2)
        with pytest.warns(UserWarning, match=r"^x\.c: a removed setting, ignored: gone$"):
            assert config_from_dict(_Cfg, {"c": [1, 2]}, "x") == _Cfg()
        for value in (False, 1, None):
            with pytest.raises(
                ValueError, match=rf"^x\.b: a removed setting, {value!r} no longer possible: use a$"
            ):
                config_from_dict(_Cfg, {"b": value}, "x")


@dataclass(frozen=True)
class _Moved:
    """A config whose ``a`` and ``c`` moved into ``inner`` (``inner.a``, ``inner.b``)."""

    inner: _Inner = field(default_factory=_Inner)
    flag: bool = False
    MOVED_FIELDS: ClassVar[dict[str, str]] = {"a": "inner.a", "c": "inner.b"}


class TestMovedSettings:
    """Settings moved into a nested config (``MOVED_FIELDS``): older files (checkpoints,
    ``config.json``, ``--config`` files) give them flat; they load into the new place."""

    OLD: ClassVar[
        dict
    ] = {  # the geometric loss as TrainConfig held it before issue 41, item 3: flat, non-default
        "lambda_normal": 0.05,
        "lambda_hard": 0.3,
        "lambda_soft": 0.2,
        "hard_until": 0.5,
        "hard_every": 2,
        "hard_stride": 1,
        "hard_fused": True,
    }

    def test_flat_geometric_settings_load_into_geometry(self):
        from vadgs.train.losses import GeometricLossConfig

        assert set(TrainConfig.MOVED_FIELDS) == set(self.OLD)
        old = {**TrainConfig(iterations=7).to_dict(), **self.OLD}
        del old["geometry"]  # an older file has no section
        data = json.loads(json.dumps(old))
        config = TrainConfig.from_dict(data)
        assert data == old  # the caller's dict is not changed
        assert config.geometry == GeometricLossConfig(**self.OLD) and config.iterations == 7
        assert config == TrainConfig(iterations=7, geometry=GeometricLossConfig(**self.OLD))
        new = config.to_dict()
        assert new["geometry"] == self.OLD and not set(self.OLD) & set(new)  # written in the new layout
        assert TrainConfig.from_dict(json.loads(json.dumps(new))) == config

    def test_one_flat_setting_keeps_the_other_defaults(self):
        config = TrainConfig.from_dict({"lambda_hard": 0.3})
        assert config.geometry.lambda_hard == 0.3
        assert dataclasses.replace(config.geometry, lambda_hard=0.1) == TrainConfig().geometry
        config = TrainConfig.from_dict({"lambda_hard": 0.3, "geometry": {"hard_every": 2}})
        assert (config.geometry.lambda_hard, config.geometry.hard_every) == (0.3, 2)

    def test_old_and_new_key(self):
        same = TrainConfig.from_dict({"lambda_hard": 0.3, "geometry": {"lambda_hard": 0.3}})
        assert same.geometry.lambda_hard == 0.3
        with pytest.raises(
            ValueError,
            match=r"^config\.lambda_hard and config\.geometry\.lambda_hard: two values of one setting "
            r"\(lambda_hard moved to geometry\.lambda_hard\), 0\.3 and 0\.5; give one, as "
            r"config\.geometry\.lambda_hard$",
        ):
            TrainConfig.from_dict({"lambda_hard": 0.3, "geometry": {"lambda_hard": 0.5}})
        with pytest.raises(ValueError, match=r"config\.hard_fused and config\.geometry\.hard_fused"):
            TrainConfig.from_dict({"hard_fused": True, "geometry": {"hard_fused": 1}})

    def test_old_values_are_checked_at_their_new_path(self):
        with pytest.raises(ValueError, match=r"^config\.geometry\.hard_every: expected int, got str 'x'$"):
            TrainConfig.from_dict({"hard_every": "x"})
        with pytest.raises(
            ValueError, match=r"^config\.geometry: hard_every: expected an integer >= 1, got 0$"
        ):
            TrainConfig.from_dict({"hard_every": 0})
        with pytest.raises(
            ValueError, match=r"^config: geometry\.hard_fused: expected geometry\.hard_stride 1"
        ):
            TrainConfig.from_dict({"hard_fused": True})  # hard_stride 2 by default

    def test_replace_names_the_new_field(self):
        with pytest.raises(ValueError, match=r"^config: 'lambda_hard' is now 'geometry\.lambda_hard'$"):
            TrainConfig().replace(lambda_hard=0.3)
        assert TrainConfig().replace(**{"geometry.lambda_hard": 0.3}).geometry.lambda_hard == 0.3

    def test_mechanism(self):
        """Generic: any dataclass's ``MOVED_FIELDS``, nested sections copied, errors at ``where``."""
        data = {"a": 2, "c": 0.5, "flag": True}
        assert config_from_dict(_Moved, data, "x") == _Moved(_Inner(2, 0.5), True)
        assert data == {"a": 2, "c": 0.5, "flag": True}
        inner = {"a": 2}
        assert config_from_dict(_Moved, {"c": 1, "inner": inner}, "x") == _Moved(_Inner(2, 1.0))
        assert inner == {"a": 2}
        assert config_from_dict(_Moved, {"a": 3, "inner": _Inner(3, 2.0)}, "x") == _Moved(_Inner(3, 2.0))
        with pytest.raises(ValueError, match=r"^x\.a and x\.inner\.a: two values of one setting .* 3 and 1;"):
            config_from_dict(_Moved, {"a": 3, "inner": _Inner()}, "x")  # an instance gives every field
        with pytest.raises(ValueError, match=r"^x\.a and x\.inner\.a: two values of one setting"):
            config_from_dict(_Moved, {"a": 3, "inner": {"a": 4}}, "x")
        with pytest.raises(
            ValueError, match=r"^x\.inner: expected an object \(it holds x\.inner\.a, given as x\.a\)"
        ):
            config_from_dict(_Moved, {"a": 3, "inner": 5}, "x")
        with pytest.raises(ValueError, match=r"^x: unknown key\(s\) \['d'\]"):
            config_from_dict(_Moved, {"d": 1}, "x")


class TestDeviceBackend:
    """``vadgs train --device cuda`` renders with gsplat unless the backend is set explicitly."""

    @staticmethod
    def _config(argv):
        from vadgs.cli.train import parse_train

        return parse_train(["scene", "--out", "run", *argv]).train

    def test_cuda_picks_gsplat(self):
        assert self._config([]).raster.backend == "torch"
        assert self._config(["--device", "cpu"]).raster.backend == "torch"
        assert self._config(["--device", "cuda"]).raster.backend == "gsplat"
        assert self._config(["--device", "cuda:1"]).raster.backend == "gsplat"

    def test_explicit_backend_wins(self, tmp_path):
        cfg = self._config(["--device", "cuda", "--raster.backend", "torch"])
        assert cfg.raster.backend == "torch"
        config = tmp_path / "c.json"
        config.write_text('{"raster": {"backend": "torch"}}')
        assert self._config(["--device", "cuda", "--config", str(config)]).raster.backend == "torch"


class TestThreads:
    """``--threads`` holds for the command only; without it torch's count is left alone."""

    def test_threads_apply_during_the_command_and_are_restored(self, monkeypatch):
        import torch

        from vadgs import cli
        from vadgs.data import sample_scene_path

        seen = []

        @dataclasses.dataclass(frozen=True)
        class Spy(cli.CheckCommand):
            """Validate a scene (counting threads)."""

            def main(self) -> int:
                seen.append(torch.get_num_threads())
                return super().main()

        monkeypatch.setitem(cli.COMMANDS, "check", Spy)
        before = torch.get_num_threads()
        other = 1 if before != 1 else 2
        assert cli.main(["--threads", str(other), "check", str(sample_scene_path())]) == 0
        assert cli.main(["check", str(sample_scene_path())]) == 0
        assert cli.main(["check", str(sample_scene_path()), "--threads", str(other)]) == 0
        assert seen == [other, before, other]
        assert torch.get_num_threads() == before

    def test_trainer_restores_the_callers_count(self, tmp_path):
        import torch

        from vadgs.data import load_scene, sample_scene_path
        from vadgs.train.init import InitConfig
        from vadgs.train.trainer import Trainer

        before = torch.get_num_threads()
        other = 1 if before != 1 else 2
        seen = []
        config = TrainConfig(
            iterations=2, threads=other, init=InitConfig(voxel_size=1.0, max_points=300, sh_degree=0)
        )
        scene = load_scene(sample_scene_path(), scale=0.25)
        Trainer(
            scene, config, progress=False, callback=lambda t, s: seen.append(torch.get_num_threads())
        ).train()
        assert seen == [other, other]
        assert torch.get_num_threads() == before
