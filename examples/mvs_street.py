"""Multi-view PatchMatch on a rendered street scene: one reference view and 4 source views.

    python examples/mvs_street.py [--scene ../shared/data/street_a] [--frame 20] [--car]

Reads the benchmark format directly (scene.json, images, depth), runs PatchMatch on the front
camera at ``--frame`` with the front camera of the frames ``f-2, f-1, f+1, f+2`` as sources,
filters by cost and by geometric consistency against the depth maps of the neighbouring
references, and prints the share of pixels within 1 % and 5 % of the ground-truth depth.
``--car`` runs it on the largest moving car of that view instead, in the car's own frame
(``vadgs.geometry.cameras_in_object_frame``), restricted to its instance mask.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from vadgs.geometry import cameras_in_object_frame
from vadgs.mvs import PatchMatchConfig, geometric_consistency, patchmatch

REPO = Path(__file__).resolve().parents[1]
DEFAULT_SCENE = REPO.parent / "shared" / "data" / "street_a"
CONFIG = PatchMatchConfig(iterations=3, sigma_color=0.1)
DEPTH_RANGE = (1.0, 80.0)


class StreetScene:
    """Just enough of the benchmark format for MVS (``vadgs.data.load_scene`` does it all)."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        self.meta = json.loads((self.root / "scene.json").read_text())

    def _view(self, frame: int, camera: str) -> dict:
        return next(v for v in self.meta["frames"][frame]["views"] if v["camera"] == camera)

    def load(self, frame: int, camera: str = "front"):
        """``image (3, H, W)``, ``depth (1, H, W)``, ``instances (H, W)``, ``K``, ``world_to_cam``."""
        v = self._view(frame, camera)
        img = np.array(Image.open(self.root / v["image"]).convert("RGB"))
        image = torch.from_numpy(img).permute(2, 0, 1).float() / 255
        depth = torch.from_numpy(np.load(self.root / v["depth"])["depth"].astype(np.float32))[None]
        inst = torch.from_numpy(np.array(Image.open(self.root / v["instances"])).astype(np.int64))
        K = torch.tensor(self.meta["cameras"][camera]["K"], dtype=torch.float32)
        world_to_cam = torch.linalg.inv(torch.tensor(v["cam_to_world"], dtype=torch.float64)).float()
        return image, depth, inst, K, world_to_cam

    def object_to_world(self, track_id: int, frame: int) -> torch.Tensor:
        track = next(t for t in self.meta["tracks"] if t["id"] == track_id)
        return torch.tensor(track["object_to_world"][str(frame)], dtype=torch.float32)

    @property
    def track_ids(self) -> list[int]:
        return [t["id"] for t in self.meta["tracks"]]


def source_frames(frame: int) -> list[int]:
    return [frame - 2, frame - 1, frame + 1, frame + 2]


def batch(scene: StreetScene, refs: list[int], camera: str = "front"):
    """Stack references and their sources: images, K, poses, GT depth, instances."""
    out = {k: [] for k in ("img", "K", "w2c", "depth", "inst", "simg", "sK", "sw2c", "sinst", "frames")}
    for f in refs:
        img, depth, inst, K, w2c = scene.load(f, camera)
        srcs = [scene.load(s, camera) for s in source_frames(f)]
        out["img"].append(img)
        out["K"].append(K)
        out["w2c"].append(w2c)
        out["depth"].append(depth)
        out["inst"].append(inst)
        out["simg"].append(torch.stack([s[0] for s in srcs]))
        out["sK"].append(torch.stack([s[3] for s in srcs]))
        out["sw2c"].append(torch.stack([s[4] for s in srcs]))
        out["sinst"].append(torch.stack([s[2] for s in srcs]))
        out["frames"].append(source_frames(f))
    return {k: (torch.stack(v) if k != "frames" else v) for k, v in out.items()}


def depth_accuracy(depth: torch.Tensor, gt: torch.Tensor, region: torch.Tensor | None = None) -> dict:
    """Shares of ground-truth pixels (``gt > 0``, in ``region``) within 1 % / 5 % (missing = wrong)."""
    known = gt > 0 if region is None else (gt > 0) & region
    rel = (depth - gt).abs() / gt.clamp_min(1e-6)
    has = depth > 0
    n = max(int(known.sum()), 1)
    return {
        "within_1pct": float(((rel <= 0.01) & has & known).sum()) / n,
        "within_5pct": float(((rel <= 0.05) & has & known).sum()) / n,
        "completeness": float((has & known).sum()) / n,
        "precision_5pct": float(((rel <= 0.05) & has & known).sum()) / max(int((has & known).sum()), 1),
    }


