"""Initialise a :class:`~vadgs.train.model.GaussianModel` from LiDAR and / or SfM points.

Static points are the training frames' LiDAR without the moving objects (world frame) and the SfM
points (given, or the scene's own ``sfm_points``: a COLMAP scene); the points
of each moving object are moved into its object frame by instance id and pose
(:func:`vadgs.data.lidar.accumulate_lidar`). Each point takes the colour of the first training
image of its own frame that sees it (grey when none does). Points are averaged per voxel, capped
in number, and each Gaussian starts isotropic with the root-mean-square distance to its ``k``
nearest neighbours as scale (3DGS).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from vadgs.checks import Checked, bool_field, checked, float_field, int_field
from vadgs.data.cache import ByteCache
from vadgs.data.lidar import accumulate_lidar
from vadgs.data.scene import ColmapPoints, Scene
from vadgs.geometry.camera import project_points
from vadgs.geometry.points import VoxelAccumulator, knn_scales, voxel_downsample
from vadgs.train.model import GaussianModel

__all__ = ["InitConfig", "init_gaussians"]


@dataclass(frozen=True)
class InitConfig(Checked):
    """Settings of :func:`init_gaussians`.

    Attributes:
        use_lidar: initialise from the scene's LiDAR when it has some.
        voxel_size: static points are averaged per voxel of this size (metres).
        object_voxel_size: the same for the points of moving objects (object frame).
        max_points: cap on static Gaussians after voxelisation (random subset, seeded).
        max_object_points: cap per moving object.
        knn: neighbours for the initial scale.
        min_scale / max_scale: clamp of the initial scale (metres).
        init_opacity: initial opacity.
        sh_degree: SH degree of the Gaussians (0–3).
        sky_degree: SH degree of the sky model (0 = one background colour).
        seed: for the random subsets.
    """

    use_lidar: bool = checked(True, bool_field())
    voxel_size: float = checked(0.1, float_field(0, note=" (0 keeps every point)"))
    object_voxel_size: float = checked(0.05, float_field(0, note=" (0 keeps every point)"))
    max_points: int = checked(150_000, int_field(1))
    max_object_points: int = checked(20_000, int_field(0))
    knn: int = checked(3, int_field(1))
    min_scale: float = checked(0.005, float_field(0, lo_open=True))
    max_scale: float = checked(1.0, float_field(0, lo_open=True))
    init_opacity: float = checked(0.1, float_field(0, 1, lo_open=True, hi_open=True))
    sh_degree: int = checked(3, int_field(0, 3))
    sky_degree: int = checked(2, int_field(0, 3))
    seed: int = checked(0, int_field(0))

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.min_scale <= self.max_scale:
            raise ValueError(
                f"min_scale, max_scale: expected min_scale <= max_scale, got {self.min_scale}, "
                f"{self.max_scale}"
            )


_IMAGE_CACHE_BYTES = 512 * 2**20  # init_gaussians' image cache (float32 images read for colours)


def _point_colors(
    scene: Scene,
    world_points: torch.Tensor,
    point_idx: torch.Tensor,
    view_idx: torch.Tensor,
    allowed_views: set[int],
    cache: ByteCache,
) -> torch.Tensor:
    """Colour of each point from the first allowed view that sees it (grey otherwise)."""
    n = world_points.shape[0]
    colors = torch.full((n, 3), 0.5)
    if n == 0 or point_idx.numel() == 0:
        return colors
    ok = torch.tensor([int(v) in allowed_views for v in view_idx.tolist()], dtype=torch.bool)
    pi, vi = point_idx[ok], view_idx[ok]
    if pi.numel() == 0:
        return colors
    # first pair of each point (pairs are sorted by point)
    first = torch.ones_like(pi, dtype=torch.bool)
    first[1:] = pi[1:] != pi[:-1]
    pi, vi = pi[first], vi[first]
    for v in vi.unique().tolist():
        sel = pi[vi == v]

        def load(view: int = v) -> torch.Tensor:
            return scene.load_images([view])[0]

        img = cache.get(v, load)
        cams = scene.cameras([v])
        uv, _ = project_points(world_points[sel][None], cams.K, cams.world_to_cam)
        h, w = img.shape[-2:]
        grid = torch.stack([uv[0, :, 0] / (w - 1) * 2 - 1, uv[0, :, 1] / (h - 1) * 2 - 1], -1)
        col = F.grid_sample(
            img[None], grid[None, None], mode="bilinear", align_corners=True, padding_mode="border"
        )
        colors[sel] = col[0, :, 0].T
    return colors


def _subsample(
    points: torch.Tensor, colors: torch.Tensor, cap: int, gen: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    if points.shape[0] <= cap:
        return points, colors
    idx = torch.randperm(points.shape[0], generator=gen)[:cap].sort().values
    return points[idx], colors[idx]


def init_gaussians(
    scene: Scene, config: InitConfig | None = None, colmap_points: ColmapPoints | None = None
) -> GaussianModel:
    """Build the initial model of a scene from its training frames' LiDAR and optional SfM points.

    Args:
        scene: the scene (its ``train_frames`` / ``train_views`` are used).
        config: :class:`InitConfig`.
        colmap_points: SfM points (world frame, with colours) added to the static node
            (default: ``scene.sfm_points``, the points of a COLMAP scene; all of them, as 3DGS does).

    Returns:
        A :class:`~vadgs.train.model.GaussianModel` with one node per track of the scene (a track
        without LiDAR points gets an empty node).

    Raises:
        ValueError: when there is nothing to initialise from (no LiDAR and no SfM points).

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> scene = load_scene(sample_scene_path(), scale=0.5)
        >>> model = init_gaussians(scene, InitConfig(voxel_size=0.5, max_points=2000, max_object_points=200))
        >>> model.num_gaussians <= 2000 + 200 * len(scene.tracks), len(model.track_ids) == len(scene.tracks)
        (True, True)
    """
    config = config or InitConfig()
    gen = torch.Generator().manual_seed(config.seed)
    train_frames = scene.train_frames or [f.index for f in scene.frames]
    train_views = set(scene.train_views or range(scene.num_views))
    # the views' images: a frame's points are coloured from its own views, so a few frames' worth
    # is all the static points use; the moving objects' points read their views again if dropped
    cache = ByteCache(_IMAGE_CACHE_BYTES)
    has_lidar = config.use_lidar and scene.lidar_loader is not None
    # the static points, frame by frame into their voxels: memory follows the voxels, not the sweeps
    static = VoxelAccumulator(config.voxel_size)
    any_static = False
    if has_lidar:
        for f in train_frames:
            acc = accumulate_lidar(scene, [f], exclude_dynamic=True)
            static.add(acc.points, _point_colors(scene, acc.points, *acc.point_views, train_views, cache))
        any_static = True
    if colmap_points is None:
        colmap_points = scene.sfm_points
    if colmap_points is not None and colmap_points.points.shape[0]:
        static.add(colmap_points.points.float(), colmap_points.colors.float().clamp(0, 1))
        any_static = True
    if not any_static:
        raise ValueError(
            f"scene {scene.name!r}: nothing to initialise from: no LiDAR"
            + (" (use_lidar=False)" if scene.lidar_loader is not None else "")
            + " and no SfM points (colmap_points / scene.sfm_points); give it points: a COLMAP model "
            "of the scene's images in its world frame (e.g. triangulated with its known poses, COLMAP's "
            "point_triangulator) as `vadgs train SCENE --colmap MODEL` (colmap_points= in Python), "
            "or convert the scene with its LiDAR (vadgs convert without --no-lidar)"
        )
    p, c = static.result()
    p, c = _subsample(p, c, config.max_points, gen)
    means, colors, nodes = [p], [c], [torch.full((p.shape[0],), -1, dtype=torch.long)]

    track_ids = sorted(scene.tracks)
    num_frames = len(scene.frames)
    o2w = (
        torch.stack([scene.tracks[t].object_to_world for t in track_ids])
        if track_ids
        else torch.zeros(0, num_frames, 4, 4)
    )
    valid = (
        torch.stack([scene.tracks[t].valid for t in track_ids])
        if track_ids
        else torch.zeros(0, num_frames, dtype=torch.bool)
    )
    for k, tid in enumerate(track_ids):
        if not has_lidar or config.max_object_points == 0:
            continue
        acc = accumulate_lidar(scene, train_frames, track_id=tid)
        if acc.points.shape[0] == 0:
            continue
        fpos = torch.tensor([scene.frame_position(int(f)) for f in acc.frame.tolist()], dtype=torch.long)
        pose = scene.tracks[tid].object_to_world[fpos]
        world = (pose[:, :3, :3] @ acc.points[:, :, None]).squeeze(-1) + pose[:, :3, 3]
        col = _point_colors(scene, world, *acc.point_views, train_views, cache)
        op, oc = voxel_downsample(acc.points, col, config.object_voxel_size)
        op, oc = _subsample(op, oc, config.max_object_points, gen)
        means.append(op)
        colors.append(oc)
        nodes.append(torch.full((op.shape[0],), k, dtype=torch.long))

    node_ids = torch.cat(nodes)
    means_t = torch.cat(means)
    scales = torch.empty(means_t.shape[0])
    for k in node_ids.unique().tolist():
        sel = node_ids == k
        scales[sel] = knn_scales(means_t[sel], config.knn)
    scales = scales.clamp(config.min_scale, config.max_scale)
    return GaussianModel(
        means_t,
        torch.cat(colors),
        scales.log()[:, None].expand(-1, 3).contiguous(),
        node_ids,
        o2w,
        valid,
        track_ids,
        sh_degree=config.sh_degree,
        sky_degree=config.sky_degree,
        init_opacity=config.init_opacity,
    )
