r"""VAD-GS: the visibility-aware densification strategy (paper, Sec. "Methodology").

:class:`VisibilityAwareDensification` wraps a standard strategy (adaptive density control) and,
every ``every_cycles`` complete sampling cycles of the training views:

1. **detects** incomplete instances: for every training view it renders depth and accumulated
   opacity, rasterises the voxels (static grid in world, each moving object's grid in its own
   frame) and flags, per instance of the view's instance map, the instances whose rendered depth
   is absent or more than 1.1× the voxel depth, or with more than 25% of pixels below 0.7 opacity
   (:func:`~vadgs.train.incomplete.find_incomplete`);
2. **reconstructs** each flagged instance from its best reference view: diversity-aware k-clique
   view selection, PatchMatch initialised from the rendered depth and normals and restricted to
   the instance (a moving object in its own frame), consistency, fusion
   (:func:`~vadgs.train.reconstruct.reconstruct_instance`);
3. **densifies**: the fused points that the current Gaussians do not already explain (no opaque
   surface within ``explained_tolerance`` in front of them in the reference view) become new
   flat Gaussians oriented by the MVS normals — in the world for static instances, in the
   object's frame for moving ones;
4. keeps the MVS depth and normals of the group views as **geometric priors**: the normal loss
   (:math:`\lambda_\text{normal} = 0.02`) and the hard and soft depth losses (0.1 each, hard off
   after 80% of the iterations) against MVS depth, falling back to the voxel depth where no MVS
   depth exists (:meth:`VisibilityAwareDensification.extra_losses`).

Ablation switches (:class:`VisibilityDensifyConfig`): ``visibility=False`` disables the whole
strategy (plain ADC), ``view_selection=False`` uses consecutive frames of the reference camera,
``geometric_losses=False`` drops the priors. Every event's cost is logged in
``state["vad_events"]`` (seconds of detection, selection + MVS, and densification).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any

import torch

from vadgs.geometry.camera import Cameras, project_points
from vadgs.geometry.zbuffer import rasterize_voxels
from vadgs.train import losses as L
from vadgs.train.incomplete import IncompleteConfig, find_incomplete
from vadgs.train.model import PER_GAUSSIAN, GaussianModel, rotation_to_quat
from vadgs.train.ops import add_gaussians
from vadgs.train.reconstruct import (
    ReconstructConfig,
    VisibilityIndex,
    build_visibility_index,
    reconstruct_instance,
)
from vadgs.train.strategy import DefaultStrategy, Strategy

__all__ = [
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
        hard_every: the hard depth loss (an extra render with opacities fixed to 1) is applied on
            every ``hard_every``-th step only, to bound its CPU cost.
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
    hard_every: int = 4
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
    the normal.

    Example:
        >>> from vadgs.render import quaternion_to_rotation
        >>> n = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]])
        >>> torch.allclose(quaternion_to_rotation(normals_to_quats(n))[:, :, 2], n, atol=1e-6)
        True
    """
    n = torch.nn.functional.normalize(normals, dim=-1)
    helper = torch.where(
        n[:, 2:3].abs() < 0.9,
        torch.tensor([0.0, 0.0, 1.0], dtype=n.dtype).expand_as(n),
        torch.tensor([1.0, 0.0, 0.0], dtype=n.dtype).expand_as(n),
    )
    a = torch.nn.functional.normalize(torch.cross(helper, n, dim=-1), dim=-1)
    b = torch.cross(n, a, dim=-1)
    R = torch.stack([a, b, n], dim=-1)  # columns: the Gaussian's axes in the world
    return rotation_to_quat(R)


