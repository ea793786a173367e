"""Add and remove Gaussians together with their optimizer state (gsplat ``strategy/ops.py``).

Every function here works on a **params mapping** in gsplat's sense — a
:class:`~torch.nn.ParameterDict` (or dict) of per-Gaussian tensors that all have the number of
Gaussians ``N`` as first dimension — and keeps consistent with it (1) the Adam moments
``exp_avg`` / ``exp_avg_sq`` of those parameters and (2) every per-Gaussian tensor of a strategy
``state`` dict (a tensor whose first dimension is ``N``, e.g. accumulated gradients). New rows start
with zero moments and zero statistics; kept rows keep theirs. Entries without an optimizer (such as
vadgs's integer ``node_ids``) follow the rows without moments, as in gsplat.

Two parameter layouts are recognised by their names (:func:`param_names`):

- vadgs's :class:`~vadgs.train.model.GaussianModel` (``model.params``): ``means``, ``quats``,
  ``log_scales``, ``opacity_logits``, ``sh_dc``, ``sh_rest``, ``node_ids`` and ``provenance``;
- gsplat's: ``means``, ``quats``, ``scales`` (log), ``opacities`` (logits), ``sh0``, ``shN`` —
  or, with gsplat's appearance optimisation, ``features`` and ``colors`` instead of the SH.

Only the geometry (means, quats, scales, opacities) must be present; every other per-Gaussian
entry (gsplat's ``features`` / ``colors``, any extra key) is kept, duplicated, split and removed
generically with the rows, as gsplat's ``strategy/ops.py`` does: a clone or a split child copies
its parent's row, removal drops it.

``optimizers`` is either one optimizer with a named param group per parameter (vadgs's
:func:`~vadgs.train.model.make_optimizer`) or gsplat's dict ``{name: optimizer}``.

Nothing here knows vadgs's model, as nothing in gsplat's ``strategy/ops.py`` does: pass
``model.params``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, MutableMapping
from typing import Any, NamedTuple, Union, cast

import torch
from torch import nn

from vadgs.geometry.rotation import quaternion_to_rotation

__all__ = [
    "GSPLAT_NAMES",
    "VADGS_NAMES",
    "ParamNames",
    "add_gaussians",
    "check_params",
    "duplicate",
    "param_names",
    "remove_gaussians",
    "reset_opacity",
    "split",
    "update_params",
]

#: ``torch.optim.Optimizer`` with named groups, or gsplat's ``{name: optimizer}``.
Optimizers = Union[torch.optim.Optimizer, Mapping[str, torch.optim.Optimizer], None]  # noqa: UP007

#: A params mapping: gsplat's dict or :class:`~torch.nn.ParameterDict` of per-Gaussian tensors.
Params = Union[MutableMapping[str, torch.Tensor], nn.ParameterDict]  # noqa: UP007


class ParamNames(NamedTuple):
    """The names of the Gaussian parameters in a params mapping (all stored raw).

    ``sh_dc`` / ``sh_rest`` are None in a layout without spherical harmonics (gsplat's appearance
    layout, ``features`` + ``colors``).
    """

    means: str
    quats: str
    log_scales: str
    opacity_logits: str
    sh_dc: str | None
    sh_rest: str | None


VADGS_NAMES = ParamNames("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")
GSPLAT_NAMES = ParamNames("means", "quats", "scales", "opacities", "sh0", "shN")


def _params(params: Any) -> Params:
    """``params``, checked to be a mapping (a read-only one fails at the first write)."""
    if isinstance(params, (Mapping, nn.ParameterDict)):
        return cast(Params, params)
    raise TypeError(
        "params: expected a params mapping (a dict or ParameterDict of per-Gaussian tensors, e.g. "
        f"model.params), got {type(params).__name__}"
    )


def param_names(params: Params | Mapping[str, torch.Tensor]) -> ParamNames:
    """The layout of a params mapping: :data:`VADGS_NAMES` or :data:`GSPLAT_NAMES`.

    Recognised by the geometry names (means, quats, scales, opacities); the SH names are None when
    absent (gsplat's appearance layout: ``features`` and ``colors``). Other keys are allowed.

    Raises:
        ValueError: if the geometry names match neither layout.

    Example:
        >>> param_names({k: None for k in ("means", "quats", "scales", "opacities", "sh0", "shN")}).sh_dc
        'sh0'
        >>> appearance = ("means", "quats", "scales", "opacities", "features", "colors")
        >>> param_names(dict.fromkeys(appearance)).sh_dc is None
        True
    """
    keys = set(_params(params).keys())
    for names in (VADGS_NAMES, GSPLAT_NAMES):
        if set(names[:4]) <= keys:
            sh = (names.sh_dc, names.sh_rest) if {names.sh_dc, names.sh_rest} <= keys else (None, None)
            return ParamNames(*names[:4], *sh)
    raise ValueError(
        f"params: expected vadgs names {list(VADGS_NAMES[:4])} or gsplat names {list(GSPLAT_NAMES[:4])} "
        f"(plus any other per-Gaussian entries), got {sorted(keys)}"
    )


def _num_rows(params: Params) -> int:
    return int(params["means"].shape[0])


def _group(optimizers: Optimizers, name: str) -> tuple[torch.optim.Optimizer, dict] | None:
    """The optimizer and param group that hold parameter ``name`` (None: not optimised)."""
    if optimizers is None:
        return None
    if isinstance(optimizers, Mapping):
        opt = optimizers.get(name)
        return (opt, opt.param_groups[0]) if opt is not None else None
    for g in optimizers.param_groups:
        if g.get("name") == name:
            return optimizers, g
    return None


def check_params(params: Params | Mapping[str, torch.Tensor], optimizers: Optimizers) -> None:
    """Check that ``params`` and ``optimizers`` agree (a strategy's ``check_sanity``).

    Every per-Gaussian entry must have the Gaussians as first dimension; the geometry must be
    vadgs's or gsplat's names (:func:`param_names`); each trainable entry must have its optimizer
    (gsplat's dict ``{name: optimizer}`` with one param group holding that tensor, or one
    optimizer with a param group named for it).

    Raises:
        ValueError: naming the key, what was expected and what was found.

    Example:
        >>> geometry = ("means", "quats", "scales", "opacities")
        >>> params = {k: torch.zeros(4, 3, requires_grad=True) for k in geometry}
        >>> check_params(params, {k: torch.optim.Adam([v]) for k, v in params.items()})  # gsplat's layout
        >>> check_params(params, None)
        Traceback (most recent call last):
        ...
        ValueError: optimizers: expected an optimizer of params['means'], got None
    """
    p = _params(params)
    names = param_names(p)
    n = int(p[names.means].shape[0])
    for k, v in p.items():
        if not isinstance(v, torch.Tensor) or v.dim() == 0 or v.shape[0] != n:
            got = tuple(v.shape) if isinstance(v, torch.Tensor) else type(v).__name__
            raise ValueError(f"params[{k!r}]: expected a tensor of {n} rows (the Gaussians), got {got}")
    for k, v in p.items():
        if not v.requires_grad:
            continue
        if optimizers is None:
            raise ValueError(f"optimizers: expected an optimizer of params[{k!r}], got None")
        if isinstance(optimizers, Mapping):
            opt = optimizers.get(k)
            if opt is None:
                raise ValueError(f"optimizers: expected a key {k!r}, got keys {sorted(optimizers)}")
            groups = opt.param_groups
            if len(groups) != 1 or len(groups[0]["params"]) != 1 or groups[0]["params"][0] is not v:
                raise ValueError(
                    f"optimizers[{k!r}]: expected one param group holding params[{k!r}], got "
                    f"{len(groups)} group(s) of {[len(g['params']) for g in groups]} tensor(s)"
                )
        else:
            group = next((g for g in optimizers.param_groups if g.get("name") == k), None)
            if group is None or not any(q is v for q in group["params"]):
                named = [g.get("name") for g in optimizers.param_groups]
                raise ValueError(
                    f"optimizers: expected a param group named {k!r} holding params[{k!r}], "
                    f"got groups {named}"
                )


@torch.no_grad()
def update_params(
    params: Params,
    optimizers: Optimizers,
    state: dict | None,
    param_fn: Callable[[str, torch.Tensor], torch.Tensor],
    moment_fn: Callable[[str, torch.Tensor], torch.Tensor],
    row_fn: Callable[[torch.Tensor], torch.Tensor],
    names: tuple[str, ...] | None = None,
) -> None:
    """The primitive all ops are built on: replace parameters, their moments and per-row tensors.

    Args:
        params: params mapping, updated in place (new :class:`~torch.nn.Parameter` objects).
        optimizers: their groups get the new parameters, with moments ``moment_fn(name, moment)``.
        state: strategy state; each tensor with first dimension ``N`` becomes ``row_fn(tensor)``.
        param_fn: ``(name, old) -> new`` data of every entry in ``names``.
        moment_fn: ``(name, old_moment) -> new_moment``.
        row_fn: applied to the per-Gaussian tensors of ``state``.
        names: the entries to update (default all: the row count changes only when all are).
    """
    params = _params(params)
    n_old = _num_rows(params)
    every = names is None or set(names) >= set(params.keys())
    for name in list(params.keys()) if names is None else names:
        old = params[name]
        new = nn.Parameter(param_fn(name, old.data), requires_grad=old.requires_grad)
        found = _group(optimizers, name)
        if found is not None:
            opt, group = found
            st = opt.state.pop(old, None)
            group["params"][0] = new
            if st:
                opt.state[new] = {
                    k: (moment_fn(name, v) if k in ("exp_avg", "exp_avg_sq") else v) for k, v in st.items()
                }
        params[name] = new
    if every and state is not None:
        for k, v in state.items():
            if isinstance(v, torch.Tensor) and v.dim() > 0 and v.shape[0] == n_old:
                state[k] = row_fn(v)


def _zero_rows(t: torch.Tensor, m: int) -> torch.Tensor:
    return torch.zeros((m, *t.shape[1:]), dtype=t.dtype, device=t.device)


def remove_gaussians(
    params: Params,
    optimizers: Optimizers,
    state: dict | None,
    mask: torch.Tensor,
) -> None:
    """Remove the Gaussians where ``mask`` is True (parameters, moments, node ids, state rows).

    Args:
        params: params mapping, updated in place.
        optimizers: their moments follow (None: parameters only).
        state: strategy state whose per-Gaussian rows follow (or None).
        mask: ``(N,)`` bool.

    Example:
        >>> params = {"means": torch.randn(5, 3), "quats": torch.rand(5, 4), "scales": torch.zeros(5, 3),
        ...           "opacities": torch.zeros(5)}  # gsplat's names
        >>> remove_gaussians(params, None, None, torch.tensor([True, False, True, False, False]))
        >>> params["means"].shape[0]
        3
    """
    params = _params(params)
    _check_mask(params, mask)
    keep = ~mask
    update_params(params, optimizers, state, lambda _, p: p[keep], lambda _, v: v[keep], lambda t: t[keep])


def duplicate(
    params: Params,
    optimizers: Optimizers,
    state: dict | None,
    mask: torch.Tensor,
) -> None:
    """Clone the Gaussians where ``mask`` is True (3DGS "clone"); copies are appended at the end.

    The copies have the same parameters and node; their moments and state rows start at zero.
    """
    params = _params(params)
    _check_mask(params, mask)
    sel = torch.nonzero(mask).squeeze(1)
    update_params(
        params,
        optimizers,
        state,
        lambda _, p: torch.cat([p, p[sel]]),
        lambda _, v: torch.cat([v, torch.zeros_like(v[sel])]),
        lambda t: torch.cat(
            [t, t[sel] if t.dtype in (torch.int64, torch.int32, torch.bool) else torch.zeros_like(t[sel])]
        ),
    )


def split(
    params: Params,
    optimizers: Optimizers,
    state: dict | None,
    mask: torch.Tensor,
    generator: torch.Generator | None = None,
    factor: float = 1.6,
) -> None:
    """Split the Gaussians where ``mask`` is True into two each (3DGS "split").

    Each child is sampled from the parent's Gaussian (in its node's frame) and gets the parent's
    scale divided by ``factor``; the parents are removed and the children appended at the end.
    Children's moments and state rows start at zero.

    Args:
        params: params mapping, updated in place.
        optimizers: their moments follow (None: parameters only).
        state: strategy state whose per-Gaussian rows follow (or None).
        mask: ``(N,)`` bool, the parents.
        generator: for the samples (keep it in the checkpoint for exact resume); a CPU generator
            (the samples are drawn on the CPU and moved to the parameters' device).
        factor: scale divisor (3DGS: 1.6).
    """
    p = params = _params(params)
    _check_mask(params, mask)
    names = param_names(params)
    sel = torch.nonzero(mask).squeeze(1)
    keep = ~mask
    scales = p[names.log_scales].data[sel].exp()
    rot = quaternion_to_rotation(torch.nn.functional.normalize(p[names.quats].data[sel], dim=-1))
    noise = torch.randn((2, sel.numel(), 3), generator=generator, dtype=scales.dtype).to(scales.device)
    offsets = (rot[None] @ (noise * scales[None])[..., None]).squeeze(-1)  # (2, S, 3)
    new_means = (p[names.means].data[sel][None] + offsets).reshape(-1, 3)
    log_factor = torch.log(torch.tensor(factor, dtype=scales.dtype, device=scales.device))

    def param_fn(name: str, old: torch.Tensor) -> torch.Tensor:
        if name == names.means:
            child = new_means
        elif name == names.log_scales:
            child = (old[sel] - log_factor).repeat(2, 1)
        else:
            child = old[sel].repeat(2, *([1] * (old.dim() - 1)))
        return torch.cat([old[keep], child])

    def row_fn(t: torch.Tensor) -> torch.Tensor:
        child = t[sel].repeat(2, *([1] * (t.dim() - 1)))
        if t.dtype not in (torch.int64, torch.int32, torch.bool):
            child = torch.zeros_like(child)
        return torch.cat([t[keep], child])

    update_params(
        params,
        optimizers,
        state,
        param_fn,
        lambda _, v: torch.cat([v[keep], torch.zeros_like(v[sel]).repeat(2, *([1] * (v.dim() - 1)))]),
        row_fn,
    )


def add_gaussians(
    params: Params,
    optimizers: Optimizers,
    state: dict | None,
    new: dict[str, torch.Tensor],
    node_ids: torch.Tensor | None = None,
    num_nodes: int | None = None,
) -> None:
    """Append new Gaussians (e.g. from MVS points), with zero moments and zero state rows.

    Args:
        params: params mapping, updated in place.
        optimizers: their moments follow (None: parameters only).
        state: strategy state whose per-Gaussian rows follow (or None).
        new: raw parameters of the new Gaussians, every key of ``params`` (``node_ids`` and
            ``provenance`` may be left out; ``provenance`` defaults to ``0``), with the same
            trailing shapes (moved to each parameter's device and dtype);
            ``means`` in the world for static Gaussians, in the object frame for a track node.
        node_ids: ``(M,)`` int64, ``-1`` static or a track node index, when ``params`` has
            ``node_ids`` (overrides ``new["node_ids"]``; default: static).
        num_nodes: the number of track nodes (vadgs's ``model.object_to_world.shape[0]``), when
            known: the node ids must then be below it.

    Raises:
        ValueError: on a missing key, a wrong shape, or a node id below ``-1`` or not below
            ``num_nodes``.

    Example:
        >>> params = {"means": torch.zeros(2, 3), "quats": torch.ones(2, 4), "log_scales": torch.zeros(2, 3),
        ...           "opacity_logits": torch.zeros(2), "node_ids": torch.tensor([-1, 0])}  # vadgs's names
        >>> new = {"means": torch.ones(3, 3), "quats": torch.ones(3, 4), "log_scales": torch.ones(3, 3),
        ...        "opacity_logits": torch.ones(3)}
        >>> add_gaussians(params, None, None, new, node_ids=torch.tensor([0, 0, -1]), num_nodes=1)
        >>> params["means"].shape[0], params["node_ids"].tolist()
        (5, [-1, 0, 0, 0, -1])
    """
    p = params = _params(params)
    first = next(iter(new.values()), None)
    m = int(first.shape[0]) if first is not None else 0
    new = dict(new)
    if node_ids is not None:
        new["node_ids"] = node_ids
    elif "node_ids" in p and "node_ids" not in new:
        new["node_ids"] = torch.full((m,), -1, dtype=torch.int64, device=p["node_ids"].device)
    if "provenance" in p and "provenance" not in new:
        new["provenance"] = torch.zeros((m,), dtype=torch.int64, device=p["provenance"].device)
    missing = [k for k in p.keys() if k not in new]
    if missing:
        raise ValueError(f"new: missing {missing}")
    for k in p.keys():
        want = (m, *p[k].shape[1:])
        if tuple(new[k].shape) != want:
            raise ValueError(f"new[{k!r}]: expected shape {want}, got {tuple(new[k].shape)}")
    if num_nodes is not None and "node_ids" in p and m:
        nid = new["node_ids"]
        lo, hi = int(nid.min()), int(nid.max())
        if lo < -1 or hi >= num_nodes:
            raise ValueError(f"node_ids: expected values in [-1, {num_nodes}), got [{lo}, {hi}]")
    update_params(
        params,
        optimizers,
        state,
        lambda name, old: torch.cat([old, new[name].to(old)]),
        lambda _, v: torch.cat([v, _zero_rows(v, m)]),
        lambda t: torch.cat([t, _zero_rows(t, m)]),
    )


def reset_opacity(params: Params, optimizers: Optimizers, value: float) -> None:
    """Clamp every opacity to at most ``value`` (3DGS opacity reset) and zero its moments."""
    params = _params(params)
    name = param_names(params).opacity_logits
    logit = float(torch.logit(torch.tensor(value)))
    update_params(
        params,
        optimizers,
        None,
        lambda _, p: p.clamp(max=logit),
        lambda _, v: torch.zeros_like(v),
        lambda t: t,
        names=(name,),
    )


def _check_mask(params: Any, mask: torch.Tensor) -> None:
    n = _num_rows(_params(params))
    if mask.dtype != torch.bool or tuple(mask.shape) != (n,):
        raise ValueError(f"mask: expected bool ({n},), got {mask.dtype} {tuple(mask.shape)}")
