"""Interactive web viewer of a trained model (``vadgs view RUN``), built on `viser <https://viser.studio>`_.

The browser shows

- the static Gaussians (world frame) and one splat object per track node, posed at the frame of a
  slider (the node's ``object_to_world``; hidden at frames where its track is not valid);
- the camera frusta of the scene's recorded views at that frame;
- a selector for the Gaussians added by visibility-aware densification (``model.provenance``):
  all, only the VAD-GS additions, or without them.

Every Gaussian is sent once, in its node's own frame; moving the slider only changes poses. The
data preparation (:func:`splat_arrays`, :func:`viewer_groups`, :func:`node_pose`,
:func:`frame_frusta`) is plain numpy/torch and needs no viser; :func:`build_viewer` takes a
running ``viser.ViserServer``. viser is an optional dependency (``pip install vadgs[viewer]``).
"""

from __future__ import annotations

import math
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from vadgs.data import Scene
from vadgs.geometry.rotation import quaternion_to_rotation, rotation_to_quat
from vadgs.render import sh_to_rgb
from vadgs.train.model import GaussianModel

__all__ = [
    "FILTERS",
    "Frustum",
    "SplatGroup",
    "Viewer",
    "browser_screenshot",
    "build_viewer",
    "find_chromium",
    "frame_frusta",
    "node_pose",
    "splat_arrays",
    "viewer_groups",
]

#: Choices of the VAD-GS additions selector.
FILTERS = ("all Gaussians", "only VAD-GS additions", "without VAD-GS additions")


def splat_arrays(
    means: torch.Tensor,
    quats: torch.Tensor,
    log_scales: torch.Tensor,
    opacity_logits: torch.Tensor,
    sh_dc: torch.Tensor,
) -> dict[str, np.ndarray]:
    """Raw Gaussian parameters → viser's splat arrays (float32 numpy).

    Returns:
        ``centers (N, 3)``, ``covariances (N, 3, 3)`` (``R diag(s)^2 R^T``), ``rgbs (N, 3)`` in
        ``[0, 1]`` (the SH DC term) and ``opacities (N, 1)``.

    Example:
        >>> a = splat_arrays(torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]]),
        ...                  torch.log(torch.tensor([[1.0, 2.0, 3.0]])), torch.zeros(1), torch.zeros(1, 1, 3))
        >>> a["covariances"][0].diagonal().tolist(), a["rgbs"][0].tolist(), a["opacities"].tolist()
        ([1.0, 4.0, 9.0], [0.5, 0.5, 0.5], [[0.5]])
    """
    with torch.no_grad():
        rot = quaternion_to_rotation(F.normalize(quats.float(), dim=-1))
        s = log_scales.float().exp()
        rs = rot * s[:, None, :]
        cov = rs @ rs.transpose(-1, -2)
        rgb = sh_to_rgb(sh_dc.float()[:, 0]).clamp(0, 1)
        op = torch.sigmoid(opacity_logits.float())[:, None]
    return {
        "centers": means.detach().float().cpu().numpy(),
        "covariances": cov.cpu().numpy(),
        "rgbs": rgb.cpu().numpy(),
        "opacities": op.cpu().numpy(),
    }


@dataclass
class SplatGroup:
    """The Gaussians of one node and one origin, in the node's frame.

    Attributes:
        name: scene-graph name, e.g. ``/gaussians/static/initial`` or ``/gaussians/track_7/vad``.
        node: ``-1`` static, ``k`` the ``k``-th track node.
        added: True for Gaussians added by VAD-GS (``provenance >= 1``).
        rows: ``(M,)`` int64 model rows.
        arrays: :func:`splat_arrays` of those rows.
    """

    name: str
    node: int
    added: bool
    rows: torch.Tensor
    arrays: dict[str, np.ndarray] = field(repr=False)


