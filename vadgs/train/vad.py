r"""VAD-GS: the visibility-aware densification strategy (paper, Sec. "Methodology").

:class:`VisibilityAwareDensification` is a gsplat-style strategy — a dataclass of its settings
with ``check_sanity`` / ``initialize_state`` / ``step_pre_backward`` / ``step_post_backward`` on
``params``, ``optimizers``, ``state``, ``step``, ``info`` — that wraps a standard one (adaptive
density control: vadgs's or gsplat's ``DefaultStrategy``, gsplat's ``MCMCStrategy``) and never sees
the training loop nor a vadgs ``Scene``: :meth:`~VisibilityAwareDensification.prepare` gives it the
data as a :class:`~vadgs.train.inputs.VisibilityInputs` (``from_scene`` / ``from_gsplat_parser``)
and, in a frozen :class:`StrategyContext`, the three things of the loop it needs — a function
that renders a view's depth, opacity and normals with the current Gaussians, the total number of
steps and the number of steps of a sampling cycle — plus the generator of its selection noise.
Every ``every_cycles`` complete sampling cycles of the training views it runs one event, a one-way
flow:

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

import inspect
import math
import time
from collections.abc import Callable, Collection, Mapping, MutableMapping
from dataclasses import dataclass, field, fields, replace
from typing import Any

import torch

from vadgs.train import ops
from vadgs.train.incomplete import IncompleteConfig, IncompleteInstances, find_incomplete
from vadgs.train.inputs import TrackTable, VisibilityInputs
from vadgs.train.losses import GeometryTargets
from vadgs.train.model import rotation_to_quat
from vadgs.train.reconstruct import (
    InstanceReconstruction,
    ReconstructConfig,
    ViewRender,
    VisibilityIndex,
    build_visibility_index,
    reconstruct_instance,
)
from vadgs.train.strategy import DefaultStrategy

__all__ = [
    "StrategyContext",
    "TrackTable",
    "ViewRender",
    "VisibilityAwareDensification",
    "VisibilityDensifyConfig",
    "VisibilityInputs",
    "normals_to_quats",
    "pick_references",
    "rank_instances",
    "voxel_depth_map",
]

_C0 = 0.28209479177387814
_MAX_PENDING = 64  # events kept in state["pending_log"] when the loop does not pop them


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
        max_instances: at most this many instances reconstructed per event, in the order of
            ``ranking`` (``None``, the default: every flagged instance, within ``time_budget``).
        time_budget: an event stops starting new instances once it has taken this fraction of
            the training time so far (the time between the strategy's calls, events excluded);
            the instances left are logged as skipped (``"time_budget"``). The first instance is
            always tried. ``None``: no limit (an exactly reproducible run).
        render_cache_mb: the loop's renders of the views trained since the last event (depth,
            opacity, normals; float16, in the strategy's state, so checkpoints hold them and a
            resumed run stays exact) are kept up to this size and reused by the event for
            detection, PatchMatch initialisation and the test of what is already explained; the
            views beyond it are rendered at the event. ``0``: render every view at the event.
        references: reference views per instance: its flagged view with the most pixels, then
            the next largest ones from another camera or at least ``min_frame_gap`` frames away
            from those already chosen (another side of the object, e.g. the back of a sign).
            3 by default (2 before the event got cheap: on street_a a third reference took PSNR
            29.15 → 29.35 dB for 118k → 125k Gaussians, docs/results.md).
        min_frame_gap: see ``references``.
        ranking: ``"class_round_robin"`` (default): one instance per class in turn, the largest
            (most pixels in its best flagged view) first within a class, so that small structures
            such as signs are not starved by large facades; ``"pixels"``: largest first overall.
        cooldown_events: an instance reconstructed at an event is skipped for this many events
            (default 0: an instance still flagged at the next event is tried again; what the
            Gaussians already explain gives no new points, so a repeat adds only what is missing).
        whole_reference: at least one reference in which the instance is whole when it was
            flagged in such a view (``whole`` of :func:`pick_references`); with
            ``reconstruct.whole_supports`` its supporting views show all of it too.
        skip_classes: instance classes never densified (e.g. the road, which LiDAR covers).
        explained_tolerance: an MVS pixel is "explained" (gives no new Gaussian) where its view's
            render has opacity above ``incomplete.alpha_threshold`` and a depth within this
            relative tolerance of (or in front of) the MVS depth.
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
    max_instances: int | None = None
    time_budget: float | None = 0.1
    render_cache_mb: float = 256.0
    references: int = 3
    min_frame_gap: int = 3
    ranking: str = "class_round_robin"
    cooldown_events: int = 0
    whole_reference: bool = True
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
        if self.references < 1 or (self.max_instances is not None and self.max_instances < 0):
            raise ValueError(
                f"references, max_instances: expected >= 1 and None or >= 0, got {self.references}, "
                f"{self.max_instances}"
            )
        if self.time_budget is not None and not self.time_budget > 0:
            raise ValueError(f"time_budget: expected None or > 0, got {self.time_budget}")


RANKINGS = ("class_round_robin", "pixels")


def pick_references(
    candidates: list[tuple[int, int]],
    scene: VisibilityInputs | Any,
    count: int,
    min_frame_gap: int = 3,
    whole: Collection[int] | None = None,
) -> list[int]:
    """Reference views of one instance: the largest first, then diverse ones.

    Args:
        candidates: ``(view, pixels)`` of the views where the instance was flagged.
        scene: :class:`~vadgs.train.inputs.VisibilityInputs` or a vadgs :class:`~vadgs.data.Scene`
            (for each view's camera and frame).
        count: how many references at most.
        min_frame_gap: a further reference must come from a camera not chosen yet, or be at
            least this many frames from every chosen view of its camera.
        whole: the candidates in which the instance is whole (not cut by the image border). When
            given and no chosen view is one of them, the last reference is replaced by the
            largest of them that keeps the rule above (the close views with the most pixels may
            all cut off the same part, e.g. the top of a sign).

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
    if isinstance(scene, VisibilityInputs):
        cam, frame = scene.view_cameras, scene.view_frames
    else:
        cam, frame = [v.camera for v in scene.views], [v.frame for v in scene.views]

    def apart(view: int, chosen: list[int]) -> bool:
        return all(cam[c] != cam[view] or abs(frame[c] - frame[view]) >= min_frame_gap for c in chosen)

    order = [v for v, _px in sorted(candidates, key=lambda vp: (-vp[1], vp[0]))]
    chosen: list[int] = []
    for view in order:
        if len(chosen) >= count:
            break
        if apart(view, chosen):
            chosen.append(view)
    if whole is not None and count >= 2 and chosen and not set(chosen) & set(whole):
        keep = chosen[: count - 1]
        extra = next((v for v in order if v in whole and v not in keep and apart(v, keep)), None)
        if extra is not None:
            chosen = [*keep, extra]
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


@dataclass(frozen=True)
class StrategyContext:
    """What :class:`VisibilityAwareDensification` needs of the training loop, given explicitly.

    Attributes:
        render: ``view -> ViewRender``: renders a view (index into the inputs' views, e.g.
            ``scene.views`` or the Parser's images) with the current Gaussians, at the view's frame,
            without gradient; normals may be zeros (unknown).
        total_steps: the run's number of steps (events stop after ``last_event_fraction`` of it).
        steps_per_cycle: steps of one sampling cycle (vadgs's trainer: one view per step, so the
            number of training views); cycle ``c`` ends after step ``c * steps_per_cycle - 1``.
        generator: seeds the view-selection noise ``ξ`` and point subsampling (checkpoint it for
            exact resume; vadgs's trainer passes its own).
        track_nodes: track id → node index of ``params["node_ids"]`` (default: the inputs' tracks
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
    """Renders of one event: the loop's own renders kept in the state, else rendered once."""

    def __init__(self, render: Callable[[int], ViewRender], kept: Mapping[int, tuple] | None = None) -> None:
        self.render, self.kept, self.cache = render, kept or {}, {}
        self.rendered = 0

    def __call__(self, view: int) -> ViewRender:
        if view not in self.cache:
            if view in self.kept:
                self.cache[view] = ViewRender(*(x.float() for x in self.kept[view]))
            else:
                self.cache[view] = self.render(view)
                self.rendered += 1
        return self.cache[view]


def _chw(x: torch.Tensor) -> torch.Tensor:
    """A single view's map as ``(C, H, W)``, detached (from ``(1, C, H, W)`` or ``(H, W)``)."""
    x = x.detach()
    return x[0] if x.dim() == 4 else x[None] if x.dim() == 2 else x


def _keep_render(store: dict, view: int, render: ViewRender, max_bytes: int) -> None:
    """Keep a view's render (float16) in ``store``, the oldest dropped beyond ``max_bytes``."""
    store.pop(view, None)
    if max_bytes <= 0:
        return
    store[view] = tuple(x.half() for x in render)
    total = sum(sum(x.numel() * x.element_size() for x in r) for r in store.values())
    while total > max_bytes and len(store) > 1:
        oldest = next(iter(store))
        total -= sum(x.numel() * x.element_size() for x in store.pop(oldest))


def _view_test(
    index: VisibilityIndex, view: int, depth: torch.Tensor, alpha: torch.Tensor, config: IncompleteConfig
) -> tuple[torch.Tensor, ...]:
    """The incompleteness test of one view, on the render's device.

    The view's instance map and voxel depth move to the render (the render does not move).
    Returns the fields of its :class:`~vadgs.train.incomplete.IncompleteInstances` (``view`` = 0).
    """
    dev = depth.device
    h, w = depth.shape[-2:]  # the view's own size (the index's maps may be padded)
    d, _ = index.voxel_depth(view)
    rows = find_incomplete(
        index.instances(view)[None, :h, :w].to(dev),
        d[None, :, :h, :w].to(dev),
        depth.detach().reshape(1, 1, *depth.shape[-2:]),
        alpha.detach().reshape(1, 1, *alpha.shape[-2:]),
        config,
    )
    return tuple(rows)


def _with_settings_of(config_cls: type) -> Callable[[type], type]:
    """Give a class the fields of the dataclass ``config_cls`` (same names, types, defaults) first.

    The strategy's settings are :class:`VisibilityDensifyConfig`'s, written once there: a mutable
    dataclass cannot inherit them from a frozen one, so they are copied in before ``@dataclass``.
    """

    def add(cls: type) -> type:
        own = dict(inspect.get_annotations(cls))
        cls.__annotations__ = {f.name: f.type for f in fields(config_cls)} | own
        for f in fields(config_cls):
            setattr(cls, f.name, field(default=f.default, default_factory=f.default_factory))
        return cls

    return add


@dataclass(eq=False)
@_with_settings_of(VisibilityDensifyConfig)
class VisibilityAwareDensification:
    """The VAD-GS densification strategy (gsplat ``Strategy`` interface). See the module docstring.

    A dataclass whose fields are its settings, as gsplat's ``DefaultStrategy`` /
    ``MCMCStrategy``: the fields, defaults and checks of :class:`VisibilityDensifyConfig` (copied
    from it, written once), then ``base``, ``on_addition`` and ``log_size``; :meth:`from_config`
    builds one from a :class:`VisibilityDensifyConfig` (vadgs's trainer and ``vadgs train
    --vad.KEY VALUE``). It holds no
    dataset: :meth:`prepare` gives it a :class:`~vadgs.train.inputs.VisibilityInputs` (per-view
    cameras, loaders, LiDAR or TRACK observations, tracks) and the loop's
    :class:`StrategyContext`, and builds the visibility index once. Use::

        strategy = VisibilityAwareDensification(base=DefaultStrategy(), every_cycles=5)
        strategy.check_sanity(params, optimizers)
        strategy.prepare(VisibilityInputs.from_gsplat_parser(parser), context)
        state = strategy.initialize_state(scene_scale)
        # each step: step_pre_backward(...); loss.backward(); step_post_backward(..., packed=...)

    Attributes:
        base: the strategy it extends, whose clone/split/prune keeps running (default
            :class:`~vadgs.train.strategy.DefaultStrategy`; gsplat's ``DefaultStrategy`` (packed or
            not) and ``MCMCStrategy`` work too: extra keyword arguments of ``step_pre_backward`` /
            ``step_post_backward`` (``packed=``, ``lr=``) are passed to it, and its
            ``initialize_state`` gets ``scene_scale`` only when it takes one).
        on_addition: optional callback, called with ``{"instance", "view", "step", "added",
            "depth", "alpha"}`` (the reference's render just before) each time an instance gets new
            Gaussians (for figures; nothing is kept by the strategy).
        log_size: at most this many events are kept in ``state["pending_log"]`` for the loop to
            pop (the oldest dropped first); ``state["vad_events"]`` keeps one summary per event.
        the others: see :class:`VisibilityDensifyConfig`.

    The incompleteness test of a view reuses the loop's own render when ``info`` carries it
    (``info["view"]`` and ``info["raster"]`` with ``depth`` / ``alpha``, as vadgs's trainer passes,
    or ``info["depth"]`` / ``info["alpha"]``): a view trained since the last event is not rendered
    again for detection. The others are rendered at the event (kept for that event only).

    Example:
        >>> import dataclasses, inspect
        >>> dataclasses.is_dataclass(VisibilityAwareDensification)
        True
        >>> list(inspect.signature(VisibilityAwareDensification).parameters)[:3]
        ['visibility', 'view_selection', 'geometric_losses']
    """

    base: Any = field(default_factory=DefaultStrategy)
    on_addition: Callable[[dict[str, Any]], None] | None = field(default=None, repr=False)
    log_size: int = _MAX_PENDING
    inputs: VisibilityInputs | None = field(default=None, init=False, repr=False)
    context: StrategyContext | None = field(default=None, init=False, repr=False)
    index: VisibilityIndex | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        self.config  # noqa: B018  (the settings' checks: VisibilityDensifyConfig.__post_init__)
        if self.log_size < 1:
            raise ValueError(f"log_size: expected >= 1, got {self.log_size}")
        self._last_call: float | None = None

    @classmethod
    def from_config(
        cls,
        config: VisibilityDensifyConfig | None = None,
        base: Any = None,
        inputs: VisibilityInputs | None = None,
        context: StrategyContext | None = None,
        index: VisibilityIndex | None = None,
        on_addition: Callable[[dict[str, Any]], None] | None = None,
    ) -> VisibilityAwareDensification:
        """A strategy with the settings of ``config``; :meth:`prepare` d when ``inputs`` or ``index``.

        Example:
            >>> s = VisibilityAwareDensification.from_config(VisibilityDensifyConfig(every_cycles=2))
            >>> s.every_cycles, s.config == VisibilityDensifyConfig(every_cycles=2)
            (2, True)
        """
        config = config or VisibilityDensifyConfig()
        kw = {f.name: getattr(config, f.name) for f in fields(config)}
        out = cls(**kw, base=base if base is not None else DefaultStrategy(), on_addition=on_addition)
        if inputs is not None or index is not None or context is not None:
            out.prepare(inputs, context, index)
        return out

    @classmethod
    def from_scene(
        cls,
        scene: Any,
        context: StrategyContext,
        config: VisibilityDensifyConfig | None = None,
        base: Any = None,
        index: VisibilityIndex | None = None,
        on_addition: Callable[[dict[str, Any]], None] | None = None,
    ) -> VisibilityAwareDensification:
        """Deprecated: the former constructor ``(scene, context, config, base, index)``.

        Use ``from_config(config, base=base, inputs=VisibilityInputs.from_scene(scene),
        context=context)``.
        """
        import warnings

        warnings.warn(
            "VisibilityAwareDensification.from_scene(scene, context, ...) is deprecated: use "
            "from_config(config, base=..., inputs=VisibilityInputs.from_scene(scene), context=...)",
            DeprecationWarning,
            stacklevel=2,
        )
        inputs = VisibilityInputs.from_scene(scene) if index is None else None
        return cls.from_config(config, base, inputs, context, index, on_addition)

    @property
    def config(self) -> VisibilityDensifyConfig:
        """The settings as a :class:`VisibilityDensifyConfig` (assignable: sets every field)."""
        return VisibilityDensifyConfig(
            **{f.name: getattr(self, f.name) for f in fields(VisibilityDensifyConfig)}
        )

    @config.setter
    def config(self, value: VisibilityDensifyConfig) -> None:
        for f in fields(VisibilityDensifyConfig):
            setattr(self, f.name, getattr(value, f.name))

    def _reconstruct_config(self) -> ReconstructConfig:
        """``reconstruct``, with consecutive-frame selection when ``view_selection`` is off."""
        if self.view_selection:
            return self.reconstruct
        sel = replace(self.reconstruct.selection, method="consecutive")
        return replace(self.reconstruct, selection=sel)

    # -- Strategy interface ----------------------------------------------------------------------------

    def check_sanity(self, params: Mapping[str, torch.Tensor], optimizers: Any) -> None:
        """Check ``params`` and ``optimizers`` before training (gsplat's ``check_sanity``).

        Every per-Gaussian entry must have the Gaussians as first dimension; the geometry must be
        vadgs's or gsplat's names (:func:`~vadgs.train.ops.param_names`); each trainable entry
        must have its optimizer (gsplat's dict ``{name: optimizer}`` with one param group holding
        that tensor, or one optimizer with a param group named for it). Then the base's own
        ``check_sanity`` when it has one.

        Raises:
            ValueError: naming the key, what was expected and what was found.
        """
        p = getattr(params, "params", params)
        names = ops.param_names(p)
        n = int(p[names.means].shape[0])
        for k, v in p.items():
            if not isinstance(v, torch.Tensor) or v.dim() == 0 or v.shape[0] != n:
                got = tuple(v.shape) if isinstance(v, torch.Tensor) else type(v).__name__
                raise ValueError(f"params[{k!r}]: expected a tensor of {n} rows (the Gaussians), got {got}")
        for k, v in p.items():
            if not v.requires_grad:
                continue
            if optimizers is None:
                raise ValueError(f"optimizers: expected an optimizer of params[{k!r}], got None")
            if isinstance(optimizers, Mapping):
                opt = optimizers.get(k)
                if opt is None:
                    raise ValueError(f"optimizers: expected a key {k!r}, got keys {sorted(optimizers)}")
                groups = opt.param_groups
                if len(groups) != 1 or len(groups[0]["params"]) != 1 or groups[0]["params"][0] is not v:
                    raise ValueError(
                        f"optimizers[{k!r}]: expected one param group holding params[{k!r}], got "
                        f"{len(groups)} group(s) of {[len(g['params']) for g in groups]} tensor(s)"
                    )
            else:
                group = next((g for g in optimizers.param_groups if g.get("name") == k), None)
                if group is None or not any(q is v for q in group["params"]):
                    named = [g.get("name") for g in optimizers.param_groups]
                    raise ValueError(
                        f"optimizers: expected a param group named {k!r} holding params[{k!r}], "
                        f"got groups {named}"
                    )
        if hasattr(self.base, "check_sanity"):
            self.base.check_sanity(params, optimizers)

    def initialize_state(self, scene_scale: float = 1.0) -> dict[str, Any]:
        """The base strategy's state plus the event log, the priors, the cycle counter and view tests.

        The base gets ``scene_scale`` when its ``initialize_state`` takes an argument (gsplat's
        ``MCMCStrategy`` takes none).
        """
        init = self.base.initialize_state
        try:
            takes = len(inspect.signature(init).parameters) > 0
        except (TypeError, ValueError):
            takes = True
        state = init(scene_scale) if takes else init()
        state.update(
            vad_events=[], vad_priors={}, vad_cycle=0, vad_last_done={}, vad_tests={}, vad_train_s=0.0
        )
        return state

    def step_pre_backward(self, params, optimizers, state, step, info, **kwargs) -> None:  # noqa: D102
        self.base.step_pre_backward(params, optimizers, state, step, info, **kwargs)

    def step_post_backward(
        self,
        params: MutableMapping[str, torch.Tensor],
        optimizers: Any,
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
        **kwargs: Any,
    ) -> None:
        """Base densification, then a visibility-aware event after every ``every_cycles`` cycles.

        Also tests the trained view for incompleteness when ``info`` carries its render.
        ``kwargs`` (e.g. ``packed=True`` for gsplat's ``DefaultStrategy``, ``lr=`` for its
        ``MCMCStrategy``) go to the base.
        """
        now = time.perf_counter()
        if self._last_call is not None:
            state["vad_train_s"] = state.get("vad_train_s", 0.0) + (now - self._last_call)
        self._last_call = now
        self.base.step_post_backward(params, optimizers, state, step, info, **kwargs)
        if not self.visibility:
            return
        context = self._context()
        self._observe(state, info)
        cycle = (step + 1) // context.steps_per_cycle
        if cycle != state["vad_cycle"]:
            state["vad_cycle"] = cycle
            late = step >= self.last_event_fraction * context.total_steps
            if cycle > 0 and cycle % self.every_cycles == 0 and not late:
                self.densify(params, optimizers, state, step)
                self._last_call = time.perf_counter()  # the event's time is not training time

    def _observe(self, state: dict[str, Any], info: Mapping[str, Any]) -> None:
        """Test the view the loop just trained, from its own render (see the class docstring)."""
        view = info.get("view") if isinstance(info, Mapping) else None
        if view is None or int(view) not in self._train_set():
            return
        raster = info.get("raster")
        src = raster if raster is not None else info
        get = (lambda k: getattr(src, k, None)) if raster is not None else src.get
        depth, alpha, normals = get("depth"), get("alpha"), get("normals")
        if depth is None or alpha is None:
            return
        view = int(view)
        depth, alpha = _chw(depth), _chw(alpha)
        state.setdefault("vad_tests", {})[view] = _view_test(
            self.prepare(), view, depth, alpha, self.incomplete
        )
        normals = torch.zeros(3, *depth.shape[-2:]).to(depth) if normals is None else _chw(normals)
        _keep_render(
            state.setdefault("vad_renders", {}),
            view,
            ViewRender(depth, alpha, normals),
            int(self.render_cache_mb * 2**20),
        )

    def _train_set(self) -> set[int]:
        if getattr(self, "_train_views", None) is None:
            self._train_views = set(self._inputs().train_views)
        return self._train_views

    def _context(self) -> StrategyContext:
        if self.context is None:
            raise RuntimeError("VisibilityAwareDensification: call prepare(inputs, context) before training")
        return self.context

    def _inputs(self) -> VisibilityInputs:
        if self.inputs is None:
            if self.index is not None:
                return self.index.inputs
            raise RuntimeError("VisibilityAwareDensification: call prepare(inputs, context) before training")
        return self.inputs

    # -- the event ---------------------------------------------------------------------------------------

    def prepare(
        self,
        inputs: VisibilityInputs | None = None,
        context: StrategyContext | None = None,
        index: VisibilityIndex | None = None,
    ) -> VisibilityIndex | None:
        """Give the strategy its data and the loop's context, and build the visibility index once.

        Call it before the first step (vadgs's trainer does, at construction). Later calls without
        arguments return the index; the index is built only when ``visibility`` is on.

        Args:
            inputs: :class:`~vadgs.train.inputs.VisibilityInputs` (e.g.
                ``VisibilityInputs.from_scene(scene)`` or ``.from_gsplat_parser(parser)``).
            context: :class:`StrategyContext`: the loop's render function, step counts, generator.
            index: a prebuilt :class:`~vadgs.train.reconstruct.VisibilityIndex` of these inputs
                (its own inputs are used when ``inputs`` is None).

        Returns:
            The index (None when ``visibility`` is off and none was given).

        Raises:
            ValueError: on arguments of the wrong type.
            RuntimeError: when an index is needed and no inputs were ever given.
        """
        if inputs is not None and not isinstance(inputs, VisibilityInputs):
            raise ValueError(f"inputs: expected VisibilityInputs, got {type(inputs).__name__}")
        if context is not None and not isinstance(context, StrategyContext):
            raise ValueError(f"context: expected a StrategyContext, got {type(context).__name__}")
        if index is not None:
            self.index = index
            self.inputs = inputs if inputs is not None else index.inputs
            self._train_views = None
        elif inputs is not None and inputs is not self.inputs:
            self.inputs, self.index, self._train_views = inputs, None, None
        if context is not None:
            self.context = context
        if self.index is None and self.visibility:
            self.index = build_visibility_index(self._inputs(), self.voxel_size)
        return self.index

    def visibility_index(self) -> VisibilityIndex:
        """The :class:`~vadgs.train.reconstruct.VisibilityIndex` (see :meth:`prepare`)."""
        if self.index is None:
            self.index = build_visibility_index(self._inputs(), self.voxel_size)
        return self.index

    @torch.no_grad()
    def detect(
        self,
        views: list[int] | None = None,
        renders: Callable[[int], ViewRender] | None = None,
        tests: Mapping[int, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] | None = None,
    ) -> tuple[IncompleteInstances, list[int]]:
        """Run the incompleteness test on training views (default all of them).

        Args:
            views: view indices.
            renders: the render function (default the context's).
            tests: per view, a test already made from the loop's render (``state["vad_tests"]``:
                the fields of its one-view :class:`~vadgs.train.incomplete.IncompleteInstances`);
                those views are not rendered again.

        Returns:
            ``(rows, views)``: :class:`~vadgs.train.incomplete.IncompleteInstances` (``rows.view``
            indexes ``views``) and the views tested.
        """
        index = self.prepare()
        render = renders or self._context().render
        views = views if views is not None else list(self._inputs().train_views)
        tests = tests or {}
        parts = []
        for k, v in enumerate(views):
            if v in tests:
                fields = tests[v]
            else:
                out = render(v)
                fields = _view_test(index, v, out.depth, out.alpha, self.incomplete)
            one = IncompleteInstances(*fields)
            parts.append(one._replace(view=torch.full_like(one.view, k)))
        dev = parts[0].view.device
        rows = IncompleteInstances(
            *(torch.cat([getattr(p, f).to(dev) for p in parts]) for f in IncompleteInstances._fields)
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
        inputs = self._inputs()
        context = self._context()
        index = self.prepare()
        renders = _Renders(context.render, state.get("vad_renders"))
        t0 = time.perf_counter()
        tests = state.get("vad_tests") or {}
        rows, views = self.detect(renders=renders, tests=tests)
        t1 = time.perf_counter()
        classes = index.classes()  # incl. derived instances (scenes without maps)
        event = len(state["vad_events"])
        has_nodes = "node_ids" in getattr(params, "params", params)
        # the flagged views of each candidate instance, with its pixel count there
        flagged: dict[int, list[tuple[int, int]]] = {}
        skipped: dict[str, int] = {}
        for k in torch.nonzero(rows.flagged).squeeze(1).tolist():
            inst, px = int(rows.instance[k]), int(rows.pixels[k])
            why = None
            if classes.get(inst, "") in cfg.skip_classes:
                why = "skip_class"
            elif inst in inputs.tracks and not has_nodes:
                why = "static_model"  # a static model (no node_ids) cannot hold a moving object
            elif event - state["vad_last_done"].get(inst, -10) <= cfg.cooldown_events:
                why = "cooldown"
            if why is None:
                flagged.setdefault(inst, []).append((views[int(rows.view[k])], px))
        flagged_ids = set(rows.instance[rows.flagged].tolist())
        for inst in flagged_ids - set(flagged):
            why = (
                "skip_class"
                if classes.get(inst, "") in cfg.skip_classes
                else "static_model"
                if inst in inputs.tracks and not has_nodes
                else "cooldown"
            )
            skipped[why] = skipped.get(why, 0) + 1
        best = {i: max(c, key=lambda vp: vp[1])[1] for i, c in flagged.items()}
        ranked = rank_instances(best, classes, cfg.ranking)
        added, log = 0, []
        t_mvs = 0.0
        budget = math.inf
        if cfg.time_budget is not None:
            budget = cfg.time_budget * float(state.get("vad_train_s", 0.0))
        occupied: dict[int | None, list[torch.Tensor]] = {}  # frame (None: world, else track) → points
        done = repaired = 0
        for inst in ranked:
            if cfg.max_instances is not None and done >= cfg.max_instances:
                skipped["max_instances"] = skipped.get("max_instances", 0) + 1
                continue
            if log and time.perf_counter() - t0 > budget:
                skipped["time_budget"] = skipped.get("time_budget", 0) + 1
                continue
            whole = (
                [v for v, _px in flagged[inst] if not index.cut_by_border(v, inst)]
                if cfg.whole_reference
                else None
            )
            refs = pick_references(flagged[inst], inputs, cfg.references, cfg.min_frame_gap, whole)
            entry_views, points, n_new_total, reasons = [], 0, 0, []
            frame_key = inst if inst in inputs.tracks else None
            for ref in refs:
                ta = time.perf_counter()
                taken = occupied.get(frame_key)
                rec = reconstruct_instance(
                    index, ref, inst, self._reconstruct_config(), context.generator, renders,
                    occupied=torch.cat(taken) if taken else None,
                )  # fmt: skip
                t_mvs += time.perf_counter() - ta
                n_new = int(rec.points.shape[0])
                if n_new:
                    self._add(params, optimizers, state, rec, event=event + 1)
                    occupied.setdefault(frame_key, []).append(rec.points)
                    if self.on_addition is not None:
                        before = renders(ref)
                        self.on_addition(
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
                points += n_new
                n_new_total += n_new
                reasons.append(rec.reason)
            added += n_new_total
            done += points > 0
            repaired += n_new_total > 0
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
        state["vad_tests"] = {}  # the next event tests (and renders) the views trained after this one
        state["vad_renders"] = {}
        entry = {
            "step": step,
            "cycle": state["vad_cycle"],
            "flagged": int(rows.flagged.sum()),
            "tested": int(rows.flagged.numel()),
            "flagged_instances": len(flagged_ids),
            "candidates": len(best),
            "attempted": len(log),
            "repaired": repaired,
            "skipped": skipped,
            "instances": log,
            "added": added,
            "views_rendered": renders.rendered,
            "tests_reused": sum(v in tests for v in views),
            "budget_s": None if math.isinf(budget) else budget,
            "detect_s": t1 - t0,
            "mvs_s": t_mvs,
            "total_s": t2 - t0,
        }
        state["vad_events"].append(entry)
        names = (
            ", ".join(f"{e['class']} {e['instance']} (+{e['added']})" for e in log if e["added"]) or "none"
        )
        cut = ", ".join(f"{n} {why}" for why, n in skipped.items()) or "none"
        summary = (
            f"visibility-aware densification: {entry['flagged_instances']} instances flagged, "
            f"{len(log)} attempted, {repaired} repaired (+{added} Gaussians), skipped: {cut}; "
            f"{entry['total_s']:.1f} s; added to {names}"
        )
        if "time_budget" in skipped:
            summary += f" (time budget {budget:.1f} s = {cfg.time_budget:g} x training time so far)"
        log_list = state.setdefault("pending_log", [])
        log_list.append({"kind": "visibility_densification", "summary": summary, **entry})
        del log_list[: -self.log_size]  # bounded when the loop does not pop it
        return entry

    def _add(
        self,
        params: MutableMapping[str, torch.Tensor],
        optimizers: Any,
        state: dict[str, Any] | None,
        rec: InstanceReconstruction,
        keep: torch.Tensor | None = None,
        event: int = 1,
    ) -> None:
        """New flat Gaussians from the (kept) points, in ``params``' layout, device and dtype.

        Where ``params`` has a ``provenance`` entry the new rows get ``event`` (1-based). Entries
        of other layouts: gsplat's appearance ``colors`` ``(N, 3)`` get the logit of the MVS colour
        (as gsplat's ``simple_trainer`` initialises them); every other unknown per-Gaussian entry
        (e.g. gsplat's ``features``) gets zeros of its trailing shape and dtype.
        """
        cfg = self.config
        names = ops.param_names(params)
        p = getattr(params, "params", params)
        ref = p[names.means]
        dev, dt = ref.device, ref.dtype
        if keep is None:
            keep = torch.ones(rec.points.shape[0], dtype=torch.bool, device=rec.points.device)
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
        }
        if names.sh_dc is not None:
            new[names.sh_dc] = ((col[:, :3] - 0.5) / _C0)[:, None, :]
            new[names.sh_rest] = torch.zeros(m, *p[names.sh_rest].shape[1:], device=dev, dtype=dt)
        node_ids = None
        if "node_ids" in p:
            node = -1 if rec.track is None else self._track_nodes()[rec.track]
            node_ids = torch.full((m,), node, dtype=torch.int64, device=p["node_ids"].device)
        if "provenance" in p:
            new["provenance"] = torch.full((m,), event, dtype=torch.int64, device=p["provenance"].device)
        for k in p.keys():
            if k in new or k == "node_ids":
                continue
            t = p[k]
            if k == "colors" and t.shape[1:] == (3,) and t.is_floating_point():
                new[k] = torch.logit(col[:, :3].clamp(1e-4, 1 - 1e-4)).to(t)
            else:
                new[k] = torch.zeros(m, *t.shape[1:], device=t.device, dtype=t.dtype)
        ops.add_gaussians(params, optimizers, state, new, node_ids)

    def _track_nodes(self) -> Mapping[int, int]:
        if self.context is not None and self.context.track_nodes is not None:
            return self.context.track_nodes
        return {t: k for k, t in enumerate(sorted(self._inputs().tracks))}

    # -- geometric priors ------------------------------------------------------------------------------

    def geometry_targets(self, state: dict[str, Any], view: int) -> GeometryTargets | None:
        """The priors of a view for :func:`vadgs.train.losses.geometric_losses`.

        MVS depth and normals of the events so far; where no MVS depth exists, the voxel depth —
        only where the voxel belongs to the pixel's own instance (elsewhere the z-buffer sees
        through missing geometry, e.g. the facade behind a sign, and would pull it backwards).
        ``None`` when the strategy or its losses are off, or the view has no prior. Tensors
        ``(1, 1, H, W)`` / ``(1, 3, H, W)`` on the device of the MVS priors (the render's), or of
        the visibility index for a view without them: move them to the render's device.
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
            depth = vd if depth is None else torch.where(depth > 0, depth, vd.to(depth.device))
        if depth is None:
            return None
        h, w = self.prepare().size(view)  # the view's own size (the index's maps may be padded)
        depth = depth[..., :h, :w]
        normal = None if normal is None else normal[..., :h, :w]
        return GeometryTargets(depth=depth[None], normal=normal if normal is None else normal[None])
