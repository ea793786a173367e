"""Type-checked construction of (nested, frozen) config dataclasses from plain dicts.

Configs come from JSON files (``--config``, checkpoints, batch arguments), so a wrong type must
fail at load time with the field's path, the expected and the actual type, not as an arithmetic
error deep inside training. :func:`config_from_dict` reads each field's annotation through
:func:`typing.get_type_hints` (the configs use ``from __future__ import annotations``, so
annotations are strings) and handles ``int``, ``float``, ``bool``, ``str``, ``X | None``,
``tuple[T, ...]``, ``tuple[A, B]``, ``list[T]``, ``dict[str, T]``, nested dataclasses and optional
nested dataclasses. ``int`` is accepted where ``float`` is expected; ``bool`` is not an ``int``.
A key that is not a field is an error naming the keys the dataclass has.

Example:
    >>> from vadgs.render import RasterConfig
    >>> config_from_dict(RasterConfig, {"near": 0.1, "tile_size": 16}).tile_size
    16
    >>> config_from_dict(RasterConfig, {"tile_size": "abc"})
    Traceback (most recent call last):
    ...
    ValueError: config.tile_size: expected int, got str 'abc'
"""

from __future__ import annotations

import dataclasses
import types
import typing
from typing import Any, TypeVar

__all__ = ["config_from_dict"]

T = TypeVar("T")


def _type_name(tp: Any) -> str:
    if tp is type(None):
        return "None"
    if isinstance(tp, type) and not typing.get_args(tp):
        return tp.__name__
    return str(tp).replace("typing.", "")


def _got(value: Any) -> str:
    text = repr(value)
    if len(text) > 60:
        text = text[:57] + "..."
    return f"{type(value).__name__} {text}"


def _convert(value: Any, tp: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None:
            if type(None) in args:
                return None
            raise ValueError(f"{where}: expected {_type_name(tp)}, got None")
        options = [a for a in args if a is not type(None)]
        errors = []
        for option in options:
            try:
                return _convert(value, option, where)
            except ValueError as e:
                errors.append(str(e))
        if len(options) == 1:
            raise ValueError(errors[0]) from None
        raise ValueError(f"{where}: expected {_type_name(tp)}, got {_got(value)}")
    if origin is typing.Literal:
        if value in args:
            return value
        raise ValueError(f"{where}: expected one of {list(args)}, got {_got(value)}")
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        if isinstance(value, tp):
            return value
        return config_from_dict(tp, value, where)
    if origin is tuple or origin is list:
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"{where}: expected {_type_name(tp)} (a list), got {_got(value)}")
        if origin is list or (len(args) == 2 and args[1] is Ellipsis):
            item = args[0] if args else Any
            out = [_convert(v, item, f"{where}[{i}]") for i, v in enumerate(value)]
        elif args:
            if len(value) != len(args):
                raise ValueError(f"{where}: expected {len(args)} items ({_type_name(tp)}), got {len(value)}")
            out = [_convert(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args))]
        else:
            out = list(value)
        return tuple(out) if origin is tuple else out
    if origin is dict:
        if not isinstance(value, dict):
            raise ValueError(f"{where}: expected {_type_name(tp)} (an object), got {_got(value)}")
        kt, vt = args if args else (Any, Any)
        return {_convert(k, kt, f"{where} key"): _convert(v, vt, f"{where}[{k!r}]") for k, v in value.items()}
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ValueError(f"{where}: expected bool, got {_got(value)}")
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise ValueError(f"{where}: expected int, got {_got(value)}")
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        raise ValueError(f"{where}: expected float, got {_got(value)}")
    if tp is str:
        if isinstance(value, str):
            return value
        raise ValueError(f"{where}: expected str, got {_got(value)}")
    if isinstance(tp, type):
        if isinstance(value, tp):
            return value
        raise ValueError(f"{where}: expected {_type_name(tp)}, got {_got(value)}")
    return value  # an annotation this helper does not know: passed through unchecked


def config_from_dict(cls: type[T], data: Any, where: str = "config") -> T:
    """Build the (frozen) dataclass ``cls`` from a dict, checking every field's type.

    Args:
        cls: a dataclass type, possibly with nested dataclass fields.
        data: a dict of field values (nested dicts for nested dataclasses), e.g. the output of
            :func:`dataclasses.asdict`; missing fields take their defaults.
        where: the name of ``data`` in error messages (field paths are appended to it).

    Returns:
        The instance of ``cls``.

    Raises:
        ValueError: on a key that is not a field, or a value of the wrong type; the message names
            the field's path, the expected and the actual type (``config.lr.means: expected
            float, got str 'x'``). Errors raised by the dataclass's own ``__post_init__``
            (range checks) are re-raised prefixed with ``where``.
    """
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected an object of {cls.__name__} fields, got {_got(data)}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; {cls.__name__} has {sorted(fields)}")
    hints = typing.get_type_hints(cls)
    kwargs = {k: _convert(v, hints.get(k, Any), f"{where}.{k}") for k, v in data.items()}
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{where}: {e}") from None
