"""Waymo LiDAR range images as points (the official conversion, without TensorFlow).

:func:`waymo_beam_inclinations` gives each range-image row its beam inclination and
:func:`waymo_range_image_to_points` turns the first return into points in the vehicle frame, or in
the world with the per-pixel vehicle poses of the ``lidar_pose`` component. Used by
:func:`vadgs.data.waymo.load_waymo`.
:func:`waymo_points_to_range_image` is the inverse (to a cell's resolution), used by
:func:`vadgs.data.waymo_writer.write_waymo_segment`.
:func:`waymo_check_range_image` and :func:`waymo_check_pixel_pose` refuse a decoded range image
(or per-pixel pose) that no Waymo laser produces: what a corrupt file decodes into.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = [
    "WAYMO_MAX_RANGE_M",
    "WAYMO_MAX_SWEEP_ROTATION",
    "WAYMO_MAX_SWEEP_TRANSLATION_M",
    "waymo_beam_inclinations",
    "waymo_check_pixel_pose",
    "waymo_check_range_image",
    "waymo_points_to_range_image",
    "waymo_range_image_to_points",
]

#: The largest range (metres) a laser's range image may hold: the dataset truncates the TOP
#: (mid-range) laser at 75 m and the four short-range ones at 20 m (Sun et al. 2020, table 1);
#: 10 % is added for calibration. A range beyond it is what a corrupt file decodes into.
WAYMO_MAX_RANGE_M = {"TOP": 82.5, "FRONT": 22.0, "SIDE_LEFT": 22.0, "SIDE_RIGHT": 22.0, "REAR": 22.0}
#: How far (metres) a per-pixel vehicle pose (``lidar_pose``) may lie from the frame's vehicle
#: pose: a sweep lasts 0.1 s, in which a vehicle at 200 km/h moves 5.6 m.
WAYMO_MAX_SWEEP_TRANSLATION_M = 20.0
#: How far (radians) a per-pixel vehicle pose may be turned from the frame's (about 29°).
WAYMO_MAX_SWEEP_ROTATION = 0.5


def waymo_beam_inclinations(
    height: int,
    inclination_min: float,
    inclination_max: float,
    values: Sequence[float] | np.ndarray | None = None,
) -> np.ndarray:
    """The inclination (radians) of each range-image row, row 0 at the top.

    The calibration lists inclinations from lowest to highest (``values``), or gives only
    ``min`` / ``max`` for uniformly spaced beams (row centres at ``(i + 0.5) / height``); the
    range image's row 0 is the highest beam, so the list is reversed.

    Raises:
        ValueError: if ``values`` does not have ``height`` entries.

    Example:
        >>> waymo_beam_inclinations(4, -0.4, 0.4).round(3).tolist()
        [0.3, 0.1, -0.1, -0.3]
    """
    if values is not None and len(values) > 0:
        incl = np.asarray(values, dtype=np.float64)
        if incl.shape != (height,):
            raise ValueError(
                f"beam_inclination.values: expected {height} values (range image rows), got {incl.shape}"
            )
    else:
        incl = inclination_min + (np.arange(height) + 0.5) / height * (inclination_max - inclination_min)
    return incl[::-1].copy()


def _euler_to_matrix(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Waymo's 3-2-1 Euler angles as rotations ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``, ``(..., 3, 3)``."""
    cr, sr, cp, sp, cy, sy = (
        np.cos(roll),
        np.sin(roll),
        np.cos(pitch),
        np.sin(pitch),
        np.cos(yaw),
        np.sin(yaw),
    )
    return np.stack(
        [
            np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
            np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
            np.stack([-sp, cp * sr, cp * cr], -1),
        ],
        -2,
    )


