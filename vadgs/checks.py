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
import math
import os
from collections.abc import Iterator, Sequence

import torch

__all__ = [
    "MAX_THREADS",
    "check_at_least",
    "check_at_most",
    "check_finite",
    "check_intrinsics",
    "check_non_negative",
    "check_positive",
    "check_quaternions",
    "check_rigid_last_row",
    "check_same_device",
    "check_shape",
    "check_size",
    "checking",
    "checks_enabled",
    "set_checks_enabled",
]

#: The most torch CPU threads a command or a training takes (``--threads``): ``torch.set_num_threads``
#: of 100 000 000 crashes the process (a segmentation fault) at the first parallel operation.
MAX_THREADS = 1024

_OFF = {"0", "false", "off", "no"}
_enabled: bool = os.environ.get("VADGS_CHECKS", "1").strip().lower() not in _OFF


def checks_enabled() -> bool:
    """Whether value checks run (``VADGS_CHECKS``, :func:`set_checks_enabled`, :func:`checking`)."""
    return _enabled


def set_checks_enabled(enabled: bool) -> bool:
    """Switch value checks on or off for the whole process; returns the previous setting."""
    global _enabled
    previous, _enabled = _enabled, bool(enabled)
    return previous


@contextlib.contextmanager
def checking(enabled: bool) -> Iterator[None]:
    """Run a block with value checks on or off, restoring the previous setting afterwards.

    Example:
        >>> with checking(False):
        ...     check_finite(torch.tensor([float("nan")]), "x")  # not checked: no error
        >>> checks_enabled()
        True
    """
    previous = set_checks_enabled(enabled)
    try:
        yield
    finally:
        set_checks_enabled(previous)


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
    if _enabled and x.is_floating_point():
        bad = ~torch.isfinite(x)
        if bool(bad.any()):
            raise ValueError(
                f"{name}: expected finite values, got {int(bad.sum())} non-finite of {x.numel()}"
            )


def check_intrinsics(K: torch.Tensor, name: str = "K") -> None:
    """Value check of ``(*, 3, 3)`` pinhole intrinsics: finite, ``fx = K[..., 0, 0] > 0``, ``fy > 0``.

    Example:
        >>> check_intrinsics(torch.zeros(2, 3, 3))
        Traceback (most recent call last):
        ...
        ValueError: K: expected positive focal lengths K[..., 0, 0], K[..., 1, 1], got fx=0, fy=0 at (0,)
    """
    check_finite(K, name)
    if _enabled:
        f = K.detach()[..., [0, 1], [0, 1]]
        bad = ~(f > 0).all(-1)
        if bool(bad.any()):
            at = tuple(int(i) for i in bad.nonzero()[0]) if bad.dim() else ()
            fx, fy = (float(v) for v in f[at])
            raise ValueError(
                f"{name}: expected positive focal lengths K[..., 0, 0], K[..., 1, 1], "
                f"got fx={fx:g}, fy={fy:g} at {at}"
            )


def check_quaternions(q: torch.Tensor, name: str = "quats") -> None:
    """Value check of ``(*, 4)`` quaternions: finite and of non-zero norm (a zero one has no rotation).

    Example:
        >>> check_quaternions(torch.tensor([[1.0, 0, 0, 0], [0, 0, 0, 0]]))
        Traceback (most recent call last):
        ...
        ValueError: quats: expected non-zero quaternions, got 1 of norm 0 (first: row 1)
    """
    check_finite(q, name)
    if _enabled and q.numel():
        zero = q.detach().norm(dim=-1) < 1e-12
        if bool(zero.any()):
            first = int(zero.flatten().nonzero()[0, 0])
            raise ValueError(
                f"{name}: expected non-zero quaternions, got {int(zero.sum())} of norm 0 (first: row {first})"
            )


