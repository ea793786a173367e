r"""VAD-GS: the visibility-aware densification strategy (paper, Sec. "Methodology").

:class:`VisibilityAwareDensification` is a gsplat-style strategy — a dataclass of its settings
with ``check_sanity`` / ``initialize_state`` / ``step_pre_backward`` / ``step_post_backward`` on
``params``, ``optimizers``, ``state``, ``step``, ``info`` — that wraps a standard one (adaptive
density control: vadgs's or gsplat's ``DefaultStrategy``, gsplat's ``MCMCStrategy``) and never sees
the training loop nor a vadgs ``Scene``: :meth:`~VisibilityAwareDensification.prepare` gives it the
data as a :class:`~vadgs.train.vad.inputs.VisibilityInputs` (``from_scene`` / ``from_gsplat_parser``)
and, in a frozen :class:`StrategyContext`, the three things of the loop it needs — a function
that renders a view's depth, opacity and normals with the current Gaussians, the total number of
steps and the number of steps of a sampling cycle — plus the generator of its selection noise.
Every ``every_cycles`` complete sampling cycles of the training views it runs one event, a one-way
flow:

1. **visibility index** (built once): voxel grids of the initial points with per-voxel view
   visibility (:func:`~vadgs.train.vad.reconstruct.build_visibility_index`: LiDAR, or COLMAP tracks);
2. **incompleteness test**: for every training view, the rendered depth and opacity against the
   voxel depth of the z-buffer (static grid in world, each moving object's grid in its own frame);
   per instance, flag when the rendered depth is absent or more than 1.1× the voxel depth, or when
   more than 25 % of its pixels are below 0.7 opacity
   (:func:`~vadgs.train.vad.incomplete.find_incomplete`);
3. **selection and MVS**: each flagged instance (:func:`~vadgs.train.vad.references.rank_instances`,
   :func:`~vadgs.train.vad.references.pick_references`) is
   reconstructed from its reference views: diversity-aware k-clique view selection, PatchMatch
   initialised from the rendered depth and normals and restricted to the instance (a moving object
   in its own frame), consistency and fusion (:func:`~vadgs.train.vad.reconstruct.reconstruct_instance`);
4. **new Gaussians**: the fused points that the current Gaussians do not already explain (no opaque
   surface within ``reconstruct.explained_tolerance`` in front of them in the view) become flat
   Gaussians oriented by the MVS normals — static, or in the object's frame for moving ones — added
   with :func:`~vadgs.train.strategy.ops.add_gaussians` (optimizer moments and state rows follow);
5. **priors**: the MVS depth and normals of the group views are kept in ``state`` and returned by
   :meth:`VisibilityAwareDensification.geometry_targets` (voxel depth where no MVS depth exists),
   which the loop turns into the normal and hard/soft depth losses with
   :func:`vadgs.train.losses.geometric_losses` — one loss path, in vadgs's trainer or any loop.

Ablation switches (:class:`VisibilityDensifyConfig`): ``view_selection=False`` uses consecutive
frames of the reference camera, ``geometric_losses=False`` drops the priors; the paper's "w/o voxel
visibility reasoning", which disables everything else, is the base strategy alone (no VAD-GS:
``TrainConfig.vad = None``). Every event's cost is logged in
``state["vad_events"]`` (seconds of detection, selection + MVS, and densification).
"""

from __future__ import annotations

import inspect
import time
from collections.abc import Callable, Mapping, MutableMapping
from dataclasses import dataclass, field, fields, replace
from typing import Any

import torch

from vadgs.checks import check_size, float_field, int_field
from vadgs.train.losses import GeometryTargets
from vadgs.train.strategy import DefaultStrategy, ops
from vadgs.train.vad.config import _FIELDS as _CONFIG_FIELDS
from vadgs.train.vad.config import StrategyContext, VisibilityDensifyConfig, _with_settings_of
from vadgs.train.vad.detect import detect, detect_view, keep_render, view_map
from vadgs.train.vad.event import EventInputs, run_event
from vadgs.train.vad.gaussians import add_reconstruction
from vadgs.train.vad.incomplete import IncompleteInstances
from vadgs.train.vad.inputs import VisibilityInputs
from vadgs.train.vad.reconstruct import InstanceReconstruction, ViewRender
from vadgs.train.vad.reconstruct_config import ReconstructConfig
from vadgs.train.vad.visibility import VisibilityIndex, build_visibility_index

