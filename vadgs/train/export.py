"""Export a trained model as standard 3DGS PLY files (static and per object) plus the object poses.

The PLY reader and writer are :mod:`vadgs.render.ply`'s (atomic writes, validated headers). The
layout is the one of the original 3DGS code (and gsplat, SuperSplat, ...): binary little
endian, one ``vertex`` element with ``x y z nx ny nz f_dc_0..2 f_rest_0..(3(K-1)-1) opacity
scale_0..2 rot_0..3``, raw values (opacity logits, log-scales, ``wxyz`` quaternions) and
``f_rest`` channel-major. ``static.ply`` is in world coordinates; ``object_<id>.ply`` in the
object's frame, placed per frame by ``poses.json`` (``object_to_world`` per frame index, only
where the track is valid).
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from vadgs.render.ply import read_raw_ply, write_raw_ply
from vadgs.train.model import GaussianModel

__all__ = ["export_model", "read_ply", "write_ply"]


def write_ply(path: str | Path, params: dict[str, torch.Tensor]) -> Path:
    """Write raw Gaussian parameters as a 3DGS PLY: :func:`vadgs.render.ply.write_raw_ply`.

    Example:
        >>> import tempfile, os
        >>> p = {"means": torch.zeros(2, 3), "quats": torch.tensor([[1.0, 0, 0, 0]] * 2),
        ...      "log_scales": torch.zeros(2, 3), "opacity_logits": torch.zeros(2),
        ...      "sh_dc": torch.zeros(2, 1, 3), "sh_rest": torch.zeros(2, 3, 3)}
        >>> path = write_ply(os.path.join(tempfile.mkdtemp(), "g.ply"), p)
        >>> {k: tuple(v.shape) for k, v in read_ply(path).items()}["sh_rest"]
        (2, 3, 3)
    """
    return write_raw_ply(path, params)


def read_ply(path: str | Path) -> dict[str, torch.Tensor]:
    """Read a 3DGS PLY into raw parameters: :func:`vadgs.render.ply.read_raw_ply`."""
    return read_raw_ply(path)


def export_model(
    model: GaussianModel, out_dir: str | Path, frame_indices: list[int] | None = None
) -> list[Path]:
    """Write ``static.ply``, ``object_<id>.ply`` per track node and ``poses.json``.

    Args:
        model: the model.
        out_dir: output folder.
        frame_indices: the scene's frame index of each frame position (default ``0..F-1``).

    Returns:
        The written paths.
    """
    out_dir = Path(out_dir)
    paths = []
    p = {k: v.detach() for k, v in model.params.items()}
    static = model.node_ids < 0
    paths.append(write_ply(out_dir / "static.ply", {k: v[static] for k, v in p.items()}))
    nf = model.object_to_world.shape[1]
    frame_indices = frame_indices if frame_indices is not None else list(range(nf))
    poses = {}
    for k, tid in enumerate(model.track_ids):
        sel = model.node_ids == k
        paths.append(write_ply(out_dir / f"object_{tid}.ply", {kk: v[sel] for kk, v in p.items()}))
        poses[str(tid)] = {
            str(frame_indices[f]): model.object_to_world[k, f].tolist()
            for f in range(nf)
            if bool(model.track_valid[k, f])
        }
    pj = out_dir / "poses.json"
    pj.write_text(json.dumps({"object_to_world": poses, "sh_degree": model.sh_degree}, indent=1))
    paths.append(pj)
    return paths
