r"""Lens undistortion for the dataset readers: OpenCV's distortion model → a pinhole camera.

The renderer, the visibility index and PatchMatch all assume pinhole cameras. Readers of
datasets whose images are distorted (Waymo, DGP or nuScenes tables that carry coefficients)
therefore *undistort the images they load*: every view the trainer sees is pinhole, and the
``K`` a reader reports is the pinhole ``K`` of the undistorted image.

The model is OpenCV's (``cv2.projectPoints``), coefficients in OpenCV order
``k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4]]]`` (4, 5, 8 or 12 of them). A point
``(x, y)`` on the normalised image plane (``z = 1``) with ``r² = x² + y²`` lands at

.. math::

    x_d = x \frac{1 + k_1 r^2 + k_2 r^4 + k_3 r^6}{1 + k_4 r^2 + k_5 r^4 + k_6 r^6}
          + 2 p_1 x y + p_2 (r^2 + 2 x^2) + s_1 r^2 + s_2 r^4

    y_d = y \frac{1 + k_1 r^2 + k_2 r^4 + k_3 r^6}{1 + k_4 r^2 + k_5 r^4 + k_6 r^6}
          + p_1 (r^2 + 2 y^2) + 2 p_2 x y + s_3 r^2 + s_4 r^4

and then at pixel ``K_raw @ (x_d, y_d, 1)``.

**The pinhole K** (:func:`undistorted_intrinsics`): the undistorted image keeps the raw image's
size, principal point and aspect ratio; its focal lengths are the raw ones times the *smallest*
factor for which every pixel of the undistorted image has a source inside the raw image (the
widest field of view without empty borders, as ``cv2.getOptimalNewCameraMatrix`` with
``alpha=0``, but keeping the principal point and ``fx / fy``). For Waymo's real cameras
(``k1 ≈ 0.04``, ``k2 ≈ -0.33``) the factor is 0.9999-1.0025 (the image edges lie near the
radius where the two radial terms cancel), so ``K`` barely changes while the pixels move by up to
several pixels near the corners.

The resampling map (:func:`undistortion_map`) is ``cv2.initUndistortRectifyMap``'s: for each pixel
of the undistorted image, the raw pixel it comes from. :func:`remap` samples an image through it,
bilinearly for colours and with ``mode="nearest"`` for per-pixel labels (instance maps) and depth.
:class:`ImageUndistorter` holds one camera's settings and its map. Only :func:`distort_points` is
differentiable; readers run the rest once per image, under no gradient.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from vadgs.checks import check_intrinsics, check_shape, check_size

__all__ = [
    "OPENCV_DISTORTION",
    "ImageUndistorter",
    "distort_points",
    "distortion_coefficients",
    "remap",
    "undistorted_intrinsics",
    "undistortion_map",
]

#: OpenCV's distortion coefficients, in OpenCV's order.
OPENCV_DISTORTION = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4")
_LENGTHS = (4, 5, 8, 12)


def distortion_coefficients(values: Sequence[float] | torch.Tensor, name: str = "distortion") -> torch.Tensor:
    """OpenCV distortion coefficients as a ``(12,)`` float64 tensor (missing ones are 0).

    Args:
        values: 4, 5, 8 or 12 coefficients in OpenCV order (:data:`OPENCV_DISTORTION`).
        name: the argument's name in error messages.

    Raises:
        ValueError: if there are not 4, 5, 8 or 12 finite numbers.

    Example:
        >>> distortion_coefficients([0.1, -0.3, 0.0, 0.0, 0.01]).tolist()[:6]
        [0.1, -0.3, 0.0, 0.0, 0.01, 0.0]
    """
    try:
        d = torch.as_tensor(values, dtype=torch.float64).flatten().cpu()
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"{name}: expected 4, 5, 8 or 12 numbers (OpenCV order), got {values!r}") from None
    if d.numel() not in _LENGTHS:
        raise ValueError(
            f"{name}: expected 4, 5, 8 or 12 coefficients {OPENCV_DISTORTION} (OpenCV order), got {d.numel()}"
        )
    if not bool(torch.isfinite(d).all()):
        raise ValueError(f"{name}: expected finite coefficients, got {d.tolist()}")
    return F.pad(d, (0, 12 - d.numel()))


def distort_points(points: torch.Tensor, distortion: torch.Tensor) -> torch.Tensor:
    """Apply OpenCV's lens distortion to points on the normalised image plane.

    See the module docstring for the formula. Differentiable w.r.t. ``points`` and
    ``distortion``.

    Args:
        points: ``(..., 2)`` undistorted normalised coordinates ``(x, y) = (X / Z, Y / Z)``.
        distortion: ``(12,)`` coefficients from :func:`distortion_coefficients`.

    Returns:
        ``(..., 2)`` distorted normalised coordinates (same dtype and device as ``points``).

    Shape:
        - points: :math:`(*, 2)`
        - distortion: :math:`(12,)`

    Example:
        >>> d = distortion_coefficients([0.0, 0.0, 0.0, 0.0, 0.0])
        >>> distort_points(torch.tensor([[0.3, -0.2]]), d)
        tensor([[ 0.3000, -0.2000]])
        >>> distort_points(torch.tensor([[0.5, 0.0]]), distortion_coefficients([-0.2, 0.0, 0.0, 0.0]))
        tensor([[0.4750, 0.0000]])
    """
    check_shape(points, "points", ("*", 2))
    check_shape(distortion, "distortion", (12,))
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = distortion.to(points).unbind()
    x, y = points[..., 0], points[..., 1]
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    radial = (1 + k1 * r2 + k2 * r4 + k3 * r6) / (1 + k4 * r2 + k5 * r4 + k6 * r6)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r4
    return torch.stack([xd, yd], -1)


def _raw_pixels(
    pixels: torch.Tensor, K_raw: torch.Tensor, new_K: torch.Tensor, d: torch.Tensor
) -> torch.Tensor:
    """Pixels of the pinhole image ``new_K`` → where they come from in the raw (distorted) image."""
    ones = torch.ones_like(pixels[..., :1])
    normalised = torch.cat([pixels, ones], -1) @ torch.linalg.inv(new_K).T
    xy = distort_points(normalised[..., :2] / normalised[..., 2:], d)
    return (torch.cat([xy, ones], -1) @ K_raw.T)[..., :2]


def _radius_monotonic(d: torch.Tensor, r_max: float) -> bool:
    """Whether the radial part ``r · radial(r)`` keeps increasing up to ``r_max`` (no fold-over)."""
    radial_only = d * torch.tensor([1, 1, 0, 0, 1, 1, 1, 1, 0, 0, 0, 0], dtype=d.dtype)
    r = torch.linspace(0.0, r_max, 2049, dtype=torch.float64)
    rd = distort_points(torch.stack([r, torch.zeros_like(r)], -1), radial_only)[:, 0]
    return bool((rd.diff() > 0).all())


def _scaled(K: torch.Tensor, factor: float) -> torch.Tensor:
    out = K.clone()
    out[:2, :2] *= factor
    return out


def _pinhole(K: torch.Tensor, name: str = "K") -> torch.Tensor:
    """``K (3, 3)`` checked (:func:`~vadgs.checks.check_intrinsics`), as float64."""
    check_shape(K, name, (3, 3))
    check_intrinsics(K, name, pinhole=True)
    return K.double()


def undistorted_intrinsics(
    K: torch.Tensor, distortion: torch.Tensor, image_size: Sequence[int], tolerance: float = 1e-9
) -> torch.Tensor:
    """The pinhole ``K`` of the undistorted image: the widest view with a source for every pixel.

    Keeps the principal point, skew-to-focal ratio and aspect ratio of ``K`` and scales the focal
    lengths by the smallest factor ``a`` for which every pixel centre of the undistorted image
    (same size as the raw one) maps inside the raw image (``[-0.5, W - 0.5] × [-0.5, H - 0.5]``)
    while the radial distortion stays monotonic (no fold-over) over the image. ``a`` is found by
    bisection on the image border. Without distortion it returns ``K`` (as float64).

    Args:
        K: ``(3, 3)`` raw intrinsics (pixel centres at integers).
        distortion: ``(12,)`` from :func:`distortion_coefficients`.
        image_size: ``(H, W)`` of the raw image (and of the undistorted one).
        tolerance: relative precision of ``a``.

    Returns:
        ``(3, 3)`` float64 pinhole intrinsics.

    Raises:
        ValueError: on a bad ``K`` or ``image_size``, or if no factor in ``[1/64, 64]`` works (a
            distortion that folds over inside the image).

    Example:
        >>> K = torch.tensor([[100.0, 0.0, 49.5], [0.0, 100.0, 29.5], [0.0, 0.0, 1.0]])
        >>> barrel = distortion_coefficients([-0.2, 0.0, 0.0, 0.0])
        >>> new_K = undistorted_intrinsics(K, barrel, (60, 100))
        >>> round(float(new_K[0, 0] / K[0, 0]), 3), new_K[:2, 2].tolist()
        (0.965, [49.5, 29.5])
    """
    h, w = check_size(image_size)
    K = _pinhole(K)
    d = distortion_coefficients(distortion)
    if not bool(d.any()):
        return K
    xs = torch.arange(w, dtype=torch.float64)
    ys = torch.arange(h, dtype=torch.float64)
    border = torch.cat(
        [
            torch.stack([xs, torch.zeros_like(xs)], -1),
            torch.stack([xs, torch.full_like(xs, h - 1)], -1),
            torch.stack([torch.zeros_like(ys), ys], -1),
            torch.stack([torch.full_like(ys, w - 1), ys], -1),
        ]
    )
    corners = torch.tensor(
        [[0.0, 0.0], [w - 1.0, 0.0], [0.0, h - 1.0], [w - 1.0, h - 1.0]], dtype=torch.float64
    )

    def valid(a: float) -> bool:
        new_K = _scaled(K, a)
        n = (torch.cat([corners, torch.ones(4, 1, dtype=torch.float64)], -1) @ torch.linalg.inv(new_K).T)[
            :, :2
        ]
        if not _radius_monotonic(d, float(n.norm(dim=-1).max()) * 1.01):
            return False
        p = _raw_pixels(border, K, new_K, d)
        return bool(
            torch.isfinite(p).all()
            and (p[:, 0] >= -0.5).all()
            and (p[:, 0] <= w - 0.5).all()
            and (p[:, 1] >= -0.5).all()
            and (p[:, 1] <= h - 0.5).all()
        )

    lo = hi = 1.0
    if valid(1.0):
        while valid(lo):
            hi, lo = lo, lo / 2
            if lo < 1 / 64:
                return _scaled(K, hi)
    else:
        while not valid(hi):
            lo, hi = hi, hi * 2
            if hi > 64:
                raise ValueError(
                    f"distortion: {d.tolist()} folds over or leaves no valid pinhole view of a "
                    f"{w}x{h} image with K {K.tolist()}"
                )
    while hi - lo > tolerance * hi:
        mid = (lo + hi) / 2
        lo, hi = (lo, mid) if valid(mid) else (mid, hi)
    return _scaled(K, hi)


def undistortion_map(
    K: torch.Tensor, distortion: torch.Tensor, image_size: Sequence[int], new_K: torch.Tensor
) -> torch.Tensor:
    """For each pixel of the undistorted image ``new_K``, its position ``(x, y)`` in the raw image.

    As ``cv2.initUndistortRectifyMap(K, distortion, None, new_K, (W, H), cv2.CV_32FC1)``.

    Args:
        K: ``(3, 3)`` raw intrinsics.
        distortion: ``(12,)`` from :func:`distortion_coefficients`.
        image_size: ``(H, W)`` of the undistorted image.
        new_K: ``(3, 3)`` its pinhole intrinsics (e.g. :func:`undistorted_intrinsics`).

    Returns:
        ``(H, W, 2)`` float64 raw pixel coordinates (pixel centres at integers).

    Example:
        >>> K = torch.tensor([[10.0, 0.0, 1.5], [0.0, 10.0, 1.0], [0.0, 0.0, 1.0]])
        >>> m = undistortion_map(K, distortion_coefficients([0.0] * 4), (3, 4), K)
        >>> m[2, 3].round(decimals=6).tolist()
        [3.0, 2.0]
    """
    h, w = check_size(image_size)
    K, new_K = _pinhole(K), _pinhole(new_K, "new_K")
    d = distortion_coefficients(distortion)
    ys, xs = torch.meshgrid(
        torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij"
    )
    return _raw_pixels(torch.stack([xs, ys], -1), K, new_K, d)


def remap(image: torch.Tensor, map_xy: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
    """Sample ``image`` at the raw positions ``map_xy`` (as ``cv2.remap`` with border replication).

    Not differentiable in practice (readers call it once per image); the sampling itself is
    ``grid_sample`` with ``align_corners=True`` (pixel centres at integers).

    Args:
        image: ``(B, C, H_raw, W_raw)`` float, or an integer label map of the same shape (then
            ``mode`` must be ``"nearest"``; it comes back with its own dtype).
        map_xy: ``(H, W, 2)`` raw pixel coordinates from :func:`undistortion_map`.
        mode: ``"bilinear"`` for colours, ``"nearest"`` for instance ids and depth.

    Returns:
        ``(B, C, H, W)``.

    Raises:
        ValueError: on bad shapes, an unknown ``mode``, or an integer image with ``"bilinear"``.

    Example:
        >>> img = torch.arange(6.0).reshape(1, 1, 2, 3)
        >>> remap(img, torch.tensor([[[2.0, 1.0], [0.5, 0.0]]])).tolist()
        [[[[5.0, 0.5]]]]
    """
    dims = check_shape(image, "image", ("B", "C", "H", "W"))
    check_shape(map_xy, "map_xy", ("h", "w", 2))
    if mode not in ("bilinear", "nearest"):
        raise ValueError(f"mode: expected 'bilinear' or 'nearest', got {mode!r}")
    floating = image.is_floating_point()
    if not floating and mode != "nearest":
        raise ValueError(
            f"mode: an integer image ({image.dtype}) must be remapped with 'nearest', got {mode!r}"
        )
    src = image if floating else image.double()
    h_raw, w_raw = dims["H"], dims["W"]
    scale = torch.tensor([2.0 / max(w_raw - 1, 1), 2.0 / max(h_raw - 1, 1)], dtype=torch.float64)
    grid = (map_xy.double().cpu() * scale - 1.0).to(device=src.device, dtype=src.dtype)
    grid = grid.expand(src.shape[0], *grid.shape)
    out = F.grid_sample(src, grid, mode=mode, padding_mode="border", align_corners=True)
    return out if floating else out.round().to(image.dtype)


@dataclass
class ImageUndistorter:
    """One camera's undistortion: the pinhole ``K`` and the map, built on first use.

    See :func:`undistorted_intrinsics`, :func:`undistortion_map` and :func:`remap`. With zero
    distortion it is the identity (``K`` unchanged, images returned as they are).

    Attributes:
        raw_K: ``(3, 3)`` float64 intrinsics of the raw images.
        distortion: ``(12,)`` OpenCV coefficients.
        image_size: ``(H, W)`` of the raw (and undistorted) images.
        K: ``(3, 3)`` float64 pinhole intrinsics of the undistorted images.

    Example:
        >>> K = torch.tensor([[100.0, 0.0, 49.5], [0.0, 100.0, 29.5], [0.0, 0.0, 1.0]])
        >>> und = ImageUndistorter(K, distortion_coefficients([-0.2, 0.0, 0.0, 0.0]), (60, 100))
        >>> und(torch.rand(1, 3, 60, 100)).shape, und.distorted
        (torch.Size([1, 3, 60, 100]), True)
    """

    raw_K: torch.Tensor
    distortion: torch.Tensor
    image_size: tuple[int, int]
    K: torch.Tensor = field(init=False)
    _map: torch.Tensor | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        self.raw_K = _pinhole(torch.as_tensor(self.raw_K), "raw_K")
        self.distortion = distortion_coefficients(self.distortion)
        self.image_size = check_size(self.image_size)
        self.K = undistorted_intrinsics(self.raw_K, self.distortion, self.image_size)

    @property
    def distorted(self) -> bool:
        """Whether any coefficient is non-zero (else images pass through unchanged)."""
        return bool(self.distortion.any())

    @property
    def map_xy(self) -> torch.Tensor:
        """``(H, W, 2)`` raw position of each undistorted pixel (float32, cached)."""
        if self._map is None:
            self._map = undistortion_map(self.raw_K, self.distortion, self.image_size, self.K).float()
        return self._map

    def __call__(self, image: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
        """Undistort ``(B, C, H, W)`` raw images (``mode="nearest"`` for labels and depth)."""
        check_shape(image, "image", ("B", "C", *self.image_size))
        if not self.distorted:
            return image
        return remap(image, self.map_xy, mode)
