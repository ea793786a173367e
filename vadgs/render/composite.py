r"""Front-to-back alpha compositing of tile-binned screen Gaussians, with a hand-written backward.

Each pixel ``p`` composites the depth-sorted Gaussians of its tile:

.. math::

    \alpha_i = \min(\alpha_{max}, o_i e^{-\sigma_i(p)}), \quad
    \sigma_i = \tfrac12 (a\,dx^2 + c\,dy^2) + b\,dx\,dy, \quad
    R(p) = \sum_i f_i \alpha_i T_i, \quad T_i = \prod_{j<i} (1 - \alpha_j)

with gsplat's rules: a Gaussian with ``alpha < alpha_min`` (1/255) is skipped, and a pixel stops
*before* the Gaussian that would bring its transmittance to ``transmittance_min`` (1e-4) or
below; that Gaussian and every later one are left out.

How it runs fast in pure torch (see ``docs/render.md`` for the measurements):

- Tiles of 8×8 pixels walk their depth-sorted lists in padded chunks of ``chunk_size`` Gaussians;
  all tiles advance together, one chunk per step, carrying each pixel's transmittance from chunk
  to chunk. A tile leaves the loop when its list ends or when every pixel in it has stopped
  (tile-level early exit), so the work follows the real per-tile depth complexity. When few
  tiles are left the chunk grows (:func:`_chunk_size`), so the few tiles with the longest lists
  do not take most of the steps.
- Within a chunk, the Gaussian exponent is a quadratic polynomial in the tile-local pixel
  coordinates, so ``log o_i - sigma_i(p)`` for all pixels and Gaussians of all tiles is one
  batched matmul of six per-pixel monomials with six per-Gaussian coefficients.
- Transmittances come from a cumulative *sum* of ``log(1 - alpha)`` (much cheaper than
  ``cumprod`` on CPU); the weights are differences of neighbouring transmittances; the rare
  pixels that stop or cross the median are fixed up on their own rows.
- The backward pass recomputes each chunk in the same front-to-back order and needs only the
  final colour and transmittance of each pixel (no per-Gaussian-per-pixel state is stored):
  with ``s_i = f_i · dL/dR`` and ``Q_i = sum_{j<=i} w_j s_j``,

  .. math::

      \frac{\partial L}{\partial \alpha_i} = T_i s_i
      - \frac{R \cdot \partial_R L - Q_i + T_{final}\, \partial_{T_{final}} L}{1 - \alpha_i}.

  An autograd version of the same loop (:func:`_composite_autograd`) is kept as the measured
  alternative and as a cross-check in the tests.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F

from vadgs.render.tiles import TileBins

__all__ = ["CompositeOutput", "composite_gaussians"]

_PAD = -1e30  # log-opacity of padding slots: exp() of it is exactly zero
_LOG_TINY = -80.0  # exp(-80) = 1.8e-35: clamp exponents here to stay off exp's slow path
_TINY = 1e-30
_MAX_CHUNK_GROWTH = 32  # the chunk grows to at most this many times chunk_size (_chunk_size)
_STEP_SLOTS = 4096  # below this many tile x Gaussian slots a step's fixed cost dominates (_chunk_size)


class CompositeOutput(NamedTuple):
    """Composited images, tile layout removed.

    Attributes:
        features: ``(B, F, H, W)`` ``sum_i w_i f_i`` (no background).
        transmittance: ``(B, 1, H, W)`` final transmittance (1 - accumulated opacity).
        median_ids: ``(B, H, W)`` int64 per-camera index of the Gaussian at which the
            transmittance first drops to 0.5 or below, ``-1`` where it never does.
    """

    features: torch.Tensor
    transmittance: torch.Tensor
    median_ids: torch.Tensor


class _Setup(NamedTuple):
    """Everything the chunk loop needs that is not a differentiable input."""

    gauss_ids: torch.Tensor
    tile_starts: torch.Tensor
    tile_counts: torch.Tensor
    tile_ox: torch.Tensor  # (n_tiles,) x of the tile origin, float
    tile_oy: torch.Tensor
    pix: torch.Tensor  # (P, 6) monomials of tile-local pixel coordinates
    init_t: torch.Tensor  # (n_tiles, P) 1 inside the image, 0 on the overhang
    chunk: int
    log_alpha_max: float
    alpha_max_value: float
    alpha_floor: float  # largest value below alpha_min: threshold keeps x > floor
    t_min: float
    clamp: bool


def _pixel_monomials(tile_size: int, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    p = torch.arange(tile_size * tile_size, device=device)
    u = (p % tile_size).to(dtype)
    v = (p // tile_size).to(dtype)
    return torch.stack([u * u, v * v, u * v, u, v, torch.ones_like(u)], dim=-1)


def _make_setup(
    bins: TileBins,
    b: int,
    image_size: tuple[int, int],
    params: torch.Tensor,
    alpha_max: float,
    alpha_min: float,
    transmittance_min: float,
    chunk_size: int,
) -> _Setup:
    device, dtype = params.device, params.dtype
    th, tw = bins.grid
    ts = bins.tile_size
    h, w = image_size
    tile = torch.arange(b * th * tw, device=device)
    tile_ox = ((tile % tw) * ts).to(dtype)
    tile_oy = (((tile // tw) % th) * ts).to(dtype)
    pix = _pixel_monomials(ts, device, dtype)
    inside = ((tile_ox[:, None] + pix[:, 3]) < w) & ((tile_oy[:, None] + pix[:, 4]) < h)
    floor = torch.nextafter(torch.tensor(alpha_min, dtype=dtype), torch.tensor(0.0, dtype=dtype))
    cap = torch.tensor(alpha_max, dtype=dtype)
    clamp = bool((params[:, 5] > math.log(alpha_max)).any()) if params.numel() else False
    return _Setup(
        bins.gauss_ids,
        bins.tile_starts,
        bins.tile_counts,
        tile_ox,
        tile_oy,
        pix,
        inside.to(dtype),
        chunk_size,
        math.log(alpha_max),
        float(torch.exp(torch.log(cap))),
        float(floor),
        transmittance_min,
        clamp,
    )


def _take(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Rows ``x[idx]`` for any index shape (``index_select`` is ~4x faster than ``x[idx]``)."""
    return x.index_select(0, idx.reshape(-1)).reshape(*idx.shape, *x.shape[1:])


