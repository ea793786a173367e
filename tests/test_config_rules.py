"""One validation mechanism for every settings dataclass of vadgs (issue 50, item 3).

Each field's rule stands next to it (:func:`vadgs.checks.checked`); :class:`vadgs.checks.Checked`'s
``__post_init__`` runs them, so a bad value fails at construction and through
:func:`dataclasses.replace` alike, naming the field. The classes are found by walking the package
(no list to keep up to date): every ``*Config``, ``*Ref`` and ``*Command`` dataclass is checked,
every field of a checked class but the CLI's commands has a rule, and each rule refuses a value that is wrong
whatever its range. The CLI reports the same messages, its flag in place of the field.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
import inspect
import pkgutil
import re
import textwrap
import typing

import pytest

import vadgs
from vadgs.checks import RULE, Checked
from vadgs.cli import main
from vadgs.train.config import TrainConfig

NAN = float("nan")


class _Opaque:
    """A value no rule accepts: not a number, a string, a sequence, a callable or a settings class."""

    def __repr__(self) -> str:
        return "<opaque>"


def _dataclasses() -> list[type]:
    found = {}
    for info in pkgutil.walk_packages(vadgs.__path__, prefix="vadgs."):
        if info.name.endswith("__main__"):  # runs the CLI
            continue
        try:
            module = importlib.import_module(info.name)
        except ImportError:  # an optional dependency missing (tests/test_imports.py checks the rest)
            continue
        for obj in vars(module).values():
            if isinstance(obj, type) and obj.__module__ == info.name and dataclasses.is_dataclass(obj):
                found[f"{obj.__module__}.{obj.__qualname__}"] = obj
    return [found[k] for k in sorted(found)]


CLASSES = _dataclasses()
CHECKED = [c for c in CLASSES if issubclass(c, Checked)]
SETTINGS = [c for c in CHECKED if not c.__name__.endswith("Command")]  # the CLI's flags aside


def _rules(cls: type) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(cls) if RULE in f.metadata]


def _valid(hint: typing.Any) -> typing.Any:
    """A value for a required field (no default) of type ``hint``."""
    if typing.get_origin(hint) is tuple:
        return ("a",)
    if hint is int:
        return 1
    if hint is str:
        return "a"
    return lambda *a: None  # a callable (StrategyContext.render)


def _instance(cls: type) -> typing.Any:
    hints = typing.get_type_hints(cls)
    required = {
        f.name: _valid(hints[f.name])
        for f in dataclasses.fields(cls)
        if f.init and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
    }
    return cls(**required)


def _bad_values(hint: typing.Any) -> list[typing.Any]:
    """Values wrong for a field of type ``hint`` whatever its range, and one wrong for any field."""
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    if type(None) in typing.get_args(hint) and len(args) == 1:
        hint = args[0]
    extra = {float: [NAN, "0.5"], int: [2.5, True, "3"], bool: [1, "yes"], str: [3]}.get(hint, [])
    return [_Opaque(), *extra]


def _cases():
    for cls in CHECKED:
        hints = typing.get_type_hints(cls)
        for f in _rules(cls):
            for bad in _bad_values(hints[f.name]):
                yield pytest.param(cls, f.name, bad, id=f"{cls.__qualname__}.{f.name}={bad!r}")


def _names_the_field(message: str, name: str) -> bool:
    return re.match(rf"{name}(\[\d\])?: expected .+, got ", message) is not None


class TestEveryConfig:
    def test_the_walk_finds_the_configs(self):
        names = {c.__name__ for c in SETTINGS}
        assert {"TrainConfig", "VisibilityDensifyConfig", "ZBufferConfig", "PlanarCompletionConfig"} <= names
        assert len(SETTINGS) >= 20, names

    def test_every_config_ref_and_command_is_checked(self):
        named = [c for c in CLASSES if c.__name__.endswith(("Config", "Ref", "Command"))]
        assert [c.__qualname__ for c in named if not issubclass(c, Checked)] == []

    def test_every_field_of_a_setting_has_a_rule(self):
        missing = [
            f"{cls.__qualname__}.{f.name}"
            for cls in SETTINGS
            for f in dataclasses.fields(cls)
            if RULE not in f.metadata
        ]
        assert missing == []

    def test_own_post_init_runs_the_rules_first(self):
        """A check relating several fields comes after ``super().__post_init__()`` (the fields' rules)."""
        for cls in CHECKED:
            if "__post_init__" not in vars(cls):
                continue
            tree = ast.parse(textwrap.dedent(inspect.getsource(vars(cls)["__post_init__"])))
            first = tree.body[0].body[0]  # type: ignore[attr-defined]
            assert ast.unparse(first) == "super().__post_init__()", cls.__qualname__

    def test_defaults_pass_their_rules(self):
        for cls in CHECKED:
            instance = _instance(cls)
            assert dataclasses.replace(instance) == instance, cls.__qualname__


@pytest.mark.parametrize(("cls", "name", "bad"), list(_cases()))
def test_bad_value_refused_at_construction_and_replace(cls, name, bad):
    base = _instance(cls)
    kwargs = {f.name: getattr(base, f.name) for f in dataclasses.fields(cls) if f.init}
    with pytest.raises(ValueError) as built:
        cls(**{**kwargs, name: bad})
    assert _names_the_field(str(built.value), name), str(built.value)
    with pytest.raises(ValueError) as replaced:
        dataclasses.replace(base, **{name: bad})
    assert str(replaced.value) == str(built.value)


def _train_flag_cases():
    hints = typing.get_type_hints(TrainConfig)
    for f in _rules(TrainConfig):
        if hints[f.name] in (int, float):
            yield pytest.param(f.name, "-1" if hints[f.name] is int else "nan", id=f.name)


@pytest.mark.parametrize(("name", "text"), list(_train_flag_cases()))
def test_cli_reports_the_same_message(name, text, tmp_path, capsys):
    """``vadgs train --FLAG bad`` fails with the config's own message, the flag for the field."""
    value = int(text) if text == "-1" else float(text)
    with pytest.raises(ValueError) as e:
        TrainConfig(**{name: value})
    flag = "--" + name.replace("_", "-")
    assert main(["train", "--sample", "--out", str(tmp_path / "x"), flag, text]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"vadgs train: error: {flag}{str(e.value)[len(name) :]}", err
