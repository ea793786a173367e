"""Adaptive density control of 3DGS (gsplat's ``DefaultStrategy``): clone, split, prune, reset opacity.

The interface it implements is :mod:`vadgs.train.strategy.base`'s.
"""

from __future__ import annotations

from collections.abc import Mapping, MutableMapping
from dataclasses import dataclass
from typing import Any, ClassVar

import torch

from vadgs.checks import Checked, bool_field, checked, float_field, int_field
from vadgs.train.strategy import ops
from vadgs.train.strategy.base import ConfiguredStrategy, StrategyStep

__all__ = ["GSPLAT_META", "DefaultStrategy", "DefaultStrategyConfig"]

GSPLAT_META = "the meta dict gsplat's rasterization() returns as its third output"
"""Where the gsplat keys of a loop's ``info`` come from (for the messages of
:func:`vadgs.train.vad.check_info`)."""


@dataclass(frozen=True)
class DefaultStrategyConfig(Checked):
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
        max_gaussians: never grow beyond this count (the largest gradients win; gsplat has no cap).
        split_factor: scale divisor of split children (gsplat hard-codes 1.6).
        pause_refine_after_reset: no densification in the first this many steps after each
            opacity reset, i.e. while ``step % reset_every < pause_refine_after_reset`` (gsplat's
            setting; 0, the default, never pauses).
    """

    prune_opa: float = checked(0.005, float_field(0, 1, hi_open=True))
    grow_grad2d: float = checked(0.0002, float_field(0))
    grow_scale3d: float = checked(0.01, float_field(0))
    prune_scale3d: float = checked(0.1, float_field(0, lo_open=True))
    refine_start_iter: int = checked(500, int_field(0))
    refine_stop_iter: int = checked(15_000, int_field(0))
    refine_every: int = checked(100, int_field(1))
    reset_every: int = checked(3000, int_field(0))
    reset_value: float = checked(0.01, float_field(0, 1))
    absgrad: bool = checked(False, bool_field())
    max_gaussians: int = checked(1_000_000, int_field(1))
    split_factor: float = checked(1.6, float_field(0, lo_open=True))
    pause_refine_after_reset: int = checked(0, int_field(0))


@dataclass(init=False, eq=False)
class DefaultStrategy(ConfiguredStrategy):
    """Standard ADC: clone/split by view-space gradient, prune by opacity and size, opacity reset.

    The state holds ``grad2d (N,)`` (summed gradient norms), ``count (N,)`` (times visible),
    ``scene_scale`` and ``num_resets``; ``generator_state`` is not kept here (the trainer's
    generator drives the splits, passed as ``info["generator"]``).

    Against ``gsplat.strategy.DefaultStrategy`` (``docs/train.md``; tested step by step): the same
    clone / split / prune decisions with the same settings and ``reset_value = 2 * prune_opa``,
    except that (1) gsplat <= 1.5.3 never resets opacities (its reset test
    ``step % reset_every == 0 & step > 0`` is always False; gsplat PR #776), (2) vadgs prunes by size
    after its first reset, gsplat once ``step > reset_every`` (the same steps whenever resets
    happen), (3) vadgs caps growth at ``max_gaussians`` and (4) has no 2D-scale rules nor
    ``revised_opacity``.

    Its settings are a :class:`DefaultStrategyConfig` in ``config``, given whole or as keywords
    (``DefaultStrategy(refine_every=50)``, as gsplat's is called) and readable / assignable as
    attributes, each checked (:class:`~vadgs.train.strategy.base.ConfiguredStrategy`).

    Args:
        config: :class:`DefaultStrategyConfig` (default: its defaults).
        **settings: fields of :class:`DefaultStrategyConfig` replaced in ``config``.
    """

    config_type: ClassVar[type[Any]] = DefaultStrategyConfig
    config: DefaultStrategyConfig

    def __init__(self, config: DefaultStrategyConfig | None = None, **settings: Any) -> None:
        self._take_config(config, settings)

    def info_keys(self, packed: bool = False) -> list[dict[str, str]]:
        """What the step methods read from ``info``: alternatives of ``{key: where it comes from}``.

        vadgs's render (``raster``, ``image_size``) or gsplat's meta (``means2d``, ``width``,
        ``height``, ``radii``; ``gaussian_ids`` too when ``packed``). The declaration
        :func:`vadgs.train.vad.check_info` checks a loop's ``info`` against.

        Example:
            >>> [sorted(a) for a in DefaultStrategy().info_keys()]
            [['image_size', 'raster'], ['height', 'means2d', 'radii', 'width']]
        """
        meta = dict.fromkeys(("means2d", "width", "height", "radii"), GSPLAT_META)
        if packed:
            meta["gaussian_ids"] = GSPLAT_META + " with packed=True"
        own = {
            "raster": "vadgs's rasterize_gaussians() output (RenderOutput)",
            "image_size": "the view's (H, W)",
        }
        return [own, meta]

    def initialize_state(self, scene_scale: float = 1.0) -> dict[str, Any]:
        """Statistics allocated at the first update; the scene scale for the size thresholds.

        Raises:
            ValueError: ``scene_scale`` is not a finite number > 0.
        """
        scene_scale = float_field(0, lo_open=True)("scene_scale", scene_scale)
        return {
            "grad2d": None,
            "count": None,
            "scene_scale": float(scene_scale),
            "num_resets": 0,
            "last_refine": {},
        }

    def check_sanity(self, params: MutableMapping[str, torch.Tensor] | Any, optimizers: Any) -> None:
        """Check ``params`` and ``optimizers`` before training (gsplat's ``check_sanity``).

        :func:`~vadgs.train.strategy.ops.check_params`: every per-Gaussian entry has the Gaussians
        as first dimension, the geometry has vadgs's or gsplat's names, every trainable entry has
        its optimizer.

        Raises:
            ValueError: naming the key, what was expected and what was found.

        Example:
            >>> geometry = ("means", "quats", "scales", "opacities")
            >>> params = {k: torch.zeros(4, 3, requires_grad=True) for k in geometry}
            >>> DefaultStrategy().check_sanity(params, {k: torch.optim.Adam([v]) for k, v in params.items()})
        """
        ops.check_params(params, optimizers)

    def pre_backward(self, call: StrategyStep) -> None:
        """Retain the gradient of the projected means (the rasterizer's ``means2d``).

        ``call.kwargs``: what another loop passes its strategies (gsplat's ``packed=``, ``lr=``), ignored.
        """
        info = call.info
        means2d = info["raster"].means2d if "raster" in info else info["means2d"]
        if means2d.requires_grad and not means2d.is_leaf:
            means2d.retain_grad()

    def post_backward(self, call: StrategyStep) -> None:
        """Accumulate the gradient statistics; densify, prune and reset opacities on schedule.

        ``call``: the step's ``params`` (vadgs's or gsplat's names), ``optimizers`` (vadgs's one
        optimizer with named groups, or gsplat's ``{name: optimizer}``), ``state`` (from
        :meth:`initialize_state`), ``step`` (the step just taken), ``info`` (vadgs's ``raster``,
        ``ids``, ``image_size``, ``generator``, or gsplat's meta) and ``kwargs``: ``packed=True``
        for gsplat's meta of ``rasterization(packed=True)`` (``means2d`` ``(nnz, 2)`` and ``radii``
        of the rows ``info["gaussian_ids"]``; unused with vadgs's ``info``); others (gsplat's MCMC
        ``lr=``) are ignored.
        """
        cfg, (params, optimizers, state, step, info, kwargs) = self.config, call
        if step >= cfg.refine_stop_iter:
            return
        self._update_state(params, state, info, bool(kwargs.get("packed", False)))
        paused = bool(cfg.reset_every) and step % cfg.reset_every < cfg.pause_refine_after_reset
        if step > cfg.refine_start_iter and step % cfg.refine_every == 0 and not paused:
            state["last_refine"] = self.refine(call)
        if cfg.reset_every and step > 0 and step % cfg.reset_every == 0:
            ops.reset_opacity(params, optimizers, cfg.reset_value)
            state["num_resets"] += 1

    @torch.no_grad()
    def _update_state(
        self, params: Mapping[str, torch.Tensor], state: dict[str, Any], info: dict[str, Any], packed: bool
    ) -> None:
        params = getattr(params, "params", params)
        packed = packed and "raster" not in info  # vadgs's own render is never packed
        if "raster" in info:  # vadgs: one camera, rows ``ids`` of the model
            raster = info["raster"]
            means2d, (h, w), cams = raster.means2d, info["image_size"], 1
            vis = raster.visible
        else:  # gsplat: (C, N, 2) means2d, radii (C, N) or (C, N, 2); packed: (nnz, 2), gaussian_ids
            means2d, h, w, cams = info["means2d"], info["height"], info["width"], info.get("n_cameras", 1)
            if packed and info.get("gaussian_ids") is None:
                raise ValueError(
                    "info['gaussian_ids']: expected the ids of gsplat's rasterization(packed=True) with "
                    f"packed=True, got {info.get('gaussian_ids', 'no such key')}"
                )
            radii = info["radii"]
            vis = None if packed else (radii > 0).all(-1) if radii.dim() == 3 else radii > 0
        grad = getattr(means2d, "absgrad", None) if self.config.absgrad else means2d.grad
        if grad is None:
            return
        n = params["means"].shape[0]
        dev = params["means"].device
        if state["grad2d"] is None:
            state["grad2d"] = torch.zeros(n, device=dev)
            state["count"] = torch.zeros(n, device=dev)
        g = grad * _pixels_row((w / 2.0 * cams, h / 2.0 * cams), grad)  # to pixels: (x, y) times these
        if packed:  # (nnz, 2): every packed row was rendered (gsplat counts them all)
            norms = g.norm(dim=-1).to(state["grad2d"].dtype)
            state["grad2d"].index_add_(0, info["gaussian_ids"], norms)
            state["count"].index_add_(0, info["gaussian_ids"], torch.ones_like(norms))
            return
        ids = info.get("ids")
        for c in range(g.shape[0]):
            # every row, the invisible ones adding 0 (no read of which rows are visible by the host)
            gid = torch.arange(g.shape[1], device=g.device) if ids is None else ids
            seen = vis[c]
            norms = torch.where(seen, g[c].norm(dim=-1), 0.0).to(state["grad2d"].dtype)
            state["grad2d"].index_add_(0, gid, norms)
            state["count"].index_add_(0, gid, seen.to(state["count"].dtype))

    @torch.no_grad()
    def refine(self, call: StrategyStep) -> dict[str, int]:
        """Grow (clone small / split large high-gradient Gaussians) then prune; resets the statistics.

        Of the step ``call`` (:meth:`post_backward`'s): its ``params``, ``optimizers`` and ``state``;
        the splits draw from ``info["generator"]`` when the ``info`` has one.

        Returns:
            ``{"cloned": .., "split": .., "pruned": .., "total": ..}``.
        """
        cfg, (params, optimizers, state) = self.config, call[:3]
        generator = call.info.get("generator")
        names = ops.param_names(params)
        p = getattr(params, "params", params)
        n = p[names.means].shape[0]
        if state["grad2d"] is None:  # no statistics yet
            grad2d = torch.zeros(n, device=p[names.means].device)
            state["grad2d"], state["count"] = grad2d, torch.zeros_like(grad2d)
        scale = state["scene_scale"]
        avg = state["grad2d"] / state["count"].clamp(min=1)
        cand = avg > cfg.grow_grad2d
        budget = max(cfg.max_gaussians - n, 0)
        if int(cand.sum()) > budget:
            top = torch.topk(torch.where(cand, avg, torch.zeros_like(avg)), budget).indices
            cand = torch.zeros_like(cand)
            cand[top] = True
        big = p[names.log_scales].exp().amax(-1) > cfg.grow_scale3d * scale
        is_dupli = cand & ~big
        is_split = cand & big
        n_dupli, n_split = int(is_dupli.sum()), int(is_split.sum())
        if n_dupli:
            ops.duplicate(params, optimizers, state, is_dupli)
            is_split = torch.cat([is_split, torch.zeros(n_dupli, dtype=torch.bool, device=is_split.device)])
        if n_split:
            ops.split(params, optimizers, state, is_split, generator, cfg.split_factor)
        opac = torch.sigmoid(p[names.opacity_logits])
        prune = opac < cfg.prune_opa
        if state["num_resets"] > 0:
            prune |= p[names.log_scales].exp().amax(-1) > cfg.prune_scale3d * scale
        n_prune = int(prune.sum())
        if n_prune:
            ops.remove_gaussians(params, optimizers, state, prune)
        state["grad2d"].zero_()
        state["count"].zero_()
        return {"cloned": n_dupli, "split": n_split, "pruned": n_prune, "total": p[names.means].shape[0]}


_ROWS: dict[tuple[Any, ...], torch.Tensor] = {}


def _pixels_row(values: tuple[float, float], like: torch.Tensor) -> torch.Tensor:
    """``values`` as a row on ``like``'s device and dtype, kept (one copy to the device a size)."""
    key = (values, like.device, like.dtype)
    row = _ROWS.get(key)
    if row is None:
        if len(_ROWS) > 64:
            _ROWS.clear()
        row = _ROWS[key] = torch.tensor(values, device=like.device, dtype=like.dtype)
    return row
