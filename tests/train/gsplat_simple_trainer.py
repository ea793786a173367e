"""Run gsplat v1.5.3's own ``examples/simple_trainer.py``, patched with vadgs's diff, on the CPU or a GPU.

On the CPU (``device="cpu"``, the tests) the GPU-only parts of gsplat's example get stand-ins here, in
the test harness (never in the diff):

- gsplat's CUDA ``rasterization`` → gsplat's own pure-torch path ``gsplat.rendering._rasterization``
  (``gsplat.cuda._torch_impl``: covariances, projection, SH, offsets), with torch stand-ins for the
  CUDA-only kernels it still calls: a vectorised ``isect_tiles`` (same 64-bit keys as gsplat's
  ``_isect_tiles``, which loops over Gaussians in Python), and ``_rasterize_to_pixels`` →
  vadgs's torch transcription of gsplat's forward kernel (``vadgs.render.gsplat_backend``; gsplat's
  calls the CUDA ``rasterize_to_indices_in_range``). ``packed``, ``absgrad``, ``sparse_grad`` and
  non-pinhole cameras are not supported by that path (an error says so);
- ``spherical_harmonics`` → ``gsplat.cuda._torch_impl._spherical_harmonics``;
- ``fused_ssim`` (CUDA) → kornia's SSIM (11-px Gaussian window, same ``padding``);
- ``nerfview`` (the viewer; the runs pass ``--disable_viewer``) → empty classes;
- torchmetrics' LPIPS (downloads weights) → a metric that returns NaN (reported as such);
- the forked ``pycolmap.SceneManager`` → :class:`SceneManager` over the official pycolmap 4.x;
- the ``cuda:{rank}`` device → ``cpu`` (``Runner.device``), ``torch.cuda`` timing calls → no-ops,
  ``gsplat.distributed.cli`` → one process.

On a CUDA device (``device="cuda"``, ``benchmarks/gpu_check.py``) gsplat's own CUDA rasterization,
SH and timing run; only what a machine without network lacks gets a stand-in: LPIPS (its weights
are a download), and each of ``fused_ssim``, ``nerfview``, ``viser`` (the viewer, off) and the forked
``pycolmap`` that is not installed — the last as :class:`TextSceneManager` when pycolmap itself is
missing, which reads a COLMAP model written as text. ``bare=True`` uses those stand-ins whether
the packages are installed or not (the CPU test of that path).

:func:`prepare_examples` copies gsplat's ``examples/`` to a folder and applies the diff;
:func:`run_trainer` runs the patched script in a subprocess through this module
(``python -m tests.train.gsplat_simple_trainer EXAMPLES RECORD -- ARGV...``), which records what
the strategy did into a JSON file: per step the number of Gaussians, per VAD-GS event its log,
and after each event the rows of every optimizer's moments and of every tensor of the strategy
state (they must all equal the number of Gaussians).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType

REPO = Path(__file__).resolve().parents[2]
#: ``../shared`` of the repository (``$VADGS_SHARED``, else next to it or to a worktree's parent)
SHARED = next(
    (p for p in (Path(os.environ.get("VADGS_SHARED", REPO.parent / "shared")), REPO.parents[1] / "shared")
     if p.is_dir()),
    REPO.parent / "shared",
)  # fmt: skip
GSPLAT_EXAMPLES = SHARED / "third_party" / "gsplat-v1.5.3" / "examples"
DIFF = REPO / "examples" / "gsplat_simple_trainer.diff"


def prepare_examples(dst: Path, diff: Path = DIFF, src: Path = GSPLAT_EXAMPLES) -> Path:
    """Copy gsplat's ``examples/`` (``src``) to ``dst/examples``, apply ``diff``; returns that folder."""
    out = dst / "examples"
    shutil.copytree(src, out)
    if shutil.which("git"):
        cmd = ["git", "apply", "--unsafe-paths", str(diff)]
    else:  # a machine without git (the GPU machine may lack it): GNU patch reads the same diff
        cmd = ["patch", "-p1", "--forward", "-i", str(diff)]
    subprocess.run(cmd, cwd=dst, check=True, capture_output=True)
    return out


def prepare_data(colmap_root: Path, factor: int) -> None:
    """gsplat's Parser reads ``images_{factor}`` for ``--data_factor`` > 1: write it (PNG, bicubic)."""
    import numpy as np
    from PIL import Image

    src, dst = colmap_root / "images", colmap_root / f"images_{factor}"
    if factor == 1 or dst.exists():
        return
    for path in sorted(p for p in src.rglob("*") if p.is_file()):
        out = dst / path.relative_to(src).with_suffix(".png")
        out.parent.mkdir(parents=True, exist_ok=True)
        with Image.open(path) as im:
            im = im.convert("RGB")
            size = (round(im.width / factor), round(im.height / factor))
            Image.fromarray(np.asarray(im.resize(size, Image.BICUBIC))).save(out)


