"""Voxel z-buffer on street_a: accuracy, coverage per class, Embree agreement, figures.

Accumulates the LiDAR of the training frames (moving cars excluded), voxelises it at 0.2 m,
rasterises the grid into every view in both depth modes and compares with the ground-truth
depth and instance maps, and (box mode) pixel by pixel with an Embree ray cast of the same boxes.

    python benchmarks/zbuffer_accuracy.py                       # all 120 views, prints tables
    python benchmarks/zbuffer_accuracy.py --views 0,31,62 --no-figures

Needs ../shared/data/street_a (or --scene), trimesh and embreex for the reference.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from vadgs.data import load_scene
from vadgs.data.lidar import accumulate_lidar
from vadgs.geometry import VoxelGrid, ZBufferConfig, backproject_depth, rasterize_voxels, voxelize

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
STREET_A = SHARED / "data" / "street_a"
ROOT = Path(__file__).resolve().parents[1]


# -- the exact reference: Embree ray cast of the same boxes -------------------------------------------


def box_mesh(centers: np.ndarray, voxel_size: float):
    """One trimesh of all voxel boxes (vectorised); face ``f`` belongs to voxel ``f // 12``."""
    import trimesh

    unit = trimesh.creation.box(extents=(voxel_size,) * 3)
    nv = len(unit.vertices)
    verts = (centers[:, None, :] + unit.vertices[None]).reshape(-1, 3)
    faces = (unit.faces[None] + nv * np.arange(len(centers))[:, None, None]).reshape(-1, 3)
    return trimesh.Trimesh(verts, faces, process=False)


class EmbreeBoxes:
    """Embree (``embreex`` through trimesh) ray caster of voxel boxes: z-depth and voxel id maps."""

    def __init__(self, centers: torch.Tensor, voxel_size: float) -> None:
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        self.caster = RayMeshIntersector(box_mesh(centers.double().numpy(), voxel_size))

    def __call__(self, K: torch.Tensor, world_to_cam: torch.Tensor, size) -> tuple[np.ndarray, np.ndarray]:
        h, w = size
        K, T = K.double().numpy(), world_to_cam.double().numpy()
        rot, trans = T[:3, :3], T[:3, 3]
        vs, us = np.mgrid[0:h, 0:w]
        pix = np.stack([us.ravel(), vs.ravel(), np.ones(h * w)], 1)
        dirs = pix @ (rot.T @ np.linalg.inv(K)).T
        origins = np.broadcast_to(-rot.T @ trans, dirs.shape)
        loc, ray, tri = self.caster.intersects_location(origins, dirs, multiple_hits=False)
        depth = np.zeros(h * w)
        index = np.full(h * w, -1, dtype=np.int64)
        depth[ray] = loc @ rot[2] + trans[2]  # hit point -> z-depth in the camera frame
        index[ray] = tri // 12
        return depth.reshape(h, w), index.reshape(h, w)


# -- data ---------------------------------------------------------------------------------------------


def street_grid(scene_path: Path = STREET_A, voxel_size: float = 0.2):
    """street_a, its static LiDAR grid (training frames, moving cars excluded) and point instances."""
    scene = load_scene(scene_path)
    acc = accumulate_lidar(scene, exclude_dynamic=True)
    grid = voxelize(acc.points, voxel_size, acc.point_views, num_views=scene.num_views)
    return scene, grid, acc


def voxel_instance(grid: VoxelGrid, point_instance: torch.Tensor) -> torch.Tensor:
    """Majority instance id of each voxel's points."""
    n_ins = int(point_instance.max()) + 1
    counts = torch.bincount(grid.point_to_voxel * n_ins + point_instance, minlength=len(grid) * n_ins)
    return counts.reshape(len(grid), n_ins).argmax(1)


# -- measurements -------------------------------------------------------------------------------------


def _pct(x: torch.Tensor, q: float) -> float:
    return float(torch.quantile(x.double(), q)) if x.numel() else float("nan")


