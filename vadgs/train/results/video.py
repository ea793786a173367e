r"""Videos of a trained model along a camera path: colour | depth | normals side by side, or colour only.

The camera path is a :class:`~vadgs.train.results.trajectory.Trajectory` (ego path, shifted,
``interpolate`` through the training cameras, ``orbit``: :mod:`vadgs.train.results.trajectory`).
The moving objects are interpolated between frames as the ego poses are
(:func:`object_poses_at`).

Every video frame (:func:`video_frame`) is colour | depth | normals (layout ``"strip"``) or the
colour alone (``"color"``, :data:`VIDEO_LAYOUTS`) over a thin timeline bar (:data:`TIMELINE_ROWS`
rows: white up to the frame's position in the video). The depth colours (inverse depth, turbo)
keep one range over the whole video, so that they do not flicker: :func:`video_depth_range`, the
lowest 2nd and highest 98th depth percentile of :data:`DEPTH_SAMPLES` frames spread along the path,
rendered up front (a close-up later in the path keeps its colours, as it would not with the first
frame's range). Videos are written
with imageio's ffmpeg plugin (the ``imageio-ffmpeg`` wheel bundles ffmpeg):
H.264 in ``yuv420p``, the frame padded with black to even sizes (:func:`write_video`). Frames go
to the encoder one by one as they are rendered, so memory does not grow with the video's length;
they are written to a temporary file and renamed, so a partial video never takes the output's
name. :func:`check_video_path` checks the output's name (suffix, length) before any rendering, and
:func:`gaussians_in_view` finds a camera path that sees nothing.
"""

from __future__ import annotations

import copy
import os
from collections.abc import Iterable
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from vadgs.checks import check_shape
from vadgs.data.scene import Scene
from vadgs.geometry.camera import invert_rigid
from vadgs.geometry.camera_path import interpolate_rigid
from vadgs.io import atomic_write
from vadgs.render import RasterConfig
from vadgs.train.model import GaussianModel, ModelRender
from vadgs.train.results.trajectory import Trajectory, make_trajectory

__all__ = [
    "DEPTH_SAMPLES",
    "NAME_MAX",
    "TIMELINE_ROWS",
    "VIDEO_LAYOUTS",
    "VIDEO_SUFFIXES",
    "VideoInfo",
    "check_video_path",
    "depth_percentiles",
    "gaussians_in_view",
    "model_at_time",
    "object_poses_at",
    "render_video",
    "video_depth_range",
    "video_frame",
    "write_video",
]

#: Height in pixels of the timeline bar under each video frame.
TIMELINE_ROWS = 4

#: The frame layouts of a video: colour | depth | normals side by side, or the colour alone.
VIDEO_LAYOUTS = ("strip", "color")

#: The frames along the path whose depths set a video's depth colour range (:func:`video_depth_range`).
DEPTH_SAMPLES = 8

#: The containers :func:`write_video` writes (H.264 in each, by ffmpeg).
VIDEO_SUFFIXES = (".mp4", ".mov", ".mkv")

#: The longest file name (bytes) of the usual file systems (ext4, APFS, NTFS, tmpfs).
NAME_MAX = 255

# atomic_write's temporary name is ".STEM.XXXXXXXX.tmpSUFFIX": 14 bytes more than the name
_TMP_EXTRA = len(".") + len(".12345678.tmp")


