"""What VAD-GS needs of the data, as data: :class:`VisibilityInputs` (no vadgs ``Scene`` required).

:class:`~vadgs.train.vad.VisibilityAwareDensification` and the visibility index
(:func:`~vadgs.train.vad.visibility.build_visibility_index`) read a dataset only through this
input: every view's camera (intrinsics ``K``, ``world_to_cam``, image size), an image loader, an
instance-mask loader or none (then the derived ground cells of the voxels stand in, as for a
COLMAP scene), the visibility observations — LiDAR (:class:`~vadgs.data.lidar.AccumulatedLidar`
per frame set, with each point's observing views) or SfM points with their TRACK table
(:class:`TrackTable`) —, and the moving-object tracks or none, on the device the source gives
(the CPU for both constructors):

- :meth:`VisibilityInputs.from_scene` for a vadgs :class:`~vadgs.data.scene.Scene` (street, DGP,
  nuScenes, Waymo, COLMAP through :func:`vadgs.data.load_colmap`);
- :meth:`VisibilityInputs.from_gsplat_parser` for gsplat's COLMAP ``Parser``
  (``examples/datasets/colmap.py``): its ``point_indices`` are the TRACK table.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import torch

from vadgs.data.gsplat_parser import read_gsplat_parser
from vadgs.data.observations import sfm_observations
from vadgs.geometry.camera import Cameras, invert_rigid

__all__ = ["TrackTable", "VisibilityInputs"]


@dataclass(frozen=True, eq=False)
class TrackTable:
    """SfM points and their observations (COLMAP's TRACK table), as a COO table.

    Attributes:
        points: ``(P, 3)`` points in the world frame.
        point_idx: ``(T,)`` int64 point of each observation.
        view_idx: ``(T,)`` int64 view (index into the inputs' views) of each observation.
    """

    points: torch.Tensor
    point_idx: torch.Tensor
    view_idx: torch.Tensor

    def __post_init__(self) -> None:
        if self.points.dim() != 2 or self.points.shape[1] != 3:
            raise ValueError(f"points: expected (P, 3), got {tuple(self.points.shape)}")
        if self.point_idx.shape != self.view_idx.shape or self.point_idx.dim() != 1:
            raise ValueError(
                f"point_idx, view_idx: expected two (T,), got {tuple(self.point_idx.shape)}, "
                f"{tuple(self.view_idx.shape)}"
            )


@dataclass(frozen=True, eq=False)
class VisibilityInputs:
    """Per-view cameras, loaders and visibility observations: everything VAD-GS reads of a dataset.

    Attributes:
        cameras: every view's camera, batched at the largest image size (``K`` ``(V, 3, 3)``,
            ``world_to_cam`` ``(V, 4, 4)``, OpenCV axes).
        sizes: per view ``(H, W)`` when the views differ in size, else None (all
            ``cameras.image_size``).
        train_views: the views VAD-GS tests, reconstructs from and supports with (training views).
        load_image: ``(view, size) -> (3, H, W)`` float image in [0, 1]; ``size`` None: the view's
            own size, else ``(H, W)`` (finer for the multi-view stereo of small structures, up to
            ``native_factor`` times).
        load_instances: ``view -> (H, W)`` int64 instance map (0 = none) for the views of
            ``instance_views``; None: no instance maps, the derived ground cells stand in
            (:func:`~vadgs.train.vad.instances.derive_instance_map`).
        instance_views: the views that have a map (default: every view when ``load_instances`` is
            given). A view without one makes the index derive instances for the views without.
        lidar: LiDAR observations, frame by frame: ``(track_id, views) ->`` an iterable of
            :class:`~vadgs.data.lidar.AccumulatedLidar`, one per frame (``track_id`` None: the
            static points in the world; a track id: that object's points in its own frame;
            ``views=False``: the points alone, without their observing views), read anew at each
            call (:func:`~vadgs.data.lidar.iter_lidar`); or None.
        sfm: SfM points with their TRACK table (used when ``lidar`` is None), or None.
        tracks: track id → :class:`~vadgs.data.scene.Track` of the moving objects (empty: static).
        classes: instance id → class name (e.g. ``"sign"``; derived cells are ``"static"``).
        view_cameras: per view, the index of its physical camera (``min_frame_gap`` between
            references and the view selection's camera ids).
        view_frames: per view, its frame (timestamp) index.
        frame_positions: per view, the position of its frame in each track's ``object_to_world``
            (default ``view_frames``).
        native_factor: how many times finer than ``sizes`` the image files are (``1 / scale`` of
            a vadgs scene; 1: no finer images).
        name: the dataset's name, for messages.
        scene_depth: the scene's typical view depth (the median camera-to-point depth of its
            observations), the unit VAD-GS's lengths follow (its defaults are for a depth of 10:
            :class:`~vadgs.train.vad.VisibilityDensifyConfig`). ``from_scene``: 10 (vadgs's scenes
            are street metres, or normalised to a median depth of 10); ``from_gsplat_parser``:
            measured; None: measured when needed (:meth:`median_view_depth`).
    """

    cameras: Cameras
    train_views: tuple[int, ...]
    load_image: Callable[[int, tuple[int, int] | None], torch.Tensor]
    view_cameras: tuple[int, ...]
    view_frames: tuple[int, ...]
    sizes: tuple[tuple[int, int], ...] | None = None
    load_instances: Callable[[int], torch.Tensor] | None = None
    instance_views: frozenset[int] | None = None
    lidar: Callable[[int | None, bool], Iterable[Any]] | None = None
    sfm: TrackTable | None = None
    tracks: Mapping[int, Any] = field(default_factory=dict)
    classes: Mapping[int, str] = field(default_factory=dict)
    frame_positions: tuple[int, ...] | None = None
    native_factor: int = 1
    name: str = ""
    scene_depth: float | None = None

    def __post_init__(self) -> None:
        v = self.num_views
        if self.scene_depth is not None and not (math.isfinite(self.scene_depth) and self.scene_depth > 0):
            raise ValueError(f"scene_depth: expected None or a finite depth > 0, got {self.scene_depth}")
        if self.cameras.world_to_cam.shape[0] != v:
            got = self.cameras.world_to_cam.shape[0]
            raise ValueError(f"cameras: expected K and world_to_cam of {v} views, got {got}")
        for what, seq in (("view_cameras", self.view_cameras), ("view_frames", self.view_frames)):
            if len(seq) != v:
                raise ValueError(f"{what}: expected {v} entries (one per view), got {len(seq)}")
        if self.sizes is not None and len(self.sizes) != v:
            raise ValueError(f"sizes: expected {v} entries (one per view), got {len(self.sizes)}")
        bad = [t for t in self.train_views if not 0 <= t < v]
        if bad:
            raise ValueError(f"train_views: expected views in [0, {v}), got {bad[:5]}")

    @property
    def num_views(self) -> int:
        """Number of views ``V``."""
        return int(self.cameras.K.shape[0])

    def size(self, view: int) -> tuple[int, int]:
        """``(H, W)`` of a view."""
        return self.sizes[view] if self.sizes is not None else self.cameras.image_size

    def frame_position(self, view: int) -> int:
        """Position of a view's frame in the tracks' per-frame arrays."""
        return (self.frame_positions if self.frame_positions is not None else self.view_frames)[view]

    @property
    def derives_instances(self) -> bool:
        """True when some view has no instance map (the index then derives them)."""
        if self.load_instances is None:
            return True
        return self.instance_views is not None and len(self.instance_views) < self.num_views

    def has_instances(self, view: int) -> bool:
        """True when ``view`` has its own instance map."""
        if self.load_instances is None:
            return False
        return self.instance_views is None or view in self.instance_views

    def median_view_depth(self) -> float:
        """The median camera-to-point depth (``z``) of the observations the visibility is built from.

        ``scene_depth`` when set; else measured over the LiDAR's static points or the SfM TRACK
        table (each observation: its point in its view's camera).

        Raises:
            ValueError: when there are no observations in front of a camera.
        """
        if self.scene_depth is not None:
            return float(self.scene_depth)
        if self.lidar is not None:
            observations = [(a.points, *a.point_views) for a in self.lidar(None, True)]
        elif self.sfm is not None:
            observations = [(self.sfm.points, self.sfm.point_idx, self.sfm.view_idx)]
        else:
            raise ValueError(f"inputs {self.name!r}: no LiDAR and no SfM observations to measure depth on")
        depths = []
        for points, pi, vi in observations:
            w2c = self.cameras.world_to_cam.to(points)
            z = (w2c[vi, 2, :3] * points[pi]).sum(-1) + w2c[vi, 2, 3]
            depths.append(z[z > 0])
        z = torch.cat(depths) if depths else torch.zeros(0)
        if z.numel() == 0:
            raise ValueError(f"inputs {self.name!r}: no observation in front of its camera")
        return float(z.median())

    # -- constructors ----------------------------------------------------------------------------------

    @classmethod
    def from_scene(cls, scene: Any, frames: Sequence[int] | None = None) -> VisibilityInputs:
        """The inputs of a vadgs :class:`~vadgs.data.scene.Scene` (loaders read its files lazily).

        Args:
            scene: the scene.
            frames: frames whose LiDAR (or whose views' SfM observations) make the visibility
                (default: the training frames, or every frame without a split).

        Example:
            >>> from vadgs.data import load_scene, sample_scene_path
            >>> inputs = VisibilityInputs.from_scene(load_scene(sample_scene_path()))
            >>> inputs.num_views, inputs.lidar is not None, inputs.derives_instances
            (24, True, False)
        """
        from vadgs.data.lidar import iter_lidar

        if len(scene.size_groups()) == 1:
            cameras, sizes = scene.cameras(), None
        else:
            sizes = tuple(scene.image_size(v) for v in range(scene.num_views))
            K = torch.stack([scene.cameras_info[v.camera].K for v in scene.views])
            cam_to_world = torch.stack([v.cam_to_world for v in scene.views])
            big = (max(h for h, _ in sizes), max(w for _, w in sizes))
            cameras = Cameras(K, invert_rigid(cam_to_world), big)
        lidar = sfm = None
        if scene.lidar_loader is not None:

            def lidar(track_id: int | None = None, views: bool = True):
                return iter_lidar(scene, frames, track_id=track_id, views=views)

        elif scene.sfm_points is not None:
            points, (pi, vi) = sfm_observations(scene, frames)
            sfm = TrackTable(points, pi, vi)
        with_maps = frozenset(v.index for v in scene.views if v.instances is not None)
        names = scene.camera_names

        def load_image(view: int, size: tuple[int, int] | None = None) -> torch.Tensor:
            return scene.load_images([view], size=size)[0]

        def load_instances(view: int) -> torch.Tensor:
            return scene.load_instances([view])[0]

        return cls(
            cameras=cameras,
            train_views=tuple(scene.train_views),
            load_image=load_image,
            view_cameras=tuple(names.index(v.camera) for v in scene.views),
            view_frames=tuple(v.frame for v in scene.views),
            sizes=sizes,
            load_instances=load_instances if with_maps else None,
            instance_views=with_maps if with_maps else None,
            lidar=lidar,
            sfm=sfm,
            tracks=dict(scene.tracks),
            classes=scene.classes(),
            frame_positions=tuple(scene.view_frame_position(v) for v in range(scene.num_views)),
            native_factor=int(1.0 / scene.scale + 1e-6),
            name=scene.name,
            scene_depth=10.0,
        )

    @classmethod
    def from_gsplat_parser(
        cls, parser: Any, train_views: Sequence[int] | None = None, test_every: int | None = None
    ) -> VisibilityInputs:
        """The inputs of gsplat's COLMAP ``Parser`` (``examples/datasets/colmap.py``), duck-typed.

        The parser is read by :func:`vadgs.data.gsplat_parser.read_gsplat_parser`.

        Reads ``image_names``, ``image_paths``, ``camtoworlds`` (``(N, 4, 4)`` OpenCV
        camera-to-world), ``camera_ids``, ``Ks_dict``, ``imsize_dict`` (camera id → ``(W, H)``),
        ``points`` and ``point_indices`` (image name → indices of the points it sees: the TRACK
        table). ``K`` is moved to vadgs's pixel convention (centres at integers: ``cx, cy`` minus
        0.5; gsplat's and COLMAP's centres are at ``i + 0.5``). Each image is its own frame; there
        are no instance maps (derived ground cells stand in) and no moving objects. Images are read
        with PIL on demand and resized (area) to the parser's size.

        Distorted cameras (``params_dict`` not empty: SIMPLE_RADIAL, RADIAL, OPENCV): the Parser's
        ``Ks_dict`` and ``imsize_dict`` are already those of the undistorted images, and each image
        is undistorted as gsplat's ``Dataset`` does it — ``cv2.remap`` with ``mapx_dict`` /
        ``mapy_dict``, then the ``roi_undist_dict`` crop. Fisheye cameras (a ``mask_dict`` entry)
        are refused. ``scene_depth`` is the median depth of the observations
        (:meth:`median_view_depth`): VAD-GS's lengths follow gsplat's normalised world.

        Args:
            parser: the parser (or any object with those attributes).
            train_views: the training views (default: gsplat's ``Dataset(split="train")``, every
                view but each ``test_every``-th when ``test_every`` is given, else every view).
            test_every: gsplat's ``test_every`` (``parser.test_every`` when present).

        Only observations by training views count for the visibility (as for a vadgs scene).
        """
        d = read_gsplat_parser(parser, train_views, test_every)
        out = cls(
            cameras=d.cameras,
            train_views=d.train_views,
            load_image=d.load_image,
            view_cameras=d.view_cameras,
            view_frames=tuple(range(d.cameras.K.shape[0])),
            sizes=d.sizes,
            sfm=TrackTable(d.points, d.point_idx, d.view_idx),
            name=d.name,
        )
        return replace(out, scene_depth=out.median_view_depth()) if d.view_idx.numel() else out