def region_stats(depth: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor, voxel_size: float) -> dict:
    """Coverage and depth error of voxel depth over the GT pixels selected by ``mask``."""
    m = mask & (gt > 0)
    n = int(m.sum())
    cov = m & (depth > 0)
    err = (depth - gt).abs()[cov]
    good = err <= 0.5
    return {
        "pixels": n,
        "coverage_any": int(cov.sum()) / max(n, 1),
        "coverage_correct": int(good.sum()) / max(n, 1),  # voxel depth within 0.5 m of GT
        "within_voxel": float((err <= voxel_size).float().mean()) if err.numel() else float("nan"),
        "behind_gt": float(((depth - gt)[cov] > 0.5).float().mean()) if err.numel() else float("nan"),
        "p50": _pct(err, 0.5),
        "p90": _pct(err, 0.9),
        "p99": _pct(err, 0.99),
    }


def evaluate(scene, grid, acc, views, modes=("box", "plane"), embree=True, threads=1) -> dict:
    torch.set_num_threads(threads)
    cams = scene.cameras(views)
    vox_ins = voxel_instance(grid, acc.instance)
    classes = scene.classes()
    dynamic = {i for i, inst in scene.instances.items() if inst.dynamic}
    regions = ["all", "road", "sidewalk", "building", "upper facade (z > 5 m)", "tree", "sign"]
    regions += ["sign board (z > 4.5 m)", "sign pole (z <= 4.5 m)"]
    regions += ["car (parked)", "car (moving)"]
    sums: dict = {mode: {r: [] for r in regions} for mode in modes}
    times: dict = {mode: [] for mode in modes}
    sign_owner: dict = {mode: {} for mode in modes}
    agree, agree_depth, t_embree = [], [], []
    caster = None
    if embree:
        t0 = time.perf_counter()
        caster = EmbreeBoxes(grid.centers, grid.voxel_size)
        t_build = time.perf_counter() - t0
    for b, vid in enumerate(views):
        gt = scene.load_depths([vid])[0, 0]
        ins = scene.load_instances([vid])[0]
        world = backproject_depth(gt[None, None], cams.K[b : b + 1], cams.cam_to_world[b : b + 1])[0]
        cls = np.vectorize(lambda i: classes.get(int(i), "sky"))(ins.numpy())
        masks = {
            "all": gt > 0,
            "road": torch.from_numpy(cls == "road"),
            "sidewalk": torch.from_numpy(cls == "sidewalk"),
            "building": torch.from_numpy(cls == "building"),
            "tree": torch.from_numpy(cls == "tree"),
            "sign": torch.from_numpy(cls == "sign"),
        }
        masks["upper facade (z > 5 m)"] = masks["building"] & (world[2] > 5.0)
        masks["sign board (z > 4.5 m)"] = masks["sign"] & (world[2] > 4.5)
        masks["sign pole (z <= 4.5 m)"] = masks["sign"] & (world[2] <= 4.5)
        moving = torch.isin(ins, torch.tensor(sorted(dynamic), dtype=torch.int64))
        masks["car (parked)"] = torch.from_numpy(cls == "car") & ~moving
        masks["car (moving)"] = moving
        for mode in modes:
            t0 = time.perf_counter()
            out = rasterize_voxels(grid, cams[[b]], [vid], ZBufferConfig(depth_mode=mode))
            times[mode].append(time.perf_counter() - t0)
            depth, index = out.depth[0, 0], out.index[0]
            for r in regions:
                sums[mode][r].append((depth, gt, masks[r]))
            sel = masks["sign"] & (index >= 0)
            for k, c in zip(*torch.unique(vox_ins[index[sel]], return_counts=True)):
                name = classes.get(int(k), "none")
                sign_owner[mode][name] = sign_owner[mode].get(name, 0) + int(c)
            if mode == "box" and caster is not None:
                t0 = time.perf_counter()
                d_ref, i_ref = caster(cams.K[b], cams.world_to_cam[b], cams.image_size)
                t_embree.append(time.perf_counter() - t0)
                same = index.numpy() == i_ref
                agree.append(same.mean())
                both = same & (i_ref >= 0)
                agree_depth.append(np.abs(depth.numpy()[both] - d_ref[both]).max() if both.any() else 0.0)
    result = {"views": len(views), "voxels": len(grid), "threads": threads, "modes": {}}
    for mode in modes:
        tab = {}
        for r in regions:
            d = torch.cat([x[0].reshape(-1) for x in sums[mode][r]])
            g = torch.cat([x[1].reshape(-1) for x in sums[mode][r]])
            m = torch.cat([x[2].reshape(-1) for x in sums[mode][r]])
            tab[r] = region_stats(d, g, m, grid.voxel_size)
        result["modes"][mode] = {
            "table": tab,
            "ms_per_view_median": 1000 * statistics.median(times[mode]),
            "sign_pixels_by_voxel_class": sign_owner[mode],
        }
    if caster is not None:
        result["embree"] = {
            "build_s": t_build,
            "ms_per_view_median": 1000 * statistics.median(t_embree),
            "index_agreement_mean": float(np.mean(agree)),
            "index_agreement_min": float(np.min(agree)),
            "max_depth_diff_on_agreeing": float(np.max(agree_depth)),
        }
    return result


