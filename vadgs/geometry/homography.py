r"""Plane-induced homographies and warping of images and patches with them.

A pixel :math:`\mathbf{p}` of the reference view with depth :math:`z` and a local plane of
normal :math:`\mathbf{n}` (reference camera frame) lies on the plane
:math:`\mathbf{n}^\top \mathbf{X} + d = 0` with :math:`d = -z\,\mathbf{n}^\top K_r^{-1}\tilde{\mathbf{p}}`
(the paper's parametrisation). Points of that plane map into a source view whose pose relative
to the reference is :math:`[R \mid \mathbf{t}]` (``src_from_ref``) by

.. math::

    \tilde{p}' \simeq K_s \left(R - \frac{t\,n^\top}{d}\right) K_r^{-1} \tilde{p}.

Whole-image warps go through :func:`kornia.geometry.transform.warp_perspective`; per-pixel
patch warps (one homography per pixel, as PatchMatch needs) through
:func:`torch.nn.functional.grid_sample` with kornia's pixel normalisation
(``align_corners=True``: integer coordinates are pixel centres). Everything here is
differentiable w.r.t. its floating-point inputs.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.geometry.conversions import normalize_pixel_coordinates
from kornia.geometry.transform import warp_perspective

from vadgs.checks import check_shape

__all__ = [
    "apply_homography",
    "homography_warp",
    "plane_distance",
    "plane_homography",
    "warp_patches",
]


def plane_distance(depth: torch.Tensor, normals: torch.Tensor, rays: torch.Tensor) -> torch.Tensor:
    r"""Plane offset :math:`d = -z\,\mathbf{n}^\top K^{-1}\tilde{\mathbf{p}}` of per-pixel planes.

    Args:
        depth: ``(*,)`` z-depths.
        normals: ``(*, 3)`` unit normals in the camera frame.
        rays: ``(*, 3)`` back-projected pixels :math:`K^{-1}\tilde{\mathbf{p}}` (z = 1).

    Returns:
        ``(*,)`` plane offsets (positive for a plane facing the camera).

    Example:
        >>> plane_distance(torch.tensor([2.0]), torch.tensor([[0.0, 0, -1]]), torch.tensor([[0.0, 0, 1]]))
        tensor([2.])
    """
    return -depth * (normals * rays).sum(-1)


def plane_homography(
    K_ref: torch.Tensor,
    K_src: torch.Tensor,
    src_from_ref: torch.Tensor,
    normals: torch.Tensor,
    distances: torch.Tensor,
) -> torch.Tensor:
    r"""Homographies :math:`K_s (R - \mathbf{t}\mathbf{n}^\top / d) K_r^{-1}` of per-pixel planes.

    Args:
        K_ref: ``(B, 3, 3)`` reference intrinsics.
        K_src: ``(B, 3, 3)`` source intrinsics.
        src_from_ref: ``(B, 4, 4)`` rigid transform from the reference to the source camera.
        normals: ``(B, *, 3)`` plane normals in the reference camera frame.
        distances: ``(B, *)`` plane offsets :math:`d` (see :func:`plane_distance`).

    Returns:
        ``(B, *, 3, 3)`` homographies mapping reference pixels to source pixels.

    Shape:
        Any number of plane dimensions ``*`` (one plane, or one per pixel ``(H, W)``).

    Example:
        >>> K = torch.tensor([[[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]]])
        >>> T = torch.eye(4)[None]; T[0, 0, 3] = -0.1  # source 0.1 to the right of the reference
        >>> H = plane_homography(K, K, T, torch.tensor([[0.0, 0, -1]]), torch.tensor([2.0]))
        >>> H[0] @ torch.tensor([50.0, 50, 1])  # a point on the plane at z = 2 shifts 5 px left
        tensor([45., 50.,  1.])
    """
    dims = check_shape(K_ref, "K_ref", ("B", 3, 3))
    check_shape(K_src, "K_src", ("B", 3, 3), dims)
    check_shape(src_from_ref, "src_from_ref", ("B", 4, 4), dims)
    if normals.ndim < 2 or normals.shape[0] != dims["B"] or normals.shape[-1] != 3:
        raise ValueError(f"normals: expected shape (B={dims['B']}, *, 3), got {tuple(normals.shape)}")
    if distances.shape != normals.shape[:-1]:
        raise ValueError(
            f"distances: expected shape {tuple(normals.shape[:-1])} (normals without the last "
            f"dimension), got {tuple(distances.shape)}"
        )
    extra = normals.ndim - 2
    view = (dims["B"],) + (1,) * extra + (3, 3)
    rot = src_from_ref[:, :3, :3].reshape(view)
    t = src_from_ref[:, :3, 3].reshape((dims["B"],) + (1,) * extra + (3, 1))
    mid = rot - t * normals.unsqueeze(-2) / distances[..., None, None]
    return K_src.reshape(view) @ mid @ torch.linalg.inv(K_ref).reshape(view)


def apply_homography(H: torch.Tensor, points: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """Apply homographies ``(*, 3, 3)`` to pixel points ``(*, 2)`` (broadcast), dehomogenised.

    Points mapped to infinity (third coordinate near zero) get large but finite coordinates.

    Example:
        >>> apply_homography(torch.eye(3) * 2, torch.tensor([3.0, 4.0]))
        tensor([3., 4.])
    """
    xyz = (H[..., :, :2] @ points.unsqueeze(-1)).squeeze(-1) + H[..., :, 2]
    w = xyz[..., 2:]
    w = torch.where(w.abs() < eps, torch.full_like(w, eps), w)
    return xyz[..., :2] / w


def homography_warp(
    src: torch.Tensor,
    H_ref_to_src: torch.Tensor,
    dsize: tuple[int, int],
    mode: str = "bilinear",
    padding_mode: str = "zeros",
) -> torch.Tensor:
    """Warp source images into the reference view with one homography per image.

    ``out[v, u] = src(H (u, v, 1))``: the source image as seen through the plane by the
    reference camera. A thin wrapper over :func:`kornia.geometry.transform.warp_perspective`.

    Args:
        src: ``(B, C, H_s, W_s)`` source images.
        H_ref_to_src: ``(B, 3, 3)`` homographies from reference to source pixels.
        dsize: ``(H, W)`` of the output.
        mode: interpolation, ``"bilinear"`` or ``"nearest"``.
        padding_mode: ``"zeros"``, ``"border"`` or ``"reflection"``.

    Returns:
        ``(B, C, H, W)`` warped images. Differentiable w.r.t. ``src`` and ``H_ref_to_src``.
    """
    dims = check_shape(src, "src", ("B", "C", "H", "W"))
    check_shape(H_ref_to_src, "H_ref_to_src", ("B", 3, 3), dims)
    return warp_perspective(
        src, torch.linalg.inv(H_ref_to_src), dsize, mode=mode, padding_mode=padding_mode, align_corners=True
    )


def warp_patches(
    src: torch.Tensor,
    H: torch.Tensor,
    centers: torch.Tensor,
    offsets: torch.Tensor,
    mode: str = "bilinear",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Sample patches of source images through per-patch homographies.

    For patch ``p`` with centre ``c_p`` (reference pixel) and offsets ``o_s``, samples the source
    image at ``H_p (c_p + o_s)``. This is the inner operation of patch-based MVS.

    Args:
        src: ``(B, C, H_s, W_s)`` source images.
        H: ``(B, P, 3, 3)`` one homography per patch (reference pixel → source pixel).
        centers: ``(B, P, 2)`` or ``(P, 2)`` patch centres ``(x, y)`` in the reference image.
        offsets: ``(S, 2)`` sample offsets ``(x, y)`` relative to the centre.
        mode: ``"bilinear"`` or ``"nearest"``.

    Returns:
        A tuple ``(patches, inside)``: sampled values ``(B, C, P, S)`` (zero outside the image)
        and a boolean mask ``(B, P, S)`` of samples that fall inside the source image.
        Differentiable w.r.t. ``src`` and ``H``.

    Example:
        >>> img = torch.arange(16.0).reshape(1, 1, 4, 4)
        >>> H = torch.eye(3).expand(1, 1, 3, 3)
        >>> centers, offsets = torch.tensor([[1.0, 1.0]]), torch.tensor([[0.0, 0], [1, 0]])
        >>> patches, inside = warp_patches(img, H, centers, offsets)
        >>> patches
        tensor([[[[5., 6.]]]])
    """
    dims = check_shape(src, "src", ("B", "C", "Hs", "Ws"))
    check_shape(H, "H", ("B", "P", 3, 3), dims)
    if centers.ndim == 2:
        centers = centers.unsqueeze(0).expand(dims["B"], -1, -1)
    check_shape(centers, "centers", ("B", "P", 2), dims)
    check_shape(offsets, "offsets", ("S", 2))
    pts = centers.unsqueeze(2) + offsets  # (B, P, S, 2)
    xy = apply_homography(H.unsqueeze(2), pts)  # (B, P, S, 2)
    h, w = dims["Hs"], dims["Ws"]
    x, y = xy[..., 0], xy[..., 1]
    inside = (x >= -0.5) & (x <= w - 0.5) & (y >= -0.5) & (y <= h - 0.5)
    grid = normalize_pixel_coordinates(xy, h, w)
    out = F.grid_sample(src, grid, mode=mode, padding_mode="zeros", align_corners=True)
    return out, inside