def _chunk_size(s: _Setup, n: int, n0: int) -> int:
    """Gaussians per tile in the next step, with ``n`` of the first step's ``n0`` tiles active.

    The base ``chunk_size``, doubled while a step would hold fewer than ``_STEP_SLOTS`` tile x
    Gaussian slots, the first step's buffers can hold the doubled step (``n * c <= n0 *
    chunk_size``) and the growth stays within ``_MAX_CHUNK_GROWTH``. A step has a fixed cost of
    some twenty small ops; without the growth the few tiles with the longest lists take most of
    the steps (while most other tiles have stopped), with it they finish in far fewer
    (``docs/benchmarks.md``, "the compositor's growing chunks"). Where most tiles are still active (the first
    steps, large images) the chunk stays: a larger one only adds slots after pixels have stopped.
    """
    c = s.chunk
    while c * n < _STEP_SLOTS and 2 * c * n <= n0 * s.chunk and c < s.chunk * _MAX_CHUNK_GROWTH:
        c *= 2
    return c


def _buffer(flat: torch.Tensor, *shape: int) -> torch.Tensor:
    """The first ``prod(shape)`` elements of the flat buffer ``flat`` as a tensor of ``shape``."""
    return flat[: math.prod(shape)].view(shape)


def _gather_chunk(s: _Setup, table: torch.Tensor, active: torch.Tensor, start: int, c: int):
    """Ids, table rows and exponent coefficients of list slots ``start .. start + c`` of the active tiles.

    ``table (B * N, 6 + F)`` holds ``x, y, a, b, c, log o`` and the features of each Gaussian.
    Returns ``gid (n, C)``, ``rows (n, C, 6 + F)``, the tile-local means ``mu, mv`` and
    ``coef (n, 6, C + 1)``: column 0 is a slot that the transmittance carried in from earlier
    chunks overwrites, columns ``1..C`` the coefficients of ``log o - sigma`` on the pixel
    monomials ``(u^2, v^2, uv, u, v, 1)``.
    """
    slot = torch.arange(c, device=active.device)
    left = _take(s.tile_counts, active) - start
    valid = slot < left[:, None]  # (n, C)
    idx = (_take(s.tile_starts, active) + start)[:, None] + slot
    idx = torch.where(valid, idx, torch.zeros_like(idx))
    gid = _take(s.gauss_ids, idx)  # (n, C)
    rows = _take(table, gid)  # (n, C, 6 + F)
    mu = rows[..., 0] - _take(s.tile_ox, active)[:, None]
    mv = rows[..., 1] - _take(s.tile_oy, active)[:, None]
    a, bb, cc = rows[..., 2], rows[..., 3], rows[..., 4]
    logo = torch.where(valid, rows[..., 5], torch.full_like(mu, _PAD))
    c3 = a * mu + bb * mv
    c4 = cc * mv + bb * mu
    coef = torch.stack([-0.5 * a, -0.5 * cc, -bb, c3, c4, logo - 0.5 * (mu * c3 + mv * c4)], dim=1)
    coef = F.pad(coef, (1, 0))  # (n, 6, C + 1) with a zero first column
    return gid, rows, mu, mv, coef


