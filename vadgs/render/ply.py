"""Gaussians to and from the standard 3DGS PLY layout, readable by common 3DGS viewers.

One ``binary_little_endian`` vertex element of float32 properties, in the order of the
reference implementation (Kerbl et al. 2023)::

    x y z  nx ny nz  f_dc_0..2  f_rest_0..(3(K-1)-1)  opacity  scale_0..2  rot_0..3

- ``f_dc`` is the degree-0 SH coefficient per channel; ``f_rest`` the higher ones stored
  channel-major (all red coefficients, then green, then blue), as 3DGS does.
- ``opacity`` is a logit and ``scale_*`` are log standard deviations (the file stores the
  optimiser's raw parameters); ``rot_*`` is the quaternion ``w, x, y, z``; normals are zero.

In memory vadgs uses *activated* values (``docs/conventions.md``): :func:`save_ply` takes them
and applies ``logit`` / ``log``; :func:`load_ply` returns them after ``sigmoid`` / ``exp``.
Opacities are clipped to ``[1e-6, 1 - 1e-6]`` and scales to at least ``1e-12`` before the
transform so that the file holds finite numbers. :func:`write_raw_ply` / :func:`read_raw_ply`
take and return the raw parameters instead (``log_scales``, ``opacity_logits``, ``sh_dc``,
``sh_rest``: the keys of :data:`vadgs.train.model.PER_GAUSSIAN`).

This is vadgs's one PLY reader and writer (on :mod:`plyfile`). Writes are atomic (a temporary
file in the same folder, then :func:`os.replace`), so an interrupted export never leaves a
truncated file under the final name. Reading validates the header: a file that is not a PLY, a
vertex count that disagrees with the data, a missing or list-typed 3DGS property, or an
``f_rest`` count that is not a full SH degree raise a :class:`ValueError` naming the file and
the property.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from vadgs.checks import check_finite, check_shape
from vadgs.io import atomic_write
from vadgs.render.sh import rgb_to_sh

__all__ = ["GaussianPly", "load_ply", "read_raw_ply", "save_ply", "write_raw_ply"]

_BASE = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
_TAIL = ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
_REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", *_TAIL]


class GaussianPly(NamedTuple):
    """Gaussians read from a 3DGS PLY file, activated (see the module docstring).

    Attributes:
        means: ``(N, 3)``.
        quats: ``(N, 4)`` ``wxyz`` as stored (not normalised).
        scales: ``(N, 3)`` standard deviations, ``exp(scale_*)``.
        opacities: ``(N,)``, ``sigmoid(opacity)``.
        sh: ``(N, K, 3)`` SH coefficients, ``K = 1 + len(f_rest) / 3``.
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor


def _write(path: Path, columns: list[np.ndarray], names: list[str]) -> Path:
    """Write float32 columns as one binary little-endian vertex element, atomically."""
    n = columns[0].shape[0]
    data = np.concatenate([c.reshape(n, int(np.prod(c.shape[1:]))) for c in columns], axis=1).astype("<f4")
    vertex = np.empty(n, dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        vertex[name] = data[:, i]
    ply = PlyData([PlyElement.describe(vertex, "vertex")], text=False, byte_order="<")
    path = Path(path)
    return atomic_write(path, lambda tmp: ply.write(str(tmp)))


def write_raw_ply(path: str | Path, params: dict[str, torch.Tensor]) -> Path:
    """Write raw Gaussian parameters as a 3DGS PLY (atomically); returns the path.

    Args:
        path: output file (parent folders are created).
        params: ``means (N, 3)``, ``quats (N, 4)``, ``log_scales (N, 3)``,
            ``opacity_logits (N,)``, ``sh_dc (N, 1, 3)``, ``sh_rest (N, K-1, 3)`` (the keys of
            :data:`vadgs.train.model.PER_GAUSSIAN`); extra keys are ignored.

    Raises:
        ValueError: on a missing key or a shape mismatch (named).

    Example:
        >>> import tempfile, os
        >>> p = {"means": torch.zeros(2, 3), "quats": torch.tensor([[1.0, 0, 0, 0]] * 2),
        ...      "log_scales": torch.zeros(2, 3), "opacity_logits": torch.zeros(2),
        ...      "sh_dc": torch.zeros(2, 1, 3), "sh_rest": torch.zeros(2, 3, 3)}
        >>> path = write_raw_ply(os.path.join(tempfile.mkdtemp(), "g.ply"), p)
        >>> {k: tuple(v.shape) for k, v in read_raw_ply(path).items()}["sh_rest"]
        (2, 3, 3)
    """
    need = ["means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest"]
    missing = [k for k in need if k not in params]
    if missing:
        raise ValueError(f"params: missing keys {missing}, expected {need}")
    dims = check_shape(params["means"], "means", ("N", 3))
    check_shape(params["quats"], "quats", ("N", 4), dims)
    check_shape(params["log_scales"], "log_scales", ("N", 3), dims)
    check_shape(params["opacity_logits"], "opacity_logits", ("N",), dims)
    check_shape(params["sh_dc"], "sh_dc", ("N", 1, 3), dims)
    check_shape(params["sh_rest"], "sh_rest", ("N", "K1", 3), dims)
    n, k1 = dims["N"], dims["K1"]

    def np_(t: torch.Tensor) -> np.ndarray:
        return t.detach().cpu().double().numpy()

    cols = [
        np_(params["means"]),
        np.zeros((n, 3)),
        np_(params["sh_dc"]).reshape(n, 3),
        np_(params["sh_rest"]).transpose(0, 2, 1).reshape(n, 3 * k1),  # channel-major
        np_(params["opacity_logits"]).reshape(n, 1),
        np_(params["log_scales"]),
        np_(params["quats"]),
    ]
    return _write(Path(path), cols, _BASE + [f"f_rest_{i}" for i in range(3 * k1)] + _TAIL)


def read_raw_ply(path: str | Path) -> dict[str, torch.Tensor]:
    """Read a 3DGS PLY (vadgs's, the original 3DGS code's, gsplat's) into raw parameters.

    Returns:
        ``means``, ``quats``, ``log_scales``, ``opacity_logits``, ``sh_dc (N, 1, 3)``,
        ``sh_rest (N, K-1, 3)``, float32 on the CPU.

    Raises:
        FileNotFoundError: if ``path`` does not exist.
        ValueError: if the file is not a PLY, its header disagrees with its data (a vertex count
            larger than the data, ...), or it lacks a 3DGS vertex property; the message names
            the file and the property.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no PLY file at {path}")
    try:
        with path.open("rb") as f:
            if f.read(4) != b"ply\n" and not path.read_bytes().startswith(b"ply\r\n"):
                raise ValueError(f"{path}: not a PLY file (missing 'ply' magic)")
        ply = PlyData.read(str(path))
    except ValueError:
        raise
    except Exception as e:  # plyfile's PlyHeaderParseError / PlyElementParseError, struct errors
        raise ValueError(f"{path}: corrupt PLY ({type(e).__name__}: {' '.join(str(e).split())})") from None
    names = [el.name for el in ply.elements]
    if "vertex" not in names:
        raise ValueError(f"{path}: no 'vertex' element (elements: {names})")
    vertex = ply["vertex"]
    props = {p.name: p for p in vertex.properties}
    missing = [p for p in _REQUIRED if p not in props]
    if missing:
        raise ValueError(f"{path}: not a 3DGS PLY, missing vertex properties {missing}")
    lists = [name for name, p in props.items() if hasattr(p, "len_dtype")]
    if lists:
        raise ValueError(f"{path}: list properties {lists} are not supported in a Gaussian file")
    rest = sorted((p for p in props if p.startswith("f_rest_")), key=lambda p: int(p.split("_")[-1]))
    if [int(p.split("_")[-1]) for p in rest] != list(range(len(rest))):
        raise ValueError(f"{path}: f_rest properties are not numbered 0..{len(rest) - 1}: {rest}")
    k = 1 + len(rest) // 3
    if len(rest) % 3 or int(np.sqrt(k)) ** 2 != k:
        raise ValueError(f"{path}: {len(rest)} f_rest properties do not make a full SH degree")
    data = vertex.data
    n = len(data)

    def cols(keys: list[str]) -> torch.Tensor:
        if not keys:
            return torch.zeros(n, 0)
        return torch.from_numpy(np.stack([np.asarray(data[p], dtype=np.float32) for p in keys], axis=1))

    return {
        "means": cols(["x", "y", "z"]),
        "quats": cols([f"rot_{i}" for i in range(4)]),
        "log_scales": cols([f"scale_{i}" for i in range(3)]),
        "opacity_logits": cols(["opacity"])[:, 0].contiguous(),
        "sh_dc": cols(["f_dc_0", "f_dc_1", "f_dc_2"])[:, None, :].contiguous(),
        "sh_rest": cols(rest).reshape(n, 3, k - 1).transpose(1, 2).contiguous(),
    }


def save_ply(
    path: str | Path,
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
) -> None:
    """Write Gaussians to a 3DGS PLY file (atomically).

    Args:
        path: output file.
        means: ``(N, 3)`` world means.
        quats: ``(N, 4)`` ``wxyz`` quaternions.
        scales: ``(N, 3)`` activated (positive) standard deviations.
        opacities: ``(N,)`` activated opacities in ``[0, 1]``.
        colors: ``(N, K, 3)`` SH coefficients, or ``(N, 3)`` RGB in ``[0, 1]`` (stored as
            degree-0 SH, ``(rgb - 0.5) / C0``).

    Example:
        >>> import tempfile, os
        >>> path = os.path.join(tempfile.mkdtemp(), "g.ply")
        >>> save_ply(path, torch.zeros(2, 3), torch.tensor([[1.0, 0, 0, 0]] * 2), torch.full((2, 3), 0.1),
        ...          torch.tensor([0.5, 0.9]), torch.rand(2, 3))
        >>> g = load_ply(path)
        >>> g.sh.shape, [round(o, 3) for o in g.opacities.tolist()]
        (torch.Size([2, 1, 3]), [0.5, 0.9])
    """
    dims = check_shape(means, "means", ("N", 3))
    check_shape(quats, "quats", ("N", 4), dims)
    check_shape(scales, "scales", ("N", 3), dims)
    check_shape(opacities, "opacities", ("N",), dims)
    if colors.dim() == 2:
        check_shape(colors, "colors", ("N", 3), dims)
        sh = rgb_to_sh(colors)[:, None, :]
    else:
        check_shape(colors, "colors", ("N", "K", 3), dims)
        sh = colors
    for name, t in (
        ("means", means),
        ("quats", quats),
        ("scales", scales),
        ("opacities", opacities),
        ("colors", sh),
    ):
        check_finite(t, name)
    with torch.no_grad():
        o = opacities.detach().double().clamp(1e-6, 1 - 1e-6)
        write_raw_ply(
            path,
            {
                "means": means.detach().double(),
                "quats": quats.detach().double(),
                "log_scales": torch.log(scales.detach().double().clamp_min(1e-12)),
                "opacity_logits": torch.log(o / (1 - o)),
                "sh_dc": sh[:, :1].detach().double(),
                "sh_rest": sh[:, 1:].detach().double(),
            },
        )


def load_ply(path: str | Path) -> GaussianPly:
    """Read Gaussians from a 3DGS PLY file (see the module docstring for the layout).

    Args:
        path: the file.

    Returns:
        The :class:`GaussianPly`, activated, float32 on the CPU.

    Raises:
        FileNotFoundError: if the file does not exist.
        ValueError: if the file is not a PLY with the 3DGS vertex properties (see
            :func:`read_raw_ply`).
    """
    raw = read_raw_ply(path)
    return GaussianPly(
        means=raw["means"],
        quats=raw["quats"],
        scales=torch.exp(raw["log_scales"]),
        opacities=torch.sigmoid(raw["opacity_logits"]),
        sh=torch.cat([raw["sh_dc"], raw["sh_rest"]], dim=1).contiguous(),
    )