def check_video_path(path: str | Path) -> Path:
    """Check a video's output path before any rendering: its suffix, its name's length, its folder.

    Args:
        path: the output video.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ValueError: one line naming ``path`` (never the temporary file) and what was expected: a
            suffix of :data:`VIDEO_SUFFIXES`, a name of at most :data:`NAME_MAX` bytes less the
            temporary file's 14, a folder that is not a file.

    Example:
        >>> check_video_path("runs/a/ego.mp4")
        PosixPath('runs/a/ego.mp4')
        >>> check_video_path("runs/a/ego.xyz")
        Traceback (most recent call last):
        ...
        ValueError: runs/a/ego.xyz: expected a video name ending in .mp4, .mov or .mkv, got suffix '.xyz'
    """
    given, path = str(path), Path(path)
    expected = ", ".join(VIDEO_SUFFIXES[:-1]) + f" or {VIDEO_SUFFIXES[-1]}"
    if path.name in ("", ".", "..") or given.endswith(("/", os.sep)):
        raise ValueError(f"{given}: expected a video file name ending in {expected}, got a folder")
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        got = f"suffix {path.suffix!r}" if path.suffix else "no suffix"
        raise ValueError(f"{path}: expected a video name ending in {expected}, got {got}")
    size = len(os.fsencode(path.name))
    if size + _TMP_EXTRA > NAME_MAX:
        raise ValueError(
            f"{path}: expected a file name of at most {NAME_MAX - _TMP_EXTRA} bytes (the file system's "
            f"{NAME_MAX} less {_TMP_EXTRA} for the temporary file), got {size}"
        )
    return path