def run_trainer(
    examples: Path,
    argv: list[str],
    record: Path,
    timeout: float = 1800,
    device: str = "cpu",
    bare: bool = False,
) -> dict:
    """Run the patched ``simple_trainer.py`` with ``argv`` in a subprocess; returns the record.

    ``device``: ``"cpu"`` (the stand-ins of the module docstring) or ``"cuda"`` (gsplat's own CUDA
    path); ``bare``: the stand-ins of a machine without the optional packages, installed or not.

    Raises:
        RuntimeError: the run failed (its last output lines in the message).
    """
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    env.setdefault("OMP_NUM_THREADS", "1")
    opts = ["--device", device] + (["--bare"] if bare else [])
    cmd = [
        sys.executable,
        "-m",
        "tests.train.gsplat_simple_trainer",
        str(examples),
        str(record),
        *opts,
        "--",
        *argv,
    ]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        tail = "\n".join((proc.stdout + proc.stderr).splitlines()[-40:])
        raise RuntimeError(f"simple_trainer.py {' '.join(argv)} failed:\n{tail}")
    out = json.loads(record.read_text())
    out["wall_s"] = time.perf_counter() - t0
    out["stdout"] = proc.stdout
    return out


# -- the stand-ins (installed in the subprocess) -----------------------------------------------------


class SceneManager:
    """The forked pycolmap's ``SceneManager`` (what gsplat's Parser reads) over the official pycolmap."""

    def __init__(self, colmap_dir: str) -> None:
        import pycolmap

        self._rec = pycolmap.Reconstruction(colmap_dir)

    def load_cameras(self) -> None:
        from types import SimpleNamespace

        self.cameras = {}
        for cid, cam in self._rec.cameras.items():
            names = [s.strip() for s in cam.params_info.split(",")]
            p = dict(zip(names, (float(x) for x in cam.params)))
            p.setdefault("fx", p.get("f"))
            p.setdefault("fy", p.get("f"))
            p.setdefault("k1", p.get("k", 0.0))
            self.cameras[cid] = SimpleNamespace(
                camera_type=int(cam.model.value), width=cam.width, height=cam.height, **p
            )

    def load_images(self) -> None:
        from types import SimpleNamespace

        import numpy as np

        self.images, self.name_to_image_id = {}, {}
        for iid in sorted(self._rec.images):
            im = self._rec.images[iid]
            cfw = im.cam_from_world
            m = np.asarray((cfw() if callable(cfw) else cfw).matrix(), dtype=np.float64)
            self.images[iid] = SimpleNamespace(
                R=lambda m=m: m[:, :3], tvec=m[:, 3].copy(), camera_id=im.camera_id, name=im.name
            )
            self.name_to_image_id[im.name] = iid

    def load_points3D(self) -> None:
        import numpy as np

        pids = sorted(self._rec.points3D)
        pts = [self._rec.points3D[p] for p in pids]
        self.points3D = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
        self.point3D_colors = np.array([p.color for p in pts], dtype=np.uint8).reshape(-1, 3)
        self.point3D_errors = np.array([p.error for p in pts], dtype=np.float64)
        self.point3D_id_to_point3D_idx = {p: i for i, p in enumerate(pids)}
        self.point3D_id_to_images = {
            p: np.array([(e.image_id, e.point2D_idx) for e in pt.track.elements]) for p, pt in zip(pids, pts)
        }


#: COLMAP camera models: id and parameter names (``cameras.txt``)
_COLMAP_MODELS = {
    "SIMPLE_PINHOLE": (0, "f cx cy"),
    "PINHOLE": (1, "fx fy cx cy"),
    "SIMPLE_RADIAL": (2, "f cx cy k"),
    "RADIAL": (3, "f cx cy k1 k2"),
    "OPENCV": (4, "fx fy cx cy k1 k2 p1 p2"),
    "OPENCV_FISHEYE": (5, "fx fy cx cy k1 k2 k3 k4"),
}


