"""A procedural driving segment in the benchmark scene format, at any size.

:func:`make_segment` writes a scene that :func:`~vadgs.data.load_scene` reads and that passes
``vadgs check --full``: a straight street (road with lane markings, parking strips, raised
sidewalks), rows of box buildings of varied heights with window-grid facades, traffic signs whose
boards sit above the LiDAR's vertical field of view (the paper's failure case), parked cars and
rigidly moving cars with tracks. The ego drives down the street (10 m/s, 10 Hz by default) with a
Waymo-like rig of up to five cameras and a spinning 64-beam LiDAR.

Everything is ray cast with Embree on the same triangles (boxes), so colour, z-depth, instance
ids and LiDAR agree exactly: a LiDAR point projected into a view lands on a pixel whose depth is
the point's depth (the rig, the ray casting and the shading: :mod:`vadgs.data.synthetic_sensors`).
Colour is a procedural albedo (a function of the surface point in the box's
own frame, so every view, and a moving car's every pose, agrees) times a Lambert sun plus
ambient; there are no shadows and no camera noise. Sky: depth 0, instance 0.

Frames are rendered and written one at a time (optionally by a process pool), so memory stays
bounded at any size; the output is deterministic for a seed. ``benchmarks/make_segment.py`` is the
command line (presets ``tiny``, ``mid``, ``waymo``).
"""

from __future__ import annotations

import dataclasses
import json
import math
import multiprocessing
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from vadgs.checks import Checked, checked, choice_field, float_field, int_field
from vadgs.data.assemble import MAX_IMAGE_PIXELS
from vadgs.data.synthetic_sensors import (
    LIDAR_IN_EGO,
    RIG,
    BoxKind,
    RayCaster,
    SegmentBoxes,
    SegmentWorld,
    box_triangles,
    lidar_scan,
    render_view,
    rig_cam_to_ego,
)

__all__ = ["SegmentConfig", "check_segment_folder", "make_segment"]

_ROAD_HALF = 9.0  # |y| < 7: four 3.5 m lanes; 7 < |y| < 9: parking strips
_WALK = 4.0  # sidewalk width in front of the buildings
_GROUND = 22.0  # the sidewalk boxes' width: on under the buildings, so alleys and setbacks show ground
_CURB = 0.15  # sidewalk height
_LANES = (-5.25, -1.75, 1.75, 5.25)  # lane centres; traffic drives on the right (+x at y < 0)

_SIGN_COLORS = ((0.1, 0.35, 0.75), (0.8, 0.15, 0.12), (0.1, 0.55, 0.25))

#: The most LiDAR points per frame :func:`make_segment` casts (about 1.6 rays each): 25 Waymo
#: TOP sweeps, 6.4M rays, about 0.5 GB of ray arrays.
MAX_SEGMENT_LIDAR_POINTS = 4_000_000
#: The most objects of each kind (moving cars, parked cars, signs).
MAX_SEGMENT_OBJECTS = 1000