def _chunk_weights(s: _Setup, coef: torch.Tensor, t0: torch.Tensor, e: torch.Tensor, w: torch.Tensor, a=None):
    """Fill ``e`` with transmittances and ``w`` with weights of one chunk (in place).

    ``e (n, P, C + 1)``: ``e[..., j]`` is the transmittance before Gaussian ``j`` and
    ``e[..., C]`` after the chunk (ignoring the stop rule); ``w (n, P, C)`` the weights
    ``alpha_j T_j``. When ``a`` is given it receives the alphas.
    """
    torch.matmul(s.pix, coef, out=e)  # log o - sigma
    # exp() takes a slow path far below its underflow point (10x slower on x86), so clamp to
    # _LOG_TINY first and zero the tiny results after: alphas below alpha_min are skipped and
    # transmittances below 1e-30 are past the stop rule, so both clamps change nothing.
    e.clamp_(min=_LOG_TINY, max=s.log_alpha_max if s.clamp else None)
    e.exp_()
    torch.threshold_(e, s.alpha_floor, 0.0)  # alpha; column 0 is exp(0) and gets overwritten
    if a is not None:
        a.copy_(e[..., 1:])
    e.neg_().log1p_()
    e[..., 0] = torch.log(t0)
    e.cumsum_(-1).clamp_min_(_LOG_TINY).exp_()
    torch.threshold_(e, _TINY, 0.0)
    torch.sub(e[..., :-1], e[..., 1:], out=w)


def _stop_rows(s: _Setup, e: torch.Tensor, t0: torch.Tensor):
    """Pixels that stop in this chunk: (tile rows, pixel cols, keep mask (r, C), T at stop)."""
    stop = (e[..., -1] <= s.t_min) & (t0 > 0)
    rt, rp = stop.nonzero(as_tuple=True)
    er = e[rt, rp]  # (r, C + 1)
    keep = er[:, 1:] > s.t_min  # a prefix
    t_stop = er.gather(1, keep.sum(-1, keepdim=True)).squeeze(1)
    return rt, rp, keep, t_stop


