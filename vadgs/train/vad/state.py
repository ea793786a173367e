"""The VAD-GS strategy's state in checkpoints: its per-view maps packed losslessly.

:func:`pack_state` / :func:`unpack_state`, used by vadgs's trainer when it saves and resumes a run
(importable from :mod:`vadgs.train.vad`).
"""

from __future__ import annotations

import zlib
from typing import Any

import torch

__all__ = ["pack_state", "unpack_state"]


def _pack_tensor(x: torch.Tensor) -> dict[str, Any]:
    raw = x.detach().cpu().contiguous().view(torch.uint8).reshape(-1).numpy().tobytes()
    return {"zlib": torch.frombuffer(bytearray(zlib.compress(raw, 1)), dtype=torch.uint8),
            "shape": list(x.shape), "dtype": str(x.dtype).removeprefix("torch.")}  # fmt: skip


def _unpack_tensor(packed: dict[str, Any]) -> torch.Tensor:
    raw = bytearray(zlib.decompress(packed["zlib"].numpy().tobytes()))
    return torch.frombuffer(raw, dtype=getattr(torch, packed["dtype"])).reshape(packed["shape"]).clone()


def pack_state(state: dict[str, Any]) -> dict[str, Any]:
    """The strategy's state for a checkpoint: its per-view maps zlib-compressed, losslessly.

    The MVS priors (``vad_priors``) are zero outside the instances an event reconstructed (and
    piecewise constant where MVS ran at a coarser scale), so they compress several times (6x on
    the bundled sample); the loop's kept renders (``vad_renders``, float16, only while an event
    can still follow) about 1.4x. The other entries are kept as they are. :func:`unpack_state`
    gives back the same bits, so a resumed run stays exact. A state without them (the standard
    strategy's, gsplat's) is returned unchanged.

    Example:
        >>> prior = (torch.zeros(1, 4, 6), torch.zeros(3, 4, 6))
        >>> prior[0][0, 1, 2] = 7.5
        >>> back = unpack_state(pack_state({"vad_priors": {3: prior}, "count": 1}))
        >>> torch.equal(back["vad_priors"][3][0], prior[0]), back["count"]
        (True, 1)
    """
    out = dict(state)
    for key in _PACKED:
        maps = state.get(key)
        if maps:
            out[key] = {v: {"packed": [_pack_tensor(x) for x in m]} for v, m in maps.items()}
    return out


def unpack_state(state: dict[str, Any]) -> dict[str, Any]:
    """The inverse of :func:`pack_state` (a state stored without packing is returned as it is)."""
    out = state
    for key in _PACKED:
        maps = state.get(key)
        if maps and any(isinstance(m, dict) for m in maps.values()):
            out = out if out is not state else dict(state)
            out[key] = {v: tuple(_unpack_tensor(x) for x in m["packed"]) if isinstance(m, dict) else m
                        for v, m in maps.items()}  # fmt: skip
    return out


_PACKED = ("vad_priors", "vad_renders")  # per view: a tuple of maps
