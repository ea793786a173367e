"""Tests of vadgs.data.undistort against OpenCV (cv2 is a dev dependency) and by hand."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from vadgs.data.undistort import (
    ImageUndistorter,
    distort_points,
    distortion_coefficients,
    remap,
    undistorted_intrinsics,
    undistortion_map,
)

cv2 = pytest.importorskip("cv2")

# Waymo's real FRONT camera (k1, k2, p1, p2, k3), its K with the 0.5 px offset applied, 1920x1280
WAYMO_K = np.array(
    [[2044.5083584358413, 0.0, 949.0746451352071], [0.0, 2044.5083584358413, 632.7422462156501], [0, 0, 1]]
)
WAYMO_DIST = [0.040358363932006036, -0.33001662226602974, 0.0010402702690110032, -0.0015669020781401406, 0.0]
SMALL_K = np.array([[60.0, 0.0, 40.2], [0.0, 58.0, 29.7], [0.0, 0.0, 1.0]])
CASES = {  # name: (K, coefficients, (H, W))
    "waymo": (WAYMO_K, WAYMO_DIST, (1280, 1920)),
    "barrel": (SMALL_K, [-0.25, 0.05, 0.0, 0.0], (60, 80)),
    "pincushion": (SMALL_K, [0.15, 0.02, 0.002, -0.001, 0.01], (60, 80)),
    "rational": (SMALL_K, [0.1, 0.01, 0.001, 0.0, 0.0, 0.05, 0.01, 0.0], (60, 80)),
    "prism": (SMALL_K, [0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.002, 0.0, -0.003, 0.0], (60, 80)),
}


def _t(a) -> torch.Tensor:
    return torch.as_tensor(np.asarray(a, dtype=np.float64))


class TestDistortionCoefficients:
    def test_pads(self):
        assert distortion_coefficients([1, 2, 3, 4]).tolist() == [1, 2, 3, 4] + [0.0] * 8
        assert distortion_coefficients(torch.arange(12.0)).dtype == torch.float64

    def test_exception(self):
        with pytest.raises(ValueError, match=r"distortion: expected 4, 5, 8 or 12 coefficients .* got 6"):
            distortion_coefficients([0.0] * 6)
        with pytest.raises(ValueError, match="finite"):
            distortion_coefficients([float("nan"), 0, 0, 0])
        with pytest.raises(ValueError, match=r"dist: expected 4, 5, 8 or 12 numbers"):
            distortion_coefficients("abc", "dist")


class TestDistortPoints:
    @pytest.mark.parametrize("case", sorted(CASES))
    def test_matches_opencv(self, case):
        K, dist, _ = CASES[case]
        rng = np.random.default_rng(0)
        pts = np.c_[rng.uniform(-0.4, 0.4, (50, 2)), np.ones(50)]
        want, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, np.asarray(dist, dtype=np.float64))
        xy = distort_points(_t(pts[:, :2]), distortion_coefficients(dist)).numpy()
        got = np.c_[xy, np.ones(50)] @ K.T
        np.testing.assert_allclose(got[:, :2], want[:, 0], atol=1e-9)

    def test_cardinality(self):
        d = distortion_coefficients([0.1, 0.0, 0.0, 0.0])
        assert distort_points(torch.zeros(2, 3, 2), d).shape == (2, 3, 2)
        assert distort_points(torch.zeros(2, dtype=torch.float32), d).dtype == torch.float32
        with pytest.raises(ValueError, match=r"points: expected shape \(\*, 2\)"):
            distort_points(torch.zeros(3, 3), d)

    def test_gradcheck(self):
        pts = torch.rand(4, 2, dtype=torch.float64, requires_grad=True)
        d = distortion_coefficients([0.1, -0.2, 0.01, 0.02, 0.03]).requires_grad_()
        assert torch.autograd.gradcheck(distort_points, (pts, d))


class TestUndistortedIntrinsics:
    @pytest.mark.parametrize("case", sorted(CASES))
    def test_every_pixel_has_a_source_and_the_view_is_widest(self, case):
        K, dist, (h, w) = CASES[case]
        d = distortion_coefficients(dist)
        new_K = undistorted_intrinsics(_t(K), d, (h, w))
        assert new_K[:2, 2].tolist() == K[:2, 2].tolist()  # principal point kept
        assert float(new_K[0, 0] / K[0, 0]) == pytest.approx(float(new_K[1, 1] / K[1, 1]), rel=1e-12)

        def inside(m: torch.Tensor, tol: float = 1e-6) -> bool:
            x, y = m[..., 0], m[..., 1]
            return bool(
                ((x >= -0.5 - tol) & (x <= w - 0.5 + tol) & (y >= -0.5 - tol) & (y <= h - 0.5 + tol)).all()
            )

        assert inside(undistortion_map(_t(K), d, (h, w), new_K))
        wider = new_K.clone()
        wider[:2, :2] *= 0.999
        assert not inside(undistortion_map(_t(K), d, (h, w), wider))

    def test_no_distortion_keeps_K(self):
        K = _t(SMALL_K)
        assert torch.equal(undistorted_intrinsics(K, distortion_coefficients([0.0] * 5), (60, 80)), K)

    def test_exception(self):
        with pytest.raises(ValueError, match=r"K: expected shape \(3, 3\)"):
            undistorted_intrinsics(torch.eye(4), distortion_coefficients([0.0] * 4), (6, 8))
        with pytest.raises(ValueError, match=r"^K: expected positive focal lengths .*, got fx=-1, fy=-1$"):
            undistorted_intrinsics(-torch.eye(3), distortion_coefficients([0.0] * 4), (6, 8))
        with pytest.raises(ValueError, match="image_size"):
            undistorted_intrinsics(_t(SMALL_K), distortion_coefficients([0.1] * 4), (0, 8))
        with pytest.raises(ValueError, match="folds over"):  # r (1 - 4000 r^2) folds at r = 0.009
            undistorted_intrinsics(_t(SMALL_K), distortion_coefficients([-4000.0, 0, 0, 0]), (60, 80))


class TestUndistortionMap:
    @pytest.mark.parametrize("case", sorted(CASES))
    def test_matches_opencv(self, case):
        K, dist, (h, w) = CASES[case]
        d = distortion_coefficients(dist)
        new_K = undistorted_intrinsics(_t(K), d, (h, w))
        m = undistortion_map(_t(K), d, (h, w), new_K).numpy()
        mx, my = cv2.initUndistortRectifyMap(
            K, np.asarray(dist, dtype=np.float64), None, new_K.numpy(), (w, h), cv2.CV_32FC1
        )
        np.testing.assert_allclose(m[..., 0], mx, atol=2e-3 * max(w, h) / 100)
        np.testing.assert_allclose(m[..., 1], my, atol=2e-3 * max(w, h) / 100)

    def test_undistort_points_lands_on_the_pinhole_projection(self):
        """cv2.undistortPoints of a raw pixel = the pinhole pixel whose map entry is that raw pixel."""
        K, dist, (h, w) = CASES["waymo"]
        new_K = undistorted_intrinsics(_t(K), distortion_coefficients(dist), (h, w)).numpy()
        rng = np.random.default_rng(1)
        raw = np.c_[rng.uniform(0, w - 1, 200), rng.uniform(0, h - 1, 200)]
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)
        pinhole = cv2.undistortPoints(raw[:, None], K, np.asarray(dist), P=new_K, criteria=crit)[:, 0]
        n = (np.c_[pinhole, np.ones(200)] @ np.linalg.inv(new_K).T)[:, :2]
        back = np.c_[distort_points(_t(n), distortion_coefficients(dist)).numpy(), np.ones(200)] @ K.T
        np.testing.assert_allclose(back[:, :2], raw, atol=1e-6)


class TestRemap:
    def test_matches_opencv(self):
        K, dist, (h, w) = CASES["pincushion"]
        d = distortion_coefficients(dist)
        m = undistortion_map(_t(K), d, (h, w), undistorted_intrinsics(_t(K), d, (h, w))).float()
        rng = np.random.default_rng(2)
        img = cv2.GaussianBlur(rng.uniform(0, 1, (h, w, 3)).astype(np.float32), (0, 0), 1.5)
        want = cv2.remap(
            img, m[..., 0].numpy(), m[..., 1].numpy(), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
        got = remap(torch.from_numpy(img).permute(2, 0, 1)[None], m)[0].permute(1, 2, 0).numpy()
        np.testing.assert_allclose(got, want, atol=2e-3)

    def test_nearest_keeps_labels(self):
        labels = torch.tensor([[[[1, 2, 3], [4, 5, 6]]]], dtype=torch.int64)
        m = torch.tensor([[[0.4, 0.6], [1.6, 0.0], [2.2, 1.0]]])
        out = remap(labels, m, mode="nearest")
        assert out.dtype == torch.int64 and out.tolist() == [[[[4, 3, 6]]]]

    def test_exception(self):
        with pytest.raises(ValueError, match="mode: an integer image"):
            remap(torch.zeros(1, 1, 2, 2, dtype=torch.int64), torch.zeros(1, 1, 2))
        with pytest.raises(ValueError, match="mode: expected 'bilinear' or 'nearest'"):
            remap(torch.zeros(1, 1, 2, 2), torch.zeros(1, 1, 2), mode="bicubic")
        with pytest.raises(ValueError, match=r"map_xy: expected shape \(h, w, 2\)"):
            remap(torch.zeros(1, 1, 2, 2), torch.zeros(1, 2))


class TestImageUndistorter:
    def test_module_equals_functions(self):
        K, dist, (h, w) = CASES["barrel"]
        und = ImageUndistorter(_t(K), distortion_coefficients(dist), (h, w))
        d = distortion_coefficients(dist)
        torch.testing.assert_close(und.K, undistorted_intrinsics(_t(K), d, (h, w)))
        img = torch.rand(2, 3, h, w)
        torch.testing.assert_close(und(img), remap(img, undistortion_map(_t(K), d, (h, w), und.K).float()))
        ids = torch.randint(0, 9, (1, 1, h, w))
        assert und(ids, mode="nearest").dtype == torch.int64

    def test_identity_without_distortion(self):
        und = ImageUndistorter(_t(SMALL_K), [0.0] * 4, (60, 80))
        img = torch.rand(1, 3, 60, 80)
        assert not und.distorted and und(img) is img and torch.equal(und.K, _t(SMALL_K))

    def test_exception(self):
        und = ImageUndistorter(_t(SMALL_K), [0.1, 0, 0, 0], (60, 80))
        with pytest.raises(ValueError, match=r"image: expected shape \(B, C, 60, 80\)"):
            und(torch.zeros(1, 3, 80, 60))