def object_poses_at(
    object_to_world: torch.Tensor, track_valid: torch.Tensor, time: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Track poses at a (fractional) frame position.

    A track valid at both neighbouring frames is interpolated
    (:func:`~vadgs.geometry.interpolate_rigid`); otherwise it takes the pose and validity of the
    nearest frame.

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


def _check_layout(layout: str) -> None:
    if layout not in VIDEO_LAYOUTS:
        raise ValueError(f"layout: expected one of {', '.join(VIDEO_LAYOUTS)}, got {layout!r}")


def depth_percentiles(render: ModelRender) -> tuple[float, float] | None:
    """The 2nd and 98th percentile of a render's depth on its opaque pixels (alpha > 0.5), or None.

    Only the opaque pixels: a faint Gaussian at the camera would squash the range.
    """
    depth, alpha = render.raster.depth, render.raster.alpha
    d = depth[(depth > 0) & (alpha > 0.5)]
    if not d.numel():
        return None
    return float(d.quantile(0.02)), float(d.quantile(0.98))


def video_depth_range(
    renders: Iterable[ModelRender], default: tuple[float, float] = (1.0, 100.0)
) -> tuple[float, float]:
    """One depth colour range for a whole video: the lowest 2nd and highest 98th percentile of ``renders``.

    Each render's percentiles are of its opaque pixels (:func:`depth_percentiles`);
    :func:`render_video` passes :data:`DEPTH_SAMPLES` frames spread along the path. ``default``
    when no render has an opaque pixel.

    Example:
        >>> from types import SimpleNamespace as NS
        >>> near = NS(raster=NS(depth=torch.full((1, 1, 2, 2), 2.0), alpha=torch.ones(1, 1, 2, 2)))
        >>> far = NS(raster=NS(depth=torch.full((1, 1, 2, 2), 30.0), alpha=torch.ones(1, 1, 2, 2)))
        >>> video_depth_range([near, far])
        (2.0, 30.0)
    """
    ranges = [r for r in map(depth_percentiles, renders) if r is not None]
    if not ranges:
        return default
    return min(r[0] for r in ranges), max(r[1] for r in ranges)


def video_frame(
    render: ModelRender,
    depth_range: tuple[float, float] | None = None,
    progress: float | None = None,
    layout: str = "strip",
) -> np.ndarray:
    """One video frame ``(H, 3W, 3)`` uint8: colour | depth (inverse, turbo) | normals, or ``(H, W, 3)``.

    Args:
        render: a :meth:`GaussianModel.render` output.
        depth_range: ``(near, far)`` metres of the depth colour map (default: this frame's 2nd and
            98th percentiles); keep it fixed over a video so that colours do not flicker
            (:func:`render_video` takes :func:`video_depth_range`'s).
        progress: position in the video in ``[0, 1]``: adds a timeline bar of
            :data:`TIMELINE_ROWS` rows below (``(H + TIMELINE_ROWS, 3W, 3)``).
        layout: ``"strip"`` (colour | depth | normals) or ``"color"`` (the colour alone, ``(H, W, 3)``).
    """
    from vadgs.viz import colorize_depth, colorize_normals, image_to_uint8

    _check_layout(layout)
    panels = [image_to_uint8(render.color[0])]
    if layout == "strip":
        near, far = depth_range if depth_range is not None else (None, None)
        panels += [
            colorize_depth(render.raster.depth[0, 0], near, far),
            colorize_normals(render.raster.normals[0]),
        ]
    frame = np.concatenate(panels, axis=1)
    if progress is None:
        return frame
    bar = np.full((TIMELINE_ROWS, frame.shape[1], 3), 64, dtype=np.uint8)
    bar[:, : round(float(np.clip(progress, 0.0, 1.0)) * frame.shape[1])] = 255
    return np.concatenate([frame, bar], axis=0)


def gaussians_in_view(
    means: torch.Tensor, cam_to_world: torch.Tensor, K: torch.Tensor, image_size: tuple[int, int]
) -> torch.Tensor:
    """How many of ``means`` each camera sees: in front of it and projected inside its image.

    Not differentiable (a count). Rows of non-finite poses see nothing.

    Args:
        means: ``(N, 3)`` points in the world.
        cam_to_world: ``(P, 4, 4)`` camera poses.
        K: ``(3, 3)`` intrinsics.
        image_size: ``(H, W)``.

    Returns:
        ``(P,)`` int64 counts.

    Example:
        >>> K = torch.tensor([[10.0, 0, 5], [0, 10, 5], [0, 0, 1]])
        >>> c2w = torch.eye(4).repeat(2, 1, 1); c2w[1, 0, 3] = 1e30
        >>> gaussians_in_view(torch.tensor([[0.0, 0, 2], [0, 0, -2]]), c2w, K, (10, 10)).tolist()
        [1, 0]
    """
    check_shape(means, "means", ("N", 3))
    check_shape(cam_to_world, "cam_to_world", ("P", 4, 4))
    check_shape(K, "K", (3, 3))
    h, w = image_size
    w2c = invert_rigid(cam_to_world.double())
    pts = means.double().to(w2c.device)
    out = torch.zeros(cam_to_world.shape[0], dtype=torch.int64)
    for i in range(0, w2c.shape[0], 64):  # (64, N, 3) at a time
        cam = torch.einsum("pij,nj->pni", w2c[i : i + 64, :3, :3], pts) + w2c[i : i + 64, None, :3, 3]
        z = cam[..., 2]
        uv = torch.einsum("ij,pnj->pni", K.double().to(cam.device), cam)[..., :2] / z[..., None].clamp(
            min=1e-9
        )
        seen = (z > 1e-6) & (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h)
        out[i : i + 64] = (seen & torch.isfinite(uv).all(-1)).sum(-1).cpu()
    return out


def write_video(
    path: str | Path,
    frames: Iterable[np.ndarray],
    fps: float = 10.0,
    total: int | None = None,
    progress: bool = True,
) -> tuple[int, tuple[int, int] | None]:
    """Write ``frames`` to a video at ``path``, atomically, one frame at a time.

    Each frame goes to imageio's ffmpeg writer as soon as ``frames`` yields it (pass a generator:
    memory does not grow with the video's length), H.264 in ``yuv420p``, padded with black to even
    sizes. The video is written to a temporary file beside ``path`` and renamed
    (:func:`~vadgs.io.atomic_write`): an interrupted or failed video leaves no file at ``path``.

    Args:
        path: the output (:func:`check_video_path` checks it first).
        frames: ``(H, W, 3)`` uint8 arrays, all of one size.
        fps: frames per second.
        total: the number of frames, for the progress bar.
        progress: a tqdm bar.

    Returns:
        ``(frames written, (H, W) of the written frames)`` (None without a frame).

    Raises:
        ImportError: without imageio and imageio-ffmpeg (the ``video`` extra).
        ValueError: for a path :func:`check_video_path` refuses.
    """
    try:
        import imageio.v2 as imageio
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        raise ImportError("videos need imageio and imageio-ffmpeg: pip install 'vadgs[video]'") from None
    from tqdm import tqdm

    path = check_video_path(path)
    count, size = 0, None

    def write(tmp: Path) -> None:  # into a temporary file: an interrupted video leaves no partial file
        nonlocal count, size
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
            for frame in tqdm(frames, total=total, disable=not progress, desc="video"):
                h, w = frame.shape[:2]
                frame = np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)))  # yuv420p needs even sizes
                size = frame.shape[:2]
                writer.append_data(frame)
                count += 1
        finally:
            writer.close()

    atomic_write(path, write)
    return count, size