def _median_rows(e: torch.Tensor, t_min: float):
    """Pixels whose transmittance crosses 0.5 in this chunk and the slot where it does."""
    cross = (e[..., 0] > 0.5) & (e[..., -1] <= 0.5)
    rt, rp = cross.nonzero(as_tuple=True)
    er = e[rt, rp]
    slot = (er[:, 1:] > 0.5).sum(-1)
    # The crossing Gaussian counts only if the stop rule did not drop it first.
    ok = er.gather(1, (slot + 1)[:, None]).squeeze(1) > t_min
    return rt[ok], rp[ok], slot[ok]


def _finished(s: _Setup, act: torch.Tensor, t_cur: torch.Tensor, end: int) -> torch.Tensor:
    """Tiles whose list ends before slot ``end`` or whose pixels have all stopped."""
    return (_take(s.tile_counts, act) <= end) | ~(t_cur > 0).any(-1)


def _forward_loop(s: _Setup, table: torch.Tensor):
    """Run the chunk loop; returns ``(tiles, F, P)`` outputs, final transmittance, median ids."""
    n_tiles, p = s.init_t.shape
    device, dtype = table.device, table.dtype
    out = torch.zeros(n_tiles, table.shape[-1] - 6, p, device=device, dtype=dtype)
    t_out = s.init_t.clone()
    t_stop = torch.full_like(t_out, -1.0)
    median = torch.full((n_tiles, p), -1, device=device, dtype=torch.long)
    act = (s.tile_counts > 0).nonzero(as_tuple=True)[0]
    acc = _take(out, act)
    t_cur = _take(s.init_t, act)
    n0 = act.numel()
    e_buf = torch.empty(n0 * p * (s.chunk + 1), device=device, dtype=dtype)
    w_buf = torch.empty(n0 * p * s.chunk, device=device, dtype=dtype)
    f_buf = torch.empty_like(acc)
    start = 0
    while act.numel():
        n = act.numel()
        c = _chunk_size(s, n, n0)
        gid, rows, _, _, coef = _gather_chunk(s, table, act, start, c)
        e, w = _buffer(e_buf, n, p, c + 1), _buffer(w_buf, n, p, c)
        _chunk_weights(s, coef, t_cur, e, w)
        t_new = e[..., -1].clone()
        rt, rp, keep, ts = _stop_rows(s, e, t_cur)
        if rt.numel():
            w[rt, rp] = w[rt, rp] * keep
            t_new[rt, rp] = 0.0
            t_stop[act[rt], rp] = ts
        mt, mp, slot = _median_rows(e, s.t_min)
        if mt.numel():
            median[act[mt], mp] = gid[mt, slot]
        # (F, C) @ (C, P) per tile: much faster on CPU than (P, C) @ (C, F), and no allocation.
        acc += torch.bmm(rows[..., 6:].transpose(1, 2), w.transpose(1, 2), out=f_buf[:n])
        t_cur = t_new
        start += c
        fin = _finished(s, act, t_cur, start)
        if bool(fin.any()):
            done, kept = fin.nonzero(as_tuple=True)[0], (~fin).nonzero(as_tuple=True)[0]
            out.index_copy_(0, act[done], _take(acc, done))
            t_out.index_copy_(0, act[done], _take(t_cur, done))
            act, acc, t_cur = act[kept], _take(acc, kept), _take(t_cur, kept)
    t_final = torch.where(t_stop >= 0, t_stop, t_out)
    # Overhang pixels (outside the image) started at zero; give them T = 1 for consistency.
    t_final = torch.where(s.init_t > 0, t_final, torch.ones_like(t_final))
    return out, t_final, median


