"""Helpers shared by the DGP, nuScenes and Waymo readers: frames, cameras, world, 3D boxes → tracks.

The three readers select cameras and frames alike (:func:`select_cameras`,
:func:`select_positions`, :func:`held_out_frames`), translate the dataset's far-away world to the first
frame (:func:`recentred`), and turn 3D boxes into instances, tracks and LiDAR labels.

The three datasets annotate each keyframe with 3D boxes that carry a persistent object identifier
(a DGP ``instance_id``, a nuScenes instance token, a Waymo ``laser_object_id``). The readers
collect them as
``{id: {frame position: BoxObservation}}`` and call :func:`build_instances` to get the instance
table and the :class:`~vadgs.data.scene.Track` of each moving rigid object.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from vadgs.checks import check_finite
from vadgs.data.scene import InstanceInfo, LidarFrame, Track

__all__ = [
    "BoxObservation",
    "as_tensor",
    "build_instances",
    "check_min_motion",
    "every_fourth_test_frames",
    "held_out_frames",
    "label_points",
    "labelled_lidar",
    "points_in_boxes",
    "quat_wxyz_to_matrix",
    "recentred",
    "select_cameras",
    "select_positions",
]


class BoxObservation(NamedTuple):
    """One annotated 3D box at one frame.

    Attributes:
        object_to_world: ``(4, 4)`` float64 box pose in the (recentred) world: centre, x along the
            length, y along the width, z up.
        size_lwh: ``(3,)`` length, width, height in metres.
        class_name: vadgs class name (e.g. ``"car"``).
    """

    object_to_world: np.ndarray
    size_lwh: np.ndarray
    class_name: str


def quat_wxyz_to_matrix(q: Sequence[float] | np.ndarray) -> np.ndarray:
    """A ``(w, x, y, z)`` quaternion as a 3×3 float64 rotation matrix (normalised first).

    The sign of ``q`` does not matter (``q`` and ``-q`` are the same rotation); the matrix is
    :class:`scipy.spatial.transform.Rotation`'s.

    Raises:
        ValueError: if ``q`` is not four finite numbers with a non-zero norm.

    Example:
        >>> quat_wxyz_to_matrix([0.0, 0.0, 0.0, 1.0]).round(6).tolist()
        [[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]
    """
    try:
        w, x, y, z = (float(v) for v in q)
    except (TypeError, ValueError):
        raise ValueError(f"quaternion: expected four numbers (w, x, y, z), got {q!r}") from None
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not (math.isfinite(n) and n > 0):
        raise ValueError(f"quaternion: expected a finite non-zero (w, x, y, z), got {q!r}")
    return Rotation.from_quat([w, x, y, z], scalar_first=True).as_matrix()


def select_cameras(cameras: Sequence[str] | None, have: Sequence[str], none_message: str) -> list[str]:
    """The cameras to load: ``cameras`` (each one of ``have``), or all of ``have`` when None.

    Raises:
        ValueError: ``none_message`` when there is no camera to load;
            ``"cameras: unknown camera 'X', have [...]"`` for a camera not in ``have``.

    Example:
        >>> have = ["FRONT", "LEFT"]
        >>> select_cameras(None, have, "no camera"), select_cameras(["LEFT"], have, "no camera")
        (['FRONT', 'LEFT'], ['LEFT'])
    """
    names = list(cameras) if cameras is not None else list(have)
    if not names:
        raise ValueError(none_message)
    for n in names:
        if n not in have:
            raise ValueError(f"cameras: unknown camera {n!r}, have {list(have)}")
    return names


def select_positions(frames: Sequence[int] | None, available: int, what: str = "frame") -> list[int]:
    """The positions of the frames to keep (``frames``, or all ``available`` when None).

    Raises:
        ValueError: ``"frames: expected <what> positions in [0, N), got [...]"`` if one is out of
            range or none is left.

    Example:
        >>> select_positions(None, 3), select_positions(range(1, 3), 3)
        ([0, 1, 2], [1, 2])
    """
    positions = list(range(available)) if frames is None else [int(f) for f in frames]
    bad = [f for f in positions if not 0 <= f < available]
    if bad or not positions:
        raise ValueError(f"frames: expected {what} positions in [0, {available}), got {list(positions)}")
    return positions


def held_out_frames(test_frames: Sequence[int] | None, num_frames: int) -> list[int]:
    """The held-out frames: ``test_frames`` sorted, or :func:`every_fourth_test_frames` when None.

    Raises:
        ValueError: ``"test_frames: unknown frame(s) [...], have 0..N-1"``.

    Example:
        >>> held_out_frames(None, 11), held_out_frames((), 11), held_out_frames([3, 1], 11)
        ([2, 6, 10], [], [1, 3])
    """
    test = (
        every_fourth_test_frames(num_frames) if test_frames is None else sorted(int(f) for f in test_frames)
    )
    bad = [f for f in test if not 0 <= f < num_frames]
    if bad:
        raise ValueError(f"test_frames: unknown frame(s) {bad}, have 0..{num_frames - 1}")
    return test


def recentred(m: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """A copy of the ``(..., 4, 4)`` transforms ``m`` with ``offset`` subtracted from their translation.

    The readers' world is the dataset's translated so that the first frame's ego sits at the origin.

    Example:
        >>> recentred(np.eye(4), np.array([1.0, 2.0, 3.0]))[:3, 3].tolist()
        [-1.0, -2.0, -3.0]
    """
    out = m.copy()
    out[..., :3, 3] -= offset
    return out


def every_fourth_test_frames(num_frames: int) -> list[int]:
    """The benchmark's test split: frames 2, 6, 10, ... (every fourth, from the third).

    Example:
        >>> every_fourth_test_frames(11)
        [2, 6, 10]
    """
    return list(range(2, num_frames, 4))


def as_tensor(m: np.ndarray, what: str) -> torch.Tensor:
    """A float64 numpy array as a finite float32 tensor (the message names ``what`` otherwise)."""
    t = torch.from_numpy(np.asarray(m, dtype=np.float64))
    check_finite(t, what)
    return t.float()


def check_min_motion(min_motion_m: float | None) -> None:
    """Raise a :class:`ValueError` unless ``min_motion_m`` is None or a non-negative number."""
    if min_motion_m is not None and not min_motion_m >= 0:
        raise ValueError(f"min_motion_m: expected a non-negative number or None, got {min_motion_m!r}")


def build_instances(
    boxes: dict[int, dict[int, BoxObservation]],
    names: dict[int, str],
    num_frames: int,
    rigid: Callable[[str], bool],
    min_motion_m: float | None,
) -> tuple[dict[int, InstanceInfo], dict[int, Track]]:
    """The instance table of every box id and the tracks of the moving rigid ones.

    An instance is ``dynamic`` when its box centre moves more than ``min_motion_m`` (0.5 m when
    None) in the world over the frames it is annotated in. It becomes a :class:`Track` when its
    class is rigid and it is dynamic, or, with ``min_motion_m=None``, whenever its class is rigid.

    Args:
        boxes: id → frame position → :class:`BoxObservation`.
        names: id → the dataset's own identifier (instance token, laser object id).
        num_frames: number of frames of the scene.
        rigid: whether a class name is a rigid object (vehicles).
        min_motion_m: motion threshold, or None for every rigid instance.

    Returns:
        ``(instances, tracks)`` keyed by id.
    """
    instances: dict[int, InstanceInfo] = {}
    tracks: dict[int, Track] = {}
    for iid in sorted(boxes):
        per_frame = boxes[iid]
        cls = next(iter(per_frame.values())).class_name
        poses = torch.eye(4).repeat(num_frames, 1, 1)
        valid = torch.zeros(num_frames, dtype=torch.bool)
        for fi, obs in per_frame.items():
            poses[fi] = as_tensor(obs.object_to_world, f"box {names[iid]} at frame {fi}")
            valid[fi] = True
        centres = poses[valid, :3, 3]
        motion = float((centres - centres[:1]).norm(dim=-1).max())
        dynamic = motion > (0.5 if min_motion_m is None else min_motion_m)
        instances[iid] = InstanceInfo(iid, names[iid], cls, dynamic)
        if rigid(cls) and (dynamic or min_motion_m is None):
            size = np.median([obs.size_lwh for obs in per_frame.values()], axis=0)
            tracks[iid] = Track(iid, cls, torch.tensor(size, dtype=torch.float32), poses, valid)
    return instances, tracks


def points_in_boxes(
    points: torch.Tensor, object_to_world: torch.Tensor, size_lwh: torch.Tensor
) -> torch.Tensor:
    """Which points lie inside which centred boxes (x along length, y along width, z up).

    Not differentiable (a boolean test).

    Args:
        points: ``(N, 3)`` world points.
        object_to_world: ``(M, 4, 4)`` box poses (box centre and axes in the world).
        size_lwh: ``(M, 3)`` box length, width, height.

    Returns:
        ``(M, N)`` bool.

    Example:
        >>> pts = torch.tensor([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
        >>> points_in_boxes(pts, torch.eye(4)[None], torch.tensor([[4.0, 2.0, 2.0]]))
        tensor([[ True, False]])
    """
    rot = object_to_world[:, :3, :3]
    local = torch.einsum("mji,mnj->mni", rot, points[None] - object_to_world[:, None, :3, 3])
    return (local.abs() <= size_lwh[:, None] / 2).all(-1)


def label_points(points: torch.Tensor, frame_boxes: dict[int, BoxObservation]) -> torch.Tensor:
    """The id of the box each world point lies in (0 outside every box), ``(N,)`` int64."""
    instance = torch.zeros(len(points), dtype=torch.int64)
    if not frame_boxes:
        return instance
    ids = sorted(frame_boxes)
    inside = points_in_boxes(
        points,
        torch.stack([as_tensor(frame_boxes[i].object_to_world, f"box {i}") for i in ids]),
        torch.stack([as_tensor(frame_boxes[i].size_lwh, f"box {i}") for i in ids]),
    )
    hit = inside.any(0)
    instance[hit] = torch.tensor(ids)[inside[:, hit].float().argmax(0)]
    return instance


def labelled_lidar(
    world: np.ndarray, origin: np.ndarray, boxes: dict[int, dict[int, BoxObservation]], frame: int
) -> LidarFrame:
    """A sweep in world coordinates as a :class:`~vadgs.data.scene.LidarFrame`, labelled by the frame's boxes.

    Args:
        world: ``(N, 3)`` float64 points in the world.
        origin: ``(3,)`` sensor position in the world.
        boxes: id → frame position → :class:`BoxObservation` (as for :func:`build_instances`).
        frame: the frame position of the sweep.

    Returns:
        float32 points, each point's box id from :func:`label_points` (0 outside), float32 origin.
    """
    pts = torch.from_numpy(world).float()
    frame_boxes = {i: b[frame] for i, b in boxes.items() if frame in b}
    return LidarFrame(pts, label_points(pts, frame_boxes), torch.from_numpy(np.asarray(origin)).float())