__all__ = ["VisibilityAwareDensification", "check_info", "info_requirements"]

_MAX_PENDING = 64  # events kept in state["pending_log"] when the loop does not pop them

_SETTINGS = {**_CONFIG_FIELDS, "log_size": int_field(1)}
"""The check of each setting of the strategy (:meth:`VisibilityAwareDensification.__setattr__`)."""

_SCENE_SCALE = float_field(0, lo_open=True)

_GSPLAT_META = "the meta dict gsplat's rasterization() returns as its third output"


def info_requirements(base: Any, packed: bool = False) -> list[dict[str, str]]:
    """What a base strategy reads from the loop's ``info``: alternatives of ``{key: where it comes from}``.

    vadgs's ``DefaultStrategy``: vadgs's render (``raster``, ``image_size``) or gsplat's meta
    (``means2d``, ``width``, ``height``, ``radii``; ``gaussian_ids`` too when ``packed``); gsplat's
    ``DefaultStrategy``: its ``key_for_gradient`` (``means2d``), ``width``, ``height``,
    ``n_cameras``, ``radii`` and ``gaussian_ids`` (None unless ``packed``); gsplat's
    ``MCMCStrategy``: nothing (it takes ``lr=``). Other bases: nothing is known (an empty list).

    Example:
        >>> [sorted(a) for a in info_requirements(DefaultStrategy())]
        [['image_size', 'raster'], ['height', 'means2d', 'radii', 'width']]
    """
    if isinstance(base, DefaultStrategy):
        meta = {k: _GSPLAT_META for k in ("means2d", "width", "height", "radii")}
        if packed:
            meta["gaussian_ids"] = _GSPLAT_META + " with packed=True"
        return [
            {
                "raster": "vadgs's rasterize_gaussians() output (RenderOutput)",
                "image_size": "the view's (H, W)",
            },
            meta,
        ]
    cls = type(base)
    if not cls.__module__.startswith("gsplat.") or not hasattr(base, "key_for_gradient"):
        return []  # gsplat's MCMCStrategy reads nothing; unknown bases: not checked
    req = {k: _GSPLAT_META for k in (base.key_for_gradient, "width", "height", "n_cameras", "radii")}
    req["gaussian_ids"] = _GSPLAT_META + (" with packed=True" if packed else " (None when packed=False)")
    return [req]


def check_info(base: Any, info: Mapping[str, Any], packed: bool = False) -> None:
    """Check the loop's ``info`` against what ``base`` reads (:func:`info_requirements`).

    Raises:
        ValueError: naming the missing key, the base that reads it and where it comes from.
    """
    alternatives = info_requirements(base, packed)
    if not alternatives:
        return
    if not isinstance(info, Mapping):
        raise ValueError(f"info: expected a dict (the renderer's meta), got {type(info).__name__}")
    missing = [[k for k in alt if k not in info] for alt in alternatives]
    if any(not m for m in missing):
        if packed and info.get("gaussian_ids", 0) is None and "gaussian_ids" in alternatives[-1]:
            raise ValueError(
                "info['gaussian_ids']: expected the ids of gsplat's rasterization(packed=True) with "
                "packed=True, got None"
            )
        return
    best = min(range(len(missing)), key=lambda i: (len(missing[i]) - len(alternatives[i]), len(missing[i])))
    key = missing[best][0]
    name = f"{type(base).__module__.split('.')[0]}'s {type(base).__name__}"
    raise ValueError(
        f"info: expected key {key!r} (read by {name}; from {alternatives[best][key]}), "
        f"got keys {sorted(info)}"
    )


