"""The scene object shared by every loader, and the readers of its files.

A :class:`Scene` holds cameras, frames and views, LiDAR per frame, the instance table, the tracks
of rigidly moving objects, the train/test split and (COLMAP scenes) sparse points. Per-view
images, depth maps and instance maps are loaded lazily from disk (or from memory for scenes built
in code) with the readers at the end of this module.

This module imports no other module of :mod:`vadgs.data` but the image decoder
(:func:`vadgs.data.images.read_image`, which imports none): the loaders
(:func:`~vadgs.data.load_scene`, :func:`~vadgs.data.load_dgp`, ...) and the checks
(:mod:`vadgs.data.checks`) build on it.
"""

from __future__ import annotations

import zipfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

from vadgs.data.images import read_image
from vadgs.geometry.camera import Cameras, invert_rigid

__all__ = [
    "CameraInfo",
    "ColmapPoints",
    "FrameInfo",
    "InstanceInfo",
    "LidarFrame",
    "Scene",
    "Track",
    "ViewInfo",
    "npz_headers",
    "read_depth",
    "read_lidar_npz",
    "read_rgb",
]


@dataclass(frozen=True)
class CameraInfo:
    """A physical camera of the rig.

    Attributes:
        name: camera name (e.g. ``"front"``).
        K: ``(3, 3)`` intrinsics at the scene's (possibly rescaled) resolution.
        image_size: ``(H, W)`` at the scene's resolution.
        cam_to_ego: ``(4, 4)`` camera-to-ego transform, or None when unknown.
    """

    name: str
    K: torch.Tensor
    image_size: tuple[int, int]
    cam_to_ego: torch.Tensor | None = None


@dataclass(frozen=True)
class ViewInfo:
    """One image: a camera at a frame.

    Attributes:
        index: the view's index in ``Scene.views``.
        frame: the frame index.
        camera: the camera name.
        timestamp: seconds.
        cam_to_world: ``(4, 4)``.
        image: path of the colour image, or None when it lives in memory.
        depth: path of the ground-truth depth ``.npz``, or None.
        instances: path of the instance-id PNG, or None.
        group: None for the recorded views; for an extrapolated *novel* view (rendered from a pose
            the rig never had, e.g. shifted 2 m sideways) its group, e.g. ``"shift+2.0"``.
            Novel views are in :attr:`Scene.views` but in no frame's ``view_ids`` and in neither
            :attr:`Scene.train_views` nor :attr:`Scene.test_views`.
    """

    index: int
    frame: int
    camera: str
    timestamp: float
    cam_to_world: torch.Tensor
    image: Path | None = None
    depth: Path | None = None
    instances: Path | None = None
    group: str | None = None


@dataclass(frozen=True)
class FrameInfo:
    """A timestamp of the recording: the ego pose and its views."""

    index: int
    timestamp: float
    ego_to_world: torch.Tensor | None
    view_ids: tuple[int, ...]
    lidar: Path | None = None


@dataclass(frozen=True)
class InstanceInfo:
    """An entry of the instance table: ``class_name`` is e.g. road, building, tree, sign, car."""

    id: int
    name: str
    class_name: str
    dynamic: bool


@dataclass(frozen=True)
class Track:
    """A rigidly moving object.

    Attributes:
        id: its instance id.
        class_name: e.g. ``"car"``.
        size_lwh: ``(3,)`` box length, width, height in metres.
        object_to_world: ``(F, 4, 4)`` pose per frame of the scene (identity where unknown).
        valid: ``(F,)`` bool, frames where the pose is known.
        mesh: path of the object's mesh in its own frame, if any.
    """

    id: int
    class_name: str
    size_lwh: torch.Tensor
    object_to_world: torch.Tensor
    valid: torch.Tensor
    mesh: Path | None = None


class LidarFrame(NamedTuple):
    """LiDAR of one frame.

    Attributes:
        points: ``(N, 3)`` float32 world coordinates.
        instance: ``(N,)`` int64 instance ids (0 where unknown).
        origin: ``(3,)`` sensor position in world.
    """

    points: torch.Tensor
    instance: torch.Tensor
    origin: torch.Tensor


