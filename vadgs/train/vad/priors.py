"""The geometric priors of the losses: MVS depth and normals of the reconstructed views (paper, Sec. 4.4).

:func:`merge_priors` keeps each event's MVS depth and normals in the strategy's state
(``state["vad_priors"]``); :func:`view_targets` (the strategy's ``geometry_targets``) reads them
back, with the voxel depth where no MVS depth exists, as the targets of
:func:`vadgs.train.losses.geometric_losses`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from vadgs.train.losses import GeometryTargets
from vadgs.train.vad.reconstruct import InstanceReconstruction
from vadgs.train.vad.visibility import VisibilityIndex

__all__ = ["merge_priors", "state_priors", "view_targets"]


def merge_priors(
    priors: dict[int, tuple[torch.Tensor, torch.Tensor]],
    rec: InstanceReconstruction,
    beyond: VisibilityIndex | None = None,
) -> None:
    """Keep the MVS depth and normals of ``rec``'s views in ``priors`` (``state["vad_priors"]``).

    Where a view already has priors, the new ones replace them only where the new depth exists.
    With ``beyond`` (the scene's index, when the strategy's ``mvs_prior_beyond_voxels`` is on a
    scene with LiDAR), the new depth and normals are kept only where the view's voxel z-buffer
    (:meth:`~vadgs.train.vad.visibility.VisibilityIndex.voxel_depth`) is empty: beyond the
    LiDAR's reach (a sign above it, a facade out of range), where nothing else measures the
    surface; elsewhere the voxel depth (:func:`view_targets`) and the trainer's LiDAR loss do.
    The voxel grid is fixed after ``prepare``, so this is done once, here, not at every step.
    """
    for v, d, n in zip(rec.views, rec.depth, rec.normal):
        if beyond is not None:
            reached = beyond.voxel_depth(v)[0].to(d.device) > 0
            d, n = d.masked_fill(reached, 0.0), n.masked_fill(reached, 0.0)
        old = priors.get(v)
        if old is not None:
            has = d > 0
            d = torch.where(has, d, old[0])
            n = torch.where(has, n, old[1])
        priors[v] = (d, n)


def state_priors(state: Any) -> dict[int, tuple[torch.Tensor, torch.Tensor]]:
    """The priors kept in a strategy's ``state`` (``state["vad_priors"]``, see :func:`merge_priors`).

    Raises:
        ValueError: ``state`` is not a state made by the strategy's ``initialize_state``.
    """
    if not isinstance(state, Mapping) or "vad_priors" not in state:
        got = f"keys {sorted(state)}" if isinstance(state, Mapping) else type(state).__name__
        raise ValueError(
            f"state: expected the strategy's state (from initialize_state(), with 'vad_priors'), got {got}"
        )
    return state["vad_priors"]


def view_targets(
    priors: dict[int, tuple[torch.Tensor, torch.Tensor]],
    index: VisibilityIndex,
    view: int,
    voxel_depth_prior: bool = True,
    voxel_prior_tracks: bool = False,
) -> GeometryTargets | None:
    """The targets of a view's geometric losses: its MVS depth and normals, else the voxel depth.

    ``priors`` is ``state["vad_priors"]`` (:func:`merge_priors`); ``index`` the scene's
    :class:`~vadgs.train.vad.visibility.VisibilityIndex`. With ``voxel_depth_prior``, pixels
    without MVS depth take the voxel depth — only where the voxel belongs to the pixel's own
    instance (elsewhere the z-buffer sees through missing geometry, e.g. the facade behind a sign,
    and would pull it backwards); on a moving object's pixels only with ``voxel_prior_tracks``
    (:meth:`~vadgs.train.vad.visibility.VisibilityIndex.own_voxel_depth`). On a scene with LiDAR
    the MVS priors are by default only those beyond the voxels (:func:`merge_priors`'
    ``beyond``). ``None`` when the view has neither.
    Tensors ``(1, 1, H, W)`` / ``(1, 3, H, W)`` at the view's own size (the index's maps may be
    padded), on the device of the MVS priors, or of the index for a view without them.
    """
    depth, normal = None, None
    if view in priors:
        depth, normal = priors[view]
    if voxel_depth_prior:
        vd = index.own_voxel_depth(view, voxel_prior_tracks)  # kept per view
        depth = vd if depth is None else torch.where(depth > 0, depth, vd.to(depth.device))
    if depth is None:
        return None
    h, w = index.size(view)
    depth = depth[..., :h, :w]
    normal = None if normal is None else normal[..., :h, :w]
    return GeometryTargets(depth=depth[None], normal=normal if normal is None else normal[None])
