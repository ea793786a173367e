"""Wrong values for the fields of the configs of :mod:`vadgs.train.vad`, by their annotation: the
cases of each config's ``test_bad_value_at_construction`` (issue 39, item 5: the Python API validates
like the CLI)."""

from __future__ import annotations

import dataclasses
import typing

import pytest
import torch

__all__ = ["INF", "NAN", "bad_values", "check_bad_value", "field_cases"]

NAN, INF = float("nan"), float("inf")


def bad_values(tp: typing.Any) -> list[typing.Any]:
    """Values wrong for a field annotated ``tp`` whatever its range (every range here is >= 0)."""
    args = [a for a in typing.get_args(tp) if a is not type(None)]
    optional = type(None) in typing.get_args(tp)
    if optional and len(args) == 1:
        tp = args[0]
    origin, inner = typing.get_origin(tp), typing.get_args(tp)
    none = [] if optional else [None]
    if tp is bool:
        return [1, "yes", None]
    if tp is int:
        return [2.5, 3.0, True, "3", -1, NAN, *none]
    if tp is float:
        return [NAN, INF, -INF, -1.0, "0.5", True, torch.tensor(0.5), *none]
    if tp is str:
        return ["bogus", 3, None]
    if origin is tuple and inner == (str, ...):
        return ["road", ("road", 3), 5, None]
    if origin is tuple and inner == (int, ...):
        return ["0", (0, 2.5), (True,), None]
    if origin is tuple and inner == (float, float):
        return [(0.5,), (0.5, 2.0, 3.0), "ab", (NAN, 2.0), (-1.0, 2.0), *none]
    if dataclasses.is_dataclass(tp):
        return [{}, "default", *none]
    raise AssertionError(f"no bad values for {tp}")


def field_cases(cls: type) -> list:
    """``pytest.param(name, bad)`` for every field of the dataclass ``cls`` and every bad value of it."""
    hints = typing.get_type_hints(cls)
    return [
        pytest.param(f.name, bad, id=f"{cls.__name__}.{f.name}={bad!r}")
        for f in dataclasses.fields(cls)
        for bad in bad_values(hints[f.name])
    ]


def check_bad_value(cls: type, name: str, bad: typing.Any) -> None:
    """``cls(name=bad)`` raises a :class:`ValueError` naming the field, the expected and the actual."""
    with pytest.raises(ValueError) as e:
        cls(**{name: bad})
    msg = str(e.value)
    assert msg.startswith(name) and "expected" in msg and "got" in msg, msg
