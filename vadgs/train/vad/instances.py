"""Derived instance maps, for scenes without instance masks (paper, Sec. 4.1: its instances).

VAD-GS tests and reconstructs per instance. Where a dataset has no segmentation,
:func:`derive_instance_map` stands in for it: the static voxels are cut into ground cells
(:func:`~vadgs.geometry.ground.ground_cells`, in the scene's :func:`~vadgs.geometry.ground.ground_frame`)
and each moving object paints its projected 3D box (:func:`box_corners`). The visibility index
(:meth:`~vadgs.train.vad.visibility.VisibilityIndex.instances`) calls it on demand.
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Protocol

import torch

from vadgs.geometry.camera import Cameras, project_points
from vadgs.train.vad.inputs import VisibilityInputs
from vadgs.train.vad.lengths import scene_lengths

__all__ = [
    "InstanceMapSource",
    "box_corners",
    "derive_instance_map",
]


class InstanceMapSource(Protocol):
    """What :func:`derive_instance_map` reads of a scene's voxels and tracks.

    :class:`~vadgs.train.vad.visibility.VisibilityIndex` has it all (the visibility module imports
    this one, so the index is named by what it offers, not by its class; mypy checks that it
    offers it).
    """

    @property
    def inputs(self) -> VisibilityInputs:
        """The views' frames (``frame_position``) and the tracks."""
        ...

    @property
    def grow(self) -> int:
        """Pixels a derived map grows beyond the voxels."""
        ...

    @property
    def scene_depth(self) -> float:
        """The scene's length unit (:func:`~vadgs.train.vad.lengths.scene_lengths`)."""
        ...

    def voxel_raster(self, view: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Static voxel depth ``(1, H, W)`` and index ``(H, W)`` (-1: no voxel) of a view."""
        ...

    def cell_ids(self) -> torch.Tensor:
        """``(M,)`` derived instance id of each static voxel (its ground cell)."""
        ...

    def camera(self, view: int) -> Cameras:
        """The view's camera at its own size."""
        ...

    def valid(self, view: int) -> torch.Tensor:
        """``(H, W)`` bool: the view's own pixels (not padding)."""
        ...

    def box_corners(self, track: int) -> torch.Tensor:
        """``(8, 3)`` box corners of a track in its object frame."""
        ...

    def size(self, view: int) -> tuple[int, int]:
        """``(H, W)`` of the view (its own)."""
        ...


def box_corners(track) -> torch.Tensor:
    """``(8, 3)`` box corners of a track in its object frame.

    The mesh's bounds when the track has a mesh (street scenes put the origin on the ground), else
    ``size_lwh`` about the origin (DGP boxes).
    """
    if track.mesh is not None and Path(track.mesh).is_file():
        import trimesh

        lo, hi = (
            torch.tensor(b, dtype=torch.float32) for b in trimesh.load(track.mesh, process=False).bounds
        )
    else:
        hi = track.size_lwh.float() / 2
        lo = -hi
    pick = torch.tensor(list(itertools.product((0, 1), repeat=3)), dtype=torch.bool)
    return torch.where(pick, hi, lo)


def derive_instance_map(index: InstanceMapSource, view: int) -> torch.Tensor:
    """An instance map for a scene without one, from the voxel index map and the tracks.

    Static pixels take the id of their voxel's ground cell (``index.cell_size`` metres square,
    :meth:`VisibilityIndex.cell_ids`); pixels without a voxel take the nearest labelled pixel's id
    within ``index.grow`` pixels (so MVS can extend a little beyond the LiDAR's reach), else 0.
    Tracks with a pose at the view's frame paint their projected 3D box (convex hull of its
    corners, far boxes first). Unlike a segmentation network, this cannot label structures far
    from any LiDAR point (a sign above the LiDAR's field of view): the strategy then only repairs
    geometry near what the LiDAR saw.

    Args:
        index: what it reads of the scene (:class:`InstanceMapSource`): the scene's
            :class:`~vadgs.train.vad.visibility.VisibilityIndex`.
        view: the view's index.

    Returns:
        ``(H, W)`` int64 instance ids (0 = none).
    """
    import numpy as np
    from scipy import ndimage
    from scipy.spatial import ConvexHull, QhullError
    from skimage.draw import polygon

    inputs = index.inputs
    _, vox = index.voxel_raster(view)
    cells = index.cell_ids()
    if cells.numel():
        lab = torch.where(vox >= 0, cells[vox.clamp_min(0)], torch.zeros_like(vox)).numpy()
    else:  # no static voxel in the scene (every point on a moving object)
        lab = np.zeros(tuple(vox.shape), dtype=np.int64)
    if index.grow > 0 and (lab > 0).any():
        dist, (iy, ix) = ndimage.distance_transform_edt(lab == 0, return_indices=True)
        lab = np.where((lab == 0) & (dist <= index.grow), lab[iy, ix], lab)
    pos = inputs.frame_position(view)
    cam = index.camera(view)
    own = index.valid(view).numpy()
    lab = np.where(own, lab, 0)  # nothing grows into the padding of a smaller view
    box_near = scene_lengths(index.scene_depth)["box_near"]
    boxes = []
    for tid, t in inputs.tracks.items():
        if not bool(t.valid[pos]):
            continue
        corners = index.box_corners(tid)
        o2w = t.object_to_world[pos].float()
        world = corners @ o2w[:3, :3].T + o2w[:3, 3]
        uv, z = project_points(world[None], cam.K, cam.world_to_cam)
        if bool((z < box_near).any()):  # a box across the image plane: skip rather than mis-project
            continue
        boxes.append((float(z.mean()), tid, uv[0].numpy()))
    for _, tid, uv_np in sorted(boxes, reverse=True):  # far first: near boxes paint over them
        try:
            hull = uv_np[ConvexHull(uv_np).vertices]
        except QhullError:
            continue
        rr, cc = polygon(hull[:, 1], hull[:, 0], shape=index.size(view))
        lab[rr, cc] = tid
    return torch.from_numpy(np.ascontiguousarray(lab)).long()
