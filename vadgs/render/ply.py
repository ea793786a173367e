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
transform so that the file holds finite numbers.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from vadgs.checks import check_finite, check_shape
from vadgs.render.sh import rgb_to_sh

__all__ = ["GaussianPly", "load_ply", "save_ply"]

_TYPES = {
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
    "uchar": "u1",
    "uint8": "u1",
    "char": "i1",
    "int8": "i1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
}


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


def save_ply(
    path: str | Path,
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
) -> None:
    """Write Gaussians to a 3DGS PLY file.

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
    n, k = sh.shape[0], sh.shape[1]
    with torch.no_grad():
        o = opacities.detach().double().clamp(1e-6, 1 - 1e-6)
        cols = [
            means.detach().double(),
            torch.zeros(n, 3, dtype=torch.float64),
            sh[:, 0].detach().double(),
            sh[:, 1:].detach().double().transpose(1, 2).reshape(n, 3 * (k - 1)),
            torch.log(o / (1 - o))[:, None],
            torch.log(scales.detach().double().clamp_min(1e-12)),
            quats.detach().double(),
        ]
        data = torch.cat([c.cpu() for c in cols], dim=1).numpy().astype("<f4")
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * (k - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property float {name}" for name in names]
    header += ["end_header"]
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(np.ascontiguousarray(data).tobytes())


def _read_header(f) -> tuple[str, list[tuple[str, int, list[tuple[str, str]]]]]:
    if f.readline().strip() != b"ply":
        raise ValueError("not a PLY file (missing 'ply' magic)")
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    while True:
        line = f.readline()
        if not line:
            raise ValueError("PLY header has no end_header")
        words = line.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise ValueError("PLY property before any element")
            if words[1] == "list":
                raise ValueError(f"PLY list property {words[-1]!r} is not supported in a Gaussian file")
            if words[1] not in _TYPES:
                raise ValueError(f"PLY property type {words[1]!r} is not supported")
            elements[-1][2].append((words[2], words[1]))
    if fmt not in ("binary_little_endian", "binary_big_endian"):
        raise ValueError(f"PLY format {fmt!r} is not supported (expected binary)")
    return fmt, elements


def load_ply(path: str | Path) -> GaussianPly:
    """Read Gaussians from a 3DGS PLY file (see the module docstring for the layout).

    Args:
        path: the file.

    Returns:
        The :class:`GaussianPly`, activated, float32 on the CPU.

    Raises:
        ValueError: if the file is not a binary PLY with the 3DGS vertex properties.
    """
    with open(path, "rb") as f:
        fmt, elements = _read_header(f)
        endian = "<" if fmt == "binary_little_endian" else ">"
        data = None
        for name, count, props in elements:
            dtype = np.dtype([(p, endian + _TYPES[t]) for p, t in props])
            arr = np.frombuffer(f.read(dtype.itemsize * count), dtype=dtype, count=count)
            if name == "vertex":
                data = arr
                break
    if data is None:
        raise ValueError(f"{path}: no vertex element")
    fields = set(data.dtype.names or ())
    need = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
    need += [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]
    missing = [p for p in need if p not in fields]
    if missing:
        raise ValueError(f"{path}: not a 3DGS PLY, missing vertex properties {missing}")
    rest = sorted((p for p in fields if p.startswith("f_rest_")), key=lambda p: int(p.split("_")[-1]))
    if len(rest) % 3 or int(np.sqrt(1 + len(rest) // 3)) ** 2 != 1 + len(rest) // 3:
        raise ValueError(f"{path}: {len(rest)} f_rest properties do not make a full SH degree")
    n = len(data)

    def cols(names: list[str]) -> torch.Tensor:
        if not names:
            return torch.zeros(n, 0)
        return torch.from_numpy(np.stack([data[p].astype(np.float32) for p in names], axis=1))

    dc = cols(["f_dc_0", "f_dc_1", "f_dc_2"])[:, None, :]
    k1 = len(rest) // 3
    higher = cols(rest).reshape(n, 3, k1).transpose(1, 2)
    return GaussianPly(
        means=cols(["x", "y", "z"]),
        quats=cols([f"rot_{i}" for i in range(4)]),
        scales=torch.exp(cols([f"scale_{i}" for i in range(3)])),
        opacities=torch.sigmoid(cols(["opacity"])[:, 0]),
        sh=torch.cat([dc, higher], dim=1).contiguous(),
    )
