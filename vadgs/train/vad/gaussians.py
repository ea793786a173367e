"""New Gaussians from an instance's fused MVS points (paper, Sec. 4.3 and Fig. 4).

:func:`flat_gaussians` turns each kept point into a flat disc oriented by its MVS normal
(:func:`~vadgs.geometry.rotation.normals_to_quats`), static or attached to the object's node, in
the model's layout: the event (:func:`~vadgs.train.vad.event.add_reconstructions`) hands them
straight to :func:`~vadgs.train.strategy.ops.add_gaussians`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from vadgs.geometry.rotation import normals_to_quats
from vadgs.train.strategy import ops
from vadgs.train.vad.reconstruct import InstanceReconstruction

__all__ = ["flat_gaussians"]


_C0 = 0.28209479177387814


def flat_gaussians(
    params: Mapping[str, torch.Tensor] | Any,
    rec: InstanceReconstruction,
    keep: torch.Tensor | None = None,
    new_opacity: float = 0.5,
    flatness: float = 0.2,
    event: int = 1,
    node: int = -1,
) -> dict[str, torch.Tensor]:
    """New flat Gaussians from an instance's (kept) fused points, in ``params``' layout.

    Each point becomes a disc oriented by its MVS normal
    (:func:`~vadgs.geometry.rotation.normals_to_quats`), of width its
    spacing and thickness ``flatness`` times that, with opacity ``new_opacity`` and the MVS colour,
    on the device and in the dtype of ``params``' means. Where ``params`` has a ``provenance``
    entry the new rows get ``event`` (1-based). Entries of other layouts: gsplat's appearance
    ``colors`` ``(N, 3)`` get the logit of the MVS colour (as gsplat's ``simple_trainer``
    initialises them); every other unknown per-Gaussian entry (e.g. gsplat's ``features``) gets
    zeros of its trailing shape and dtype. Where ``params`` has ``node_ids`` the new rows get
    ``node``. Not differentiable (new leaf values): the rows
    :func:`~vadgs.train.strategy.ops.add_gaussians` appends.

    Args:
        params: the per-Gaussian tensors (vadgs's or gsplat's names,
            :func:`~vadgs.train.strategy.ops.param_names`).
        rec: the instance's :class:`~vadgs.train.vad.reconstruct.InstanceReconstruction`.
        keep: boolean mask ``(M,)`` of the points to use (default all).
        new_opacity: opacity of the new Gaussians, in (0, 1).
        flatness: thickness along the normal relative to the width.
        event: the 1-based event number written to ``provenance``.
        node: the track node the new Gaussians join (``-1``: static), written to ``node_ids``;
            their ``means`` are then in that node's object frame (``rec.track``'s, as
            :func:`~vadgs.train.vad.reconstruct.finish_match` gives them).

    Returns:
        ``{name: (m, ...)}`` for every entry of ``params``.
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
    for k, value in (("provenance", event), ("node_ids", node)):
        if k in p:
            new[k] = torch.full((m,), value, dtype=torch.int64, device=p[k].device)
    for k in p.keys():
        if k in new:
            continue
        t = p[k]
        if k == "colors" and t.shape[1:] == (3,) and t.is_floating_point():
            new[k] = torch.logit(col[:, :3].clamp(1e-4, 1 - 1e-4)).to(t)
        else:
            new[k] = torch.zeros(m, *t.shape[1:], device=t.device, dtype=t.dtype)
    return new
