r"""Select the supporting views of a reference view: diversity-aware (max-weight k-clique) or a baseline.

For a reference view ``R`` and a set of voxels (one instance's, or everything ``R`` sees), the
diversity-aware selection (paper, Sec. 4.2; supplement, "View Selection")

1. keeps the voxels ``R`` sees and, as candidates, the views sharing at least ``min_shared`` of
   them (the union of their visibility sets, across all cameras and timestamps);
2. scores every pair among ``R`` and the candidates on those voxels
   (:func:`vadgs.select.diversity_scores`) and drops candidates with ``s_iR = 0`` (no baseline or
   no rotation) or whose rays meet ``R``'s at less than ``min_angle`` degrees at the 75th
   percentile of those voxels (:func:`vadgs.select.triangulation_angles`, COLMAP's rule: a
   baseline too short for the depth fixes no depth);
3. joins two candidates by an edge when they co-observe at least ``min_shared`` of those voxels;
4. draws ``ξ ~ N(1, noise_std²)`` (seeded), keeps at most ``max_candidates`` candidates (those
   with the largest optimistic share ``s_iR ξ_iR + ½ top_{k-1}(λ s_ij ξ_ij)`` of the objective)
   and solves, exactly,

.. math::

    \max_{V_s \subset V_c,\ |V_s| = k}
    \sum_{i \in V_s} s_{iR} \xi_{iR} + \lambda \sum_{\{i, j\} \subset V_s} s_{ij} \xi_{ij}

over the k-cliques of that graph (:func:`vadgs.select.max_weight_clique`), with ``s_ij`` the
symmetrised pair score ``(s[i, j] + s[j, i]) / 2``.

The solver is exact over the candidates after the cap. The cap bounds the search
(``C(24, 4) = 10626`` subsets at most); ``docs/select.md`` measures how often it returns the
uncapped optimum.

Nothing here raises on a hard case: no voxel, no candidate (or only narrow ones), fewer
candidates than ``k`` or a graph without a k-clique all return a :class:`ViewSelection` with
fewer views (or none) and the reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from vadgs.checks import Checked, check_shape, checked, choice_field, float_field, int_field
from vadgs.select.baselines import colmap_scores, consecutive_views, mvsnet_scores, top_k_views
from vadgs.select.clique import MAX_SUBSETS, max_weight_clique
from vadgs.select.covisibility import Covisibility
from vadgs.select.score import diversity_scores, triangulation_angles

__all__ = ["METHODS", "ViewSelection", "ViewSelectionConfig", "ViewSelector", "select_views"]

METHODS = ("diversity", "consecutive", "mvsnet", "colmap")


@dataclass(frozen=True)
class ViewSelectionConfig(Checked):
    """Settings of :func:`select_views`.

    Attributes:
        k: supporting views wanted.
        lam: ``λ``, weight of the pairwise diversity among the supporting views.
        noise_std: standard deviation of ``ξ ~ N(1, noise_std²)``; ``0`` is deterministic.
        eps: ``ε`` of the diversity score, metres (see :func:`vadgs.select.pose_terms`).
        count_exponent: ``2`` (default) makes the score grow with the number of shared voxels, as
            the paper's text says it should; ``1`` is its equation as printed, where ``N`` cancels
            against ``d_R^T d_S`` (see :mod:`vadgs.select.score`).
        min_shared: voxels a candidate must share with the reference, and two candidates with
            each other to be joined in the graph.
        min_angle: least triangulation angle, degrees, of a candidate with the reference (the
            75th percentile over the voxels they share; COLMAP's PatchMatch sources: 1°). Not in
            the paper; its rendered and Waymo sequences move, but a car waiting at a light sees
            its far cells from centimetres apart, and matching them places points anywhere along
            the ray. ``0`` turns it off.
        min_parallax: the same bound in pixels of the reference, for a caller that passes its
            focal length (``select_views(focal=...)``): candidates need at least
            ``degrees(min_parallax / focal)``. With ``10``, a depth 10 % off moves a point by
            about a pixel in the support, so matching can tell it: ~3° at 240 pixels across a
            64° view, ~0.3° at 1920. ``0`` (default) leaves only ``min_angle``.
        max_candidates: cap on the candidates entering the clique search (best ``s_iR`` kept).
        method: ``"diversity"`` (the paper), or a baseline: ``"consecutive"`` (same camera,
            nearest frames), ``"mvsnet"``, ``"colmap"`` (see :mod:`vadgs.select.baselines`).
    """

    k: int = checked(4, int_field(1))
    lam: float = checked(0.5, float_field(0))
    noise_std: float = checked(0.05, float_field(0))
    eps: float = checked(0.1, float_field(0, lo_open=True))
    count_exponent: float = checked(2.0, float_field(0))
    min_shared: int = checked(8, int_field(1))
    min_angle: float = checked(1.0, float_field(0, 90, hi_open=True, note=" degrees"))
    min_parallax: float = checked(0.0, float_field(0, note=" pixels"))
    max_candidates: int = checked(24, int_field(1))
    method: str = checked("diversity", choice_field(METHODS))

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.max_candidates < self.k:
            raise ValueError(f"max_candidates: expected >= k = {self.k}, got {self.max_candidates}")
        subsets = math.comb(self.max_candidates, self.k)
        if subsets > MAX_SUBSETS:
            raise ValueError(
                f"max_candidates, k: expected C(max_candidates, k) <= {MAX_SUBSETS:.3g} subsets (the clique "
                f"search's bound), got C({self.max_candidates}, {self.k}) = {subsets:.3g}"
            )

    def least_angle(self, focal: float | None) -> float:
        """The least triangulation angle, degrees: ``min_angle``, or ``min_parallax`` pixels at ``focal``."""
        if self.min_parallax == 0:
            return self.min_angle
        if focal is None or not focal > 0:
            raise ValueError(
                f"focal: expected the reference's focal length in pixels (> 0) with min_parallax = "
                f"{self.min_parallax}, got {focal}"
            )
        return max(self.min_angle, math.degrees(self.min_parallax / focal))


@dataclass(frozen=True)
class ViewSelection:
    """The supporting views chosen for one reference view.

    The view ids are host data (CPU tensors): the choice is made on the host, after one read of
    what it needs (:func:`select_views`).

    Attributes:
        views: ``(s,)`` int64 view ids, ``s <= k`` (fewer, or none, only when ``reason`` says why).
        score: the objective of ``views`` (diversity: with the drawn noise; baselines: the sum of
            their scores; ``0.0`` when empty).
        reason: ``"ok"`` when ``k`` views were found, otherwise why not: starts with one of
            ``"no_voxels"``, ``"no_candidates"``, ``"narrow_baselines"`` (candidates, but all
            under ``min_angle``), ``"few_candidates"``, ``"no_k_clique"``.
            A ``"; capped ..."`` suffix says the candidate cap was applied.
        candidates: ``(c,)`` int64 the candidate views the choice was made from.
    """

    views: torch.Tensor
    score: float
    reason: str
    candidates: torch.Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.long))

    @property
    def ids(self) -> list[int]:
        """``views`` as Python ints (a CPU tensor's values: no read of a device)."""
        return [int(v) for v in self.views.numpy()]

    @property
    def complete(self) -> bool:
        """Whether ``k`` views were found (``reason == "ok"``, possibly capped)."""
        return self.reason.startswith("ok")


def _empty() -> torch.Tensor:
    return torch.zeros(0, dtype=torch.long)


def _allowed(allowed: torch.Tensor | None, num_views: int, device: torch.device) -> torch.Tensor:
    if allowed is None:
        return torch.ones(num_views, dtype=torch.bool, device=device)
    check_shape(allowed, "allowed", (num_views,))
    if allowed.dtype != torch.bool:
        raise ValueError(f"allowed: expected a bool mask, got {allowed.dtype}")
    return allowed.to(device)


def _select_baseline(
    ref: int, covis: Covisibility, config: ViewSelectionConfig, allowed: torch.Tensor
) -> ViewSelection:
    if config.method == "consecutive":
        if covis.camera_ids is None or covis.frame_ids is None:
            raise ValueError("method='consecutive' needs covis.camera_ids and covis.frame_ids")
        cand = consecutive_views(ref, covis.camera_ids, covis.frame_ids, covis.num_views, allowed)
        views = cand[: config.k]
        score = 0.0
    else:
        fn = mvsnet_scores if config.method == "mvsnet" else colmap_scores
        scores = fn(covis, ref)
        cand = top_k_views(scores, ref, covis.num_views, allowed)
        views = cand[: config.k]
        score = float(scores[views].sum()) if len(views) else 0.0
    cand, views = cand.cpu(), views.cpu()
    if len(cand) == 0:
        return ViewSelection(_empty(), 0.0, f"no_candidates: {config.method} found none", cand)
    if len(views) < config.k:
        reason = f"few_candidates: {len(cand)} candidates < k={config.k}"
        return ViewSelection(views, score, reason, cand)
    return ViewSelection(views, score, "ok", cand)


def _cap(node: torch.Tensor, edge: torch.Tensor, adjacency: torch.Tensor, k: int, cap: int) -> torch.Tensor:
    """Indices (sorted) of the ``cap`` candidates with the largest optimistic contribution.

    A candidate's share of the objective of any k-clique containing it is at most its node weight
    plus half its ``k - 1`` largest edge weights to neighbours: ``u_i = w_i + ½ top_{k-1}(W_ij)``.
    """
    half = torch.where(adjacency, edge / 2, torch.zeros_like(edge))
    u = node + torch.topk(half, min(k - 1, len(node)), dim=1).values.sum(1)
    return torch.sort(torch.topk(u, cap).indices).values


def select_views(
    ref: int,
    covis: Covisibility,
    config: ViewSelectionConfig | None = None,
    generator: torch.Generator | None = None,
    allowed: torch.Tensor | None = None,
    focal: float | None = None,
) -> ViewSelection:
    """Choose the supporting views of reference view ``ref`` (see the module docstring).

    The diversity scores are computed on the voxels of ``covis`` that ``ref`` sees (``N``,
    ``d_R``, ``d_S`` of every pair, candidates among themselves included, count only those), for
    ``ref`` and the views sharing at least ``min_shared`` of them. Runs under ``torch.no_grad()``;
    nothing is differentiable.

    The diversity method reads the device once: the scores, counts and angles of every view are
    computed on ``covis``'s device over all its entries (those at voxels ``ref`` does not see
    weigh nothing: ``O(entries)``, so restrict a scene-sized ``covis`` to an instance first), then
    read together; the candidates, the noise and the clique search are on the host.

    Args:
        ref: the reference view, an index into ``covis``'s views.
        covis: the views, voxels and visibility; restrict it to an instance's voxels
            (:meth:`Covisibility.restrict`) to select for that instance, in the object's frame for
            a moving one. Unrestricted, the selection is for the whole reference view.
        config: settings (defaults: :class:`ViewSelectionConfig`).
        generator: draws ``ξ`` (``None``: torch's global generator). Seed it for reproducible picks.
        allowed: optional ``(V,)`` bool, the views that may be chosen (e.g. training views).
        focal: the reference's focal length in pixels; needed when ``config.min_parallax > 0``.

    Returns:
        A :class:`ViewSelection`; fewer than ``k`` views (or none) only with a reason.

    Raises:
        ValueError: if ``ref`` is out of range, ``allowed`` has the wrong shape, or a baseline
            lacks the ids it needs.

    Example:
        >>> import math
        >>> # six cameras on a circle of radius 10 looking at the origin; everything sees 20 voxels
        >>> w2c = torch.eye(4).repeat(6, 1, 1)
        >>> for v in range(6):
        ...     a = math.radians(20.0 * v)
        ...     R = torch.tensor([[math.cos(a), 0, -math.sin(a)], [0, 1, 0], [math.sin(a), 0, math.cos(a)]])
        ...     w2c[v, :3, :3] = R; w2c[v, :3, 3] = torch.tensor([0.0, 0, 10.0])
        >>> covis = Covisibility.from_visible([torch.arange(20)] * 6, torch.randn(20, 3) * 0.5, w2c)
        >>> sel = select_views(0, covis, ViewSelectionConfig(k=3, noise_std=0.0))
        >>> sel.views.tolist(), sel.reason
        ([1, 2, 3], 'ok')
        >>> select_views(0, covis, ViewSelectionConfig(k=3, method="mvsnet")).views.tolist()
        [1, 2, 3]
    """
    config = ViewSelectionConfig() if config is None else config
    num, device = covis.num_views, covis.world_to_cam.device
    if not 0 <= int(ref) < num:
        raise ValueError(f"ref: expected a view index in [0, {num}), got {ref}")
    ref = int(ref)
    ok = _allowed(allowed, num, device)
    least = config.least_angle(focal)
    with torch.no_grad():
        if config.method != "diversity":
            return _select_baseline(ref, covis, config, ok)
        # everything the choice needs, for every view, on the device; then one read of it all
        rows, cols = covis.incidence.indices()
        seen = covis.seen_by(ref)
        shared_ref = torch.zeros(num, dtype=torch.long, device=device).index_add_(0, rows, seen[cols].long())
        mask = (shared_ref >= config.min_shared) & ok
        mask[ref] = False
        # the scores on the voxels ref sees: those of covis.restrict(seen) (its reads left out)
        scores = diversity_scores(covis, config.eps, config.count_exponent, voxels=seen)
        s_ref = scores.score[ref]
        wide = triangulation_angles(covis, ref, seen=seen) >= least
        flags = torch.stack([mask & (s_ref > 0) & wide, mask & (s_ref > 0) & ~wide])
        packed = torch.cat(
            [seen.any().double()[None], flags.double().flatten(), scores.score.double().flatten(),
             scores.shared.double().flatten()]
        )  # fmt: skip
        host = packed.tolist()  # the one read
        if not host[0]:
            return ViewSelection(_empty(), 0.0, "no_voxels: the reference sees none of the voxels")
        good = [v for v in range(num) if host[1 + v]]
        narrow = sum(map(bool, host[1 + num : 1 + 2 * num]))
        at = 1 + 2 * num
        score = torch.tensor(host[at : at + num * num], dtype=scores.score.dtype).view(num, num)
        shared = torch.tensor(host[at + num * num :], dtype=torch.float64).view(num, num)
        cand = torch.tensor(good, dtype=torch.long)  # on the host
        total = len(good)
        if total == 0:
            reason = f"no_candidates: no view shares >= {config.min_shared} voxels and a baseline with it"
            if narrow:
                reason = (
                    f"narrow_baselines: {narrow} views share >= {config.min_shared} voxels with it, all at a "
                    f"triangulation angle < {least:.3g}°"
                )
            return ViewSelection(_empty(), 0.0, reason, cand)
        node = score[ref][cand]
        pair = score[cand][:, cand]
        pair = (pair + pair.T) / 2
        if config.noise_std > 0:
            gdev = generator.device if generator is not None else torch.device("cpu")
            xi_node = torch.randn(total, generator=generator, device=gdev, dtype=node.dtype)
            xi_pair = torch.randn(total, total, generator=generator, device=gdev, dtype=node.dtype).triu(1)
            xi_pair = xi_pair + xi_pair.T
            node = node * (1 + config.noise_std * xi_node.cpu())
            pair = pair * (1 + config.noise_std * xi_pair.cpu())
        edge = config.lam * pair
        adjacency = shared[cand][:, cand] >= config.min_shared
        adjacency.fill_diagonal_(False)
        capped = ""
        if total > config.max_candidates:
            keep = _cap(node, edge, adjacency, config.k, config.max_candidates)
            node, edge, adjacency, cand = (
                node[keep],
                edge[keep][:, keep],
                adjacency[keep][:, keep],
                cand[keep],
            )
            capped = f"; capped to {config.max_candidates} of {total} candidates"
        clique = max_weight_clique(node, edge, config.k, adjacency)
        chosen = cand[clique.nodes]
        c = len(cand)
        if len(chosen) == config.k:
            reason = "ok" + capped
        elif c < config.k:
            reason = f"few_candidates: {c} candidates < k={config.k}" + capped
        else:
            reason = (
                f"no_k_clique: the largest group of {c} candidates that pairwise co-observe "
                f">= {config.min_shared} voxels has {len(chosen)} views" + capped
            )
        return ViewSelection(chosen, clique.weight, reason, cand)


class ViewSelector:
    """Holds a :class:`ViewSelectionConfig` and a seeded generator; see :func:`select_views`.

    Args:
        config: settings.
        seed: seed of the generator drawing ``ξ``: the same seed and calls give the same picks.

    Example:
        >>> w2c = torch.eye(4).repeat(3, 1, 1); w2c[1, 0, 3] = -1.0; w2c[2, 0, 3] = 1.0
        >>> w2c[1, :3, :3] = torch.tensor([[0.96, 0, -0.28], [0, 1, 0], [0.28, 0, 0.96]])
        >>> w2c[2, :3, :3] = torch.tensor([[0.96, 0, 0.28], [0, 1, 0], [-0.28, 0, 0.96]])
        >>> covis = Covisibility.from_visible([torch.arange(10)] * 3, torch.rand(10, 3) + 3, w2c)
        >>> selector = ViewSelector(ViewSelectionConfig(k=2, min_shared=5), seed=0)
        >>> [sel.views.tolist() for sel in selector.select_all(covis)]
        [[1, 2], [0, 2], [0, 1]]
    """

    def __init__(self, config: ViewSelectionConfig | None = None, seed: int = 0) -> None:
        self.config = ViewSelectionConfig() if config is None else config
        self.seed = seed
        self.generator = torch.Generator().manual_seed(seed)

    def __call__(
        self,
        ref: int,
        covis: Covisibility,
        allowed: torch.Tensor | None = None,
        focal: float | None = None,
    ) -> ViewSelection:
        """Select for one reference view (see :func:`select_views`)."""
        return select_views(ref, covis, self.config, self.generator, allowed, focal)

    def select_all(
        self,
        covis: Covisibility,
        refs: list[int] | torch.Tensor | None = None,
        allowed: torch.Tensor | None = None,
        focal: list[float] | None = None,
    ) -> list[ViewSelection]:
        """Select for every view in ``refs`` (default: all views), in order; ``focal``: ``(V,)`` pixels."""
        ids = range(covis.num_views) if refs is None else [int(r) for r in refs]
        return [self(r, covis, allowed, None if focal is None else focal[r]) for r in ids]

    def __repr__(self) -> str:
        return f"ViewSelector({self.config!r}, seed={self.seed})"
