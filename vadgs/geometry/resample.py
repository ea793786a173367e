"""Maps resampled by an integer factor: nearest upsampling, and means over blocks of valid pixels.

:func:`repeat` upsamples the last two dimensions by repeating each pixel ``f x f`` times;
:func:`pool_valid` averages each ``f x f`` block over its valid pixels (zero where fewer than half
are valid; renormalised for unit vectors such as normals); :func:`pool_mask` keeps the blocks where
at least half the pixels are set. VAD-GS moves depth, normals and masks between the scene's
resolution and an instance's matching scale with them (:mod:`vadgs.train.vad.crops`). Pixel
``(y, x)`` of a coarse map covers pixels ``(f y .. f y + f - 1, f x .. f x + f - 1)`` of the fine
one (blocks aligned on the top-left corner, as ``avg_pool2d`` without padding: a remainder of
fewer than ``f`` rows or columns is dropped).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["pool_mask", "pool_valid", "repeat"]


def _check_factor(f: int) -> None:
    if isinstance(f, bool) or not isinstance(f, int) or f < 1:
        raise ValueError(f"f: expected an integer >= 1 (the resampling factor), got {f!r}")


def repeat(x: torch.Tensor, f: int) -> torch.Tensor:
    """Nearest upsampling of the last two dimensions by ``f``: pixel ``(y, x)`` fills its ``f x f`` block.

    Args:
        x: ``(..., H, W)`` map of any dtype (depth, normals, a bool mask).
        f: the factor, an integer >= 1 (1: ``x`` itself).

    Returns:
        ``(..., f H, f W)``, of ``x``'s dtype and device; differentiable w.r.t. ``x``.

    Example:
        >>> repeat(torch.tensor([[1, 2]]), 2).tolist()
        [[1, 1, 2, 2], [1, 1, 2, 2]]
    """
    _check_factor(f)
    return x if f == 1 else x.repeat_interleave(f, -2).repeat_interleave(f, -1)


def pool_valid(x: torch.Tensor, valid: torch.Tensor, f: int, unit: bool = False) -> torch.Tensor:
    """The mean of the valid pixels of each ``f x f`` block: ``(C, H, W)`` → ``(C, H // f, W // f)``.

    A block with fewer than half its pixels valid is zero. At ``f = 1``, ``x`` with zeros outside
    ``valid``.

    Args:
        x: ``(C, H, W)`` float map (depth ``C = 1``, normals ``C = 3``).
        valid: ``(H, W)`` or ``(C, H, W)`` bool, the pixels that count.
        f: the factor, an integer >= 1.
        unit: renormalise each pooled vector to unit length (normals).

    Returns:
        ``(C, H // f, W // f)``, of ``x``'s dtype and device; differentiable w.r.t. ``x``.

    Example:
        >>> x = torch.tensor([[[1.0, 3.0, 5.0, 7.0], [9.0, 9.0, 9.0, 9.0]]])
        >>> valid = torch.tensor([[True, True, True, False], [False, False, False, False]])
        >>> pool_valid(x, valid, 2).tolist()  # block 1: 2 of 4 valid, block 2: 1 of 4
        [[[2.0, 0.0]]]
    """
    _check_factor(f)
    if f == 1:
        return torch.where(valid, x, torch.zeros_like(x))
    v = valid.to(x.dtype)
    cnt = F.avg_pool2d(v[None], f)[0]
    out = F.avg_pool2d((x * v)[None], f)[0] / cnt.clamp(min=1e-6)
    if unit:
        out = F.normalize(out, dim=0)
    return torch.where(cnt >= 0.5, out, torch.zeros_like(out))


def pool_mask(m: torch.Tensor, f: int) -> torch.Tensor:
    """The ``f x f`` blocks where at least half the pixels are set: ``(..., H, W)`` → ``(..., H/f, W/f)``.

    Args:
        m: bool mask ``(..., H, W)``.
        f: the factor, an integer >= 1 (1: ``m`` itself).

    Returns:
        bool ``(..., H // f, W // f)`` on ``m``'s device.

    Example:
        >>> pool_mask(torch.tensor([[True, True, True, False], [False, False, False, False]]), 2).tolist()
        [[True, False]]
    """
    _check_factor(f)
    if f == 1:
        return m
    lead = m.shape[:-2]
    x = F.avg_pool2d(m.reshape(-1, 1, *m.shape[-2:]).float(), f)
    return (x >= 0.5).reshape(*lead, *x.shape[-2:])