def _check_info_values(info: Mapping[str, Any], num_views: int | None) -> None:
    """Check the values ``info`` carries for the strategy: metadata only (no tensor value is read).

    ``view`` an integer in ``[0, num_views)`` (when known), ``image_size`` a positive ``(H, W)``,
    ``width`` / ``height`` positive integers, and the render's ``depth`` / ``alpha`` (of
    ``info["raster"]`` or ``info``) tensors of shape ``(1, H, W)``, ``(H, W)`` or ``(1, 1, H, W)``
    of one ``(H, W)``, that of ``image_size`` or ``height``, ``width`` when given.

    Raises:
        ValueError: naming the key, the expected and the actual value or shape.
    """
    if not isinstance(info, Mapping):
        return  # check_info names it when the base reads info; otherwise nothing is read
    view = info.get("view")
    if view is not None:
        hi = None if num_views is None else num_views - 1
        note = "" if num_views is None else f" (a view of the inputs' {num_views})"
        int_field(0, hi, note=note)("info['view']", view)
    size = None
    if info.get("image_size") is not None:
        size = check_size(info["image_size"], "info['image_size']")
    for key in ("height", "width"):
        if info.get(key) is not None:
            int_field(1)(f"info[{key!r}]", info[key])
    if size is None and info.get("height") is not None and info.get("width") is not None:
        size = (int(info["height"]), int(info["width"]))
    raster = info.get("raster")
    maps = {}
    for key in ("depth", "alpha"):
        name, value = f"info[{key!r}]", info.get(key)
        if raster is not None:
            name, value = f"info['raster'].{key}", getattr(raster, key, None)
        if value is None:
            continue
        if not isinstance(value, torch.Tensor):
            raise ValueError(
                f"{name}: expected a torch.Tensor (the view's rendered {key}), got {type(value).__name__}"
            )
        shape = tuple(value.shape)
        ok = (
            (len(shape) == 2)
            or (len(shape) == 3 and shape[0] == 1)
            or (len(shape) == 4 and shape[:2] == (1, 1))
        )
        hw = shape[-2:]
        want = (
            "(1, H, W), (H, W) or (1, 1, H, W)"
            if size is None
            else f"(1, {size[0]}, {size[1]}) or (H, W) = {size}"
        )
        if not ok or (size is not None and hw != size):
            raise ValueError(f"{name}: expected the view's {key} of shape {want}, got {shape}")
        maps[name] = hw
    if len(set(maps.values())) > 1:
        (a, ha), (b, hb) = maps.items()
        raise ValueError(f"{a}, {b}: expected maps of one size (H, W), got {ha} and {hb}")


