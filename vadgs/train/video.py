r"""Videos of a trained model along the ego path: colour | depth | normals side by side.

A **trajectory** is one camera of the rig following the ego vehicle through the scene's frames,
optionally shifted in the ego frame (``shift_ego_m = (0, 2, 0)``: 2 m to the left, a lane change,
as the scene's novel views):

.. math::

    T_{cam \to world}(t) = T_{ego \to world}(t)\, T(\text{shift})\, T_{cam \to ego}

With ``frames_between = n > 0``, ``n`` poses are inserted between consecutive frames: rotations are
slerped, translations interpolated linearly (:func:`interpolate_rigid`). The moving objects are
interpolated the same way between the two frames when their track is valid at both, else they take
the pose (and validity) of the nearest frame (:func:`object_poses_at`). Time ``t`` is measured in
frame positions (``t = 2.5`` is half-way between ``scene.frames[2]`` and ``scene.frames[3]``).

Without ``ego_to_world`` or ``cam_to_ego`` (e.g. a COLMAP scene) the camera's own poses are
interpolated instead and only ``shift_ego_m = (0, 0, 0)`` is accepted.

Every video frame (:func:`video_frame`) is colour | depth | normals over a thin timeline bar
(:data:`TIMELINE_ROWS` rows: white up to the frame's position in the video). Videos are written
with imageio's ffmpeg plugin (the ``imageio-ffmpeg`` wheel bundles ffmpeg):
H.264 in ``yuv420p``, the frame padded with black to even sizes, written to a temporary file
and renamed, so a partial video never takes the output's name.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from vadgs.checks import check_shape
from vadgs.data.scene import Scene
from vadgs.geometry.camera import invert_rigid
from vadgs.io import atomic_write
from vadgs.render import RasterConfig, quaternion_to_rotation
from vadgs.train.model import GaussianModel, ModelRender, rotation_to_quat

__all__ = [
    "TIMELINE_ROWS",
    "Trajectory",
    "VideoInfo",
    "ego_trajectory",
    "interpolate_rigid",
    "model_at_time",
    "object_poses_at",
    "parse_trajectory",
    "render_video",
    "video_frame",
]


#: Height in pixels of the timeline bar under each video frame.
TIMELINE_ROWS = 4


def interpolate_rigid(a: torch.Tensor, b: torch.Tensor, t: float) -> torch.Tensor:
    """Rigid transform between ``a`` (``t = 0``) and ``b`` (``t = 1``): slerped rotation, linear translation.

    Not differentiable (poses are fixed).

    Shape:
        ``(*, 4, 4)`` and ``(*, 4, 4)`` → ``(*, 4, 4)``.

    Example:
        >>> a = torch.eye(4); b = torch.eye(4); b[:3, :3] = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
        >>> b[0, 3] = 2.0
        >>> m = interpolate_rigid(a, b, 0.5)  # 45° about z, half-way
        >>> [round(v, 4) for v in (m[0, 0].item(), m[1, 0].item(), m[0, 3].item())]
        [0.7071, 0.7071, 1.0]
    """
    qa = rotation_to_quat(a[..., :3, :3].double())
    qb = rotation_to_quat(b[..., :3, :3].double())
    dot = (qa * qb).sum(-1, keepdim=True)
    qb = torch.where(dot < 0, -qb, qb)  # the short way round
    dot = dot.abs().clamp(max=1.0)
    theta = torch.acos(dot)
    sin = torch.sin(theta)
    near = sin < 1e-6  # (almost) the same rotation: linear interpolation is exact enough
    wa = torch.where(near, 1.0 - t, torch.sin((1.0 - t) * theta) / sin.clamp(min=1e-12))
    wb = torch.where(near, torch.full_like(theta, t), torch.sin(t * theta) / sin.clamp(min=1e-12))
    out = a.double().clone()
    out[..., :3, :3] = quaternion_to_rotation(wa * qa + wb * qb)
    out[..., :3, 3] = (1.0 - t) * a[..., :3, 3].double() + t * b[..., :3, 3].double()
    return out.to(a.dtype)


def object_poses_at(
    object_to_world: torch.Tensor, track_valid: torch.Tensor, time: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Track poses at a (fractional) frame position.

    A track valid at both neighbouring frames is interpolated (:func:`interpolate_rigid`); otherwise
    it takes the pose and validity of the nearest frame.

    Args:
        object_to_world: ``(T, F, 4, 4)``.
        track_valid: ``(T, F)`` bool.
        time: frame position in ``[0, F - 1]``.

    Returns:
        ``(T, 4, 4)`` poses and ``(T,)`` validity.

    Example:
        >>> o2w = torch.eye(4).repeat(1, 2, 1, 1); o2w[0, 1, 0, 3] = 4.0
        >>> poses, valid = object_poses_at(o2w, torch.ones(1, 2, dtype=torch.bool), 0.25)
        >>> poses[0, 0, 3].item(), valid.tolist()
        (1.0, [True])
    """
    dims = check_shape(object_to_world, "object_to_world", ("T", "F", 4, 4))
    check_shape(track_valid, "track_valid", ("T", "F"), dims)
    nf = dims["F"]
    if not 0.0 <= time <= nf - 1:
        raise ValueError(f"time: expected a frame position in [0, {nf - 1}], got {time}")
    f0 = min(int(np.floor(time)), nf - 1)
    f1 = min(f0 + 1, nf - 1)
    s = float(time - f0)
    nearest = f0 if s < 0.5 else f1
    poses = object_to_world[:, nearest].clone()
    valid = track_valid[:, nearest].clone()
    both = track_valid[:, f0] & track_valid[:, f1]
    if s > 0 and bool(both.any()):
        poses[both] = interpolate_rigid(object_to_world[both, f0], object_to_world[both, f1], s)
        valid = valid | both
    return poses, valid