def _vfov(name: str, value: Any) -> tuple[float, float]:
    """``(min, max)`` elevation in degrees: two finite numbers, ``-90 <= min < max <= 90``."""
    try:
        lo, hi = (float_field(-90, 90)(name, v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(
            f"{name}: expected (min, max) degrees with -90 <= min < max <= 90, got {value!r}"
        ) from None
    if not lo < hi:
        raise ValueError(f"{name}: expected (min, max) degrees with min < max, got {value!r}")
    return (lo, hi)


@dataclass(frozen=True)
class SegmentConfig(Checked):
    """What :func:`make_segment` writes.

    Attributes:
        frames: number of frames.
        cameras: how many cameras of :data:`RIG` (1–5, in its order: front, front_left,
            front_right, side_left, side_right).
        width: image width (all cameras).
        height: image height of the front cameras.
        side_height: image height of the side cameras (None: ``height``; Waymo: 886).
        hfov_deg: horizontal field of view of every camera.
        lidar_points: LiDAR points per frame (exactly, unless the scene offers fewer hits).
        moving_cars: rigidly moving cars (with tracks): alternately overtaken on the right and
            oncoming.
        parked_cars: static cars on the parking strips.
        signs: traffic signs; boards at 5.3–6.3 m, above every beam of the LiDAR within range.
        seed: the random layout (building sizes and colours, car colours, sign places), >= 0.
        speed: ego speed in m/s.
        rate_hz: frame rate.
        image_format: ``"jpg"`` or ``"png"``.
        jpeg_quality: JPEG quality (1-100).
        lidar_beams: beams of the spinning LiDAR.
        lidar_vfov: its vertical field of view ``(min, max)`` in degrees, ``-90 <= min < max <= 90``.

    Sizes are bounded so that a typo fails here rather than as an allocation of gigabytes: each
    image at most :data:`~vadgs.data.assemble.MAX_IMAGE_PIXELS` pixels, ``lidar_points`` at most
    :data:`MAX_SEGMENT_LIDAR_POINTS`, ``lidar_beams`` 4096, ``frames`` 100,000, 1000 objects of a
    kind, ``speed`` 100 m/s, ``lidar_range`` 1000 m.
        lidar_range: its range in metres.
    """

    frames: int = checked(4, int_field(1, 100_000))
    cameras: int = checked(2, int_field(1, len(RIG)))
    width: int = checked(64, int_field(1, 1 << 16))
    height: int = checked(48, int_field(1, 1 << 16))
    side_height: int | None = checked(None, int_field(1, 1 << 16, optional=True))
    hfov_deg: float = checked(50.4, float_field(0, 170, lo_open=True, hi_open=True))
    lidar_points: int = checked(2000, int_field(1, MAX_SEGMENT_LIDAR_POINTS))
    moving_cars: int = checked(3, int_field(0, MAX_SEGMENT_OBJECTS))
    parked_cars: int = checked(4, int_field(0, MAX_SEGMENT_OBJECTS))
    signs: int = checked(2, int_field(0, MAX_SEGMENT_OBJECTS))
    seed: int = checked(0, int_field(0, 2**63 - 1))
    speed: float = checked(10.0, float_field(0, 100))
    rate_hz: float = checked(10.0, float_field(0, 1000, lo_open=True))
    image_format: str = checked("jpg", choice_field(("jpg", "png")))
    jpeg_quality: int = checked(90, int_field(1, 100))
    lidar_beams: int = checked(64, int_field(1, 4096))
    lidar_vfov: tuple[float, float] = checked((-17.6, 2.4), _vfov)
    lidar_range: float = checked(75.0, float_field(0, 1000, lo_open=True))

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("height", "side_height"):
            h = getattr(self, name)
            if h is not None and h * self.width > MAX_IMAGE_PIXELS:
                raise ValueError(
                    f"width, {name}: {self.width}x{h} is {h * self.width} pixels per image; expected at "
                    f"most {MAX_IMAGE_PIXELS} (the largest image the loaders read)"
                )

    @property
    def camera_names(self) -> list[str]:
        """The rig's cameras in use."""
        return list(RIG)[: self.cameras]

    def image_size(self, camera: str) -> tuple[int, int]:
        """``(H, W)`` of a camera."""
        if RIG[camera][1] and self.side_height is not None:
            return self.side_height, self.width
        return self.height, self.width


# ---------------------------------------------------------------------------------------------------
# the world: boxes with a bottom-centre origin


def _yaw_pose(x: float, y: float, z: float, yaw: float = 0.0) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0, x], [s, c, 0, y], [0, 0, 1, z], [0, 0, 0, 1]], dtype=np.float64)