def _subsample(n: int, max_gaussians: int | None, seed: int) -> torch.Tensor:
    if max_gaussians is None or n <= max_gaussians:
        return torch.arange(n)
    gen = torch.Generator().manual_seed(seed)
    return torch.randperm(n, generator=gen)[:max_gaussians].sort().values


def viewer_groups(
    model: GaussianModel, max_gaussians: int | None = 200_000, seed: int = 0
) -> list[SplatGroup]:
    """Split the model into :class:`SplatGroup` s (node × initial / VAD-GS), subsampled for the browser.

    Args:
        model: the model.
        max_gaussians: at most this many Gaussians in all (a uniform random subset; None: all).
        seed: of the subset.

    Returns:
        Non-empty groups: static first, then the track nodes in order; initial before added.
    """
    if max_gaussians is not None and max_gaussians < 1:
        raise ValueError(f"max_gaussians: expected >= 1 or None, got {max_gaussians}")
    p = {k: v.detach().cpu() for k, v in model.params.items()}
    keep = _subsample(model.num_gaussians, max_gaussians, seed)
    node_ids = p["node_ids"][keep]
    added = p["provenance"][keep] > 0
    groups = []
    for node in range(-1, len(model.track_ids)):
        label = "static" if node < 0 else f"track_{model.track_ids[node]}"
        for is_added in (False, True):
            rows = keep[(node_ids == node) & (added == is_added)]
            if not rows.numel():
                continue
            arrays = splat_arrays(
                p["means"][rows],
                p["quats"][rows],
                p["log_scales"][rows],
                p["opacity_logits"][rows],
                p["sh_dc"][rows],
            )
            name = f"/gaussians/{label}/{'vad' if is_added else 'initial'}"
            groups.append(SplatGroup(name, node, is_added, rows, arrays))
    return groups


def node_pose(model: GaussianModel, node: int, frame: int) -> tuple[np.ndarray, np.ndarray, bool]:
    """``(wxyz, position, visible)`` of a node at a frame position (static: identity, always visible)."""
    if node < 0:
        return np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3), True
    o2w = model.object_to_world[node, frame].detach().cpu().double()
    wxyz = rotation_to_quat(o2w[:3, :3]).numpy()
    return wxyz, o2w[:3, 3].numpy(), bool(model.track_valid[node, frame])


@dataclass(frozen=True)
class Frustum:
    """A view's camera for :meth:`viser.SceneApi.add_camera_frustum` (OpenCV axes, like vadgs)."""

    view: int
    camera: str
    fov: float  # vertical, radians
    aspect: float  # width / height
    wxyz: np.ndarray
    position: np.ndarray


def frame_frusta(scene: Scene, frame: int) -> list[Frustum]:
    """The recorded views of a frame position as camera frusta in the world."""
    out = []
    for v in scene.frames[frame].view_ids:
        info = scene.views[v]
        cam = scene.cameras_info[info.camera]
        h, w = cam.image_size
        fy = float(cam.K[1, 1])
        c2w = info.cam_to_world.detach().cpu().double()
        out.append(
            Frustum(
                v,
                info.camera,
                2.0 * math.atan(h / (2.0 * fy)),
                w / h,
                rotation_to_quat(c2w[:3, :3]).numpy(),
                c2w[:3, 3].numpy(),
            )
        )
    return out


_CAMERA_COLORS = [
    (230, 80, 40),
    (40, 120, 230),
    (40, 170, 70),
    (200, 60, 200),
    (220, 180, 30),
    (30, 180, 180),
]


