"""PatchMatch stereo on the Middlebury 2014 Motorcycle pair shipped with scikit-image.

    python examples/mvs_middlebury.py [--out docs/img/mvs_middlebury.png] [--threads 1]

The pair is treated as a two-view MVS problem with the given calibration: the left camera at the
origin, the right one 193.001 mm to its right with its principal point ``doffs`` further right
(Middlebury convention: ``Z = b f / (d + doffs)``, hence ``cx_right = cx_left + doffs``). Both
directions run in one batch (left → right, right → left); a left–right check
(:func:`vadgs.mvs.geometric_consistency`, 1 px) removes occluded and mismatched pixels, which are
then filled scanline-wise with the farther of the nearest valid neighbours
(:func:`vadgs.mvs.fill_holes_scanline`, the classic PatchMatch-stereo / SGM post-processing).
Prints EPE and bad-1 / bad-2 over all pixels with finite ground truth (pixels without an estimate
count as bad) next to OpenCV's StereoSGBM.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from vadgs.mvs import PatchMatchConfig, fill_holes_scanline, geometric_consistency, patchmatch

F_PX, CX, CY, DOFFS, BASELINE = 994.978, 311.193, 254.877, 31.086, 0.193001  # metres
CONFIG = PatchMatchConfig(iterations=3, sigma_color=0.1)


def load_motorcycle():
    """Left, right (uint8 HxWx3) and ground-truth disparity (+inf where unknown)."""
    from skimage.data import stereo_motorcycle

    return stereo_motorcycle()


def stereo_cameras():
    """``K (2, 3, 3)``, ``world_to_cam (2, 4, 4)`` of the left and right cameras."""
    K = torch.tensor([[F_PX, 0, CX], [0, F_PX, CY], [0, 0, 1]])
    K_right = K.clone()
    K_right[0, 2] += DOFFS
    right = torch.eye(4)
    right[0, 3] = -BASELINE  # the right camera centre is at x = +baseline
    return torch.stack([K, K_right]), torch.stack([torch.eye(4), right])


def depth_to_disparity(depth: np.ndarray) -> np.ndarray:
    return np.where(depth > 0, BASELINE * F_PX / np.maximum(depth, 1e-12) - DOFFS, np.nan)


def patchmatch_stereo(left: np.ndarray, right: np.ndarray, config: PatchMatchConfig = CONFIG):
    """Disparity of the left view (filled) and the left–right-checked mask."""
    imgs = torch.from_numpy(np.stack([left, right])).permute(0, 3, 1, 2).float() / 255
    K, w2c = stereo_cameras()
    res = patchmatch(
        imgs, imgs.flip(0)[:, None], K, K.flip(0)[:, None], w2c, w2c.flip(0)[:, None], (1.5, 10.0), config
    )
    cons = geometric_consistency(
        res.raw_depth, K, w2c, res.raw_depth.flip(0)[:, None], K.flip(0)[:, None], w2c.flip(0)[:, None],
        max_reproj_error=1.0, max_rel_depth=0.05, min_views=1,
    )  # fmt: skip
    filled = fill_holes_scanline(res.raw_depth[:1], cons.mask[:1], keep="far")
    ok = cons.mask[0, 0].numpy()
    return depth_to_disparity(filled[0, 0].numpy()), ok, depth_to_disparity(res.raw_depth[0, 0].numpy())


def sgbm(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    import cv2

    matcher = cv2.StereoSGBM_create(
        minDisparity=0, numDisparities=64, blockSize=5, P1=8 * 3 * 25, P2=32 * 3 * 25,
        uniquenessRatio=10, speckleWindowSize=100, speckleRange=2, disp12MaxDiff=1,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )  # fmt: skip
    disp = matcher.compute(left, right).astype(np.float32) / 16
    return np.where(disp < 0, np.nan, disp)


def metrics(disp: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """EPE over estimated pixels; bad-1 / bad-2 over all finite-GT pixels (missing = bad)."""
    known = np.isfinite(gt)
    err = np.abs(disp - gt)[known]
    has = np.isfinite(err)
    return {
        "epe": float(err[has].mean()),
        "bad1": float(1 - (err[has] <= 1).sum() / err.size),
        "bad2": float(1 - (err[has] <= 2).sum() / err.size),
        "coverage": float(has.mean()),
    }


def save_figure(path: str, left, gt, disp, sg) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 2, figsize=(10, 7))
    panels = [
        (left, "left image"),
        (gt, "ground truth"),
        (disp, "PatchMatch (LR check + fill)"),
        (sg, "StereoSGBM"),
    ]
    for a, (img, title) in zip(ax.flat, panels):
        a.imshow(img) if img.ndim == 3 else a.imshow(np.where(np.isfinite(img), img, np.nan), vmin=0, vmax=65)
        a.set_title(title)
        a.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=55)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="mvs_middlebury.png")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    left, right, gt = load_motorcycle()
    t0 = time.perf_counter()
    disp, _, raw = patchmatch_stereo(left, right)
    t_pm = time.perf_counter() - t0
    t0 = time.perf_counter()
    sg = sgbm(left, right)
    t_sg = time.perf_counter() - t0
    for name, d in [("patchmatch raw", raw), ("patchmatch LR+fill", disp), ("StereoSGBM", sg)]:
        m = metrics(d, gt)
        print(f"{name:20s} EPE {m['epe']:.2f} px  bad-1 {m['bad1']:.1%}  bad-2 {m['bad2']:.1%}", end="")
        print(f"  coverage {m['coverage']:.1%}")
    print(f"time: patchmatch {t_pm:.1f} s, SGBM {t_sg * 1e3:.0f} ms, ratio {t_pm / t_sg:.0f}x")
    save_figure(args.out, left, gt, disp, sg)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
