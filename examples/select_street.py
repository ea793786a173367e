"""Diversity-aware view selection on a benchmark street scene (street_a / street_b).

Builds the view × voxel visibility of the traffic sign (static, world frame), of the overtaken
car (moving, in its own object frame) and of whole views straight from the scene's ground-truth
depth and instance maps (a z-buffer by construction), selects k = 4 supporting views for every
reference view, prints a summary and draws the selection of one sign reference from above.

    python examples/select_street.py [--scene ../shared/data/street_a] [--out docs/img/select_sign.png]

The loader below reads ``scene.json`` directly so that this example (and the tests and
benchmarks that reuse it) does not depend on ``vadgs.data``; only ``vadgs.select`` and
``vadgs.geometry`` are used.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from vadgs.geometry import invert_rigid
from vadgs.select import Covisibility, ViewSelectionConfig, ViewSelector

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
CAMERAS = ("front", "front_left", "front_right")


@dataclass
class StreetViews:
    """Per-view data of a street scene, views ordered frame-major (view = 3 * frame + camera)."""

    meta: dict
    world_to_cam: torch.Tensor  # (V, 4, 4) float64
    K: torch.Tensor  # (V, 3, 3)
    camera_ids: torch.Tensor  # (V,)
    frame_ids: torch.Tensor  # (V,)
    depth: np.ndarray  # (V, H, W) float32, 0 = sky
    instances: np.ndarray  # (V, H, W) int64

    def instance_id(self, cls: str) -> int:
        return next(i["id"] for i in self.meta["instances"] if i["class"] == cls)

    def overtaken_car(self) -> int:
        """The moving car that drives the ego's way on its right (x grows, y < 0)."""
        for t in self.meta["tracks"]:
            a, b = (np.asarray(t["object_to_world"][f])[:3, 3] for f in ("0", str(self.num_frames - 1)))
            if b[0] > a[0] and a[1] < 0:
                return int(t["id"])
        raise LookupError("no overtaken car")

    @property
    def num_frames(self) -> int:
        return len(self.meta["frames"])

    def object_to_world(self, track_id: int) -> torch.Tensor:
        """``(V, 4, 4)`` the track's pose at each view's frame."""
        track = next(t for t in self.meta["tracks"] if t["id"] == track_id)
        per_frame = torch.tensor(
            np.stack([np.asarray(track["object_to_world"][str(f)]) for f in range(self.num_frames)])
        )
        return per_frame[self.frame_ids]


def load_street(scene: Path, stride: int = 2) -> StreetViews:
    """Read poses, depth and instance maps (subsampled by ``stride``) of every view."""
    meta = json.loads((scene / "scene.json").read_text())
    w2c, Ks, cams, frames, depths, insts = [], [], [], [], [], []
    for frame in meta["frames"]:
        for view in frame["views"]:
            cam = meta["cameras"][view["camera"]]
            w2c.append(np.linalg.inv(np.asarray(view["cam_to_world"])))
            Ks.append(np.asarray(cam["K"]))
            cams.append(CAMERAS.index(view["camera"]))
            frames.append(frame["index"])
            depths.append(np.load(scene / view["depth"])["depth"][::stride, ::stride].astype(np.float32))
            insts.append(
                np.asarray(Image.open(scene / view["instances"]))[::stride, ::stride].astype(np.int64)
            )
    K = torch.tensor(np.stack(Ks))
    K[:, :2, :2] /= stride  # pixel (u, v) of the subsampled map is pixel (stride u, stride v)
    K[:, :2, 2] /= stride
    return StreetViews(
        meta,
        torch.tensor(np.stack(w2c)),
        K,
        torch.tensor(cams),
        torch.tensor(frames),
        np.stack(depths),
        np.stack(insts),
    )


def street_covisibility(
    views: StreetViews,
    instance: int | None = None,
    voxel_size: float = 0.2,
    object_frame: bool = False,
    max_depth: float = 60.0,
    dtype: torch.dtype = torch.float32,
) -> Covisibility:
    """Voxelise the pixels of ``instance`` (all static pixels when None) and record who sees what.

    With ``object_frame`` the points are moved into the instance's own frame at each view's
    timestamp and the cameras become object-to-camera transforms (a moving car is static there).
    """
    V, H, W = views.depth.shape
    dynamic = {t["id"] for t in views.meta["tracks"]}
    us, vs = np.meshgrid(np.arange(W), np.arange(H))
    pix = np.stack([us, vs, np.ones_like(us)], -1).reshape(-1, 3).astype(np.float64)
    c2w = invert_rigid(views.world_to_cam).numpy()
    o2w = views.object_to_world(instance).numpy() if object_frame else None
    pts, owner = [], []
    for v in range(V):
        d = views.depth[v].reshape(-1)
        ids = views.instances[v].reshape(-1)
        keep = (d > 0) & (d < max_depth)
        keep &= (ids == instance) if instance is not None else ~np.isin(ids, list(dynamic))
        rays = pix[keep] @ np.linalg.inv(views.K[v].numpy()).T
        p = (rays * d[keep, None]) @ c2w[v, :3, :3].T + c2w[v, :3, 3]
        if o2w is not None:
            w2o = np.linalg.inv(o2w[v])
            p = p @ w2o[:3, :3].T + w2o[:3, 3]
        pts.append(p)
        owner.append(np.full(len(p), v))
    pts, owner = np.concatenate(pts), np.concatenate(owner)
    keys = np.floor(pts / voxel_size).astype(np.int64)
    keys -= keys.min(0)
    span = keys.max(0) + 1
    flat = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
    uniq, vox = np.unique(flat, return_inverse=True)
    cell = np.stack(np.unravel_index(uniq, tuple(span)), -1) + np.floor(pts / voxel_size).astype(
        np.int64
    ).min(0)
    centers = torch.tensor((cell + 0.5) * voxel_size, dtype=dtype)
    pairs = np.unique(owner.astype(np.int64) * len(uniq) + vox.reshape(-1))  # (view, voxel), sorted
    bounds = np.searchsorted(pairs, np.arange(V + 1) * len(uniq))
    visible = [torch.from_numpy(pairs[bounds[v] : bounds[v + 1]] - v * len(uniq)) for v in range(V)]
    w2c = views.world_to_cam
    if o2w is not None:
        w2c = w2c @ torch.tensor(o2w)
    return Covisibility.from_visible(visible, centers, w2c.to(dtype), views.camera_ids, views.frame_ids)


