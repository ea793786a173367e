"""A duck-typed stand-in for gsplat's COLMAP ``Parser`` (``examples/datasets/colmap.py``).

gsplat's ``Parser`` is not an installed module (it lives in gsplat's ``examples/``), so the tests
build a ``SimpleNamespace`` with the attributes VAD-GS reads, the way the Parser computes them from
a COLMAP model (here the bundled sample written by :func:`tests.data.colmap_sample.write_sample_colmap`):
``image_names`` sorted, ``image_paths``, ``camtoworlds`` ``(N, 4, 4)`` OpenCV camera-to-world,
``camera_ids``, ``Ks_dict`` (COLMAP's K, scaled by ``1 / factor``; pixel centres at ``i + 0.5``),
``imsize_dict`` (camera id → ``(W, H)``), ``points`` / ``points_rgb`` in COLMAP's point order and
``point_indices`` (image name → indices of the points it sees: the TRACK table), ``test_every``.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np


def sample_parser(root: Path, factor: int = 1, test_every: int = 8) -> SimpleNamespace:
    """The Parser-like namespace of the COLMAP project at ``root`` (``root/sparse/0``, ``root/images``)."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    images = sorted(rec.images.values(), key=lambda im: im.name)
    pids = sorted(rec.points3D)
    index_of = {pid: i for i, pid in enumerate(pids)}
    Ks, imsize = {}, {}
    for cid, cam in rec.cameras.items():
        K = np.asarray(cam.calibration_matrix(), dtype=np.float64).copy()
        K[:2, :] /= factor
        Ks[cid] = K
        imsize[cid] = (cam.width // factor, cam.height // factor)
    c2w = []
    point_indices: dict[str, list[int]] = {}
    for im in images:
        cfw = im.cam_from_world
        cfw = cfw() if callable(cfw) else cfw
        w2c = np.eye(4)
        w2c[:3, :4] = np.asarray(cfw.matrix(), dtype=np.float64)
        c2w.append(np.linalg.inv(w2c))
    name_of = {im.image_id: im.name for im in images}
    for pid in pids:
        for el in rec.points3D[pid].track.elements:
            point_indices.setdefault(name_of[el.image_id], []).append(index_of[pid])
    return SimpleNamespace(
        data_dir=str(root),
        factor=factor,
        test_every=test_every,
        image_names=[im.name for im in images],
        image_paths=[str(root / "images" / im.name) for im in images],
        camtoworlds=np.stack(c2w),
        camera_ids=[im.camera_id for im in images],
        Ks_dict=Ks,
        imsize_dict=imsize,
        points=np.stack([rec.points3D[p].xyz for p in pids]).astype(np.float32),
        points_rgb=np.stack([rec.points3D[p].color for p in pids]).astype(np.uint8),
        point_indices={k: np.asarray(v, dtype=np.int32) for k, v in point_indices.items()},
    )