def voxel_depth_map(index: VisibilityIndex, view: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Voxel depth ``(1, H, W)`` of a view from the static grid and every moving object's grid.

    Returns:
        ``(depth, label)``: the nearest voxel surface and the instance label of its voxel
        (``(H, W)`` int64, 0 where empty). Moving objects are rasterised in their own frame at the
        view's timestamp.
    """
    cache = index.__dict__.setdefault("_combined", {})
    if view in cache:
        return cache[view]
    depth, vidx = index.voxel_raster(view)
    label = torch.where(vidx >= 0, index.labels[vidx.clamp(min=0)], torch.zeros_like(vidx))
    depth = depth.clone()
    scene = index.scene
    fpos = scene.frame_position(scene.views[view].frame)
    cams = index.cameras[view]
    for tid, grid in index.track_grids.items():
        track = scene.tracks[tid]
        if not bool(track.valid[fpos]):
            continue
        obj_cams = Cameras(cams.K, cams.world_to_cam @ track.object_to_world[fpos][None], cams.image_size)
        r = rasterize_voxels(grid, obj_cams, config=index.zbuffer)
        closer = (r.depth[0] > 0) & ((depth == 0) | (r.depth[0] < depth))
        depth = torch.where(closer, r.depth[0], depth)
        label = torch.where(closer[0], torch.full_like(label, tid), label)
    cache[view] = (depth, label)
    return depth, label


class VisibilityAwareDensification:
    """The VAD-GS densification strategy. See the module docstring.

    Args:
        config: :class:`VisibilityDensifyConfig`.
        base: the strategy it extends, whose clone/split/prune keeps running. ``None`` (default):
            the trainer's standard :class:`~vadgs.train.strategy.DefaultStrategy` with its
            ``TrainConfig.strategy`` (set by :class:`~vadgs.train.trainer.Trainer`; a plain
            ``DefaultStrategy()`` outside a trainer).
        index: a prebuilt :class:`~vadgs.train.reconstruct.VisibilityIndex` (built from the
            trainer's scene at the first event otherwise).
    """

    def __init__(
        self,
        config: VisibilityDensifyConfig | None = None,
        base: Strategy | None = None,
        index: VisibilityIndex | None = None,
    ) -> None:
        self.config = config or VisibilityDensifyConfig()
        self.base = base
        self.index = index
        #: per reconstructed instance, the reference render just before new Gaussians were added:
        #: ``{"instance", "view", "step", "added", "depth", "alpha"}`` (for figures; not checkpointed)
        self.snapshots: list[dict[str, Any]] = []
        if not self.config.view_selection:
            sel = replace(self.config.reconstruct.selection, method="consecutive")
            self.config = replace(self.config, reconstruct=replace(self.config.reconstruct, selection=sel))

    # -- Strategy interface ----------------------------------------------------------------------------

    def initialize_state(self, model: GaussianModel, scene_scale: float) -> dict[str, Any]:
        """Base state plus the event log, the priors and the cycle counter."""
        if self.base is None:
            self.base = DefaultStrategy()
        state = self.base.initialize_state(model, scene_scale)
        state.update(vad_events=[], vad_priors={}, vad_cycle=0, vad_last_done={})
        return state

    def step_pre_backward(self, model, optimizer, state, step, info) -> None:  # noqa: D102
        self.base.step_pre_backward(model, optimizer, state, step, info)

    def step_post_backward(self, model, optimizer, state, step, info) -> None:
        """Base densification, then a visibility-aware event after every ``every_cycles`` cycles."""
        self.base.step_post_backward(model, optimizer, state, step, info)
        trainer = info.get("trainer")
        if not self.config.visibility or trainer is None:
            return
        cycle = trainer.sampler.cycle
        if cycle != state["vad_cycle"]:
            state["vad_cycle"] = cycle
            late = step >= self.config.last_event_fraction * trainer.config.iterations
            if cycle > 0 and cycle % self.config.every_cycles == 0 and not late:
                self.densify(trainer, model, optimizer, state, step)

    # -- the event ---------------------------------------------------------------------------------------

    def _index(self, trainer) -> VisibilityIndex:
        if self.index is None:
            self.index = build_visibility_index(trainer.scene, self.config.voxel_size)
        return self.index

    @torch.no_grad()
    def detect(self, trainer, views: list[int] | None = None):
        """Run the incompleteness test on training views; returns the rows and the renders."""
        index = self._index(trainer)
        views = views if views is not None else list(trainer.train_views)
        ins, vdepth, rdepth, ralpha = [], [], [], []
        for v in views:
            out = trainer.render_view(v)
            d, _ = voxel_depth_map(index, v)
            ins.append(index.instances(v))
            vdepth.append(d)
            rdepth.append(out.raster.depth[0])
            ralpha.append(out.raster.alpha[0])
        rows = find_incomplete(
            torch.stack(ins),
            torch.stack(vdepth),
            torch.stack(rdepth),
            torch.stack(ralpha),
            self.config.incomplete,
        )
        return rows, views

    def densify(
        self, trainer, model: GaussianModel, optimizer, state: dict[str, Any], step: int
    ) -> dict[str, Any]:
        """One visibility-aware densification event (detect, reconstruct, add); returns its log."""
        cfg = self.config
        scene = trainer.scene
        t0 = time.perf_counter()
        rows, views = self.detect(trainer)
        t1 = time.perf_counter()
        classes = self._index(trainer).classes()  # incl. derived instances (scenes without maps)
        event = len(state["vad_events"])
        # the flagged views of each candidate instance, with its pixel count there
        flagged: dict[int, list[tuple[int, int]]] = {}
        for k in torch.nonzero(rows.flagged).squeeze(1).tolist():
            inst, px = int(rows.instance[k]), int(rows.pixels[k])
            if classes.get(inst, "") in cfg.skip_classes:
                continue
            if event - state["vad_last_done"].get(inst, -10) <= cfg.cooldown_events:
                continue
            flagged.setdefault(inst, []).append((views[int(rows.view[k])], px))
        best = {i: max(c, key=lambda vp: vp[1])[1] for i, c in flagged.items()}
        ranked = rank_instances(best, classes, cfg.ranking)
        added, log = 0, []
        t_mvs = 0.0
        gen = trainer.generator if hasattr(trainer, "generator") else None

        def prior(v: int) -> tuple[torch.Tensor, torch.Tensor]:
            out = trainer.render_view(v)
            return out.raster.depth[0].detach(), out.raster.normals[0].detach()

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
                rec = reconstruct_instance(self._index(trainer), ref, inst, cfg.reconstruct, gen, prior)
                t_mvs += time.perf_counter() - ta
                n_new = 0
                if rec.points.shape[0]:
                    keep, before = self._unexplained(trainer, rec, ref)
                    n_new = int(keep.sum())
                    if n_new:
                        self._add(model, optimizer, state, rec, keep)
                        raster = before.raster
                        self.snapshots.append(
                            {"instance": inst, "view": ref, "step": step, "added": n_new,
                             "depth": raster.depth[0, 0].detach(), "alpha": raster.alpha[0, 0].detach()}
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
    def _unexplained(self, trainer, rec, ref: int):
        """Points that no opaque rendered surface covers (in front or within tolerance) in ``ref``.

        Returns the mask and the reference render it was computed on.
        """
        out = trainer.render_view(ref)
        scene = trainer.scene
        cams = scene.cameras([ref])
        w2c = cams.world_to_cam[0]
        if rec.track is not None:
            fpos = scene.frame_position(scene.views[ref].frame)
            w2c = w2c @ scene.tracks[rec.track].object_to_world[fpos]
        uv, z = project_points(rec.points[None], cams.K, w2c[None])
        uv, z = uv[0], z[0]
        u, v = uv[:, 0].round().long(), uv[:, 1].round().long()
        h, w = cams.image_size
        inside = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        keep = torch.ones(z.shape[0], dtype=torch.bool)
        uu, vv = u[inside], v[inside]
        alpha = out.raster.alpha[0, 0, vv, uu]
        depth = out.raster.depth[0, 0, vv, uu]
        explained = (alpha >= self.config.incomplete.alpha_threshold) & (
            depth <= z[inside] * (1 + self.config.explained_tolerance)
        )
        keep[inside] = ~explained
        return keep, out

    def _add(self, model: GaussianModel, optimizer, state, rec, keep: torch.Tensor) -> None:
        cfg = self.config
        pts, nrm, col, spc = rec.points[keep], rec.normals[keep], rec.colors[keep], rec.spacing[keep]
        m = pts.shape[0]
        dev, dt = model.params["means"].device, model.params["means"].dtype
        width = spc.clamp(min=1e-4)
        log_scales = torch.log(torch.stack([width, width, width * cfg.flatness], -1))
        opacity = torch.full((m,), cfg.new_opacity)
        params = {
            "means": pts,
            "quats": normals_to_quats(nrm),
            "log_scales": log_scales,
            "opacity_logits": torch.log(opacity / (1 - opacity)),
            "sh_dc": ((col[:, :3] - 0.5) / _C0)[:, None, :],
            "sh_rest": torch.zeros(m, *model.params["sh_rest"].shape[1:]),
        }
        params = {k: params[k].to(dev, dt) for k in PER_GAUSSIAN}
        node = -1 if rec.track is None else model.track_ids.index(rec.track)
        add_gaussians(model, optimizer, state, params, torch.full((m,), node, dtype=torch.int64, device=dev))

    # -- geometric losses ----------------------------------------------------------------------------------

    def extra_losses(
        self, model: GaussianModel, state: dict[str, Any], step: int, info: dict[str, Any]
    ) -> dict:
        """Normal and hard/soft depth losses on the MVS priors (voxel depth where no MVS depth)."""
        cfg = self.config
        trainer = info.get("trainer")
        if not (cfg.visibility and cfg.geometric_losses) or trainer is None:
            return {}
        view, out = info["view"], info["render"]
        tc = trainer.config
        w = L.geometric_weights(
            step, tc.iterations, tc.lambda_normal, tc.lambda_hard, tc.lambda_soft, tc.hard_until
        )
        depth, normal = None, None
        if view in state["vad_priors"]:
            depth, normal = state["vad_priors"][view]
        if cfg.voxel_depth_prior:
            # only where the voxel belongs to the pixel's own instance: elsewhere the z-buffer sees
            # through missing geometry (the facade behind a sign) and would pull it backwards
            index = self._index(trainer)
            vd, vlabel = voxel_depth_map(index, view)
            vd = torch.where((vlabel == index.instances(view))[None], vd, torch.zeros_like(vd))
            depth = vd if depth is None else torch.where(depth > 0, depth, vd)
        if depth is None:
            return {}
        dev = out.raster.depth.device
        depth = depth[None].to(dev)
        mask = depth > 0
        terms = {}
        if w["soft"] > 0:
            terms["soft"] = w["soft"] * L.depth_loss_soft(out.raster.depth, depth, mask)
        if w["hard"] > 0 and step % cfg.hard_every == 0:
            hard = trainer.render_view(view, opacity_override=1.0)
            terms["hard"] = w["hard"] * L.depth_loss_hard(hard.raster.depth, depth, mask)
        if normal is not None and w["normal"] > 0:
            normal = normal[None].to(dev)
            nmask = normal.abs().sum(1, keepdim=True) > 0
            if bool(nmask.any()):
                terms["normal"] = w["normal"] * L.normal_loss(out.raster.normals, normal, nmask)
        return terms