def model_at_time(model: GaussianModel, time: float) -> GaussianModel:
    """A shallow copy of ``model`` with one frame (position 0): its tracks posed at ``time``.

    Parameters and the other buffers are shared with ``model`` (nothing is copied), so
    ``model_at_time(model, t).render(..., frame=0)`` renders exactly as :meth:`GaussianModel.render`
    does at an integer ``t``, and between frames with the poses of :func:`object_poses_at`.
    """
    poses, valid = object_poses_at(model.object_to_world, model.track_valid, time)
    out = copy.copy(model)
    out._buffers = dict(model._buffers)
    out._buffers["object_to_world"] = poses[:, None]
    out._buffers["track_valid"] = valid[:, None]
    return out


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

    Example:
        >>> parse_trajectory("ego"), parse_trajectory("shift:-2"), parse_trajectory("shift:1,0,0.5")
        ((0.0, 0.0, 0.0), (0.0, -2.0, 0.0), (1.0, 0.0, 0.5))
    """
    if spec == "ego":
        return (0.0, 0.0, 0.0)
    if spec.startswith("shift:"):
        try:
            parts = [float(p) for p in spec[len("shift:") :].split(",")]
        except ValueError:
            parts = []
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
    if c2e is not None and all(f.ego_to_world is not None for f in scene.frames):
        keys = torch.stack([f.ego_to_world @ shift @ c2e for f in scene.frames])
    else:
        if bool(shift[:3, 3].any()):
            raise ValueError(
                f"shift_ego_m: scene {scene.name!r} has no ego poses (ego_to_world, cam_to_ego); "
                "only the 'ego' trajectory (no shift) is available"
            )
        keys = torch.stack([scene.views[scene.view_id(f.index, camera)].cam_to_world for f in scene.frames])
    n = int(frames_between) + 1
    poses, times = [], []
    for i in range(len(keys)):
        for j in range(n if i + 1 < len(keys) else 1):
            s = j / n
            poses.append(keys[i] if j == 0 else interpolate_rigid(keys[i], keys[i + 1], s))
            times.append(i + s)
    return Trajectory(torch.stack(poses), torch.tensor(times, dtype=torch.float64), camera)


def video_frame(
    render: ModelRender, depth_range: tuple[float, float] | None = None, progress: float | None = None
) -> np.ndarray:
    """One video frame ``(H, 3W, 3)`` uint8: colour | depth (inverse, turbo) | normals.

    Args:
        render: a :meth:`GaussianModel.render` output.
        depth_range: ``(near, far)`` metres of the depth colour map (default: this frame's 2nd and
            98th percentiles); keep it fixed over a video so that colours do not flicker
            (:func:`render_video` takes the first frame's, on pixels of alpha > 0.5).
        progress: position in the video in ``[0, 1]``: adds a timeline bar of
            :data:`TIMELINE_ROWS` rows below (``(H + TIMELINE_ROWS, 3W, 3)``).
    """
    from vadgs.viz import colorize_depth, colorize_normals, image_to_uint8

    depth = render.raster.depth[0, 0]
    near, far = depth_range if depth_range is not None else (None, None)
    frame = np.concatenate(
        [
            image_to_uint8(render.color[0]),
            colorize_depth(depth, near, far),
            colorize_normals(render.raster.normals[0]),
        ],
        axis=1,
    )
    if progress is None:
        return frame
    bar = np.full((TIMELINE_ROWS, frame.shape[1], 3), 64, dtype=np.uint8)
    bar[:, : round(float(np.clip(progress, 0.0, 1.0)) * frame.shape[1])] = 255
    return np.concatenate([frame, bar], axis=0)


class VideoInfo(NamedTuple):
    """What :func:`render_video` wrote: ``path``, ``num_frames`` and the frame ``size`` ``(H, W)``."""

    path: Path
    num_frames: int
    size: tuple[int, int]


@torch.no_grad()
def render_video(
    model: GaussianModel,
    scene: Scene,
    path: str | Path,
    trajectory: Trajectory | None = None,
    fps: float = 10.0,
    config: RasterConfig | None = None,
    progress: bool = True,
) -> VideoInfo:
    """Render a trajectory and write it as an MP4: colour | depth | normals per frame, a timeline bar below.

    Args:
        model: the trained model.
        scene: its scene (intrinsics and image size of the trajectory's camera).
        path: output ``.mp4``.
        trajectory: default :func:`ego_trajectory` of the front camera (or the first camera).
        fps: frames per second.
        config: rasterizer settings.
        progress: tqdm bar.

    Returns:
        :class:`VideoInfo`.

    Raises:
        ImportError: without imageio and imageio-ffmpeg (the ``video`` extra).
    """
    try:
        import imageio.v2 as imageio
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        raise ImportError(
            "render_video needs imageio and imageio-ffmpeg: pip install 'vadgs[video]'"
        ) from None
    from tqdm import tqdm

    if trajectory is None:
        trajectory = ego_trajectory(
            scene, "front" if "front" in scene.cameras_info else scene.camera_names[0]
        )
    info = scene.cameras_info[trajectory.camera]
    K = info.K[None]
    path = Path(path)
    size = None  # of the frames written

    def write(tmp: Path) -> None:  # into a temporary file: an interrupted video leaves no partial file
        nonlocal size
        depth_range = None
        writer = imageio.get_writer(
            tmp,
            format="FFMPEG",
            mode="I",
            fps=fps,
            codec="libx264",
            pixelformat="yuv420p",
            macro_block_size=1,
        )
        try:
            last = max(len(trajectory.time) - 1, 1)
            poses = list(zip(trajectory.cam_to_world, trajectory.time.tolist()))
            for i, (c2w, t) in enumerate(tqdm(poses, disable=not progress, desc="video")):
                w2c = invert_rigid(c2w[None].to(K.dtype))
                out = model_at_time(model, t).render(w2c, K, info.image_size, 0, config)
                if depth_range is None:
                    # the opaque pixels only: a faint Gaussian at the camera would squash the range
                    d = out.raster.depth[(out.raster.depth > 0) & (out.raster.alpha > 0.5)]
                    depth_range = (
                        (float(d.quantile(0.02)), float(d.quantile(0.98))) if d.numel() else (1.0, 100.0)
                    )
                frame = video_frame(out, depth_range, i / last)
                h, w = frame.shape[:2]
                frame = np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)))  # yuv420p needs even sizes
                size = frame.shape[:2]
                writer.append_data(frame)
        finally:
            writer.close()

    atomic_write(path, write)
    return VideoInfo(path, len(trajectory.time), size)
