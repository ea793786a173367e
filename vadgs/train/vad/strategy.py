r"""VAD-GS: the visibility-aware densification strategy (paper, Sec. "Methodology").

:class:`VisibilityAwareDensification` is a gsplat-style strategy that wraps a standard one and never
sees the training loop nor a vadgs ``Scene``. Every ``every_cycles`` complete sampling cycles of the
training views it runs one event (:func:`~vadgs.train.vad.event.run_event`): detection
(:mod:`~vadgs.train.vad.detect`), references (:mod:`~vadgs.train.vad.references`), multi-view
stereo (:mod:`~vadgs.train.vad.reconstruct`), new Gaussians (:mod:`~vadgs.train.vad.gaussians`)
and the priors of the geometric losses (:mod:`~vadgs.train.vad.priors`). ``docs/vad.md`` maps the
paper's sections to these modules; each event's cost is logged in ``state["vad_events"]``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, MutableMapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import torch

from vadgs.checks import float_field, int_field
from vadgs.train.losses import GeometryTargets
from vadgs.train.strategy import (
    ConfiguredStrategy,
    DefaultStrategy,
    StrategyStep,
    initialize_base_state,
    ops,
)
from vadgs.train.vad.config import StrategyContext, VisibilityDensifyConfig
from vadgs.train.vad.detect import EventRenders, detect, observe_view
from vadgs.train.vad.event import EventInputs, run_event
from vadgs.train.vad.incomplete import IncompleteInstances
from vadgs.train.vad.info import check_info, check_info_values
from vadgs.train.vad.inputs import VisibilityInputs
from vadgs.train.vad.priors import state_priors, view_targets
from vadgs.train.vad.reconstruct import ViewRender
from vadgs.train.vad.visibility import VisibilityIndex, build_visibility_index

__all__ = ["VisibilityAwareDensification"]

_MAX_PENDING = 64  # events kept in state["pending_log"] when the loop does not pop them

_LOG_SIZE = int_field(1)
_SCENE_SCALE = float_field(0, lo_open=True)


@dataclass(init=False, eq=False)
class VisibilityAwareDensification(ConfiguredStrategy):
    """The VAD-GS densification strategy (gsplat ``Strategy`` interface). See the module docstring.

    Its settings are a :class:`VisibilityDensifyConfig` in ``config``, given whole or as keywords
    and readable / assignable as attributes, each checked as the config's field is
    (:class:`~vadgs.train.strategy.ConfiguredStrategy`). It holds no dataset: :meth:`prepare`
    gives it a :class:`~vadgs.train.vad.inputs.VisibilityInputs` and the loop's
    :class:`StrategyContext`, and builds the visibility index once. Use::

        strategy = VisibilityAwareDensification(base=DefaultStrategy(), every_cycles=5)
        strategy.check_sanity(params, optimizers)
        strategy.prepare(VisibilityInputs.from_gsplat_parser(parser), context)
        state = strategy.initialize_state(scene_scale)
        # each step: step_pre_backward(...); loss.backward(); step_post_backward(..., packed=...)

    Args:
        config: :class:`VisibilityDensifyConfig` (default: the paper's settings).
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
        **settings: fields of :class:`VisibilityDensifyConfig` replaced in ``config``
            (``VisibilityAwareDensification(every_cycles=2)``; the settings read and are assigned
            as :class:`~vadgs.train.strategy.ConfiguredStrategy`'s example shows).
    """

    config_type: ClassVar[type[Any]] = VisibilityDensifyConfig
    config: VisibilityDensifyConfig
    base: Any
    on_addition: Callable[[dict[str, Any]], None] | None = field(repr=False)
    on_progress: Callable[[str], None] | None = field(repr=False)
    log_size: int
    inputs: VisibilityInputs | None = field(repr=False)
    context: StrategyContext | None = field(repr=False)
    index: VisibilityIndex | None = field(repr=False)

    def __init__(
        self,
        config: VisibilityDensifyConfig | None = None,
        base: Any = None,
        on_addition: Callable[[dict[str, Any]], None] | None = None,
        on_progress: Callable[[str], None] | None = None,
        log_size: int = _MAX_PENDING,
        **settings: Any,
    ) -> None:
        self._take_config(config, settings)
        self.base = base if base is not None else DefaultStrategy()
        self.on_addition, self.on_progress, self.log_size = on_addition, on_progress, log_size
        self.inputs: VisibilityInputs | None = None
        self.context: StrategyContext | None = None
        self.index: VisibilityIndex | None = None
        self._last_call: float | None = None
        self._info_checked = self._post_info_checked = False
        self._train_views: set[int] | None = None
        self._num_ids: dict[int, int] = {}  # observe_view's: one more than a view's largest instance id

    def __setattr__(self, name: str, value: Any) -> None:
        if name == "log_size":
            value = _LOG_SIZE(name, value)
        super().__setattr__(name, value)

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
        """The strategy of ``config`` and ``base``; :meth:`prepare` d when given its other arguments."""
        out = cls(config, base=base, on_addition=on_addition)
        if inputs is not None or index is not None or context is not None:
            out.prepare(inputs, context, index)
        return out

    # -- Strategy interface ----------------------------------------------------------------------------

    def check_sanity(self, params: Mapping[str, torch.Tensor], optimizers: Any) -> None:
        """:func:`~vadgs.train.strategy.ops.check_params`, then the base's ``check_sanity`` if it has one.

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
        state = initialize_base_state(self.base, _SCENE_SCALE("scene_scale", scene_scale))
        state.update(
            vad_events=[], vad_priors={}, vad_cycle=0, vad_last_done={}, vad_tests={}, vad_train_s=0.0
        )
        return state

    def pre_backward(self, call: StrategyStep) -> None:
        """The base's ``step_pre_backward`` (given ``call.kwargs``); at the first step, checks ``info``.

        Raises:
            ValueError: a key the base reads is missing from ``info`` (see :func:`check_info`).
        """
        if not self._info_checked:
            check_info(self.base, call.info)
            self._info_checked = True
        call.forward_to(self.base.step_pre_backward)

    def post_backward(self, call: StrategyStep) -> None:
        """Base densification, then a visibility-aware event after every ``every_cycles`` cycles.

        Also tests the trained view for incompleteness when ``info`` carries its render.
        ``call.kwargs`` (e.g. ``packed=True`` for gsplat's ``DefaultStrategy``, ``lr=`` for its
        ``MCMCStrategy``) go to the base.

        Raises:
            ValueError: a key the base reads is missing from ``info`` (:func:`check_info`), or a
                value in it is out of range (:func:`check_info_values`), naming the key.
        """
        params, optimizers, state, step, info, kwargs = call
        now = time.perf_counter()
        if self._last_call is not None:
            state["vad_train_s"] = state.get("vad_train_s", 0.0) + (now - self._last_call)
        self._last_call = now
        if not self._post_info_checked:  # with packed= now known
            check_info(self.base, info, bool(kwargs.get("packed", False)))
            self._post_info_checked = True
        has_inputs = self.inputs is not None or self.index is not None
        check_info_values(info, self._inputs().num_views if has_inputs else None)
        call.forward_to(self.base.step_post_backward)
        context = self._context()
        if step < self.config.last_event_fraction * context.total_steps:
            self._observe(state, info)
        elif state.get("vad_renders") or state.get("vad_tests"):
            # no event can follow (each is at a later step): their tests and renders are never used
            state["vad_tests"], state["vad_renders"] = {}, {}
        cycle = (step + 1) // context.steps_per_cycle
        if cycle != state["vad_cycle"]:
            state["vad_cycle"] = cycle
            late = step >= self.config.last_event_fraction * context.total_steps
            if cycle > 0 and cycle % self.config.every_cycles == 0 and not late:
                self.densify(params, optimizers, state, step)
                self._last_call = time.perf_counter()  # the event's time is not training time

    def _observe(self, state: dict[str, Any], info: Mapping[str, Any]) -> None:
        """Test the view just trained from the loop's render (the others are rendered at the event)."""
        view = info.get("view") if isinstance(info, Mapping) else None
        if view is None or int(view) not in self._train_set():
            return
        mb = self.config.render_cache_mb
        index, inputs = self.prepare(), self._inputs()
        observe_view(state, info, index, inputs, self.config.incomplete, int(mb * 2**20), self._num_ids)

    def trained_pixels(self, step: int) -> float:
        """Training pixels up to and including ``step``: ``(step + 1)`` × the training views' mean size.

        The scale of the event's ``work_budget`` (a function of the step, hence the same on any
        machine and on resume).
        """
        inputs = self._inputs()
        sizes = [inputs.size(v) for v in inputs.train_views]
        return (step + 1) * (sum(h * w for h, w in sizes) / max(len(sizes), 1))

    def _train_set(self) -> set[int]:
        if self._train_views is None:
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

    def prepare(
        self,
        inputs: VisibilityInputs | None = None,
        context: StrategyContext | None = None,
        index: VisibilityIndex | None = None,
    ) -> VisibilityIndex:
        """Give the strategy its data and the loop's context, and build the visibility index once.

        Call it before the first step (vadgs's trainer does, at construction); without arguments
        it returns the index.

        Args:
            inputs: :class:`~vadgs.train.vad.inputs.VisibilityInputs` (e.g.
                ``VisibilityInputs.from_scene(scene)`` or ``.from_gsplat_parser(parser)``).
            context: :class:`StrategyContext`: the loop's render function, step counts, generator.
            index: a prebuilt :class:`~vadgs.train.vad.visibility.VisibilityIndex` of these inputs
                (its own inputs are used when ``inputs`` is None).

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
            self._num_ids = {}
        elif inputs is not None and inputs is not self.inputs:
            self.inputs, self.index, self._train_views = inputs, None, None
            self._num_ids = {}
        if context is not None:
            self.context = context
        if self.index is None:
            cfg = self.config
            self.index = build_visibility_index(
                self._inputs(),
                cfg.voxel_size,
                cell_size=cfg.cell_size,
                scene_depth=cfg.scene_depth,
                cache_mb=cfg.index_cache_mb,
            )
        return self.index

    def visibility_index(self) -> VisibilityIndex:
        """The visibility index, built if needed: :meth:`prepare` without arguments."""
        return self.prepare()

    @property
    def lengths(self) -> dict[str, float]:
        """The lengths in use (world units; empty before :meth:`prepare`): the index's scale."""
        i = self.index
        if i is None:
            return {}
        return {"scene_depth": i.scene_depth, "voxel_size": i.grid.voxel_size, "cell_size": i.cell_size}

    @torch.no_grad()
    def detect(
        self,
        views: list[int] | None = None,
        renders: Callable[[int], ViewRender] | None = None,
        tests: Mapping[int, tuple[torch.Tensor, ...]] | None = None,
        kept: Mapping[int, tuple[torch.Tensor, ...]] | None = None,
    ) -> tuple[IncompleteInstances, list[int]]:
        """:func:`~vadgs.train.vad.detect.detect` on ``views`` (default: every training view).

        ``renders`` defaults to the context's; a view in ``tests`` (``state["vad_tests"]``: tests
        made from the loop's renders, or left to here) is not rendered again: an empty entry is
        tested from its render in ``kept`` (``state["vad_renders"]``). Returns ``(rows, views
        tested)``, ``rows.view`` indexing the views tested.
        """
        return detect(
            self.prepare(),
            views if views is not None else list(self._inputs().train_views),
            EventRenders(renders or self._context().render, kept),
            tests or {},
            self.config.incomplete,
        )

    def densify(
        self,
        params: MutableMapping[str, torch.Tensor],
        optimizers: Any,
        state: dict[str, Any],
        step: int,
    ) -> dict[str, Any]:
        """One event (:func:`~vadgs.train.vad.event.run_event` on this strategy's parts); returns its log."""
        context = self._context()
        event = EventInputs(
            index=self.prepare(),
            inputs=self._inputs(),
            render=context.render,
            generator=context.generator,
            config=self.config,
            reconstruct=self.config.effective_reconstruct(),
            track_nodes=self._track_nodes(),
            trained_pixels=None if self.config.work_budget is None else self.trained_pixels(step),
            on_progress=self.on_progress,
            on_addition=self.on_addition,
            log_size=self.log_size,
        )
        return run_event(event, params, optimizers, state, step)

    def _track_nodes(self) -> Mapping[int, int]:
        """Track id → node of ``params["node_ids"]``: the context's, else the inputs' tracks in order."""
        if self.context is not None and self.context.track_nodes is not None:
            return self.context.track_nodes
        return {t: k for k, t in enumerate(sorted(self._inputs().tracks))}

    def geometry_targets(self, state: dict[str, Any], view: int) -> GeometryTargets | None:
        """The priors of a view for :func:`vadgs.train.losses.geometric_losses`.

        :func:`~vadgs.train.vad.priors.view_targets`: the MVS depth and normals of the events so
        far, the voxel depth of the pixel's own instance elsewhere; ``None`` when the losses are off
        (``geometric_losses``) or the view has no prior. Move the tensors to the render's device.

        Raises:
            ValueError: before :meth:`prepare` or with a ``state`` not made by
                :meth:`initialize_state`, or a ``view`` that is not one of the inputs'.
        """
        if not self.config.geometric_losses:
            return None
        if self.inputs is None and self.index is None:
            raise ValueError(
                "geometry_targets: expected a prepared strategy, got none: call prepare(inputs, "
                "context) and initialize_state() first"
            )
        n = self._inputs().num_views
        view = int_field(0, n - 1, note=f" (a view of the inputs' {n})")("view", view)
        cfg = self.config
        priors = state_priors(state)
        return view_targets(priors, self.prepare(), view, cfg.voxel_depth_prior, cfg.voxel_prior_tracks)
