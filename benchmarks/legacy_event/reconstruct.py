# Frozen copy of vadgs/train/reconstruct.py at commit 274c932 (before issue 21), the reference of
# benchmarks/bench_vad_event.py. Not maintained: do not import it from vadgs.
# ruff: noqa
r"""Reconstruct one flagged instance by multi-view stereo (paper, Fig. 2 and 4).

:class:`VisibilityIndex` gathers what the visibility-aware densification needs about a scene:
the static voxel grid (world frame) and one grid per moving object (its own frame), each voxel's
instance label and visibility set, and the cameras of every view, as
:class:`~vadgs.select.Covisibility` objects for view selection.

:func:`reconstruct_instance` then, for a reference view and an instance flagged by
:func:`~vadgs.train.incomplete.find_incomplete`:

1. takes the instance's voxels (their visibility sets are the candidate views) — or, when the
   instance has almost no voxels of its own (the LiDAR missed it), the voxels the z-buffer sees
   *through* it in the reference view, whose observers also look at the missing surface;
2. selects ``k`` supporting views with the diversity-aware k-clique
   (:func:`~vadgs.select.select_views`), in the object's frame for a moving object;
3. runs PatchMatch on the whole group (each member as reference against the others), on crops
   around the instance (small instances at up to ``max_upsample`` times the resolution),
   matching only inside the instance's masks (static instances only
   against static pixels, a moving object only against itself), initialised from rendered depth
   and normals when given;
4. keeps the pixels whose depth at least ``min_consistent_views`` other members confirm
   (forward–backward reprojection, relative depth), completes the textureless parts of static
   planar instances, and
5. fuses them into points with normals and colours, in the instance's frame (world, or the
   object's own frame), with :func:`vadgs.mvs.fuse_depth_maps` (one point per consistent pixel);
6. returns each member's consistent depth and normals at the scene's resolution as priors.

Each step is a small function (``_instance_frame``, :func:`~vadgs.select.select_views`,
``_crop_group`` and ``_match``, ``_consistent``, fusion, ``_depth_priors``) on the device of the
index.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import torch
import torch.nn.functional as F

from vadgs.data.lidar import accumulate_lidar
from vadgs.data.scene import Scene
from vadgs.geometry.camera import Cameras, invert_rigid, project_points, scale_intrinsics
from vadgs.geometry.voxel import VoxelGrid, voxelize
from vadgs.geometry.zbuffer import ZBufferConfig, rasterize_voxels
from vadgs.mvs.consistency import geometric_consistency
from vadgs.mvs.fusion import FusionConfig, fuse_depth_maps
from benchmarks.legacy_event.patchmatch import PatchMatchConfig, patchmatch
from vadgs.mvs.planar import PlanarCompletionConfig, complete_planar
from vadgs.select.covisibility import Covisibility
from vadgs.select.selector import ViewSelectionConfig, select_views
from vadgs.train.incomplete import voxel_labels

__all__ = [
    "InstanceReconstruction",
    "ReconstructConfig",
    "VisibilityIndex",
    "build_visibility_index",
    "reconstruct_instance",
    "sfm_observations",
]


@dataclass(frozen=True)
class ReconstructConfig:
    """Settings of :func:`reconstruct_instance`.

    Attributes:
        selection: view selection (``k = 4`` supporting views by default; ``method="consecutive"``
            is the paper's "w/o view selection" ablation).
        patchmatch: PatchMatch settings.
        margin: pixels added around each instance's bounding box for the crops.
        max_crop: crops are limited to this many pixels per side (larger instances are
            reconstructed in their central part only; keeps the cost bounded).
        max_reproj_error: forward–backward reprojection threshold (px) of the consistency check.
        max_rel_depth: relative depth threshold of the consistency check.
        min_consistent_views: other group members that must confirm a pixel.
        min_instance_voxels: below this many own voxels, the voxels seen through the instance
            in the reference view stand in for its candidates.
        min_pixels: members whose instance mask has fewer pixels are used as sources only.
        max_points: cap on the points returned (random subset, seeded).
        max_upsample: small instances, whose crop is at most ``max_crop / f`` pixels, are matched
            at ``f`` times the scene's resolution, ``f`` up to this integer and never finer than
            the image files (``1 / scene.scale``): a sign 40 px tall at half resolution gets four
            times the pixels and half the depth error (on street_a: its MVS points within 5 cm of
            the true surface 35 % → 60 %, its surface covered 51 % → 65 %), while the crop stays
            within ``max_crop`` so the cost stays bounded. ``1``: always the scene's resolution.
        planar: planar completion of the textureless parts of static instances
            (:func:`vadgs.mvs.complete_planar`); ``None`` turns it off. Never applied to moving
            objects: a car is not planar, and one plane fitted to it fills many of its pixels off
            its surface. On by default since small instances are matched at a finer resolution
            (``max_upsample``): on street_a it took the sign's completeness in training from 76 %
            to 84 % at +0.3 dB (docs/results.md). (At the training resolution alone it had tilted
            the sign's board.)
    """

    selection: ViewSelectionConfig = field(default_factory=lambda: ViewSelectionConfig(min_shared=2))
    patchmatch: PatchMatchConfig = field(default_factory=lambda: PatchMatchConfig(iterations=3))
    margin: int = 6
    max_crop: int = 160
    max_reproj_error: float = 2.0
    max_rel_depth: float = 0.01
    min_consistent_views: int = 1
    min_instance_voxels: int = 8
    min_pixels: int = 16
    max_points: int = 20000
    max_upsample: int = 2
    planar: PlanarCompletionConfig | None = field(default_factory=PlanarCompletionConfig)

    def __post_init__(self) -> None:
        if not (isinstance(self.max_upsample, int) and self.max_upsample >= 1):
            raise ValueError(f"max_upsample: expected an integer >= 1, got {self.max_upsample!r}")
        if self.max_crop < 8:
            raise ValueError(f"max_crop: expected >= 8 pixels, got {self.max_crop}")


class InstanceReconstruction(NamedTuple):
    """Result of :func:`reconstruct_instance`.

    Attributes:
        points: ``(P, 3)`` in the instance's frame (world, or the track's object frame).
        normals: ``(P, 3)`` unit normals in that frame.
        colors: ``(P, 3)`` RGB in [0, 1].
        spacing: ``(P,)`` pixel footprint of each point (metres per pixel at its depth).
        track: the track id when the instance moves (points in its frame), else None.
        views: the group: the reference first, then the supporting views.
        depth: per group member, ``(1, H, W)`` consistent MVS depth in its full image (0 elsewhere),
            usable as a depth prior.
        normal: per group member, ``(3, H, W)`` MVS normals (camera frame), zeros elsewhere.
        reason: ``"ok"`` or why nothing (or little) was reconstructed.
    """

    points: torch.Tensor
    normals: torch.Tensor
    colors: torch.Tensor
    spacing: torch.Tensor
    track: int | None
    views: list[int]
    depth: list[torch.Tensor]
    normal: list[torch.Tensor]
    reason: str


@dataclass
class VisibilityIndex:
    """Voxel grids, labels and covisibility of a scene, built once by :func:`build_visibility_index`.

    Attributes:
        scene: the scene.
        cameras: all views' cameras (world frame).
        grid: static voxel grid (world frame).
        labels: ``(M,)`` instance label of each static voxel.
        covis: view selection input over the static voxels.
        track_grids: track id → voxel grid in the object's frame.
        track_covis: track id → view selection input in the object's frame.
        allowed: ``(V,)`` bool, views that may support (the training views).
        zbuffer: settings of the z-buffer.
    """

    scene: Scene
    cameras: Cameras
    grid: VoxelGrid
    labels: torch.Tensor
    covis: Covisibility
    track_grids: dict[int, VoxelGrid]
    track_covis: dict[int, Covisibility]
    allowed: torch.Tensor
    zbuffer: ZBufferConfig = field(default_factory=ZBufferConfig)
    _rasters: dict[int, tuple[torch.Tensor, torch.Tensor]] = field(default_factory=dict, repr=False)
    _images: dict[int, torch.Tensor] = field(default_factory=dict, repr=False)
    _instances: dict[int, torch.Tensor] = field(default_factory=dict, repr=False)
    cell_size: float = 10.0
    grow: int = 6
    _cells: torch.Tensor | None = field(default=None, repr=False)
    _corners: dict[int, torch.Tensor] = field(default_factory=dict, repr=False)
    _voxel_depths: dict[int, tuple[torch.Tensor, torch.Tensor]] = field(default_factory=dict, repr=False)

    def image(self, view: int, factor: int = 1) -> torch.Tensor:
        """``(3, H, W)`` image of a view (cached), or ``factor`` times finer (re-read, not cached)."""
        if factor != 1:
            h, w = self.cameras.image_size
            return self.scene.load_images([view], size=(h * factor, w * factor))[0]
        if view not in self._images:
            self._images[view] = self.scene.load_images([view])[0]
        return self._images[view]

    @property
    def derives_instances(self) -> bool:
        """True when the scene has no instance maps and :meth:`instances` derives them."""
        return any(v.instances is None for v in self.scene.views)

    def instances(self, view: int) -> torch.Tensor:
        """``(H, W)`` instance map of a view (cached).

        The scene's own map when it has one; otherwise :func:`derive_instance_map` (static
        voxel cells plus projected track boxes), which stands in for a segmentation network.
        """
        if view not in self._instances:
            if self.scene.views[view].instances is not None:
                self._instances[view] = self.scene.load_instances([view])[0]
            else:
                self._instances[view] = derive_instance_map(self, view)
        return self._instances[view]

    def classes(self) -> dict[int, str]:
        """Instance id → class name, including derived static cells (``"static"``)."""
        out = dict(self.scene.classes())
        if self.derives_instances:
            out.update(dict.fromkeys(self.cell_ids().unique().tolist(), "static"))
        return out

    def box_corners(self, track: int) -> torch.Tensor:
        """``(8, 3)`` box corners of a track in its object frame (cached: a mesh is read once)."""
        if track not in self._corners:
            self._corners[track] = _box_corners(self.scene.tracks[track])
        return self._corners[track]

    def cell_ids(self) -> torch.Tensor:
        """``(M,)`` derived instance id of each static voxel: its ``cell_size`` ground cell."""
        if self._cells is None:
            xy = torch.floor(self.grid.centers[:, :2] / self.cell_size).long()
            _, cell = torch.unique(xy, dim=0, return_inverse=True)
            first = max([0, *self.scene.tracks, *self.scene.classes()]) + 1
            self._cells = cell + first
        return self._cells

    def voxel_raster(self, view: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Static voxel z-buffer of a view: depth ``(1, H, W)`` and index ``(H, W)`` (cached)."""
        if view not in self._rasters:
            r = rasterize_voxels(self.grid, self.cameras[view], [view], self.zbuffer)
            self._rasters[view] = (r.depth[0], r.index[0])
        return self._rasters[view]

    def voxel_depth(self, view: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Voxel depth ``(1, H, W)`` of a view from the static grid and every moving object's grid.

        Moving objects are rasterised in their own frame at the view's timestamp; the nearest
        voxel surface wins. Cached per view.

        Returns:
            ``(depth, label)``: the nearest voxel surface (0 where empty) and the instance label of
            its voxel (``(H, W)`` int64, 0 where empty; a track's id on its voxels).
        """
        if view in self._voxel_depths:
            return self._voxel_depths[view]
        depth, vidx = self.voxel_raster(view)
        label = torch.where(vidx >= 0, self.labels[vidx.clamp(min=0)], torch.zeros_like(vidx))
        depth = depth.clone()
        fpos = self.scene.view_frame_position(view)
        cams = self.cameras[view]
        for tid, grid in self.track_grids.items():
            track = self.scene.tracks[tid]
            if not bool(track.valid[fpos]):
                continue
            o2w = track.object_to_world[fpos].to(cams.world_to_cam)
            obj_cams = Cameras(cams.K, cams.world_to_cam @ o2w[None], cams.image_size)
            r = rasterize_voxels(grid, obj_cams, config=self.zbuffer)
            closer = (r.depth[0] > 0) & ((depth == 0) | (r.depth[0] < depth))
            depth = torch.where(closer, r.depth[0], depth)
            label = torch.where(closer[0], torch.full_like(label, tid), label)
        self._voxel_depths[view] = (depth, label)
        return depth, label

    def object_cameras(self, track: int) -> torch.Tensor:
        """``(V, 4, 4)`` object-to-camera transforms of every view for a track."""
        t = self.scene.tracks[track]
        pos = torch.tensor([self.scene.frame_position(v.frame) for v in self.scene.views])
        return self.cameras.world_to_cam @ t.object_to_world[pos].to(self.cameras.world_to_cam)


def _covis(grid: VoxelGrid, world_to_cam: torch.Tensor, scene: Scene) -> Covisibility:
    cam_ids = torch.tensor([scene.camera_names.index(v.camera) for v in scene.views])
    frame_ids = torch.tensor([v.frame for v in scene.views])
    return Covisibility.from_csr(
        grid.vis_indptr, grid.vis_views, grid.centers, world_to_cam, cam_ids, frame_ids
    )


def _box_corners(track) -> torch.Tensor:
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


def derive_instance_map(index: VisibilityIndex, view: int) -> torch.Tensor:
    """An instance map for a scene without one, from the voxel index map and the tracks.

    Static pixels take the id of their voxel's ground cell (``index.cell_size`` metres square,
    :meth:`VisibilityIndex.cell_ids`); pixels without a voxel take the nearest labelled pixel's id
    within ``index.grow`` pixels (so MVS can extend a little beyond the LiDAR's reach), else 0.
    Tracks with a pose at the view's frame paint their projected 3D box (convex hull of its
    corners, far boxes first). Unlike a segmentation network, this cannot label structures far
    from any LiDAR point (a sign above the LiDAR's field of view): the strategy then only repairs
    geometry near what the LiDAR saw.

    Returns:
        ``(H, W)`` int64 instance ids (0 = none).
    """
    import numpy as np
    from scipy import ndimage
    from scipy.spatial import ConvexHull, QhullError
    from skimage.draw import polygon

    scene = index.scene
    _, vox = index.voxel_raster(view)
    cells = index.cell_ids()
    lab = torch.where(vox >= 0, cells[vox.clamp_min(0)], torch.zeros_like(vox)).numpy()
    if index.grow > 0 and (lab > 0).any():
        dist, (iy, ix) = ndimage.distance_transform_edt(lab == 0, return_indices=True)
        lab = np.where((lab == 0) & (dist <= index.grow), lab[iy, ix], lab)
    h, w = lab.shape
    info = scene.views[view]
    pos = scene.frame_position(info.frame)
    cam = index.cameras[view]
    boxes = []
    for tid, t in scene.tracks.items():
        if not bool(t.valid[pos]):
            continue
        corners = index.box_corners(tid)
        o2w = t.object_to_world[pos].float()
        world = corners @ o2w[:3, :3].T + o2w[:3, 3]
        uv, z = project_points(world[None], cam.K, cam.world_to_cam)
        if bool((z < 0.1).any()):  # a box across the image plane: skip rather than mis-project
            continue
        boxes.append((float(z.mean()), tid, uv[0].numpy()))
    for _, tid, uv in sorted(boxes, reverse=True):  # far first: near boxes paint over them
        try:
            hull = uv[ConvexHull(uv).vertices]
        except QhullError:
            continue
        rr, cc = polygon(hull[:, 1], hull[:, 0], shape=(h, w))
        lab[rr, cc] = tid
    return torch.from_numpy(np.ascontiguousarray(lab)).long()


def build_visibility_index(
    scene: Scene,
    voxel_size: float = 0.2,
    frames: Sequence[int] | None = None,
    zbuffer: ZBufferConfig | None = None,
) -> VisibilityIndex:
    """Voxelise the scene's LiDAR (static in world, each track in its frame) with visibility sets.

    A scene without LiDAR but with SfM points (``scene.sfm_points``: a COLMAP scene) is voxelised
    from those, and a voxel's visibility set is the union of its points' TRACK table views
    (supplement, "Visibility Reasoning"); only observations by views of ``frames`` count, and
    points observed by none of them are left out. SfM scenes are static: no track grids.

    Args:
        scene: a scene with LiDAR, or with ``sfm_points``.
        voxel_size: voxel edge (m).
        frames: frames whose LiDAR (or whose views' SfM observations) are used (default: the
            training frames, or every frame without a split).
        zbuffer: z-buffer settings for the per-view voxel depth.

    Returns:
        The :class:`VisibilityIndex`.

    Raises:
        ValueError: if there are no static points to voxelise (no LiDAR and no SfM points).

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> index = build_visibility_index(load_scene(sample_scene_path()))
        >>> len(index.grid) > 1000, sorted(index.track_grids) == sorted(index.scene.tracks)
        (True, True)
    """
    has_lidar = scene.lidar_loader is not None
    if has_lidar:
        acc = accumulate_lidar(scene, frames)
        points, point_views, instance = acc.points, acc.point_views, acc.instance
        what = "static LiDAR points"
    elif scene.sfm_points is not None:
        points, point_views = sfm_observations(scene, frames)
        instance = torch.zeros(points.shape[0], dtype=torch.int64)
        what = "SfM points observed by views"
    else:
        raise ValueError(
            f"scene {scene.name!r}: no LiDAR and no SfM points (scene.sfm_points) to build the voxel "
            "visibility from"
        )
    if points.shape[0] == 0:
        raise ValueError(f"scene {scene.name!r}: no {what} of frames {frames}")
    grid = voxelize(points, voxel_size, point_views, scene.num_views)
    labels = voxel_labels(grid.point_to_voxel, instance, len(grid))
    cameras = scene.cameras()
    allowed = torch.zeros(scene.num_views, dtype=torch.bool, device=cameras.K.device)
    allowed[scene.train_views] = True
    index = VisibilityIndex(
        scene,
        cameras,
        grid,
        labels,
        _covis(grid, cameras.world_to_cam, scene),
        {},
        {},
        allowed,
        zbuffer or ZBufferConfig(),
    )
    for tid in scene.tracks if has_lidar else ():
        tacc = accumulate_lidar(scene, frames, track_id=tid)
        if tacc.points.shape[0] < 3:
            continue
        tgrid = voxelize(tacc.points, voxel_size, tacc.point_views, scene.num_views)
        index.track_grids[tid] = tgrid
        index.track_covis[tid] = _covis(tgrid, index.object_cameras(tid), scene)
    return index


def sfm_observations(
    scene: Scene, frames: Sequence[int] | None = None
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


def _crops(
    masks: Sequence[torch.Tensor], margin: int, size: tuple[int, int], max_crop: int
) -> tuple[list[tuple[int, int]], int, int]:
    """One crop size for all masks and each crop's top-left corner.

    The size is the largest bounding box plus margin (capped); each crop is centred on its mask's
    box and clipped to the image.
    """
    hh, ww = size
    centres, hs, ws = [], [], []
    for m in masks:
        ys, xs = m.nonzero(as_tuple=True)
        centres.append(((int(ys.min()) + int(ys.max())) // 2, (int(xs.min()) + int(xs.max())) // 2))
        hs.append(int(ys.max()) - int(ys.min()) + 1 + 2 * margin)
        ws.append(int(xs.max()) - int(xs.min()) + 1 + 2 * margin)
    ch, cw = min(max(hs), max_crop, hh), min(max(ws), max_crop, ww)
    corners = [(min(max(cy - ch // 2, 0), hh - ch), min(max(cx - cw // 2, 0), ww - cw)) for cy, cx in centres]
    return corners, ch, cw


def _upsample_factor(scene: Scene, ch: int, cw: int, cfg: ReconstructConfig) -> int:
    """The integer factor a crop of ``ch x cw`` pixels is matched at (see ``max_upsample``)."""
    native = int(1.0 / scene.scale + 1e-6)  # the files' resolution
    return max(1, min(cfg.max_upsample, native, cfg.max_crop // max(ch, cw, 1)))


def _repeat(x: torch.Tensor, f: int) -> torch.Tensor:
    """Nearest upsampling of the last two dims by ``f`` (pixel (y, x) -> block (fy.., fx..))."""
    return x if f == 1 else x.repeat_interleave(f, -2).repeat_interleave(f, -1)


def _pool_valid(x: torch.Tensor, valid: torch.Tensor, f: int, unit: bool = False) -> torch.Tensor:
    """``(C, H, W)`` → ``(C, H/f, W/f)``: the mean of the valid pixels of each ``f x f`` block.

    Zero where fewer than half are valid (``unit``: renormalised, for normals); at ``f = 1``, ``x``
    with zeros outside ``valid``.
    """
    if f == 1:
        return torch.where(valid, x, torch.zeros_like(x))
    v = valid.to(x.dtype)
    cnt = F.avg_pool2d(v[None], f)[0]
    out = F.avg_pool2d((x * v)[None], f)[0] / cnt.clamp(min=1e-6)
    if unit:
        out = F.normalize(out, dim=0)
    return torch.where(cnt >= 0.5, out, torch.zeros_like(out))


def _shift_K(K: torch.Tensor, x0: int, y0: int) -> torch.Tensor:
    K = K.clone()
    K[..., 0, 2] -= x0
    K[..., 1, 2] -= y0
    return K


class _InstanceFrame(NamedTuple):
    """Step 1's result: where the instance is matched and which voxels stand for it."""

    covis: Covisibility
    voxels: torch.Tensor  # (M,) bool
    world_to_cam: torch.Tensor  # (V, 4, 4): world (static) or object frame (track) to each view
    allowed: torch.Tensor  # (V,) bool: views that may support


class _Crops(NamedTuple):
    """Step 3's input: the group's images and masks cropped around the instance, at factor ``f``."""

    members: list[int]  # group positions whose instance mask is large enough to be a reference
    images: torch.Tensor  # (G, 3, H*f, W*f) full images of the group
    masks: list[torch.Tensor]  # per group view (H*f, W*f): the instance
    regions: torch.Tensor  # (G, 1, H*f, W*f): where sources may match (static or the object)
    K: torch.Tensor  # (G, 3, 3) at factor f
    corners: list[tuple[int, int]]  # per member: top-left of its crop, at factor f
    size: tuple[int, int]  # crop (ch, cw) at factor f
    corners_lo: list[tuple[int, int]]  # the same at the scene's resolution
    size_lo: tuple[int, int]
    factor: int


def _instance_frame(
    index: VisibilityIndex, ref: int, instance: int, track: int | None, cfg: ReconstructConfig
) -> _InstanceFrame | str:
    """Step 1: the instance's voxels (their visibility sets are the candidate views) and its frame.

    A moving object: all voxels of its own grid, in its frame, views where its pose is known. A
    static instance with almost no voxels of its own (the LiDAR missed it): the voxels the z-buffer
    sees *through* it in the reference view, whose observers also look at the missing surface.
    Returns the reason as a string when there is nothing to match.
    """
    scene = index.scene
    dev = index.cameras.K.device
    if track is not None:
        if track not in index.track_covis:
            return "no_lidar_on_track"
        covis = index.track_covis[track]
        valid = scene.tracks[track].valid.to(dev)
        pos = torch.tensor([scene.frame_position(v.frame) for v in scene.views], device=dev)
        return _InstanceFrame(
            covis,
            torch.ones(covis.num_voxels, dtype=torch.bool, device=dev),
            index.object_cameras(track),
            index.allowed & valid[pos],
        )
    voxels = index.labels == instance
    if int(voxels.sum()) < cfg.min_instance_voxels:
        _, vidx = index.voxel_raster(ref)
        through = torch.unique(vidx[(index.instances(ref) == instance) & (vidx >= 0)])
        voxels = voxels.clone()
        voxels[through] = True
    if int(voxels.sum()) == 0:
        return "no_voxels"
    return _InstanceFrame(index.covis, voxels, index.cameras.world_to_cam, index.allowed)


def _crop_group(
    index: VisibilityIndex, group: list[int], instance: int, track: int | None, cfg: ReconstructConfig
) -> _Crops | str:
    """Step 3a: crops around the instance in each group view, small instances at a finer resolution.

    Sources match only inside their region: static pixels for a static instance, the object's own
    pixels for a moving one.
    """
    scene = index.scene
    h, w = index.cameras.image_size
    masks = [index.instances(v) == instance for v in group]
    members = [i for i, m in enumerate(masks) if int(m.sum()) >= cfg.min_pixels]
    if len(members) < 2:
        return "instance_seen_in_fewer_than_two_group_views"
    corners, ch, cw = _crops([masks[i] for i in members], cfg.margin, (h, w), cfg.max_crop)

    def region(v: int) -> torch.Tensor:
        ins = index.instances(v)
        if track is not None:
            return ins == instance
        return ~torch.isin(ins, torch.tensor(sorted(scene.tracks), dtype=ins.dtype, device=ins.device))

    regions = torch.stack([region(v) for v in group])[:, None]
    K = index.cameras.K[group]
    f = _upsample_factor(scene, ch, cw, cfg)
    corners_lo, size_lo = corners, (ch, cw)
    if f > 1:
        masks = [_repeat(m, f) for m in masks]
        regions = _repeat(regions, f)
        corners, ch, cw = [(y0 * f, x0 * f) for y0, x0 in corners], ch * f, cw * f
        K = scale_intrinsics(K, f)
    images = torch.stack([index.image(v, f) for v in group])
    return _Crops(members, images, masks, regions, K, corners, (ch, cw), corners_lo, size_lo, f)


def _match(
    crops: _Crops,
    group: list[int],
    world_to_cam: torch.Tensor,
    depth_range: tuple[float, float],
    cfg: ReconstructConfig,
    render_prior: Callable[[int], tuple[torch.Tensor, torch.Tensor]] | None,
):
    """Step 3b: PatchMatch on the group, each member's crop as reference against all other views."""
    ch, cw = crops.size
    f = crops.factor
    ref_imgs, ref_masks, ref_K, init_d, init_n = [], [], [], [], []
    for i, (y0, x0) in zip(crops.members, crops.corners):
        ref_imgs.append(crops.images[i, :, y0 : y0 + ch, x0 : x0 + cw])
        ref_masks.append(crops.masks[i][None, y0 : y0 + ch, x0 : x0 + cw])
        ref_K.append(_shift_K(crops.K[i], x0, y0))
        if render_prior is not None:
            d, n = render_prior(group[i])
            d, n = _repeat(d, f), _repeat(n, f)
            init_d.append(d[:, y0 : y0 + ch, x0 : x0 + cw])
            init_n.append(n[:, y0 : y0 + ch, x0 : x0 + cw])
    others = [[j for j in range(len(group)) if j != i] for i in crops.members]
    res = patchmatch(
        torch.stack(ref_imgs),
        torch.stack([crops.images[o] for o in others]),
        torch.stack(ref_K),
        torch.stack([crops.K[o] for o in others]),
        world_to_cam[crops.members],
        torch.stack([world_to_cam[o] for o in others]),
        depth_range,
        cfg.patchmatch,
        init_depth=torch.stack(init_d) if init_d else None,
        init_normal=torch.stack(init_n) if init_n else None,
        mask=torch.stack(ref_masks),
        src_masks=torch.stack([crops.regions[o] for o in others]),
    )
    return res, torch.stack(ref_imgs), torch.stack(ref_masks), torch.stack(ref_K)


def _consistent(
    res,
    crops: _Crops,
    group: list[int],
    world_to_cam: torch.Tensor,
    ref_imgs: torch.Tensor,
    ref_masks: torch.Tensor,
    ref_K: torch.Tensor,
    planar: bool,
    cfg: ReconstructConfig,
    generator: torch.Generator | None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Step 4: keep the pixels that other members confirm; planar completion of static instances.

    Returns ``(depth, normal, keep)``: ``(b, 1, ch, cw)``, ``(b, 3, ch, cw)`` camera frame, bool.
    """
    members = crops.members
    w2c = world_to_cam[members]
    depth = torch.where(res.mask, res.depth, torch.zeros_like(res.depth))
    b = len(members)
    src = [[j for j in range(b) if j != i] for i in range(b)]
    cons = geometric_consistency(
        depth,
        ref_K,
        w2c,
        torch.stack([depth[o] for o in src]),
        torch.stack([ref_K[o] for o in src]),
        torch.stack([w2c[o] for o in src]),
        cfg.max_reproj_error,
        cfg.max_rel_depth,
        min(cfg.min_consistent_views, b - 1),
    )
    keep = cons.mask & res.mask
    normal = res.normal
    if planar:
        normal = res.normal.clone()
        c2w = invert_rigid(w2c)
        for k in range(b):
            o = [j for j in range(len(group)) if j != members[k]]
            d_k, n_k, add = complete_planar(
                depth[k], keep[k], ref_masks[k], ref_imgs[k], ref_K[k], c2w[k], crops.images[o],
                torch.stack([crops.masks[j] for j in o])[:, None], crops.K[o], world_to_cam[o], cfg.planar,
                generator, res.normal[k],
            )  # fmt: skip
            depth[k] = d_k
            keep[k] |= add
            normal[k] = torch.where(add, n_k[:, None, None].expand_as(normal[k]), normal[k])
    return depth, normal, keep


def _depth_priors(
    depth: torch.Tensor, normal: torch.Tensor, keep: torch.Tensor, crops: _Crops, size: tuple[int, int]
) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Step 6: each member's consistent depth and normals in its full image at the scene's resolution."""
    h, w = size
    ch, cw = crops.size_lo
    full_depth, full_normal = [], []
    for k, (y0, x0) in enumerate(crops.corners_lo):
        fd = depth.new_zeros(1, h, w)
        fn = normal.new_zeros(3, h, w)
        fd[:, y0 : y0 + ch, x0 : x0 + cw] = _pool_valid(depth[k], keep[k], crops.factor)
        fn[:, y0 : y0 + ch, x0 : x0 + cw] = _pool_valid(normal[k], keep[k], crops.factor, unit=True)
        full_depth.append(fd)
        full_normal.append(fn)
    return full_depth, full_normal


@torch.no_grad()
def reconstruct_instance(
    index: VisibilityIndex,
    ref: int,
    instance: int,
    config: ReconstructConfig | None = None,
    generator: torch.Generator | None = None,
    render_prior: Callable[[int], tuple[torch.Tensor, torch.Tensor]] | None = None,
) -> InstanceReconstruction:
    """Reconstruct an instance seen in view ``ref`` from selected supporting views by PatchMatch.

    Not differentiable (a search). The steps (see the module docstring): the instance's voxels and
    frame, view selection (:func:`~vadgs.select.select_views`), crops, PatchMatch
    (:func:`~vadgs.mvs.patchmatch`), consistency (:func:`~vadgs.mvs.geometric_consistency`) and
    planar completion (:func:`~vadgs.mvs.complete_planar`), fusion
    (:func:`~vadgs.mvs.fuse_depth_maps`, one point per consistent pixel), depth priors. On the
    device of ``index``.

    Args:
        index: the scene's :class:`VisibilityIndex`.
        ref: the reference view.
        instance: the instance id (a track id for a moving object: matched in its own frame).
        config: :class:`ReconstructConfig`.
        generator: seeds the selection noise ``ξ`` (a CPU generator).
        render_prior: optional ``view -> (depth (1, H, W), normal (3, H, W))`` rendered by the
            Gaussians (camera frame normals, in the instance's frame of reference), the
            PatchMatch initialisation; ``0`` where unknown.

    Returns:
        :class:`InstanceReconstruction` (possibly empty, with the reason).
    """
    cfg = config or ReconstructConfig()
    scene = index.scene
    if not 0 <= ref < scene.num_views:
        raise ValueError(f"ref: expected a view in [0, {scene.num_views}), got {ref}")
    track = instance if instance in scene.tracks else None
    dev = index.cameras.K.device
    empty3 = torch.zeros(0, 3, device=dev)

    def nothing(reason: str, views: list[int] | None = None) -> InstanceReconstruction:
        return InstanceReconstruction(
            empty3, empty3, empty3, torch.zeros(0, device=dev), track, views or [ref], [], [], reason
        )

    if int((index.instances(ref) == instance).sum()) < cfg.min_pixels:
        return nothing("instance_too_small_in_reference")
    frame = _instance_frame(index, ref, instance, track, cfg)  # 1. voxels and frame
    if isinstance(frame, str):
        return nothing(frame)
    sel = select_views(ref, frame.covis.restrict(frame.voxels), cfg.selection, generator, frame.allowed)  # 2.
    group = [ref, *sel.views.tolist()]
    if len(group) < 2:
        return nothing(f"selection:{sel.reason}")
    crops = _crop_group(index, group, instance, track, cfg)  # 3. crops and PatchMatch
    if isinstance(crops, str):
        return nothing(crops, group)
    w2c = frame.world_to_cam[group]
    # depth range from the instance's voxels as seen by the reference
    cen = frame.covis.voxel_centers[frame.voxels]
    z = cen @ w2c[0, 2, :3] + w2c[0, 2, 3]
    z = z[z > 0.1]
    lo, hi = (float(z.min()) * 0.5, float(z.max()) * 2.0) if z.numel() else (0.5, 150.0)
    res, ref_imgs, ref_masks, ref_K = _match(
        crops, group, w2c, (max(lo, 0.2), max(hi, lo * 4, 1.0)), cfg, render_prior
    )
    planar = cfg.planar is not None and track is None  # a car is not planar
    depth, normal, keep = _consistent(
        res, crops, group, w2c, ref_imgs, ref_masks, ref_K, planar, cfg, generator
    )  # 4.
    members_w2c = w2c[crops.members]
    fused = fuse_depth_maps(  # 5. one point per consistent pixel, in the instance's frame
        depth, ref_imgs, ref_K, members_w2c, normal, keep, FusionConfig(min_views=0, deduplicate=False)
    )
    seed_w2c, seed_K = members_w2c[fused.view_index], ref_K[fused.view_index]
    z_seed = (seed_w2c[:, 2, :3] * fused.points).sum(-1) + seed_w2c[:, 2, 3]
    points, normals, colors, spacing = fused.points, fused.normals, fused.colors, z_seed / seed_K[:, 0, 0]
    if points.shape[0] > cfg.max_points:
        g = generator or torch.Generator().manual_seed(0)
        sub = torch.randperm(points.shape[0], generator=g)[: cfg.max_points].to(dev)
        points, normals, colors, spacing = points[sub], normals[sub], colors[sub], spacing[sub]
    full_depth, full_normal = _depth_priors(depth, normal, keep, crops, index.cameras.image_size)  # 6.
    views = [group[i] for i in crops.members]
    reason = "ok" if points.shape[0] else "no_consistent_pixels"
    return InstanceReconstruction(
        points, normals, colors, spacing, track, views, full_depth, full_normal, reason
    )