def _backward_loop(
    s: _Setup,
    table: torch.Tensor,
    out: torch.Tensor,
    t_final: torch.Tensor,
    g_out: torch.Tensor,
    g_t: torch.Tensor,
    absgrad: torch.Tensor | None,
) -> torch.Tensor:
    """Recompute the chunks front to back; returns the gradient of ``table``."""
    p = s.init_t.shape[1]
    device, dtype = table.device, table.dtype
    d_table = torch.zeros_like(table)
    act = (s.tile_counts > 0).nonzero(as_tuple=True)[0]
    t_cur = _take(s.init_t, act)
    g_r = _take(g_out, act)  # (n, F, P)
    # K = R . dL/dR + T_final dL/dT_final minus what the Gaussians already visited took:
    # the "everything behind" term of dL/dalpha; zero for pixels that have stopped.
    k_rem = ((_take(out, act) * g_r).sum(1) + _take(t_final * g_t, act)) * (t_cur > 0)
    n0 = act.numel()
    e_buf = torch.empty(n0 * p * (s.chunk + 1), device=device, dtype=dtype)
    w_buf, a_buf, s_buf, q_buf = (torch.empty(n0 * p * s.chunk, device=device, dtype=dtype) for _ in range(4))
    start = 0
    while act.numel():
        n = act.numel()
        c = _chunk_size(s, n, n0)  # the forward's schedule: same tiles, same transmittances
        gid, rows, mu, mv, coef = _gather_chunk(s, table, act, start, c)
        a, bb, cc = rows[..., 2], rows[..., 3], rows[..., 4]
        e, w, alpha = _buffer(e_buf, n, p, c + 1), _buffer(w_buf, n, p, c), _buffer(a_buf, n, p, c)
        _chunk_weights(s, coef, t_cur, e, w, alpha)
        t_new = e[..., -1].clone()
        rt, rp, keep, _ = _stop_rows(s, e, t_cur)
        if rt.numel():
            w[rt, rp] = w[rt, rp] * keep
            t_new[rt, rp] = 0.0
        feat_t = rows[..., 6:].transpose(1, 2)  # (n, F, C)
        q = torch.bmm(g_r.transpose(1, 2), feat_t, out=_buffer(s_buf, n, p, c)).mul_(w)  # w_i f_i . dL/dR
        x = torch.cumsum(q, -1, out=_buffer(q_buf, n, p, c))
        k_next = k_rem - x[..., -1]
        torch.sub(k_rem.unsqueeze(-1), x, out=x)  # behind-term after each Gaussian
        if s.clamp:
            unclamped = alpha < s.alpha_max_value
        r = alpha.neg_().add_(1.0).reciprocal_().sub_(1.0)  # alpha / (1 - alpha)
        dg = torch.sub(q, x.mul_(r), out=x)  # dL / d(log o - sigma)
        if rt.numel():
            dg[rt, rp] = dg[rt, rp] * keep
        if s.clamp:
            dg.masked_fill_(~unclamped, 0.0)
        dcoef = torch.matmul(s.pix.T, dg)  # (n, 6, C)
        dc0, dc1, dc2, dc3, dc4, dc5 = dcoef.unbind(1)
        hx = dc3 - dc5 * mu
        hy = dc4 - dc5 * mv
        d_rows = torch.cat(
            [
                torch.stack(
                    [
                        a * hx + bb * hy,
                        bb * hx + cc * hy,
                        -0.5 * dc0 + mu * (dc3 - 0.5 * dc5 * mu),
                        -dc2 + dc3 * mv + dc4 * mu - dc5 * mu * mv,
                        -0.5 * dc1 + mv * (dc4 - 0.5 * dc5 * mv),
                        dc5,
                    ],
                    dim=-1,
                ),
                torch.bmm(g_r, w).transpose(1, 2),  # dL/df: (n, C, F)
            ],
            dim=-1,
        )
        flat = gid.reshape(-1)
        d_table.index_add_(0, flat, d_rows.reshape(flat.numel(), -1))
        if absgrad is not None:
            # Per-pixel d(log o - sigma)/d(mean) = (a du + b dv, b du + c dv), du = u - mu.
            lin = torch.stack([a, bb, -(a * mu + bb * mv), bb, cc, -(bb * mu + cc * mv)], dim=1)
            gx = torch.matmul(s.pix[:, 3:], lin[:, 0:3])  # (n, P, C)
            gy = torch.matmul(s.pix[:, 3:], lin[:, 3:6])
            ab = torch.stack([(dg * gx).abs_().sum(1), (dg * gy).abs_().sum(1)], dim=-1)
            absgrad.index_add_(0, flat, ab.reshape(-1, 2))
        t_cur = t_new
        k_rem = k_next * (t_cur > 0)
        start += c
        fin = _finished(s, act, t_cur, start)
        if bool(fin.any()):
            kept = (~fin).nonzero(as_tuple=True)[0]
            act, t_cur, k_rem, g_r = act[kept], _take(t_cur, kept), _take(k_rem, kept), _take(g_r, kept)
    return d_table


