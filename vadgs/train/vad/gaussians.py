"""New Gaussians from an instance's fused MVS points (paper, Sec. 3.3, "Densification").

:func:`flat_gaussians` turns each kept point into a flat disc oriented by its MVS normal
(:func:`~vadgs.geometry.rotation.normals_to_quats`); :func:`add_reconstruction` adds them with
their optimizer state
(:func:`~vadgs.train.strategy.ops.add_gaussians`), static or attached to the object's node.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, MutableMapping
from typing import Any

import torch

from vadgs.geometry.rotation import normals_to_quats
from vadgs.train.strategy import ops
from vadgs.train.vad.config import VisibilityDensifyConfig
from vadgs.train.vad.reconstruct import (
    InstanceReconstruction,
)

__all__ = [
    "add_reconstruction",
    "flat_gaussians",
]


_C0 = 0.28209479177387814


def flat_gaussians(
    params: Mapping[str, torch.Tensor] | Any,
    rec: InstanceReconstruction,
    keep: torch.Tensor | None = None,
    new_opacity: float = 0.5,
    flatness: float = 0.2,
    event: int = 1,
) -> dict[str, torch.Tensor]:
    """New flat Gaussians from an instance's (kept) fused points, in ``params``' layout.

    Each point becomes a disc oriented by its MVS normal
    (:func:`~vadgs.geometry.rotation.normals_to_quats`), of width its
    spacing and thickness ``flatness`` times that, with opacity ``new_opacity`` and the MVS colour,
    on the device and in the dtype of ``params``' means. Where ``params`` has a ``provenance``
    entry the new rows get ``event`` (1-based). Entries of other layouts: gsplat's appearance
    ``colors`` ``(N, 3)`` get the logit of the MVS colour (as gsplat's ``simple_trainer``
    initialises them); every other unknown per-Gaussian entry (e.g. gsplat's ``features``) gets
    zeros of its trailing shape and dtype. ``node_ids`` is left to the caller (it depends on the
    model's tracks). Not differentiable (new leaf values).

    Args:
        params: the per-Gaussian tensors (vadgs's or gsplat's names,
            :func:`~vadgs.train.strategy.ops.param_names`).
        rec: the instance's :class:`~vadgs.train.vad.reconstruct.InstanceReconstruction`.
        keep: boolean mask ``(M,)`` of the points to use (default all).
        new_opacity: opacity of the new Gaussians, in (0, 1).
        flatness: thickness along the normal relative to the width.
        event: the 1-based event number written to ``provenance``.

    Returns:
        ``{name: (m, ...)}`` for every entry of ``params`` but ``node_ids``.
    """
    names = ops.param_names(params)
    p = getattr(params, "params", params)
    ref = p[names.means]
    dev, dt = ref.device, ref.dtype
    fields: tuple[torch.Tensor, ...] = (rec.points, rec.normals, rec.colors, rec.spacing)
    if keep is not None:  # one read for the four fields
        rows = keep.to(rec.points.device).nonzero().squeeze(1)
        fields = tuple(x[rows] for x in fields)
    pts, nrm, col, spc = (x.to(dev, dt) for x in fields)
    m = pts.shape[0]
    width = spc.clamp(min=1e-4)
    opacity = torch.full((m,), new_opacity, device=dev, dtype=dt)
    new = {
        names.means: pts,
        names.quats: normals_to_quats(nrm),
        names.log_scales: torch.log(torch.stack([width, width, width * flatness], -1)),
        names.opacity_logits: torch.log(opacity / (1 - opacity)),
    }
    if names.sh_dc is not None and names.sh_rest is not None:
        new[names.sh_dc] = ((col[:, :3] - 0.5) / _C0)[:, None, :]
        new[names.sh_rest] = torch.zeros(m, *p[names.sh_rest].shape[1:], device=dev, dtype=dt)
    if "provenance" in p:
        new["provenance"] = torch.full((m,), event, dtype=torch.int64, device=p["provenance"].device)
    for k in p.keys():
        if k in new or k == "node_ids":
            continue
        t = p[k]
        if k == "colors" and t.shape[1:] == (3,) and t.is_floating_point():
            new[k] = torch.logit(col[:, :3].clamp(1e-4, 1 - 1e-4)).to(t)
        else:
            new[k] = torch.zeros(m, *t.shape[1:], device=t.device, dtype=t.dtype)
    return new


def add_reconstruction(
    params: MutableMapping[str, torch.Tensor],
    optimizers: Any,
    state: dict[str, Any] | None,
    rec: InstanceReconstruction,
    keep: torch.Tensor | None,
    event: int,
    config: VisibilityDensifyConfig,
    track_nodes: Callable[[], Mapping[int, int]],
) -> None:
    """Add the :func:`flat_gaussians` of ``rec``'s (kept) points (``VisibilityAwareDensification._add``).

    Through :func:`~vadgs.train.strategy.ops.add_gaussians`, with ``node_ids`` (when ``params`` has
    them) the node of the instance's track (``track_nodes()``: track id → node, asked only then),
    or -1 for a static instance.
    """
    new = flat_gaussians(params, rec, keep, config.new_opacity, config.flatness, event)
    p = getattr(params, "params", params)
    node_ids = None
    if "node_ids" in p:
        node = -1 if rec.track is None else track_nodes()[rec.track]
        m = new[ops.param_names(params).means].shape[0]
        node_ids = torch.full((m,), node, dtype=torch.int64, device=p["node_ids"].device)
    ops.add_gaussians(params, optimizers, state, new, node_ids)