def check_rigid_last_row(T: torch.Tensor, name: str) -> None:
    """Value check of ``(*, 4, 4)`` transforms: finite, last row ``(0, 0, 0, 1)`` (within 1e-5).

    Example:
        >>> check_rigid_last_row(torch.zeros(4, 4), "transform")
        Traceback (most recent call last):
        ...
        ValueError: transform: expected a transform with last row (0, 0, 0, 1), got [0.0, 0.0, 0.0, 0.0]
    """
    check_finite(T, name)
    if _enabled and T.numel():
        row = T.detach()[..., 3, :].reshape(-1, 4)
        want = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=row.dtype, device=row.device)
        bad = ((row - want).abs() > 1e-5).any(-1)
        if bool(bad.any()):
            got = row[int(bad.nonzero()[0, 0])].tolist()
            raise ValueError(f"{name}: expected a transform with last row (0, 0, 0, 1), got {got}")


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


def check_at_least(config: object, minimum: float, *names: str, note: str = "") -> None:
    """Raise ``ValueError`` unless every field ``names`` of ``config`` is ``>= minimum`` (NaN fails).

    The message names the fields together, the bound and the values, e.g.
    ``"log_every, hard_every: expected >= 1, got 50, 0"`` (``note`` follows the bound). For the
    ``__post_init__`` of a frozen config dataclass.

    Example:
        >>> from types import SimpleNamespace
        >>> check_at_least(SimpleNamespace(a=1, b=0), 1, "a", "b")
        Traceback (most recent call last):
        ...
        ValueError: a, b: expected >= 1, got 1, 0
    """
    values = [getattr(config, name) for name in names]
    if not all(v >= minimum for v in values):
        got = ", ".join(str(v) for v in values)
        raise ValueError(f"{', '.join(names)}: expected >= {minimum:g}{note}, got {got}")


def check_at_most(config: object, maximum: float, *names: str, note: str = "") -> None:
    """Raise ``ValueError`` unless every field ``names`` of ``config`` is ``<= maximum`` (NaN fails).

    The upper bound of a count a user types (threads, ports, frames), checked before any work; the
    message names the fields, the bound (``note`` follows it: how to raise it) and the values.

    Example:
        >>> from types import SimpleNamespace
        >>> check_at_most(SimpleNamespace(port=70000), 65535, "port")
        Traceback (most recent call last):
        ...
        ValueError: port: expected <= 65535, got 70000
    """
    values = [getattr(config, name) for name in names]
    if not all(v <= maximum for v in values):
        got = ", ".join(str(v) for v in values)
        raise ValueError(f"{', '.join(names)}: expected <= {maximum:g}{note}, got {got}")


def check_positive(config: object, *names: str) -> None:
    """Raise ``ValueError`` unless every field ``names`` of ``config`` is a finite number > 0.

    Fields that are None (an optional setting left unset) pass. For the ``__post_init__`` of a
    frozen config dataclass, like :func:`check_at_least`.

    Example:
        >>> from types import SimpleNamespace
        >>> check_positive(SimpleNamespace(fps=10.0, scale=0.0), "fps", "scale")
        Traceback (most recent call last):
        ...
        ValueError: scale: expected a positive number, got 0.0
    """
    bad = [n for n in names if not _positive_or_none(getattr(config, n))]
    if bad:
        got = ", ".join(str(getattr(config, n)) for n in bad)
        raise ValueError(f"{', '.join(bad)}: expected a positive number, got {got}")


def check_non_negative(config: object, *names: str) -> None:
    """Raise ``ValueError`` unless every field ``names`` of ``config`` is a finite number >= 0.

    For weights and learning rates, where 0 switches a term off and NaN, infinity or a negative
    value would train silently wrong. Like :func:`check_positive` (None passes).

    Example:
        >>> from types import SimpleNamespace
        >>> check_non_negative(SimpleNamespace(lambda_lidar=float("nan"), ssim_weight=0.2), "lambda_lidar")
        Traceback (most recent call last):
        ...
        ValueError: lambda_lidar: expected a finite number >= 0, got nan
    """
    bad = [n for n in names if not _non_negative_or_none(getattr(config, n))]
    if bad:
        got = ", ".join(str(getattr(config, n)) for n in bad)
        raise ValueError(f"{', '.join(bad)}: expected a finite number >= 0, got {got}")


def _non_negative_or_none(value: float | None) -> bool:
    return value is None or (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0)


def _positive_or_none(value: float | None) -> bool:
    return value is None or (math.isfinite(value) and value > 0)
