"""The scene model: static Gaussians in the world, one node per moving object, and a sky.

:class:`GaussianModel` stores every Gaussian *raw* (means, ``wxyz`` quaternions, log-scales,
opacity logits, SH coefficients) in one flat :class:`~torch.nn.ParameterDict`, with an integer
``node_ids`` entry (not trainable) saying where each Gaussian lives: ``-1`` for the static
background (world frame), ``k >= 0`` for the ``k``-th track node (its object frame, posed per frame
by ``object_to_world``). Every entry of ``params`` is per Gaussian (gsplat's convention), so the
densification helpers of :mod:`vadgs.train.strategy.ops` add or remove Gaussians of any node with one
optimizer, and a strategy written for gsplat's params dict sees the same structure; a node is just
an index set. A second integer entry, ``provenance``, records where each Gaussian came from: ``0``
for the initial ones (and their clones and splits), ``k >= 1`` for those added by the ``k``-th
visibility-aware densification event (:mod:`vadgs.train.vad`) and their descendants.

:func:`gaussians_at` composes the activated Gaussians of a frame in the world;
:meth:`GaussianModel.render` renders them (colours from SH evaluated with the viewing direction
in each Gaussian's own frame, so a turning car keeps its view-dependent colour) over a learned
sky: a low-degree spherical-harmonics function of the world ray direction.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from vadgs.checks import check_shape
from vadgs.geometry.camera import invert_rigid, pixel_grid
from vadgs.geometry.rotation import quat_left_matrix, rotation_to_quat
from vadgs.render import RasterConfig, RenderOutput, eval_sh, num_sh_bases, rasterize_gaussians, rgb_to_sh

__all__ = [
    "PER_GAUSSIAN",
    "FramePlan",
    "GaussianModel",
    "Gaussians",
    "ModelRender",
    "adam",
    "frame_plan",
    "gaussians_at",
    "make_optimizer",
]

#: Names of the per-Gaussian parameters, in storage order.
PER_GAUSSIAN = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")


class Gaussians(NamedTuple):
    """Activated Gaussians of one frame, in the world frame.

    Attributes:
        means: ``(M, 3)`` world positions.
        quats: ``(M, 4)`` ``wxyz`` world orientations (not normalised).
        scales: ``(M, 3)`` positive.
        opacities: ``(M,)`` in ``(0, 1)``.
        sh: ``(M, K, 3)`` SH coefficients (in each Gaussian's own frame).
        ids: ``(M,)`` int64 index of each row in the model (rows of absent nodes are left out).
        object_to_world_rot: ``(M, 3, 3)`` rotation of each Gaussian's frame (identity for static).
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor
    ids: torch.Tensor
    object_to_world_rot: torch.Tensor


class ModelRender(NamedTuple):
    """What :meth:`GaussianModel.render` returns.

    Attributes:
        color: ``(1, 3, H, W)`` Gaussians composited over the sky.
        raster: the renderer's :class:`~vadgs.render.RenderOutput` (black background); its
            ``means2d`` rows follow ``ids``.
        sky: ``(1, 3, H, W)`` the sky colour of every pixel.
        ids: ``(M,)`` model rows that were rendered (see :attr:`Gaussians.ids`).
    """

    color: torch.Tensor
    raster: RenderOutput
    sky: torch.Tensor
    ids: torch.Tensor


def gaussians_at(
    params: dict[str, torch.Tensor],
    node_ids: torch.Tensor,
    object_to_world: torch.Tensor,
    track_valid: torch.Tensor,
    frame: int,
    plan: FramePlan | None = None,
) -> Gaussians:
    r"""Compose static and moving Gaussians of one frame in the world.

    A Gaussian of node ``k`` at ``(\mu, q)`` in its object frame is placed at
    ``R_k \mu + t_k`` with orientation ``q(R_k) ⊗ q``, ``[R_k | t_k] = object_to_world[k, frame]``.
    Nodes whose pose is not valid at ``frame`` are left out. Scales are ``exp(log_scales)``,
    opacities ``sigmoid(opacity_logits)``. Differentiable w.r.t. every parameter; the poses are
    constants.

    Args:
        params: raw parameters, keys :data:`PER_GAUSSIAN` (``sh_dc (N, 1, 3)``, ``sh_rest (N, K-1, 3)``).
        node_ids: ``(N,)`` int64, ``-1`` static, ``k`` track node.
        object_to_world: ``(T, F, 4, 4)`` poses of the track nodes.
        track_valid: ``(T, F)`` bool.
        frame: frame position (index into ``Scene.frames`` and ``Track.object_to_world``).
        plan: :func:`frame_plan` of these arguments, made before (what does not depend on the
            parameters' values): without it, made here (a read or two by the host).

    Returns:
        :class:`Gaussians`.

    Example:
        >>> p = {"means": torch.zeros(2, 3), "quats": torch.tensor([[1.0, 0, 0, 0]] * 2),
        ...      "log_scales": torch.zeros(2, 3), "opacity_logits": torch.zeros(2),
        ...      "sh_dc": torch.zeros(2, 1, 3), "sh_rest": torch.zeros(2, 0, 3)}
        >>> o2w = torch.eye(4).repeat(1, 1, 1, 1); o2w[0, 0, 0, 3] = 5.0
        >>> g = gaussians_at(p, torch.tensor([-1, 0]), o2w, torch.ones(1, 1, dtype=torch.bool), 0)
        >>> g.means[:, 0].tolist(), g.ids.tolist()
        ([0.0, 5.0], [0, 1])
    """
    means, quats = params["means"], params["quats"]
    if plan is None:
        plan = frame_plan(node_ids, object_to_world, track_valid, frame, means.dtype)
    n = means.shape[0]
    if plan.present == n:  # every Gaussian: no gather
        ids = torch.arange(n, device=means.device)
    else:
        present = node_ids < 0
        if object_to_world.shape[0]:
            node_valid = track_valid[:, frame]
            present = present | ((node_ids >= 0) & node_valid[node_ids.clamp(min=0)])
        ids = torch.nonzero_static(present, size=plan.present).squeeze(1)

    def take(t: torch.Tensor) -> torch.Tensor:
        return t if plan.present == n else t[ids]

    m, q = take(means), take(quats)
    eye = torch.eye(3, device=means.device, dtype=means.dtype)
    rot = eye.expand(plan.present, 3, 3)
    if plan.node_rot is not None:
        assert plan.node_t is not None and plan.node_q is not None  # made together
        slot = take(node_ids) + 1
        rot = plan.node_rot[slot]
        m = (rot @ m[:, :, None]).squeeze(-1) + plan.node_t[slot]
        q = (plan.node_q[slot] @ q[:, :, None]).squeeze(-1)  # q(R_k) ⊗ q (quat_left_matrix)
    sh = torch.cat([take(params["sh_dc"]), take(params["sh_rest"])], 1)
    return Gaussians(
        m, q, take(params["log_scales"]).exp(), torch.sigmoid(take(params["opacity_logits"])), sh, ids, rot
    )


class FramePlan(NamedTuple):
    """What :func:`gaussians_at` needs of a frame besides the parameters' values (:func:`frame_plan`).

    Attributes:
        present: Gaussians present at the frame (static ones and those of nodes valid there).
        node_rot: ``(T + 1, 3, 3)`` rotation of each node at the frame (slot 0: static, identity);
            None when no Gaussian of a valid node is present (every Gaussian is placed as it is).
        node_t: ``(T + 1, 3)`` translations, likewise.
        node_q: ``(T + 1, 4, 4)`` the rotations as ``wxyz`` quaternions, as the matrices of
            their left multiplication (:func:`~vadgs.geometry.rotation.quat_left_matrix`), likewise.
    """

    present: int
    node_rot: torch.Tensor | None
    node_t: torch.Tensor | None
    node_q: torch.Tensor | None


def frame_plan(
    node_ids: torch.Tensor,
    object_to_world: torch.Tensor,
    track_valid: torch.Tensor,
    frame: int,
    dtype: torch.dtype,
    node_counts: list[int] | None = None,
) -> FramePlan:
    """The :class:`FramePlan` of :func:`gaussians_at`'s arguments at ``frame``.

    Reads the frame's node validity and, without ``node_counts`` (Gaussians of each node slot,
    ``[static, node 0, node 1, ...]``), the node of every Gaussian: a model keeps both
    (:meth:`GaussianModel.gaussians_at`) and makes a frame's plan again only when they change.

    Example:
        >>> o2w = torch.eye(4).repeat(1, 2, 1, 1); valid = torch.tensor([[True, False]])
        >>> [frame_plan(torch.tensor([-1, 0, 0]), o2w, valid, f, torch.float32).present for f in (0, 1)]
        [3, 1]
    """
    num_tracks = object_to_world.shape[0]
    if node_counts is None:
        node_counts = torch.bincount(node_ids + 1, minlength=num_tracks + 1).tolist()
    valid = track_valid[:, frame].tolist() if num_tracks else []
    moving = sum(c for c, v in zip(node_counts[1:], valid) if v)
    if not moving:
        return FramePlan(node_counts[0] + moving, None, None, None)
    dev = object_to_world.device
    o2w = object_to_world[:, frame].to(dtype)  # (T, 4, 4)
    eye = torch.eye(3, device=dev, dtype=dtype)
    node_rot = torch.cat([eye[None], o2w[:, :3, :3]])  # slot 0 = static
    node_t = torch.cat([torch.zeros(1, 3, device=dev, dtype=dtype), o2w[:, :3, 3]])
    return FramePlan(node_counts[0] + moving, node_rot, node_t, quat_left_matrix(rotation_to_quat(node_rot)))


class GaussianModel(nn.Module):
    """Static background Gaussians, one node per rigidly moving track, and a learned sky.

    See :func:`gaussians_at` for the composition. Parameters are stored raw in
    :attr:`params` (keys :data:`PER_GAUSSIAN`); :attr:`sky` holds the sky's SH coefficients
    ``(num_sh_bases(sky_degree), 3)`` over world ray directions (degree 0 = a single learned
    background colour).

    Args:
        means: ``(N, 3)`` positions (world for static, object frame for track nodes).
        colors: ``(N, 3)`` initial RGB in ``[0, 1]``.
        log_scales: ``(N, 3)``.
        node_ids: ``(N,)`` int64 (``-1`` static, ``k`` the ``k``-th of ``track_ids``).
        object_to_world: ``(T, F, 4, 4)`` track poses; ``(0, F, 4, 4)`` without tracks.
        track_valid: ``(T, F)`` bool.
        track_ids: the instance id of each track node.
        sh_degree: maximum SH degree of the Gaussians (0–3).
        sky_degree: SH degree of the sky (0–3).
        init_opacity: initial opacity.
        quats: ``(N, 4)`` initial ``wxyz`` (identity when None).

    Example:
        >>> model = GaussianModel(torch.randn(10, 3), torch.rand(10, 3), torch.full((10, 3), -2.0),
        ...                       torch.full((10,), -1), torch.zeros(0, 1, 4, 4),
        ...                       torch.zeros(0, 1, dtype=torch.bool), [], sh_degree=1)
        >>> model.num_gaussians, tuple(model.params["sh_rest"].shape)
        (10, (10, 3, 3))
    """

    # buffers (registered in __init__), declared for the type checker
    object_to_world: torch.Tensor
    track_valid: torch.Tensor

    def __init__(
        self,
        means: torch.Tensor,
        colors: torch.Tensor,
        log_scales: torch.Tensor,
        node_ids: torch.Tensor,
        object_to_world: torch.Tensor,
        track_valid: torch.Tensor,
        track_ids: Sequence[int],
        sh_degree: int = 3,
        sky_degree: int = 2,
        init_opacity: float = 0.1,
        quats: torch.Tensor | None = None,
    ) -> None:
        super().__init__()
        dims = check_shape(means, "means", ("N", 3))
        check_shape(colors, "colors", ("N", 3), dims)
        check_shape(log_scales, "log_scales", ("N", 3), dims)
        check_shape(node_ids, "node_ids", ("N",), dims)
        check_shape(object_to_world, "object_to_world", ("T", "F", 4, 4), dims)
        check_shape(track_valid, "track_valid", ("T", "F"), dims)
        if len(track_ids) != dims["T"]:
            raise ValueError(f"track_ids: expected {dims['T']} ids, got {len(track_ids)}")
        if node_ids.numel() and int(node_ids.max()) >= dims["T"]:
            raise ValueError(f"node_ids: expected values in [-1, {dims['T']}), got max {int(node_ids.max())}")
        n = dims["N"]
        k = num_sh_bases(sh_degree)
        num_sh_bases(sky_degree)
        if quats is None:
            quats = torch.zeros(n, 4, dtype=means.dtype, device=means.device)
            quats[:, 0] = 1.0
        logit = torch.logit(torch.tensor(init_opacity, dtype=means.dtype))
        self.params = nn.ParameterDict(
            {
                "means": nn.Parameter(means.clone()),
                "quats": nn.Parameter(quats.clone()),
                "log_scales": nn.Parameter(log_scales.clone()),
                "opacity_logits": nn.Parameter(
                    torch.full((n,), float(logit), dtype=means.dtype, device=means.device)
                ),
                "sh_dc": nn.Parameter(rgb_to_sh(colors.clamp(0, 1))[:, None, :].clone()),
                "sh_rest": nn.Parameter(torch.zeros(n, k - 1, 3, dtype=means.dtype, device=means.device)),
            }
        )
        sky = torch.zeros(num_sh_bases(sky_degree), 3, dtype=means.dtype, device=means.device)
        sky[0] = rgb_to_sh(torch.full((3,), 0.7, dtype=means.dtype))
        self.params["node_ids"] = nn.Parameter(node_ids.long().clone(), requires_grad=False)
        self.params["provenance"] = nn.Parameter(
            torch.zeros(n, dtype=torch.int64, device=means.device), requires_grad=False
        )
        self.sky = nn.Parameter(sky)
        self.register_buffer("object_to_world", object_to_world.clone())
        self.register_buffer("track_valid", track_valid.bool().clone())
        self.track_ids = [int(t) for t in track_ids]
        self.sh_degree = sh_degree
        self.sky_degree = sky_degree
        self.active_sh_degree = 0
        self._plans: dict = {}  # _plan's

    # -- sizes ----------------------------------------------------------------------------------------

    @property
    def node_ids(self) -> torch.Tensor:
        """``(N,)`` int64 node of each Gaussian (``-1``: static, ``k``: ``k``-th track)."""
        return self.params["node_ids"]

    @node_ids.setter
    def node_ids(self, value: torch.Tensor) -> None:
        self.params["node_ids"] = nn.Parameter(value.long(), requires_grad=False)

    @property
    def provenance(self) -> torch.Tensor:
        """``(N,)`` int64 origin of each Gaussian: ``0`` initial, ``k >= 1`` added by VAD-GS event ``k``.

        Clones and splits inherit their parent's value (:mod:`vadgs.train.strategy.ops` copies integer rows).
        """
        return self.params["provenance"]

    @provenance.setter
    def provenance(self, value: torch.Tensor) -> None:
        self.params["provenance"] = nn.Parameter(value.long(), requires_grad=False)

    @property
    def num_gaussians(self) -> int:
        """Number of Gaussians (all nodes)."""
        return self.params["means"].shape[0]

    def node_counts(self) -> dict[str, int]:
        """Gaussians per node: ``{"static": n, "track_<id>": n, ...}``."""
        out = {"static": int((self.node_ids < 0).sum())}
        for k, tid in enumerate(self.track_ids):
            out[f"track_{tid}"] = int((self.node_ids == k).sum())
        return out

    # -- composition and rendering --------------------------------------------------------------------

    def gaussians_at(self, frame: int) -> Gaussians:
        """Activated Gaussians of a frame in the world; see :func:`gaussians_at`.

        The frame's :class:`FramePlan` is kept until the nodes of the Gaussians or the poses
        change (a strategy's refinement, an event): a step composes its frame without a read.
        """
        return gaussians_at(
            dict(self.params), self.node_ids, self.object_to_world, self.track_valid, frame, self._plan(frame)
        )

    def _plan(self, frame: int) -> FramePlan:
        """The frame's :class:`FramePlan`, kept while ``node_ids``, the poses and the dtype are the same."""
        tensors = (self.node_ids, self.object_to_world, self.track_valid)
        # the tensors themselves are held: a new one cannot reuse their storage while the key is kept
        key = (*tensors, *(t._version for t in tensors), self.params["means"].dtype)
        cached = self._plans
        old = cached.get("key")
        if old is None or any(a is not b for a, b in zip(old[:3], key[:3])) or old[3:] != key[3:]:
            counts = torch.bincount(tensors[0] + 1, minlength=tensors[1].shape[0] + 1).tolist()
            cached.clear()
            cached.update(key=key, counts=counts, frames={})
        frames = cached["frames"]
        if frame not in frames:
            frames[frame] = frame_plan(*tensors, frame, key[-1], cached["counts"])
        return frames[frame]

    def sky_color(
        self, world_to_cam: torch.Tensor, K: torch.Tensor, image_size: tuple[int, int]
    ) -> torch.Tensor:
        """Sky colour ``(B, 3, H, W)``: ``max(0, 0.5 + Σ Y_k(d) s_k)`` over each pixel's world ray ``d``.

        Differentiable w.r.t. :attr:`sky`.
        """
        return self._sky_color(invert_rigid(world_to_cam), K, image_size)

    def _sky_color(
        self,
        cam_to_world: torch.Tensor,
        K: torch.Tensor,
        image_size: tuple[int, int],
        rays: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """:meth:`sky_color` of cameras given as camera-to-world transforms (already inverted).

        ``rays``: :meth:`sky_rays` of ``K`` and ``image_size`` when the caller keeps them.
        """
        h, w = image_size
        rays = self.sky_rays(K, image_size) if rays is None else rays
        dirs = F.normalize(rays @ cam_to_world[:, :3, :3].transpose(-1, -2), dim=-1)
        b = cam_to_world.shape[0]
        coeffs = self.sky[None].expand(h * w, -1, -1)
        col = eval_sh(coeffs, dirs.reshape(b, h * w, 3), self.sky_degree, max_value=1.0)
        return col.reshape(b, h, w, 3).permute(0, 3, 1, 2)

    @staticmethod
    def sky_rays(K: torch.Tensor, image_size: tuple[int, int]) -> torch.Tensor:
        """Each pixel's ray in the camera frame, ``(B, H W, 3)`` (``(u, v, 1) K⁻ᵀ``), for the sky."""
        pix = pixel_grid(image_size, device=K.device, dtype=K.dtype).reshape(-1, 2)
        ones = torch.ones_like(pix[:, :1])
        return torch.cat([pix, ones], -1) @ torch.linalg.inv(K).transpose(-1, -2)  # (B, HW, 3) camera

    def _to_render(
        self, world_to_cam: torch.Tensor, K: torch.Tensor, frame: int, opacity_override: float | None
    ) -> tuple[Gaussians, torch.Tensor]:
        """The frame's Gaussians and the opacities to render them with (checked camera)."""
        check_shape(world_to_cam, "world_to_cam", (1, 4, 4))
        check_shape(K, "K", (1, 3, 3))
        g = self.gaussians_at(frame)
        if opacity_override is None:
            return g, g.opacities
        return g, torch.full_like(g.opacities.detach(), float(opacity_override))

    def render(
        self,
        world_to_cam: torch.Tensor,
        K: torch.Tensor,
        image_size: tuple[int, int],
        frame: int,
        config: RasterConfig | None = None,
        opacity_override: float | None = None,
        hard_depth: bool = False,
        cam_to_world: torch.Tensor | None = None,
        sky_rays: torch.Tensor | None = None,
    ) -> ModelRender:
        """Render one view of a frame: the frame's Gaussians over the sky.

        Colours are the SH evaluated at the active degree with the viewing direction rotated into
        each Gaussian's own frame. Differentiable w.r.t. every parameter and the sky.

        Args:
            world_to_cam: ``(1, 4, 4)``.
            K: ``(1, 3, 3)``.
            image_size: ``(H, W)``.
            frame: frame position.
            config: rasterizer settings.
            opacity_override: when given, every Gaussian is rendered with this *fixed* opacity
                (no gradient to the opacity logits), e.g. ``1.0`` for the "hard" depth of
                :func:`vadgs.train.losses.depth_loss_hard`.
            hard_depth: also the hard depth (every opacity 1) in the same pass, as
                ``raster.hard_depth`` (:func:`~vadgs.render.rasterize_gaussians`).
            cam_to_world: ``invert_rigid(world_to_cam)`` when the caller keeps it (vadgs's
                trainer, per view), else computed here with its value check (one read a render).
            sky_rays: :meth:`sky_rays` of ``K`` and ``image_size`` when the caller keeps them
                (vadgs's trainer, per camera), else computed here.

        Returns:
            :class:`ModelRender`.
        """
        g, opac = self._to_render(world_to_cam, K, frame, opacity_override)
        if cam_to_world is None:
            cam_to_world = invert_rigid(world_to_cam)
        else:
            check_shape(cam_to_world, "cam_to_world", (1, 4, 4))
        center = cam_to_world[0, :3, 3]
        dirs = F.normalize(g.means.detach() - center, dim=-1)
        dirs_local = (g.object_to_world_rot.transpose(-1, -2) @ dirs[:, :, None]).squeeze(-1)
        colors = eval_sh(g.sh, dirs_local, self.active_sh_degree)
        raster = rasterize_gaussians(
            g.means, g.quats, g.scales, opac, colors, world_to_cam, K, image_size, config=config,
            hard_depth=hard_depth,
        )  # fmt: skip
        sky = self._sky_color(cam_to_world, K, image_size, sky_rays)
        color = raster.color + (1.0 - raster.alpha) * sky
        return ModelRender(color, raster, sky, g.ids)

    def render_depth(
        self,
        world_to_cam: torch.Tensor,
        K: torch.Tensor,
        image_size: tuple[int, int],
        frame: int,
        config: RasterConfig | None = None,
        opacity_override: float | None = None,
    ) -> RenderOutput:
        """Render geometry only: :meth:`render`'s ``raster`` without colour (no SH, no sky).

        ``color`` is ``(1, 0, H, W)`` (``(1, 1, H, W)`` of zeros with the gsplat backend); depth,
        alpha, normals and the rest equal :meth:`render`'s (each channel is composited on its own),
        at less cost: for the hard depth loss (``opacity_override=1.0``:
        :func:`~vadgs.train.objective.render_hard_depth`) and other depth-only renders.
        """
        g, opac = self._to_render(world_to_cam, K, frame, opacity_override)
        channels = 1 if config is not None and config.backend == "gsplat" else 0  # gsplat: >= 1 channel
        no_color = g.means.new_zeros(g.means.shape[0], channels)
        return rasterize_gaussians(
            g.means, g.quats, g.scales, opac, no_color, world_to_cam, K, image_size, config=config
        )

    # -- (de)serialisation ----------------------------------------------------------------------------

    def extra_state(self) -> dict:
        """Non-tensor state for checkpoints."""
        return {
            "track_ids": list(self.track_ids),
            "sh_degree": self.sh_degree,
            "sky_degree": self.sky_degree,
            "active_sh_degree": self.active_sh_degree,
        }

    @classmethod
    def from_state(cls, state_dict: dict[str, torch.Tensor], extra: dict) -> GaussianModel:
        """Rebuild a model of the stored size from :meth:`state_dict` and :meth:`extra_state`."""
        n = state_dict["params.means"].shape[0]
        model = cls(
            torch.zeros(n, 3),
            torch.zeros(n, 3),
            torch.zeros(n, 3),
            state_dict["params.node_ids"] if "params.node_ids" in state_dict else state_dict["node_ids"],
            state_dict["object_to_world"],
            state_dict["track_valid"],
            extra["track_ids"],
            sh_degree=int(extra["sh_degree"]),
            sky_degree=int(extra["sky_degree"]),
        )
        model.load_state_dict(state_dict)
        model.active_sh_degree = int(extra["active_sh_degree"])
        return model


def make_optimizer(
    model: GaussianModel, lrs: dict[str, float], eps: float = 1e-15, fused: bool | None = None
) -> torch.optim.Adam:
    """One Adam with a named param group per parameter (per-Gaussian ones and ``"sky"``).

    The layout :mod:`vadgs.train.strategy.ops` expects of one optimizer: each group is named for
    the entry of ``model.params`` it holds (``"sky"``: :attr:`GaussianModel.sky`).

    Args:
        model: the model.
        lrs: learning rate per name (:data:`PER_GAUSSIAN` and ``"sky"``).
        eps: Adam epsilon (3DGS uses 1e-15).
        fused: torch's fused Adam (one kernel a group instead of about nine, no read of the step
            count by the host, and an update skipped on the device when ``optimizer.found_inf`` is
            1: see :meth:`~vadgs.train.trainer.Trainer.train_step`); it rounds differently from the
            ``foreach`` one in the last bit. None: fused where this torch has it for the model's
            device (:func:`adam`).

    Raises:
        ValueError: if ``lrs`` lacks a name.

    Example:
        >>> m = GaussianModel(torch.zeros(4, 3), torch.zeros(4, 3), torch.zeros(4, 3), torch.full((4,), -1),
        ...                   torch.zeros(0, 1, 4, 4), torch.zeros(0, 1, dtype=torch.bool), [], sh_degree=0)
        >>> opt = make_optimizer(m, dict.fromkeys([*PER_GAUSSIAN, "sky"], 1e-3))
        >>> [g["name"] for g in opt.param_groups][:2]
        ['means', 'quats']
    """
    missing = [k for k in (*PER_GAUSSIAN, "sky") if k not in lrs]
    if missing:
        raise ValueError(f"lrs: missing learning rates for {missing}")
    groups = [{"params": [model.params[k]], "lr": lrs[k], "name": k} for k in PER_GAUSSIAN]
    groups.append({"params": [model.sky], "lr": lrs["sky"], "name": "sky"})
    return adam(groups, eps=eps, fused=fused)


def adam(params: Any, fused: bool | None = None, **kwargs: Any) -> torch.optim.Adam:
    """``torch.optim.Adam(params, fused=fused, **kwargs)``; ``fused=None``: fused where torch has it.

    Torch's fused Adam runs on CPU and CUDA from torch 2.4; an older torch, or a device it does not
    support, gets the default (``foreach``) one when ``fused`` is None, and the error when it is True.

    Example:
        >>> opt = adam([torch.nn.Parameter(torch.zeros(3))], lr=0.1)
        >>> opt.param_groups[0]["fused"]
        True
    """
    if fused is not None:
        return torch.optim.Adam(params, fused=fused, **kwargs)
    params = list(params)
    try:
        return torch.optim.Adam(params, fused=True, **kwargs)
    except (RuntimeError, ValueError, TypeError):  # this torch or device has no fused Adam
        return torch.optim.Adam(params, **kwargs)
