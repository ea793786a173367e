"""Which flagged instances to reconstruct, and from which reference views (paper, Sec. 4.2).

:func:`rank_instances` orders an event's flagged instances; :func:`pick_references` chooses each
one's reference views (the largest first, then views of other cameras or frames apart).
"""

from __future__ import annotations

from collections.abc import Collection
from typing import Any

from vadgs.train.vad.config import RANKINGS
from vadgs.train.vad.inputs import VisibilityInputs

__all__ = [
    "pick_references",
    "rank_instances",
]


def pick_references(
    candidates: list[tuple[int, int]],
    scene: VisibilityInputs | Any,
    count: int,
    min_frame_gap: int = 3,
    whole: Collection[int] | None = None,
    tie: float = 0.05,
) -> list[int]:
    """Reference views of one instance: the largest first, then diverse ones.

    Views within ``tie`` of the largest pixel count are taken as equally large and ordered by
    view index: neighbouring frames often see an instance at a few percent of each other, and
    that difference follows the voxels' discretisation (another world frame, e.g. gsplat's
    normalised one, flips it), not the views.

    Args:
        candidates: ``(view, pixels)`` of the views where the instance was flagged.
        scene: :class:`~vadgs.train.vad.inputs.VisibilityInputs` or a vadgs :class:`~vadgs.data.Scene`
            (for each view's camera and frame).
        count: how many references at most.
        min_frame_gap: a further reference must come from a camera not chosen yet, or be at
            least this many frames from every chosen view of its camera.
        whole: the candidates in which the instance is whole (not cut by the image border). When
            given and no chosen view is one of them, the last reference is replaced by the
            largest of them that keeps the rule above (the close views with the most pixels may
            all cut off the same part, e.g. the top of a sign).
        tie: relative band below the largest count whose views count as equally large.

    Returns:
        View indices, largest first.

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> sc = load_scene(sample_scene_path())
        >>> [(sc.views[v].camera, sc.views[v].frame) for v in (0, 1, 3)]
        [('front', 16), ('front_left', 16), ('front', 17)]
        >>> pick_references([(0, 500), (3, 450), (1, 100)], sc, 2)  # view 3: same camera, 1 frame on
        [0, 1]
        >>> pick_references([(3, 500), (0, 490), (1, 100)], sc, 2)  # 0 and 3 tie (2 %): the first view
        [0, 1]
    """
    if isinstance(scene, VisibilityInputs):
        cam, frame = list(scene.view_cameras), list(scene.view_frames)
    else:
        cam, frame = [v.camera for v in scene.views], [v.frame for v in scene.views]

    def apart(view: int, chosen: list[int]) -> bool:
        return all(cam[c] != cam[view] or abs(frame[c] - frame[view]) >= min_frame_gap for c in chosen)

    top = max((px for _v, px in candidates), default=0)
    tied = {v for v, px in candidates if px >= (1 - tie) * top}

    def rank(vp: tuple[int, int]) -> tuple[int, ...]:  # the tied views first, by index; then by size
        return (0, vp[0]) if vp[0] in tied else (1, -vp[1], vp[0])

    order = [v for v, _px in sorted(candidates, key=rank)]
    chosen: list[int] = []
    for view in order:
        if len(chosen) >= count:
            break
        if apart(view, chosen):
            chosen.append(view)
    if whole is not None and count >= 2 and chosen and not set(chosen) & set(whole):
        keep = chosen[: count - 1]
        extra = next((v for v in order if v in whole and v not in keep and apart(v, keep)), None)
        if extra is not None:
            chosen = [*keep, extra]
    return chosen


def rank_instances(
    pixels: dict[int, int], classes: dict[int, str], ranking: str = "class_round_robin"
) -> list[int]:
    """Order flagged instances for reconstruction.

    Args:
        pixels: instance id → its size (pixels in its best flagged view).
        classes: instance id → class name (missing ids form one class ``""``).
        ranking: ``"pixels"`` (largest first) or ``"class_round_robin"`` (the largest of each class
            in turn; classes ordered by their largest instance).

    Example:
        >>> px = {1: 900, 2: 800, 3: 700, 7: 50, 9: 300}
        >>> cls = {1: "building", 2: "building", 3: "building", 7: "sign", 9: "tree"}
        >>> rank_instances(px, cls, "pixels")
        [1, 2, 3, 9, 7]
        >>> rank_instances(px, cls)
        [1, 9, 7, 2, 3]
    """
    if ranking not in RANKINGS:
        raise ValueError(f"ranking: expected one of {RANKINGS}, got {ranking!r}")
    order = sorted(pixels, key=lambda i: (-pixels[i], i))
    if ranking == "pixels":
        return order
    queues: dict[str, list[int]] = {}
    for i in order:  # classes in the order of their largest instance
        queues.setdefault(classes.get(i, ""), []).append(i)
    out: list[int] = []
    while any(queues.values()):
        for q in queues.values():
            if q:
                out.append(q.pop(0))
    return out
