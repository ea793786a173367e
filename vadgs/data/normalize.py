r"""Similarity normalisation of structure-from-motion scenes (arbitrary frame and scale).

vadgs's settings in world units (voxel sizes, the initial scale clamp, the ground cells of derived
instances) are metres tuned for street scenes, where the cameras are about 1.5 m above the ground
and most surfaces are 5–30 m away. An SfM reconstruction has an arbitrary frame and scale.
:func:`normalization_transform` computes the similarity

.. math::

    x' = s\,R\,(x - c)

that brings one into a street-like frame:

- **centre** ``c``: the mean of the camera centres (they move to the origin);
- **up** ``R``: the smallest rotation taking the cameras' mean "up" direction (``-y`` of the OpenCV
  camera axes, in world) to ``+z`` — as in the street scenes (the voxel grid's cubes then lie
  level; derived instances follow the scene's own ground frame in any case,
  :meth:`vadgs.train.vad.visibility.VisibilityIndex.ground_frame`);
- **scale** ``s``: the median camera-to-point depth of the observations (``z`` of each observed
  point in the camera of each observation, the TRACK table) becomes ``target_depth`` (default 10
  units, "about 10 m", a typical street depth). Without observations, the median distance of the
  camera centres from ``c`` becomes ``target_depth``; a single camera without points keeps ``s = 1``.

:func:`transform_points` and :func:`transform_cam_to_world` apply it; intrinsics do not change and
depths scale by ``s``.
"""

from __future__ import annotations

import torch

from vadgs.checks import check_shape

__all__ = ["normalization_transform", "similarity_scale", "transform_cam_to_world", "transform_points"]


def _rotation_to_z(up: torch.Tensor) -> torch.Tensor:
    """``(3, 3)`` the smallest rotation taking the unit vector ``up`` to ``+z`` (Rodrigues)."""
    z = torch.tensor([0.0, 0.0, 1.0], dtype=up.dtype)
    axis = torch.linalg.cross(up, z)
    sin, cos = axis.norm(), torch.dot(up, z)
    if sin < 1e-12:  # already up, or exactly down: a half turn about x
        return torch.eye(3, dtype=up.dtype) if cos > 0 else torch.diag(up.new_tensor([1.0, -1.0, -1.0]))
    k = axis / sin
    kx = torch.tensor([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]], dtype=up.dtype)
    return torch.eye(3, dtype=up.dtype) + sin * kx + (1 - cos) * (kx @ kx)


def normalization_transform(
    cam_to_world: torch.Tensor,
    points: torch.Tensor | None = None,
    point_views: tuple[torch.Tensor, torch.Tensor] | None = None,
    target_depth: float = 10.0,
) -> torch.Tensor:
    r"""The similarity ``x' = s R (x - c)`` that normalises an SfM scene (see the module docstring).

    Not differentiable (a data-preparation step).

    Args:
        cam_to_world: ``(V, 4, 4)`` camera poses.
        points: ``(P, 3)`` points (world).
        point_views: ``(point_idx (T,), view_idx (T,))`` observations of ``points`` by the cameras
            (a COLMAP TRACK table, :attr:`vadgs.data.ColmapPoints.point_views`).
        target_depth: the median observation depth after the transform.

    Returns:
        ``(4, 4)`` float64 ``[[s R, -s R c], [0, 1]]``.

    Raises:
        ValueError: on bad shapes or a non-positive ``target_depth``.

    Example:
        >>> c2w = torch.eye(4).repeat(2, 1, 1)
        >>> c2w[1, 0, 3] = 2.0  # two cameras looking along +z, 2 units apart
        >>> point, seen_by = torch.tensor([[1.0, 0, 5]]), (torch.tensor([0, 0]), torch.tensor([0, 1]))
        >>> T = normalization_transform(c2w, point, seen_by)  # the point is 5 units deep in both
        >>> transform_points(T, torch.tensor([[1.0, 0, 0]])).tolist()  # the cameras' centre -> origin
        [[0.0, 0.0, 0.0]]
        >>> round(similarity_scale(T), 6)  # depth 5 -> 10
        2.0
        >>> transform_cam_to_world(T, c2w)[0, :3, 1].tolist()  # camera y (down) -> -z, so up is +z
        [0.0, 0.0, -1.0]
    """
    check_shape(cam_to_world, "cam_to_world", ("V", 4, 4))
    if not target_depth > 0:
        raise ValueError(f"target_depth: expected a positive number, got {target_depth}")
    c2w = cam_to_world.detach().to("cpu", torch.float64)
    centres = c2w[:, :3, 3]
    c = centres.mean(0)
    up = -c2w[:, :3, 1].mean(0)
    R = _rotation_to_z(up / up.norm()) if up.norm() > 1e-9 else torch.eye(3, dtype=torch.float64)
    size = 0.0
    if points is not None and point_views is not None and point_views[0].numel():
        check_shape(points, "points", ("P", 3))
        pi, vi = (t.to("cpu") for t in point_views)
        p = points.detach().to("cpu", torch.float64)[pi]
        w2c_rot = c2w[vi, :3, :3].transpose(1, 2)
        z = (w2c_rot @ (p - centres[vi])[:, :, None])[:, 2, 0]
        z = z[z > 0]
        size = float(z.median()) if z.numel() else 0.0
    if size <= 0 and centres.shape[0] > 1:
        size = float((centres - c).norm(dim=-1).median())
    s = target_depth / size if size > 0 else 1.0
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = s * R
    T[:3, 3] = -s * R @ c
    return T


def similarity_scale(transform: torch.Tensor) -> float:
    """The scale ``s`` of a similarity ``[[s R, t], [0, 1]]`` (its rows have norm ``s``)."""
    return float(transform[:3, :3].double().det().abs() ** (1 / 3))


def transform_points(transform: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """``(N, 3)`` points mapped by a ``(4, 4)`` transform (float64 internally, ``points``' dtype out)."""
    T = transform.to("cpu", torch.float64)
    out = points.to(torch.float64) @ T[:3, :3].T + T[:3, 3]
    return out.to(points.dtype)


def transform_cam_to_world(transform: torch.Tensor, cam_to_world: torch.Tensor) -> torch.Tensor:
    """``(..., 4, 4)`` camera poses mapped by a similarity: centres move as points, axes rotate.

    The result stays rigid (the scale goes into the centres only), so intrinsics are unchanged.
    """
    T = transform.to("cpu", torch.float64)
    s = similarity_scale(T)
    c2w = cam_to_world.to(torch.float64)
    out = c2w.clone()
    out[..., :3, :3] = (T[:3, :3] / s) @ c2w[..., :3, :3]
    out[..., :3, 3] = c2w[..., :3, 3] @ T[:3, :3].T + T[:3, 3]
    return out.to(cam_to_world.dtype)
