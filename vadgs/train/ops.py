"""Add and remove Gaussians together with their optimizer state (gsplat ``strategy/ops.py``).

Every function here changes the per-Gaussian parameters of a
:class:`~vadgs.train.model.GaussianModel` *and*, consistently, (1) the Adam moments
``exp_avg`` / ``exp_avg_sq`` of those parameters in the optimizer, (2) the model's per-Gaussian
buffers (``node_ids``) and (3) every per-Gaussian tensor of a strategy ``state`` dict (a tensor
whose first dimension is the number of Gaussians, e.g. accumulated gradients). New rows start with
zero moments and zero statistics; kept rows keep theirs.

The optimizer must have one param group per per-Gaussian parameter, with the parameter's name in
the group's ``"name"`` (:func:`make_optimizer` builds one).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from vadgs.render import quaternion_to_rotation
from vadgs.train.model import PER_GAUSSIAN, GaussianModel

__all__ = [
    "add_gaussians",
    "duplicate",
    "make_optimizer",
    "remove_gaussians",
    "reset_opacity",
    "split",
    "update_params",
]


def make_optimizer(model: GaussianModel, lrs: dict[str, float], eps: float = 1e-15) -> torch.optim.Adam:
    """One Adam with a named param group per parameter (per-Gaussian ones and ``"sky"``).

    Args:
        model: the model.
        lrs: learning rate per name (:data:`~vadgs.train.model.PER_GAUSSIAN` and ``"sky"``).
        eps: Adam epsilon (3DGS uses 1e-15).

    Example:
        >>> from vadgs.train.model import GaussianModel
        >>> m = GaussianModel(torch.zeros(4, 3), torch.zeros(4, 3), torch.zeros(4, 3), torch.full((4,), -1),
        ...                   torch.zeros(0, 1, 4, 4), torch.zeros(0, 1, dtype=torch.bool), [], sh_degree=0)
        >>> opt = make_optimizer(m, dict.fromkeys([*PER_GAUSSIAN, "sky"], 1e-3))
        >>> [g["name"] for g in opt.param_groups][:2]
        ['means', 'quats']
    """
    missing = [k for k in (*PER_GAUSSIAN, "sky") if k not in lrs]
    if missing:
        raise ValueError(f"lrs: missing learning rates for {missing}")
    groups = [{"params": [model.params[k]], "lr": lrs[k], "name": k} for k in PER_GAUSSIAN]
    groups.append({"params": [model.sky], "lr": lrs["sky"], "name": "sky"})
    return torch.optim.Adam(groups, eps=eps)


def _group(optimizer: torch.optim.Optimizer, name: str) -> dict:
    for g in optimizer.param_groups:
        if g.get("name") == name:
            return g
    raise ValueError(f"optimizer: no param group named {name!r}")


@torch.no_grad()
def update_params(
    model: GaussianModel,
    optimizer: torch.optim.Optimizer | None,
    state: dict | None,
    param_fn: Callable[[str, torch.Tensor], torch.Tensor],
    moment_fn: Callable[[str, torch.Tensor], torch.Tensor],
    row_fn: Callable[[torch.Tensor], torch.Tensor],
    names: tuple[str, ...] = PER_GAUSSIAN,
) -> None:
    """The primitive all ops are built on: replace parameters, their moments and per-row tensors.

    Args:
        model: updated in place (new :class:`~torch.nn.Parameter` objects).
        optimizer: its groups get the new parameters, with moments ``moment_fn(name, moment)``.
        state: strategy state; each tensor with first dimension ``N`` becomes ``row_fn(tensor)``.
        param_fn: ``(name, old) -> new`` parameter data.
        moment_fn: ``(name, old_moment) -> new_moment``.
        row_fn: applied to ``node_ids`` and to the per-Gaussian tensors of ``state``.
        names: the parameters to update (the row count changes only when all are updated).
    """
    n_old = model.num_gaussians
    for name in names:
        old = model.params[name]
        new = nn.Parameter(param_fn(name, old.data), requires_grad=old.requires_grad)
        if optimizer is not None:
            group = _group(optimizer, name)
            st = optimizer.state.pop(old, None)
            group["params"][0] = new
            if st:
                optimizer.state[new] = {
                    k: (moment_fn(name, v) if k in ("exp_avg", "exp_avg_sq") else v) for k, v in st.items()
                }
        model.params[name] = new
    if set(names) == set(PER_GAUSSIAN):
        model.node_ids = row_fn(model.node_ids)
        if state is not None:
            for k, v in state.items():
                if isinstance(v, torch.Tensor) and v.dim() > 0 and v.shape[0] == n_old:
                    state[k] = row_fn(v)


def remove_gaussians(
    model: GaussianModel, optimizer: torch.optim.Optimizer | None, state: dict | None, mask: torch.Tensor
) -> None:
    """Remove the Gaussians where ``mask`` is True (parameters, moments, node ids, state rows).

    Args:
        model: updated in place.
        optimizer: its moments follow (None: parameters only).
        state: strategy state whose per-Gaussian rows follow (or None).
        mask: ``(N,)`` bool.

    Example:
        >>> m = GaussianModel(torch.randn(5, 3), torch.rand(5, 3), torch.zeros(5, 3), torch.full((5,), -1),
        ...                   torch.zeros(0, 1, 4, 4), torch.zeros(0, 1, dtype=torch.bool), [], sh_degree=0)
        >>> remove_gaussians(m, None, None, torch.tensor([True, False, True, False, False]))
        >>> m.num_gaussians
        3
    """
    _check_mask(model, mask)
    keep = ~mask
    update_params(model, optimizer, state, lambda _, p: p[keep], lambda _, v: v[keep], lambda t: t[keep])


def duplicate(
    model: GaussianModel, optimizer: torch.optim.Optimizer | None, state: dict | None, mask: torch.Tensor
) -> None:
    """Clone the Gaussians where ``mask`` is True (3DGS "clone"); copies are appended at the end.

    The copies have the same parameters and node; their moments and state rows start at zero.
    """
    _check_mask(model, mask)
    sel = torch.nonzero(mask).squeeze(1)
    update_params(
        model,
        optimizer,
        state,
        lambda _, p: torch.cat([p, p[sel]]),
        lambda _, v: torch.cat([v, torch.zeros_like(v[sel])]),
        lambda t: torch.cat(
            [t, t[sel] if t.dtype in (torch.int64, torch.int32, torch.bool) else torch.zeros_like(t[sel])]
        ),
    )


def split(
    model: GaussianModel,
    optimizer: torch.optim.Optimizer | None,
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
        model: updated in place.
        optimizer: its moments follow (None: parameters only).
        state: strategy state whose per-Gaussian rows follow (or None).
        mask: ``(N,)`` bool, the parents.
        generator: for the samples (keep it in the checkpoint for exact resume).
        factor: scale divisor (3DGS: 1.6).
    """
    _check_mask(model, mask)
    sel = torch.nonzero(mask).squeeze(1)
    keep = ~mask
    p = model.params
    scales = p["log_scales"].data[sel].exp()
    rot = quaternion_to_rotation(torch.nn.functional.normalize(p["quats"].data[sel], dim=-1))
    noise = torch.randn((2, sel.numel(), 3), generator=generator, dtype=scales.dtype).to(scales.device)
    offsets = (rot[None] @ (noise * scales[None])[..., None]).squeeze(-1)  # (2, S, 3)
    new_means = (p["means"].data[sel][None] + offsets).reshape(-1, 3)

    def param_fn(name: str, old: torch.Tensor) -> torch.Tensor:
        if name == "means":
            child = new_means
        elif name == "log_scales":
            child = (old[sel] - torch.log(torch.tensor(factor, dtype=old.dtype))).repeat(2, 1)
        else:
            child = old[sel].repeat(2, *([1] * (old.dim() - 1)))
        return torch.cat([old[keep], child])

    def row_fn(t: torch.Tensor) -> torch.Tensor:
        child = t[sel].repeat(2, *([1] * (t.dim() - 1)))
        if t.dtype not in (torch.int64, torch.int32, torch.bool):
            child = torch.zeros_like(child)
        return torch.cat([t[keep], child])

    update_params(
        model,
        optimizer,
        state,
        param_fn,
        lambda _, v: torch.cat([v[keep], torch.zeros_like(v[sel]).repeat(2, *([1] * (v.dim() - 1)))]),
        row_fn,
    )


