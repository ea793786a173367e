"""The interface of a densification strategy (gsplat's ``Strategy``) and of a priors provider.

A strategy follows gsplat's ``Strategy``: an object with settings whose training state lives in a
dict that the training loop owns, checkpoints and passes back (what must survive a resume is in
that dict; a strategy may keep caches derived from its inputs, such as the visibility-aware
strategy's voxel index and the timings of its events, which are rebuilt after a resume and do
not change the results). Any loop calls

.. code-block:: python

    strategy.check_sanity(params, optimizers)     # once: params and optimizers agree
    state = strategy.initialize_state(scene_scale)
    for step in ...:
        out = render(params, view)                 # info: what the rasterizer reports
        strategy.step_pre_backward(params, optimizers, state, step, info)
        loss.backward()
        for opt in optimizers.values(): opt.step()  # or one optimizer with named groups
        strategy.step_post_backward(params, optimizers, state, step, info)  # may add / remove rows

Both step methods take further keyword arguments, as a loop written for gsplat passes them
(``step_post_backward(..., packed=cfg.packed)`` to gsplat's ``DefaultStrategy``, ``lr=`` to its
``MCMCStrategy``): a strategy uses those it knows and ignores the others.

``params`` is gsplat's mapping of per-Gaussian tensors (``means``, ``quats``, ``scales``,
``opacities``, ``sh0``, ``shN``) or vadgs's ``GaussianModel.params`` (``log_scales``,
``opacity_logits``, ``sh_dc``, ``sh_rest`` and the integer ``node_ids``); ``optimizers`` is gsplat's
``{name: optimizer}`` or one optimizer with a named group per parameter
(:func:`vadgs.train.model.make_optimizer`). Strategies change the set of Gaussians only through
:mod:`vadgs.train.strategy.ops`, which keeps the optimizer moments and every per-Gaussian tensor of
``state`` consistent. A strategy never sees the training loop: what else it needs is given to it
explicitly (e.g. :class:`~vadgs.train.vad.StrategyContext` for the visibility-aware one).

vadgs's strategies share one shape, :class:`ConfiguredStrategy`: the settings are a frozen,
validated config dataclass held in ``strategy.config`` (``DefaultStrategyConfig``,
``VisibilityDensifyConfig``: what ``TrainConfig`` and the CLI hold), given as ``config=`` or as
keyword settings (``DefaultStrategy(refine_every=50)``, as gsplat's strategies are called), and
readable and assignable as attributes (``strategy.refine_every = 0`` is checked as the config's
field is, then replaces the config). An attribute that is neither a setting nor one the strategy
has (a typo: ``strategy.refine_evrey = 50``) is refused with an ``AttributeError``, as a frozen
dataclass refuses it; a subclass's ``__init__`` may add its own attributes. Its two step methods
are gsplat's, written once: each hands the call's arguments, as one :class:`StrategyStep`, to the
subclass's :meth:`~ConfiguredStrategy.pre_backward` / :meth:`~ConfiguredStrategy.post_backward`.

``info`` is either vadgs's (``raster``: the :class:`~vadgs.render.RenderOutput`, ``ids``: the model
rows it rendered, ``image_size``, ``generator``) or gsplat's (``means2d`` with its gradient,
``radii``, ``width``, ``height``, ``n_cameras``; :func:`gsplat.rasterization`'s ``meta``).
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import inspect
from collections.abc import MutableMapping
from typing import Any, ClassVar, NamedTuple, Protocol, runtime_checkable

import torch

from vadgs.train.losses import GeometryTargets

__all__ = ["ConfiguredStrategy", "GeometryPriors", "Strategy", "StrategyStep", "initialize_base_state"]


@runtime_checkable
class Strategy(Protocol):
    """The interface every densification strategy implements (gsplat's ``Strategy``).

    A strategy may append JSON-serialisable dicts to ``state["pending_log"]``: vadgs's trainer
    writes each as an ``{"step": ..., "event": ...}`` line of ``log.jsonl`` right after the step
    and removes them from the state.
    """

    def check_sanity(self, params: MutableMapping[str, torch.Tensor], optimizers: Any) -> None:
        """Check ``params`` and ``optimizers`` before training; raises ``ValueError`` naming the key."""
        ...

    def initialize_state(self, scene_scale: float = 1.0) -> dict[str, Any]:
        """A fresh state dict (per-Gaussian tensors are allocated lazily, at their first use)."""
        ...

    def step_pre_backward(
        self,
        params: MutableMapping[str, torch.Tensor],
        optimizers: Any,
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
        **kwargs: Any,
    ) -> None:
        """Called after the render, before ``loss.backward()``."""
        ...

    def step_post_backward(
        self,
        params: MutableMapping[str, torch.Tensor],
        optimizers: Any,
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
        **kwargs: Any,
    ) -> None:
        """Called after ``loss.backward()`` and the optimizer step; may add or remove Gaussians."""
        ...


class StrategyStep(NamedTuple):
    """The arguments of one call of a step method, as the training loop passed them.

    :class:`ConfiguredStrategy`'s ``step_pre_backward`` / ``step_post_backward`` hand them to the
    subclass's :meth:`~ConfiguredStrategy.pre_backward` / :meth:`~ConfiguredStrategy.post_backward`;
    :meth:`forward_to` passes them on to another strategy (one that a strategy wraps).
    """

    params: MutableMapping[str, torch.Tensor]
    """gsplat's mapping of per-Gaussian tensors or vadgs's ``GaussianModel.params``."""
    optimizers: Any
    """gsplat's ``{name: optimizer}`` or vadgs's one optimizer with named groups."""
    state: dict[str, Any]
    """The strategy's state (:meth:`Strategy.initialize_state`)."""
    step: int
    """The step (just taken, in ``step_post_backward``)."""
    info: dict[str, Any]
    """What the render reports (vadgs's or gsplat's; see the module docstring)."""
    kwargs: dict[str, Any]
    """The further keyword arguments (gsplat's ``packed=``, ``lr=``)."""

    def forward_to(self, method: Any) -> None:
        """Call a strategy's step ``method`` with these arguments (e.g. a wrapped base's)."""
        method(self.params, self.optimizers, self.state, self.step, self.info, **self.kwargs)


@runtime_checkable
class GeometryPriors(Protocol):
    """A strategy that also provides geometric priors (VAD-GS's MVS and voxel depth, normals).

    A training loop turns them into loss terms with :func:`vadgs.train.losses.geometric_losses`;
    vadgs's trainer does so for every strategy that implements this protocol.
    """

    def geometry_targets(self, state: dict[str, Any], view: int) -> GeometryTargets | None:
        """The priors of a view (None: no geometric loss for it)."""
        ...


@dataclasses.dataclass(init=False, eq=False)
class ConfiguredStrategy:
    """The shape of vadgs's strategies: settings in a frozen, validated config (``config``).

    A subclass names its config class in ``config_type`` and calls :meth:`_take_config` in its
    ``__init__`` with ``config`` and the keyword settings it was given. Each setting is then an
    attribute too: reading ``strategy.NAME`` reads ``strategy.config.NAME``; assigning it builds
    a new config with ``dataclasses.replace`` (so the config's own checks run, e.g. ``every_cycles =
    0`` raises ``ValueError``) and stores that. Assigning ``config`` checks its type.

    Example:
        >>> from vadgs.train.strategy import DefaultStrategy, DefaultStrategyConfig
        >>> s = DefaultStrategy(refine_every=50)
        >>> s.refine_every, s.config == DefaultStrategyConfig(refine_every=50)
        (50, True)
        >>> s.refine_every = 0
        Traceback (most recent call last):
        ...
        ValueError: refine_every: expected an integer >= 1, got 0
    """

    config_type: ClassVar[type[Any]]
    config: Any
    # the config's field names, once per class: read at every attribute set (some at every step)
    _setting_names: ClassVar[frozenset[str]] = frozenset()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if hasattr(cls, "config_type"):
            cls._setting_names = _field_names(cls.config_type)
        init = cls.__dict__.get("__init__")
        if init is not None:  # while an __init__ runs, it may add attributes (see __setattr__)

            @functools.wraps(init)
            def constructing(self: Any, *args: Any, **kw: Any) -> None:
                depth = self.__dict__.get("_constructing", 0)
                object.__setattr__(self, "_constructing", depth + 1)
                try:
                    init(self, *args, **kw)
                finally:
                    object.__setattr__(self, "_constructing", depth)

            cls.__init__ = constructing  # type: ignore[method-assign]

    def step_pre_backward(
        self,
        params: MutableMapping[str, torch.Tensor],
        optimizers: Any,
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
        **kwargs: Any,
    ) -> None:
        """Called after the render, before ``loss.backward()``: :meth:`pre_backward` of the arguments."""
        self.pre_backward(StrategyStep(params, optimizers, state, step, info, kwargs))

    def step_post_backward(
        self,
        params: MutableMapping[str, torch.Tensor],
        optimizers: Any,
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
        **kwargs: Any,
    ) -> None:
        """Called after ``loss.backward()`` and the optimizer step: :meth:`post_backward` of the arguments."""
        self.post_backward(StrategyStep(params, optimizers, state, step, info, kwargs))

    def pre_backward(self, call: StrategyStep) -> None:
        """What the strategy does after the render, before ``loss.backward()`` (a subclass's)."""
        raise NotImplementedError(f"{type(self).__name__}.pre_backward")

    def post_backward(self, call: StrategyStep) -> None:
        """What the strategy does after ``loss.backward()`` and the optimizer step (a subclass's)."""
        raise NotImplementedError(f"{type(self).__name__}.post_backward")

    def _take_config(self, config: Any, settings: dict[str, Any]) -> None:
        """Set ``config`` (default: the config type's defaults) with ``settings`` replaced in it.

        Raises:
            ValueError: ``config`` is not a ``config_type``, or a setting fails the config's check.
            TypeError: a setting that is not a field of the config (as an unknown keyword would).
        """
        cls = type(self).config_type
        config = cls() if config is None else config
        if settings:
            unknown = sorted(set(settings) - self._setting_names)
            if unknown:
                raise TypeError(
                    f"{type(self).__name__}: unexpected keyword argument(s) {unknown}: expected the "
                    f"fields of {cls.__name__} ({', '.join(sorted(self._setting_names))})"
                )
            if not isinstance(config, cls):
                raise ValueError(f"config: expected a {cls.__name__}, got {type(config).__name__}")
            config = dataclasses.replace(config, **settings)
        self.config = config

    def __getattr__(self, name: str) -> Any:
        # only for names not found otherwise: a setting reads the config's field
        config = self.__dict__.get("config")
        if config is not None and name in _field_names(type(config)):
            return getattr(config, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def __setattr__(self, name: str, value: Any) -> None:
        cls = type(self).config_type
        if name == "config":
            if not isinstance(value, cls):
                raise ValueError(f"config: expected a {cls.__name__}, got {type(value).__name__}")
        elif name in self._setting_names:
            name, value = "config", dataclasses.replace(self.config, **{name: value})
        elif not (
            name.startswith("_")
            or name in self.__dict__
            or hasattr(type(self), name)
            or self.__dict__.get("_constructing", 0)
        ):
            known = sorted(self._setting_names | {k for k in self.__dict__ if not k.startswith("_")})
            near = difflib.get_close_matches(name, known, n=1)
            hint = f"; did you mean {near[0]!r}?" if near else ""
            raise AttributeError(
                f"{type(self).__name__}: no setting or attribute {name!r}{hint} (settings: the fields of "
                f"{cls.__name__}: {', '.join(sorted(self._setting_names))})"
            )
        object.__setattr__(self, name, value)


def initialize_base_state(strategy: Any, scene_scale: float) -> dict[str, Any]:
    """``strategy.initialize_state(scene_scale)``, or without the argument when it takes none.

    For a strategy that wraps another: gsplat's ``MCMCStrategy.initialize_state`` takes no
    ``scene_scale``, its ``DefaultStrategy`` and vadgs's do.
    """
    init = strategy.initialize_state
    try:
        takes = len(inspect.signature(init).parameters) > 0
    except (TypeError, ValueError):  # a builtin or C callable: assume gsplat's signature
        takes = True
    return init(scene_scale) if takes else init()


def _field_names(cls: type) -> frozenset[str]:
    return frozenset(f.name for f in dataclasses.fields(cls))
