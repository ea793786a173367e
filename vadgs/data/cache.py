"""Per-view data kept up to a byte budget: what makes memory follow the work, not the scene.

A training run, its initialisation and the VAD-GS visibility index read per-view data (images,
LiDAR depth maps, z-buffer maps) many times. Keeping all of it grows with the number of views
(a 1000-view segment at 1024 px is ~8 GB of float32 images alone); reading it every time costs a
decode per step. :class:`ByteCache` keeps the most recently used values up to ``max_bytes`` and
drops the least recently used first, so a run holds at most its budget and re-reads what was
dropped. What it holds is compact: :func:`to_uint8` / :func:`from_uint8` for colour images (1 byte
a channel instead of 4), :class:`SparseDepth` for LiDAR depth maps (8 bytes a point instead of 4 a
pixel).

Example:
    >>> cache = ByteCache(max_bytes=100)
    >>> a = cache.get(("image", 0), lambda: torch.zeros(10))  # 40 bytes
    >>> b = cache.get(("image", 1), lambda: torch.zeros(10))
    >>> c = cache.get(("image", 2), lambda: torch.zeros(10))  # 120 > 100: view 0 dropped
    >>> sorted(k[1] for k in cache.keys()), cache.nbytes, cache.misses
    ([1, 2], 80, 3)
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Any, NamedTuple

import torch

__all__ = ["DEFAULT_CACHE_GB", "ByteCache", "SparseDepth", "from_uint8", "to_uint8"]

#: The default budget of a training run's per-view caches (images and LiDAR depth), in GB (2^30 bytes).
DEFAULT_CACHE_GB = 2.0


class ByteCache:
    """Values kept up to a byte budget, the least recently used dropped first (see the module docstring).

    The size of a value is the bytes of its tensors (a tensor, or a tuple / NamedTuple of them);
    the value last added is always kept, even when it alone exceeds the budget.

    Args:
        max_bytes: the budget (> 0).

    Attributes:
        nbytes: the bytes held now.
        hits, misses: lookups that found their key, and those that made the value.
    """

    def __init__(self, max_bytes: int = 1 << 30) -> None:
        if isinstance(max_bytes, bool) or not isinstance(max_bytes, (int, float)) or not max_bytes > 0:
            raise ValueError(f"max_bytes: expected a positive number of bytes, got {max_bytes!r}")
        if not math.isfinite(max_bytes):
            raise ValueError(f"max_bytes: expected a finite number of bytes, got {max_bytes!r}")
        self.max_bytes = int(max_bytes)
        self._items: OrderedDict = OrderedDict()
        self.nbytes = 0
        self.hits = 0
        self.misses = 0

    @staticmethod
    def size_of(value: Any) -> int:
        """The bytes of the tensors in ``value`` (a tensor or a tuple of them; other items count 0)."""
        items = value if isinstance(value, tuple) else (value,)
        return sum(x.numel() * x.element_size() for x in items if isinstance(x, torch.Tensor))

    def get(self, key: Hashable, make: Callable[[], Any]) -> Any:
        """The cached value of ``key``, made by ``make()`` (and kept) when absent."""
        if key in self._items:
            self._items.move_to_end(key)
            self.hits += 1
            return self._items[key]
        self.misses += 1
        value = make()
        self._items[key] = value
        self.nbytes += self.size_of(value)
        while self.nbytes > self.max_bytes and len(self._items) > 1:
            _, old = self._items.popitem(last=False)
            self.nbytes -= self.size_of(old)
        return value

    def __contains__(self, key: Hashable) -> bool:
        return key in self._items

    def __len__(self) -> int:
        return len(self._items)

    def keys(self) -> list:
        """The keys held, least recently used first."""
        return list(self._items)

    def clear(self) -> None:
        """Drop everything."""
        self._items.clear()
        self.nbytes = 0


def to_uint8(image: torch.Tensor) -> torch.Tensor:
    """A float image in [0, 1] as uint8 (rounded; values outside [0, 1] clamped).

    :func:`from_uint8` of it is the image within 0.5/255; an 8-bit image read at its own
    resolution (``k / 255``) comes back bit for bit.

    Example:
        >>> x = torch.tensor([0.0, 1 / 255, 0.5, 1.0])
        >>> bool(torch.equal(from_uint8(to_uint8(x)), x[:2].new_tensor([0.0, 1 / 255, 128 / 255, 1.0])))
        True
    """
    return (image.detach() * 255.0).round_().clamp_(0, 255).to(torch.uint8)


def from_uint8(image: torch.Tensor, device: torch.device | str | None = None) -> torch.Tensor:
    """A uint8 image as float32 in [0, 1] (``k / 255``), moved to ``device`` first (None: where it is)."""
    return image.to(device).float().div_(255.0)


class SparseDepth(NamedTuple):
    """A sparse depth map (LiDAR points in a view) as its non-zero pixels.

    Attributes:
        index: ``(P,)`` int64 flat pixel indices (``row * W + col``) of the points.
        depth: ``(P,)`` float32 depths there.
        shape: the dense map's shape, e.g. ``(1, 1, H, W)``.
    """

    # the field shadows tuple.index (the method); the public name stays
    index: torch.Tensor  # type: ignore[assignment]
    depth: torch.Tensor
    shape: tuple[int, ...]

    @classmethod
    def from_dense(cls, dense: torch.Tensor) -> SparseDepth:
        """The non-zero pixels of ``dense`` (any shape).

        Example:
            >>> d = torch.zeros(1, 1, 2, 3); d[0, 0, 1, 2] = 4.5
            >>> s = SparseDepth.from_dense(d)
            >>> s.index.tolist(), s.depth.tolist(), bool(torch.equal(s.to_dense(), d))
            ([5], [4.5], True)
        """
        flat = dense.detach().reshape(-1)
        index = torch.nonzero(flat).squeeze(1)
        return cls(index, flat[index].clone(), tuple(dense.shape))

    def to_dense(self, device: torch.device | str | None = None) -> torch.Tensor:
        """The dense map (zeros where there is no point), built on ``device`` (None: where it is)."""
        device = self.depth.device if device is None else device
        out = torch.zeros(math.prod(self.shape), dtype=self.depth.dtype, device=device)
        out[self.index.to(device)] = self.depth.to(device)
        return out.reshape(self.shape)

    @property
    def points(self) -> int:
        """The number of points."""
        return int(self.index.numel())