def _build_world(cfg: SegmentConfig) -> SegmentWorld:
    """The street, its instances, the moving cars' poses and the ego trajectory (deterministic)."""
    rng = np.random.default_rng(cfg.seed)
    dt = 1.0 / cfg.rate_hz
    t = np.arange(cfg.frames) * dt
    travel = cfg.speed * float(t[-1])
    x0, x1 = -120.0, travel + 160.0  # the street around the drive, with room to see down it

    size, pose, kind, inst, color, track = [], [], [], [], [], []
    instances: list[dict] = []

    def add(name, cls, dims, T, k, rgb, dynamic=False, tr=-1, iid=None):
        if iid is None:
            iid = len(instances) + 1
            instances.append({"id": iid, "name": name, "class": cls, "dynamic": dynamic})
        size.append(dims)
        pose.append(T)
        kind.append(k)
        inst.append(iid)
        color.append(rgb)
        track.append(tr)
        return iid

    add(
        "road",
        "road",
        (x1 - x0, 2 * _ROAD_HALF, 0.2),
        _yaw_pose((x0 + x1) / 2, 0, -0.2),
        BoxKind.ROAD,
        (0.3, 0.3, 0.32),
    )
    for side, name in ((1, "sidewalk_left"), (-1, "sidewalk_right")):
        y = side * (_ROAD_HALF + _GROUND / 2)
        walk = _yaw_pose((x0 + x1) / 2, y, -0.2)
        add(name, "sidewalk", (x1 - x0, _GROUND, 0.2 + _CURB), walk, BoxKind.WALKWAY, (0.62, 0.6, 0.56))
    palette = np.array(
        [[0.72, 0.62, 0.5], [0.6, 0.6, 0.62], [0.75, 0.7, 0.6], [0.55, 0.42, 0.36], [0.8, 0.78, 0.72],
         [0.5, 0.55, 0.6], [0.68, 0.5, 0.4], [0.85, 0.8, 0.65]]
    )  # fmt: skip
    y_front = _ROAD_HALF + _WALK
    for side in (1, -1):
        x = x0
        while x < x1:
            length = float(rng.uniform(10, 24))
            gap = float(rng.choice([0.0, 0.0, 0.0, 4.0]))
            height = float(rng.uniform(7, 30))
            depth = float(rng.uniform(10, 16))
            setback = float(rng.uniform(0, 1.5))
            rgb = np.clip(palette[rng.integers(len(palette))] + rng.uniform(-0.06, 0.06, 3), 0, 1)
            y = side * (y_front + setback + depth / 2)
            add(f"building_{len(instances) + 1}", "building", (length, depth, height),
                _yaw_pose(x + length / 2, y, 0), BoxKind.BUILDING, tuple(rgb))  # fmt: skip
            x += length + gap
    for k in range(cfg.signs):
        side = 1 if k % 2 == 0 else -1
        x = float(rng.uniform(15, max(travel + 40, 45)))
        y = side * (_ROAD_HALF + 0.6)
        pole = _yaw_pose(x, y, _CURB)
        iid = add(f"sign_{k}", "sign", (0.12, 0.12, 6.3), pole, BoxKind.POLE, (0.55, 0.56, 0.58))
        board_y = y - side * 0.7  # the board hangs over the road's edge, facing the oncoming ego
        add("", "", (0.06, 1.4, 1.0), _yaw_pose(x - 0.1, board_y, 5.3), BoxKind.BOARD,
            _SIGN_COLORS[k % 3], iid=iid)  # fmt: skip
    car_size = (4.4, 1.9, 1.5)
    for k in range(cfg.parked_cars):
        side = 1 if k % 2 == 0 else -1
        x = float(rng.uniform(-10, travel + 60))
        parked = _yaw_pose(x, side * 8.0, 0, 0 if side < 0 else math.pi)
        add(f"parked_car_{k}", "car", car_size, parked, BoxKind.CAR, tuple(rng.uniform(0.1, 0.9, 3)))

    duration = float(t[-1]) if cfg.frames > 1 else 1.0
    n_on = cfg.moving_cars // 2
    car_poses = np.zeros((cfg.moving_cars, cfg.frames, 4, 4))
    for k in range(cfg.moving_cars):
        if k % 2 == 0:  # same direction on the outer lane, slower: the ego overtakes it
            v, lane = 0.8 * cfg.speed, _LANES[0]
            start = 10.0 + 12.0 * (k // 2)
            yaw = 0.0
        else:  # oncoming, meeting the ego at a fraction of the drive
            j = k // 2
            v, lane = -max(0.8 * cfg.speed, 6.0), _LANES[2 + j % 2]
            meet = duration * (j + 1) / (n_on + 1)
            start = 25.0 + (cfg.speed - v) * meet
            yaw = math.pi
        for f, tf in enumerate(t):
            car_poses[k, f] = _yaw_pose(start + v * tf, lane, 0, yaw)
        add(
            f"car_{k}",
            "car",
            car_size,
            car_poses[k, 0],
            BoxKind.CAR,
            tuple(rng.uniform(0.1, 0.9, 3)),
            dynamic=True,
            tr=k,
        )

    sway = 0.3 * np.sin(2 * np.pi * t / 8.0)
    ego = np.stack([
        _yaw_pose(cfg.speed * tf, _LANES[1] + s, 0.0,
                  math.atan2(0.3 * 2 * np.pi / 8.0 * math.cos(2 * np.pi * tf / 8.0), max(cfg.speed, 1e-6)))
        for tf, s in zip(t, sway)
    ])  # fmt: skip
    boxes = SegmentBoxes(
        np.array(size, dtype=np.float32),
        np.stack(pose),
        np.array(kind),
        np.array(inst),
        np.array(color, dtype=np.float32),
        np.array(track),
    )
    return SegmentWorld(boxes, instances, car_poses, ego)


# ---------------------------------------------------------------------------------------------------
# the cameras' intrinsics


def _intrinsics(cfg: SegmentConfig, camera: str) -> np.ndarray:
    h, w = cfg.image_size(camera)
    f = (w / 2) / math.tan(math.radians(cfg.hfov_deg) / 2)
    return np.array([[f, 0, w / 2 - 0.5], [0, f, h / 2 - 0.5], [0, 0, 1.0]])


# ---------------------------------------------------------------------------------------------------
# writing


def _names(cfg: SegmentConfig, frame: int) -> str:
    return f"{frame:0{max(3, len(str(cfg.frames - 1)))}d}"


def _view_files(cfg: SegmentConfig, camera: str, frame: int) -> dict[str, str]:
    n = _names(cfg, frame)
    return {
        "image": f"images/{camera}/{n}.{cfg.image_format}",
        "depth": f"depth/{camera}/{n}.npz",
        "instances": f"instances/{camera}/{n}.png",
    }


_STATE: dict = {}


def _init_worker(cfg: SegmentConfig, world: SegmentWorld, out: Path) -> None:
    _STATE.update(cfg=cfg, world=world, out=out)


def _write_frame(frame: int) -> int:
    """Render and write every view and the LiDAR of one frame; returns its LiDAR point count."""
    cfg, world, out = _STATE["cfg"], _STATE["world"], _STATE["out"]
    caster = RayCaster(world, frame)
    ego = world.ego_to_world[frame]
    for camera in cfg.camera_names:
        files = _view_files(cfg, camera, frame)
        c2w = ego @ rig_cam_to_ego(camera)
        rgb, depth, inst = render_view(caster, _intrinsics(cfg, camera), c2w, cfg.image_size(camera))
        img = Image.fromarray(rgb)
        if cfg.image_format == "jpg":
            img.save(out / files["image"], quality=cfg.jpeg_quality)
        else:
            img.save(out / files["image"], compress_level=3)
        np.savez_compressed(out / files["depth"], depth=depth)
        Image.fromarray(inst).save(out / files["instances"], compress_level=3)
    origin = (ego @ np.append(LIDAR_IN_EGO, 1.0))[:3]
    yaw = math.atan2(ego[1, 0], ego[0, 0])
    pts, ids = lidar_scan(
        caster, origin, yaw, cfg.lidar_beams, cfg.lidar_vfov, cfg.lidar_points, cfg.lidar_range
    )
    np.savez_compressed(out / f"lidar/{_names(cfg, frame)}.npz", points=pts, instance=ids,
                        origin=origin.astype(np.float32))  # fmt: skip
    return len(pts)


def _mat(T: np.ndarray) -> list[list[float]]:
    return [[round(float(v), 6) for v in row] for row in T]


def _write_meshes(cfg: SegmentConfig, world: SegmentWorld, out: Path) -> None:
    import trimesh

    b = world.boxes
    static = b.track < 0
    tris = box_triangles(b.size[static], b.pose[static])
    mesh = trimesh.Trimesh(tris.reshape(-1, 3), np.arange(len(tris) * 3).reshape(-1, 3), process=False)
    mesh.merge_vertices()
    mesh.export(out / "gt" / "static.ply")
    np.save(out / "gt" / "static_face_instance.npy", np.repeat(b.instance[static], 12).astype(np.uint16))
    for i in np.flatnonzero(~static):
        tris = box_triangles(b.size[i : i + 1], np.eye(4)[None])
        car = trimesh.Trimesh(tris.reshape(-1, 3), np.arange(36).reshape(-1, 3), process=False)
        car.merge_vertices()
        car.export(out / "gt" / f"object_{b.instance[i]}.ply")


def _scene_json(cfg: SegmentConfig, world: SegmentWorld) -> dict:
    cams = cfg.camera_names
    cameras = {}
    for c in cams:
        h, w = cfg.image_size(c)
        cameras[c] = {
            "width": w,
            "height": h,
            "K": _mat(_intrinsics(cfg, c)),
            "cam_to_ego": _mat(rig_cam_to_ego(c)),
        }
    frames = []
    for f in range(cfg.frames):
        ego = world.ego_to_world[f]
        views = [
            {"camera": c, **_view_files(cfg, c, f), "cam_to_world": _mat(ego @ rig_cam_to_ego(c))}
            for c in cams
        ]
        frames.append({
            "index": f, "timestamp": round(f / cfg.rate_hz, 6), "ego_to_world": _mat(ego),
            "lidar": f"lidar/{_names(cfg, f)}.npz", "views": views,
        })  # fmt: skip
    b = world.boxes
    tracks = []
    for i in np.flatnonzero(b.track >= 0):
        poses = world.car_poses[b.track[i]]
        tracks.append({
            "id": int(b.instance[i]), "class": "car", "size_lwh": [float(v) for v in b.size[i]],
            "object_to_world": {str(f): _mat(poses[f]) for f in range(cfg.frames)},
            "mesh": f"gt/object_{b.instance[i]}.ply",
        })  # fmt: skip
    test = list(range(2, cfg.frames, 4))
    return {
        "name": "segment",
        "conventions": {
            "world": "right-handed, z up, metres",
            "camera": "OpenCV: x right, y down, z forward; cam_to_world maps camera to world coordinates",
            "pixels": "integer pixel coordinates are pixel centres (OpenCV); K is 3x3",
            "depth": "z-depth in metres along the camera's optical axis, 0 where no surface (sky); "
            "float16 in npz key 'depth'",
            "instances": "uint16 PNG of instance ids, 0 = sky; ids are listed under 'instances'",
            "lidar": "npz: points (N,3) float32 world, instance (N,) uint16, "
            "origin (3,) sensor position in world",
            "objects": "object frame: origin at the bottom centre of the box, x forward, z up",
        },
        "generator": {"module": "vadgs.data.synthetic", "config": _config_json(cfg)},
        "cameras": cameras,
        "lidar": {
            "profile": "waymo" if cfg.lidar_beams == 64 else "custom",
            "beams": cfg.lidar_beams,
            "vfov": list(cfg.lidar_vfov),
            "max_range": cfg.lidar_range,
            "points_per_frame": cfg.lidar_points,
            "origin_in_ego": LIDAR_IN_EGO.tolist(),
        },
        "instances": world.instances,
        "tracks": tracks,
        "gt_static_mesh": "gt/static.ply",
        "split": {
            "test_frames": test,
            "train_frames": [f for f in range(cfg.frames) if f not in set(test)],
            "rule": "every fourth frame, with all of its cameras, is held out for testing",
        },
        "frames": frames,
    }


def _config_json(cfg: SegmentConfig) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(cfg).items()}