def run_street(scene: StreetScene, frame: int, config: PatchMatchConfig = CONFIG):
    """PatchMatch on references ``frame - 1, frame, frame + 1``; ``frame`` filtered by the others."""
    refs = [frame - 1, frame, frame + 1]
    b = batch(scene, refs)
    t0 = time.perf_counter()
    res = patchmatch(b["img"], b["simg"], b["K"], b["sK"], b["w2c"], b["sw2c"], DEPTH_RANGE, config)
    seconds = time.perf_counter() - t0
    # the middle reference, checked against the depth maps of its two neighbours
    cons = geometric_consistency(
        res.depth[1:2], b["K"][1:2], b["w2c"][1:2], res.depth[[0, 2]][None], b["K"][[0, 2]][None],
        b["w2c"][[0, 2]][None], max_reproj_error=1.0, max_rel_depth=0.01, min_views=2,
    )  # fmt: skip
    filtered = torch.where(cons.mask, res.depth[1:2], torch.zeros_like(res.depth[1:2]))
    gt = b["depth"][1:2]
    return (
        {
            "raw": depth_accuracy(res.raw_depth[1:2], gt),
            "cost_filtered": depth_accuracy(res.depth[1:2], gt),
            "consistency_filtered": depth_accuracy(filtered, gt),
            "seconds_3_refs": seconds,
        },
        res,
        filtered,
        gt,
        b,
    )


def largest_moving_car(scene: StreetScene, frame: int, camera: str = "front") -> int:
    inst = scene.load(frame, camera)[2]
    areas = {t: int((inst == t).sum()) for t in scene.track_ids}
    return max(areas, key=areas.get)


def run_car(scene: StreetScene, frame: int, config: PatchMatchConfig = CONFIG):
    """PatchMatch on the largest moving car of the front view, in the car's own frame."""
    track = largest_moving_car(scene, frame)
    b = batch(scene, [frame])
    frames = [frame, *source_frames(frame)]
    obj = torch.stack([scene.object_to_world(track, f) for f in frames])
    w2c_all = torch.cat([b["w2c"], b["sw2c"][0]])
    w2c_obj = cameras_in_object_frame(w2c_all, obj)  # object_to_cam: the car is static in it
    mask = b["inst"][:, None] == track
    src_masks = (b["sinst"] == track)[:, :, None]
    res = patchmatch(
        b["img"], b["simg"], b["K"], b["sK"], w2c_obj[:1], w2c_obj[None, 1:], DEPTH_RANGE, config,
        mask=mask, src_masks=src_masks,
    )  # fmt: skip
    world = patchmatch(
        b["img"], b["simg"], b["K"], b["sK"], b["w2c"], b["sw2c"], DEPTH_RANGE, config, mask=mask
    )
    gt = b["depth"]
    return {
        "track": track,
        "pixels": int(mask.sum()),
        "object_frame": depth_accuracy(res.depth, gt, mask),
        "object_frame_raw": depth_accuracy(res.raw_depth, gt, mask),
        "world_frame_raw": depth_accuracy(world.raw_depth, gt, mask),
    }


def save_figure(path, image, gt, depth, filtered) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    inv = lambda d: np.where(d > 0, 1 / np.maximum(d, 1e-6), np.nan)  # noqa: E731
    rel = np.where(gt > 0, np.abs(depth - gt) / np.maximum(gt, 1e-6), np.nan)
    fig, ax = plt.subplots(2, 2, figsize=(10, 6.4))
    panels = [
        (image, "reference (front)"), (inv(gt), "ground-truth inverse depth"),
        (inv(depth), "PatchMatch inverse depth (raw)"), (inv(filtered), "after consistency filtering"),
    ]  # fmt: skip
    for a, (img, title) in zip(ax.flat, panels):
        a.imshow(img) if img.ndim == 3 else a.imshow(img, vmin=0, vmax=0.5)
        a.set_title(title)
        a.axis("off")
    ax[1, 0].set_title(f"PatchMatch inverse depth (raw), {np.mean(rel[gt > 0] < 0.05):.0%} within 5 %")
    fig.tight_layout()
    fig.savefig(path, dpi=55)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default=str(DEFAULT_SCENE))
    parser.add_argument("--frame", type=int, default=20)
    parser.add_argument("--car", action="store_true")
    parser.add_argument("--out", default="mvs_street.png")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    scene = StreetScene(args.scene)
    if args.car:
        print(json.dumps(run_car(scene, args.frame), indent=1))
        return
    metrics, res, filtered, gt, b = run_street(scene, args.frame)
    print(json.dumps(metrics, indent=1))
    save_figure(
        args.out, b["img"][1].permute(1, 2, 0).numpy(), gt[0, 0].numpy(), res.raw_depth[1, 0].numpy(),
        filtered[0, 0].numpy(),
    )  # fmt: skip
    print("wrote", args.out)


if __name__ == "__main__":
    main()
