"""Training-view sampling without replacement (paper, "Implementation Details").

One *sampling cycle* visits every training view exactly once in a random order; the next cycle
draws a fresh permutation. The sampler's state (generator, current permutation, position, cycle)
goes into checkpoints, so a resumed run draws the very same views.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch

__all__ = ["ViewSampler"]


class ViewSampler:
    """Seeded sampling of views without replacement, cycle by cycle.

    Args:
        view_ids: the training views.
        seed: seed of the permutations.

    Example:
        >>> s = ViewSampler([3, 5, 7], seed=0)
        >>> sorted(s.next() for _ in range(3)), s.cycle
        ([3, 5, 7], 1)
    """

    def __init__(self, view_ids: Sequence[int], seed: int = 0) -> None:
        if len(view_ids) == 0:
            raise ValueError("view_ids: expected at least one training view, got none")
        self.view_ids = [int(v) for v in view_ids]
        self.generator = torch.Generator().manual_seed(int(seed))
        self.order: list[int] = []
        self.pos = 0
        self.cycle = 0

    def __len__(self) -> int:
        return len(self.view_ids)

    def next(self) -> int:
        """The next view; a new permutation starts when the current cycle is exhausted."""
        if self.pos >= len(self.order):
            perm = torch.randperm(len(self.view_ids), generator=self.generator).tolist()
            self.order = [self.view_ids[i] for i in perm]
            self.pos = 0
        v = self.order[self.pos]
        self.pos += 1
        if self.pos == len(self.order):
            self.cycle += 1
        return v

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue the same sequence."""
        return {
            "view_ids": list(self.view_ids),
            "generator": self.generator.get_state(),
            "order": list(self.order),
            "pos": self.pos,
            "cycle": self.cycle,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`.

        Raises:
            ValueError: if the stored views differ from this sampler's.
        """
        if [int(v) for v in state["view_ids"]] != self.view_ids:
            raise ValueError("sampler state: the stored training views differ from this scene's")
        self.generator.set_state(state["generator"])
        self.order = [int(v) for v in state["order"]]
        self.pos = int(state["pos"])
        self.cycle = int(state["cycle"])
