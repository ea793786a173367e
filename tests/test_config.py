"""Tests of vadgs.config.config_from_dict on the real (nested) config classes."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field

import pytest

from vadgs.config import config_from_dict
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
            ({"raster": {"near": -1.0}}, r"config.raster: near: expected a finite number > 0, got -1.0"),
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


class TestNoOldNames:
    """Nothing is kept for compatibility (issue 50): a setting that moved or went is an unknown key,
    refused in one line naming the keys the config has; old runs are refused by their checkpoint's
    format version (``tests/train/test_checkpoint_format.py``)."""

    def test_a_moved_setting_is_an_unknown_key(self):
        with pytest.raises(
            ValueError, match=r"^config: unknown key\(s\) \['lambda_hard'\]; TrainConfig has \[.*'geometry'"
        ):
            TrainConfig.from_dict({"lambda_hard": 0.3})
        with pytest.raises(ValueError, match=r"^config: unknown field 'lambda_hard'$"):
            TrainConfig().replace(lambda_hard=0.3)
        assert TrainConfig().replace(**{"geometry.lambda_hard": 0.3}).geometry.lambda_hard == 0.3

    def test_a_removed_setting_is_an_unknown_key(self):
        for section, key in (("vad", "visibility"), ("vad", "explained_tolerance")):
            with pytest.raises(ValueError, match=rf"^config\.{section}: unknown key\(s\) \['{key}'\]"):
                TrainConfig.from_dict({section: {key: True}})
        with pytest.raises(
            ValueError, match=r"^config\.vad\.incomplete: unknown key\(s\) \['foreign_fraction'\]"
        ):
            TrainConfig.from_dict({"vad": {"incomplete": {"foreign_fraction": 0.5}}})


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
