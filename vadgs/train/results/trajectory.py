r"""Camera paths for videos: the ego path (shifted), or a path through a photo collection.

A **trajectory** is one camera of the rig following the ego vehicle through the scene's frames,
optionally shifted in the ego frame (``shift_ego_m = (0, 2, 0)``: 2 m to the left, a lane change,
as the scene's novel views):

.. math::

    T_{cam \to world}(t) = T_{ego \to world}(t)\, T(\text{shift})\, T_{cam \to ego}

With ``frames_between = n > 0``, ``n`` poses are inserted between consecutive frames: rotations are
slerped, translations interpolated linearly (:func:`~vadgs.geometry.keyframe_path`). The moving
objects are interpolated the same way between the two frames when their track is valid at both,
else they take the pose (and validity) of the nearest frame
(:func:`~vadgs.train.results.video.object_poses_at`). Time ``t`` is measured in frame positions
(``t = 2.5`` is half-way between ``scene.frames[2]`` and ``scene.frames[3]``).

Without ``ego_to_world`` or ``cam_to_ego`` the camera's own poses are interpolated instead (when it
has a view at every frame) and only ``shift_ego_m = (0, 0, 0)`` is accepted.

A **photo collection** (a COLMAP scene: one photo per frame, cameras of several sizes) has no ego
path. Two trajectories need none, every scene offers them (:func:`trajectory_choices`;
:func:`make_trajectory` builds one from its name, ``vadgs render --video --trajectory``):

- ``interpolate`` (:func:`interpolated_trajectory`): a smooth path through the training cameras
  in frame (name) order, as gsplat's ``generate_interpolated_path``
  (:func:`~vadgs.geometry.spline_path`). The camera centres and look-at points (``focus`` ahead of
  each camera: the median depth of the SfM points) follow a centripetal Catmull-Rom spline, which
  passes through every camera without overshoot or cusps; every pose looks at its look-at point
  with the scene's up (:func:`scene_up`), so the path does not roll with a photo taken sideways.
- ``orbit`` (:func:`orbit_trajectory`): a circle around the scene's centre (the point nearest to
  every training camera's optical axis, as multinerf's ``focus_point_fn``) in the plane normal to
  the up, at the cameras' median distance and mean height, looking at the centre, starting at the
  first training camera and turning the way the cameras do, as nerfstudio's orbit
  (:func:`~vadgs.geometry.orbit_path`).

Both render with the intrinsics and image size of one camera (:func:`default_video_camera`: the
one with the most training views) and sweep the frame time from the first frame to the last.

The path math is :mod:`vadgs.geometry.camera_path`'s; this module picks the keys from a scene,
names the paths and times them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple, cast

import numpy as np
import torch

from vadgs.data.scene import FrameInfo, Scene
from vadgs.geometry.camera import invert_rigid, level_up
from vadgs.geometry.camera_path import keyframe_path, orbit_path, spline_path

__all__ = [
    "INTERPOLATE_BETWEEN",
    "MAX_FRAMES",
    "ORBIT_FRAMES",
    "Trajectory",
    "default_video_camera",
    "ego_trajectory",
    "interpolated_trajectory",
    "make_trajectory",
    "orbit_trajectory",
    "parse_trajectory",
    "scene_up",
    "trajectory_choices",
    "trajectory_length",
]

#: ``interpolate``: poses between consecutive training cameras unless ``frames_between`` says.
INTERPOLATE_BETWEEN = 8

#: ``orbit``: the number of poses of the circle unless ``orbit:FRAMES`` says.
ORBIT_FRAMES = 60

#: The most poses :func:`make_trajectory` builds unless its ``max_frames`` says (``vadgs render
#: --max-frames``): 100 000 frames are 2.8 hours at 10 fps; ``orbit:100000000`` would fill memory.
MAX_FRAMES = 100_000


class Trajectory(NamedTuple):
    """Camera poses of a video.

    Attributes:
        cam_to_world: ``(P, 4, 4)``.
        time: ``(P,)`` float64 frame positions (see the module docstring).
        camera: the rig camera (its intrinsics and image size are used).
    """

    cam_to_world: torch.Tensor
    time: torch.Tensor
    camera: str


def parse_trajectory(spec: str) -> tuple[float, float, float]:
    """Ego-frame shift of a trajectory: ``"ego"``, ``"shift:M"`` (``(0, M, 0)``, + = left), ``"shift:X,Y,Z"``.

    Raises:
        ValueError: for another spec, or a shift that is not finite (``shift:nan``, ``shift:inf``).

    Example:
        >>> parse_trajectory("ego"), parse_trajectory("shift:-2"), parse_trajectory("shift:1,0,0.5")
        ((0.0, 0.0, 0.0), (0.0, -2.0, 0.0), (1.0, 0.0, 0.5))
        >>> parse_trajectory("shift:nan")
        Traceback (most recent call last):
        ...
        ValueError: trajectory: expected finite metres in shift:METRES or shift:X,Y,Z, got 'shift:nan'
    """
    if spec == "ego":
        return (0.0, 0.0, 0.0)
    if spec.startswith("shift:"):
        try:
            parts = [float(p) for p in spec[len("shift:") :].split(",")]
        except ValueError:
            parts = []
        if len(parts) in (1, 3) and not all(math.isfinite(p) for p in parts):
            raise ValueError(
                f"trajectory: expected finite metres in shift:METRES or shift:X,Y,Z, got {spec!r}"
            )
        if len(parts) == 1:
            return (0.0, parts[0], 0.0)
        if len(parts) == 3:
            return (parts[0], parts[1], parts[2])
    raise ValueError(f"trajectory: expected 'ego', 'shift:METRES' or 'shift:X,Y,Z', got {spec!r}")


def ego_trajectory(
    scene: Scene,
    camera: str = "front",
    shift_ego_m: Sequence[float] = (0.0, 0.0, 0.0),
    frames_between: int = 0,
) -> Trajectory:
    """The poses of one rig camera along the ego path (see the module docstring).

    Args:
        scene: the scene.
        camera: a camera of the rig.
        shift_ego_m: ``(3,)`` shift in the ego frame (x forward, y left, z up), metres.
        frames_between: poses inserted between consecutive frames.

    Returns:
        :class:`Trajectory` with ``(len(frames) - 1) * (frames_between + 1) + 1`` poses.

    Raises:
        ValueError: for an unknown camera, a negative ``frames_between``, or a shift on a scene
            without ego poses.

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> scene = load_scene(sample_scene_path())
        >>> traj = ego_trajectory(scene, "front", (0, 2, 0), frames_between=1)
        >>> traj.cam_to_world.shape, traj.time[:3].tolist()
        (torch.Size([15, 4, 4]), [0.0, 0.5, 1.0])
    """
    if camera not in scene.cameras_info:
        raise ValueError(f"camera: expected one of {scene.camera_names}, got {camera!r}")
    if int(frames_between) < 0:
        raise ValueError(f"frames_between: expected >= 0, got {frames_between}")
    shift = torch.eye(4)
    shift[:3, 3] = torch.as_tensor([float(c) for c in shift_ego_m])
    c2e = scene.cameras_info[camera].cam_to_ego
    ego_to_world = [f.ego_to_world for f in scene.frames if f.ego_to_world is not None]
    if c2e is not None and len(ego_to_world) == len(scene.frames):
        keys = torch.stack([e2w @ shift @ c2e for e2w in ego_to_world])
    else:
        if bool(shift[:3, 3].any()):
            raise ValueError(
                f"shift_ego_m: scene {scene.name!r} has no ego poses (ego_to_world, cam_to_ego); "
                "only the 'ego' trajectory (no shift) is available"
            )
        missing = next((f.index for f in scene.frames if not _has_view(scene, f, camera)), None)
        if missing is not None:
            raise ValueError(
                f"camera: scene {scene.name!r} has no ego poses and no view of {camera!r} at frame "
                f"{missing}, so no ego path; it offers {trajectory_choices(scene, camera)}"
            )
        keys = torch.stack([scene.views[scene.view_id(f.index, camera)].cam_to_world for f in scene.frames])
    path = keyframe_path(keys, int(frames_between))
    return Trajectory(path.cam_to_world, path.t, camera)


def _has_view(scene: Scene, frame: FrameInfo, camera: str) -> bool:
    return any(scene.views[v].camera == camera for v in frame.view_ids)


def _has_ego_poses(scene: Scene, camera: str) -> bool:
    return scene.cameras_info[camera].cam_to_ego is not None and all(
        f.ego_to_world is not None for f in scene.frames
    )


def default_video_camera(scene: Scene) -> str:
    """The camera whose intrinsics and size a video takes.

    ``front`` if the rig has one, else the camera of the most training views (the first of the
    rig on a tie).

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> default_video_camera(load_scene(sample_scene_path()))
        'front'
    """
    if "front" in scene.cameras_info:
        return "front"
    counts = {name: 0 for name in scene.camera_names}
    for v in scene.train_views or range(scene.num_views):
        counts[scene.views[v].camera] += 1
    return max(counts, key=lambda name: counts[name])  # the first of the maximal ones


def trajectory_choices(scene: Scene, camera: str | None = None) -> list[str]:
    """The trajectories ``scene`` offers for ``camera`` (default :func:`default_video_camera`).

    ``ego`` when the rig has ego poses or the camera a view at every frame, ``shift:...`` with ego
    poses only; ``interpolate`` and ``orbit`` always. The first is the default: ``ego`` with ego
    poses, else ``interpolate`` (a photo collection of one camera has a view of it at every
    frame, but its ``ego`` path is a jump from photo to photo, test photos included).

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> trajectory_choices(load_scene(sample_scene_path()))
        ['ego', 'shift:METRES', 'shift:X,Y,Z', 'interpolate', 'orbit', 'orbit:FRAMES']
    """
    camera = camera or default_video_camera(scene)
    if camera not in scene.cameras_info:
        raise ValueError(f"camera: expected one of {scene.camera_names}, got {camera!r}")
    if _has_ego_poses(scene, camera):
        return ["ego", "shift:METRES", "shift:X,Y,Z", "interpolate", "orbit", "orbit:FRAMES"]
    ego = ["ego"] if all(_has_view(scene, f, camera) for f in scene.frames) else []
    return ["interpolate", *ego, "orbit", "orbit:FRAMES"]


def _plan(
    scene: Scene, spec: str | None, camera: str | None, frames_between: int | None
) -> tuple[str, str, object, int]:
    """``(camera, kind, argument, poses)`` of the trajectory ``spec``, checked, nothing built.

    ``kind`` is ``ego`` (argument: the shift), ``interpolate`` (poses between the keys) or
    ``orbit`` (its pose count); ``poses`` is the number of poses it will have.
    """
    camera = camera or default_video_camera(scene)
    choices = trajectory_choices(scene, camera)
    spec = choices[0] if spec is None else spec.strip()
    if frames_between is not None and int(frames_between) < 0:
        raise ValueError(f"frames_between: expected >= 0, got {frames_between}")
    if spec == "ego" or spec.startswith("shift:"):
        no_ego = "ego" not in choices if spec == "ego" else "shift:METRES" not in choices
        if no_ego:
            raise ValueError(
                f"trajectory: scene {scene.name!r} has no ego path for camera {camera!r} (no ego "
                f"poses{'' if spec.startswith('shift:') else ', no view of it at every frame'}); "
                f"it offers {choices}"
            )
        try:
            shift = parse_trajectory(spec)
        except ValueError as e:
            if "finite" in str(e):
                raise
            raise ValueError(f"trajectory: expected one of {choices}, got {spec!r}") from None
        between = int(frames_between or 0)
        return camera, "ego", shift, (len(scene.frames) - 1) * (between + 1) + 1
    if spec == "interpolate":
        between = INTERPOLATE_BETWEEN if frames_between is None else int(frames_between)
        _, keys, _ = _path_keys(scene, camera)
        return camera, "interpolate", between, (len(keys) - 1) * (between + 1) + 1
    if spec == "orbit" or spec.startswith("orbit:"):
        if frames_between is not None:
            raise ValueError(
                f"frames_between: not used by {spec} (orbit:FRAMES sets its poses), got {frames_between}"
            )
        count = spec[len("orbit:") :] if spec.startswith("orbit:") else str(ORBIT_FRAMES)
        # ASCII digits only (int() takes '²', and refuses a string of over 4300 digits)
        digits = count.lstrip("0")
        if not (count.isascii() and count.isdigit()) or not digits:
            raise ValueError(f"trajectory: expected orbit:FRAMES with FRAMES >= 1, got {spec!r}")
        frames = int(digits) if len(digits) <= 18 else 10**18  # past 10**18: over any bound
        return camera, "orbit", frames, frames
    raise ValueError(f"trajectory: expected one of {choices}, got {spec!r}")


def trajectory_length(
    scene: Scene, spec: str | None = None, camera: str | None = None, frames_between: int | None = None
) -> int:
    """The number of poses :func:`make_trajectory` would build, computed without building them.

    Checks the arguments as :func:`make_trajectory` does (the same errors), so a caller can bound a
    video's length before any work.

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> scene = load_scene(sample_scene_path())
        >>> trajectory_length(scene, "orbit:100000000"), trajectory_length(scene, "ego", frames_between=9)
        (100000000, 71)
    """
    return _plan(scene, spec, camera, frames_between)[3]


def make_trajectory(
    scene: Scene,
    spec: str | None = None,
    camera: str | None = None,
    frames_between: int | None = None,
    max_frames: int | None = MAX_FRAMES,
) -> Trajectory:
    """The trajectory named ``spec`` (one of :func:`trajectory_choices`; None: the scene's default).

    Args:
        scene: the scene.
        spec: ``ego``, ``shift:METRES``, ``shift:X,Y,Z``, ``interpolate``, ``orbit`` or
            ``orbit:FRAMES``; None: ``ego`` with ego poses, else ``interpolate``.
        camera: the camera (default :func:`default_video_camera`).
        frames_between: poses between consecutive frames (``ego``, ``shift``; default 0) or
            training cameras (``interpolate``; default :data:`INTERPOLATE_BETWEEN`); not with
            ``orbit`` (``orbit:FRAMES`` sets its poses).
        max_frames: the most poses it may have (default :data:`MAX_FRAMES`; None: no bound),
            checked before any pose is built (:func:`trajectory_length`).

    Raises:
        ValueError: for a name the scene does not offer (the message lists those it does), a shift
            that is not finite, or more poses than ``max_frames``.

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> scene = load_scene(sample_scene_path())
        >>> len(make_trajectory(scene).time), len(make_trajectory(scene, "orbit:12").time)
        (8, 12)
        >>> make_trajectory(scene, "orbit:100000000")
        Traceback (most recent call last):
        ...
        ValueError: max_frames: expected at most 100000 frames, got 100000000 (orbit:100000000)
    """
    camera, kind, arg, count = _plan(scene, spec, camera, frames_between)
    if max_frames is not None and count > max_frames:
        shown = spec if spec is not None else trajectory_choices(scene, camera)[0]
        between = "" if frames_between is None else f", frames_between {frames_between}"
        raise ValueError(f"max_frames: expected at most {max_frames} frames, got {count} ({shown}{between})")
    if kind == "ego":
        return ego_trajectory(scene, camera, cast(Sequence[float], arg), frames_between or 0)
    if kind == "interpolate":
        return interpolated_trajectory(scene, camera, cast(int, arg))
    return orbit_trajectory(scene, camera, cast(int, arg))


def scene_up(scene: Scene, views: Sequence[int] | None = None) -> torch.Tensor:
    """The scene's up direction ``(3,)`` (unit, float64): :func:`level_up` of its cameras.

    Args:
        scene: the scene.
        views: the views (default: the training views, else all).
    """
    views = list(views) if views is not None else (scene.train_views or list(range(scene.num_views)))
    return level_up(torch.stack([scene.views[v].cam_to_world for v in views]))


def _path_keys(scene: Scene, camera: str | None) -> tuple[str, list[int], torch.Tensor]:
    """The keys of a path: ``(camera, views, (K, 4, 4) float64 cam_to_world)``.

    The camera checked (default :func:`default_video_camera`); one training view per training
    frame, in frame order: the frame's view of ``camera`` if it has one.
    """
    camera = camera or default_video_camera(scene)
    if camera not in scene.cameras_info:
        raise ValueError(f"camera: expected one of {scene.camera_names}, got {camera!r}")
    train = set(scene.train_views) or set(range(scene.num_views))
    keys = []
    for f in scene.frames:
        ids = [v for v in f.view_ids if v in train]
        if ids:
            keys.append(next((v for v in ids if scene.views[v].camera == camera), ids[0]))
    if not keys:
        raise ValueError(f"scene {scene.name!r}: no training view to put a camera path through")
    return camera, keys, torch.stack([scene.views[v].cam_to_world for v in keys]).double()


def _focus_depth(scene: Scene, views: Sequence[int]) -> float:
    """The median depth of the SfM points in ``views`` (10 scene units without SfM points)."""
    pts = scene.sfm_points
    if pts is None or pts.point_idx.numel() == 0:
        return 10.0
    w2c = invert_rigid(torch.stack([v.cam_to_world for v in scene.views]).double())
    z = (w2c[pts.view_idx, 2, :3] * pts.points.double()[pts.point_idx]).sum(-1) + w2c[pts.view_idx, 2, 3]
    z = z[torch.isin(pts.view_idx, torch.tensor(list(views))) & (z > 0)]
    return float(z.median()) if z.numel() else 10.0


def interpolated_trajectory(
    scene: Scene, camera: str | None = None, frames_between: int = INTERPOLATE_BETWEEN
) -> Trajectory:
    """A smooth path through the training cameras (see the module docstring, ``interpolate``).

    Args:
        scene: the scene.
        camera: the camera whose intrinsics the video takes and whose views a rig's path follows
            (default :func:`default_video_camera`).
        frames_between: poses between consecutive training cameras.

    Returns:
        :class:`Trajectory` with ``(K - 1) * (frames_between + 1) + 1`` poses for ``K`` training
        frames: every ``frames_between + 1``-th at a training camera's centre, looking where it
        looks, without its roll.
    """
    if int(frames_between) < 0:
        raise ValueError(f"frames_between: expected >= 0, got {frames_between}")
    camera, keys, c2w = _path_keys(scene, camera)
    path = spline_path(c2w, scene_up(scene, keys), _focus_depth(scene, keys), int(frames_between))
    key_times = [float(scene.view_frame_position(v)) for v in keys]
    times = torch.from_numpy(np.interp(path.t.numpy(), np.arange(len(keys)), key_times))
    return Trajectory(path.cam_to_world.float(), times, camera)


def orbit_trajectory(scene: Scene, camera: str | None = None, num_frames: int = ORBIT_FRAMES) -> Trajectory:
    """A circle around the scene's centre, looking at it (see the module docstring, ``orbit``).

    Args:
        scene: the scene.
        camera: the camera whose intrinsics the video takes (default :func:`default_video_camera`).
        num_frames: poses on the circle (the last one short of the first: the video loops).

    Returns:
        :class:`Trajectory` of ``num_frames`` poses, the frame time sweeping the scene's frames.
    """
    if int(num_frames) < 1:
        raise ValueError(f"num_frames: expected >= 1, got {num_frames}")
    camera, keys, c2w = _path_keys(scene, camera)
    path = orbit_path(c2w, scene_up(scene, keys), int(num_frames), _focus_depth(scene, keys))
    last = len(scene.frames) - 1
    times = torch.linspace(0.0, float(last), int(num_frames), dtype=torch.float64)
    return Trajectory(path.cam_to_world.float(), times, camera)