def summarize(name: str, covis: Covisibility, selections, refs) -> dict:
    """Share of references whose selection spans >= 2 cameras, or >= 3 timestamps."""
    cams, frames = covis.camera_ids, covis.frame_ids
    n_ok = n_multi_cam = n_multi_time = n_possible = 0
    for sel in selections:
        n_ok += sel.complete
        if len(sel.views) == 0:
            continue
        n_multi_cam += len(set(cams[sel.views].tolist())) >= 2
        n_multi_time += len(set(frames[sel.views].tolist())) >= 3
        n_possible += len(set(cams[sel.candidates].tolist())) >= 2
    out = dict(
        name=name,
        refs=len(refs),
        complete=n_ok,
        multi_camera=n_multi_cam,
        multi_camera_possible=n_possible,
        multi_timestamp=n_multi_time,
    )
    print(
        f"{name:28s} refs={len(refs):3d} k-complete={n_ok:3d} >=2 cameras={n_multi_cam:3d} "
        f"(possible {n_possible:3d}) >=3 timestamps={n_multi_time:3d}"
    )
    return out


def plot_selection(covis: Covisibility, ref: int, views: torch.Tensor, path: Path, title: str) -> None:
    """Camera frusta from above (x forward, y left), reference black, selected coloured by camera."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c2w = invert_rigid(covis.world_to_cam.double())
    centers = c2w[:, :3, 3].numpy()
    fwd = c2w[:, :3, 2].numpy()
    colors = {0: "tab:blue", 1: "tab:orange", 2: "tab:green"}
    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=100)
    vox = covis.voxel_centers.numpy()
    seen = covis.incidence.to_dense()[ref].bool().numpy()
    ax.scatter(vox[seen, 0], vox[seen, 1], s=4, c="crimson", label="voxels seen by the reference", zorder=3)
    ax.scatter(centers[:, 0], centers[:, 1], s=3, c="lightgray", zorder=1)

    def frustum(v: int, color: str, lw: float, label: str | None) -> None:
        c, f = centers[v], fwd[v]
        half = np.radians(32.0)
        rot = np.array([[np.cos(half), -np.sin(half)], [np.sin(half), np.cos(half)]])
        f2 = f[:2] / np.linalg.norm(f[:2]) * 6.0
        a, b = rot @ f2, rot.T @ f2
        poly = np.array([c[:2], c[:2] + a, c[:2] + b, c[:2]])
        ax.plot(poly[:, 0], poly[:, 1], color=color, lw=lw, label=label, zorder=2)

    frames = covis.frame_ids
    frustum(ref, "black", 2.0, f"reference: {CAMERAS[int(covis.camera_ids[ref])]} @ frame {int(frames[ref])}")
    for v in views.tolist():
        cam = int(covis.camera_ids[v])
        frustum(v, colors[cam], 1.5, f"{CAMERAS[cam]} @ frame {int(frames[v])}")
    involved = np.concatenate([centers[[ref, *views.tolist()], :2], vox[seen, :2]])
    lo, hi = involved.min(0) - 8.0, involved.max(0) + 8.0
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, driving direction)")
    ax.set_ylabel("y (m, left)")
    ax.set_title(title)
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.02, 0.5))
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, default=SHARED / "data" / "street_a")
    parser.add_argument("--out", type=Path, default=None, help="picture of one sign selection")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    views = load_street(args.scene)
    selector = ViewSelector(ViewSelectionConfig(k=4), seed=args.seed)
    sign = views.instance_id("sign")
    car = views.overtaken_car()
    cases = {
        "traffic sign (world)": street_covisibility(views, sign),
        "overtaken car (object frame)": street_covisibility(views, car, object_frame=True),
    }
    for name, covis in cases.items():
        refs = torch.nonzero(covis.visible_counts() >= selector.config.min_shared).squeeze(1).tolist()
        selections = selector.select_all(covis, refs)
        summarize(name, covis, selections, refs)

    covis = cases["traffic sign (world)"]
    refs = torch.nonzero(covis.visible_counts() >= selector.config.min_shared).squeeze(1).tolist()
    ref = refs[len(refs) // 2]
    sel = selector(ref, covis)
    print(
        f"sign reference {ref}: views {sel.views.tolist()}, cameras "
        f"{covis.camera_ids[sel.views].tolist()}, frames {covis.frame_ids[sel.views].tolist()}, {sel.reason}"
    )
    if args.out is not None:
        plot_selection(covis, ref, sel.views, args.out, f"{args.scene.name}: supporting views of the sign")
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
