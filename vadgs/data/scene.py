"""The scene object shared by every loader, and the loader of the benchmark scene format.

A :class:`Scene` holds cameras, frames and views, LiDAR per frame, the instance table, the tracks
of rigidly moving objects and the train/test split. Per-view images, depth maps and instance maps
are loaded lazily from disk (or from memory for scenes built in code).

The benchmark format (``scene.json`` beside ``images/``, ``depth/``, ``instances/``, ``lidar/``)
is described in ``../shared/data/README.md``; :func:`load_scene` reads it. Loading validates the
whole ``scene.json`` and checks that every referenced file exists before returning, so a scene is
never half-loaded silently.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

from vadgs.checks import check_finite
from vadgs.data._json import read_json, require_key
from vadgs.data.validate import (
    check_intrinsics,
    check_rigid,
    check_split,
    npz_headers,
    read_depth,
    validate_scene,
)
from vadgs.geometry.camera import Cameras, invert_rigid, scale_intrinsics

if TYPE_CHECKING:
    from vadgs.data.colmap import ColmapPoints

__all__ = [
    "CameraInfo",
    "FrameInfo",
    "InstanceInfo",
    "LidarFrame",
    "Scene",
    "Track",
    "ViewInfo",
    "load_scene",
    "novel_view_group",
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
            (:class:`~vadgs.data.colmap.ColmapPoints`, ``view_idx`` indexing :attr:`views`), or
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
                img = torch.from_numpy(_read_png(v.image, expect_rgb=True)).permute(2, 0, 1).float() / 255.0
            out.append(self._resize(img[None], i, "area", size)[0])
        return torch.stack(out)

    def load_depths(self, view_ids: Sequence[int] | None = None) -> torch.Tensor:
        """Ground-truth z-depth ``(B, 1, H, W)`` float32 (0 = no surface).

        Raises:
            FileNotFoundError: if a view has no depth.
        """
        out = []
        for i in self._ids(view_ids):
            v = self.views[i]
            if v.depth is None:
                raise FileNotFoundError(f"view {i} ({v.camera}@{v.frame}) has no ground-truth depth")
            d = torch.from_numpy(read_depth(v.depth).astype(np.float32))
            out.append(self._resize(d[None, None], i, "nearest")[0])
        return torch.stack(out)

    def load_instances(self, view_ids: Sequence[int] | None = None) -> torch.Tensor:
        """Instance-id maps ``(B, H, W)`` int64 (0 = sky / none).

        Raises:
            FileNotFoundError: if a view has no instance map.
        """
        out = []
        for i in self._ids(view_ids):
            v = self.views[i]
            if v.instances is None:
                raise FileNotFoundError(f"view {i} ({v.camera}@{v.frame}) has no instance map")
            ins = torch.from_numpy(_read_png(v.instances).astype(np.int64))
            out.append(self._resize(ins[None, None].double(), i, "nearest")[0, 0].long())
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
        return (
            f"Scene({self.name!r}, {len(self.frames)} frames, {self.num_views} views, "
            f"cameras={self.camera_names}, {len(self.tracks)} tracks{sfm}, scale={self.scale})"
        )


# ---------------------------------------------------------------------------------------------------
# the benchmark scene format


def _read_png(path: Path, expect_rgb: bool = False) -> np.ndarray:
    if not path.is_file():
        raise FileNotFoundError(f"missing file {path}")
    try:
        with Image.open(path) as im:
            if expect_rgb:
                im = im.convert("RGB")
            return np.asarray(im).copy()
    except (OSError, SyntaxError, ValueError) as e:
        raise ValueError(f"{path}: not a decodable image ({type(e).__name__}: {e})") from None


def _read_lidar(path: Path) -> LidarFrame:
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


def _int(value: object, what: str) -> int:
    """An integer field of scene.json (an int, or a float / string holding one)."""
    if isinstance(value, bool):
        raise ValueError(f"scene.json: {what}: expected an integer, got {value!r}")
    if isinstance(value, int):
        return value
    if isinstance(value, float) and value.is_integer():
        return int(value)
    if isinstance(value, str):
        try:
            return int(value)
        except ValueError:
            pass
    raise ValueError(f"scene.json: {what}: expected an integer, got {value!r}")


def _float(value: object, what: str) -> float:
    if isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value):
        return float(value)
    raise ValueError(f"scene.json: {what}: expected a finite number, got {value!r}")


def _str(value: object, what: str) -> str:
    if isinstance(value, str) and value:
        return value
    raise ValueError(f"scene.json: {what}: expected a non-empty string, got {value!r}")


def _bool(value: object, what: str) -> bool:
    if isinstance(value, bool):
        return value
    raise ValueError(f"scene.json: {what}: expected true or false, got {value!r}")


def _pose(value: object, what: str) -> torch.Tensor:
    """A rigid 4x4 transform of scene.json (see :func:`~vadgs.data.validate.check_rigid`)."""
    t = _matrix(value, (4, 4), what)
    check_rigid(t, f"scene.json: {what}")
    return t


def _frame_list(value: object, what: str) -> list[int]:
    if not isinstance(value, list):
        raise ValueError(f"scene.json: {what}: expected a list of frame indices, got {value!r}")
    return [_int(f, f"{what}[{i}]") for i, f in enumerate(value)]


def _matrix(value: object, shape: tuple[int, ...], what: str) -> torch.Tensor:
    try:
        t = torch.tensor(value, dtype=torch.float64)
    except (TypeError, ValueError):
        raise ValueError(f"scene.json: {what}: expected a {shape} matrix of numbers, got {value!r}") from None
    if tuple(t.shape) != shape:
        raise ValueError(f"scene.json: {what}: expected shape {shape}, got {tuple(t.shape)}")
    check_finite(t, f"scene.json: {what}")
    return t.float()


def _get(d: dict, key: str, what: str) -> Any:
    return require_key(d, key, f"scene.json: {what}")


def novel_view_group(shift_ego_m: Sequence[float]) -> str:
    """Group name of a novel view from its ego-frame shift: ``"shift+2.0"`` for a lateral ``(0, 2, 0)``.

    Any other shift is named by its three components, ``"shift+1.0,+0.0,+0.5"``.

    Example:
        >>> novel_view_group([0.0, -2.0, 0.0]), novel_view_group([1, 0, 0.5])
        ('shift-2.0', 'shift+1.0,+0.0,+0.5')
    """
    x, y, z = (float(c) for c in shift_ego_m)
    if x == 0.0 and z == 0.0:
        return f"shift{y:+.1f}"
    return f"shift{x:+.1f},{y:+.1f},{z:+.1f}"


def _novel_views(
    meta: dict, root: Path, cameras: dict[str, CameraInfo], frames: dict[int, FrameInfo], start: int
) -> list[ViewInfo]:
    """The ``novel_views`` entries of ``scene.json`` as :class:`ViewInfo` (indices from ``start``)."""
    entries = meta.get("novel_views", [])
    if not isinstance(entries, list):
        raise ValueError("scene.json: novel_views: expected a list")
    views = []
    for ni, nm in enumerate(entries):
        what = f"novel_views[{ni}]"
        frame = int(_get(nm, "frame", what))
        if frame not in frames:
            raise ValueError(f"scene.json: {what}.frame: no frame {frame} in the scene")
        cam = str(_get(nm, "camera", what))
        if cam not in cameras:
            raise ValueError(f"scene.json: {what}.camera: unknown camera {cam!r}, have {list(cameras)}")
        c2w = _matrix(_get(nm, "cam_to_world", what), (4, 4), f"{what}.cam_to_world")
        if "group" in nm:
            group = str(nm["group"])
        else:
            shift = _get(nm, "shift_ego_m", what)
            if not (isinstance(shift, list) and len(shift) == 3):
                raise ValueError(f"scene.json: {what}.shift_ego_m: expected 3 numbers, got {shift!r}")
            group = novel_view_group(shift)
        files = {k: (root / nm[k]) if nm.get(k) else None for k in ("image", "depth", "instances")}
        if files["image"] is None:
            raise ValueError(f"scene.json: {what}: missing key 'image'")
        views.append(ViewInfo(start + ni, frame, cam, frames[frame].timestamp, c2w, **files, group=group))
    return views


def load_scene(
    path: str | Path, scale: float = 1.0, check_files: bool = True, validate: str = "headers"
) -> Scene:
    """Load a scene in the benchmark format (``scene.json`` and its files).

    Args:
        path: the scene folder (or its ``scene.json``).
        scale: resolution factor; images are resized on load and intrinsics rescaled
            (e.g. ``0.5`` for 240×144 from 480×288).
        check_files: verify that every referenced file exists before returning.
        validate: content checks of the files (:func:`~vadgs.data.validate_scene`):
            ``"headers"`` (default: image sizes and decodable headers, ``.npz`` keys, shapes and
            dtypes, a non-empty LiDAR total, the test views' depth decoded), ``"full"`` (decode
            and check every file, as ``vadgs check --full``) or ``"none"``. The metadata
            (field types, ``K``, rigid poses, the split) is always checked.

    Returns:
        The :class:`Scene`, with per-view data loaded lazily. ``novel_views`` entries of
        ``scene.json`` become views after the recorded ones (:attr:`Scene.novel_views`).

    Raises:
        FileNotFoundError: if ``scene.json`` or a referenced file is missing.
        ValueError: if ``scene.json`` is malformed (the message names the entry: a field of the
            wrong type, a singular ``K``, a pose that is not rigid, a duplicate or unknown split
            frame) or a file's content is wrong (the message names the file, the expected and
            the actual: an image of another size, a corrupt PNG or ``.npz``, no LiDAR points).

    Example:
        >>> from vadgs.data import sample_scene_path
        >>> scene = load_scene(sample_scene_path())
        >>> scene.num_views, scene.camera_names
        (24, ['front', 'front_left', 'front_right'])
        >>> scene.load_images([0]).shape
        torch.Size([1, 3, 144, 240])
    """
    path = Path(path)
    root = path.parent if path.name == "scene.json" else path
    meta_path = root / "scene.json"
    if not meta_path.is_file():
        raise FileNotFoundError(f"no scene.json in {root}")
    meta = read_json(meta_path, "scene.json")
    if not (isinstance(scale, (int, float)) and scale > 0):
        raise ValueError(f"scale: expected a positive number, got {scale!r}")
    if validate not in ("none", "headers", "full"):
        raise ValueError(f"validate: expected 'none', 'headers' or 'full', got {validate!r}")

    cams_meta = _get(meta, "cameras", "top level")
    if not isinstance(cams_meta, dict) or not cams_meta:
        raise ValueError("scene.json: cameras: expected a non-empty object")
    cameras: dict[str, CameraInfo] = {}
    for name, c in cams_meta.items():
        w = _int(_get(c, "width", f"cameras.{name}"), f"cameras.{name}.width")
        h = _int(_get(c, "height", f"cameras.{name}"), f"cameras.{name}.height")
        if w <= 0 or h <= 0:
            raise ValueError(f"scene.json: cameras.{name}: expected positive width and height, got {w}x{h}")
        K = _matrix(_get(c, "K", f"cameras.{name}"), (3, 3), f"cameras.{name}.K")
        check_intrinsics(K, f"scene.json: cameras.{name}.K")
        size = (round(h * scale), round(w * scale))
        if scale != 1.0:
            K = scale_intrinsics(K, size[1] / w)
        c2e = _pose(c["cam_to_ego"], f"cameras.{name}.cam_to_ego") if "cam_to_ego" in c else None
        cameras[name] = CameraInfo(name, K, size, c2e)

    frames: list[FrameInfo] = []
    views: list[ViewInfo] = []
    frames_meta = _get(meta, "frames", "top level")
    if not isinstance(frames_meta, list) or not frames_meta:
        raise ValueError("scene.json: frames: expected a non-empty list")
    for fi, fm in enumerate(frames_meta):
        what = f"frames[{fi}]"
        index = _int(_get(fm, "index", what), f"{what}.index")
        ts = _float(fm.get("timestamp", index), f"{what}.timestamp")
        e2w = _pose(fm["ego_to_world"], f"{what}.ego_to_world") if "ego_to_world" in fm else None
        ids = []
        vms = _get(fm, "views", what)
        if not isinstance(vms, list):
            raise ValueError(f"scene.json: {what}.views: expected a list")
        for vi, vm in enumerate(vms):
            vwhat = f"{what}.views[{vi}]"
            cam = _str(_get(vm, "camera", vwhat), f"{vwhat}.camera")
            if cam not in cameras:
                raise ValueError(f"scene.json: {vwhat}.camera: unknown camera {cam!r}, have {list(cameras)}")
            c2w = _pose(_get(vm, "cam_to_world", vwhat), f"{vwhat}.cam_to_world")
            files = {
                k: (root / _str(vm[k], f"{vwhat}.{k}")) if vm.get(k) else None
                for k in ("image", "depth", "instances")
            }
            if files["image"] is None:
                raise ValueError(f"scene.json: {vwhat}: missing key 'image'")
            views.append(ViewInfo(len(views), index, cam, ts, c2w, **files))
            ids.append(len(views) - 1)
        lidar = root / _str(fm["lidar"], f"{what}.lidar") if fm.get("lidar") else None
        frames.append(FrameInfo(index, ts, e2w, tuple(ids), lidar))

    views += _novel_views(meta, root, cameras, {f.index: f for f in frames}, len(views))

    instances = {}
    inst_meta = meta.get("instances", [])
    if not isinstance(inst_meta, list):
        raise ValueError(f"scene.json: instances: expected a list, got {type(inst_meta).__name__}")
    for ii, im in enumerate(inst_meta):
        iid = _int(_get(im, "id", f"instances[{ii}]"), f"instances[{ii}].id")
        instances[iid] = InstanceInfo(
            iid,
            str(im.get("name", iid)),
            _str(im.get("class", "unknown"), f"instances[{ii}].class"),
            _bool(im.get("dynamic", False), f"instances[{ii}].dynamic"),
        )

    frame_pos = {f.index: i for i, f in enumerate(frames)}
    tracks = {}
    for ti, tm in enumerate(meta.get("tracks", [])):
        what = f"tracks[{ti}]"
        tid = _int(_get(tm, "id", what), f"{what}.id")
        poses = torch.eye(4).repeat(len(frames), 1, 1)
        valid = torch.zeros(len(frames), dtype=torch.bool)
        o2w = _get(tm, "object_to_world", what)
        if not isinstance(o2w, dict):
            raise ValueError(
                f"scene.json: {what}.object_to_world: expected an object (frame -> 4x4), got {o2w!r}"
            )
        for key, mat in o2w.items():
            fk = _int(key, f"{what}.object_to_world key")
            if fk in frame_pos:
                poses[frame_pos[fk]] = _pose(mat, f"{what}.object_to_world[{key}]")
                valid[frame_pos[fk]] = True
        lwh = _matrix(tm.get("size_lwh", [0.0, 0.0, 0.0]), (3,), f"{what}.size_lwh")
        tracks[tid] = Track(
            tid,
            str(tm.get("class", "car")),
            lwh,
            poses,
            valid,
            root / tm["mesh"] if tm.get("mesh") else None,
        )

    split = meta.get("split", {})
    if not isinstance(split, dict):
        raise ValueError(f"scene.json: split: expected an object, got {split!r}")
    all_frames = [f.index for f in frames]
    if len(set(all_frames)) != len(all_frames):
        check_split(all_frames, all_frames, "scene.json: frames[].index")
    test_frames = _frame_list(split.get("test_frames", []), "split.test_frames")
    train_frames = _frame_list(
        split.get("train_frames", [f for f in all_frames if f not in test_frames]), "split.train_frames"
    )
    check_split(test_frames, all_frames, "scene.json: split.test_frames")
    check_split(train_frames, all_frames, "scene.json: split.train_frames")

    if check_files:
        missing = [
            p for v in views for p in (v.image, v.depth, v.instances) if p is not None and not p.is_file()
        ] + [f.lidar for f in frames if f.lidar is not None and not f.lidar.is_file()]
        if missing:
            raise FileNotFoundError(
                f"scene {root}: {len(missing)} referenced file(s) missing, "
                f"e.g. {[str(m) for m in missing[:3]]}"
            )

    lidar_paths = {f.index: f.lidar for f in frames}

    def lidar_loader(frame: int) -> LidarFrame:
        if frame not in frame_pos:
            raise FileNotFoundError(
                f"scene {root}: no LiDAR for frame {frame}: the scene has no such frame "
                f"(frames {min(all_frames)}..{max(all_frames)})"
            )
        p = lidar_paths.get(frame)
        if p is None:
            raise FileNotFoundError(f"scene {root}: no LiDAR for frame {frame}")
        return _read_lidar(p)

    scene = Scene(
        name=str(meta.get("name", root.name)),
        root=root,
        cameras_info=cameras,
        frames=frames,
        views=views,
        instances=instances,
        tracks=tracks,
        train_frames=train_frames,
        test_frames=test_frames,
        scale=float(scale),
        lidar_loader=lidar_loader if any(lidar_paths.values()) else None,
    )
    if check_files and validate != "none":
        validate_scene(scene, full=validate == "full").raise_if_errors()
    return scene
