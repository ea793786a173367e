# Frozen copy of vadgs/train/vad.py at commit 274c932 (before issue 21), the reference of
# benchmarks/bench_vad_event.py. Not maintained: do not import it from vadgs.
# ruff: noqa
r"""VAD-GS: the visibility-aware densification strategy (paper, Sec. "Methodology").

:class:`VisibilityAwareDensification` is a gsplat-style strategy
(``initialize_state`` / ``step_pre_backward`` / ``step_post_backward`` on ``params``,
``optimizers``, ``state``, ``step``, ``info``) that wraps a standard one (adaptive density control)
and never sees the training loop: it gets the scene at construction and, in a frozen
:class:`StrategyContext`, the three things of the loop it needs — a function that renders a view's
depth, opacity and normals with the current Gaussians, the total number of steps and the number
of steps of a sampling cycle — plus the generator of its selection noise. Every ``every_cycles``
complete sampling cycles of the training views it runs one event, a one-way flow:

1. **visibility index** (built once): voxel grids of the initial points with per-voxel view
   visibility (:func:`~vadgs.train.reconstruct.build_visibility_index`: LiDAR, or COLMAP tracks);
2. **incompleteness test**: for every training view, the rendered depth and opacity against the
   voxel depth of the z-buffer (static grid in world, each moving object's grid in its own frame);
   per instance, flag when the rendered depth is absent or more than 1.1× the voxel depth, or when
   more than 25 % of its pixels are below 0.7 opacity
   (:func:`~vadgs.train.incomplete.find_incomplete`);
3. **selection and MVS**: each flagged instance (:func:`rank_instances`, :func:`pick_references`) is
   reconstructed from its reference views: diversity-aware k-clique view selection, PatchMatch
   initialised from the rendered depth and normals and restricted to the instance (a moving object
   in its own frame), consistency and fusion (:func:`~vadgs.train.reconstruct.reconstruct_instance`);
4. **new Gaussians**: the fused points that the current Gaussians do not already explain (no opaque
   surface within ``explained_tolerance`` in front of them in the reference view) become flat
   Gaussians oriented by the MVS normals — static, or in the object's frame for moving ones — added
   with :func:`~vadgs.train.ops.add_gaussians` (optimizer moments and state rows follow);
5. **priors**: the MVS depth and normals of the group views are kept in ``state`` and returned by
   :meth:`VisibilityAwareDensification.geometry_targets` (voxel depth where no MVS depth exists),
   which the loop turns into the normal and hard/soft depth losses with
   :func:`vadgs.train.losses.geometric_losses` — one loss path, in vadgs's trainer or any loop.

Ablation switches (:class:`VisibilityDensifyConfig`): ``visibility=False`` disables the whole
strategy (plain ADC), ``view_selection=False`` uses consecutive frames of the reference camera,
``geometric_losses=False`` drops the priors. Every event's cost is logged in
``state["vad_events"]`` (seconds of detection, selection + MVS, and densification).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, MutableMapping
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import torch

from vadgs.data.scene import Scene
from vadgs.geometry.camera import project_points
from vadgs.train import ops
from vadgs.train.incomplete import IncompleteConfig, find_incomplete
from vadgs.train.losses import GeometryTargets
from vadgs.train.model import rotation_to_quat
from benchmarks.legacy_event.reconstruct import (
    InstanceReconstruction,
    ReconstructConfig,
    VisibilityIndex,
    build_visibility_index,
    reconstruct_instance,
)
from vadgs.train.strategy import DefaultStrategy, Strategy

__all__ = [
    "StrategyContext",
    "ViewRender",
    "VisibilityAwareDensification",
    "VisibilityDensifyConfig",
    "normals_to_quats",
    "pick_references",
    "rank_instances",
    "voxel_depth_map",
]

_C0 = 0.28209479177387814


@dataclass(frozen=True)
class VisibilityDensifyConfig:
    """Settings of :class:`VisibilityAwareDensification` (paper values by default).

    Attributes:
        visibility: the whole strategy on (False: the "w/o voxel visibility reasoning" ablation,
            which disables everything else).
        view_selection: diversity-aware selection (False: consecutive frames of the reference
            camera, the "w/o view selection" ablation).
        geometric_losses: normal and hard/soft depth losses on the priors.
        every_cycles: detection and densification every this many complete sampling cycles.
        voxel_size: voxel edge (m) of the visibility grids.
        incomplete: thresholds of the incompleteness test.
        reconstruct: view selection / PatchMatch / consistency settings.
        max_instances: instances reconstructed per event, in the order of ``ranking`` (an instance
            whose reconstruction yields no point does not count; at most twice as many are tried).
        references: reference views per instance: its flagged view with the most pixels, then
            the next largest ones from another camera or at least ``min_frame_gap`` frames away
            from those already chosen (another side of the object, e.g. the back of a sign).
        min_frame_gap: see ``references``.
        ranking: ``"class_round_robin"`` (default): one instance per class in turn, the largest
            (most pixels in its best flagged view) first within a class, so that small structures
            such as signs are not starved by large facades; ``"pixels"``: largest first overall.
        cooldown_events: an instance reconstructed at an event is skipped for this many events.
        skip_classes: instance classes never densified (e.g. the road, which LiDAR covers).
        explained_tolerance: a point is "explained" when the reference render has opacity above
            ``incomplete.alpha_threshold`` and depth within this relative tolerance of (or in front
            of) the point.
        new_opacity: opacity of the new Gaussians.
        flatness: thickness of the new Gaussians along their normal, relative to their width.
        voxel_depth_prior: use the voxel depth where no MVS depth exists.
        last_event_fraction: no event after this fraction of the iterations (Gaussians added at
            the very end would not be trained).
    """

    visibility: bool = True
    view_selection: bool = True
    geometric_losses: bool = True
    every_cycles: int = 5
    voxel_size: float = 0.2
    incomplete: IncompleteConfig = field(default_factory=IncompleteConfig)
    reconstruct: ReconstructConfig = field(default_factory=ReconstructConfig)
    max_instances: int = 8
    references: int = 2
    min_frame_gap: int = 3
    ranking: str = "class_round_robin"
    cooldown_events: int = 1
    skip_classes: tuple[str, ...] = ("road",)
    explained_tolerance: float = 0.05
    new_opacity: float = 0.5
    flatness: float = 0.2
    voxel_depth_prior: bool = True
    last_event_fraction: float = 0.9

    def __post_init__(self) -> None:
        if self.every_cycles < 1:
            raise ValueError(f"every_cycles: expected >= 1, got {self.every_cycles}")
        if not 0 < self.new_opacity < 1:
            raise ValueError(f"new_opacity: expected in (0, 1), got {self.new_opacity}")
        if self.ranking not in RANKINGS:
            raise ValueError(f"ranking: expected one of {RANKINGS}, got {self.ranking!r}")
        if self.references < 1 or self.max_instances < 0:
            raise ValueError(
                f"references, max_instances: expected >= 1 and >= 0, got {self.references}, "
                f"{self.max_instances}"
            )


RANKINGS = ("class_round_robin", "pixels")


def pick_references(
    candidates: list[tuple[int, int]], scene, count: int, min_frame_gap: int = 3
) -> list[int]:
    """Reference views of one instance: the largest first, then diverse ones.

    Args:
        candidates: ``(view, pixels)`` of the views where the instance was flagged.
        scene: the :class:`~vadgs.data.Scene` (for each view's camera and frame).
        count: how many references at most.
        min_frame_gap: a further reference must come from a camera not chosen yet, or be at
            least this many frames from every chosen view of its camera.

    Returns:
        View indices, largest first.

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> sc = load_scene(sample_scene_path())
        >>> [(sc.views[v].camera, sc.views[v].frame) for v in (0, 1, 3)]
        [('front', 16), ('front_left', 16), ('front', 17)]
        >>> pick_references([(0, 500), (3, 450), (1, 100)], sc, 2)  # view 3: same camera, 1 frame on
        [0, 1]
    """
    chosen: list[int] = []
    for view, _px in sorted(candidates, key=lambda vp: (-vp[1], vp[0])):
        if len(chosen) >= count:
            break
        info = scene.views[view]
        if all(
            scene.views[c].camera != info.camera or abs(scene.views[c].frame - info.frame) >= min_frame_gap
            for c in chosen
        ):
            chosen.append(view)
    return chosen


def rank_instances(
    pixels: dict[int, int], classes: dict[int, str], ranking: str = "class_round_robin"
) -> list[int]:
    """Order flagged instances for reconstruction.

    Args:
        pixels: instance id → its size (pixels in its best flagged view).
        classes: instance id → class name (missing ids form one class ``""``).
        ranking: ``"pixels"`` (largest first) or ``"class_round_robin"`` (the largest of each class
            in turn; classes ordered by their largest instance).

    Example:
        >>> px = {1: 900, 2: 800, 3: 700, 7: 50, 9: 300}
        >>> cls = {1: "building", 2: "building", 3: "building", 7: "sign", 9: "tree"}
        >>> rank_instances(px, cls, "pixels")
        [1, 2, 3, 9, 7]
        >>> rank_instances(px, cls)
        [1, 9, 7, 2, 3]
    """
    if ranking not in RANKINGS:
        raise ValueError(f"ranking: expected one of {RANKINGS}, got {ranking!r}")
    order = sorted(pixels, key=lambda i: (-pixels[i], i))
    if ranking == "pixels":
        return order
    queues: dict[str, list[int]] = {}
    for i in order:  # classes in the order of their largest instance
        queues.setdefault(classes.get(i, ""), []).append(i)
    out: list[int] = []
    while any(queues.values()):
        for q in queues.values():
            if q:
                out.append(q.pop(0))
    return out


def normals_to_quats(normals: torch.Tensor) -> torch.Tensor:
    """``wxyz`` quaternions of rotations whose third axis is the given unit normal ``(N, 3)``.

    A Gaussian with scales ``(s, s, t)``, ``t << s``, and this rotation is a disc in the plane of
    the normal. On the device and in the dtype of ``normals``.

    Example:
        >>> from vadgs.render import quaternion_to_rotation
        >>> n = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]])
        >>> torch.allclose(quaternion_to_rotation(normals_to_quats(n))[:, :, 2], n, atol=1e-6)
        True
    """
    n = torch.nn.functional.normalize(normals, dim=-1)
    helper = torch.where(
        n[:, 2:3].abs() < 0.9,
        n.new_tensor([0.0, 0.0, 1.0]).expand_as(n),
        n.new_tensor([1.0, 0.0, 0.0]).expand_as(n),
    )
    a = torch.nn.functional.normalize(torch.cross(helper, n, dim=-1), dim=-1)
    b = torch.cross(n, a, dim=-1)
    R = torch.stack([a, b, n], dim=-1)  # columns: the Gaussian's axes in the world
    return rotation_to_quat(R)


def voxel_depth_map(index: VisibilityIndex, view: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Voxel depth ``(1, H, W)`` and instance label ``(H, W)`` of a view.

    See :meth:`~vadgs.train.reconstruct.VisibilityIndex.voxel_depth`.
    """
    return index.voxel_depth(view)


