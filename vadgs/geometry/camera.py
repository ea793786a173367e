"""Pinhole cameras: batched intrinsics and extrinsics, projection and back-projection.

And which cameras see which points (:func:`observing_views`: the input of the voxels' visibility
sets, :mod:`vadgs.geometry.voxel`).

Conventions (``docs/conventions.md``): OpenCV camera axes (x right, y down, z forward),
``K (B, 3, 3)``, ``world_to_cam (B, 4, 4)`` maps world points into the camera frame,
``cam_to_world`` is its inverse, integer pixel coordinates are pixel centres, pixel points are
``(x, y)`` and image sizes ``(H, W)``. Depth means z-depth along the optical axis.

The heavy lifting is kornia's (:func:`kornia.geometry.linalg.transform_points`,
:func:`kornia.geometry.depth.depth_to_3d_v2`); this module fixes names and shapes and adds the
checks and the small pieces kornia lacks (rigid inversion, object-frame cameras).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from kornia.geometry.depth import depth_to_3d_v2
from kornia.geometry.linalg import transform_points

from vadgs.checks import check_finite, check_intrinsics, check_shape, check_size, checks_enabled

__all__ = [
    "Cameras",
    "backproject_depth",
    "camera_centers",
    "cameras_in_object_frame",
    "invert_rigid",
    "level_up",
    "observing_views",
    "pixel_grid",
    "project_points",
    "relative_pose",
    "scale_intrinsics",
    "shift_K",
]


def _check_rigid_last_row(T: torch.Tensor, name: str) -> None:
    """Value check of ``(*, 4, 4)`` transforms: finite, last row ``(0, 0, 0, 1)`` (within 1e-5).

    Example:
        >>> _check_rigid_last_row(torch.zeros(4, 4), "transform")
        Traceback (most recent call last):
        ...
        ValueError: transform: expected a transform with last row (0, 0, 0, 1), got [0.0, 0.0, 0.0, 0.0]
    """
    check_finite(T, name)
    if checks_enabled() and T.numel():
        row = T.detach()[..., 3, :].reshape(-1, 4)
        want = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=row.dtype, device=row.device)
        bad = ((row - want).abs() > 1e-5).any(-1)
        if bool(bad.any()):
            got = row[int(bad.nonzero()[0, 0])].tolist()
            raise ValueError(f"{name}: expected a transform with last row (0, 0, 0, 1), got {got}")


def invert_rigid(transform: torch.Tensor) -> torch.Tensor:
    """Invert rigid transforms ``[R | t]`` in closed form (``[R^T | -R^T t]``).

    Differentiable.

    Args:
        transform: rigid transforms of shape ``(*, 4, 4)``.

    Returns:
        The inverse transforms, ``(*, 4, 4)``.

    Example:
        >>> T = torch.eye(4); T[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
        >>> invert_rigid(T)[:3, 3]
        tensor([-1., -2., -3.])
    """
    check_shape(transform, "transform", ("*", 4, 4))
    _check_rigid_last_row(transform, "transform")
    rot = transform[..., :3, :3]
    trans = transform[..., :3, 3:]
    rot_t = rot.transpose(-1, -2)
    out = torch.zeros_like(transform)
    out[..., :3, :3] = rot_t
    out[..., :3, 3:] = -rot_t @ trans
    out[..., 3, 3] = 1
    return out


def relative_pose(world_to_ref: torch.Tensor, world_to_src: torch.Tensor) -> torch.Tensor:
    """Return ``src_from_ref = world_to_src @ ref_to_world``: ref camera points into the source.

    Args:
        world_to_ref: ``(*, 4, 4)`` world-to-camera transforms of the reference views.
        world_to_src: ``(*, 4, 4)`` world-to-camera transforms of the source views
            (broadcast against ``world_to_ref``).

    Returns:
        ``(*, 4, 4)`` transforms mapping reference-camera coordinates to source-camera ones.
    """
    check_shape(world_to_ref, "world_to_ref", ("*", 4, 4))
    check_shape(world_to_src, "world_to_src", ("*", 4, 4))
    return world_to_src @ invert_rigid(world_to_ref)


def camera_centers(world_to_cam: torch.Tensor) -> torch.Tensor:
    """Camera centres in world coordinates, ``(*, 3)``, from ``world_to_cam (*, 4, 4)``."""
    check_shape(world_to_cam, "world_to_cam", ("*", 4, 4))
    rot = world_to_cam[..., :3, :3]
    return -(rot.transpose(-1, -2) @ world_to_cam[..., :3, 3:]).squeeze(-1)


def project_points(
    points: torch.Tensor, K: torch.Tensor, world_to_cam: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Project 3D points into pixels.

    Differentiable w.r.t. points, intrinsics and poses. Points at or behind the camera get
    non-finite or meaningless pixel coordinates: mask them with ``depth > 0``.

    Args:
        points: ``(B, N, 3)`` points in world coordinates (or camera coordinates when
            ``world_to_cam`` is None).
        K: ``(B, 3, 3)`` intrinsics.
        world_to_cam: optional ``(B, 4, 4)`` world-to-camera transforms.

    Returns:
        A tuple ``(uv, depth)``: pixel coordinates ``(B, N, 2)`` as ``(x, y)`` with pixel centres
        at integers, and z-depths ``(B, N)``.

    Example:
        >>> K = torch.tensor([[[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]]])
        >>> uv, z = project_points(torch.tensor([[[0.0, 0.0, 2.0]]]), K)
        >>> uv, z
        (tensor([[[50., 40.]]]), tensor([[2.]]))
    """
    dims = check_shape(points, "points", ("B", "N", 3))
    check_shape(K, "K", ("B", 3, 3), dims)
    check_intrinsics(K)
    if world_to_cam is not None:
        check_shape(world_to_cam, "world_to_cam", ("B", 4, 4), dims)
        _check_rigid_last_row(world_to_cam, "world_to_cam")
        points = transform_points(world_to_cam, points)
    z = points[..., 2]
    xy = points[..., :2] / z.unsqueeze(-1)
    uv = xy @ K[:, :2, :2].transpose(-1, -2) + K[:, None, :2, 2]
    return uv, z


def pixel_grid(
    image_size: tuple[int, int], device: torch.device | None = None, dtype: torch.dtype | None = None
) -> torch.Tensor:
    """Pixel-centre coordinates ``(H, W, 2)`` as ``(x, y)``: ``grid[v, u] = (u, v)``."""
    h, w = check_size(image_size)
    ys, xs = torch.meshgrid(
        torch.arange(h, device=device, dtype=dtype or torch.float32),
        torch.arange(w, device=device, dtype=dtype or torch.float32),
        indexing="ij",
    )
    return torch.stack([xs, ys], dim=-1)


def backproject_depth(
    depth: torch.Tensor,
    K: torch.Tensor,
    cam_to_world: torch.Tensor | None = None,
    method: str = "kornia",
) -> torch.Tensor:
    r"""Back-project z-depth maps to 3D points: pixel ``(u, v)`` at depth ``z`` to ``z K^{-1} (u, v, 1)^T``.

    Differentiable w.r.t. depth, intrinsics and pose. The two methods give the same points to float
    rounding (a few ulps) for intrinsics without skew:

    - ``"kornia"``: :func:`kornia.geometry.depth.depth_to_3d_v2`, the rays
      ``((u - cx) / fx, (v - cy) / fy, 1)`` (the skew ``K[0, 1]`` is not read), the pose applied by
      :func:`kornia.geometry.linalg.transform_points`;
    - ``"inverse"``: the rays ``K^{-1} (u, v, 1)^T`` by a matrix inverse and product (any ``K``,
      skew included), the pose applied as ``R X + t``: the arithmetic of :mod:`vadgs.mvs`
      (consistency and fusion), whose results it keeps bit for bit.

    .. math::

        X(u, v) = T_{cam \to world} \begin{pmatrix} z(u, v)\, K^{-1} (u, v, 1)^T \\ 1 \end{pmatrix}

    Args:
        depth: ``(B, 1, H, W)`` z-depth maps.
        K: ``(B, 3, 3)`` intrinsics.
        cam_to_world: optional ``(B, 4, 4)``; when given the points are in world coordinates,
            otherwise in camera coordinates.
        method: ``"kornia"`` or ``"inverse"`` (see above).

    Returns:
        ``(B, 3, H, W)`` points.

    Raises:
        ValueError: for a shape other than the above, intrinsics without positive focal lengths,
            or another ``method``.

    Example:
        >>> K = torch.tensor([[[2.0, 0, 1], [0, 2.0, 1], [0, 0, 1]]])
        >>> backproject_depth(torch.full((1, 1, 3, 3), 4.0), K)[0, :, 1, 1]
        tensor([0., 0., 4.])
        >>> backproject_depth(torch.full((1, 1, 3, 3), 4.0), K, method="inverse")[0, :, 2, 2]
        tensor([2., 2., 4.])
    """
    dims = check_shape(depth, "depth", ("B", 1, "H", "W"))
    check_shape(K, "K", ("B", 3, 3), dims)
    check_intrinsics(K)
    if cam_to_world is not None:
        check_shape(cam_to_world, "cam_to_world", ("B", 4, 4), dims)
    b, h, w = dims["B"], dims["H"], dims["W"]
    if method == "inverse":
        grid = pixel_grid((h, w), device=depth.device, dtype=depth.dtype).permute(2, 0, 1)  # (2, H, W)
        pix = torch.cat([grid, torch.ones_like(grid[:1])]).reshape(3, h * w)
        pts = (torch.linalg.inv(K) @ pix) * depth.reshape(b, 1, h * w)  # (B, 3, P)
        if cam_to_world is not None:
            pts = cam_to_world[:, :3, :3] @ pts + cam_to_world[:, :3, 3:]
        return pts.reshape(b, 3, h, w)
    if method != "kornia":
        raise ValueError(f"method: expected 'kornia' or 'inverse', got {method!r}")
    pts = depth_to_3d_v2(depth[:, 0], K)  # (B, H, W, 3)
    if cam_to_world is not None:
        pts = transform_points(cam_to_world, pts.reshape(b, h * w, 3)).reshape(b, h, w, 3)
    return pts.permute(0, 3, 1, 2)


def scale_intrinsics(K: torch.Tensor, scale: float | tuple[float, float]) -> torch.Tensor:
    """Intrinsics for an image resized by ``scale``, keeping pixel centres at integers.

    With pixel centres at integers a resize by ``s`` maps ``x -> s (x + 0.5) - 0.5``, so
    ``f' = s f`` and ``c' = s (c + 0.5) - 0.5``. ``scale`` may be ``(sx, sy)`` for a resize with
    different factors along x and y (e.g. to ``ceil(W / 2) x ceil(H / 2)``).

    Example:
        >>> K = torch.tensor([[384.0, 0, 239.5], [0, 384.0, 143.5], [0, 0, 1]])
        >>> scale_intrinsics(K, 0.5)[:2]
        tensor([[192.0000,   0.0000, 119.5000],
                [  0.0000, 192.0000,  71.5000]])
        >>> scale_intrinsics(K, (0.5, 0.25))[1]
        tensor([ 0.0000, 96.0000, 35.5000])
    """
    check_shape(K, "K", ("*", 3, 3))
    sx, sy = (scale, scale) if isinstance(scale, (int, float)) else scale
    out = K.clone()
    out[..., 0, :] = K[..., 0, :] * sx
    out[..., 1, :] = K[..., 1, :] * sy
    out[..., 0, 2] += 0.5 * sx - 0.5
    out[..., 1, 2] += 0.5 * sy - 0.5
    return out


def shift_K(K: torch.Tensor, x0: int, y0: int) -> torch.Tensor:
    """Intrinsics ``(..., 3, 3)`` of the crop whose top-left corner is pixel ``(x0, y0)`` (a copy).

    Example:
        >>> shift_K(torch.eye(3), 2, 5)[:2, 2].tolist()
        [-2.0, -5.0]
    """
    K = K.clone()
    K[..., 0, 2] -= x0
    K[..., 1, 2] -= y0
    return K


def cameras_in_object_frame(world_to_cam: torch.Tensor, object_to_world: torch.Tensor) -> torch.Tensor:
    """Express cameras in a rigid object's own frame: ``object_to_cam = world_to_cam @ object_to_world``.

    A rigidly moving object is static in its own frame, so multi-view stereo on it runs on
    these poses as on a static scene (paper, "MVS Reconstruction from Selected Views").

    Args:
        world_to_cam: ``(B, 4, 4)`` per-view world-to-camera transforms.
        object_to_world: ``(B, 4, 4)`` the object's pose at each view's timestamp.

    Returns:
        ``(B, 4, 4)`` object-to-camera transforms: use them as ``world_to_cam`` of the views.
    """
    dims = check_shape(world_to_cam, "world_to_cam", ("B", 4, 4))
    check_shape(object_to_world, "object_to_world", ("B", 4, 4), dims)
    return world_to_cam @ object_to_world


@dataclass(frozen=True)
class Cameras:
    """A batch of pinhole cameras sharing one image size.

    Attributes:
        K: ``(B, 3, 3)`` intrinsics.
        world_to_cam: ``(B, 4, 4)`` world-to-camera transforms.
        image_size: ``(H, W)``.

    Example:
        >>> world_to_cam = torch.eye(4)[None]; world_to_cam[0, :3, 3] = torch.tensor([1.0, 2.0, 5.0])
        >>> cams = Cameras(torch.eye(3)[None], world_to_cam, (4, 6))
        >>> len(cams), cams.cam_to_world.shape, cams.centers
        (1, torch.Size([1, 4, 4]), tensor([[-1., -2., -5.]]))
    """

    K: torch.Tensor
    world_to_cam: torch.Tensor
    image_size: tuple[int, int]

    def __post_init__(self) -> None:
        dims = check_shape(self.K, "K", ("B", 3, 3))
        check_shape(self.world_to_cam, "world_to_cam", ("B", 4, 4), dims)
        check_finite(self.K, "K")
        check_finite(self.world_to_cam, "world_to_cam")
        object.__setattr__(self, "image_size", check_size(self.image_size))

    @classmethod
    def from_cam_to_world(
        cls, K: torch.Tensor, cam_to_world: torch.Tensor, image_size: tuple[int, int]
    ) -> Cameras:
        """Build cameras from camera-to-world transforms."""
        check_shape(cam_to_world, "cam_to_world", ("B", 4, 4))
        return cls(K, invert_rigid(cam_to_world), image_size)

    def __len__(self) -> int:
        return self.K.shape[0]

    def __getitem__(self, idx: int | slice | torch.Tensor | list[int]) -> Cameras:
        if isinstance(idx, int):
            idx = [idx]
        return Cameras(self.K[idx], self.world_to_cam[idx], self.image_size)

    @property
    def cam_to_world(self) -> torch.Tensor:
        """``(B, 4, 4)`` camera-to-world transforms."""
        return invert_rigid(self.world_to_cam)

    @property
    def centers(self) -> torch.Tensor:
        """``(B, 3)`` camera centres in world coordinates."""
        return camera_centers(self.world_to_cam)

    @property
    def device(self) -> torch.device:
        """The device of the tensors."""
        return self.K.device

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Cameras:
        """Move (and optionally cast) to a device, as :meth:`torch.Tensor.to`."""
        return Cameras(self.K.to(device, dtype), self.world_to_cam.to(device, dtype), self.image_size)

    def rescale(self, scale: float) -> Cameras:
        """Cameras for images resized by ``scale`` (see :func:`scale_intrinsics`)."""
        h, w = self.image_size
        return Cameras(
            scale_intrinsics(self.K, scale), self.world_to_cam, (round(h * scale), round(w * scale))
        )

    def in_object_frame(self, object_to_world: torch.Tensor) -> Cameras:
        """These cameras in a rigid object's frame (see :func:`cameras_in_object_frame`)."""
        return Cameras(self.K, cameras_in_object_frame(self.world_to_cam, object_to_world), self.image_size)


def level_up(cam_to_world: torch.Tensor) -> torch.Tensor:
    """The up direction ``(3,)`` (unit, float64) of cameras held level, from their image axes.

    A photo held level has a horizontal image row, whatever its pitch: the up is the direction
    normal to the cameras' horizontal image axes (the smallest eigenvector of their scatter),
    signed as the ``-y`` of the photos not sideways. A camera's horizontal axis is its ``x``, or
    its ``y`` for a photo stored sideways (its EXIF orientation tag, which COLMAP and vadgs
    ignore, shows it upright): the one more normal to the current estimate, starting from the
    mean ``-y``; three rounds. Where the axes leave the up open (every camera turned the same
    way) the estimate nearest to the previous one is kept. Unlike the mean ``-y``, which leans
    towards the object of cameras looking down at it, exact for level cameras.

    Shape:
        ``(V, 4, 4)`` (or ``(V, 3, 3)``) OpenCV camera-to-world → ``(3,)``, on the input's device.

    Example:
        >>> import math
        >>> def cam(yaw, pitch):  # OpenCV axes (x right, y down, z forward) in a z-up world
        ...     c, s = math.cos(pitch), math.sin(pitch)
        ...     f = torch.tensor([c * math.cos(yaw), c * math.sin(yaw), -s])
        ...     r = torch.tensor([math.sin(yaw), -math.cos(yaw), 0.0])
        ...     return torch.stack([r, torch.linalg.cross(f, r), f], 1)
        >>> c2w = torch.stack([cam(a, 0.6) for a in (0.0, 2.0, 4.0)])  # looking down
        >>> [round(v, 6) + 0.0 for v in level_up(c2w).tolist()], float(-c2w[:, 2, 1].mean()) < 0.95
        ([0.0, 0.0, 1.0], True)
    """
    rot = cam_to_world[..., :3, :3].double()
    x, y = rot[:, :, 0], rot[:, :, 1]
    start = torch.nn.functional.normalize(-y.mean(0), dim=0)
    up = start
    eye = torch.eye(3, dtype=torch.float64, device=rot.device)
    for _ in range(3):
        sideways = (x @ up).abs() > (y @ up).abs()
        horizontal = torch.where(sideways[:, None], y, x)
        scatter = horizontal.T @ horizontal / len(rot) + 1e-4 * (eye - up[:, None] * up[None])
        up = torch.linalg.eigh(scatter).eigenvectors[:, 0]
        ref = -y[~sideways].sum(0) if bool((~sideways).any()) else start  # the level photos' up
        up = -up if float(up @ ref) < 0 else up
    return up


def observing_views(
    points: torch.Tensor,
    cameras: Cameras,
    view_ids: Sequence[int] | torch.Tensor | None = None,
    groups: tuple[torch.Tensor, torch.Tensor] | None = None,
    near: float = 0.1,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Which cameras see which points: points in front of a camera that project inside its image.

    For LiDAR, a point is observed by the cameras *of its own frame* that see it: pass
    ``groups=(point_frame, camera_frame)`` so that each point is tested only against the cameras
    of the same group (processed group by group, so memory stays ``O(N_group × B_group)``).
    Occlusion is not tested here; the voxel z-buffer resolves it.

    Args:
        points: ``(N, 3)`` world points.
        cameras: ``B`` cameras.
        view_ids: ``(B,)`` the view id of each camera (default ``0..B-1``).
        groups: optional ``(point_group (N,), camera_group (B,))`` integer labels.
        near: minimum z-depth.

    Returns:
        COO pairs ``(point_idx, view_idx)``, each ``(P,)`` int64, sorted by point.

    Example:
        >>> K = torch.tensor([[[10.0, 0, 4.5], [0, 10.0, 4.5], [0, 0, 1]]])
        >>> cams = Cameras(K, torch.eye(4)[None], (10, 10))
        >>> observing_views(torch.tensor([[0.0, 0, 2], [0, 0, -2], [5, 0, 1]]), cams)
        (tensor([0]), tensor([0]))
    """
    check_shape(points, "points", ("N", 3))
    b = len(cameras)
    ids = torch.arange(b) if view_ids is None else torch.as_tensor(view_ids, dtype=torch.int64)
    if ids.shape != (b,):
        raise ValueError(f"view_ids: expected shape ({b},), got {tuple(ids.shape)}")
    ids = ids.to(points.device)
    if groups is None:
        point_sel = [torch.arange(points.shape[0], device=points.device)]
        cam_sel = [torch.arange(b, device=points.device)]
    else:
        pg, cg = groups
        check_shape(pg, "groups[0]", (points.shape[0],))
        check_shape(cg, "groups[1]", (b,))
        labels = torch.unique(cg)
        point_sel = [(pg == g).nonzero().squeeze(1) for g in labels]
        cam_sel = [(cg == g).nonzero().squeeze(1) for g in labels]
    h, w = cameras.image_size
    out_p, out_v = [], []
    for psel, csel in zip(point_sel, cam_sel):
        if psel.numel() == 0:
            continue
        sub = cameras[csel]
        uv, z = project_points(points[psel].expand(len(sub), -1, -1), sub.K, sub.world_to_cam)
        u, v = uv[..., 0], uv[..., 1]
        ok = (z > near) & (u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5)
        bi, pi = ok.nonzero(as_tuple=True)
        out_p.append(psel[pi])
        out_v.append(ids[csel[bi]])
    if not out_p:
        empty = torch.zeros(0, dtype=torch.int64, device=points.device)
        return empty, empty.clone()
    pidx, vidx = torch.cat(out_p), torch.cat(out_v)
    order = torch.argsort(pidx * (int(ids.max()) + 1) + vidx)
    return pidx[order], vidx[order]
