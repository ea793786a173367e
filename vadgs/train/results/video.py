r"""Videos of a trained model along the ego path: colour | depth | normals side by side.

The camera path is a :class:`~vadgs.train.results.trajectory.Trajectory` (ego path, shifted,
``interpolate`` through the training cameras, ``orbit``: :mod:`vadgs.train.results.trajectory`).
The moving objects are interpolated between frames as the ego poses are
(:func:`object_poses_at`).

Every video frame (:func:`video_frame`) is colour | depth | normals over a thin timeline bar
(:data:`TIMELINE_ROWS` rows: white up to the frame's position in the video). Videos are written
with imageio's ffmpeg plugin (the ``imageio-ffmpeg`` wheel bundles ffmpeg):
H.264 in ``yuv420p``, the frame padded with black to even sizes, written to a temporary file
and renamed, so a partial video never takes the output's name.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from vadgs.checks import check_shape
from vadgs.data.scene import Scene
from vadgs.geometry.camera import invert_rigid
from vadgs.io import atomic_write
from vadgs.render import RasterConfig
from vadgs.train.model import GaussianModel, ModelRender
from vadgs.train.results.trajectory import Trajectory, interpolate_rigid, make_trajectory

__all__ = [
    "TIMELINE_ROWS",
    "VideoInfo",
    "model_at_time",
    "object_poses_at",
    "render_video",
    "video_frame",
]

#: Height in pixels of the timeline bar under each video frame.
TIMELINE_ROWS = 4


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
        trajectory: default :func:`make_trajectory`'s: the ego path of the front camera, or on a
            scene without one (a photo collection) the path through its training cameras.
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
        trajectory = make_trajectory(scene)
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