class _CompositeFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, params, features, setup, absgrad):
        table = torch.cat([params, features], dim=-1)
        out, t_final, median = _forward_loop(setup, table)
        ctx.setup = setup
        ctx.absgrad = absgrad
        ctx.save_for_backward(table, out, t_final)
        ctx.mark_non_differentiable(median)
        return out, t_final, median

    @staticmethod
    def backward(ctx, g_out, g_t, _g_median):
        table, out, t_final = ctx.saved_tensors
        s = ctx.setup
        g_out = torch.zeros_like(out) if g_out is None else g_out.contiguous()
        g_t = torch.zeros_like(t_final) if g_t is None else g_t
        g_t = g_t * s.init_t  # overhang pixels do not take part
        d_table = _backward_loop(s, table, out, t_final, g_out, g_t, ctx.absgrad)
        return d_table[:, :6], d_table[:, 6:], None, None


def _composite_autograd(params: torch.Tensor, features: torch.Tensor, s: _Setup):
    """The same chunk loop written with differentiable torch ops, for autograd.

    Kept as the measured alternative to the hand-written backward (benchmarks) and as a
    cross-check (tests). Same outputs as :class:`_CompositeFn`, no absgrad.
    """
    n_tiles, p = s.init_t.shape
    out = torch.zeros(n_tiles, features.shape[-1], p, device=params.device, dtype=params.dtype)
    t_cur = s.init_t.clone()
    done = torch.zeros_like(t_cur, dtype=torch.bool)
    t_stop = torch.ones_like(t_cur)
    counts = s.tile_counts
    active = (counts > 0).nonzero(as_tuple=True)[0]
    table = torch.cat([params, features], -1)
    n0 = active.numel()
    start = 0
    while active.numel():
        c = _chunk_size(s, active.numel(), n0)
        _, rows, _, _, coef = _gather_chunk(s, table, active, start, c)
        g = torch.matmul(s.pix, coef[..., 1:])
        if s.clamp:
            g = torch.clamp_max(g, s.log_alpha_max)
        alpha = F.threshold(torch.exp(g), s.alpha_floor, 0.0)
        t0 = t_cur[active] * ~done[active]
        t_incl = t0.unsqueeze(-1) * torch.cumprod(1.0 - alpha, -1)
        t_excl = torch.cat([t0.unsqueeze(-1), t_incl[..., :-1]], -1)
        inc = t_incl > s.t_min
        w = alpha * t_excl * inc
        out = out.index_add(0, active, torch.bmm(rows[..., 6:].transpose(1, 2), w.transpose(1, 2)))
        stopped = (~inc[..., -1]) & (t0 > 0)
        t_at_stop = t0 - w.sum(-1)
        t_stop = t_stop.index_put((active,), torch.where(stopped, t_at_stop, t_stop[active]))
        t_cur = t_cur.index_put((active,), torch.where(stopped, t_cur[active], t_incl[..., -1]))
        done = done.index_put((active,), done[active] | stopped)
        start += c
        active = active[counts[active] > start]
    t_final = torch.where(done, t_stop, t_cur)
    t_final = torch.where(s.init_t > 0, t_final, torch.ones_like(t_final))
    return out, t_final


