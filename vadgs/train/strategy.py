"""Densification strategies: the interface and the standard adaptive density control (3DGS / gsplat).

A strategy is an object with settings and *no hidden state*: its state lives in a dict that the
trainer owns, checkpoints and passes back (gsplat's ``Strategy``). The trainer calls

.. code-block:: python

    state = strategy.initialize_state(model, scene_scale)
    for step in ...:
        out = model.render(...)
        info = {"raster": out.raster, "ids": out.ids, "image_size": (H, W), "view": v, "frame": f, ...}
        strategy.step_pre_backward(model, optimizer, state, step, info)
        loss.backward()
        optimizer.step()
        strategy.step_post_backward(model, optimizer, state, step, info)  # may add / remove rows

Strategies change the set of Gaussians only through :mod:`vadgs.train.ops`, which keeps the
optimizer's moments, the model's node ids and every per-Gaussian tensor of ``state`` consistent.
A strategy may also contribute losses: the trainer adds the dict returned by
``strategy.extra_losses(model, state, step, info)`` when the strategy defines it (the next issue's
visibility-aware densification uses it for its normal and depth losses).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import torch

from vadgs.train import ops
from vadgs.train.model import GaussianModel

__all__ = ["DefaultStrategy", "DefaultStrategyConfig", "Strategy"]


@runtime_checkable
class Strategy(Protocol):
    """The interface every densification strategy implements.

    A strategy may append JSON-serialisable dicts to ``state["pending_log"]``: the trainer writes
    each as an ``{"step": ..., "event": ...}`` line of ``log.jsonl`` right after the step and
    removes them from the state.
    """

    def initialize_state(self, model: GaussianModel, scene_scale: float) -> dict[str, Any]:
        """A fresh state dict (per-Gaussian tensors have the model's row count as first dim)."""
        ...

    def step_pre_backward(
        self,
        model: GaussianModel,
        optimizer: torch.optim.Optimizer,
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
    ) -> None:
        """Called after the render, before ``loss.backward()``."""
        ...

    def step_post_backward(
        self,
        model: GaussianModel,
        optimizer: torch.optim.Optimizer,
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
    ) -> None:
        """Called after ``loss.backward()`` and ``optimizer.step()``; may add or remove Gaussians."""
        ...


@dataclass(frozen=True)
class DefaultStrategyConfig:
    """Settings of the standard adaptive density control (gsplat ``DefaultStrategy`` defaults).

    Attributes:
        prune_opa: prune Gaussians with opacity below this.
        grow_grad2d: densify Gaussians whose mean view-space gradient (NDC units, gsplat's
            normalisation: pixel gradient × W/2, H/2) exceeds this.
        grow_scale3d: clone if the largest scale ≤ ``grow_scale3d · scene_scale``, else split.
        prune_scale3d: after the first opacity reset, prune Gaussians larger than
            ``prune_scale3d · scene_scale``.
        refine_start_iter / refine_stop_iter: densify and prune in ``(start, stop)``.
        refine_every: densify every this many steps.
        reset_every: opacity reset interval (0 = never).
        reset_value: opacities are clamped to this at a reset (gsplat: ``2 · prune_opa``... 3DGS 0.01).
        absgrad: use the absolute gradient (``RasterConfig.absgrad`` must be on).
        max_gaussians: never grow beyond this count (the largest gradients win).
        split_factor: scale divisor of split children.
    """

    prune_opa: float = 0.005
    grow_grad2d: float = 0.0002
    grow_scale3d: float = 0.01
    prune_scale3d: float = 0.1
    refine_start_iter: int = 500
    refine_stop_iter: int = 15_000
    refine_every: int = 100
    reset_every: int = 3000
    reset_value: float = 0.01
    absgrad: bool = False
    max_gaussians: int = 1_000_000
    split_factor: float = 1.6

    def __post_init__(self) -> None:
        if self.refine_every < 1:
            raise ValueError(f"refine_every: expected >= 1, got {self.refine_every}")
        if self.max_gaussians < 1:
            raise ValueError(f"max_gaussians: expected >= 1, got {self.max_gaussians}")


class DefaultStrategy:
    """Standard ADC: clone/split by view-space gradient, prune by opacity and size, opacity reset.

    The state holds ``grad2d (N,)`` (summed gradient norms), ``count (N,)`` (times visible),
    ``scene_scale`` and ``num_resets``; ``generator_state`` is not kept here (the trainer's
    generator drives the splits, passed as ``info["generator"]``).

    Args:
        config: :class:`DefaultStrategyConfig`.
    """

    def __init__(self, config: DefaultStrategyConfig | None = None) -> None:
        self.config = config or DefaultStrategyConfig()

    def initialize_state(self, model: GaussianModel, scene_scale: float) -> dict[str, Any]:
        """Zero statistics for the model's Gaussians."""
        n = model.num_gaussians
        dev = model.params["means"].device
        return {
            "grad2d": torch.zeros(n, device=dev),
            "count": torch.zeros(n, device=dev),
            "scene_scale": float(scene_scale),
            "num_resets": 0,
            "last_refine": {},
        }

    def step_pre_backward(
        self,
        model: GaussianModel,
        optimizer: torch.optim.Optimizer,
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
    ) -> None:
        """Nothing to do: the renderer already retains the gradient of ``means2d``."""
        raster = info["raster"]
        if raster.means2d.requires_grad and not raster.means2d.is_leaf:
            raster.means2d.retain_grad()

    def step_post_backward(
        self,
        model: GaussianModel,
        optimizer: torch.optim.Optimizer,
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
    ) -> None:
        """Accumulate the gradient statistics; densify, prune and reset opacities on schedule."""
        cfg = self.config
        if step >= cfg.refine_stop_iter:
            return
        self._update_state(state, info)
        if step > cfg.refine_start_iter and step % cfg.refine_every == 0:
            state["last_refine"] = self.refine(model, optimizer, state, step, info.get("generator"))
        if cfg.reset_every and step > 0 and step % cfg.reset_every == 0:
            ops.reset_opacity(model, optimizer, cfg.reset_value)
            state["num_resets"] += 1

    @torch.no_grad()
    def _update_state(self, state: dict[str, Any], info: dict[str, Any]) -> None:
        raster = info["raster"]
        grad = raster.means2d_absgrad if self.config.absgrad else raster.means2d.grad
        if grad is None:
            return
        h, w = info["image_size"]
        g = grad[0].clone()
        g[:, 0] *= w / 2.0
        g[:, 1] *= h / 2.0
        vis = raster.visible[0]
        ids = info["ids"][vis]
        state["grad2d"].index_add_(0, ids, g[vis].norm(dim=-1).to(state["grad2d"].dtype))
        state["count"].index_add_(0, ids, torch.ones_like(ids, dtype=state["count"].dtype))

    @torch.no_grad()
    def refine(
        self,
        model: GaussianModel,
        optimizer: torch.optim.Optimizer,
        state: dict[str, Any],
        step: int,
        generator: torch.Generator | None = None,
    ) -> dict[str, int]:
        """Grow (clone small / split large high-gradient Gaussians) then prune; resets the statistics.

        Returns:
            ``{"cloned": .., "split": .., "pruned": .., "total": ..}``.
        """
        cfg = self.config
        scale = state["scene_scale"]
        avg = state["grad2d"] / state["count"].clamp(min=1)
        cand = avg > cfg.grow_grad2d
        budget = max(cfg.max_gaussians - model.num_gaussians, 0)
        if int(cand.sum()) > budget:
            top = torch.topk(torch.where(cand, avg, torch.zeros_like(avg)), budget).indices
            cand = torch.zeros_like(cand)
            cand[top] = True
        big = model.params["log_scales"].exp().amax(-1) > cfg.grow_scale3d * scale
        is_dupli = cand & ~big
        is_split = cand & big
        n_dupli, n_split = int(is_dupli.sum()), int(is_split.sum())
        if n_dupli:
            ops.duplicate(model, optimizer, state, is_dupli)
            is_split = torch.cat([is_split, torch.zeros(n_dupli, dtype=torch.bool, device=is_split.device)])
        if n_split:
            ops.split(model, optimizer, state, is_split, generator, cfg.split_factor)
        opac = torch.sigmoid(model.params["opacity_logits"])
        prune = opac < cfg.prune_opa
        if state["num_resets"] > 0:
            prune |= model.params["log_scales"].exp().amax(-1) > cfg.prune_scale3d * scale
        n_prune = int(prune.sum())
        if n_prune:
            ops.remove_gaussians(model, optimizer, state, prune)
        state["grad2d"].zero_()
        state["count"].zero_()
        return {"cloned": n_dupli, "split": n_split, "pruned": n_prune, "total": model.num_gaussians}