def add_gaussians(
    model: GaussianModel,
    optimizer: torch.optim.Optimizer | None,
    state: dict | None,
    params: dict[str, torch.Tensor],
    node_ids: torch.Tensor,
) -> None:
    """Append new Gaussians (e.g. from MVS points) to a node, with zero moments and state rows.

    Args:
        model: updated in place.
        optimizer: its moments follow (None: parameters only).
        state: strategy state whose per-Gaussian rows follow (or None).
        params: raw parameters of the new Gaussians, every key of
            :data:`~vadgs.train.model.PER_GAUSSIAN` with the model's trailing shapes; ``means``
            in the world for static Gaussians, in the object frame for a track node.
        node_ids: ``(M,)`` int64, ``-1`` static or a track node index.

    Example:
        >>> m = GaussianModel(torch.randn(2, 3), torch.rand(2, 3), torch.zeros(2, 3), torch.full((2,), -1),
        ...                   torch.zeros(0, 1, 4, 4), torch.zeros(0, 1, dtype=torch.bool), [], sh_degree=0)
        >>> new = {k: torch.zeros(3, *v.shape[1:]) for k, v in m.params.items()}
        >>> add_gaussians(m, None, None, new, torch.full((3,), -1))
        >>> m.num_gaussians
        5
    """
    missing = [k for k in PER_GAUSSIAN if k not in params]
    if missing:
        raise ValueError(f"params: missing {missing}")
    m = node_ids.shape[0]
    for k in PER_GAUSSIAN:
        want = (m, *model.params[k].shape[1:])
        if tuple(params[k].shape) != want:
            raise ValueError(f"params[{k!r}]: expected shape {want}, got {tuple(params[k].shape)}")
    num_tracks = model.object_to_world.shape[0]
    if m and (int(node_ids.min()) < -1 or int(node_ids.max()) >= num_tracks):
        raise ValueError(
            f"node_ids: expected values in [-1, {num_tracks}), "
            f"got [{int(node_ids.min())}, {int(node_ids.max())}]"
        )

    def row_fn(t: torch.Tensor) -> torch.Tensor:
        if t is model.node_ids:
            return torch.cat([t, node_ids.to(t)])
        return torch.cat([t, torch.zeros((m, *t.shape[1:]), dtype=t.dtype, device=t.device)])

    update_params(
        model,
        optimizer,
        state,
        lambda name, p: torch.cat([p, params[name].to(p)]),
        lambda _, v: torch.cat([v, torch.zeros((m, *v.shape[1:]), dtype=v.dtype, device=v.device)]),
        row_fn,
    )


def reset_opacity(model: GaussianModel, optimizer: torch.optim.Optimizer | None, value: float) -> None:
    """Clamp every opacity to at most ``value`` (3DGS opacity reset) and zero its moments."""
    logit = float(torch.logit(torch.tensor(value)))
    update_params(
        model,
        optimizer,
        None,
        lambda _, p: p.clamp(max=logit),
        lambda _, v: torch.zeros_like(v),
        lambda t: t,
        names=("opacity_logits",),
    )


def _check_mask(model: GaussianModel, mask: torch.Tensor) -> None:
    if mask.dtype != torch.bool or tuple(mask.shape) != (model.num_gaussians,):
        raise ValueError(
            f"mask: expected bool ({model.num_gaussians},), got {mask.dtype} {tuple(mask.shape)}"
        )