def waymo_range_image_to_points(
    ranges: np.ndarray,
    extrinsic: np.ndarray,
    row_inclination: np.ndarray,
    pixel_pose: np.ndarray | None = None,
) -> np.ndarray:
    """The points of a Waymo range image (pixels with range > 0), as the official conversion.

    Column ``c`` of a ``W``-wide image looks at azimuth ``(2 (W - c - 0.5) / W - 1) π - yaw`` in
    the LiDAR frame, ``yaw = atan2(E[1, 0], E[0, 0])`` of the extrinsic ``E``; row ``r`` at
    ``row_inclination[r]``. The point ``range · (cos az cos inc, sin az cos inc, sin inc)`` is
    then moved to the vehicle frame by ``E``, and to the world by ``pixel_pose`` if given.

    Args:
        ranges: ``(H, W)`` ranges in metres (channel 0 of the range image; ``<= 0`` = no return).
        extrinsic: ``(4, 4)`` LiDAR → vehicle.
        row_inclination: ``(H,)`` from :func:`waymo_beam_inclinations`.
        pixel_pose: optional ``(H, W, 6)`` per-pixel vehicle → world pose ``roll, pitch, yaw,
            x, y, z`` (the ``lidar_pose`` component).

    Returns:
        ``(N, 3)`` float64 points, row-major over the valid pixels: in the vehicle frame, or in
        the world when ``pixel_pose`` is given.

    Raises:
        ValueError: on inconsistent shapes.

    Example:
        >>> pts = waymo_range_image_to_points(np.array([[0.0, 10.0, 0.0, 0.0]]), np.eye(4), np.zeros(1))
        >>> pts.round(4).tolist()  # column 1 of 4 looks 45° to the left
        [[7.0711, 7.0711, 0.0]]
    """
    ranges = np.asarray(ranges, dtype=np.float64)
    if ranges.ndim != 2:
        raise ValueError(f"ranges: expected shape (H, W), got {ranges.shape}")
    h, w = ranges.shape
    if np.shape(extrinsic) != (4, 4):
        raise ValueError(f"extrinsic: expected shape (4, 4), got {np.shape(extrinsic)}")
    if np.shape(row_inclination) != (h,):
        raise ValueError(f"row_inclination: expected shape ({h},), got {np.shape(row_inclination)}")
    if pixel_pose is not None and np.shape(pixel_pose) != (h, w, 6):
        raise ValueError(f"pixel_pose: expected shape ({h}, {w}, 6), got {np.shape(pixel_pose)}")
    yaw = np.arctan2(extrinsic[1, 0], extrinsic[0, 0])
    azimuth = (2.0 * (w - np.arange(w) - 0.5) / w - 1.0) * np.pi - yaw
    rows, cols = np.nonzero(ranges > 0)
    r, az, inc = ranges[rows, cols], azimuth[cols], np.asarray(row_inclination, dtype=np.float64)[rows]
    local = np.stack([np.cos(az) * np.cos(inc), np.sin(az) * np.cos(inc), np.sin(inc)], -1) * r[:, None]
    pts = local @ extrinsic[:3, :3].T + extrinsic[:3, 3]
    if pixel_pose is not None:
        pp = np.asarray(pixel_pose, dtype=np.float64)[rows, cols]
        rot = _euler_to_matrix(pp[:, 0], pp[:, 1], pp[:, 2])
        pts = np.einsum("nij,nj->ni", rot, pts) + pp[:, 3:]
    return pts