class TextSceneManager:
    """What :class:`SceneManager` gives, without pycolmap: a COLMAP model written as text (``*.txt``)."""

    def __init__(self, colmap_dir: str) -> None:
        self._dir = Path(colmap_dir)

    def _rows(self, name: str):
        with open(self._dir / name) as f:
            return [line.split() for line in f if line.strip() and not line.startswith("#")]

    def load_cameras(self) -> None:
        from types import SimpleNamespace

        self.cameras = {}
        for row in self._rows("cameras.txt"):
            cid, model, w, h = int(row[0]), row[1], int(row[2]), int(row[3])
            type_id, names = _COLMAP_MODELS[model]
            p = dict(zip(names.split(), (float(x) for x in row[4:])))
            p.setdefault("fx", p.get("f"))
            p.setdefault("fy", p.get("f"))
            p.setdefault("k1", p.get("k", 0.0))
            self.cameras[cid] = SimpleNamespace(camera_type=type_id, width=w, height=h, **p)

    def load_images(self) -> None:
        from types import SimpleNamespace

        import numpy as np

        self.images, self.name_to_image_id = {}, {}
        # an image is two lines (its pose, then its 2D points); the second may be empty
        with open(self._dir / "images.txt") as f:
            lines = [line.rstrip("\n") for line in f if not line.startswith("#")]
        for pose in lines[0::2]:
            if not pose.strip():
                continue
            row = pose.split()
            iid, (qw, qx, qy, qz), t = int(row[0]), map(float, row[1:5]), np.array(row[5:8], dtype=np.float64)
            r = np.array([
                [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)],
                [2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)],
                [2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)],
            ])  # fmt: skip
            self.images[iid] = SimpleNamespace(R=lambda r=r: r, tvec=t, camera_id=int(row[8]), name=row[9])
            self.name_to_image_id[row[9]] = iid

    def load_points3D(self) -> None:
        import numpy as np

        rows = sorted(self._rows("points3D.txt"), key=lambda r: int(r[0]))
        pids = [int(r[0]) for r in rows]
        self.points3D = np.array([r[1:4] for r in rows], dtype=np.float64).reshape(-1, 3)
        self.point3D_colors = np.array([r[4:7] for r in rows], dtype=np.uint8).reshape(-1, 3)
        self.point3D_errors = np.array([r[7] for r in rows], dtype=np.float64)
        self.point3D_id_to_point3D_idx = {p: i for i, p in enumerate(pids)}
        self.point3D_id_to_images = {
            p: np.array(r[8:], dtype=np.int64).reshape(-1, 2) for p, r in zip(pids, rows)
        }


