"""The visibility index: what VAD-GS knows about a scene's voxels and views, built once.

:class:`VisibilityIndex` holds the static voxel grid (world frame) and one grid per moving object
(its own frame), each voxel's instance label and visibility set (the views that observed it: the
LiDAR frames, or COLMAP's TRACK table), and the cameras of every view, as
:class:`~vadgs.select.Covisibility` objects for view selection; per-view maps (voxel depth,
pixel → voxel index, instance masks) are computed on demand and kept in a bounded
:class:`~vadgs.data.cache.ByteCache` (1 GiB by default: every view of the street scenes at
240×144; some hundred views at 1920×1280). :func:`build_visibility_index` builds it from
:class:`~vadgs.train.vad.inputs.VisibilityInputs` (or a vadgs scene), its lengths scaled to the
scene (:mod:`vadgs.train.vad.lengths`), derived instance maps where a dataset has no masks.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
import torch.nn.functional as F

from vadgs.checks import float_field
from vadgs.data.cache import ByteCache
from vadgs.geometry.camera import Cameras, invert_rigid
from vadgs.geometry.ground import ground_cells, ground_frame, points_in_frame, sample_rows
from vadgs.geometry.voxel import PointChunk, VoxelGrid, voxelize, voxelize_chunks
from vadgs.geometry.zbuffer import ZBufferConfig, rasterize_voxels
from vadgs.select.covisibility import Covisibility
from vadgs.train.vad.inputs import VisibilityInputs
from vadgs.train.vad.instances import box_corners, derive_instance_map
from vadgs.train.vad.lengths import REFERENCE_DEPTH, scene_lengths

__all__ = [
    "GROUND_FRAME_POINTS",
    "VisibilityIndex",
    "build_visibility_index",
    "own_instance_depth",
]


def own_instance_depth(depth: torch.Tensor, label: torch.Tensor, instances: torch.Tensor) -> torch.Tensor:
    """``depth`` ``(1, H, W)`` where the voxel's ``label`` is the pixel's own instance, else 0.

    ``label`` and ``instances`` ``(H, W)``: :meth:`VisibilityIndex.own_voxel_depth`'s map.
    """
    return torch.where((label == instances)[None], depth, torch.zeros_like(depth))


@dataclass
class VisibilityIndex:
    """Voxel grids, labels and covisibility of a scene, built once by :func:`build_visibility_index`.

    What is computed per view (voxel z-buffer and depth, instance map, image) is kept in
    ``view_cache``, a byte-bounded :class:`~vadgs.data.cache.ByteCache`.

    Attributes:
        inputs: the :class:`~vadgs.train.vad.inputs.VisibilityInputs` it was built from (loaders,
            tracks, classes, per-view camera and frame).
        cameras: all views' cameras (world frame).
        grid: static voxel grid, in the scene's own ground frame (``static_to_world``): its cubes
            and cells turn with the scene, so a rotated, shifted or rescaled copy of a scene
            (gsplat's normalised world) gets the same voxels.
        labels: ``(M,)`` instance label of each static voxel.
        covis: view selection input over the static voxels.
        track_grids: track id → voxel grid in the object's frame.
        track_covis: track id → view selection input in the object's frame.
        allowed: ``(V,)`` bool, views that may support (the training views).
        zbuffer: settings of the z-buffer.
        sizes: per view ``(H, W)`` when the views differ in size (a rig of cameras of different
            sizes, a photo collection), else None. ``cameras.image_size`` is then the largest, and
            every per-view map (voxel depth, index, instance map, image) is padded at its bottom
            and right to it (depth 0, index -1, instance 0: no pixel there); intrinsics are
            unchanged by such padding. :meth:`size` is a view's own size, :meth:`valid` its area.
        cell_size: ground-cell edge of derived instances (scenes without instance maps).
        grow: pixels a derived instance map grows beyond the voxels.
        view_cache: the per-view cache (``build_visibility_index(cache_mb=)``).
        static_to_world: ``(4, 4)`` rigid transform of the static grid's frame to the world
            (:func:`ground_frame`: the cameras' up, the points' principal ground axes, their
            median); the identity for a grid built in the world.
        scene_depth: the scene's length unit (``VisibilityInputs.median_view_depth``; 10 for
            vadgs's scenes) that the lengths left unset were derived from
            (:data:`~vadgs.train.vad.lengths.LENGTHS`).
    """

    inputs: VisibilityInputs
    cameras: Cameras
    grid: VoxelGrid
    labels: torch.Tensor
    covis: Covisibility
    track_grids: dict[int, VoxelGrid]
    track_covis: dict[int, Covisibility]
    allowed: torch.Tensor
    zbuffer: ZBufferConfig = field(default_factory=ZBufferConfig)
    sizes: tuple[tuple[int, int], ...] | None = None
    cell_size: float = 10.0
    grow: int = 6
    view_cache: ByteCache = field(default_factory=ByteCache, repr=False)
    scene_depth: float = REFERENCE_DEPTH
    static_to_world: torch.Tensor = field(default_factory=lambda: torch.eye(4))
    _cells: torch.Tensor | None = field(default=None, repr=False)
    _corners: dict[int, torch.Tensor] = field(default_factory=dict, repr=False)

    def size(self, view: int) -> tuple[int, int]:
        """``(H, W)`` of a view (its own, before padding)."""
        return self.sizes[view] if self.sizes is not None else self.cameras.image_size

    def camera(self, view: int) -> Cameras:
        """The camera of one view at its own image size."""
        return Cameras(
            self.cameras.K[view : view + 1], self.cameras.world_to_cam[view : view + 1], self.size(view)
        )

    def cut_by_border(self, view: int, instance: int) -> bool:
        """Whether the instance's mask in ``view`` touches the border of the view's own image.

        Such a view shows only part of the instance (e.g. the top of a sign above the frame of a
        close view). An instance that is not in the view is not cut.
        """
        return self.cut_by_border_views([view], instance)[0]

    def cut_by_border_views(self, views: Sequence[int], instance: int) -> list[bool]:
        """:meth:`cut_by_border` of each of ``views``, in one host read (views of a size batched)."""
        return [bool(f) for f in self.border_cuts(views, instance).tolist()] if len(views) else []

    def border_cuts(self, views: Sequence[int], instance: int) -> torch.Tensor:
        """``(len(views),)`` bool on the device: :meth:`cut_by_border` of each view (no read)."""
        by_size: dict[tuple[int, int], list[int]] = {}
        for k, v in enumerate(views):
            by_size.setdefault(self.size(v), []).append(k)
        order: list[int] = []
        parts = []
        for (h, w), ks in by_size.items():
            m = torch.stack([self.instances(views[k])[:h, :w] for k in ks]) == instance  # (n, h, w)
            edges = torch.cat([m[:, 0], m[:, -1], m[:, :, 0], m[:, :, -1]], 1)  # (n, 2w + 2h)
            parts.append(edges.any(1))
            order += ks
        dev = self.cameras.K.device
        if not parts:
            return torch.zeros(0, dtype=torch.bool, device=dev)
        out = torch.zeros(len(views), dtype=torch.bool, device=parts[0].device)
        out[torch.tensor(order, device=out.device)] = torch.cat(parts)
        return out

    def valid(self, view: int) -> torch.Tensor:
        """``(H, W)`` bool at the padded size: the view's own pixels."""
        h, w = self.size(view)
        out = torch.zeros(self.cameras.image_size, dtype=torch.bool, device=self.cameras.K.device)
        out[:h, :w] = True
        return out

    def pad(self, x: torch.Tensor, value: float = 0, factor: int = 1) -> torch.Tensor:
        """A view's map ``(..., h, w)`` padded at the bottom and right to the index's size (x ``factor``)."""
        H, W = (n * factor for n in self.cameras.image_size)
        h, w = x.shape[-2:]
        return x if (h, w) == (H, W) else F.pad(x, (0, W - w, 0, H - h), value=value)

    def image(self, view: int, factor: int = 1) -> torch.Tensor:
        """``(3, H, W)`` image of a view (cached), or ``factor`` times finer (re-read, not cached)."""
        if factor != 1:
            h, w = self.size(view)
            return self.pad(self.inputs.load_image(view, (h * factor, w * factor)), factor=factor)
        return self.view_cache.get(("image", view), lambda: self.pad(self.inputs.load_image(view, None)))

    @property
    def derives_instances(self) -> bool:
        """True when the scene has no instance maps and :meth:`instances` derives them."""
        return self.inputs.derives_instances

    def instances(self, view: int) -> torch.Tensor:
        """``(H, W)`` instance map of a view (cached).

        The scene's own map when it has one; otherwise :func:`derive_instance_map` (static
        voxel cells plus projected track boxes), which stands in for a segmentation network.
        """

        def make() -> torch.Tensor:
            load = self.inputs.load_instances
            if load is not None and self.inputs.has_instances(view):
                return self.pad(load(view))
            return derive_instance_map(self, view)

        return self.view_cache.get(("instances", view), make)

    def classes(self) -> dict[int, str]:
        """Instance id → class name, including derived static cells (``"static"``)."""
        out = dict(self.inputs.classes)
        if self.derives_instances:
            out.update(dict.fromkeys(self.cell_ids().unique().tolist(), "static"))
        return out

    def box_corners(self, track: int) -> torch.Tensor:
        """``(8, 3)`` box corners of a track in its object frame (cached: a mesh is read once)."""
        if track not in self._corners:
            self._corners[track] = box_corners(self.inputs.tracks[track])
        return self._corners[track]

    def cell_ids(self) -> torch.Tensor:
        """``(M,)`` derived instance id of each static voxel: its ``cell_size`` ground cell.

        The cells are :func:`~vadgs.geometry.ground.ground_cells` of the voxel centres in the static
        grid's ground frame (:meth:`ground_frame`): they move with the scene, so a rotated, shifted or
        rescaled copy of it (gsplat's Parser normalisation) is cut into the same cells.
        """
        if self._cells is None:
            eye = torch.eye(3, dtype=torch.float64, device=self.grid.centers.device)
            cell = ground_cells(self.grid.centers, None, self.cell_size, (eye, eye[0] * 0))  # in the frame
            first = max([0, *self.inputs.tracks, *self.inputs.classes]) + 1
            self._cells = cell + first
        return self._cells

    def ground_frame(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The static grid's frame in the world: :func:`ground_frame` of the static points and cameras.

        Returns ``(rotation, origin)`` (float64): ``local = (x - origin) @ rotation.T``.
        """
        rot = self.static_to_world[:3, :3].double()
        return rot.T, self.static_to_world[:3, 3].double()

    def to_ground(self, points: torch.Tensor) -> torch.Tensor:
        """``(N, 3)`` world points in the static grid's frame (float64, on the points' device)."""
        rotation, origin = (x.to(points.device) for x in self.ground_frame())
        return points_in_frame(points, rotation, origin)

    def voxel_raster(self, view: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Static voxel z-buffer of a view: depth ``(1, H, W)`` and index ``(H, W)`` (cached)."""

        def make() -> tuple[torch.Tensor, torch.Tensor]:
            cam = self.camera(view)
            cam = cam.in_object_frame(self.static_to_world.to(cam.world_to_cam)[None])  # the grid's frame
            r = rasterize_voxels(self.grid, cam, [view], self.zbuffer)
            return self.pad(r.depth[0]), self.pad(r.index[0], -1)

        return self.view_cache.get(("raster", view), make)

    def observed_depth(self, view: int, track: int | None = None) -> torch.Tensor:
        """:meth:`voxel_raster`'s depth where the pixel's voxel is in the view's own visibility set, else 0.

        ``(1, H, W)``, cached: where the nearest static voxel surface is one the view's own LiDAR
        sweep (or, for a COLMAP scene, its SfM track) observed: what the view measured, not what
        the whole scan holds (a nearer voxel seen only from other frames leaves the pixel
        unmeasured). No read by the host. The reconstruction's LiDAR check
        (:func:`~vadgs.train.vad.fusion.lidar_check`) compares the MVS depth with it.

        ``track``: the same for a moving object's grid posed at the view's timestamp (its voxels
        that the view's own sweep observed, gathered with that frame's box, so a label's jitter
        does not move them), where it is the nearest voxel surface of :meth:`voxel_depth`; 0
        everywhere when its pose is unknown there. None: the static grid's.

        Raises:
            ValueError: if ``track`` is not a track of the inputs.
        """
        if track is not None:
            self._check_track(track)

        def make() -> torch.Tensor:
            if track is None:
                (depth, vidx), covis = self.voxel_raster(view), self.covis
            else:  # the track's voxels where its surface is the nearest
                depth, label, vidx = self._voxel_surface(view)
                covis, vidx = self.track_covis[track], torch.where(label == track, vidx, -1)
            seen = covis.seen_by(view).to(vidx.device)
            own = (vidx >= 0) & seen[vidx.clamp(min=0)]
            return torch.where(own[None], depth, torch.zeros_like(depth))

        return self.view_cache.get(("observed", view, track), make)

    def voxel_depth(self, view: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Voxel depth ``(1, H, W)`` of a view from the static grid and every moving object's grid.

        Moving objects are rasterised in their own frame at the view's timestamp; the nearest
        voxel surface wins. Cached per view.

        Returns:
            ``(depth, label)``: the nearest voxel surface (0 where empty) and the instance label of
            its voxel (``(H, W)`` int64, 0 where empty; a track's id on its voxels).
        """
        depth, label, _ = self._voxel_surface(view)
        return depth, label

    def own_voxel_depth(self, view: int, tracks: bool = True) -> torch.Tensor:
        """:meth:`voxel_depth` only where the voxel is of the pixel's own instance, else 0: ``(1, H, W)``.

        The geometric losses' voxel depth prior (:func:`~vadgs.train.vad.priors.view_targets`):
        elsewhere the z-buffer sees through missing geometry. ``tracks=False``: the static voxels
        only (a moving object's pixels get none). Cached per view.
        """

        def make() -> torch.Tensor:
            depth, label = self.voxel_depth(view)
            if not tracks and self.track_grids:
                ids = torch.tensor(sorted(self.track_grids), dtype=label.dtype, device=label.device)
                label = label.masked_fill(torch.isin(label, ids), -1)  # no instance is -1
            return own_instance_depth(depth, label, self.instances(view))

        return self.view_cache.get(("own_voxel_depth", view, tracks), make)

    def _voxel_surface(self, view: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`voxel_depth`'s ``(depth, label)`` and the nearest voxel's id in its own grid (cached)."""
        return self.view_cache.get(("voxel_surface", view), lambda: self._make_voxel_surface(view))

    def _make_voxel_surface(self, view: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        depth, vidx = self.voxel_raster(view)
        label = torch.where(vidx >= 0, self.labels[vidx.clamp(min=0)], torch.zeros_like(vidx))
        depth, vidx = depth.clone(), vidx.clone()  # not the static z-buffer's cached tensors
        fpos = self.inputs.frame_position(view)
        cams = self.camera(view)
        for tid, grid in self.track_grids.items():
            track = self.inputs.tracks[tid]
            if not bool(track.valid[fpos]):
                continue
            o2w = track.object_to_world[fpos].to(cams.world_to_cam)
            obj_cams = Cameras(cams.K, cams.world_to_cam @ o2w[None], cams.image_size)
            r = rasterize_voxels(grid, obj_cams, config=self.zbuffer)
            d, i = self.pad(r.depth[0]), self.pad(r.index[0], -1)
            closer = (d > 0) & ((depth == 0) | (d < depth))
            depth = torch.where(closer, d, depth)
            label = torch.where(closer[0], torch.full_like(label, tid), label)
            vidx = torch.where(closer[0], i, vidx)
        return depth, label, vidx

    def seen_voxels(self, view: int, track: int | None = None) -> torch.Tensor:
        """Sorted ids of the voxels a view's z-buffer shows (occlusion included; cached).

        ``track``: of that moving object's grid (its own frame), rasterised at the view's
        timestamp (none when its pose is unknown there or it has no LiDAR point), where it is the
        nearest voxel surface of :meth:`voxel_depth` (not behind static voxels or another object);
        None: the static grid's.

        Raises:
            ValueError: if ``track`` is not a track of the inputs.
        """
        if track is None:

            def make() -> torch.Tensor:
                vidx = self.voxel_raster(view)[1]
                return torch.unique(vidx[vidx >= 0])

            return self.view_cache.get(("seen", view), make)
        self._check_track(track)
        return self.view_cache.get(("seen_track", view, track), lambda: self._seen_track(view, track))

    def _check_track(self, track: int) -> None:
        if track not in self.inputs.tracks:
            raise ValueError(f"track: expected one of the tracks {sorted(self.inputs.tracks)}, got {track}")

    def _seen_track(self, view: int, track: int) -> torch.Tensor:
        _, label, vidx = self._voxel_surface(view)
        return torch.unique(vidx[(label == track) & (vidx >= 0)])  # where its surface is the nearest

    def seen_covis(
        self, voxels: torch.Tensor, views: Sequence[int], track: int | None = None
    ) -> Covisibility:
        """Covisibility of some voxels where ``views`` see them: visibility sets or z-buffer.

        A voxel is seen by one of ``views`` when it is in its visibility set (the LiDAR frame's
        points, the TRACK table) or its voxel z-buffer shows it (:meth:`seen_voxels`); by any other
        view only through its visibility set. A far facade that the LiDAR hit only from closer
        frames is thus seen by a reference in front of it, which its visibility sets do not say;
        so is a moving car whose points came from other frames (its grid gathers them all).

        Args:
            voxels: ``(M,)`` bool over the grid: the voxels kept (e.g. one instance's).
            views: the views whose z-buffer counts too.
            track: a moving object's id: its grid (:attr:`track_covis`, in its own frame); None:
                the static grid.

        Returns:
            :meth:`~vadgs.select.Covisibility.restrict` of that covisibility to ``voxels``.
        """
        covis, zbuf = (self.covis if track is None else self.track_covis[track]), set(views)
        keep = voxels.to(covis.voxel_centers.device)
        visible = []
        for v in range(covis.num_views):
            ids = covis.voxels_of(v)
            if v in zbuf:
                ids = torch.unique(torch.cat([ids, self.seen_voxels(v, track).to(ids)]))
            visible.append(ids[keep[ids]])
        out = Covisibility.from_visible(
            visible, covis.voxel_centers, covis.world_to_cam, covis.camera_ids, covis.frame_ids
        )
        return out.restrict(keep)

    def object_cameras(self, track: int) -> torch.Tensor:
        """``(V, 4, 4)`` object-to-camera transforms of every view for a track."""
        t = self.inputs.tracks[track]
        pos = torch.tensor([self.inputs.frame_position(v) for v in range(self.inputs.num_views)])
        return self.cameras.world_to_cam @ t.object_to_world[pos].to(self.cameras.world_to_cam)


def _covis(
    grid: VoxelGrid,
    world_to_cam: torch.Tensor,
    inputs: VisibilityInputs,
    to_world: torch.Tensor | None = None,
) -> Covisibility:
    """Covisibility of a grid's voxels in the frame of ``world_to_cam``.

    ``to_world`` takes the grid's frame to that one, when the grid is in another.
    """
    cam_ids = torch.tensor(inputs.view_cameras)
    frame_ids = torch.tensor(inputs.view_frames)
    centers = grid.centers
    if to_world is not None:
        centers = centers @ to_world[:3, :3].T.to(centers) + to_world[:3, 3].to(centers)
    return Covisibility.from_csr(grid.vis_indptr, grid.vis_views, centers, world_to_cam, cam_ids, frame_ids)


#: The most points :func:`ground_frame` is measured on when building a visibility index: beyond,
#: a sample of them (:func:`~vadgs.geometry.ground.sample_rows`).
GROUND_FRAME_POINTS = 1 << 22

_CACHE_MB = float_field(0, lo_open=True)


def build_visibility_index(
    source: VisibilityInputs | Any,
    voxel_size: float | None = None,
    frames: Sequence[int] | None = None,
    zbuffer: ZBufferConfig | None = None,
    cell_size: float | None = None,
    scene_depth: float | None = None,
    cache_mb: float = 1024.0,
) -> VisibilityIndex:
    """Voxelise the LiDAR (static in world, each track in its frame) or SfM points with visibility sets.

    Inputs without LiDAR but with SfM points (:class:`~vadgs.train.vad.inputs.TrackTable`: a COLMAP
    scene, gsplat's ``Parser``) are voxelised from those, and a voxel's visibility set is the union
    of its points' TRACK table views (supplement, "Visibility Reasoning"); only observations by
    training views count (:meth:`~vadgs.train.vad.inputs.VisibilityInputs.from_scene` keeps those of
    ``frames``), and points observed by none of them are left out. SfM inputs are static: no track
    grids.

    Args:
        source: :class:`~vadgs.train.vad.inputs.VisibilityInputs`, or a vadgs
            :class:`~vadgs.data.scene.Scene` (then ``VisibilityInputs.from_scene(scene, frames)``).
        voxel_size: voxel edge; None: 0.2 at a scene depth of 10 (:func:`scene_lengths`).
        frames: for a scene, frames whose LiDAR (or whose views' SfM observations) are used
            (default: the training frames, or every frame without a split); must be None for
            inputs (their observations are already chosen).
        zbuffer: z-buffer settings for the per-view voxel depth (None: the defaults, with the near
            plane 0.1 at a scene depth of 10).
        cell_size: ground-cell edge of derived instances; None: 10 at a scene depth of 10.
        scene_depth: the scene's length unit; None: the inputs'
            (:meth:`~vadgs.train.vad.inputs.VisibilityInputs.median_view_depth`).
        cache_mb: the bound of the index's per-view cache (a :class:`~vadgs.data.cache.ByteCache`),
            in MiB: views dropped from it are recomputed identically when needed again.

    Returns:
        The :class:`VisibilityIndex`.

    Raises:
        ValueError: if there are no static points to voxelise (no LiDAR and no SfM points), or
            ``cache_mb`` is not a positive number.

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> index = build_visibility_index(load_scene(sample_scene_path()))
        >>> len(index.grid) > 1000, sorted(index.track_grids) == sorted(index.inputs.tracks)
        (True, True)
    """
    view_cache = ByteCache(_CACHE_MB("cache_mb", cache_mb) * 2**20)
    if isinstance(source, VisibilityInputs):
        if frames is not None:
            raise ValueError(f"frames: expected None with VisibilityInputs, got {list(frames)}")
        inputs = source
    else:
        inputs = VisibilityInputs.from_scene(source, frames)
    lidar = inputs.lidar
    if lidar is not None:  # frame by frame: the sweeps are never held together
        points = sample_rows((a.points for a in lidar(None, False)), GROUND_FRAME_POINTS)
        what = "static LiDAR points"
    elif inputs.sfm is not None:
        points, point_views = inputs.sfm.points, (inputs.sfm.point_idx, inputs.sfm.view_idx)
        what = "SfM points observed by views"
    else:
        raise ValueError(
            f"scene {inputs.name!r}: no LiDAR and no SfM points (scene.sfm_points) to build the voxel "
            "visibility from"
        )
    if points.shape[0] == 0:
        raise ValueError(f"scene {inputs.name!r}: no {what} of frames {frames}")
    depth = float(scene_depth) if scene_depth is not None else inputs.median_view_depth()
    lengths = scene_lengths(depth, voxel_size=voxel_size, cell_size=cell_size)
    voxel_size = lengths["voxel_size"]
    cameras, sizes = inputs.cameras, inputs.sizes
    # the static grid in the scene's own ground frame: the same voxels in any world frame
    rotation, origin = ground_frame(points, invert_rigid(cameras.world_to_cam), walls=voxel_size)
    if torch.linalg.det(rotation) < 0:  # right-handed (the sign of an axis is free)
        rotation = rotation * rotation.new_tensor([1.0, -1.0, 1.0])[:, None]
    static_to_world = torch.eye(4, dtype=torch.float64, device=rotation.device)
    static_to_world[:3, :3], static_to_world[:3, 3] = rotation.T, origin
    static_to_world = static_to_world.to(dtype=points.dtype, device=cameras.K.device)
    local = points_in_frame(points.to(rotation.device), rotation, origin).to(points)
    if lidar is None:
        grid = voxelize(local, voxel_size, point_views, inputs.num_views)
        labels = torch.zeros(len(grid), dtype=torch.int64, device=grid.coords.device)
    else:
        corner = torch.floor(local.min(0).values / voxel_size) * voxel_size  # of all points when sampled all

        def static_chunks() -> Iterator[PointChunk]:
            for a in lidar(None, True):
                p = points_in_frame(a.points.to(rotation.device), rotation, origin).to(a.points)
                yield PointChunk(p, a.point_views, a.instance)

        grid, labels = voxelize_chunks(static_chunks, voxel_size, inputs.num_views, corner)
    allowed = torch.zeros(inputs.num_views, dtype=torch.bool, device=cameras.K.device)
    allowed[list(inputs.train_views)] = True
    index = VisibilityIndex(
        inputs,
        cameras,
        grid,
        labels,
        _covis(grid, cameras.world_to_cam, inputs, static_to_world),
        {},
        {},
        allowed,
        zbuffer or ZBufferConfig(near=lengths["zbuffer_near"]),
        sizes,
        cell_size=lengths["cell_size"],
        scene_depth=depth,
        static_to_world=static_to_world,
        view_cache=view_cache,
    )
    track_lidar = lidar if lidar is not None else (lambda _tid, _views: ())
    for tid in inputs.tracks if lidar is not None else ():
        count, low = 0, None
        for a in track_lidar(tid, False):
            if a.points.shape[0]:
                count += a.points.shape[0]
                m = a.points.min(0).values
                low = m if low is None else torch.minimum(low, m)
        if count < 3 or low is None:
            continue

        def track_chunks(tid: int = tid) -> Iterator[PointChunk]:
            return (PointChunk(a.points, a.point_views) for a in track_lidar(tid, True))

        corner = torch.floor(low / voxel_size) * voxel_size
        tgrid = voxelize_chunks(track_chunks, voxel_size, inputs.num_views, corner).grid
        index.track_grids[tid] = tgrid
        index.track_covis[tid] = _covis(tgrid, index.object_cameras(tid), inputs)
    return index