def _progress(it: Iterator[int], total: int, show: bool) -> Iterator[int]:
    if not show:
        return it
    from tqdm.auto import tqdm

    return tqdm(it, total=total, desc="segment", unit="frame")


def _segment_files(cfg: SegmentConfig, world: SegmentWorld) -> list[str]:
    """Every file :func:`make_segment` writes for ``cfg`` (relative paths; ``scene.json`` last)."""
    files = ["gt/static.ply", "gt/static_face_instance.npy"]
    b = world.boxes
    files += [f"gt/object_{b.instance[i]}.ply" for i in np.flatnonzero(b.track >= 0)]
    for f in range(cfg.frames):
        files += [path for c in cfg.camera_names for path in _view_files(cfg, c, f).values()]
        files.append(f"lidar/{_names(cfg, f)}.npz")
    return [*files, "scene.json"]


def check_segment_folder(out: str | Path, overwrite: bool, flag: str = "overwrite=True") -> list[Path]:
    """Check ``out`` for :func:`make_segment`: the files of an earlier segment to replace (``[]``: none).

    A new path or an empty folder is fine. A folder that :func:`make_segment` wrote (its manifest,
    :mod:`vadgs.runfolder`) is replaced with ``overwrite``: the files it wrote, never the folder's
    other files.
    Any other non-empty folder is refused with or without ``overwrite``.

    Raises:
        ValueError: one line naming ``out`` (and ``flag`` only for a segment make_segment wrote).
        vadgs.runfolder.ManifestError: an unreadable manifest, or an entry outside ``out``.
    """
    from vadgs.runfolder import check_removable, foreign_entries, manifest_kind, read_manifest

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"out: {out} exists and is a file; give a folder")
    entries = foreign_entries(out)
    if not entries:
        return []
    if read_manifest(out) is not None and manifest_kind(out) != "segment":  # a run or an output folder
        raise ValueError(
            f"out: {out} holds a vadgs run or output folder, not a segment; give a new or empty folder"
        )
    if read_manifest(out) is None:
        shown = ", ".join(entries[:5]) + (f", ... ({len(entries)} entries)" if len(entries) > 5 else "")
        raise ValueError(
            f"out: {out} exists and is not empty (holds {shown}) nor a segment that make_segment wrote; "
            "nothing was changed: give a new or empty folder"
        )
    if not overwrite:
        raise ValueError(
            f"out: {out} exists and is not empty: a segment make_segment wrote ({flag} replaces it)"
        )
    return [*check_removable(out), out / ".vadgs" / "manifest.json"]


