"""Densification strategies, as gsplat's ``gsplat/strategy/``: one module per strategy.

- :mod:`~vadgs.train.strategy.base`: the interface every strategy implements (:class:`Strategy`,
  :class:`GeometryPriors`) and the shape of vadgs's own (:class:`ConfiguredStrategy`, whose step methods hand
  their arguments to the subclass as one :class:`StrategyStep`);
- :mod:`~vadgs.train.strategy.default`: adaptive density control of 3DGS (:class:`DefaultStrategy`);
- :mod:`~vadgs.train.strategy.ops`: the row operations (add, remove, split, duplicate, reset) that
  keep the optimizer moments and the strategy state in step.

VAD-GS's strategy is in :mod:`vadgs.train.vad`. Add a strategy as a module here.
"""

from vadgs.train.strategy.base import (
    ConfiguredStrategy,
    GeometryPriors,
    Strategy,
    StrategyStep,
    initialize_base_state,
)
from vadgs.train.strategy.default import DefaultStrategy, DefaultStrategyConfig

__all__ = [
    "ConfiguredStrategy",
    "DefaultStrategy",
    "DefaultStrategyConfig",
    "GeometryPriors",
    "Strategy",
    "StrategyStep",
    "initialize_base_state",
]