def _isect_tiles(
    means2d, radii, depths, tile_size, tile_width, tile_height, sort=True, segmented=False,
    packed=False, n_images=None, image_ids=None, gaussian_ids=None,
):  # fmt: skip
    """gsplat's ``isect_tiles`` (unpacked), vectorised: keys ``image | tile | depth bits`` as gsplat's."""
    import math

    import torch

    if packed:
        raise NotImplementedError("the CPU stand-in of isect_tiles supports packed=False only")
    dims, n = means2d.shape[:-2], means2d.shape[-2]
    count = math.prod(dims)
    m = means2d.detach().reshape(count, n, 2) / tile_size
    r = radii.reshape(count, n, 2) / tile_size
    hi_clamp = torch.tensor([tile_width, tile_height], device=m.device)
    lo = torch.minimum(torch.floor(m - r).int().clamp_min(0), hi_clamp)
    hi = torch.minimum(torch.ceil(m + r).int().clamp_min(0), hi_clamp)
    per = (hi - lo).prod(-1) * (radii.reshape(count, n, 2) > 0).all(-1)
    flat = per.flatten().long()
    idx = torch.repeat_interleave(torch.arange(count * n, device=m.device), flat)
    offs = torch.arange(idx.numel(), device=m.device) - torch.repeat_interleave(flat.cumsum(0) - flat, flat)
    width = (hi - lo)[..., 0].flatten()[idx].long()
    x = lo[..., 0].flatten()[idx].long() + offs % width.clamp_min(1)
    y = lo[..., 1].flatten()[idx].long() + offs // width.clamp_min(1)
    tile = y * tile_width + x
    bits = depths.detach().float().reshape(-1).contiguous().view(torch.int32)[idx].long() & 0xFFFFFFFF
    tile_bits = (tile_width * tile_height).bit_length()
    isect_ids = ((((idx // n) << tile_bits) | tile) << 32) | bits
    flatten_ids = idx.int()
    if sort:
        isect_ids, order = torch.sort(isect_ids, stable=True)
        flatten_ids = flatten_ids[order]
    return per.reshape(*dims, n).int(), isect_ids, flatten_ids


def _spherical_harmonics(degrees_to_use, dirs, coeffs, masks=None):
    import torch
    from gsplat.cuda._torch_impl import _spherical_harmonics as sh

    out = sh(degrees_to_use, dirs, coeffs)
    return out if masks is None else torch.where(masks[..., None], out, torch.zeros_like(out))


def _rasterize_to_pixels(means2d, conics, colors, opacities, width, height, tile_size, offsets, flatten_ids,
                         backgrounds=None, batch_per_iter=100):  # fmt: skip
    from vadgs.render.gsplat_backend import rasterize_to_pixels_torch

    if means2d.dim() != 3:
        raise NotImplementedError("the CPU stand-in of _rasterize_to_pixels takes (C, N, ...) inputs")
    return rasterize_to_pixels_torch(
        means2d, conics, colors, opacities, width, height, tile_size, offsets, flatten_ids, backgrounds
    )


def _rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, packed=True,
                   absgrad=False, sparse_grad=False, distributed=False, camera_model="pinhole",
                   with_ut=False, with_eval3d=False, radius_clip=0.0, **kwargs):  # fmt: skip
    """gsplat's ``rasterization`` on the CPU: its pure-torch ``_rasterization`` (same asserts)."""
    from gsplat.rendering import _rasterization as torch_path

    unsupported = dict(packed=packed, absgrad=absgrad, sparse_grad=sparse_grad, distributed=distributed,
                       with_ut=with_ut, with_eval3d=with_eval3d, radius_clip=radius_clip)  # fmt: skip
    bad = {k: v for k, v in unsupported.items() if v} | (
        {"camera_model": camera_model} if camera_model != "pinhole" else {}
    )
    if bad:
        raise NotImplementedError(
            f"the CPU rasterization stand-in does not support {bad} (pass --packed False)"
        )
    return torch_path(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **kwargs)


def _module(name: str, **attrs) -> ModuleType:
    mod = ModuleType(name)
    mod.__dict__.update(attrs)
    sys.modules[name] = mod
    return mod


def _missing(name: str, bare: bool) -> bool:
    """Whether ``name`` gets a stand-in: ``bare``, or it cannot be imported here."""
    if bare:
        return True
    try:
        __import__(name)
    except ImportError:
        return True
    return False


def install_stand_ins(device: str = "cpu", bare: bool = False) -> None:
    """Put the stand-ins in place (see the module docstring); call before running the script."""
    import kornia
    import torch
    import torchmetrics.image.lpip

    global DEVICE
    DEVICE = device

    def fused_ssim(img1, img2, padding="same", train=True):
        return kornia.metrics.ssim(img1, img2, 11, padding=padding).mean()

    class _Stub:
        def __init__(self, *args, **kwargs) -> None:
            pass

    class _NoLPIPS(torch.nn.Module):
        """LPIPS without weights: NaN (gsplat's metric needs a download)."""

        def __init__(self, *args, **kwargs) -> None:
            super().__init__()

        def forward(self, a, b):
            return torch.tensor(float("nan"))

    cpu = device == "cpu"
    if cpu or _missing("fused_ssim", bare):
        _module("fused_ssim", fused_ssim=fused_ssim)
    if cpu or _missing("nerfview", bare):
        _module("nerfview", CameraState=_Stub, RenderTabState=_Stub, Viewer=_Stub, apply_float_colormap=None)
    if _missing("viser", bare):  # the viewer (off: --disable_viewer) and gsplat_viewer.py import it
        _module("viser", ViserServer=_Stub)
        _module("gsplat_viewer", GsplatViewer=_Stub, GsplatRenderTabState=_Stub)
    torchmetrics.image.lpip.LearnedPerceptualImagePatchSimilarity = _NoLPIPS
    if _missing("pycolmap", bare):
        _module("pycolmap", SceneManager=TextSceneManager)
    else:
        import pycolmap

        pycolmap.SceneManager = SceneManager
    stubs = [m for m in ("fused_ssim", "nerfview", "viser", "pycolmap") if sys.modules.get(m) is not None]
    RECORD["config"]["stand_ins"] = [m for m in stubs if getattr(sys.modules[m], "__file__", None) is None]
    import gsplat.distributed

    gsplat.distributed.cli = _one_process
    if not cpu:
        return
    import gsplat.cuda._torch_impl as torch_impl
    import gsplat.rendering

    gsplat.rendering.rasterization = _rasterization
    gsplat.rendering.isect_tiles = _isect_tiles
    gsplat.rendering.isect_offset_encode = torch_impl._isect_offset_encode
    gsplat.rendering.spherical_harmonics = _spherical_harmonics
    torch_impl._rasterize_to_pixels = _rasterize_to_pixels
    torch.cuda.synchronize = lambda *a, **k: None
    torch.cuda.max_memory_allocated = lambda *a, **k: 0


# -- the record ----------------------------------------------------------------------------------------

RECORD: dict = {"steps": [], "events": [], "config": {}}
DEVICE = "cpu"  # the Runner's device (install_stand_ins)


def _rows(params, optimizers, state) -> dict:
    """Rows of every parameter, optimizer moment and strategy-state tensor."""
    import torch

    out = {"params": {k: int(v.shape[0]) for k, v in params.items()}, "moments": {}, "state": {}}
    for name, opt in optimizers.items():
        for group in opt.param_groups:
            for p in group["params"]:
                for key, val in opt.state.get(p, {}).items():
                    if isinstance(val, torch.Tensor) and val.dim() > 0:
                        out["moments"][f"{name}.{key}"] = int(val.shape[0])
    for key, val in state.items():
        if isinstance(val, torch.Tensor) and val.dim() > 0:
            out["state"][key] = int(val.shape[0])
    return out


def _recording(cls) -> None:
    """Wrap ``cls.step_post_backward`` to record steps, events and rows into :data:`RECORD`."""
    import inspect

    orig = cls.step_post_backward
    sig = inspect.signature(orig)

    def step_post_backward(self, *args, **kwargs):
        a = sig.bind(self, *args, **kwargs).arguments
        params, optimizers, state, step = a["params"], a["optimizers"], a["state"], a["step"]
        before = len(state.get("vad_events", []))
        out = orig(self, *args, **kwargs)
        n = int(params["means"].shape[0])
        RECORD["steps"].append([int(step), n, time.perf_counter()])
        for ev in state.get("vad_events", [])[before:]:
            keep = ("step", "flagged", "tested", "flagged_instances", "candidates", "attempted", "repaired",
                    "skipped", "added", "views_rendered", "tests_reused", "total_s")  # fmt: skip
            entry = {k: ev[k] for k in keep}
            entry["instances"] = [
                {k: i[k] for k in ("instance", "class", "references", "points", "added", "reason")}
                for i in ev["instances"]
            ]
            entry["n_after"] = n
            entry["rows"] = _rows(params, optimizers, state)
            RECORD["events"].append(entry)
        return out

    cls.step_post_backward = step_post_backward


def _one_process(fn, args, verbose=False):
    """``gsplat.distributed.cli`` for one process; on the CPU, the Runner's device is the CPU."""
    runner_cls = fn.__globals__["Runner"]
    if DEVICE == "cpu":
        runner_cls.device = property(lambda self: "cpu", lambda self, value: None)
    if getattr(args, "vad", None) is not None:
        from vadgs.train.vad import VisibilityAwareDensification

        _recording(VisibilityAwareDensification)
        RECORD["config"]["vad"] = repr(args.vad)
        init = runner_cls.__init__

        def __init__(self, *a, **k):  # the strategy's scale as prepared, for the record
            init(self, *a, **k)
            index = self.vad.index
            RECORD["config"]["voxels"] = len(index.grid) if index is not None else 0
            RECORD["config"]["scene_scale"] = float(self.scene_scale)
            RECORD["config"]["lengths"] = {k: v for k, v in getattr(self.vad, "lengths", {}).items()}

        runner_cls.__init__ = __init__
    else:
        _recording(type(args.strategy))
    RECORD["config"]["strategy"] = type(args.strategy).__name__
    return fn(0, 0, 1, args)


def main() -> None:
    """``python -m tests.train.gsplat_simple_trainer EXAMPLES RECORD [--device D] [--bare] -- ARGV...``."""
    import argparse
    import runpy

    cut = sys.argv.index("--")
    ap = argparse.ArgumentParser()
    ap.add_argument("examples", type=Path)
    ap.add_argument("record", type=Path)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--bare", action="store_true")
    opts = ap.parse_args(sys.argv[1:cut])
    examples, record, argv = opts.examples, opts.record, sys.argv[cut + 1 :]
    install_stand_ins(opts.device, opts.bare)
    RECORD["config"]["device"] = opts.device
    sys.path.insert(0, str(examples))
    sys.argv = [str(examples / "simple_trainer.py"), *argv]
    try:
        runpy.run_path(str(examples / "simple_trainer.py"), run_name="__main__")
    finally:
        record.write_text(json.dumps(RECORD, default=str))


if __name__ == "__main__":
    main()
