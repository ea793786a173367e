"""Export a trained model as standard 3DGS PLY files (static and per object) plus the object poses.

The PLY layout is the one of the original 3DGS code (and gsplat, SuperSplat, ...): binary little
endian, one ``vertex`` element with ``x y z nx ny nz f_dc_0..2 f_rest_0..(3(K-1)-1) opacity
scale_0..2 rot_0..3``, raw values (opacity logits, log-scales, ``wxyz`` quaternions) and
``f_rest`` channel-major. ``static.ply`` is in world coordinates; ``object_<id>.ply`` in the
object's frame, placed per frame by ``poses.json`` (``object_to_world`` per frame index, only
where the track is valid).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from vadgs.train.model import GaussianModel

__all__ = ["export_model", "read_ply", "write_ply"]


def write_ply(path: str | Path, params: dict[str, torch.Tensor]) -> Path:
    """Write raw Gaussian parameters (keys of :data:`~vadgs.train.model.PER_GAUSSIAN`) as a 3DGS PLY.

    Example:
        >>> import tempfile, os
        >>> p = {"means": torch.zeros(2, 3), "quats": torch.tensor([[1.0, 0, 0, 0]] * 2),
        ...      "log_scales": torch.zeros(2, 3), "opacity_logits": torch.zeros(2),
        ...      "sh_dc": torch.zeros(2, 1, 3), "sh_rest": torch.zeros(2, 3, 3)}
        >>> path = write_ply(os.path.join(tempfile.mkdtemp(), "g.ply"), p)
        >>> {k: tuple(v.shape) for k, v in read_ply(path).items()}["sh_rest"]
        (2, 3, 3)
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    n = params["means"].shape[0]
    rest = params["sh_rest"].detach().cpu().float()
    k1 = rest.shape[1]
    cols = [
        params["means"].detach().cpu().float(),
        torch.zeros(n, 3),
        params["sh_dc"].detach().cpu().float().reshape(n, 3),
        rest.transpose(1, 2).reshape(n, 3 * k1),
        params["opacity_logits"].detach().cpu().float().reshape(n, 1),
        params["log_scales"].detach().cpu().float(),
        params["quats"].detach().cpu().float(),
    ]
    names = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
             + [f"f_rest_{i}" for i in range(3 * k1)] + ["opacity", "scale_0", "scale_1", "scale_2"]
             + [f"rot_{i}" for i in range(4)])  # fmt: skip
    data = torch.cat(cols, 1).numpy().astype("<f4")
    header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {n}\n"
    header += "".join(f"property float {nm}\n" for nm in names) + "end_header\n"
    with path.open("wb") as f:
        f.write(header.encode("ascii"))
        f.write(data.tobytes())
    return path


def read_ply(path: str | Path) -> dict[str, torch.Tensor]:
    """Read a 3DGS PLY written by :func:`write_ply` (or the original 3DGS code) into raw parameters."""
    raw = Path(path).read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    header = raw[:end].decode("ascii").splitlines()
    n = next(int(line.split()[2]) for line in header if line.startswith("element vertex"))
    names = [line.split()[2] for line in header if line.startswith("property float")]
    data = torch.from_numpy(
        np.frombuffer(raw[end:], dtype="<f4", count=n * len(names)).reshape(n, len(names)).copy()
    )
    col = {nm: i for i, nm in enumerate(names)}

    def get(prefix: str, count: int) -> torch.Tensor:
        return data[:, [col[f"{prefix}{i}"] for i in range(count)]]

    k1 = sum(nm.startswith("f_rest_") for nm in names) // 3
    return {
        "means": data[:, [col["x"], col["y"], col["z"]]],
        "quats": get("rot_", 4),
        "log_scales": get("scale_", 3),
        "opacity_logits": data[:, col["opacity"]],
        "sh_dc": get("f_dc_", 3)[:, None],
        "sh_rest": get("f_rest_", 3 * k1).reshape(n, 3, k1).transpose(1, 2).contiguous(),
    }


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
