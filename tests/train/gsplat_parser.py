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


def dense_points(parser: SimpleNamespace, views: list[int], step: int = 4):
    """Static surface points of the sample seen by ``views`` of the parser (from the sample's depth).

    The bundled sample is the scene the COLMAP project was written from (same images, cameras and
    world frame); its ground-truth depth, backprojected every ``step`` pixels at the parser's
    resolution, gives dense points (moving cars left out), their colours and spacings: an
    initialisation complete enough that only what is deleted from it is incomplete.

    Returns:
        ``(points (P, 3), colors (P, 3), spacing (P,))``.
    """
    import torch

    from vadgs.data import load_scene, sample_scene_path
    from vadgs.geometry import backproject_depth

    scene = load_scene(sample_scene_path(), scale=1.0 / parser.factor)
    images_root = sample_scene_path() / "images"
    by_name = {str(Path(v.image).relative_to(images_root)): v.index for v in scene.views}
    ids = [by_name[parser.image_names[v]] for v in views]
    depth = scene.load_depths(ids)
    cams = scene.cameras(ids)
    pts = backproject_depth(depth, cams.K, cams.cam_to_world)[:, :, ::step, ::step].permute(0, 2, 3, 1)
    img = scene.load_images(ids)[:, :, ::step, ::step].permute(0, 2, 3, 1)
    ins = scene.load_instances(ids)[:, ::step, ::step]
    d = depth[:, 0, ::step, ::step]
    spacing = d / cams.K[:, 0, 0, None, None] * step
    valid = (d > 0) & ~torch.isin(ins, torch.tensor(sorted(scene.tracks)))
    return pts[valid], img[valid], spacing[valid]


#: The deleted facade: the 10 m ground cell around this point (x, y in metres) of the sample
#: (buildings 9 and 10 and their sidewalk), one derived instance of the COLMAP path.
FACADE_POINT = (35.0, -15.0)


def facade_cell(inputs, cell_size: float = 10.0, at=FACADE_POINT, voxel_size: float = 0.2):
    """``in_cell(points (Q, 3)) -> (Q,) bool``: the ``cell_size`` ground cell around ``at``, in the
    ground frame VAD-GS derives its instances in (:func:`~vadgs.geometry.ground.ground_frame`
    of the inputs' SfM points and the views' cameras, walls aligned at ``voxel_size``, as
    ``build_visibility_index`` does)."""
    import torch

    from vadgs.geometry import invert_rigid
    from vadgs.geometry.ground import ground_frame

    c2w = invert_rigid(inputs.cameras.world_to_cam)
    rotation, origin = ground_frame(inputs.sfm.points, c2w, walls=voxel_size)

    def cell_of(p: torch.Tensor) -> torch.Tensor:
        local = (p.double() - origin) @ rotation.T
        return torch.floor(local[:, :2] / cell_size + 0.5).long()

    target = cell_of(torch.tensor([[*at, 0.0]]))[0]

    def in_cell(p: torch.Tensor) -> torch.Tensor:
        return (cell_of(p) == target).all(1)

    return in_cell


def facade_splats(parser: SimpleNamespace, inputs, cell_size: float = 10.0, at=FACADE_POINT):
    """gsplat-layout splats (``ParameterDict``; ``shN`` of degree 0) and one Adam per key, from the
    dense points of the training views with every point of the ground cell around ``at`` deleted
    (:func:`facade_cell`), opaque (so that the complete instances pass the incompleteness test).

    Returns:
        ``(splats, optimizers, in_cell)``: ``in_cell(points (Q, 3)) -> (Q,) bool``.
    """
    import torch

    from vadgs.render import rgb_to_sh

    pts, col, spc = dense_points(parser, list(inputs.train_views))
    in_cell = facade_cell(inputs, cell_size, at)

    keep = ~in_cell(pts)
    assert int((~keep).sum()) > 1000  # a real facade is deleted
    pts, col, spc = pts[keep], col[keep], spc[keep]
    n = pts.shape[0]
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1.0
    splats = torch.nn.ParameterDict(
        {
            "means": pts.clone(),
            "scales": torch.log(spc.clamp(min=1e-3))[:, None].repeat(1, 3),
            "quats": quats,
            "opacities": torch.full((n,), 3.0),
            "sh0": rgb_to_sh(col)[:, None, :].clone(),
            "shN": torch.zeros(n, 0, 3),
        }
    )
    lrs = {"means": 1.6e-4, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2, "sh0": 2.5e-3, "shN": 1.25e-4}
    optimizers = {k: torch.optim.Adam([splats[k]], lr=lr, eps=1e-15) for k, lr in lrs.items()}
    return splats, optimizers, in_cell
