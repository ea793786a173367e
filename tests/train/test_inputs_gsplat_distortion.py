"""``VisibilityInputs.from_gsplat_parser`` on distorted cameras: the images and intrinsics gsplat trains
on (its ``Dataset`` undistorts each image with the Parser's ``mapx`` / ``mapy`` and crops it to
``roi_undist``), or one clear error."""

from __future__ import annotations

import copy
import sys

import numpy as np
import pytest
import torch

from vadgs.geometry.camera import project_points
from vadgs.train.vad import VisibilityInputs

from ..data.colmap_sample import write_sample_colmap
from .gsplat_parser import sample_parser
from .gsplat_simple_trainer import GSPLAT_EXAMPLES, SceneManager, prepare_data

K1 = 0.05  # SIMPLE_RADIAL k: a few pixels at the corners of the 120x72 images


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    root = tmp_path_factory.mktemp("radial") / "proj"
    write_sample_colmap(root, model="SIMPLE_RADIAL", k=K1, n_points=400)
    prepare_data(root, 2)
    return root


@pytest.fixture(scope="module")
def gsplat_parser(project):
    """gsplat's own ``Parser`` of ``../shared``'s v1.5.3 examples (forked SceneManager: pycolmap 4.x)."""
    if not GSPLAT_EXAMPLES.is_dir():
        pytest.skip("needs ../shared/third_party/gsplat-v1.5.3")
    pycolmap = pytest.importorskip("pycolmap")
    pytest.importorskip("cv2")
    mp = pytest.MonkeyPatch()
    mp.setattr(pycolmap, "SceneManager", SceneManager, raising=False)
    mp.syspath_prepend(str(GSPLAT_EXAMPLES))
    for name in ("datasets", "datasets.colmap"):
        mp.delitem(sys.modules, name, raising=False)
    from datasets.colmap import Dataset, Parser

    parser = Parser(str(project), factor=2, normalize=False, test_every=8)
    yield parser, Dataset
    mp.undo()


@pytest.mark.shared
def test_images_and_intrinsics_are_gsplats_undistorted_ones(gsplat_parser):
    parser, dataset_cls = gsplat_parser
    assert all(len(p) == 4 and p[0] == pytest.approx(K1) for p in parser.params_dict.values())
    inputs = VisibilityInputs.from_gsplat_parser(parser)
    train = dataset_cls(parser, split="train")
    for item in (0, 7, 20):
        data = train[item]
        view = int(train.indices[item])
        assert view == inputs.train_views[item]
        img = inputs.load_image(view, None)
        h, w = data["image"].shape[:2]
        assert inputs.size(view) == (h, w) and (h, w) != (72, 120)  # the ROI crop
        torch.testing.assert_close(img, data["image"].permute(2, 0, 1) / 255.0, rtol=0, atol=0)
        K = data["K"].clone()
        K[:2, 2] -= 0.5  # gsplat: pixel centres at i + 0.5
        torch.testing.assert_close(inputs.cameras.K[view], K)
    # geometry: COLMAP's keypoints (distorted pixels of the SfM points), undistorted with OpenCV
    # into the new camera, are where the inputs' pinhole camera projects the points
    import cv2

    cid = parser.camera_ids[0]
    dist = np.asarray(parser.params_dict[cid], dtype=np.float64)
    K0 = np.array(parser.Ks_dict[cid], dtype=np.float64)  # the undistorted K
    view = 0
    idx = parser.point_indices[parser.image_names[view]]
    pts = torch.as_tensor(parser.points[idx], dtype=torch.float32)
    uv, _ = project_points(
        pts[None], inputs.cameras.K[view : view + 1], inputs.cameras.world_to_cam[view : view + 1]
    )
    w2c = np.linalg.inv(parser.camtoworlds[view])
    cam = parser.points[idx].astype(np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
    # the distorted pixels, as COLMAP projected them (factor 2: K halved, distortion unchanged)
    x, y = cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2]
    r = 1 + K1 * (x * x + y * y)
    Kd = _distorted_K(parser, cid)
    dpx = np.stack([Kd[0, 0] * x * r + Kd[0, 2], Kd[1, 1] * y * r + Kd[1, 2]], -1)
    und = cv2.undistortPoints(dpx[:, None], Kd, dist, P=K0)[:, 0] - 0.5  # vadgs's pixel centres
    roi = parser.roi_undist_dict[cid]
    assert roi[0] == roi[1] == 0  # getOptimalNewCameraMatrix(alpha=0) keeps the origin here
    np.testing.assert_allclose(uv[0].numpy(), und, atol=0.02)


def _distorted_K(parser, cid) -> np.ndarray:
    """The K of the distorted images at the parser's factor (before gsplat's undistortion)."""
    cam = SceneManager(str(parser.data_dir) + "/sparse/0")
    cam.load_cameras()
    c = cam.cameras[cid]
    return np.array([[c.fx, 0, c.cx], [0, c.fy, c.cy], [0, 0, 1]], dtype=np.float64) / np.array(
        [[parser.factor], [parser.factor], [1]]
    )


def test_refuses_distortion_without_maps_and_fisheye(tmp_path):
    write_sample_colmap(tmp_path / "p", n_points=200)
    parser = sample_parser(tmp_path / "p", factor=2)
    assert VisibilityInputs.from_gsplat_parser(parser).num_views == 24  # pinhole: no params_dict
    bad = copy.copy(parser)
    bad.params_dict = {c: np.array([0.05, 0, 0, 0], dtype=np.float32) for c in parser.Ks_dict}
    with pytest.raises(
        ValueError, match=r"parser camera 1: expected mapx_dict / mapy_dict / roi_undist_dict"
    ):
        VisibilityInputs.from_gsplat_parser(bad)
    fisheye = copy.copy(bad)
    fisheye.mask_dict = {c: np.ones((4, 4), dtype=bool) for c in parser.Ks_dict}
    with pytest.raises(
        ValueError, match=r"parser camera 1: expected a perspective camera, got a fisheye one"
    ):
        VisibilityInputs.from_gsplat_parser(fisheye)
