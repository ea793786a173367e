"""Input validation shared by every vadgs module.

Public functions validate their inputs at the boundary with these helpers, so that bad input
fails with a :class:`ValueError` that names the argument, the expected and the actual shape,
instead of a crash deep inside a kernel (kornia's ``KORNIA_CHECK_SHAPE`` in spirit).

Two kinds of check: *shape* checks (:func:`check_shape`, :func:`check_size`) read only
metadata and always run; *value* checks (:func:`check_finite` and the range checks of the
components, guarded by :func:`checks_enabled`) read tensor values, which on a GPU costs a host
synchronisation each. Value checks can be switched off for speed in a trusted training loop: set
the environment variable ``VADGS_CHECKS=0`` before importing vadgs, call
:func:`set_checks_enabled`, or use the :func:`checking` context manager (kornia's
``KORNIA_CHECKS`` in spirit).

The settings dataclasses (every ``*Config`` of the library, the scene references, the CLI's
commands) check their fields one way: each field's rule stands next to it (:func:`checked`,
:func:`nested`; the rules :func:`int_field`, :func:`float_field`, ...), and their base
:class:`Checked` runs the rules at construction, hence also in :func:`dataclasses.replace`.

Shape specs are sequences whose items are an ``int`` (that exact size), a ``str`` (a named
dimension: every use of the same name within one call must agree) or ``"*"`` (any number of
leading dimensions, only as the first item) or ``"_"`` (any size).

Example:
    >>> import torch
    >>> dims = check_shape(torch.zeros(2, 3, 3), "K", ("B", 3, 3))
    >>> dims["B"]
    2
    >>> check_shape(torch.zeros(2, 4), "K", ("B", 3, 3))
    Traceback (most recent call last):
    ...
    ValueError: K: expected shape (B, 3, 3), got (2, 4)
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import numbers
import operator
import os
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import torch

__all__ = [
    "MAX_THREADS",
    "RULE",
    "Checked",
    "FieldCheck",
    "bool_field",
    "check_fields",
    "check_finite",
    "check_intrinsics",
    "check_same_device",
    "check_shape",
    "check_size",
    "checked",
    "checking",
    "checks_enabled",
    "choice_field",
    "first_false",
    "float_field",
    "instance_field",
    "int_field",
    "ints_field",
    "names_field",
    "nested",
    "pair_field",
    "set_checks_enabled",
]

#: The most torch CPU threads a command or a training takes (``--threads``): ``torch.set_num_threads``
#: of 100 000 000 crashes the process (a segmentation fault) at the first parallel operation.
MAX_THREADS = 1024

_OFF = {"0", "false", "off", "no"}
_enabled: bool = os.environ.get("VADGS_CHECKS", "1").strip().lower() not in _OFF
_local = threading.local()  # checking()'s override, per thread (None: the process's setting)


def checks_enabled() -> bool:
    """Whether value checks run (``VADGS_CHECKS``, :func:`set_checks_enabled`, :func:`checking`)."""
    override = getattr(_local, "override", None)
    return _enabled if override is None else override


def set_checks_enabled(enabled: bool) -> bool:
    """Switch value checks on or off for the whole process; returns the previous setting."""
    global _enabled
    previous, _enabled = _enabled, bool(enabled)
    return previous


@contextlib.contextmanager
def checking(enabled: bool) -> Iterator[None]:
    """Run a block with value checks on or off in this thread, restoring its setting afterwards.

    The setting holds for the calling thread only (another thread, e.g. a viewer rendering
    beside a training, keeps its own), so blocks in several threads cannot leave each other's
    setting behind.

    Example:
        >>> with checking(False):
        ...     check_finite(torch.tensor([float("nan")]), "x")  # not checked: no error
        >>> checks_enabled()
        True
    """
    previous = getattr(_local, "override", None)
    _local.override = bool(enabled)
    try:
        yield
    finally:
        _local.override = previous


def _fmt(spec: Sequence[int | str]) -> str:
    return "(" + ", ".join(str(s) for s in spec) + ")"


def check_shape(
    x: torch.Tensor,
    name: str,
    spec: Sequence[int | str],
    dims: dict[str, int] | None = None,
) -> dict[str, int]:
    """Check that ``x`` is a tensor of shape ``spec``.

    Args:
        x: the tensor to check.
        name: the argument's name, used in the error message.
        spec: the expected shape (see the module docstring).
        dims: sizes already bound to named dimensions (updated in place and returned), so that
            several arguments can be checked against each other.

    Returns:
        The mapping of named dimensions to sizes.

    Raises:
        ValueError: if ``x`` is not a tensor or its shape does not match.
    """
    dims = {} if dims is None else dims
    if not isinstance(x, torch.Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor of shape {_fmt(spec)}, got {type(x).__name__}")
    shape = tuple(x.shape)
    spec = list(spec)
    if spec and spec[0] == "*":
        tail = spec[1:]
        if len(shape) < len(tail):
            raise ValueError(f"{name}: expected shape {_fmt(spec)}, got {shape}")
        lead, shape_tail = shape[: len(shape) - len(tail)], shape[len(shape) - len(tail) :]
        if "*" in dims and tuple(dims["*"]) != lead:  # type: ignore[arg-type]
            raise ValueError(
                f"{name}: expected leading shape {tuple(dims['*'])}, got leading shape {lead}"  # type: ignore[arg-type]
            )
        spec_tail = tail
    else:
        shape_tail, spec_tail = shape, spec
    if len(shape_tail) != len(spec_tail):
        raise ValueError(f"{name}: expected shape {_fmt(spec)}, got {shape}")
    for size, want in zip(shape_tail, spec_tail):
        if isinstance(want, int):
            if size != want:
                raise ValueError(f"{name}: expected shape {_fmt(spec)}, got {shape}")
        elif want == "_":
            continue
        elif want in dims:
            if dims[want] != size:
                raise ValueError(f"{name}: expected shape {_fmt(spec)} with {want}={dims[want]}, got {shape}")
        else:
            dims[want] = size
    return dims


def check_finite(x: torch.Tensor, name: str) -> None:
    """Raise a :class:`ValueError` if ``x`` has a NaN or infinite entry (a value check).

    Example:
        >>> check_finite(torch.tensor([1.0, float("nan")]), "points")
        Traceback (most recent call last):
        ...
        ValueError: points: expected finite values, got 1 non-finite of 2
    """
    if checks_enabled() and x.is_floating_point():
        bad = ~torch.isfinite(x)
        if bool(bad.any()):
            raise ValueError(
                f"{name}: expected finite values, got {int(bad.sum())} non-finite of {x.numel()}"
            )


def first_false(flags: Sequence[torch.Tensor]) -> int | None:
    """The index of the first 0-d boolean tensor of ``flags`` that is False, or None if all hold.

    The flags are read back together, once (a host synchronisation on a GPU): value checks that
    would each read their own result cost one read, and the failing one is named only on a failure.

    Example:
        >>> x = torch.tensor([1.0, 2.0])
        >>> first_false([torch.isfinite(x).all(), (x > 1).all()]), first_false([(x > 0).all()])
        (1, None)
    """
    if not flags:
        return None
    ok = torch.stack([f.reshape(()).to(flags[0].device) for f in flags])
    if bool(ok.all()):
        return None
    return ok.tolist().index(False)


def check_intrinsics(K: torch.Tensor, name: str = "K", pinhole: bool = False) -> None:
    """Check ``(*, 3, 3)`` intrinsics: finite, positive focal lengths ``K[..., 0, 0]``, ``K[..., 1, 1]``.

    The shape is always checked; the values are a value check (:func:`checks_enabled`). With
    ``pinhole`` (a ``K`` read from a file or given by a user) also the form
    ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` (to 1e-9), and the values whatever
    :func:`checks_enabled` says: a file is refused at load, never trained on.

    Example:
        >>> check_intrinsics(torch.zeros(2, 3, 3))
        Traceback (most recent call last):
        ...
        ValueError: K: expected positive focal lengths K[..., 0, 0], K[..., 1, 1], got fx=0, fy=0 at (0,)
        >>> check_intrinsics(torch.eye(3) * 2, "raw_K", pinhole=True)
        Traceback (most recent call last):
        ...
        ValueError: raw_K: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got [[2.0, 0.0, 0.0], [...]]
    """
    check_shape(K, name, ("*", 3, 3))
    check_finite(K, name)
    if not pinhole and not checks_enabled():
        return
    K = K.detach()
    f = K[..., [0, 1], [0, 1]]
    bad = ~(f > 0).all(-1)
    if bool(bad.any()):
        at = tuple(int(i) for i in bad.nonzero()[0]) if bad.dim() else ()
        fx, fy = (float(v) for v in f[at])
        where = f" at {at}" if at else ""
        raise ValueError(
            f"{name}: expected positive focal lengths K[..., 0, 0], K[..., 1, 1], "
            f"got fx={fx:g}, fy={fy:g}{where}"
        )
    if pinhole:
        form = K.double()[..., [1, 2, 2, 2], [0, 0, 1, 2]] - K.new_tensor(
            [0.0, 0.0, 0.0, 1.0], dtype=torch.float64
        )
        bad = (form.abs() > 1e-9).any(-1)
        if bool(bad.any()):
            at = tuple(int(i) for i in bad.nonzero()[0]) if bad.dim() else ()
            where = f" at {at}" if at else ""
            raise ValueError(
                f"{name}: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K[at].tolist()}{where}"
            )


def check_size(size: Sequence[int], name: str = "image_size") -> tuple[int, int]:
    """Validate an image size ``(H, W)`` of positive ints and return it as a tuple.

    Example:
        >>> check_size((288, 480))
        (288, 480)
    """
    try:
        h, w = (int(s) for s in size)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected (H, W), got {size!r}") from None
    if h <= 0 or w <= 0:
        raise ValueError(f"{name}: expected positive (H, W), got {(h, w)}")
    return h, w


def check_same_device(*named: tuple[str, torch.Tensor]) -> None:
    """Raise a :class:`ValueError` if the named tensors live on different devices."""
    devices = {name: t.device for name, t in named if isinstance(t, torch.Tensor)}
    if len(set(devices.values())) > 1:
        raise ValueError(f"expected all tensors on one device, got {devices}")


# -- the settings dataclasses: each field's rule declared next to it -------------------------------

FieldCheck = Callable[[str, Any], Any]
"""A field's rule: ``rule(name, value)`` returns the value (normalised: a numpy int becomes an
``int``, a list a tuple) or raises :class:`ValueError` naming ``name``, the expected and the actual."""

RULE = "vadgs.rule"
"""The key of a field's rule in its :func:`dataclasses.field` metadata (set by :func:`checked`)."""


def checked(default: Any = dataclasses.MISSING, rule: FieldCheck | None = None, **field_kwargs: Any) -> Any:
    """A dataclass field whose rule (a :data:`FieldCheck` such as ``int_field(1)``) stands next to it.

    The rule runs in :class:`Checked`'s ``__post_init__``: at construction, hence also in
    :func:`dataclasses.replace` (which constructs). ``field_kwargs`` go to :func:`dataclasses.field`
    (``default_factory``, ``hash``, ...).

    Example:
        >>> @dataclasses.dataclass(frozen=True)
        ... class Every(Checked):
        ...     every: int = checked(5, int_field(1))
        >>> dataclasses.replace(Every(), every=0)
        Traceback (most recent call last):
        ...
        ValueError: every: expected an integer >= 1, got 0
    """
    if rule is None:
        raise ValueError("rule: expected a field check such as int_field(1), got None")
    return dataclasses.field(default=default, metadata={RULE: rule}, **field_kwargs)


def nested(cls: type, optional: bool = False) -> Any:
    """A field holding a nested settings dataclass ``cls``: by default ``cls()`` (None when ``optional``)."""
    if optional:
        return checked(None, instance_field(cls, optional=True))
    return checked(rule=instance_field(cls), default_factory=cls)


def check_fields(obj: Any) -> None:
    """Run the rule of each field of the dataclass ``obj`` (:func:`checked`), storing normalised values."""
    for f in dataclasses.fields(obj):
        rule = f.metadata.get(RULE)
        if rule is not None:
            value = getattr(obj, f.name)
            out = rule(f.name, value)
            if out is not value:
                object.__setattr__(obj, f.name, out)


class Checked:
    """Base of every settings dataclass of vadgs: its ``__post_init__`` runs each field's rule.

    The rules stand next to the fields (:func:`checked`, :func:`nested`); a rule relating several
    fields goes in the subclass's ``__post_init__``, after ``super().__post_init__()``.
    """

    def __post_init__(self) -> None:
        check_fields(self)


def _bounds(lo: float | None, hi: float | None, lo_open: bool, hi_open: bool) -> str:
    def num(x: float) -> str:  # an int in full (4000000, not 4e+06)
        return str(x) if isinstance(x, int) else f"{x:g}"

    if lo is not None and hi is not None:
        return f" in {'(' if lo_open else '['}{num(lo)}, {num(hi)}{')' if hi_open else ']'}"
    if lo is not None:
        return f" {'>' if lo_open else '>='} {num(lo)}"
    if hi is not None:
        return f" {'<' if hi_open else '<='} {num(hi)}"
    return ""


def _within(v: float, lo: float | None, hi: float | None, lo_open: bool, hi_open: bool) -> bool:
    if lo is not None and not (v > lo if lo_open else v >= lo):
        return False
    return hi is None or (v < hi if hi_open else v <= hi)


def int_field(
    lo: int | None = None, hi: int | None = None, optional: bool = False, note: str = ""
) -> FieldCheck:
    """An integer field (a numpy int passes; ``bool``, ``2.5`` and ``3.0`` do not) in ``[lo, hi]``.

    Example:
        >>> int_field(1)("every_cycles", 2.5)
        Traceback (most recent call last):
        ...
        ValueError: every_cycles: expected an integer >= 1, got 2.5
    """
    want = ("None or " if optional else "") + "an integer" + _bounds(lo, hi, False, False) + note

    def check(name: str, value: Any) -> Any:
        if value is None and optional:
            return None
        try:
            out = None if isinstance(value, bool) else operator.index(value)
        except TypeError:
            out = None
        if out is None or not _within(out, lo, hi, False, False):
            raise ValueError(f"{name}: expected {want}, got {value!r}")
        return out

    return check


def float_field(
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
    hi_open: bool = False,
    optional: bool = False,
    note: str = "",
    finite: bool = True,
) -> FieldCheck:
    """A finite real number (an ``int`` or numpy scalar passes, as a ``float``; not a ``bool``).

    ``lo`` / ``hi`` bound it (``lo_open`` / ``hi_open``: strictly); ``finite=False`` lets infinity
    pass (not NaN).

    Example:
        >>> float_field(0, 1, lo_open=True, hi_open=True)("new_opacity", float("nan"))
        Traceback (most recent call last):
        ...
        ValueError: new_opacity: expected a finite number in (0, 1), got nan
    """
    kind = "a finite number" if finite else "a number (inf allowed)"
    want = ("None or " if optional else "") + kind + _bounds(lo, hi, lo_open, hi_open) + note

    def check(name: str, value: Any) -> Any:
        if value is None and optional:
            return None
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise ValueError(f"{name}: expected {want}, got {type(value).__name__} {value!r}")
        out = float(value)
        if not (
            (math.isfinite(out) or not (finite or math.isnan(out))) and _within(out, lo, hi, lo_open, hi_open)
        ):
            raise ValueError(f"{name}: expected {want}, got {value!r}")
        return out

    return check


def bool_field() -> FieldCheck:
    """``True`` or ``False`` (a numpy bool passes; ``0`` / ``1`` / ``"yes"`` do not).

    Example:
        >>> bool_field()("visibility", "no")
        Traceback (most recent call last):
        ...
        ValueError: visibility: expected True or False, got 'no'
    """

    def check(name: str, value: Any) -> Any:
        if isinstance(value, bool):
            return value
        if type(value).__module__ == "numpy" and type(value).__name__ in ("bool", "bool_"):
            return bool(value)
        raise ValueError(f"{name}: expected True or False, got {value!r}")

    return check


def choice_field(choices: Sequence[Any]) -> FieldCheck:
    """One of ``choices``.

    Example:
        >>> choice_field(("a", "b"))("ranking", "c")
        Traceback (most recent call last):
        ...
        ValueError: ranking: expected one of ('a', 'b'), got 'c'
    """
    choices = tuple(choices)

    def check(name: str, value: Any) -> Any:
        if isinstance(value, bool) or value not in choices:
            raise ValueError(f"{name}: expected one of {choices}, got {value!r}")
        return value

    return check


def instance_field(cls: type, optional: bool = False) -> FieldCheck:
    """An instance of ``cls`` (a nested config dataclass), or None when ``optional``."""
    want = ("None or " if optional else "") + f"a {cls.__name__}"

    def check(name: str, value: Any) -> Any:
        if (value is None and optional) or isinstance(value, cls):
            return value
        raise ValueError(f"{name}: expected {want}, got {type(value).__name__} {value!r}")

    return check


def _sequence(name: str, value: Any, what: str, example: str) -> tuple:
    if isinstance(value, (str, bytes)):
        raise ValueError(
            f"{name}: expected a sequence of {what}, got the string {value!r} (write ({value!r},))"
        )
    if not isinstance(value, (Sequence, set, frozenset)) or isinstance(value, Mapping):
        raise ValueError(
            f"{name}: expected a sequence of {what} such as {example}, got {type(value).__name__} {value!r}"
        )
    return tuple(value)


def names_field(what: str = "names", optional: bool = False) -> FieldCheck:
    """A sequence of strings (returned as a tuple; None when ``optional``); a bare string is refused.

    Example:
        >>> names_field("class names")("skip_classes", "road")
        Traceback (most recent call last):
        ...
        ValueError: skip_classes: expected a sequence of class names, got the string 'road' (write ('road',))
    """

    def check(name: str, value: Any) -> Any:
        if value is None and optional:
            return None
        items = _sequence(name, value, what, "('road', 'sky')")
        bad = [v for v in items if not isinstance(v, str)]
        if bad:
            raise ValueError(f"{name}: expected a sequence of {what} (strings), got {bad[0]!r} in {value!r}")
        return items

    return check


def ints_field(what: str = "integers") -> FieldCheck:
    """A sequence of integers (returned as a tuple of ``int``).

    Example:
        >>> ints_field("instance ids")("ignore_ids", (0, 1.5))
        Traceback (most recent call last):
        ...
        ValueError: ignore_ids: expected a sequence of instance ids (integers), got 1.5 in (0, 1.5)
    """
    item = int_field()

    def check(name: str, value: Any) -> Any:
        items = _sequence(name, value, what, "(0, 1)")
        out = []
        for v in items:
            try:
                out.append(item(name, v))
            except ValueError:
                raise ValueError(
                    f"{name}: expected a sequence of {what} (integers), got {v!r} in {value!r}"
                ) from None
        return tuple(out)

    return check


def pair_field(
    item: FieldCheck,
    optional: bool = False,
    rule: Callable[[float, float], bool] | None = None,
    note: str = "",
) -> FieldCheck:
    """A pair ``(a, b)`` whose items pass ``item`` and, with ``rule``, satisfy ``rule(a, b)``.

    ``note`` says the rule in the message.

    Example:
        >>> pair_field(float_field(0, lo_open=True), rule=lambda a, b: a < b, note="lo < hi")("range", (2, 1))
        Traceback (most recent call last):
        ...
        ValueError: range: expected a pair (lo < hi), got (2, 1)
    """
    want = ("None or " if optional else "") + "a pair" + (f" ({note})" if note else "")

    def check(name: str, value: Any) -> Any:
        if value is None and optional:
            return None
        if isinstance(value, (str, bytes)) or not isinstance(value, Sequence) or len(value) != 2:
            raise ValueError(f"{name}: expected {want}, got {value!r}")
        a, b = (item(f"{name}[{i}]", v) for i, v in enumerate(value))
        if rule is not None and not rule(a, b):
            raise ValueError(f"{name}: expected {want}, got {value!r}")
        return (a, b)

    return check
