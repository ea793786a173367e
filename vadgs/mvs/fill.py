r"""Hole filling of depth maps after a consistency check (stereo post-processing).

A left–right (or multi-view) check (:func:`vadgs.mvs.geometric_consistency`) leaves holes at
occlusions and mismatches. Classic PatchMatch-stereo and SGM pipelines fill each hole along its
scanline with the *farther* of its nearest valid neighbours on the left and on the right: an
occluded pixel belongs to the background, which is the farther surface. This is that step, batched
in torch (``torch.cummax`` / ``torch.cummin`` over the scanline, no Python loop over pixels).

Only for dense two-view stereo benchmarks: multi-view fusion keeps the holes (they carry no
evidence).
"""

from __future__ import annotations

import torch

from vadgs.checks import check_shape

__all__ = ["fill_holes_scanline"]


def fill_holes_scanline(depth: torch.Tensor, valid: torch.Tensor, keep: str = "far") -> torch.Tensor:
    """Fill invalid pixels from the nearest valid pixels to their left and right on the same row.

    Args:
        depth: ``(B, 1, H, W)`` depth maps.
        valid: ``(B, 1, H, W)`` bool, pixels to keep.
        keep: ``"far"`` (the larger depth of the two neighbours: the background, for occlusions)
            or ``"near"``. Pixels with a valid neighbour on one side only take that one; rows
            without any valid pixel get 0.

    Returns:
        ``(B, 1, H, W)`` filled depth (equal to ``depth`` where ``valid``).

    Example:
        >>> d = torch.tensor([[[[1.0, 0.0, 0.0, 3.0, 0.0]]]])
        >>> fill_holes_scanline(d, d > 0)
        tensor([[[[1., 3., 3., 3., 3.]]]])
        >>> fill_holes_scanline(d, d > 0, keep="near")
        tensor([[[[1., 1., 1., 3., 3.]]]])
    """
    dims = check_shape(depth, "depth", ("B", 1, "H", "W"))
    check_shape(valid, "valid", ("B", 1, "H", "W"), dims)
    if keep not in ("far", "near"):
        raise ValueError(f"keep: expected 'far' or 'near', got {keep!r}")
    w = dims["W"]
    valid = valid.bool()
    cols = torch.arange(w, device=depth.device).expand_as(depth)
    left = torch.where(valid, cols, torch.full_like(cols, -1)).cummax(-1).values
    right = torch.where(valid, cols, torch.full_like(cols, w)).flip(-1).cummin(-1).values.flip(-1)
    z = torch.where(valid, depth, torch.zeros_like(depth))
    zl = torch.where(left >= 0, z.gather(-1, left.clamp(0, w - 1)), torch.nan)
    zr = torch.where(right < w, z.gather(-1, right.clamp(0, w - 1)), torch.nan)
    pick = torch.fmax(zl, zr) if keep == "far" else torch.fmin(zl, zr)  # fmax/fmin ignore NaN
    return torch.where(valid, depth, torch.nan_to_num(pick, nan=0.0))
