"""gsplat's COLMAP Parser read as data (vadgs.data.gsplat_parser), on a hand-made duck-typed parser:
the pixel convention, the training views, the TRACK table of the training views, the images."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from PIL import Image

from vadgs.data.gsplat_parser import parser_undistortion, read_gsplat_parser


def _parser(tmp_path, n: int = 4, **extra) -> SimpleNamespace:
    paths = []
    for v in range(n):
        p = tmp_path / f"im{v}.png"
        Image.fromarray(np.full((6, 8, 3), 40 * v, dtype=np.uint8)).save(p)
        paths.append(str(p))
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, 0, 3] = np.arange(n)
    return SimpleNamespace(
        image_names=[f"im{v}" for v in range(n)],
        image_paths=paths,
        camtoworlds=c2w,
        camera_ids=[1] * n,
        Ks_dict={1: np.array([[10.0, 0, 4.0], [0, 10.0, 3.0], [0, 0, 1]])},
        imsize_dict={1: (8, 6)},  # (W, H)
        points=np.arange(15, dtype=np.float64).reshape(5, 3),
        point_indices={
            "im0": np.array([3, 1]),
            "im1": np.array([1]),
            "im2": np.array([4]),
            "im3": np.array([0]),
        },
        data_dir="hand-made",
        **extra,
    )


def test_views_track_table_and_images(tmp_path):
    d = read_gsplat_parser(_parser(tmp_path), test_every=2)  # views 0 and 2 are gsplat's test views
    assert d.train_views == (1, 3) and d.view_cameras == (0, 0, 0, 0) and d.sizes is None
    assert d.cameras.image_size == (6, 8) and d.name == "hand-made"
    assert d.cameras.K[0, :2, 2].tolist() == [3.5, 2.5]  # pixel centres at integers: minus 0.5
    assert torch.allclose(d.cameras.world_to_cam[3, 0, 3], torch.tensor(-3.0))
    # the training views' observations only: view 1 saw point 1, view 3 point 0; renumbered in order
    assert d.points.tolist() == [[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]]
    assert d.point_idx.tolist() == [1, 0] and d.view_idx.tolist() == [1, 3]
    img = d.load_image(2, None)
    assert img.shape == (3, 6, 8) and torch.allclose(img, torch.full_like(img, 80 / 255))
    assert d.load_image(2, (3, 4)).shape == (3, 3, 4)
    assert read_gsplat_parser(_parser(tmp_path), train_views=[0]).point_idx.tolist() == [1, 0]


def test_clear_errors(tmp_path):
    bad = _parser(tmp_path)
    bad.camtoworlds = bad.camtoworlds[:, :3]
    with pytest.raises(ValueError, match=r"parser.camtoworlds: expected \(4, 4, 4\), got \(4, 3, 4\)"):
        read_gsplat_parser(bad)
    radial = _parser(tmp_path, params_dict={1: [0.05]})
    with pytest.raises(
        ValueError, match=r"parser camera 1: expected mapx_dict / mapy_dict / roi_undist_dict"
    ):
        parser_undistortion(radial, 1)
    fisheye = _parser(tmp_path, params_dict={1: [0.05]}, mask_dict={1: np.ones((6, 8))})
    with pytest.raises(ValueError, match="expected a perspective camera, got a fisheye one"):
        read_gsplat_parser(fisheye)
    assert parser_undistortion(_parser(tmp_path), 1) is None  # pinhole: nothing to undo