class Viewer:
    """The handles of :func:`build_viewer`; :meth:`set_frame` / :meth:`set_filter` update the scene.

    Attributes:
        server: the ``viser.ViserServer``.
        slider, index, choice: the GUI's frame slider, frame-index text and VAD-GS selector (None
            until :func:`build_viewer` adds them).
        groups: the :class:`SplatGroup` s, with ``handles[i]`` their splat handles.
        frame: the current frame position.
        filter: the current choice of :data:`FILTERS`.
    """

    def __init__(
        self, model: GaussianModel, scene: Scene, server: Any, groups: list[SplatGroup], frustum_scale: float
    ):
        self.model, self.scene, self.server, self.groups = model, scene, server, groups
        self.frustum_scale = frustum_scale
        self.handles = [server.scene.add_gaussian_splats(g.name, **g.arrays) for g in groups]
        self.frusta: list[Any] = []
        self.frame = 0
        self.filter = FILTERS[0]
        self.slider: Any = None  # GUI handles, set by build_viewer
        self.index: Any = None
        self.choice: Any = None

    def visible(self, group: SplatGroup) -> bool:
        """Whether a group is shown at the current frame and filter."""
        if self.filter == FILTERS[1] and not group.added:
            return False
        if self.filter == FILTERS[2] and group.added:
            return False
        return node_pose(self.model, group.node, self.frame)[2]

    def visible_counts(self) -> dict[str, int]:
        """Shown Gaussians per node (``static``, ``track_<id>``)."""
        out: dict[str, int] = {}
        for g in self.groups:
            if self.visible(g):
                key = "static" if g.node < 0 else f"track_{self.model.track_ids[g.node]}"
                out[key] = out.get(key, 0) + int(g.rows.numel())
        return out

    def set_frame(self, frame: int) -> None:
        """Pose the track nodes and draw the frusta of frame position ``frame``."""
        if not 0 <= frame < len(self.scene.frames):
            raise ValueError(f"frame: expected a position in [0, {len(self.scene.frames)}), got {frame}")
        self.frame = int(frame)
        if self.slider is not None and int(self.slider.value) != self.frame:
            self.slider.value = self.frame
        if self.index is not None:
            self.index.content = f"frame index {self.scene.frames[self.frame].index}"
        for g, h in zip(self.groups, self.handles):
            wxyz, pos, _ = node_pose(self.model, g.node, self.frame)
            h.wxyz, h.position = wxyz, pos
            h.visible = self.visible(g)
        for h in self.frusta:
            h.remove()
        self.frusta = []
        names = self.scene.camera_names
        for fr in frame_frusta(self.scene, self.frame):
            color = _CAMERA_COLORS[names.index(fr.camera) % len(_CAMERA_COLORS)]
            self.frusta.append(
                self.server.scene.add_camera_frustum(
                    f"/cameras/{fr.camera}",
                    fov=fr.fov,
                    aspect=fr.aspect,
                    scale=self.frustum_scale,
                    color=color,
                    wxyz=fr.wxyz,
                    position=fr.position,
                )
            )

    def set_filter(self, choice: str) -> None:
        """Show all Gaussians, only the VAD-GS additions, or none of them (:data:`FILTERS`)."""
        if choice not in FILTERS:
            raise ValueError(f"filter: expected one of {list(FILTERS)}, got {choice!r}")
        self.filter = choice
        for g, h in zip(self.groups, self.handles):
            h.visible = self.visible(g)
        if self.choice is not None and self.choice.value != choice:
            self.choice.value = choice  # the GUI shows what the scene shows

    def home_camera(self) -> tuple[np.ndarray, np.ndarray]:
        """``(position, look_at)`` of a default viewpoint: above and behind the frame's first camera."""
        fr = frame_frusta(self.scene, self.frame)[0]
        c2w = quaternion_to_rotation(torch.tensor(fr.wxyz, dtype=torch.float64)).numpy()
        forward = c2w[:, 2] * np.array([1.0, 1.0, 0.0])
        forward = forward / max(np.linalg.norm(forward), 1e-9)
        position = fr.position - 8.0 * forward + np.array([0.0, 0.0, 6.0])
        return position, fr.position + 15.0 * forward


