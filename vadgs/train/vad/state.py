"""The VAD-GS strategy's state: its kept renders, compact, and its per-view maps packed losslessly.

:func:`compact_render` / :func:`expand_render`: how the strategy keeps the loop's renders between
its events (``state["vad_renders"]``); :func:`pack_state` / :func:`unpack_state`, used by vadgs's
trainer when it saves and resumes a run (importable from :mod:`vadgs.train.vad`).
"""

from __future__ import annotations

import zlib
from typing import Any

import numpy as np
import torch

from vadgs.geometry.octahedral import octahedral_decode, octahedral_encode

__all__ = ["compact_render", "expand_render", "pack_state", "unpack_state"]


def compact_render(
    depth: torch.Tensor, alpha: torch.Tensor, normals: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A view's render as the strategy keeps it: 5 bytes a pixel instead of 20.

    Depth as ``float16`` (relative error ≤ 2⁻¹¹), opacity as ``uint8`` (``round(255 alpha)``,
    error ≤ 1/510), normals as two ``int8`` octahedral codes (within 0.95°, zero vectors kept;
    :func:`~vadgs.geometry.octahedral.octahedral_encode`). :func:`expand_render` gives back
    ``float32`` maps; the event reads those, whether the run was resumed or not.

    Args:
        depth: ``(1, H, W)``.
        alpha: ``(1, H, W)``, in ``[0, 1]``.
        normals: ``(3, H, W)``, unit or zero.

    Returns:
        ``(depth float16 (1, H, W), alpha uint8 (1, H, W), normals int8 (2, H, W))`` on the inputs'
        device (detached).

    Example:
        >>> d, a, n = torch.full((1, 1, 2), 7.3), torch.tensor([[[1.0, 0.25]]]), torch.zeros(3, 1, 2)
        >>> n[2, 0, 0] = -1.0
        >>> kept = compact_render(d, a, n)
        >>> [x.dtype for x in kept], kept[1].tolist(), kept[2][:, 0, 1].tolist()
        ([torch.float16, torch.uint8, torch.int8], [[[255, 64]]], [-128, -128])
        >>> d2, a2, n2 = expand_render(kept)
        >>> d2[0, 0, 0].item(), a2[0, 0].tolist(), n2[:, 0, 0].tolist(), n2[:, 0, 1].tolist()
        (7.30078125, [1.0, 0.250980406999588], [0.0, 0.0, -1.0], [0.0, 0.0, 0.0])
    """
    depth, alpha, normals = depth.detach(), alpha.detach(), normals.detach()
    code = alpha.float().clamp(0, 1).mul(255).round().to(torch.uint8)
    return depth.half(), code, octahedral_encode(normals, dim=-3)


def expand_render(kept: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The ``float32`` ``(depth, alpha, normals)`` of a :func:`compact_render`."""
    depth, code, normals = kept
    return depth.float(), code.float() / 255, octahedral_decode(normals, dim=-3).float()


# The packed form of a tensor: zlib (level 1) of its bytes, after a "Sub" filter (as in PNG) along
# its last axis on the integer bit patterns of its elements when "filter" is "sub" (each element
# minus its left neighbour, wrapping: exact both ways); without it (the priors), no "filter".
_UINT = {1: np.uint8, 2: np.uint16, 4: np.uint32, 8: np.uint64}


def _pack_tensor(x: torch.Tensor, sub: bool = True) -> dict[str, Any]:
    x = x.detach().cpu().contiguous()
    out: dict[str, Any] = {"shape": list(x.shape), "dtype": str(x.dtype).removeprefix("torch.")}
    raw = x.reshape(-1).view(torch.uint8).numpy()
    if sub and x.dim() and x.element_size() in _UINT:
        bits = raw.view(_UINT[x.element_size()]).reshape(x.shape)
        raw = bits.copy()
        raw[..., 1:] -= bits[..., :-1]  # unsigned: wraps
        out["filter"] = "sub"
    out["zlib"] = torch.frombuffer(bytearray(zlib.compress(raw.tobytes(), 1)), dtype=torch.uint8)
    return out


def _unpack_tensor(packed: dict[str, Any]) -> torch.Tensor:
    dtype, shape = getattr(torch, packed["dtype"]), packed["shape"]
    raw = bytearray(zlib.decompress(packed["zlib"].numpy().tobytes()))
    filt = packed.get("filter")
    if filt == "sub":
        size = torch.empty((), dtype=dtype).element_size()
        bits = np.frombuffer(raw, dtype=_UINT[size]).reshape(shape)
        raw = bytearray(np.cumsum(bits, axis=-1, dtype=_UINT[size]).tobytes())  # wraps like the filter
    elif filt is not None:
        raise ValueError(f"unpack_state: a packed map's filter must be 'sub' or absent, got {filt!r}")
    return torch.frombuffer(raw, dtype=dtype).reshape(shape).clone()


def pack_state(state: dict[str, Any]) -> dict[str, Any]:
    """The strategy's state for a checkpoint: its per-view maps zlib-compressed, losslessly.

    The MVS priors (``vad_priors``) are zero outside the instances an event reconstructed (and
    piecewise constant where MVS ran at a coarser scale), so they compress several times; the
    loop's kept renders (``vad_renders``, 5 bytes a pixel in their :func:`compact_render` form,
    only while an event can still follow) about twice, with a PNG-style "Sub" filter (each
    value's bits minus its left neighbour's) before zlib. The other
    entries are kept as they are. :func:`unpack_state` gives back the same bits, so a resumed
    run stays exact. A state without them (the standard strategy's, gsplat's) is returned
    unchanged.

    Example:
        >>> prior = (torch.zeros(1, 4, 6), torch.zeros(3, 4, 6))
        >>> prior[0][0, 1, 2] = 7.5
        >>> back = unpack_state(pack_state({"vad_priors": {3: prior}, "count": 1}))
        >>> torch.equal(back["vad_priors"][3][0], prior[0]), back["count"]
        (True, 1)
    """
    out = dict(state)
    for key, sub in _PACKED.items():
        maps = state.get(key)
        if maps:
            out[key] = {v: {"packed": [_pack_tensor(x, sub) for x in m]} for v, m in maps.items()}
    return out


def unpack_state(state: dict[str, Any]) -> dict[str, Any]:
    """The inverse of :func:`pack_state`."""
    out = dict(state)
    for key in _PACKED:
        maps = state.get(key)
        if maps:
            out[key] = {v: tuple(_unpack_tensor(x) for x in m["packed"]) for v, m in maps.items()}
    return out


# per view: a tuple of maps; whether the Sub filter goes before zlib. The renders pack smaller with
# it; the priors, mostly zero and piecewise constant, do not (docs/train.md, "Checkpoints").
_PACKED = {"vad_priors": False, "vad_renders": True}