@dataclass(eq=False)
@_with_settings_of(VisibilityDensifyConfig)
class VisibilityAwareDensification:
    """The VAD-GS densification strategy (gsplat ``Strategy`` interface). See the module docstring.

    A dataclass whose fields are its settings, as gsplat's ``DefaultStrategy`` /
    ``MCMCStrategy``: the fields, defaults and checks of :class:`VisibilityDensifyConfig` (copied
    from it, written once), then ``base``, ``on_addition`` and ``log_size``; :meth:`from_config`
    builds one from a :class:`VisibilityDensifyConfig` (vadgs's trainer and ``vadgs train
    --vad.KEY VALUE``). It holds no
    dataset: :meth:`prepare` gives it a :class:`~vadgs.train.vad.inputs.VisibilityInputs` (per-view
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
        on_progress: optional callback, called with one line while an event runs (``"VAD-GS event
            2: instance 3/5 (sign 12), 41 s so far"``): a loop's progress bar shows it (vadgs's
            trainer does), so that a long event does not look like a frozen run.
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
        ['view_selection', 'geometric_losses', 'every_cycles']
    """

    base: Any = field(default_factory=DefaultStrategy)
    on_addition: Callable[[dict[str, Any]], None] | None = field(default=None, repr=False)
    on_progress: Callable[[str], None] | None = field(default=None, repr=False)
    log_size: int = _MAX_PENDING
    inputs: VisibilityInputs | None = field(default=None, init=False, repr=False)
    context: StrategyContext | None = field(default=None, init=False, repr=False)
    index: VisibilityIndex | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        self._last_call: float | None = None

    def __setattr__(self, name: str, value: Any) -> None:
        """Set an attribute; a setting is checked first (its check in :data:`_SETTINGS`).

        Each setting is checked once, when it is set (by ``__init__`` or later), with the check of
        :class:`VisibilityDensifyConfig`'s own field: ``strategy.every_cycles = 0`` raises as
        ``VisibilityDensifyConfig(every_cycles=0)`` does.
        """
        check = _SETTINGS.get(name)
        if check is not None:
            value = check(name, value)
            self.__dict__.pop("_config", None)  # the cached config of the settings
        object.__setattr__(self, name, value)

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
        config = self.__dict__.get("_config")
        if config is None:  # built again only after a setting changed
            config = VisibilityDensifyConfig(
                **{f.name: getattr(self, f.name) for f in fields(VisibilityDensifyConfig)}
            )
            self.__dict__["_config"] = config
        return config

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

        :func:`~vadgs.train.strategy.ops.check_params`, then the base's own ``check_sanity`` when it has
        one.

        Raises:
            ValueError: naming the key, what was expected and what was found.
        """
        ops.check_params(params, optimizers)
        if hasattr(self.base, "check_sanity"):
            self.base.check_sanity(params, optimizers)

    def initialize_state(self, scene_scale: float = 1.0) -> dict[str, Any]:
        """The base strategy's state plus the event log, the priors, the cycle counter and view tests.

        The base gets ``scene_scale`` when its ``initialize_state`` takes an argument (gsplat's
        ``MCMCStrategy`` takes none).

        Raises:
            ValueError: ``scene_scale`` is not a finite number > 0.
        """
        scene_scale = _SCENE_SCALE("scene_scale", scene_scale)
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

    def step_pre_backward(
        self,
        params: MutableMapping[str, torch.Tensor],
        optimizers: Any,
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
        **kwargs: Any,
    ) -> None:
        """The base's ``step_pre_backward``; at the first step, checks ``info`` for the base.

        ``kwargs`` go to the base (gsplat's loop passes none here).

        (``step_post_backward`` checks it again at its first call, with its ``packed=``.)

        Raises:
            ValueError: a key the base reads is missing from ``info`` (see :func:`check_info`).
        """
        if not getattr(self, "_info_checked", False):
            check_info(self.base, info)
            self._info_checked = True
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

        Raises:
            ValueError: a key the base reads is missing from ``info`` (:func:`check_info`), or a
                value in it is out of range: ``view`` not a view of the inputs, ``image_size``,
                ``width`` or ``height`` not positive, a ``depth`` / ``alpha`` of the wrong shape
                (naming the key, the expected and the actual).
        """
        now = time.perf_counter()
        if self._last_call is not None:
            state["vad_train_s"] = state.get("vad_train_s", 0.0) + (now - self._last_call)
        self._last_call = now
        if not getattr(self, "_post_info_checked", False):  # with packed= now known
            check_info(self.base, info, bool(kwargs.get("packed", False)))
            self._post_info_checked = True
        has_inputs = self.inputs is not None or self.index is not None
        _check_info_values(info, self._inputs().num_views if has_inputs else None)
        self.base.step_post_backward(params, optimizers, state, step, info, **kwargs)
        context = self._context()
        if step < self.last_event_fraction * context.total_steps:
            self._observe(state, info)
        elif state.get("vad_renders") or state.get("vad_tests"):
            # no event can follow (each is at a later step): their tests and renders are never used
            state["vad_tests"], state["vad_renders"] = {}, {}
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
        depth, alpha = view_map(depth), view_map(alpha)
        if tuple(depth.shape[-2:]) != tuple(self._inputs().size(view)):
            return  # a crop or another scale of the view (gsplat's patch_size): not the view's render
        state.setdefault("vad_tests", {})[view] = detect_view(
            self.prepare(), view, depth, alpha, self.incomplete
        )
        normals = torch.zeros(3, *depth.shape[-2:]).to(depth) if normals is None else view_map(normals)
        keep_render(
            state.setdefault("vad_renders", {}),
            view,
            ViewRender(depth, alpha, normals),
            int(self.render_cache_mb * 2**20),
        )

    def trained_pixels(self, step: int) -> float:
        """Training pixels up to and including ``step``: ``(step + 1)`` × the training views' mean size.

        The scale of the event's ``work_budget`` (a function of the step, hence the same on any
        machine and on resume).
        """
        if getattr(self, "_mean_pixels", None) is None:
            inputs = self._inputs()
            sizes = [inputs.size(v) for v in inputs.train_views]
            self._mean_pixels = sum(h * w for h, w in sizes) / max(len(sizes), 1)
        return (step + 1) * self._mean_pixels

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
        arguments return the index.

        Args:
            inputs: :class:`~vadgs.train.vad.inputs.VisibilityInputs` (e.g.
                ``VisibilityInputs.from_scene(scene)`` or ``.from_gsplat_parser(parser)``).
            context: :class:`StrategyContext`: the loop's render function, step counts, generator.
            index: a prebuilt :class:`~vadgs.train.vad.reconstruct.VisibilityIndex` of these inputs
                (its own inputs are used when ``inputs`` is None).

        Returns:
            The index.

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
            self._train_views = self._mean_pixels = None
        elif inputs is not None and inputs is not self.inputs:
            self.inputs, self.index, self._train_views, self._mean_pixels = inputs, None, None, None
        if context is not None:
            self.context = context
        if self.index is None:
            self.index = self._build_index()
        return self.index

    def _build_index(self) -> VisibilityIndex:
        return build_visibility_index(
            self._inputs(), self.voxel_size, cell_size=self.cell_size, scene_depth=self.scene_depth
        )

    def visibility_index(self) -> VisibilityIndex:
        """The :class:`~vadgs.train.vad.reconstruct.VisibilityIndex` (see :meth:`prepare`)."""
        if self.index is None:
            self.index = self._build_index()
        return self.index

    @property
    def lengths(self) -> dict[str, Any]:
        """The lengths in use (world units; empty before :meth:`prepare`).

        ``scene_depth``, ``voxel_size`` and ``cell_size`` of the visibility index.
        """
        if self.index is None:
            return {}
        i = self.index
        return {"scene_depth": i.scene_depth, "voxel_size": i.grid.voxel_size, "cell_size": i.cell_size}

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
                the fields of its one-view :class:`~vadgs.train.vad.incomplete.IncompleteInstances`);
                those views are not rendered again.

        Returns:
            ``(rows, views)``: :class:`~vadgs.train.vad.incomplete.IncompleteInstances` (``rows.view``
            indexes ``views``) and the views tested.
        """
        return detect(
            self.prepare(),
            views if views is not None else list(self._inputs().train_views),
            renders or self._context().render,
            tests or {},
            self.incomplete,
        )

    def densify(
        self,
        params: MutableMapping[str, torch.Tensor],
        optimizers: Any,
        state: dict[str, Any],
        step: int,
    ) -> dict[str, Any]:
        """One visibility-aware densification event (detect, reconstruct, add); returns its log.

        See :func:`vadgs.train.vad.event.run_event`, given this strategy's parts as an
        :class:`~vadgs.train.vad.event.EventInputs`.
        """
        context = self._context()
        event = EventInputs(
            index=self.prepare(),
            inputs=self._inputs(),
            render=context.render,
            generator=context.generator,
            config=self.config,
            reconstruct=self._reconstruct_config(),
            add=self._add,
            trained_pixels=None if self.work_budget is None else self.trained_pixels(step),
            on_progress=self.on_progress,
            on_addition=self.on_addition,
            log_size=self.log_size,
        )
        return run_event(event, params, optimizers, state, step)

    def _add(
        self,
        params: MutableMapping[str, torch.Tensor],
        optimizers: Any,
        state: dict[str, Any] | None,
        rec: InstanceReconstruction,
        keep: torch.Tensor | None = None,
        event: int = 1,
    ) -> None:
        """Add the flat Gaussians of the (kept) points (:func:`~vadgs.train.vad.event.add_reconstruction`)."""
        add_reconstruction(params, optimizers, state, rec, keep, event, self.config, self._track_nodes)

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
        ``None`` when the losses are off (``geometric_losses``), or the view has no prior. Tensors
        ``(1, 1, H, W)`` / ``(1, 3, H, W)`` on the device of the MVS priors (the render's), or of
        the visibility index for a view without them: move them to the render's device.

        Raises:
            ValueError: before :meth:`prepare` or with a ``state`` not made by
                :meth:`initialize_state`, or a ``view`` that is not one of the inputs'.
        """
        cfg = self.config
        if not cfg.geometric_losses:
            return None
        if self.inputs is None and self.index is None:
            raise ValueError(
                "geometry_targets: expected a prepared strategy, got none: call prepare(inputs, "
                "context) and initialize_state() first"
            )
        if not isinstance(state, Mapping) or "vad_priors" not in state:
            got = f"keys {sorted(state)}" if isinstance(state, Mapping) else type(state).__name__
            raise ValueError(
                "state: expected the strategy's state (from initialize_state(), with 'vad_priors'), "
                f"got {got}"
            )
        n = self._inputs().num_views
        view = int_field(0, n - 1, note=f" (a view of the inputs' {n})")("view", view)
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