class ColmapPoints(NamedTuple):
    """The sparse points of a COLMAP model and their TRACK table.

    The track table is in coordinate (COO) form: observation ``t`` says that point
    ``point_idx[t]`` is seen in view ``view_idx[t]`` (an index into ``Scene.views``) at pixel
    ``uv[t]`` (vadgs pixel convention, at the scene's scale).

    Attributes:
        points: ``(P, 3)`` float32 world coordinates.
        colors: ``(P, 3)`` float32 RGB in ``[0, 1]``.
        errors: ``(P,)`` float32 mean reprojection error in pixels at full resolution as stored
            by COLMAP (``-1`` where COLMAP has none).
        point_ids: ``(P,)`` int64 COLMAP ``point3D_id`` of each point.
        point_idx: ``(T,)`` int64 index into ``points`` of each observation.
        view_idx: ``(T,)`` int64 index into ``Scene.views`` of each observation.
        uv: ``(T, 2)`` float32 observed pixel ``(x, y)`` of each observation.
    """

    points: torch.Tensor
    colors: torch.Tensor
    errors: torch.Tensor
    point_ids: torch.Tensor
    point_idx: torch.Tensor
    view_idx: torch.Tensor
    uv: torch.Tensor

    @property
    def point_views(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(point_idx, view_idx)``, as ``vadgs.geometry.voxelize(..., point_views=...)`` takes it."""
        return self.point_idx, self.view_idx


@dataclass
class Scene:
    """A recorded scene: rig, frames, views, LiDAR, instances, tracks and split.

    Per-view data is read lazily through :meth:`load_images`, :meth:`load_depths` and
    :meth:`load_instances`; the ``scale`` given at load time resizes images (area) and depth and
    instance maps (nearest) on the fly and rescales the intrinsics to match.

    Attributes:
        name: scene name.
        root: the folder it was loaded from (or None).
        cameras_info: camera name → :class:`CameraInfo`.
        frames: the frames in order.
        views: all views, frame-major in camera order (``views[i].index == i``), then the novel
            views (``group`` set; see :attr:`novel_views`).
        instances: instance id → :class:`InstanceInfo`.
        tracks: instance id → :class:`Track` for the rigidly moving objects.
        train_frames / test_frames: the split by frame index.
        scale: the resolution factor applied at load time.
        lidar_loader: frame index → :class:`LidarFrame`, or None without LiDAR.
        image_loader: view → ``(3, H, W)`` image, for scenes whose images live in memory.
        sfm_points: sparse structure-from-motion points with their TRACK table
            (:class:`ColmapPoints`, ``view_idx`` indexing :attr:`views`), or
            None. COLMAP scenes have them instead of LiDAR: the trainer initialises from them and
            VAD-GS builds its voxel visibility from their tracks.
    """

    name: str
    root: Path | None
    cameras_info: dict[str, CameraInfo]
    frames: list[FrameInfo]
    views: list[ViewInfo]
    instances: dict[int, InstanceInfo] = field(default_factory=dict)
    tracks: dict[int, Track] = field(default_factory=dict)
    train_frames: list[int] = field(default_factory=list)
    test_frames: list[int] = field(default_factory=list)
    scale: float = 1.0
    lidar_loader: Callable[[int], LidarFrame] | None = None
    image_loader: Callable[[ViewInfo], torch.Tensor] | None = None
    sfm_points: ColmapPoints | None = None
    _frame_positions: dict[int, int] = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self._frame_positions = {f.index: i for i, f in enumerate(self.frames)}
        if len(self._frame_positions) != len(self.frames):
            dup = sorted({f.index for f in self.frames if [g.index for g in self.frames].count(f.index) > 1})
            raise ValueError(f"frames: expected unique frame indices, got duplicates {dup[:5]}")

    # -- indexing -------------------------------------------------------------------------------------

    @property
    def num_views(self) -> int:
        """Number of views."""
        return len(self.views)

    @property
    def camera_names(self) -> list[str]:
        """The rig's camera names in order."""
        return list(self.cameras_info)

    @property
    def is_photo_collection(self) -> bool:
        """Whether the scene is a collection of photos (a COLMAP scene), not a recording.

        One photo per frame, structure-from-motion points, no LiDAR and no moving objects: what
        the commands call photos rather than frames, tracks and moving objects.

        Example:
            >>> from vadgs.data import load_scene, sample_scene_path
            >>> load_scene(sample_scene_path()).is_photo_collection
            False
        """
        return (
            self.sfm_points is not None
            and self.lidar_loader is None
            and not self.tracks
            and all(len(f.view_ids) == 1 for f in self.frames)
        )

    @property
    def train_views(self) -> list[int]:
        """Indices of the recorded views of the training frames."""
        frames = set(self.train_frames)
        return [v.index for v in self.views if v.frame in frames and v.group is None]

    @property
    def test_views(self) -> list[int]:
        """Indices of the recorded views of the test frames."""
        frames = set(self.test_frames)
        return [v.index for v in self.views if v.frame in frames and v.group is None]

    @property
    def novel_views(self) -> list[int]:
        """Indices of the novel (extrapolated) views, every group; empty for most scenes.

        Example:
            >>> from vadgs.data import load_scene, sample_scene_path
            >>> load_scene(sample_scene_path()).novel_views
            []
        """
        return [v.index for v in self.views if v.group is not None]

    def novel_groups(self) -> dict[str, list[int]]:
        """Novel view indices by group (e.g. ``{"shift+2.0": [...], "shift-2.0": [...]}``), in file order."""
        out: dict[str, list[int]] = {}
        for v in self.views:
            if v.group is not None:
                out.setdefault(v.group, []).append(v.index)
        return out

    def view_id(self, frame: int, camera: str) -> int:
        """The index of the view of ``camera`` at ``frame``."""
        for v in self.frames[self.frame_position(frame)].view_ids:
            if self.views[v].camera == camera:
                return v
        raise KeyError(f"no view of camera {camera!r} at frame {frame}")

    def frame_position(self, frame: int) -> int:
        """Position of a frame index in :attr:`frames` (and in ``Track.object_to_world``); O(1).

        Raises:
            KeyError: if the scene has no such frame.

        Example:
            >>> from vadgs.data import load_scene, sample_scene_path
            >>> scene = load_scene(sample_scene_path())
            >>> scene.frames[0].index, scene.frame_position(scene.frames[0].index)
            (16, 0)
        """
        try:
            return self._frame_positions[int(frame)]
        except KeyError:
            raise KeyError(f"no frame {frame} in scene {self.name!r}") from None

    def view_frame_position(self, view: int) -> int:
        """Position in :attr:`frames` of a view's frame (the ``frame`` argument of the model's render)."""
        return self._frame_positions[self.views[view].frame]

    def _ids(self, view_ids: Sequence[int] | None) -> list[int]:
        if view_ids is None:
            return list(range(self.num_views))
        ids = [int(v) for v in view_ids]
        bad = [v for v in ids if not 0 <= v < self.num_views]
        if bad:
            raise ValueError(f"view_ids: out of range [0, {self.num_views}): {bad[:5]}")
        return ids

    # -- cameras --------------------------------------------------------------------------------------

    def cameras(self, view_ids: Sequence[int] | None = None) -> Cameras:
        """The views' cameras in the world frame, batched (all views share one image size).

        Raises:
            ValueError: if the selected views have different image sizes.
        """
        ids = self._ids(view_ids)
        infos = [self.cameras_info[self.views[i].camera] for i in ids]
        sizes = {c.image_size for c in infos}
        if len(sizes) > 1:
            raise ValueError(f"view_ids: views have different image sizes {sorted(sizes)}; select fewer")
        K = torch.stack([c.K for c in infos])
        cam_to_world = torch.stack([self.views[i].cam_to_world for i in ids])
        return Cameras(K, invert_rigid(cam_to_world), infos[0].image_size)

    def size_groups(self, view_ids: Sequence[int] | None = None) -> list[list[int]]:
        """The views split by image size (in order of first appearance), for batched camera ops.

        Example:
            >>> from vadgs.data import load_scene, sample_scene_path
            >>> sc = load_scene(sample_scene_path())
            >>> [len(g) for g in sc.size_groups()]  # one rig size
            [24]
        """
        groups: dict[tuple[int, int], list[int]] = {}
        for i in self._ids(view_ids):
            groups.setdefault(self.image_size(i), []).append(i)
        return list(groups.values())

    # -- lazy per-view data ---------------------------------------------------------------------------

    def image_size(self, view_id: int) -> tuple[int, int]:
        """``(H, W)`` of a view at the scene's resolution."""
        return self.cameras_info[self.views[view_id].camera].image_size

    def load_images(
        self, view_ids: Sequence[int] | None = None, size: tuple[int, int] | None = None
    ) -> torch.Tensor:
        """Colour images ``(B, 3, H, W)`` float in [0, 1].

        Args:
            view_ids: the views (default all).
            size: ``(H, W)`` to resize to instead of the scene's resolution, e.g. a finer one up to
                the files' own (``image_size / scale``) for multi-view stereo on small structures
                (the intrinsics are then :func:`~vadgs.geometry.scale_intrinsics` of ``K``).

        Raises:
            ValueError: if ``size`` is not two positive integers.
        """
        ids = self._ids(view_ids)
        if size is not None and not (len(size) == 2 and all(isinstance(n, int) and n > 0 for n in size)):
            raise ValueError(f"size: expected (H, W) positive integers, got {size!r}")
        out = []
        for i in ids:
            v = self.views[i]
            if self.image_loader is not None:
                img = self.image_loader(v)
            else:
                if v.image is None:
                    raise FileNotFoundError(f"view {i} ({v.camera}@{v.frame}) has no image")
                img = read_rgb(v.image)
            out.append(self._resize(img[None], i, "area", size)[0])
        return torch.stack(out)

    def load_depths(self, view_ids: Sequence[int] | None = None) -> torch.Tensor:
        """Ground-truth z-depth ``(B, 1, H, W)`` float32 (0 = no surface).

        Raises:
            FileNotFoundError: if a view has no depth.
        """

        def read(path: Path) -> torch.Tensor:
            return torch.from_numpy(read_depth(path).astype(np.float32))

        return self._load_maps(view_ids, "depth", "ground-truth depth", read)

    def load_instances(self, view_ids: Sequence[int] | None = None) -> torch.Tensor:
        """Instance-id maps ``(B, H, W)`` int64 (0 = sky / none).

        Raises:
            FileNotFoundError: if a view has no instance map.
        """

        def read(path: Path) -> torch.Tensor:  # float64 through the resize: exact below 2^53
            return torch.from_numpy(_read_png(path).astype(np.int64)).double()

        return self._load_maps(view_ids, "instances", "instance map", read)[:, 0].long()

    def _load_maps(
        self, view_ids: Sequence[int] | None, field: str, what: str, read: Callable[[Path], torch.Tensor]
    ) -> torch.Tensor:
        """``(B, 1, H, W)``: ``read(view.<field>)`` of each view, resized (nearest) to the view's size."""
        out = []
        for i in self._ids(view_ids):
            v = self.views[i]
            path = getattr(v, field)
            if path is None:
                raise FileNotFoundError(f"view {i} ({v.camera}@{v.frame}) has no {what}")
            out.append(self._resize(read(path)[None, None], i, "nearest")[0])
        return torch.stack(out)

    def _resize(
        self, x: torch.Tensor, view_id: int, mode: str, size: tuple[int, int] | None = None
    ) -> torch.Tensor:
        h, w = size or self.image_size(view_id)
        if x.shape[-2:] == (h, w):
            return x
        if mode == "area" and (h > x.shape[-2] or w > x.shape[-1]):
            mode = "bilinear"  # enlarging (finer than the file): area would replicate pixels
        return F.interpolate(
            x, size=(h, w), mode=mode, **({"align_corners": False} if mode == "bilinear" else {})
        )

    # -- LiDAR ----------------------------------------------------------------------------------------

    def lidar(self, frame: int) -> LidarFrame:
        """The LiDAR sweep of a frame (world coordinates).

        Raises:
            FileNotFoundError: if the scene has no LiDAR for that frame.
        """
        if self.lidar_loader is None:
            raise FileNotFoundError(f"scene {self.name!r} has no LiDAR")
        return self.lidar_loader(frame)

    def classes(self) -> dict[int, str]:
        """Instance id → class name."""
        return {i: inst.class_name for i, inst in self.instances.items()}

    def instance_ids(self, class_name: str) -> list[int]:
        """Ids of the instances of a class (e.g. ``"sign"``)."""
        return [i for i, inst in self.instances.items() if inst.class_name == class_name]

    def __repr__(self) -> str:
        sfm = f", {self.sfm_points.points.shape[0]} SfM points" if self.sfm_points is not None else ""
        if self.is_photo_collection:  # photos: no frames, tracks or rig to speak of
            return (
                f"Scene({self.name!r}, {len(self.frames)} photos, {len(self.cameras_info)} "
                f"camera{'s' if len(self.cameras_info) != 1 else ''}{sfm}, scale={self.scale})"
            )
        return (
            f"Scene({self.name!r}, {len(self.frames)} frames, {self.num_views} views, "
            f"cameras={self.camera_names}, {len(self.tracks)} tracks{sfm}, scale={self.scale})"
        )


# ---------------------------------------------------------------------------------------------------
# readers of the files a scene references


def read_rgb(path: Path) -> torch.Tensor:
    """A colour image ``(3, H, W)`` float32 in ``[0, 1]`` (:func:`vadgs.data.images.read_image`)."""
    return torch.from_numpy(read_image(path)).permute(2, 0, 1)


def _read_png(path: Path) -> np.ndarray:
    """A PNG's stored values (instance maps; colour images: :func:`read_rgb`)."""
    if not path.is_file():
        raise FileNotFoundError(f"missing file {path}")
    try:
        with Image.open(path) as im:
            return np.asarray(im).copy()
    except (OSError, SyntaxError, ValueError) as e:
        raise ValueError(f"{path}: not a decodable image ({type(e).__name__}: {e})") from None


def read_lidar_npz(path: Path) -> LidarFrame:
    """A benchmark LiDAR ``.npz``, checked: (N, 3) finite points, (N,) ids, (3,) origin."""
    npz_headers(path)  # a clear error for a file that is not an .npz (0 bytes, truncated)
    try:
        with np.load(path) as z:
            if "points" not in z:
                raise ValueError(f"{path}: expected key 'points', got keys {sorted(z.keys())}")
            pts = np.asarray(z["points"])
            ins = np.asarray(z["instance"]) if "instance" in z else None
            origin = np.asarray(z["origin"]) if "origin" in z else np.zeros(3)
    except ValueError:
        raise
    except Exception as e:  # zlib.error, BadZipFile, EOFError on a corrupt member
        raise ValueError(f"{path}: corrupt LiDAR archive ({type(e).__name__}: {e})") from None
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.dtype.kind != "f":
        raise ValueError(f"{path}: points: expected (N, 3) floating, got shape {pts.shape} dtype {pts.dtype}")
    bad = ~np.isfinite(pts).all(-1)
    if bad.any():
        raise ValueError(
            f"{path}: points: expected finite values, got {int(bad.sum())} non-finite points of {len(pts)}"
        )
    if ins is None:
        ins = np.zeros(len(pts), dtype=np.int64)
    if ins.shape != (len(pts),) or ins.dtype.kind not in "iu":
        raise ValueError(
            f"{path}: instance: expected ({len(pts)},) integers, got shape {ins.shape} dtype {ins.dtype}"
        )
    if origin.shape != (3,) or not np.isfinite(origin).all():
        raise ValueError(f"{path}: origin: expected 3 finite numbers, got {origin!r}")
    return LidarFrame(
        torch.from_numpy(pts.astype(np.float32)),
        torch.from_numpy(ins.astype(np.int64)),
        torch.from_numpy(origin.astype(np.float32)),
    )


def npz_headers(path: str | Path) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """Shapes and dtypes of the arrays in an ``.npz``, read from their headers (no decompression).

    Raises:
        ValueError: if the file is not a readable ``.npz`` (the message names the file).
    """
    path = Path(path)
    out = {}
    try:
        with zipfile.ZipFile(path) as zf:
            for name in zf.namelist():
                if not name.endswith(".npy"):
                    continue
                with zf.open(name) as f:
                    version = np.lib.format.read_magic(f)
                    read = (
                        np.lib.format.read_array_header_1_0
                        if version == (1, 0)
                        else np.lib.format.read_array_header_2_0
                    )
                    shape, _, dtype = read(f)
                out[name[: -len(".npy")]] = (tuple(shape), dtype)
    except (OSError, zipfile.BadZipFile, ValueError, EOFError, NotImplementedError, RuntimeError) as e:
        size = path.stat().st_size if path.is_file() else None
        what = "an empty file (0 bytes)" if size == 0 else f"{type(e).__name__}: {e}"
        raise ValueError(f"{path}: not a readable .npz archive ({what})") from None
    return out


def read_depth(path: Path) -> np.ndarray:
    """The ``depth`` array of a depth ``.npz``, checked (2-D, floating, finite, non-negative).

    Raises:
        ValueError: naming the file and what is wrong.
    """
    try:
        with np.load(path) as z:
            if "depth" not in z:
                raise ValueError(f"{path}: expected key 'depth', got keys {sorted(z.keys())}")
            d = np.asarray(z["depth"])
    except ValueError:
        raise
    except (OSError, zipfile.BadZipFile, EOFError) as e:
        raise ValueError(f"{path}: not a readable .npz archive ({type(e).__name__}: {e})") from None
    except Exception as e:  # zlib.error and friends on a corrupt member
        raise ValueError(f"{path}: corrupt depth array ({type(e).__name__}: {e})") from None
    if d.ndim != 2 or d.dtype.kind != "f":
        raise ValueError(f"{path}: depth: expected a 2-D floating array, got shape {d.shape} dtype {d.dtype}")
    bad = ~np.isfinite(d)
    if bad.any():
        raise ValueError(
            f"{path}: depth: expected finite values, got {int(bad.sum())} non-finite of {d.size}"
        )
    if (d < 0).any():
        raise ValueError(
            f"{path}: depth: expected values >= 0 (0 = no surface), got min {float(d.min()):.3g}"
        )
    return d
