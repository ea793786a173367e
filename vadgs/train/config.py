"""The training run's settings: :class:`TrainConfig` and its :class:`LearningRates`.

Frozen dataclasses, each field checked by its rule (:func:`vadgs.checks.checked`), stored in every checkpoint
(:meth:`TrainConfig.to_dict` / :meth:`TrainConfig.from_dict`, through
:func:`vadgs.config.config_from_dict`); :class:`~vadgs.train.trainer.Trainer` runs them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import torch

from vadgs.checks import MAX_THREADS, Checked, checked, float_field, int_field, nested
from vadgs.data.cache import DEFAULT_CACHE_GB
from vadgs.render import RasterConfig
from vadgs.train.appearance import AppearanceConfig
from vadgs.train.init import InitConfig
from vadgs.train.losses import GeometricLossConfig
from vadgs.train.strategy import DefaultStrategyConfig
from vadgs.train.vad import VisibilityDensifyConfig

__all__ = [
    "SCHEDULE_FIELDS",
    "SCHEDULE_ITERATIONS",
    "LearningRates",
    "TrainConfig",
    "refine_steps",
    "scale_schedule",
]

_MAX_SEED = 2**63 - 1  # torch.manual_seed takes up to 2^64 - 1; the sampler adds to it
_POSITIVE = float_field(0, lo_open=True)
_RATE = float_field(0)  # a learning rate or a weight: 0 switches it off


def _device(name: str, value: object) -> str:
    """A torch device name such as ``"cpu"``, ``"cuda"`` or ``"cuda:1"``."""
    try:
        if isinstance(value, str):
            torch.device(value)
            return value
    except (RuntimeError, TypeError):
        pass
    raise ValueError(f"{name}: expected a torch device such as 'cpu' or 'cuda', got {value!r}")


@dataclass(frozen=True)
class LearningRates(Checked):
    """Adam learning rates (3DGS's).

    ``means`` decays exponentially to ``means_final``; both are multiplied by the scene scale.
    """

    means: float = checked(1.6e-4, _POSITIVE)  # the decay is exponential: log of both
    means_final: float = checked(1.6e-6, _POSITIVE)
    quats: float = checked(1e-3, _RATE)
    log_scales: float = checked(5e-3, _RATE)
    opacity_logits: float = checked(5e-2, _RATE)
    sh_dc: float = checked(2.5e-3, _RATE)
    sh_rest: float = checked(2.5e-3 / 20, _RATE)
    sky: float = checked(1e-2, _RATE)


@dataclass(frozen=True)
class TrainConfig(Checked):
    """Everything a run depends on.

    Composed frozen dataclasses; JSON round trip with :meth:`to_dict` / :meth:`from_dict`.

    Attributes:
        iterations: optimisation steps (one view each).
        seed: seeds the sampler, the split noise and torch.
        init: :class:`~vadgs.train.init.InitConfig`.
        strategy: :class:`~vadgs.train.strategy.DefaultStrategyConfig`.
        raster: :class:`~vadgs.render.RasterConfig`.
        lr: :class:`LearningRates`.
        ssim_weight: λ of the colour loss.
        sh_degree_interval: the active SH degree grows by one every this many steps.
        lambda_lidar: weight of the relative L1 between the rendered depth and the view's own
            LiDAR sweep projected into it (0 disables; the baseline's only geometric term).
        geometry: :class:`~vadgs.train.losses.GeometricLossConfig`: the paper's geometric loss
            (normal, hard and soft depth on priors: VAD-GS's, or a GeometryTargets provider's),
            its weights, the hard term's switch-off after 80 % of the iterations and the settings
            that bound its cost. Older files' flat lambda_normal, lambda_hard, ... are read into it.
        vad: :class:`~vadgs.train.vad.VisibilityDensifyConfig` to train with VAD-GS's
            visibility-aware densification (extending ``strategy``); None: standard ADC only.
            Stored in checkpoints: a resumed run continues with the same strategy.
        appearance: :class:`~vadgs.train.appearance.AppearanceConfig` to learn a colour transform
            per camera (and optionally per frame) applied to the render before the colour loss
            (real rigs with differently exposed cameras); None (the default): no transform, no
            extra parameters. The transforms have their own Adam and go into checkpoints.
        device: where the model, images and losses live (``"cpu"``, ``"cuda"``, ``"cuda:1"``);
            the scene and its visibility index stay on the CPU.
        checkpoint_every: steps between checkpoints (0 = only at the end / on interruption).
        checkpoint_minutes: also checkpoint when this much wall-clock time has passed since the
            last checkpoint (0 = off). The end of the first sampling cycle always checkpoints.
        log_every: steps between log lines in ``log.jsonl``.
        max_minutes: stop (and checkpoint) after this much training time (0 = no limit).
        cache_gb: host memory for the training views' images and LiDAR depth maps, in GB (2^30
            bytes; default 2): they are read from disk when a view is first trained and kept as
            uint8 images and sparse depth in a :class:`~vadgs.data.cache.ByteCache`, the least
            recently trained dropped first and read again. 2 GB hold ~1000 views at 960×640, all
            views of the street scenes; it does not change what is trained, only how often files
            are read.
        threads: ``torch.set_num_threads`` while :meth:`Trainer.train` runs, restored afterwards
            (0 = leave torch's count: all cores unless the caller set it).
        diverge_distance, diverge_share: at step 1, every ``log_every`` steps and at the end of
            each sampling cycle, training stops with
            :class:`DivergenceError` when more than ``diverge_share`` of the static Gaussians are
            farther than ``diverge_distance`` x the scene scale from the cameras' centre
            (``diverge_distance`` 0 = off).
        diverge_loss_factor: training stops with :class:`DivergenceError` when the running mean of
            the colour loss exceeds this factor x its lowest value, after the first sampling cycle
            (0 = off).
    """

    iterations: int = checked(3000, int_field(1))
    seed: int = checked(0, int_field(0, _MAX_SEED))
    init: InitConfig = nested(InitConfig)
    strategy: DefaultStrategyConfig = nested(DefaultStrategyConfig)
    raster: RasterConfig = nested(RasterConfig)
    lr: LearningRates = nested(LearningRates)
    ssim_weight: float = checked(0.2, float_field(0, 1))
    sh_degree_interval: int = checked(1000, int_field(1))
    lambda_lidar: float = checked(0.05, _RATE)
    geometry: GeometricLossConfig = nested(GeometricLossConfig)
    vad: VisibilityDensifyConfig | None = nested(VisibilityDensifyConfig, optional=True)
    appearance: AppearanceConfig | None = nested(AppearanceConfig, optional=True)
    device: str = checked("cpu", _device)
    checkpoint_every: int = checked(500, int_field(0, note=" (0 = off)"))
    checkpoint_minutes: float = checked(5.0, float_field(0, note=" (0 = off)"))
    log_every: int = checked(50, int_field(1))
    max_minutes: float = checked(0.0, float_field(0, note=" (0 = no limit)"))
    cache_gb: float = checked(DEFAULT_CACHE_GB, float_field(0, lo_open=True, note=" (GB)"))
    threads: int = checked(0, int_field(0, MAX_THREADS, note=" (0 = torch's own count)"))
    diverge_distance: float = checked(100.0, float_field(0, note=" (0 = off)"))
    diverge_share: float = checked(0.2, float_field(0, 1))
    diverge_loss_factor: float = checked(10.0, float_field(0, note=" (0 = off)"))

    def __post_init__(self) -> None:
        super().__post_init__()
        g = self.geometry
        if g.hard_fused and (g.hard_stride != 1 or self.raster.backend != "torch" or self.raster.antialiased):
            raise ValueError(
                "geometry.hard_fused: expected geometry.hard_stride 1, raster.backend 'torch' and no "
                f"antialiasing, got geometry.hard_stride {g.hard_stride}, backend "
                f"{self.raster.backend!r}, antialiased {self.raster.antialiased}"
            )

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (JSON-serialisable)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        """Inverse of :meth:`to_dict`, type-checked (:func:`vadgs.config.config_from_dict`).

        Raises:
            ValueError: on an unknown key or a value of the wrong type, naming the field's path
                (``config.strategy.refine_every: expected int, got str 'abc'``).

        Example:
            >>> c = TrainConfig(iterations=10)
            >>> TrainConfig.from_dict(c.to_dict()) == c
            True
        """
        from vadgs.config import config_from_dict

        return config_from_dict(cls, d)

    def replace(self, **changes: Any) -> TrainConfig:
        """A copy with changes; nested fields as ``"init.max_points"``."""
        flat = self.to_dict()
        for k, v in changes.items():
            parts = k.split(".")
            target = flat
            for p in parts[:-1]:
                target = target[p]
            if parts[-1] not in target:
                raise ValueError(f"config: unknown field {k!r}")
            target[parts[-1]] = v
        return TrainConfig.from_dict(flat)


SCHEDULE_ITERATIONS = 3000
"""The run length the step counts of the default schedule are set for (``TrainConfig.iterations``):
densification from step 500 every 100 steps, an opacity reset every 3000, the SH degree up every 1000."""

SCHEDULE_FIELDS = (
    "refine_start_iter",
    "refine_stop_iter",
    "refine_every",
    "reset_every",
    "pause_refine_after_reset",
)
"""The step counts of the strategy's config (:class:`~vadgs.train.strategy.DefaultStrategyConfig`)
that :func:`scale_schedule` scales."""


def scale_schedule(config: TrainConfig, reference: int = SCHEDULE_ITERATIONS) -> TrainConfig:
    """The schedule's step counts scaled to a run shorter than ``reference`` (gsplat's ``steps_scaler``).

    With ``f = config.iterations / reference < 1``, ``strategy.refine_start_iter``,
    ``refine_stop_iter``, ``refine_every``, ``reset_every``, ``pause_refine_after_reset`` and
    ``sh_degree_interval`` are multiplied by ``f`` (rounded; at least 1, and 0 stays 0;
    ``refine_every`` at least 10, or its own value if smaller, so that a refinement sees some
    gradient statistics), so a 300-step run densifies from step 50 every 10 steps as a 3000-step
    run does from 500 every 100.
    A run of ``reference`` steps or more is returned unchanged (the defaults are its schedule).

    Example:
        >>> c = scale_schedule(TrainConfig(iterations=300))
        >>> s = c.strategy
        >>> s.refine_start_iter, s.refine_every, s.reset_every, c.sh_degree_interval
        (50, 10, 300, 100)
        >>> scale_schedule(TrainConfig()) == TrainConfig()
        True
    """
    if reference < 1:
        raise ValueError(f"reference: expected >= 1, got {reference}")
    f = config.iterations / reference
    if f >= 1:
        return config

    def scaled(n: int) -> int:
        return max(1, round(n * f)) if n else 0

    changes: dict[str, Any] = {k: scaled(getattr(config.strategy, k)) for k in SCHEDULE_FIELDS}
    # at least 10 steps of gradient statistics between refinements (or the configured count if fewer)
    changes["refine_every"] = max(changes["refine_every"], min(config.strategy.refine_every, 10))
    strategy = dataclasses.replace(config.strategy, **changes)
    sh = scaled(config.sh_degree_interval)
    return dataclasses.replace(config, strategy=strategy, sh_degree_interval=sh)


def refine_steps(config: TrainConfig) -> range:
    """The steps at which the standard densification refines (before any pause after a reset).

    ``range(first, last, refine_every)``, empty when the run is too short to refine at all
    (e.g. ``iterations`` 300 with ``refine_start_iter`` 500).

    Example:
        >>> len(refine_steps(TrainConfig(iterations=300)))
        0
        >>> refine_steps(TrainConfig())[:3]
        range(600, 900, 100)
    """
    s = config.strategy
    first = (s.refine_start_iter // s.refine_every + 1) * s.refine_every
    return range(first, min(config.iterations, s.refine_stop_iter), s.refine_every)