class ViewRender(NamedTuple):
    """What a strategy needs of a rendered view (no gradient; camera-frame normals).

    Attributes:
        depth: ``(1, H, W)`` expected z-depth.
        alpha: ``(1, H, W)`` accumulated opacity.
        normals: ``(3, H, W)`` camera-frame normals (zeros where nothing is rendered).
    """

    depth: torch.Tensor
    alpha: torch.Tensor
    normals: torch.Tensor


@dataclass(frozen=True)
class StrategyContext:
    """What :class:`VisibilityAwareDensification` needs of the training loop, given explicitly.

    Attributes:
        render: ``view -> ViewRender``: renders a view of the scene (index into ``scene.views``)
            with the current Gaussians, at the view's frame, without gradient.
        total_steps: the run's number of steps (events stop after ``last_event_fraction`` of it).
        steps_per_cycle: steps of one sampling cycle (vadgs's trainer: one view per step, so the
            number of training views); cycle ``c`` ends after step ``c * steps_per_cycle - 1``.
        generator: seeds the view-selection noise ``ξ`` and point subsampling (checkpoint it for
            exact resume; vadgs's trainer passes its own).
        track_nodes: track id → node index of ``params["node_ids"]`` (default: the scene's tracks
            in sorted order, as :func:`~vadgs.train.init.init_gaussians` numbers them). Without
            ``node_ids`` in ``params`` (a static gsplat model) moving objects are not densified.

    Example:
        >>> ctx = StrategyContext(render=lambda v: None, total_steps=3000, steps_per_cycle=40)
        >>> ctx.steps_per_cycle
        40
    """

    render: Callable[[int], ViewRender]
    total_steps: int
    steps_per_cycle: int
    generator: torch.Generator | None = None
    track_nodes: Mapping[int, int] | None = None

    def __post_init__(self) -> None:
        if self.total_steps < 0 or self.steps_per_cycle < 1:
            raise ValueError(
                f"total_steps, steps_per_cycle: expected >= 0 and >= 1, got {self.total_steps}, "
                f"{self.steps_per_cycle}"
            )


