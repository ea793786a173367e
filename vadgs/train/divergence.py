"""When a run has gone wrong: non-finite values and divergence, each an error naming the step.

:class:`DivergenceMonitor` watches a run from what the loop already has: the colour loss of each
step (a running mean that explodes far above its lowest value) and, now and then, the static
Gaussians' means (too large a share flown far from the cameras). :class:`~vadgs.train.trainer.Trainer`
calls it after every step; a raised error leaves the last good checkpoint untouched.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

__all__ = ["DivergenceError", "DivergenceMonitor", "NonFiniteLossError"]


class NonFiniteLossError(FloatingPointError):
    """A loss or parameter became NaN / infinite; ``step`` says when."""

    def __init__(self, step: int, what: str) -> None:
        super().__init__(f"non-finite value at step {step}: {what}")
        self.step = step


class DivergenceError(FloatingPointError):
    """The model diverged (Gaussians flew out of the scene, or the loss exploded); ``step`` says when."""

    def __init__(self, step: int, what: str) -> None:
        super().__init__(f"training diverged at step {step}: {what}")
        self.step = step


@dataclass
class DivergenceMonitor:
    """Raise :class:`DivergenceError` when a run diverges (the ``diverge_*`` fields of ``TrainConfig``).

    Attributes:
        centre: ``(3,)`` the training cameras' mean centre.
        scene_scale: the scene's scale (the cameras' extent).
        distance: a static Gaussian is *far* beyond ``distance`` x ``scene_scale`` from ``centre``
            (0: no test).
        share: the run diverged when more than this share of the static Gaussians is far.
        loss_factor: ... or when the running mean of the colour loss exceeds this many times its
            lowest value, after the first sampling cycle (0: no test).

    Example:
        >>> m = DivergenceMonitor(torch.zeros(3), 1.0, distance=10.0, share=0.2, loss_factor=10.0)
        >>> m.check(1, 0.1, torch.zeros(5, 3), warm=False, test_means=True)
        >>> m.check(2, 0.1, torch.full((5, 3), 100.0), warm=False, test_means=True)
        Traceback (most recent call last):
        ...
        vadgs.train.divergence.DivergenceError: training diverged at step 2: 100% of the static ...
    """

    centre: torch.Tensor
    scene_scale: float
    distance: float = 100.0
    share: float = 0.2
    loss_factor: float = 10.0
    _ema: float | None = field(default=None, init=False, repr=False)
    _lowest: float = field(default=math.inf, init=False, repr=False)

    def check(
        self, step: int, color: float | None, static_means: torch.Tensor | None, warm: bool, test_means: bool
    ) -> None:
        """One step's test.

        Args:
            step: the step done (for the message).
            color: its colour loss (on the host), or None.
            static_means: ``(N, 3)`` the static Gaussians' means (read only when ``test_means``).
            warm: the first sampling cycle is over (the loss test starts then).
            test_means: test the means at this step (one reduction; the loop does it now and then).
        """
        if self.loss_factor > 0 and color is not None:
            self._ema = color if self._ema is None else 0.9 * self._ema + 0.1 * color
            if warm:
                if self._ema > self.loss_factor * max(self._lowest, 1e-4):
                    raise DivergenceError(
                        step,
                        f"the colour loss exploded (running mean {self._ema:.4g}, more than "
                        f"{self.loss_factor:g} x its lowest {self._lowest:.4g})",
                    )
                self._lowest = min(self._lowest, self._ema)
        if self.distance <= 0 or not test_means or static_means is None or static_means.shape[0] == 0:
            return
        with torch.no_grad():
            far = (static_means - self.centre.to(static_means)).norm(
                dim=-1
            ) > self.distance * self.scene_scale
            share = float(far.float().mean())
        if share > self.share:
            raise DivergenceError(
                step,
                f"{share:.0%} of the static Gaussians are farther than {self.distance:g} x "
                f"the scene scale ({self.distance * self.scene_scale:.4g}) from the cameras' "
                f"centre (limit {self.share:.0%}; a learning rate too high?)",
            )