class VideoInfo(NamedTuple):
    """What :func:`render_video` wrote: ``path``, ``num_frames`` and the frame ``size`` ``(H, W)``.

    ``size`` is None when no frame was written (a trajectory without poses).
    """

    path: Path
    num_frames: int
    size: tuple[int, int] | None


@torch.no_grad()
def render_video(
    model: GaussianModel,
    scene: Scene,
    path: str | Path,
    trajectory: Trajectory | None = None,
    fps: float = 10.0,
    config: RasterConfig | None = None,
    progress: bool = True,
    layout: str = "strip",
) -> VideoInfo:
    """Render a trajectory as an MP4: colour | depth | normals (or colour) per frame, a timeline bar below.

    Args:
        model: the trained model.
        scene: its scene (intrinsics and image size of the trajectory's camera).
        path: output ``.mp4`` (or another of :data:`VIDEO_SUFFIXES`), checked before any rendering
            (:func:`check_video_path`).
        trajectory: default :func:`make_trajectory`'s: the ego path of the front camera, or on a
            scene without one (a photo collection) the path through its training cameras.
        fps: frames per second.
        config: rasterizer settings.
        progress: tqdm bar.
        layout: ``"strip"``: colour | depth | normals, the depth colours over
            :func:`video_depth_range` of :data:`DEPTH_SAMPLES` frames spread along the path
            (rendered first); ``"color"``: the colour alone.

    Returns:
        :class:`VideoInfo`.

    Raises:
        ImportError: without imageio and imageio-ffmpeg (the ``video`` extra).
        ValueError: for a path :func:`check_video_path` refuses, or a layout not in :data:`VIDEO_LAYOUTS`.
    """
    _check_layout(layout)
    try:
        import imageio.v2  # noqa: F401
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        raise ImportError(
            "render_video needs imageio and imageio-ffmpeg: pip install 'vadgs[video]'"
        ) from None

    path = check_video_path(path)
    if trajectory is None:
        trajectory = make_trajectory(scene)
    info = scene.cameras_info[trajectory.camera]
    K = info.K[None]
    last = max(len(trajectory.time) - 1, 1)

    times = trajectory.time.tolist()

    def render(i: int) -> ModelRender:
        w2c = invert_rigid(trajectory.cam_to_world[i][None].to(K.dtype))
        return model_at_time(model, times[i]).render(w2c, K, info.image_size, 0, config)

    depth_range = None
    if layout == "strip" and times:  # one range for the whole video, from frames along the path
        picks = sorted({round(x) for x in np.linspace(0, len(times) - 1, min(DEPTH_SAMPLES, len(times)))})
        depth_range = video_depth_range(render(i) for i in picks)

    def frames() -> Iterable[np.ndarray]:  # one at a time: the encoder takes each as it is made
        for i in range(len(times)):
            yield video_frame(render(i), depth_range, i / last, layout)

    count, size = write_video(path, frames(), fps, total=len(trajectory.time), progress=progress)
    return VideoInfo(path, count, size)