def waymo_points_to_range_image(
    points: np.ndarray, extrinsic: np.ndarray, row_inclination: np.ndarray, width: int
) -> np.ndarray:
    """The ranges of a range image that :func:`waymo_range_image_to_points` turns back into ``points``.

    The inverse of :func:`waymo_range_image_to_points` (without ``pixel_pose``) up to the cell
    size: each point goes to the row of the nearest beam inclination and to the column whose
    azimuth interval (in the vehicle frame, ``π - 2π (c + 1) / W`` to ``π - 2π c / W``) holds its
    azimuth, and keeps its exact range. Read back, a point lies at its row's inclination and its
    column's centre azimuth: off by at most half a column (``range · π / W``) sideways, and by
    the distance to the nearest beam's cone vertically (nothing for points that a beam of
    ``row_inclination`` measured). Where several points share a cell, the nearest one is kept
    (the first return); the others are dropped.

    Args:
        points: ``(N, 3)`` points in the vehicle frame.
        extrinsic: ``(4, 4)`` LiDAR → vehicle.
        row_inclination: ``(H,)`` beam inclination (radians) of each row, row 0 the highest
            (:func:`waymo_beam_inclinations`), strictly decreasing.
        width: ``W``, the number of columns (Waymo's TOP laser: 2650).

    Returns:
        ``(H, W)`` float64 ranges in metres, ``-1`` where no point fell (Waymo's "no return").

    Raises:
        ValueError: on inconsistent shapes, a non-positive ``width`` or inclinations that do not
            decrease.

    Example:
        >>> ranges = waymo_points_to_range_image(np.array([[7.0711, 7.0711, 0.0]]), np.eye(4), np.zeros(1), 4)
        >>> ranges.round(3).tolist()  # 45° to the left: column 1 of 4
        [[-1.0, 10.0, -1.0, -1.0]]
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points: expected shape (N, 3), got {points.shape}")
    if np.shape(extrinsic) != (4, 4):
        raise ValueError(f"extrinsic: expected shape (4, 4), got {np.shape(extrinsic)}")
    incl = np.asarray(row_inclination, dtype=np.float64)
    if incl.ndim != 1 or len(incl) == 0 or not (np.diff(incl) < 0).all():
        raise ValueError(
            f"row_inclination: expected a strictly decreasing (H,) array (row 0 the highest beam), got {incl}"
        )
    if not (isinstance(width, (int, np.integer)) and width > 0):
        raise ValueError(f"width: expected a positive integer, got {width!r}")
    ext = np.asarray(extrinsic, dtype=np.float64)
    local = (points - ext[:3, 3]) @ ext[:3, :3]  # vehicle -> LiDAR frame (rigid inverse)
    rng = np.linalg.norm(local, axis=-1)
    keep = rng > 0
    local, rng = local[keep], rng[keep]
    inc = np.arcsin(np.clip(local[:, 2] / rng, -1.0, 1.0))
    # the nearest beam: rows by decreasing inclination, so search the increasing midpoints reversed
    mid = (incl[1:] + incl[:-1]) / 2
    rows = len(incl) - 1 - np.searchsorted(mid[::-1], inc)
    yaw = np.arctan2(ext[1, 0], ext[0, 0])
    azimuth = np.arctan2(local[:, 1], local[:, 0]) + yaw  # in the vehicle frame
    cols = np.floor((np.pi - azimuth) / (2 * np.pi) * width).astype(np.int64) % width
    cell = rows * width + cols
    order = np.lexsort((rng, cell))  # by cell, nearest first
    cell, first = np.unique(cell[order], return_index=True)
    out = np.full(len(incl) * width, -1.0)
    out[cell] = rng[order][first]
    return out.reshape(len(incl), width)


def waymo_check_range_image(image: np.ndarray, max_range: float, what: str) -> None:
    """Refuse a decoded first-return range image that no Waymo laser produces.

    A range image holds finite values; its range channel (0) holds, at each pixel, either a
    return in ``(0, max_range]`` metres or Waymo's "no return" (``-1``, or ``0``). Random bytes in a
    parquet file decode into values that are mostly neither (about three quarters of random
    float32 values are negative, non-finite or beyond 82.5 m): what was silently dropped (the
    negative ones) or kept at up to 3e38 m before.

    Args:
        image: ``(H, W, C)`` range image, ``C >= 1``.
        max_range: the laser's limit (:data:`WAYMO_MAX_RANGE_M`).
        what: what the error calls the image (file, row group, frame and laser).

    Raises:
        ValueError: naming ``what``, the number of bad values and the first few.

    Example:
        >>> waymo_check_range_image(np.array([[[-1.0], [20.0]]]), 82.5, "x")
        >>> waymo_check_range_image(np.array([[[-5.0], [3e38]]]), 82.5, "x")
        Traceback (most recent call last):
        ...
        ValueError: x: 2 of 2 ranges are neither a return in (0, 82.5] m nor -1 / 0 (no return), e.g. ...
    """
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[-1] < 1:
        raise ValueError(f"{what}: expected a range image of shape (H, W, C >= 1), got {image.shape}")
    finite = np.isfinite(image)
    if not finite.all():
        n = int((~finite).sum())
        raise ValueError(f"{what}: {n} of {image.size} values are not finite; the file is corrupt")
    r = image[..., 0]
    bad = ~(((r > 0) & (r <= max_range)) | (r == -1) | (r == 0))
    if bad.any():
        eg = [float(v) for v in r[bad][:3]]
        raise ValueError(
            f"{what}: {int(bad.sum())} of {r.size} ranges are neither a return in (0, {max_range:g}] m "
            f"nor -1 / 0 (no return), e.g. {eg}; the file is corrupt"
        )


def waymo_check_pixel_pose(
    pixel_pose: np.ndarray, ranges: np.ndarray, world_from_vehicle: np.ndarray, what: str
) -> None:
    """Refuse per-pixel vehicle poses (``lidar_pose``) that no sweep of the frame has.

    Each pixel with a return (``ranges > 0``) must hold finite ``roll, pitch, yaw, x, y, z`` within
    :data:`WAYMO_MAX_SWEEP_TRANSLATION_M` and :data:`WAYMO_MAX_SWEEP_ROTATION` of the frame's
    vehicle pose (pixels without a return are not read, so not checked).

    Args:
        pixel_pose: ``(H, W, 6)`` per-pixel pose.
        ranges: ``(H, W)`` ranges of the same laser and frame.
        world_from_vehicle: ``(4, 4)`` the frame's vehicle pose (``vehicle_pose``, not recentred).
        what: what the error calls the image.

    Raises:
        ValueError: naming ``what``, the number of bad pixels and the largest offset.

    Example:
        >>> pose = np.zeros((1, 2, 6)); pose[0, 1, 3] = 100.0
        >>> waymo_check_pixel_pose(pose, np.array([[10.0, -1.0]]), np.eye(4), "x")  # no return at the bad one
        >>> waymo_check_pixel_pose(pose, np.array([[10.0, 10.0]]), np.eye(4), "x")
        Traceback (most recent call last):
        ...
        ValueError: x: 1 of 2 per-pixel vehicle poses (pixels with a return) lie more than 20 m or 0.5 rad ...
    """
    h, w = np.shape(ranges)
    if np.shape(pixel_pose) != (h, w, 6):
        raise ValueError(
            f"{what}: expected per-pixel poses of shape ({h}, {w}, 6), got {np.shape(pixel_pose)}"
        )
    pp = np.asarray(pixel_pose, dtype=np.float64)[np.asarray(ranges) > 0]
    if len(pp) == 0:
        return
    finite = np.isfinite(pp).all(-1)
    if not finite.all():
        raise ValueError(
            f"{what}: {int((~finite).sum())} of {len(pp)} per-pixel vehicle poses are not finite; "
            "the file is corrupt"
        )
    frame = np.asarray(world_from_vehicle, dtype=np.float64)
    dist = np.linalg.norm(pp[:, 3:] - frame[:3, 3], axis=-1)
    rel = np.einsum("ji,njk->nik", frame[:3, :3], _euler_to_matrix(pp[:, 0], pp[:, 1], pp[:, 2]))
    angle = np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0))
    bad = (dist > WAYMO_MAX_SWEEP_TRANSLATION_M) | (angle > WAYMO_MAX_SWEEP_ROTATION)
    if bad.any():
        raise ValueError(
            f"{what}: {int(bad.sum())} of {len(pp)} per-pixel vehicle poses (pixels with a return) lie more "
            f"than {WAYMO_MAX_SWEEP_TRANSLATION_M:g} m or {WAYMO_MAX_SWEEP_ROTATION:g} rad from the frame's "
            f"vehicle pose (up to {float(dist.max()):.3g} m, {float(angle.max()):.3g} rad); "
            "the file is corrupt"
        )
