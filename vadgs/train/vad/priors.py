"""The geometric priors of the losses: MVS depth and normals of the reconstructed views (Sec. 3.4).

:func:`merge_priors` keeps each event's MVS depth and normals in the strategy's state
(``state["vad_priors"]``); the strategy's ``geometry_targets`` reads them back as the targets of
:func:`vadgs.train.losses.geometric_losses`.
"""

from __future__ import annotations

import torch

from vadgs.train.vad.reconstruct import (
    InstanceReconstruction,
)

__all__ = [
    "merge_priors",
]


def merge_priors(priors: dict[int, tuple[torch.Tensor, torch.Tensor]], rec: InstanceReconstruction) -> None:
    """Keep the MVS depth and normals of ``rec``'s views in ``priors`` (``state["vad_priors"]``).

    Where a view already has priors, the new ones replace them only where the new depth exists.
    """
    for v, d, n in zip(rec.views, rec.depth, rec.normal):
        old = priors.get(v)
        if old is not None:
            has = d > 0
            d = torch.where(has, d, old[0])
            n = torch.where(has, n, old[1])
        priors[v] = (d, n)
