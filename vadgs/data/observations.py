"""The SfM observations a scene's visibility is built from: its points seen by the views of some frames.

A COLMAP scene (:func:`vadgs.data.load_colmap`) carries its SfM points with COLMAP's TRACK table
(``scene.sfm_points``, :class:`~vadgs.data.scene.ColmapPoints`); :func:`sfm_observations` keeps the
observations by views of the given frames (the training frames by default), as VAD-GS's visibility
(:meth:`vadgs.train.vad.VisibilityInputs.from_scene`) and ``vadgs voxels`` voxelise them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch

__all__ = ["sfm_observations"]


def sfm_observations(
    scene: Any, frames: Sequence[int] | None = None
) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
    """The scene's SfM points observed by views of ``frames``, with those observations only.

    Args:
        scene: a scene with ``sfm_points``.
        frames: frame indices (default: the training frames, or every frame without a split).

    Returns:
        ``(points (P', 3), (point_idx (T',), view_idx (T',)))``: the points with at least one such
        observation (renumbered, in their order) and their observations, as
        :func:`vadgs.geometry.voxelize` takes them.

    Raises:
        ValueError: if the scene has no ``sfm_points``.
    """
    sfm = scene.sfm_points
    if sfm is None:
        raise ValueError(f"scene {scene.name!r}: no SfM points (scene.sfm_points)")
    frames = frames if frames is not None else (scene.train_frames or [f.index for f in scene.frames])
    wanted = set(int(f) for f in frames)
    view_ok = torch.tensor([v.frame in wanted and v.group is None for v in scene.views], dtype=torch.bool)
    keep = view_ok[sfm.view_idx] if sfm.view_idx.numel() else sfm.view_idx.bool()
    pi, vi = sfm.point_idx[keep], sfm.view_idx[keep]
    used = torch.zeros(sfm.points.shape[0], dtype=torch.bool)
    used[pi] = True
    new_id = torch.cumsum(used.long(), 0) - 1
    return sfm.points[used], (new_id[pi], vi)