def print_tables(result: dict) -> None:
    print(f"{result['views']} views, {result['voxels']} voxels, torch threads {result['threads']}")
    for mode, res in result["modes"].items():
        print(f"\n### depth_mode={mode!r}: {res['ms_per_view_median']:.0f} ms per view (median)\n")
        print("| region | GT pixels | covered (any voxel) | covered (correct, ≤ 0.5 m) | within 0.2 m "
              "| voxel behind GT (> 0.5 m) | err p50 | p90 | p99 |")  # fmt: skip
        print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
        for r, s in res["table"].items():
            print(
                f"| {r} | {s['pixels']} | {100 * s['coverage_any']:.1f}% "
                f"| {100 * s['coverage_correct']:.1f}% | {100 * s['within_voxel']:.1f}% "
                f"| {100 * s['behind_gt']:.1f}% | {s['p50']:.3f} | {s['p90']:.3f} | {s['p99']:.3f} |"
            )
        print(
            f"\nsign pixels by the class of the voxel that covers them: {res['sign_pixels_by_voxel_class']}"
        )
    if "embree" in result:
        e = result["embree"]
        print(
            f"\nEmbree box ray cast: index agreement mean {100 * e['index_agreement_mean']:.3f}% "
            f"(min {100 * e['index_agreement_min']:.3f}%), max |depth diff| on agreeing pixels "
            f"{e['max_depth_diff_on_agreeing']:.2e} m, {e['ms_per_view_median']:.0f} ms per view "
            f"(+ {e['build_s']:.1f} s BVH build)"
        )


# -- figures ------------------------------------------------------------------------------------------


def _id_colours(index: torch.Tensor) -> np.ndarray:
    rng = np.random.default_rng(0)
    lut = rng.uniform(0.15, 1.0, size=(int(index.max()) + 2, 3))
    rgb = lut[index.numpy() + 1]
    rgb[index.numpy() < 0] = 0.0
    return rgb


