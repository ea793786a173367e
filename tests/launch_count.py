"""Count the aten ops (one kernel launch each on a GPU) and host reads of a piece of torch code.

A test / benchmark helper (not part of vadgs): on the CPU, every aten operator that reaches the
dispatcher is one kernel launch on a GPU, and every read of a tensor's value by Python
(``.item()``, ``bool(t)``, ``int(t)``, ``float(t)``, ``if t:``, ``.tolist()``, ``nonzero`` and
boolean-mask indexing, whose output size depends on the data) is one device-to-host
synchronisation. ``benchmarks/bench_patchmatch_launches.py`` prints the counts of a PatchMatch
call and ``tests/mvs/test_patchmatch_launches.py`` bounds them.

Example:
    >>> import torch
    >>> with LaunchCounter() as c:
    ...     x = torch.ones(3) * 2
    ...     _ = bool(x.sum() > 0)
    >>> c.launches, c.host_reads
    (5, 1)
"""

from __future__ import annotations

import collections
from typing import Any

import torch
from torch.utils._python_dispatch import TorchDispatchMode

# Ops whose result needs a value (or a data-dependent size) on the host.
_SYNC_OPS = {
    "aten._local_scalar_dense",  # item(), bool(), int(), float(), if tensor
    "aten.nonzero",
    "aten.masked_select",
    "aten.unique_dim",
    "aten._unique2",
    "aten.unique_consecutive",
    "aten.repeat_interleave",
}


# Ops that only re-label memory (no kernel) although the dispatcher does not flag them as views.
_NO_KERNEL = {"aten._unsafe_view", "aten._reshape_alias", "aten.lift_fresh"}


def _packet(func: Any) -> str:
    return f"aten.{func._overloadpacket.__name__}" if hasattr(func, "_overloadpacket") else str(func)


class LaunchCounter(TorchDispatchMode):
    """Context manager counting aten ops (``launches``) and host reads (``host_reads``).

    Attributes:
        launches: aten ops dispatched, views (``view``, ``select``, ``expand``...: no kernel) left
            out.
        all_ops: every aten op dispatched, views included.
        host_reads: reads of tensor values by the host (see the module docstring).
        ops: per-op counts (``"aten.add"`` → n), for finding where launches come from.
        marks: ``(label, launches, host_reads)`` snapshots taken by :meth:`mark`.
    """

    def __init__(self) -> None:
        super().__init__()
        self.launches = 0
        self.all_ops = 0
        self.host_reads = 0
        self.ops: collections.Counter[str] = collections.Counter()
        self.marks: list[tuple[str, int, int]] = []
        self._tolist: Any = None

    def mark(self, label: str) -> None:
        """Record the counts so far under ``label``."""
        self.marks.append((label, self.launches, self.host_reads))

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = _packet(func)
        self.all_ops += 1
        if getattr(func, "is_view", False) or name in _NO_KERNEL:  # a view launches no kernel
            return func(*args, **(kwargs or {}))
        self.launches += 1
        self.ops[name] += 1
        if name in _SYNC_OPS:
            self.host_reads += 1
        elif name == "aten.index" and any(
            isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in (args[1] if len(args) > 1 else ())
        ):
            self.host_reads += 1  # boolean-mask indexing: a nonzero inside
        return func(*args, **(kwargs or {}))

    def __enter__(self):
        # .tolist() reads values without going through the dispatcher: count it by hand.
        self._tolist = torch.Tensor.tolist
        counter = self

        def tolist(t, *a, **k):
            counter.host_reads += 1
            return counter._tolist(t, *a, **k)

        torch.Tensor.tolist = tolist  # type: ignore[method-assign]
        return super().__enter__()

    def __exit__(self, *exc):
        torch.Tensor.tolist = self._tolist  # type: ignore[method-assign]
        return super().__exit__(*exc)
