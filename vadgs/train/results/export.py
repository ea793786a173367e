"""Export a trained model as standard 3DGS PLY files: per node with poses, or the whole world at a frame.

The PLY reader and writer are :mod:`vadgs.render.ply`'s (atomic writes, validated headers). The
layout is the one of the original 3DGS code (and gsplat, SuperSplat, ...): binary little
endian, one ``vertex`` element with ``x y z nx ny nz f_dc_0..2 f_rest_0..(3(K-1)-1) opacity
scale_0..2 rot_0..3``, raw values (opacity logits, log-scales, ``wxyz`` quaternions) and
``f_rest`` channel-major. ``static.ply`` is in world coordinates; ``object_<id>.ply`` in the
object's frame, placed per frame by ``poses.json`` (``object_to_world`` per frame index, only
where the track is valid).

**The world at one frame** (:func:`export_world`, ``vadgs export RUN --frame F``) is what a viewer
(SuperSplat, the INRIA SIBR viewer, gsplat's, nerfstudio's) opens as is: one PLY with the static
Gaussians and every track valid at ``F`` posed into the world, means ``R μ + t`` and quaternions
``q(R) ⊗ q``, and their SH coefficients *rotated into the world* (:func:`~vadgs.render.rotate_sh`), since a
viewer evaluates every Gaussian's SH at the world viewing direction while the model evaluates a car's
at the direction in the car's frame. Only the SH degrees the model renders with
(``active_sh_degree``) are written. Optionally the INRIA model layout
(``point_cloud/iteration_N/point_cloud.ply``, ``cameras.json``, ``cfg_args``).

**Axes.** The PLY is in vadgs's world: **z up** (a driving scene's ground frame; a COLMAP scene
normalised with its cameras' mean up on ``+z``), metres (or the normalised units). Many splat
viewers take a PLY's up to be ``-y``, the convention of 3DGS models trained on COLMAP
reconstructions (SuperSplat rotates such a file 180° about z to show it upright in its y-up world),
and y-up tools (three.js, Unity) ``+y``: ``up="-y"`` (``vadgs export --up -y``) or ``up="y"``
writes the world rotated so that its up lies on that axis (:data:`UP_AXES`: means, quaternions
and SH coefficients rotated exactly, a rotation about ``x``). ``sky.json``'s mapping stays in
vadgs's world (z up).

**The sky** is written beside it as an equirectangular environment map ``sky.png``
(:func:`sky_equirect`, 256×128 by default, 8-bit, the model's sky colour, linear values as the
model renders them) and ``sky.json`` (its SH coefficients and the mapping). Pixel ``(u, v)`` (column,
row, centres at ``+ 0.5``) of a ``W × H`` map looks along world azimuth ``φ = π - 2π (u + 0.5) / W``
(from the world ``+x`` axis towards ``+y``; the image's centre column looks along ``+x``, its left
edge along ``-x`` turning through ``+y``) and elevation ``θ = π/2 - π (v + 0.5) / H`` (top row: up,
``+z``), i.e. the direction ``(cos θ cos φ, cos θ sin φ, sin θ)`` (world z up).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, NamedTuple

import torch

from vadgs.data.scene import Scene
from vadgs.io import atomic_write
from vadgs.render import eval_sh, num_sh_bases, rotate_sh, save_ply
from vadgs.render.ply import write_raw_ply
from vadgs.train.model import GaussianModel

__all__ = [
    "UP_AXES",
    "WorldExport",
    "equirect_directions",
    "export_model",
    "export_world",
    "sky_equirect",
    "world_gaussians",
]


#: ``vadgs export --up``: the rotation from vadgs's world (z up) to a PLY whose up is that axis.
UP_AXES: dict[str, tuple[tuple[float, ...], ...]] = {
    "z": ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),  # as trained
    "y": ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, -1.0, 0.0)),  # -90° about x: z -> y
    "-y": ((1.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0)),  # 90° about x: z -> -y (3DGS, COLMAP)
}


def rotate_world(gaussians: dict[str, torch.Tensor], R: torch.Tensor) -> dict[str, torch.Tensor]:
    """:func:`world_gaussians`'s output rotated by ``(3, 3)`` ``R``: means, quaternions and SH.

    Means ``R μ``, quaternions ``q(R) ⊗ q``, SH :func:`~vadgs.render.rotate_sh` (a viewer looking
    along ``R d`` sees what the model shows along ``d``); scales and opacities as they are.

    Example:
        >>> g = {"means": torch.tensor([[0.0, 0, 1]]), "quats": torch.tensor([[1.0, 0, 0, 0]]),
        ...      "sh": torch.zeros(1, 1, 3)}
        >>> rotate_world(g, torch.tensor(UP_AXES["-y"]))["means"].tolist()
        [[0.0, -1.0, 0.0]]
    """
    from vadgs.geometry.rotation import quat_multiply, rotation_to_quat

    R = R.to(gaussians["means"])
    out = dict(gaussians)
    out["means"] = gaussians["means"] @ R.T
    out["quats"] = quat_multiply(rotation_to_quat(R).expand_as(gaussians["quats"]), gaussians["quats"])
    out["sh"] = rotate_sh(gaussians["sh"], R)
    return out


def export_model(
    model: GaussianModel, out_dir: str | Path, frame_indices: list[int] | None = None
) -> list[Path]:
    """Write ``static.ply``, ``object_<id>.ply`` per track node and ``poses.json``.

    Each file is written atomically (a temporary file, then :func:`os.replace`): an interrupted
    export leaves the previous file or none, never a truncated one.

    Args:
        model: the model.
        out_dir: output folder.
        frame_indices: the scene's frame index of each frame position (default ``0..F-1``).

    Returns:
        The written paths.
    """
    out_dir = Path(out_dir)
    paths = []
    p = {k: v.detach() for k, v in model.params.items()}
    static = model.node_ids < 0
    paths.append(write_raw_ply(out_dir / "static.ply", {k: v[static] for k, v in p.items()}))
    nf = model.object_to_world.shape[1]
    frame_indices = frame_indices if frame_indices is not None else list(range(nf))
    poses = {}
    for k, tid in enumerate(model.track_ids):
        sel = model.node_ids == k
        paths.append(write_raw_ply(out_dir / f"object_{tid}.ply", {kk: v[sel] for kk, v in p.items()}))
        poses[str(tid)] = {
            str(frame_indices[f]): model.object_to_world[k, f].tolist()
            for f in range(nf)
            if bool(model.track_valid[k, f])
        }
    text = json.dumps({"object_to_world": poses, "sh_degree": model.sh_degree}, indent=1)
    paths.append(atomic_write(out_dir / "poses.json", text))
    return paths


# ---------------------------------------------------------------------------------------------------
# the world at one frame


def equirect_directions(height: int, width: int) -> torch.Tensor:
    """``(H, W, 3)`` world directions of an equirectangular map (the mapping of the module docstring).

    Example:
        >>> d = equirect_directions(2, 4)
        >>> [round(v, 4) for v in d[0, 1].tolist()]  # top half, second column: azimuth 45°, elevation 45°
        [0.5, 0.5, 0.7071]
    """
    u = torch.arange(width, dtype=torch.float64) + 0.5
    v = torch.arange(height, dtype=torch.float64) + 0.5
    phi = math.pi - 2 * math.pi * u / width
    theta = math.pi / 2 - math.pi * v / height
    th, ph = torch.meshgrid(theta, phi, indexing="ij")
    return torch.stack([th.cos() * ph.cos(), th.cos() * ph.sin(), th.sin()], -1)


@torch.no_grad()
def sky_equirect(model: GaussianModel, height: int = 128, width: int = 256) -> torch.Tensor:
    """The model's sky as an equirectangular image ``(3, H, W)`` in ``[0, 1]`` (see the module docstring).

    Each pixel is :meth:`GaussianModel.sky_color`'s value for its direction.

    Example:
        >>> from vadgs.train.model import GaussianModel
        >>> m = GaussianModel(torch.zeros(1, 3), torch.zeros(1, 3), torch.zeros(1, 3), torch.full((1,), -1),
        ...                   torch.zeros(0, 1, 4, 4), torch.zeros(0, 1, dtype=torch.bool), [], sky_degree=1)
        >>> sky_equirect(m, 4, 8).shape, round(float(sky_equirect(m, 4, 8).mean()), 3)  # 0.7 grey at start
        (torch.Size([3, 4, 8]), 0.7)
    """
    dirs = equirect_directions(height, width).reshape(-1, 3).to(model.sky)
    coeffs = model.sky[None].expand(dirs.shape[0], -1, -1)
    col = eval_sh(coeffs, dirs, model.sky_degree).clamp(0.0, 1.0)
    return col.T.reshape(3, height, width)


class WorldExport(NamedTuple):
    """The files :func:`export_world` wrote (``None`` where not asked for).

    Attributes:
        ply: the world's 3DGS PLY.
        sky_png: the sky's equirectangular map; ``sky_json``: its SH and mapping.
        cameras_json, cfg_args: the INRIA layout's camera list and arguments.
        num_gaussians: Gaussians in the PLY.
    """

    ply: Path
    sky_png: Path
    sky_json: Path
    cameras_json: Path | None
    cfg_args: Path | None
    num_gaussians: int


@torch.no_grad()
def world_gaussians(model: GaussianModel, frame: int) -> dict[str, torch.Tensor]:
    """Activated Gaussians of a frame position in the world, SH rotated into the world.

    Returns:
        ``{"means", "quats", "scales", "opacities", "sh", "ids"}`` (``sh`` truncated to the active
        degree), the arguments of :func:`~vadgs.render.save_ply` plus the model rows.
    """
    g = model.gaussians_at(frame)
    k = num_sh_bases(model.active_sh_degree)
    sh = g.sh[:, :k].clone()
    nodes = model.node_ids[g.ids]
    for node in torch.unique(nodes[nodes >= 0]).tolist():
        sel = nodes == node
        R = model.object_to_world[node, frame, :3, :3]
        sh[sel] = rotate_sh(sh[sel], R)
    return {"means": g.means, "quats": g.quats, "scales": g.scales, "opacities": g.opacities, "sh": sh,
            "ids": g.ids}  # fmt: skip


@torch.no_grad()
def export_world(
    model: GaussianModel,
    scene: Scene,
    frame: int,
    out_dir: str | Path,
    inria: bool = False,
    iteration: int = 0,
    sky_size: tuple[int, int] = (128, 256),
    scene_ref: dict[str, Any] | None = None,
    up: str = "z",
) -> WorldExport:
    """Write the world at one frame as one standard 3DGS PLY, and the sky as an environment map.

    See the module docstring for what is written and the sky's mapping. Every file is written to a
    temporary name and renamed.

    Args:
        model: the trained model.
        scene: its scene (frame indices; the cameras of ``cameras.json``).
        frame: the scene's frame index (``scene.frames[i].index``).
        out_dir: output folder.
        inria: the INRIA layout: ``point_cloud/iteration_<iteration>/point_cloud.ply``,
            ``cameras.json`` (every recorded view of the scene, the rig's views of ``frame``
            first, in the PLY's frame: ``position`` = camera centre, ``rotation`` =
            camera-to-world rotation rows, OpenCV axes as in 3DGS) and ``cfg_args``, whose
            ``source_path`` is in the PLY's frame too: the scene's folder, or for a normalised
            COLMAP scene the model mapped by the run's similarity, written to ``out_dir/sparse/0``
            (``images`` then the absolute images folder); otherwise ``world_frame<frame>.ply``.
        iteration: the ``iteration_N`` of the INRIA layout (e.g. the checkpoint's step).
        sky_size: ``(H, W)`` of ``sky.png``.
        scene_ref: the run's scene reference (:func:`~vadgs.train.scenes.open_scene`): with
            ``inria``, a COLMAP reference's ``transform`` and ``images`` give the source model.
        up: the PLY's up axis (:data:`UP_AXES`): ``"z"`` (vadgs's world, as trained), ``"-y"``
            (the 3DGS / COLMAP convention most splat viewers expect) or ``"y"``; only ``"z"``
            with ``inria`` (its ``cameras.json`` and source model are in the world's frame).

    Returns:
        :class:`WorldExport`.

    Raises:
        KeyError: if the scene has no such frame.
        ValueError: for an ``up`` not in :data:`UP_AXES`, or not ``"z"`` with ``inria``.

    Example:
        >>> import tempfile
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> from vadgs.train.init import InitConfig, init_gaussians
        >>> scene = load_scene(sample_scene_path(), scale=0.25)
        >>> model = init_gaussians(scene, InitConfig(voxel_size=1.0, max_points=300, sh_degree=0))
        >>> out = export_world(model, scene, 18, tempfile.mkdtemp())
        >>> out.ply.name, out.num_gaussians == len(model.gaussians_at(scene.frame_position(18)).ids)
        ('world_frame018.ply', True)
    """
    from PIL import Image

    from vadgs.viz import image_to_uint8

    if up not in UP_AXES:
        raise ValueError(f"up: expected one of {', '.join(UP_AXES)}, got {up!r}")
    if inria and up != "z":
        raise ValueError(
            f"up: expected 'z' with inria (cameras.json and the source model are z up), got {up!r}"
        )
    out_dir = Path(out_dir)
    fpos = scene.frame_position(frame)
    w = world_gaussians(model, fpos)
    if up != "z":
        w = rotate_world(w, torch.tensor(UP_AXES[up], dtype=w["means"].dtype))
    ply = (
        out_dir / "point_cloud" / f"iteration_{int(iteration)}" / "point_cloud.ply"
        if inria
        else out_dir / f"world_frame{frame:03d}.ply"
    )
    save_ply(ply, w["means"], w["quats"], w["scales"], w["opacities"], w["sh"])
    sky = image_to_uint8(sky_equirect(model, *sky_size))
    sky_png = atomic_write(out_dir / "sky.png", lambda p: Image.fromarray(sky).save(p, format="PNG"))
    sky_meta = {
        "image": "sky.png",
        "projection": "equirectangular",
        "size_hw": list(sky_size),
        "mapping": "pixel (u, v) centre -> azimuth phi = pi - 2 pi (u + 0.5) / W from world +x towards +y, "
        "elevation theta = pi/2 - pi (v + 0.5) / H; direction (cos theta cos phi, cos theta sin phi, "
        "sin theta), world z up",
        "colour": "max(0, 0.5 + sum_k Y_k(d) c_k) clamped to 1, SH basis of vadgs.render.sh_basis",
        "sh_degree": model.sky_degree,
        "sh_coefficients": model.sky.detach().cpu().tolist(),
    }
    sky_json = atomic_write(out_dir / "sky.json", json.dumps(sky_meta, indent=1))
    cameras_json = cfg_args = None
    if inria:
        cams: list[dict[str, Any]] = []
        rig = list(scene.frames[fpos].view_ids)
        others = [vid for f in scene.frames for vid in f.view_ids if vid not in rig]
        for vid in rig + others:
            v = scene.views[vid]
            info = scene.cameras_info[v.camera]
            c2w = v.cam_to_world.double()
            cams.append(
                {
                    "id": len(cams),
                    "img_name": Path(v.image).stem if v.image is not None else f"{v.camera}_{v.frame:03d}",
                    "width": info.image_size[1],
                    "height": info.image_size[0],
                    "position": c2w[:3, 3].tolist(),
                    "rotation": c2w[:3, :3].tolist(),
                    "fy": float(info.K[1, 1]),
                    "fx": float(info.K[0, 0]),
                }
            )
        cameras_json = atomic_write(out_dir / "cameras.json", json.dumps(cams, indent=1))
        source, images = str(scene.root or ""), "images"
        ref = scene_ref or {}
        if ref.get("kind") == "colmap" and ref.get("transform") is not None:
            source, images = str(out_dir.resolve()), str(Path(ref["images"]).resolve())
            _normalised_colmap_model(ref["path"], ref["transform"], out_dir / "sparse" / "0")
        args = (
            f"Namespace(data_device='cuda', eval=True, images={images!r}, model_path={str(out_dir)!r}, "
            f"resolution=-1, sh_degree={model.active_sh_degree}, "
            f"source_path={source!r}, white_background=False)"
        )
        cfg_args = atomic_write(out_dir / "cfg_args", args)
    return WorldExport(ply, sky_png, sky_json, cameras_json, cfg_args, int(w["means"].shape[0]))


def _normalised_colmap_model(model: str | Path, transform: list, out: Path) -> Path:
    """The COLMAP model mapped by a run's normalising similarity (pycolmap), written to ``out``."""
    import numpy as np
    import pycolmap

    rec = pycolmap.Reconstruction(str(model))
    T = np.asarray(transform, dtype=np.float64)
    rec.transform(pycolmap.Sim3d(T[:3, :4]))
    out.mkdir(parents=True, exist_ok=True)
    rec.write(str(out))
    return out