def figure_panels(scene, grid, view: int, out: Path, mode: str = "plane") -> None:
    """Image, voxel depth, index map (coloured by voxel id) and GT depth of one view."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cams = scene.cameras([view])
    r = rasterize_voxels(grid, cams, [view], ZBufferConfig(depth_mode=mode))
    img = scene.load_images([view])[0].permute(1, 2, 0).numpy()
    gt = scene.load_depths([view])[0, 0]
    vmax = float(torch.quantile(gt[gt > 0], 0.95))
    fig, ax = plt.subplots(1, 4, figsize=(16, 2.9))
    panels = [
        (img, "image", {}),
        (np.ma.masked_equal(r.depth[0, 0].numpy(), 0), f"voxel depth ({mode})", {"vmin": 0, "vmax": vmax}),
        (_id_colours(r.index[0]), "pixel → voxel index", {}),
        (np.ma.masked_equal(gt.numpy(), 0), "ground-truth depth", {"vmin": 0, "vmax": vmax}),
    ]
    for a, (x, title, kw) in zip(ax, panels):
        a.imshow(x, cmap="turbo", **kw)
        a.set_title(title, fontsize=10)
        a.axis("off")
    fig.tight_layout()
    fig.savefig(out, dpi=80)
    plt.close(fig)


def figure_missing(scene, grid, view: int, out: Path) -> None:
    """Where the grid has no correct depth: the sign and the upper facades (the failure case)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cams = scene.cameras([view])
    r = rasterize_voxels(grid, cams, [view], ZBufferConfig(depth_mode="plane"))
    img = scene.load_images([view])[0].permute(1, 2, 0).numpy()
    gt = scene.load_depths([view])[0, 0]
    ins = scene.load_instances([view])[0]
    world = backproject_depth(gt[None, None], cams.K, cams.cam_to_world)[0]
    classes = scene.classes()
    cls = np.vectorize(lambda i: classes.get(int(i), "sky"))(ins.numpy())
    sign = torch.from_numpy(cls == "sign")
    upper = torch.from_numpy(cls == "building") & (world[2] > 5.0)
    depth = r.depth[0, 0]
    correct = (depth > 0) & ((depth - gt).abs() <= 0.5) & (gt > 0)
    colour = np.zeros_like(img)
    colour[correct.numpy()] = [0.1, 0.85, 0.1]  # correct voxel depth
    colour[((gt > 0) & ~correct).numpy()] = [0.95, 0.1, 0.1]  # no voxel, or a voxel > 0.5 m off
    has_gt = (gt > 0).numpy()[..., None]
    over = np.where(has_gt, 0.45 * img + 0.55 * colour, img)
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.0))
    outline = np.zeros((*gt.shape, 4))
    outline[sign.numpy()] = [1.0, 1.0, 0.0, 0.6]
    outline[upper.numpy()] = [0.0, 0.8, 1.0, 0.5]
    ax[0].imshow(img)
    ax[0].imshow(outline)
    ax[0].set_title("sign (yellow), upper facades z > 5 m (cyan)", fontsize=10)
    ax[1].imshow(over)
    ax[1].set_title("voxel depth within 0.5 m of GT (green) / not (red)", fontsize=10)
    ax[2].imshow(np.ma.masked_equal(depth.numpy(), 0), cmap="turbo", vmin=0, vmax=60)
    ax[2].set_title("voxel depth: no voxel on the sign board or upper facades", fontsize=10)
    for a in ax:
        a.axis("off")
    fig.tight_layout()
    fig.savefig(out, dpi=80)
    plt.close(fig)


def sign_view(scene, views) -> int:
    """The view with the most sign pixels."""
    sign_ids = torch.tensor(scene.instance_ids("sign"))
    counts = [int(torch.isin(scene.load_instances([v])[0], sign_ids).sum()) for v in views]
    return views[int(np.argmax(counts))]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scene", type=Path, default=STREET_A)
    p.add_argument("--views", default="all", help="comma-separated view ids, or 'all'")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--no-embree", action="store_true")
    p.add_argument("--no-figures", action="store_true")
    p.add_argument("--figures-only", action="store_true")
    p.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    args = p.parse_args()
    t0 = time.perf_counter()
    scene, grid, acc = street_grid(args.scene)
    print(f"{grid} built in {time.perf_counter() - t0:.1f} s from {acc.points.shape[0]} LiDAR points")
    views = list(range(scene.num_views)) if args.views == "all" else [int(v) for v in args.views.split(",")]
    if not args.figures_only:
        result = evaluate(scene, grid, acc, views, embree=not args.no_embree, threads=args.threads)
        print_tables(result)
        if args.json:
            args.json.write_text(json.dumps(result, indent=1))
    if not args.no_figures:
        view = sign_view(scene, scene.train_views)
        figure_panels(scene, grid, view, ROOT / "docs" / "img" / "geometry_zbuffer.png")
        figure_missing(scene, grid, view, ROOT / "docs" / "img" / "geometry_zbuffer_missing.png")
        print(f"figures of view {view} written to docs/img/geometry_zbuffer*.png")


if __name__ == "__main__":
    main()
