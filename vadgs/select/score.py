r"""The diversity score between two views (paper, Sec. 4.2, Eq. (eq.diversity)).

.. math::

    s = \frac{N}{\mathbf{d}_R^\top \mathbf{d}_S}
        \frac{\sqrt{t_x^2 + t_y^2}}{|t_z| + \epsilon} \sin\theta

``N`` voxels are seen by both the reference view ``R`` and the supporting view ``S``;
``d_R``, ``d_S`` hold their distances to each camera centre; ``t`` is the supporting camera's
centre in the reference camera frame (lateral ``t_x, t_y``, longitudinal ``t_z``); ``θ`` is the
angle of the relative rotation. Large lateral baselines, little forward motion, different
orientations and close voxels score high.

A note on the count term: ``d_R^T d_S`` is a sum over the same ``N`` voxels, so
``N / (d_R^T d_S) = 1 / mean(d_R d_S)``: taken literally, the equation does not grow with the
number of shared voxels (only with their closeness), although the paper's text says that "denser"
voxels score higher. ``count_exponent=1`` (the default) is the equation as printed;
``count_exponent=2`` multiplies it by ``N`` (``N / mean(d_R d_S)``) so that views sharing more of
the instance score higher, as the text describes.

All pairs are scored at once: with ``B`` the sparse 0/1 view × voxel incidence and ``A`` the same
pattern holding voxel-to-camera distances, ``N = B B^T`` and ``d_R^T d_S = A A^T`` (two sparse
products), and the pose terms are broadcast over ``(V, V)``.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from vadgs.checks import check_shape
from vadgs.geometry.camera import camera_centers
from vadgs.select.covisibility import Covisibility, sparse_gram

__all__ = [
    "DiversityScores",
    "diversity_score",
    "diversity_scores",
    "pose_terms",
    "ray_angles",
    "shared_voxel_stats",
    "triangulation_angles",
]


class DiversityScores(NamedTuple):
    """All pairwise diversity scores of a set of views.

    Attributes:
        score: ``(V, V)`` ``score[r, s]`` is the diversity of view ``s`` as a support of the
            reference ``r`` (``t`` expressed in ``r``'s frame, so not symmetric); ``0`` on the
            diagonal and wherever no voxel is shared.
        shared: ``(V, V)`` symmetric, the number ``N`` of voxels both views see.
        dist_dot: ``(V, V)`` symmetric, ``d_R^T d_S`` over those voxels.
    """

    score: torch.Tensor
    shared: torch.Tensor
    dist_dot: torch.Tensor


def shared_voxel_stats(
    covis: Covisibility, voxels: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Shared voxel counts ``N`` and distance products ``d_R^T d_S`` of all pairs of views.

    Two sparse products, ``B B^T`` and ``A A^T`` (see the module docstring); no loop over pairs.
    Not differentiable (runs under ``torch.no_grad()``).

    Args:
        covis: the views, voxels and visibility.
        voxels: optional ``(M,)`` bool, the voxels that count (the others' entries weigh 0: the
            same values as on ``covis.restrict(voxels)``, without its reads by the host).

    Returns:
        ``(shared, dist_dot)``, both ``(V, V)`` dense and symmetric, dtype of the voxel centres.

    Example:
        >>> cams = torch.eye(4).repeat(2, 1, 1); cams[1, 0, 3] = -1.0  # second centre at x = 1
        >>> covis = Covisibility.from_visible(
        ...     [torch.tensor([0, 1]), torch.tensor([1])], torch.tensor([[0.0, 0, 2], [1.0, 0, 2]]), cams)
        >>> shared, dist_dot = shared_voxel_stats(covis)
        >>> shared[0, 1].item(), round(dist_dot[0, 1].item(), 4)  # voxel 1: sqrt(5) and 2 away
        (1.0, 4.4721)
    """
    with torch.no_grad():
        inc = covis.incidence
        idx = inc.indices()
        centers = camera_centers(covis.world_to_cam)  # (V, 3)
        dist = (covis.voxel_centers[idx[1]] - centers[idx[0]].to(covis.voxel_centers.dtype)).norm(dim=-1)
        shape = (inc.shape[0], inc.shape[1])
        ones = inc.values()
        if voxels is not None:
            check_shape(voxels, "voxels", (covis.num_voxels,))
            ones = voxels.to(ones.device)[idx[1]].to(ones.dtype)
            dist = dist * ones.to(dist.dtype)
        shared = sparse_gram(idx, ones, ones, shape)
        dist_dot = sparse_gram(idx, dist, dist, shape)
    return shared, dist_dot


def ray_angles(covis: Covisibility, ref: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The triangulation angle of ``ref`` with every other view at each voxel both see.

    ``θ(p)`` is the angle at voxel centre ``p`` between the rays to the two camera centres.
    Vectorised over the non-zeros of the view × voxel incidence; not differentiable.

    Args:
        covis: the views, voxels and visibility.
        ref: the reference view.

    Returns:
        ``(view, voxel, angle)``, each ``(n,)``: for every non-zero ``(view, voxel)`` of a view
        other than ``ref`` at a voxel ``ref`` sees, the angle in degrees.

    Example:
        >>> cams = torch.eye(4).repeat(2, 1, 1); cams[1, 0, 3] = -2.0  # second centre at x = 2
        >>> covis = Covisibility.from_visible([torch.tensor([0])] * 2, torch.tensor([[0.0, 0, 2]]), cams)
        >>> view, voxel, angle = ray_angles(covis, 0)  # rays from (0,0,0) and (2,0,0) to (0,0,2)
        >>> view.tolist(), voxel.tolist(), round(angle.item(), 3)
        ([1], [0], 45.0)
    """
    with torch.no_grad():
        seen = covis.voxels_of(ref)
        view, pos = covis.entries_of(seen)
        keep = view != ref
        view, voxel = view[keep], seen[pos[keep]]
        return view, voxel, _angles(covis, ref, view, voxel)


def _angles(covis: Covisibility, ref: int, view: torch.Tensor, voxel: torch.Tensor) -> torch.Tensor:
    """Degrees between the rays from voxel ``voxel[i]`` to ``ref``'s and ``view[i]``'s camera centres."""
    centers = camera_centers(covis.world_to_cam)
    p = covis.voxel_centers[voxel]
    to_ref = torch.nn.functional.normalize(centers[ref] - p, dim=-1)
    to_src = torch.nn.functional.normalize(centers[view] - p, dim=-1)
    # atan2(|a x b|, a . b): exact to rounding at hundredths of a degree, where acos is not
    sin = torch.linalg.cross(to_ref, to_src).norm(dim=-1)
    return torch.rad2deg(torch.atan2(sin, (to_ref * to_src).sum(-1)))


def triangulation_angles(
    covis: Covisibility, ref: int, percentile: float = 75.0, seen: torch.Tensor | None = None
) -> torch.Tensor:
    """Each view's triangulation angle with ``ref`` over the voxels both see: a percentile, degrees.

    The ``percentile``-th percentile (nearest rank, rounded down) of :func:`ray_angles` over the
    shared voxels, as COLMAP's ``Model::GetMaxOverlappingImages`` ranks the sources of its
    PatchMatch (75th, and at least 1°). A pair whose rays meet at a small angle fixes depth poorly:
    the diversity score does not see it when every baseline is short (a car waiting at a light).

    Computed over every entry of the incidence, those at voxels ``ref`` does not see left out by a
    mask (no read by the host: ``O(entries)``).

    Args:
        covis: the views, voxels and visibility.
        ref: the reference view.
        percentile: in ``[0, 100]``.
        seen: ``covis.seen_by(ref)`` when the caller has it.

    Returns:
        ``(V,)`` degrees, ``0`` for ``ref`` and for views sharing no voxel with it.

    Example:
        >>> w2c = torch.eye(4).repeat(3, 1, 1); w2c[1, 0, 3] = -0.5; w2c[2, 0, 3] = -0.001
        >>> covis = Covisibility.from_visible(
        ...     [torch.tensor([0, 1])] * 3, torch.tensor([[0.0, 0, 4], [1.0, 0, 4]]), w2c)
        >>> [round(a, 3) for a in triangulation_angles(covis, 0).tolist()]  # 1 mm aside: 0.013°
        [0.0, 6.911, 0.013]
    """
    with torch.no_grad():
        view, voxel = covis.incidence.indices()
        if seen is None:
            seen = covis.seen_by(ref)
        use = seen[voxel] & (view != ref)
        theta = torch.where(use, _angles(covis, ref, view, voxel), torch.inf)
        num = covis.num_views
        counts = torch.zeros(num, dtype=torch.long, device=theta.device).index_add_(0, view, use.long())
        entries = torch.zeros_like(counts).index_add_(0, view, torch.ones_like(view))
        # grouped percentile: sort by angle, then stably by view (each view's unused entries last)
        order = torch.argsort(theta, stable=True)
        order = order[torch.argsort(view[order], stable=True)]
        start = torch.cumsum(entries, 0) - entries
        rank = torch.floor((counts - 1).clamp_min(0).to(theta.dtype) * percentile / 100).long()
        padded = torch.cat([theta[order], theta.new_zeros(1)])  # a view sharing nothing reads the 0
        at = torch.where(counts > 0, start + rank, len(theta))
        return padded[at]


def pose_terms(
    world_to_ref: torch.Tensor, world_to_src: torch.Tensor, eps: float = 0.1
) -> tuple[torch.Tensor, torch.Tensor]:
    """The baseline ratio ``sqrt(t_x² + t_y²) / (|t_z| + ε)`` and ``sin θ`` of pairs of views.

    ``t`` is the source camera centre in the reference camera frame (the translation of
    ``ref_from_src``); ``θ ∈ [0, π]`` is the angle of the relative rotation
    ``R_ref R_src^T``. Differentiable w.r.t. the poses (except where ``t_x = t_y = 0``).

    Args:
        world_to_ref: ``(*, 4, 4)`` reference views.
        world_to_src: ``(*, 4, 4)`` source views, broadcast against ``world_to_ref``.
        eps: ``ε`` in metres, keeps the ratio finite when ``t_z = 0``.

    Returns:
        ``(baseline_ratio, sin_theta)``, each of the broadcast shape ``(*)``.

    Example:
        >>> ref = torch.eye(4); src = torch.eye(4); src[0, 3] = -2.0  # src centre 2 m to the right
        >>> pose_terms(ref, src, eps=0.5)
        (tensor(4.), tensor(0.))
    """
    check_shape(world_to_ref, "world_to_ref", ("*", 4, 4))
    check_shape(world_to_src, "world_to_src", ("*", 4, 4))
    # t = R_ref C_src + t_ref with C_src = -R_src^T t_src (no 4x4 inverses: cheap on (V, V) grids)
    rot_ref, rot_src = world_to_ref[..., :3, :3], world_to_src[..., :3, :3]
    center_src = -(rot_src.transpose(-1, -2) @ world_to_src[..., :3, 3:])
    t = (rot_ref @ center_src + world_to_ref[..., :3, 3:]).squeeze(-1)
    ratio = t[..., :2].norm(dim=-1) / (t[..., 2].abs() + eps)
    # sin θ = |vee(R - R^T)| / 2 for θ in [0, π]: accurate for small angles, unlike sqrt(1 - cos²)
    rot = rot_ref @ rot_src.transpose(-1, -2)
    skew = torch.stack(
        [rot[..., 2, 1] - rot[..., 1, 2], rot[..., 0, 2] - rot[..., 2, 0], rot[..., 1, 0] - rot[..., 0, 1]],
        -1,
    )
    return ratio, skew.norm(dim=-1) / 2


def diversity_score(
    shared: torch.Tensor,
    dist_dot: torch.Tensor,
    world_to_ref: torch.Tensor,
    world_to_src: torch.Tensor,
    eps: float = 0.1,
    count_exponent: float = 1.0,
) -> torch.Tensor:
    r"""The diversity score of pairs of views (paper, Sec. 4.2, Eq. (eq.diversity)).

    .. math::

        s = \frac{N^{p}}{\mathbf{d}_R^\top \mathbf{d}_S}
            \frac{\sqrt{t_x^2 + t_y^2}}{|t_z| + \epsilon} \sin\theta

    with ``p = count_exponent`` (``1``: the paper's equation as printed; see the module
    docstring). Pairs sharing no voxel score ``0``. Elementwise and broadcast; differentiable
    w.r.t. ``dist_dot`` and the poses.

    Args:
        shared: ``(*)`` number ``N`` of voxels both views see.
        dist_dot: ``(*)`` ``d_R^T d_S``, the sum over those voxels of the product of their
            distances to the two camera centres.
        world_to_ref: ``(*, 4, 4)`` reference views.
        world_to_src: ``(*, 4, 4)`` supporting views.
        eps: ``ε`` in metres (see :func:`pose_terms`).
        count_exponent: ``p`` above.

    Returns:
        ``(*)`` the scores, ``>= 0``.

    Shape:
        All leading shapes broadcast together.

    Example:
        >>> ref = torch.eye(4)
        >>> src = torch.eye(4); src[:3, :3] = torch.tensor([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]])
        >>> src[:3, 3] = torch.tensor([0.0, 0, -2.0])  # turned 90°, centre 2 m to the right
        >>> diversity_score(torch.tensor(10.0), torch.tensor(40.0), ref, src, eps=0.5)
        tensor(1.)
    """
    ratio, sin = pose_terms(world_to_ref, world_to_src, eps)
    safe = torch.where(shared > 0, dist_dot, torch.ones_like(dist_dot))
    density = torch.where(shared > 0, shared.to(dist_dot.dtype) ** count_exponent / safe, 0.0)
    return density * ratio * sin


def diversity_scores(
    covis: Covisibility, eps: float = 0.1, count_exponent: float = 1.0, voxels: torch.Tensor | None = None
) -> DiversityScores:
    """Score every ordered pair of views at once (:func:`diversity_score` on ``(V, V)``).

    Runs under ``torch.no_grad()``: view selection is a search, nothing is learned.

    Args:
        covis: the views, voxels and visibility (restrict it to an instance's voxels first to
            score views for that instance).
        eps: ``ε`` in metres (see :func:`pose_terms`).
        count_exponent: see :func:`diversity_score`.
        voxels: optional ``(M,)`` bool, the voxels that count (see :func:`shared_voxel_stats`).

    Returns:
        A :class:`DiversityScores` with ``score[r, s]`` for reference ``r`` and support ``s``.

    Example:
        >>> w2c = torch.eye(4).repeat(3, 1, 1)
        >>> w2c[1, :3, :3] = torch.tensor([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]])
        >>> w2c[1, :3, 3] = torch.tensor([0.0, 0, -2.0])
        >>> covis = Covisibility.from_visible(
        ...     [torch.tensor([0, 1]), torch.tensor([0, 1]), torch.tensor([5])], torch.rand(6, 3) + 1, w2c)
        >>> out = diversity_scores(covis)
        >>> out.shared[0].tolist(), bool(out.score[0, 1] > 0), out.score[0, 2].item()
        ([2.0, 2.0, 0.0], True, 0.0)
    """
    with torch.no_grad():
        shared, dist_dot = shared_voxel_stats(covis, voxels)
        w2c = covis.world_to_cam
        score = diversity_score(shared, dist_dot, w2c[:, None], w2c[None, :], eps, count_exponent)
        score.fill_diagonal_(0)
    return DiversityScores(score, shared, dist_dot)