def composite_gaussians(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    bins: TileBins,
    image_size: tuple[int, int],
    alpha_max: float = 0.999,
    alpha_min: float = 1.0 / 255.0,
    transmittance_min: float = 1e-4,
    chunk_size: int = 32,
    absgrad: torch.Tensor | None = None,
    backward: str = "manual",
) -> CompositeOutput:
    """Composite binned screen Gaussians front to back (see the module docstring).

    Differentiable w.r.t. means2d, conics, opacities and features (hand-written backward); the
    median ids are not.

    Args:
        means2d: ``(B, N, 2)`` screen means in pixels.
        conics: ``(B, N, 3)`` inverse screen covariances ``(a, b, c)``.
        opacities: ``(B, N)`` opacities in ``(0, 1]`` (zero only for Gaussians in no tile).
        features: ``(B, N, F)`` per-camera features to composite (colour, depth, normal, ...).
        bins: tile lists from :func:`vadgs.render.tiles.bin_gaussians`.
        image_size: ``(H, W)``.
        alpha_max: alpha cap (gsplat: 0.999; the original 3DGS: 0.99).
        alpha_min: Gaussians with ``alpha < alpha_min`` at a pixel are skipped.
        transmittance_min: a pixel stops before transmittance would reach this.
        chunk_size: Gaussians per tile per step.
        absgrad: optional ``(B, N, 2)`` buffer; the backward adds to it the sum over pixels of
            the absolute per-pixel gradient w.r.t. ``means2d`` (gsplat's ``absgrad``).
        backward: ``"manual"`` (hand-written backward) or ``"autograd"`` (the same loop under
            autograd; slower, more memory, no absgrad).

    Returns:
        The :class:`CompositeOutput`.

    Example:
        >>> from vadgs.render.tiles import bin_gaussians
        >>> m = torch.tensor([[[4.0, 4.0]]]); r = torch.tensor([[[6, 6]]], dtype=torch.int32)
        >>> bins = bin_gaussians(m, r, torch.ones(1, 1), (8, 8))
        >>> out = composite_gaussians(m, torch.tensor([[[0.5, 0.0, 0.5]]]), torch.tensor([[0.8]]),
        ...                           torch.ones(1, 1, 1), bins, (8, 8))
        >>> round(out.features[0, 0, 4, 4].item(), 4), round(out.transmittance[0, 0, 4, 4].item(), 4)
        (0.8, 0.2)
    """
    b, n = means2d.shape[:2]
    h, w = image_size
    params = torch.cat(
        [means2d.reshape(b * n, 2), conics.reshape(b * n, 3), torch.log(opacities.reshape(b * n, 1))], dim=-1
    )
    feats = features.reshape(b * n, features.shape[-1])
    s = _make_setup(bins, b, image_size, params.detach(), alpha_max, alpha_min, transmittance_min, chunk_size)
    if backward == "manual":
        ab = None if absgrad is None else absgrad.view(b * n, 2)
        out, t_final, median = _CompositeFn.apply(params, feats, s, ab)
    elif backward == "autograd":
        out, t_final = _composite_autograd(params, feats, s)
        with torch.no_grad():
            median = _forward_loop(s, torch.cat([params, feats], -1))[2]
    else:
        raise ValueError(f"backward: expected 'manual' or 'autograd', got {backward!r}")
    th, tw = bins.grid
    ts = bins.tile_size

    def untile(x: torch.Tensor) -> torch.Tensor:  # (b*th*tw, C, P) -> (b, C, H, W)
        c = x.shape[1]
        x = x.reshape(b, th, tw, c, ts, ts).permute(0, 3, 1, 4, 2, 5)
        return x.reshape(b, c, th * ts, tw * ts)[:, :, :h, :w]

    median = torch.where(median >= 0, median % max(n, 1), median)
    return CompositeOutput(untile(out), untile(t_final[:, None]), untile(median[:, None])[:, 0])