class _Renders:
    """Renders of one event, each made at most once until the Gaussians change."""

    def __init__(self, render: Callable[[int], ViewRender]) -> None:
        self.render, self.cache = render, {}

    def __call__(self, view: int) -> ViewRender:
        if view not in self.cache:
            self.cache[view] = self.render(view)
        return self.cache[view]

    def invalidate(self) -> None:
        self.cache.clear()


class VisibilityAwareDensification:
    """The VAD-GS densification strategy (gsplat ``Strategy`` interface). See the module docstring.

    Args:
        scene: the scene (training views = ``scene.train_views``; LiDAR or COLMAP tracks for the
            visibility index; instance maps, or instances derived from the voxels).
        context: :class:`StrategyContext`: the loop's render function, step counts and generator.
        config: :class:`VisibilityDensifyConfig`.
        base: the strategy it extends, whose clone/split/prune keeps running
            (default :class:`~vadgs.train.strategy.DefaultStrategy` with its defaults; vadgs's
            trainer passes its ``TrainConfig.strategy``). gsplat's ``DefaultStrategy`` works too.
        index: a prebuilt :class:`~vadgs.train.reconstruct.VisibilityIndex` (built from
            ``scene`` at the first event otherwise).

    Attributes:
        snapshots: per instance that got new Gaussians, its reference render just before:
            ``{"instance", "view", "step", "added", "depth", "alpha"}`` (for figures; not in the state).
    """

    def __init__(
        self,
        scene: Scene,
        context: StrategyContext,
        config: VisibilityDensifyConfig | None = None,
        base: Strategy | None = None,
        index: VisibilityIndex | None = None,
    ) -> None:
        if not isinstance(scene, Scene):
            raise ValueError(f"scene: expected a vadgs.data.Scene, got {type(scene).__name__}")
        if not isinstance(context, StrategyContext):
            raise ValueError(f"context: expected a StrategyContext, got {type(context).__name__}")
        self.scene = scene
        self.context = context
        self.config = config or VisibilityDensifyConfig()
        self.base = base if base is not None else DefaultStrategy()
        self.index = index
        self.snapshots: list[dict[str, Any]] = []
        if not self.config.view_selection:
            sel = replace(self.config.reconstruct.selection, method="consecutive")
            self.config = replace(self.config, reconstruct=replace(self.config.reconstruct, selection=sel))

    # -- Strategy interface ----------------------------------------------------------------------------

    def initialize_state(self, scene_scale: float = 1.0) -> dict[str, Any]:
        """The base strategy's state plus the event log, the priors and the cycle counter."""
        state = self.base.initialize_state(scene_scale)
        state.update(vad_events=[], vad_priors={}, vad_cycle=0, vad_last_done={})
        return state

    def step_pre_backward(self, params, optimizers, state, step, info) -> None:  # noqa: D102
        self.base.step_pre_backward(params, optimizers, state, step, info)

    def step_post_backward(
        self,
        params: MutableMapping[str, torch.Tensor],
        optimizers: Any,
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
    ) -> None:
        """Base densification, then a visibility-aware event after every ``every_cycles`` cycles."""
        self.base.step_post_backward(params, optimizers, state, step, info)
        if not self.config.visibility:
            return
        cycle = (step + 1) // self.context.steps_per_cycle
        if cycle != state["vad_cycle"]:
            state["vad_cycle"] = cycle
            late = step >= self.config.last_event_fraction * self.context.total_steps
            if cycle > 0 and cycle % self.config.every_cycles == 0 and not late:
                self.densify(params, optimizers, state, step)

    # -- the event ---------------------------------------------------------------------------------------

    def visibility_index(self) -> VisibilityIndex:
        """The scene's :class:`~vadgs.train.reconstruct.VisibilityIndex` (built at the first use)."""
        if self.index is None:
            self.index = build_visibility_index(self.scene, self.config.voxel_size)
        return self.index

    @torch.no_grad()
    def detect(self, views: list[int] | None = None, renders: Callable[[int], ViewRender] | None = None):
        """Run the incompleteness test on training views (default all of them).

        Args:
            views: view indices.
            renders: the render function (default the context's).

        Returns:
            ``(rows, views)``: :class:`~vadgs.train.incomplete.IncompleteInstances` (``rows.view``
            indexes ``views``) and the views tested.
        """
        index = self.visibility_index()
        render = renders or self.context.render
        views = views if views is not None else list(self.scene.train_views)
        ins, vdepth, rdepth, ralpha = [], [], [], []
        for v in views:
            out = render(v)
            dev = out.depth.device
            d, _ = index.voxel_depth(v)
            ins.append(index.instances(v).to(dev))
            vdepth.append(d.to(dev))
            rdepth.append(out.depth)
            ralpha.append(out.alpha)
        rows = find_incomplete(
            torch.stack(ins),
            torch.stack(vdepth),
            torch.stack(rdepth),
            torch.stack(ralpha),
            self.config.incomplete,
        )
        return rows, views

    def densify(
        self,
        params: MutableMapping[str, torch.Tensor],
        optimizers: Any,
        state: dict[str, Any],
        step: int,
    ) -> dict[str, Any]:
        """One visibility-aware densification event (detect, reconstruct, add); returns its log."""
        cfg = self.config
        scene = self.scene
        index = self.visibility_index()
        renders = _Renders(self.context.render)
        t0 = time.perf_counter()
        rows, views = self.detect(renders=renders)
        t1 = time.perf_counter()
        classes = index.classes()  # incl. derived instances (scenes without maps)
        event = len(state["vad_events"])
        has_nodes = "node_ids" in getattr(params, "params", params)
        # the flagged views of each candidate instance, with its pixel count there
        flagged: dict[int, list[tuple[int, int]]] = {}
        for k in torch.nonzero(rows.flagged).squeeze(1).tolist():
            inst, px = int(rows.instance[k]), int(rows.pixels[k])
            if classes.get(inst, "") in cfg.skip_classes:
                continue
            if inst in scene.tracks and not has_nodes:
                continue  # a static model (no node_ids) cannot hold a moving object
            if event - state["vad_last_done"].get(inst, -10) <= cfg.cooldown_events:
                continue
            flagged.setdefault(inst, []).append((views[int(rows.view[k])], px))
        best = {i: max(c, key=lambda vp: vp[1])[1] for i, c in flagged.items()}
        ranked = rank_instances(best, classes, cfg.ranking)
        added, log = 0, []
        t_mvs = 0.0
        idx_dev = index.cameras.K.device

        def prior(v: int) -> tuple[torch.Tensor, torch.Tensor]:
            out = renders(v)
            return out.depth.to(idx_dev), out.normals.to(idx_dev)

        done = 0
        # instances whose reconstruction yields nothing (e.g. no supporting views) do not use up
        # a slot; at most twice max_instances are attempted
        for inst in ranked[: 2 * cfg.max_instances]:
            if done >= cfg.max_instances:
                break
            refs = pick_references(flagged[inst], scene, cfg.references, cfg.min_frame_gap)
            entry_views, points, n_new_total, reasons = [], 0, 0, []
            for ref in refs:
                ta = time.perf_counter()
                rec = reconstruct_instance(index, ref, inst, cfg.reconstruct, self.context.generator, prior)
                t_mvs += time.perf_counter() - ta
                n_new = 0
                if rec.points.shape[0]:
                    before = renders(ref)
                    keep = self._unexplained(rec, ref, before)
                    n_new = int(keep.sum())
                    if n_new:
                        self._add(params, optimizers, state, rec, keep, event + 1)
                        renders.invalidate()  # the Gaussians changed
                        self.snapshots.append(
                            {"instance": inst, "view": ref, "step": step, "added": n_new,
                             "depth": before.depth[0], "alpha": before.alpha[0]}
                        )  # fmt: skip
                if cfg.geometric_losses:
                    for v, d, n in zip(rec.views, rec.depth, rec.normal):
                        old = state["vad_priors"].get(v)
                        if old is not None:
                            has = d > 0
                            d = torch.where(has, d, old[0])
                            n = torch.where(has, n, old[1])
                        state["vad_priors"][v] = (d, n)
                entry_views.append(rec.views)
                points += int(rec.points.shape[0])
                n_new_total += n_new
                reasons.append(rec.reason)
            added += n_new_total
            done += points > 0
            state["vad_last_done"][inst] = event
            log.append(
                {
                    "instance": inst,
                    "class": classes.get(inst, "?"),
                    "references": refs,
                    "views": entry_views,
                    "points": points,
                    "added": n_new_total,
                    "reason": "; ".join(dict.fromkeys(reasons)),
                }
            )
        t2 = time.perf_counter()
        entry = {
            "step": step,
            "cycle": state["vad_cycle"],
            "flagged": int(rows.flagged.sum()),
            "tested": int(rows.flagged.numel()),
            "flagged_instances": int(rows.instance[rows.flagged].unique().numel()),
            "candidates": len(best),
            "instances": log,
            "added": added,
            "detect_s": t1 - t0,
            "mvs_s": t_mvs,
            "total_s": t2 - t0,
        }
        state["vad_events"].append(entry)
        names = ", ".join(f"{e['class']} {e['instance']} (+{e['added']})" for e in log) or "none"
        summary = (
            f"visibility-aware densification: {entry['flagged_instances']} instances flagged, "
            f"reconstructed {names} in {entry['total_s']:.0f} s"
        )
        state.setdefault("pending_log", []).append(
            {"kind": "visibility_densification", "summary": summary, **entry}
        )
        return entry

    @torch.no_grad()
    def _unexplained(self, rec: InstanceReconstruction, ref: int, out: ViewRender) -> torch.Tensor:
        """Points that no opaque rendered surface covers (in front or within tolerance) in ``ref``.

        On the device of the render.
        """
        scene = self.scene
        dev = out.depth.device
        cams = scene.cameras([ref])
        w2c = cams.world_to_cam[0]
        if rec.track is not None:
            w2c = w2c @ scene.tracks[rec.track].object_to_world[scene.view_frame_position(ref)]
        uv, z = project_points(rec.points[None].to(dev), cams.K.to(dev), w2c[None].to(dev))
        uv, z = uv[0], z[0]
        u, v = uv[:, 0].round().long(), uv[:, 1].round().long()
        h, w = cams.image_size
        inside = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        keep = torch.ones(z.shape[0], dtype=torch.bool, device=dev)
        uu, vv = u[inside], v[inside]
        alpha = out.alpha[0, vv, uu]
        depth = out.depth[0, vv, uu]
        explained = (alpha >= self.config.incomplete.alpha_threshold) & (
            depth <= z[inside] * (1 + self.config.explained_tolerance)
        )
        keep[inside] = ~explained
        return keep

    def _add(
        self,
        params: MutableMapping[str, torch.Tensor],
        optimizers: Any,
        state: dict[str, Any] | None,
        rec: InstanceReconstruction,
        keep: torch.Tensor,
        event: int = 1,
    ) -> None:
        """New flat Gaussians from the kept points, in ``params``' layout, device and dtype.

        Where ``params`` has a ``provenance`` entry the new rows get ``event`` (1-based).
        """
        cfg = self.config
        names = ops.param_names(params)
        p = getattr(params, "params", params)
        ref = p[names.means]
        dev, dt = ref.device, ref.dtype
        keep = keep.to(rec.points.device)
        pts, nrm, col, spc = (x[keep].to(dev, dt) for x in (rec.points, rec.normals, rec.colors, rec.spacing))
        m = pts.shape[0]
        width = spc.clamp(min=1e-4)
        opacity = torch.full((m,), cfg.new_opacity, device=dev, dtype=dt)
        new = {
            names.means: pts,
            names.quats: normals_to_quats(nrm),
            names.log_scales: torch.log(torch.stack([width, width, width * cfg.flatness], -1)),
            names.opacity_logits: torch.log(opacity / (1 - opacity)),
            names.sh_dc: ((col[:, :3] - 0.5) / _C0)[:, None, :],
            names.sh_rest: torch.zeros(m, *p[names.sh_rest].shape[1:], device=dev, dtype=dt),
        }
        node_ids = None
        if "node_ids" in p:
            node = -1 if rec.track is None else self._track_nodes()[rec.track]
            node_ids = torch.full((m,), node, dtype=torch.int64, device=p["node_ids"].device)
        if "provenance" in p:
            new["provenance"] = torch.full((m,), event, dtype=torch.int64, device=p["provenance"].device)
        extra = [k for k in p.keys() if k not in new and k != "node_ids"]
        if extra:
            raise ValueError(f"params: cannot initialise extra per-Gaussian entries {extra} of new Gaussians")
        ops.add_gaussians(params, optimizers, state, new, node_ids)

    def _track_nodes(self) -> Mapping[int, int]:
        if self.context.track_nodes is not None:
            return self.context.track_nodes
        return {t: k for k, t in enumerate(sorted(self.scene.tracks))}

    # -- geometric priors ------------------------------------------------------------------------------

    def geometry_targets(self, state: dict[str, Any], view: int) -> GeometryTargets | None:
        """The priors of a view for :func:`vadgs.train.losses.geometric_losses`.

        MVS depth and normals of the events so far; where no MVS depth exists, the voxel depth —
        only where the voxel belongs to the pixel's own instance (elsewhere the z-buffer sees
        through missing geometry, e.g. the facade behind a sign, and would pull it backwards).
        ``None`` when the strategy or its losses are off, or the view has no prior. Tensors
        ``(1, 1, H, W)`` / ``(1, 3, H, W)`` on the visibility index's device (the CPU for
        LiDAR-built indices): move them to the render's device.
        """
        cfg = self.config
        if not (cfg.visibility and cfg.geometric_losses):
            return None
        depth, normal = None, None
        if view in state["vad_priors"]:
            depth, normal = state["vad_priors"][view]
        if cfg.voxel_depth_prior:
            index = self.visibility_index()
            vd, vlabel = index.voxel_depth(view)
            vd = torch.where((vlabel == index.instances(view))[None], vd, torch.zeros_like(vd))
            depth = vd if depth is None else torch.where(depth > 0, depth, vd)
        if depth is None:
            return None
        return GeometryTargets(depth=depth[None], normal=None if normal is None else normal[None])
