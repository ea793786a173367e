r"""Camera paths: poses between key poses, a smooth path through cameras, an orbit around them.

The math of the videos' trajectories (:mod:`vadgs.train.results.trajectory` picks the keys from a
scene and names the paths); every function takes and returns camera-to-world poses ``(*, 4, 4)``
with OpenCV axes (x right, y down, z forward) and knows nothing about scenes.

- :func:`interpolate_rigid`: a rigid transform between two, rotation slerped (shortest way),
  translation linear; :func:`keyframe_path` inserts such poses between consecutive key poses.
- :func:`spline_path`: a smooth path through cameras, as gsplat's ``generate_interpolated_path``:
  the centres and the look-at points (``focus_depth`` ahead of each camera) follow a centripetal
  Catmull-Rom spline (:func:`catmull_rom`), which passes through every key without overshoot or
  cusps; each pose looks at its look-at point with a fixed up (:func:`look_at`), so the path does
  not roll.
- :func:`orbit_path`: a circle around the point nearest to every optical axis
  (:func:`focus_point`, multinerf's ``focus_point_fn``) in the plane normal to the up, at the
  cameras' median distance and mean height, looking at the centre, starting at the first camera
  and turning the way the cameras do, as nerfstudio's orbit.

Not differentiable (poses are fixed).
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from vadgs.checks import check_shape
from vadgs.geometry.rotation import quaternion_to_rotation, rotation_to_quat

__all__ = [
    "CameraPath",
    "catmull_rom",
    "focus_point",
    "interpolate_rigid",
    "keyframe_path",
    "look_at",
    "orbit_path",
    "spline_path",
]


class CameraPath(NamedTuple):
    """Poses of a path and where each lies along it.

    Attributes:
        cam_to_world: ``(P, 4, 4)`` poses.
        t: ``(P,)`` float64 path parameter: key pose ``i`` at ``t = i`` (:func:`keyframe_path`,
            :func:`spline_path`); the fraction of the turn (:func:`orbit_path`).
    """

    cam_to_world: torch.Tensor
    t: torch.Tensor


def interpolate_rigid(a: torch.Tensor, b: torch.Tensor, t: float) -> torch.Tensor:
    """Rigid transform between ``a`` (``t = 0``) and ``b`` (``t = 1``): slerped rotation, linear translation.

    Computed in float64, returned in ``a``'s dtype. Not differentiable (poses are fixed).

    Shape:
        ``(*, 4, 4)`` and ``(*, 4, 4)`` → ``(*, 4, 4)``.

    Example:
        >>> a = torch.eye(4); b = torch.eye(4); b[:3, :3] = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
        >>> b[0, 3] = 2.0
        >>> m = interpolate_rigid(a, b, 0.5)  # 45° about z, half-way
        >>> [round(v, 4) for v in (m[0, 0].item(), m[1, 0].item(), m[0, 3].item())]
        [0.7071, 0.7071, 1.0]
    """
    check_shape(a, "a", ("*", 4, 4))
    check_shape(b, "b", ("*", 4, 4))
    qa = rotation_to_quat(a[..., :3, :3].double())
    qb = rotation_to_quat(b[..., :3, :3].double())
    dot = (qa * qb).sum(-1, keepdim=True)
    qb = torch.where(dot < 0, -qb, qb)  # the short way round
    dot = dot.abs().clamp(max=1.0)
    theta = torch.acos(dot)
    sin = torch.sin(theta)
    near = sin < 1e-6  # (almost) the same rotation: linear interpolation is exact enough
    wa = torch.where(near, 1.0 - t, torch.sin((1.0 - t) * theta) / sin.clamp(min=1e-12))
    wb = torch.where(near, torch.full_like(theta, t), torch.sin(t * theta) / sin.clamp(min=1e-12))
    out = a.double().clone()
    out[..., :3, :3] = quaternion_to_rotation(wa * qa + wb * qb)
    out[..., :3, 3] = (1.0 - t) * a[..., :3, 3].double() + t * b[..., :3, 3].double()
    return out.to(a.dtype)


def keyframe_path(keys: torch.Tensor, frames_between: int = 0) -> CameraPath:
    """The key poses with ``frames_between`` poses inserted between consecutive ones.

    The inserted poses are :func:`interpolate_rigid`'s; the keys are kept as they are.

    Args:
        keys: ``(K, 4, 4)`` camera-to-world poses, ``K >= 1``.
        frames_between: poses inserted between consecutive keys, ``>= 0``.

    Returns:
        :class:`CameraPath` of ``(K - 1) * (frames_between + 1) + 1`` poses in ``keys``' dtype, key
        ``i`` at ``t = i``.

    Example:
        >>> keys = torch.eye(4).repeat(3, 1, 1); keys[:, 0, 3] = torch.tensor([0.0, 2.0, 6.0])
        >>> path = keyframe_path(keys, frames_between=1)
        >>> path.t.tolist(), path.cam_to_world[:, 0, 3].tolist()
        ([0.0, 0.5, 1.0, 1.5, 2.0], [0.0, 1.0, 2.0, 4.0, 6.0])
    """
    check_shape(keys, "keys", ("K", 4, 4))
    if keys.shape[0] < 1:
        raise ValueError("keys: expected at least one pose, got 0")
    if int(frames_between) < 0:
        raise ValueError(f"frames_between: expected >= 0, got {frames_between}")
    n = int(frames_between) + 1
    poses, times = [], []
    for i in range(len(keys)):
        for j in range(n if i + 1 < len(keys) else 1):
            s = j / n
            poses.append(keys[i] if j == 0 else interpolate_rigid(keys[i], keys[i + 1], s))
            times.append(i + s)
    return CameraPath(torch.stack(poses), torch.tensor(times, dtype=torch.float64))


def look_at(position: torch.Tensor, target: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """Camera-to-world poses looking from ``position`` at ``target``, no roll about ``up``.

    OpenCV axes: z towards the target, x right (normal to ``up``), y down. Where the view is
    along ``up`` (no right direction), x is taken normal to the nearest world axis instead.

    Shape:
        ``(*, 3)``, ``(*, 3)``, ``(3,)`` → ``(*, 4, 4)``, on the inputs' device and dtype.

    Example:
        >>> c2w = look_at(torch.zeros(3), torch.tensor([0.0, 1, 0]), torch.tensor([0.0, 0, 1]))
        >>> c2w[:3, :3].tolist()  # right = +x, down = -z, forward = +y
        [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]
    """
    check_shape(position, "position", ("*", 3))
    check_shape(target, "target", ("*", 3))
    check_shape(up, "up", (3,))
    z = torch.nn.functional.normalize(target - position, dim=-1)
    up = up.to(z).expand_as(z)
    x = torch.linalg.cross(z, up)
    flat = x.norm(dim=-1, keepdim=True) < 1e-6
    if bool(flat.any()):  # looking along up: any axis not along z gives a right direction
        axis = torch.eye(3, dtype=z.dtype, device=z.device)[z.abs().argmin(-1)]
        x = torch.where(flat, torch.linalg.cross(z, axis), x)
    x = torch.nn.functional.normalize(x, dim=-1)
    out = torch.zeros(*z.shape[:-1], 4, 4, dtype=z.dtype, device=z.device)
    out[..., :3, 0], out[..., :3, 1], out[..., :3, 2] = x, torch.linalg.cross(z, x), z
    out[..., :3, 3] = position
    out[..., 3, 3] = 1.0
    return out


def catmull_rom(points: torch.Tensor, t: torch.Tensor, alpha: float = 0.5) -> torch.Tensor:
    """A Catmull-Rom spline through ``points`` at parameters ``t`` (point ``i`` at ``t = i``).

    ``alpha = 0.5`` is the centripetal spline: no cusp or self-intersection within a segment,
    no overshoot on a straight run. The ends are extended by reflecting their neighbour.

    Shape:
        ``(N, D)``, ``(P,)`` in ``[0, N - 1]`` → ``(P, D)``.

    Raises:
        ValueError: for a parameter outside ``[0, N - 1]``.

    Example:
        >>> pts = torch.tensor([[0.0, 0], [1, 1], [2, 0], [3, 1]])
        >>> catmull_rom(pts, torch.tensor([0.0, 1.0, 2.5])).tolist()[:2]
        [[0.0, 0.0], [1.0, 1.0]]
    """
    check_shape(points, "points", ("N", "D"))
    n = points.shape[0]
    t = torch.as_tensor(t, dtype=points.dtype, device=points.device)
    if n == 1:
        return points.expand(t.shape[0], -1).clone()
    if bool(((t < 0) | (t > n - 1)).any()):
        raise ValueError(f"t: expected parameters in [0, {n - 1}], got {t.min().item()}..{t.max().item()}")
    ext = torch.cat([2 * points[:1] - points[1:2], points, 2 * points[-1:] - points[-2:-1]])
    i = t.floor().long().clamp(max=n - 2)
    u = (t - i)[:, None]
    p0, p1, p2, p3 = ext[i], ext[i + 1], ext[i + 2], ext[i + 3]

    def knot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return (b - a).norm(dim=-1, keepdim=True).pow(alpha).clamp(min=1e-9)

    t0 = torch.zeros_like(u)
    t1 = t0 + knot(p0, p1)
    t2 = t1 + knot(p1, p2)
    t3 = t2 + knot(p2, p3)
    tt = t1 + u * (t2 - t1)
    a1 = ((t1 - tt) * p0 + (tt - t0) * p1) / (t1 - t0)
    a2 = ((t2 - tt) * p1 + (tt - t1) * p2) / (t2 - t1)
    a3 = ((t3 - tt) * p2 + (tt - t2) * p3) / (t3 - t2)
    b1 = ((t2 - tt) * a1 + (tt - t0) * a2) / (t2 - t0)
    b2 = ((t3 - tt) * a2 + (tt - t1) * a3) / (t3 - t1)
    return ((t2 - tt) * b1 + (tt - t1) * b2) / (t2 - t1)


def spline_path(
    cam_to_world: torch.Tensor, up: torch.Tensor, focus_depth: float, frames_between: int = 0
) -> CameraPath:
    """A smooth path through cameras (see the module docstring).

    Args:
        cam_to_world: ``(K, 4, 4)`` the cameras, in path order.
        up: ``(3,)`` unit up direction (e.g. :func:`~vadgs.geometry.level_up` of the cameras).
        focus_depth: how far ahead of each camera its look-at point lies.
        frames_between: poses between consecutive cameras, ``>= 0``.

    Returns:
        :class:`CameraPath` of ``(K - 1) * (frames_between + 1) + 1`` poses in ``cam_to_world``'s
        dtype, camera ``i`` at ``t = i``: there at its centre, looking where it looks, without its
        roll.

    Example:
        >>> keys = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
        >>> keys[:, 0, 3] = torch.tensor([0.0, 1.0, 3.0])  # along x, looking along +z
        >>> up = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)  # OpenCV: y down
        >>> path = spline_path(keys, up, 10.0, frames_between=3)
        >>> path.cam_to_world.shape, path.t[:3].tolist(), path.cam_to_world[4, :3, 3].tolist()
        (torch.Size([9, 4, 4]), [0.0, 0.25, 0.5], [1.0, 0.0, 0.0])
    """
    check_shape(cam_to_world, "cam_to_world", ("K", 4, 4))
    if int(frames_between) < 0:
        raise ValueError(f"frames_between: expected >= 0, got {frames_between}")
    centres, targets = cam_to_world[:, :3, 3], cam_to_world[:, :3, 3] + focus_depth * cam_to_world[:, :3, 2]
    n = int(frames_between) + 1
    t = torch.arange((len(cam_to_world) - 1) * n + 1, dtype=torch.float64) / n
    return CameraPath(look_at(catmull_rom(centres, t), catmull_rom(targets, t), up), t)


def focus_point(centres: torch.Tensor, forward: torch.Tensor) -> torch.Tensor | None:
    """The point nearest (least squares) to every optical axis (multinerf's ``focus_point_fn``).

    Args:
        centres: ``(V, 3)`` camera centres.
        forward: ``(V, 3)`` unit viewing directions (each camera's ``z`` axis).

    Returns:
        ``(3,)``, or None when the axes are about parallel (a street) or the point lies behind
        most cameras.

    Example:
        >>> centres = torch.tensor([[-1.0, 0, 0], [0.0, -1, 0], [1.0, 0, 0]])
        >>> focus_point(centres, -centres)  # three cameras looking at the origin
        tensor([0., 0., 0.])
    """
    dims = check_shape(centres, "centres", ("V", 3))
    check_shape(forward, "forward", ("V", 3), dims)
    eye = torch.eye(3, dtype=centres.dtype, device=centres.device)
    proj = eye - forward[:, :, None] * forward[:, None, :]  # (V, 3, 3)
    A, b = proj.sum(0), (proj @ centres[:, :, None]).sum(0)[:, 0]
    eig = torch.linalg.eigvalsh(A)
    if float(eig[0]) < 0.02 * float(eig[-1]):
        return None
    point = torch.linalg.solve(A, b)
    ahead = ((point - centres) * forward).sum(-1) > 0
    return point if float(ahead.double().mean()) > 0.5 else None


def orbit_path(
    cam_to_world: torch.Tensor, up: torch.Tensor, num_frames: int, focus_depth: float = 10.0
) -> CameraPath:
    """A circle around the cameras' centre of attention, looking at it (see the module docstring).

    The centre is :func:`focus_point` of the cameras; where it is None (cameras looking the same
    way), the mean of the points ``focus_depth`` ahead of each camera.

    Args:
        cam_to_world: ``(V, 4, 4)`` the cameras (the first one starts the circle).
        up: ``(3,)`` unit up direction, the circle's axis.
        num_frames: poses on the circle (the last one short of the first: a video loops), ``>= 1``.
        focus_depth: how far ahead of each camera it looks, for the fallback centre.

    Returns:
        :class:`CameraPath` of ``num_frames`` poses in ``cam_to_world``'s dtype, ``t`` the
        fraction of the turn.

    Example:
        >>> c2w = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
        >>> c2w[:, :3, 3] = torch.tensor([[0.0, -4, 0], [4.0, 0, 0], [0.0, 4, 0]])  # around the origin,
        >>> c2w[:, :3, :3] = look_at(c2w[:, :3, 3], torch.zeros(3, 3, dtype=torch.float64),
        ...                          torch.tensor([0.0, 0, 1], dtype=torch.float64))[:, :3, :3]  # facing it
        >>> path = orbit_path(c2w, torch.tensor([0.0, 0, 1], dtype=torch.float64), 4)
        >>> [[round(v, 6) + 0.0 for v in p] for p in path.cam_to_world[:, :3, 3].tolist()]
        [[0.0, -4.0, 0.0], [4.0, 0.0, 0.0], [0.0, 4.0, 0.0], [-4.0, 0.0, 0.0]]
    """
    check_shape(cam_to_world, "cam_to_world", ("V", 4, 4))
    if int(num_frames) < 1:
        raise ValueError(f"num_frames: expected >= 1, got {num_frames}")
    centres, forward = cam_to_world[:, :3, 3], cam_to_world[:, :3, 2]
    up = up.to(cam_to_world)
    centre = focus_point(centres, forward)
    if centre is None:  # cameras looking the same way (a street): the middle of what they look at
        centre = (centres + focus_depth * forward).mean(0)
    offset = centres - centre
    height = float((offset @ up).mean())
    flat = offset - (offset @ up)[:, None] * up
    radius = float(flat.norm(dim=-1).median())
    e1 = flat[0] if float(flat[0].norm()) > 1e-9 * max(radius, 1e-9) else torch.linalg.cross(up, forward[0])
    e1 = torch.nn.functional.normalize(e1 - (e1 @ up) * up, dim=0)
    e2 = torch.linalg.cross(up, e1)
    azimuth = torch.atan2(flat @ e2, flat @ e1)
    turn = torch.remainder(azimuth.diff() + torch.pi, 2 * torch.pi) - torch.pi  # steps in (-pi, pi]
    sense = -1.0 if float(turn.sum()) < 0 else 1.0
    steps = torch.arange(int(num_frames), dtype=cam_to_world.dtype, device=cam_to_world.device)
    angle = sense * 2 * torch.pi * steps / int(num_frames)
    radius = radius if radius > 0 else 1.0
    positions = centre + radius * (angle.cos()[:, None] * e1 + angle.sin()[:, None] * e2) + height * up
    fraction = torch.arange(int(num_frames), dtype=torch.float64) / int(num_frames)
    return CameraPath(look_at(positions, centre.expand_as(positions), up), fraction)