def build_viewer(
    model: GaussianModel,
    scene: Scene,
    server: Any,
    frame: int = 0,
    max_gaussians: int | None = 200_000,
    frustum_scale: float = 0.6,
) -> Viewer:
    """Populate a viser server with the model, the cameras and the controls.

    Args:
        model: the trained model (its frames are the scene's, by position).
        scene: the scene of the run.
        server: a ``viser.ViserServer``.
        frame: initial frame position.
        max_gaussians: at most this many Gaussians are sent to the browser.
        frustum_scale: size of the camera frusta (metres).

    Returns:
        The :class:`Viewer`; the GUI (frame slider, VAD-GS selector) drives it.
    """
    if model.object_to_world.shape[1] != len(scene.frames):
        raise ValueError(
            f"model has {model.object_to_world.shape[1]} frames, scene {scene.name!r} {len(scene.frames)}"
        )
    server.scene.set_up_direction("+z")
    viewer = Viewer(model, scene, server, viewer_groups(model, max_gaussians), frustum_scale)
    viewer.set_frame(frame)
    added = int((model.provenance > 0).sum())
    events = int(model.provenance.max()) if model.num_gaussians else 0
    server.gui.add_markdown(
        f"**{scene.name}**: {model.num_gaussians} Gaussians ({added} added by {events} VAD-GS events), "
        f"{len(model.track_ids)} moving objects; showing {sum(int(g.rows.numel()) for g in viewer.groups)}"
    )
    viewer.slider = server.gui.add_slider(
        "frame", min=0, max=max(len(scene.frames) - 1, 1), step=1, initial_value=viewer.frame
    )
    viewer.index = server.gui.add_markdown(f"frame index {scene.frames[viewer.frame].index}")
    viewer.choice = server.gui.add_dropdown("VAD-GS additions", FILTERS, initial_value=FILTERS[0])

    @viewer.slider.on_update
    def _(_event: Any) -> None:
        pos = min(int(viewer.slider.value), len(scene.frames) - 1)
        if pos != viewer.frame:
            viewer.set_frame(pos)

    @viewer.choice.on_update
    def _(_event: Any) -> None:
        if viewer.choice.value != viewer.filter:
            viewer.set_filter(str(viewer.choice.value))

    @server.on_client_connect
    def _(client: Any) -> None:
        position, look_at = viewer.home_camera()
        client.camera.up_direction = (0.0, 0.0, 1.0)
        client.camera.position = tuple(position)
        client.camera.look_at = tuple(look_at)

    return viewer


def find_chromium() -> str | None:
    """The path of ``chromium``, ``chromium-browser`` or ``google-chrome`` on the PATH (None: none)."""
    found = (shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome"))
    return next(filter(None, found), None)


def browser_screenshot(
    url: str,
    path: str | Path,
    size: tuple[int, int] = (1280, 800),
    budget_ms: int = 30000,
    chromium: str | None = None,
) -> Path:
    """Load ``url`` in headless Chromium (software WebGL) and write a PNG screenshot.

    Args:
        url: the viewer's address, e.g. ``http://127.0.0.1:8080``.
        path: output PNG.
        size: window ``(width, height)``.
        budget_ms: Chromium's virtual time budget: how long the page may load and draw.
        chromium: the browser executable (default: ``chromium``, ``chromium-browser`` or
            ``google-chrome`` on the PATH).

    Returns:
        ``path``.
    """
    exe = chromium or find_chromium()
    if exe is None:
        raise FileNotFoundError("chromium: not found on the PATH (Debian: apt install chromium)")
    path = Path(path)
    cmd = [
        exe,
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu-sandbox",
        "--enable-unsafe-swiftshader",  # software WebGL where there is no GPU
        "--use-angle=swiftshader",
        f"--window-size={size[0]},{size[1]}",
        f"--virtual-time-budget={budget_ms}",
        "--hide-scrollbars",
        f"--screenshot={path}",
        url,
    ]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=60 + 4 * budget_ms / 1000)
    if r.returncode != 0 or not path.is_file():
        raise RuntimeError(
            f"chromium: screenshot of {url} failed (exit {r.returncode}): {r.stderr.strip()[-500:]}"
        )
    return path