def make_segment(
    out: str | Path,
    config: SegmentConfig | None = None,
    *,
    workers: int = 1,
    progress: bool = True,
    overwrite: bool = False,
    **fields: Any,
) -> Path:
    """Write a procedural driving segment in the benchmark scene format; see the module docstring.

    Args:
        out: the scene folder to create.
        config: the scene's :class:`SegmentConfig` (default: the tiny default one).
        workers: processes rendering frames in parallel (1: in this process).
        progress: show a progress bar over frames.
        overwrite: replace the segment in ``out`` that make_segment wrote: the files it wrote, not
            the folder's other files (:func:`check_segment_folder`). Refused otherwise when ``out``
            is not empty; a non-empty folder make_segment did not write is refused either way.
        **fields: :class:`SegmentConfig` fields overriding ``config`` (``frames=200``, ...).

    Returns:
        ``out``, holding ``scene.json`` (written last, so an interrupted run leaves no loadable
        scene), ``images/``, ``depth/``, ``instances/``, ``lidar/`` and ``gt/``.

    Raises:
        ValueError: on a bad setting (the message names it), an existing non-empty ``out``
            without ``overwrite``, or one that make_segment did not write.

    Example:
        >>> import tempfile
        >>> from vadgs.data import load_scene
        >>> folder = make_segment(tempfile.mkdtemp() + "/seg", frames=2, width=32, height=24, progress=False)
        >>> scene = load_scene(folder, validate="full")
        >>> scene.num_views, scene.camera_names, len(scene.tracks)
        (4, ['front', 'front_left'], 3)
    """
    cfg = dataclasses.replace(config or SegmentConfig(), **fields)
    if not (isinstance(workers, int) and workers >= 1):
        raise ValueError(f"workers: expected a positive integer, got {workers!r}")
    out = Path(out)
    old = check_segment_folder(out, overwrite)
    world = _build_world(cfg)
    written = [out / rel for rel in _segment_files(cfg, world)]
    replaced = set(old)
    theirs = [p for p in written if p not in replaced and (p.exists() or p.is_symlink())]
    if theirs:  # a file of the user's where the segment writes one (in a folder make_segment wrote)
        raise ValueError(
            f"out: {theirs[0]} is not a file make_segment wrote ({len(theirs)} such), where the segment "
            "writes one; nothing was changed: move it away or give a new folder"
        )
    from vadgs.runfolder import record_files, remove_files

    remove_files(out, old)
    out.mkdir(parents=True, exist_ok=True)
    record_files(out, written, kind="segment")  # before they are written: a killed run's are known too
    for sub in ("images", "depth", "instances"):
        for c in cfg.camera_names:
            (out / sub / c).mkdir(parents=True, exist_ok=True)
    (out / "lidar").mkdir(parents=True, exist_ok=True)
    (out / "gt").mkdir(parents=True, exist_ok=True)
    _write_meshes(cfg, world, out)
    frames = range(cfg.frames)
    if workers == 1:
        _init_worker(cfg, world, out)
        for _ in _progress(map(_write_frame, frames), cfg.frames, progress):
            pass
    else:
        ctx = multiprocessing.get_context("spawn")
        with ctx.Pool(workers, initializer=_init_worker, initargs=(cfg, world, out)) as pool:
            for _ in _progress(pool.imap(_write_frame, frames), cfg.frames, progress):
                pass
    from vadgs.io import atomic_write

    atomic_write(out / "scene.json", json.dumps(_scene_json(cfg, world), indent=1))
    return out
