"""Small visualisation helpers: colour maps for depth, index and error maps, and image panels.

Used by the command line, the examples and the docs. Inputs are tensors ``(H, W)`` or images
``(3, H, W)`` in [0, 1]; outputs are uint8 numpy arrays ``(H, W, 3)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from vadgs.io import atomic_write

__all__ = ["colorize_depth", "colorize_index", "colorize_normals", "image_to_uint8", "save_panel"]


def image_to_uint8(image: torch.Tensor) -> np.ndarray:
    """``(3, H, W)`` float image in [0, 1] → ``(H, W, 3)`` uint8."""
    return (image.detach().clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255 + 0.5).astype(np.uint8)


def colorize_depth(
    depth: torch.Tensor, vmin: float | None = None, vmax: float | None = None, cmap: str = "turbo"
) -> np.ndarray:
    """Colour a depth map ``(H, W)`` by inverse depth; ``0`` (no value) is black.

    Example:
        >>> colorize_depth(torch.tensor([[1.0, 0.0], [2.0, 4.0]])).shape
        (2, 2, 3)
    """
    import matplotlib

    d = depth.detach().float().cpu().numpy()
    valid = d > 0
    out = np.zeros((*d.shape, 3), dtype=np.uint8)
    if not valid.any():
        return out
    inv = np.zeros_like(d)
    inv[valid] = 1.0 / d[valid]
    lo = 1.0 / vmax if vmax else float(np.percentile(inv[valid], 1))
    hi = 1.0 / vmin if vmin else float(np.percentile(inv[valid], 99))
    x = np.clip((inv - lo) / max(hi - lo, 1e-12), 0, 1)
    rgb = matplotlib.colormaps[cmap](x)[..., :3]
    out[valid] = (rgb[valid] * 255).astype(np.uint8)
    return out


def colorize_normals(normals: torch.Tensor) -> np.ndarray:
    """Colour camera-frame normals ``(3, H, W)`` as ``0.5 - n / 2`` (facing the camera: blue); zero: black.

    Example:
        >>> colorize_normals(torch.tensor([0.0, 0.0, -1.0]).reshape(3, 1, 1))[0, 0].tolist()
        [128, 128, 255]
    """
    rendered = normals.abs().sum(0) > 0
    return image_to_uint8((-normals * 0.5 + 0.5) * rendered)


def colorize_index(index: torch.Tensor, seed: int = 0) -> np.ndarray:
    """Colour an index map ``(H, W)`` with a random colour per id; ``-1`` is black.

    Example:
        >>> colorize_index(torch.tensor([[-1, 3], [3, 7]]))[0, 0].tolist()
        [0, 0, 0]
    """
    idx = index.detach().cpu().numpy()
    valid = idx >= 0
    out = np.zeros((*idx.shape, 3), dtype=np.uint8)
    if valid.any():
        # a cheap integer hash gives stable, well-spread colours per id
        h = (idx[valid].astype(np.uint64) * np.uint64(2654435761) + np.uint64(seed)) & np.uint64(0xFFFFFF)
        out[valid] = np.stack([(h >> 16) & 255, (h >> 8) & 255, h & 255], -1).astype(np.uint8) | 64
    return out


def save_panel(
    images: Sequence[np.ndarray], titles: Sequence[str], path: str | Path, columns: int | None = None
) -> Path:
    """Save images side by side (with titles) as one PNG; returns the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(images)
    cols = columns or n
    rows = (n + cols - 1) // cols
    h, w = images[0].shape[:2]
    panel_w = max(w / 100, 3.2)  # small images are enlarged so that titles stay readable
    panel_h = panel_w * h / w
    fig, axes = plt.subplots(rows, cols, figsize=(cols * panel_w * 1.05, rows * (panel_h + 0.35)), dpi=100)
    axes = np.atleast_1d(axes).ravel()
    for ax in axes:
        ax.axis("off")
    for ax, im, title in zip(axes, images, titles):
        ax.imshow(im)
        ax.set_title(title, fontsize=8)
    fig.tight_layout(pad=0.3)
    try:
        return atomic_write(path, fig.savefig)  # the format from the suffix, kept by the temporary
    finally:
        plt.close(fig)
