"""The GPU check: what a session with a CUDA device measures in one run, written to one JSON.

    python3 benchmarks/gpu_check.py --out "$OUT/gpu_check.json"        # on a CUDA device
    python benchmarks/gpu_check.py --cpu --out /tmp/gpu_check_cpu.json  # the CPU sections, reduced

(On the device, ``bash benchmarks/gpu_check.sh "$OUT"`` installs the wheels of
``benchmarks/gpu_wheels.sh`` first and runs this under a hard overall timeout (450 s); ``docs/benchmarks.md``,
"The GPU check".)

Sections, in the order they run, each a function returning a dict; each records ``status``
(``ok`` / ``failed`` / ``skipped``), ``seconds`` and, when not ok, ``reason``:

- ``environment``: torch / CUDA versions, the device and its memory, nvcc, CPU count. Then gsplat's
  CUDA extension starts compiling (JIT, as on first use) in a background subprocess.
- ``vad_ops``: one VAD-GS event on the bundled sample scene (torch renderer), its z-buffers, view
  selections, PatchMatch runs and ``reconstruct_instance`` calls (one per instance and reference
  view: crops, selection, PatchMatch, consistency, fusion) timed as they happen (synchronised),
  then the first call of each replayed (median after a warm-up): ms per operation, next to the
  paper's ~48 ms per operation (RTX 4090). The first PatchMatch call is replayed once more with
  ``PatchMatchConfig.compile=True`` (``ops.patchmatch.compiled``): the compile's seconds, ms per
  call and CUDA kernels per call (profiler) against the eager ones, and their agreement.
- ``segment_memory``: ``vadgs.data.synthetic.make_segment`` (when importable) generates a segment
  (timed), ~100 steps with VAD-GS train on it at its working resolution and one event runs: peak
  GPU memory (``torch.cuda.max_memory_allocated``) and the host's peak RSS. The raster backend is
  gsplat if its build has finished by then, else torch (recorded, with ``compiling_meanwhile``).
- ``gsplat_build``: the wait for the compile, up to its budget from its start (then killed): its
  seconds and log tail. The sections above ran while it compiled.
- ``cuda_tests``: ``pytest tests -k cuda`` (the ``device`` fixture's CUDA cases, the gsplat CUDA
  backend tests, ...; ``and not gsplat`` when the build failed) with a time cap: passed / failed /
  skipped counts, the failures' names.
- ``gsplat_vs_torch``: gsplat's CUDA rasterizer (``rasterize_gaussians_gsplat``) against vadgs's
  pure-torch renderer on a seeded random scene: max abs / relative errors of colour, depth,
  alpha and of the gradients w.r.t. means, quats, scales, opacities, colours; forward + backward
  time of both.
- ``train_step``: ms per ``Trainer.train_step`` on the bundled sample (240x144) with each available
  raster backend, then one VAD-GS event's seconds and its operations' median ms (as ``vad_ops``,
  but after the compile: ``vad_ops`` runs while gsplat compiles on most of the cores).
- ``simple_trainer``: gsplat v1.5.3's own ``examples/simple_trainer.py`` patched with vadgs's diff
  (``examples/gsplat_simple_trainer.diff``), ``default`` and ``vad``, on the COLMAP sample (24 images,
  120x72) with gsplat's CUDA rasterizer (``tests/train/gsplat_simple_trainer.py``, ``device="cuda"``:
  stand-ins only for what a machine without network lacks). Per run: seconds, ms per step, the
  Gaussians, the VAD-GS events (every row of params, moments and strategy state kept), the
  validation PSNR / SSIM. gsplat's examples and the sample as a text COLMAP model travel in
  ``.whl/data`` (``gpu_wheels.sh``; the device has no pycolmap). On the CPU: 3 steps of ``vad``
  with the CPU stand-ins and a bare machine's (no pycolmap, viser, ...), when ``../shared`` has
  gsplat's examples.

``--cpu`` runs them on the CPU at reduced sizes (``--tiny``: the smallest, for the test); the
sections that need CUDA report ``skipped: no CUDA device``. The JSON is rewritten after every
section, so a run cut short still leaves what finished. Each section stops at its budget
(``BUDGET_S``, SIGALRM; the tests and the compile are subprocesses with a timeout).
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import math
import os
import platform
import resource
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import traceback
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import torch

REPO = Path(__file__).resolve().parents[1]

# --- parameters ---------------------------------------------------------------------------------
PAPER_MS_PER_OP = 48.0  # the paper's time per operation on an RTX 4090
# seconds per section (capped further by what is left of --budget)
BUDGET_S = {
    "environment": 30,
    "vad_ops": 75,
    "segment_memory": 120,
    "gsplat_build": 240,  # from its start (in the background, after environment) to the end of the wait
    "cuda_tests": 90,
    "gsplat_vs_torch": 35,
    "train_step": 60,
    "simple_trainer": 90,
}
# sizes per mode: "cuda" (the device), "cpu" (--cpu), "tiny" (--cpu --tiny, the test)
SIZES: dict[str, dict[str, Any]] = {
    "cuda": dict(
        gs_gaussians=4000, gs_size=(192, 256), gs_reps=20,  # gsplat_vs_torch
        ops_scale=1.0, ops_steps=30, ops_reps=10, ops_max_instances=4, max_crop=None,  # vad_ops
        train_scale=1.0, train_steps=20, train_warmup=3, train_event=True,  # train_step
        train_cycle=True, st_steps=300, st_factor=1,  # steady state; simple_trainer at train_step's size
        seg=dict(frames=50, cameras=5, width=1920, height=1280), seg_steps=100,  # segment_memory
        seg_scale=None, seg_max_instances=None,  # None: the working resolution, every instance
    ),
    "cpu": dict(
        gs_gaussians=300, gs_size=(48, 64), gs_reps=2,
        ops_scale=0.5, ops_steps=6, ops_reps=3, ops_max_instances=2, max_crop=None,
        train_scale=0.5, train_steps=5, train_warmup=1, train_event=True,
        train_cycle=True, st_steps=3, st_factor=2,
        seg=dict(frames=4, cameras=2, width=128, height=96), seg_steps=10,
        seg_scale=None, seg_max_instances=2,
    ),
    "tiny": dict(
        gs_gaussians=60, gs_size=(24, 32), gs_reps=1,
        ops_scale=0.25, ops_steps=2, ops_reps=1, ops_max_instances=1, max_crop=32,
        train_scale=0.25, train_steps=2, train_warmup=1, train_event=False,
        train_cycle=False, st_steps=3, st_factor=2,
        seg=dict(frames=2, cameras=1, width=64, height=48), seg_steps=3,
        seg_scale=0.25, seg_max_instances=1,
    ),
}  # fmt: skip
CUDA_TESTS = ["tests"]  # pytest paths, selected with -k cuda
CUDA_TESTS_DRY = ["tests/render/test_splat.py"]  # without CUDA: the pytest machinery, on one file
GSPLAT_JOBS = 12  # MAX_JOBS of the gsplat compile (the device has 16 cores)


class SectionTimeout(Exception):
    """A section ran past its budget (raised by SIGALRM)."""


def _alarm(_signum, _frame):
    raise SectionTimeout


class Check:
    """The run: mode, sizes, deadline and the JSON, written after each section."""

    def __init__(self, out: Path, device: str, mode: str, budget: float):
        self.out, self.device, self.mode = out, device, mode
        self.sizes = dict(SIZES[mode])  # this run's (--seg-frames), the module's table untouched
        self.budgets = dict(BUDGET_S)  # this run's seconds per section (--section-budget)
        self.t0 = time.monotonic()
        self.deadline = self.t0 + budget
        self.cuda = device == "cuda"
        self.data: dict[str, Any] = {
            "mode": mode,
            "device": device,
            "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "budget_s": budget,
            "sections": {},
        }
        self.build: subprocess.Popen | None = None
        self.build_t0 = 0.0
        self.gsplat_cuda = False  # gsplat's CUDA extension compiled and loaded
        self.partial: dict[str, Any] = {}  # what the running section has so far (kept on a timeout)

    def write(self) -> None:
        self.data["elapsed_s"] = round(time.monotonic() - self.t0, 2)
        self.out.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.out.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.data, indent=1, default=str))
        tmp.replace(self.out)

    def left(self) -> float:
        return self.deadline - time.monotonic()

    def run(self, name: str, fn) -> dict[str, Any]:
        budget = min(self.budgets[name], self.left() - 5)
        t = time.monotonic()
        print(f"[gpu_check] {name} (budget {budget:.0f} s) ...", flush=True)
        if budget < 3:
            res = {"status": "skipped", "reason": f"no time left ({self.left():.0f} s of the overall budget)"}
        else:
            old = signal.signal(signal.SIGALRM, _alarm)
            signal.setitimer(signal.ITIMER_REAL, budget)
            self.partial = {}
            try:
                res = fn(self, budget)
                res.setdefault("status", "ok")
            except SectionTimeout:
                res = {
                    **self.partial,
                    "status": "failed",
                    "reason": f"timeout: ran past its budget of {budget:.0f} s",
                }
            except Exception as e:  # a failed section is recorded; the others run
                res = {
                    **self.partial,
                    "status": "failed",
                    "reason": f"{type(e).__name__}: {e}"[:2000],
                    "traceback": traceback.format_exc()[-4000:],
                }
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0)
                signal.signal(signal.SIGALRM, old)
        res["seconds"] = round(time.monotonic() - t, 3)
        self.data["sections"][name] = res
        self.write()
        print(
            f"[gpu_check] {name}: {res['status']} in {res['seconds']:.1f} s {res.get('reason', '')}",
            flush=True,
        )
        return res


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def _median_ms(fn, reps: int, device: str, warmup: int = 1) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(max(reps, 1)):
        _sync(device)
        t = time.perf_counter()
        fn()
        _sync(device)
        times.append(1e3 * (time.perf_counter() - t))
    return statistics.median(times)


def _no_cuda() -> dict[str, Any]:
    return {"status": "skipped", "reason": "no CUDA device"}


# --- a. environment -----------------------------------------------------------------------------
def environment(chk: Check, budget: float) -> dict[str, Any]:
    import numpy

    res: dict[str, Any] = {
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "torch": torch.__version__,
        "torch_cuda": torch.version.cuda,
        "numpy": numpy.__version__,
        "cuda_available": torch.cuda.is_available(),
        "torch_threads": torch.get_num_threads(),
    }
    for mod in ("gsplat", "kornia", "tyro", "pycolmap", "trimesh", "plyfile", "ninja"):
        try:
            res[mod] = getattr(__import__(mod), "__version__", "present")
        except Exception as e:
            res[mod] = f"missing ({type(e).__name__})"
    nvcc = shutil.which("nvcc") or (
        str(Path(os.environ.get("CUDA_HOME", "/usr/local/cuda")) / "bin" / "nvcc")
        if (Path(os.environ.get("CUDA_HOME", "/usr/local/cuda")) / "bin" / "nvcc").exists()
        else None
    )
    res["nvcc"] = nvcc
    if nvcc:
        out = subprocess.run([nvcc, "--version"], capture_output=True, text=True, timeout=20).stdout
        res["nvcc_version"] = out.strip().splitlines()[-1] if out.strip() else None
    if chk.cuda:
        p = torch.cuda.get_device_properties(0)
        res.update(
            device_name=p.name,
            device_memory_gib=round(p.total_memory / 2**30, 2),
            capability=f"{p.major}.{p.minor}",
            multiprocessors=p.multi_processor_count,
            cudnn=torch.backends.cudnn.version(),
        )
    return res


# --- gsplat's CUDA extension: compiled in the background ---------------------------------------
_BUILD = (
    "import time; t = time.perf_counter()\n"
    "from gsplat.cuda._backend import _C\n"
    "assert _C is not None, 'gsplat.cuda._backend._C is None (the compile failed)'\n"
    "print('gsplat _C loaded in', round(time.perf_counter() - t, 1), 's')\n"
)


def start_gsplat_build(chk: Check) -> None:
    """Start compiling gsplat's CUDA extension (JIT) in its own process group, if there is CUDA."""
    if not chk.cuda:
        return
    os.environ.setdefault("TORCH_EXTENSIONS_DIR", "/tmp/torch_extensions")
    os.environ.setdefault("MAX_JOBS", str(GSPLAT_JOBS))
    if "TORCH_CUDA_ARCH_LIST" not in os.environ:
        major, minor = torch.cuda.get_device_capability(0)
        os.environ["TORCH_CUDA_ARCH_LIST"] = f"{major}.{minor}"  # the device's only: a shorter build
    log = open(Path(tempfile.gettempdir()) / "gsplat_build.log", "w")  # the child's output; closed at exit
    chk.build_t0 = time.monotonic()
    chk.build = subprocess.Popen(
        [sys.executable, "-c", _BUILD], stdout=log, stderr=subprocess.STDOUT, start_new_session=True
    )


def _gsplat_ready(chk: Check) -> bool:
    """Whether gsplat's CUDA extension can be used here: the background build exited 0 and ``_C``
    loads (from the build's cache) in this process. Never starts a compile in this process."""
    if not chk.gsplat_cuda and chk.build is not None and chk.build.poll() == 0:
        from gsplat.cuda._backend import _C

        chk.gsplat_cuda = _C is not None
    return chk.gsplat_cuda


def gsplat_build(chk: Check, budget: float) -> dict[str, Any]:
    if not chk.cuda:
        return _no_cuda()
    if chk.build is None:
        return {"status": "failed", "reason": "the build was not started"}
    res = {
        "torch_extensions_dir": os.environ.get("TORCH_EXTENSIONS_DIR"),
        "max_jobs": os.environ.get("MAX_JOBS"),
        "arch_list": os.environ.get("TORCH_CUDA_ARCH_LIST"),
    }
    wait = max(chk.budgets["gsplat_build"] - (time.monotonic() - chk.build_t0), 1.0)
    wait = min(wait, budget - 2)
    try:
        rc = chk.build.wait(timeout=wait)
    except subprocess.TimeoutExpired:
        os.killpg(chk.build.pid, signal.SIGKILL)
        chk.build.wait()
        rc = None
    res["compile_s"] = round(time.monotonic() - chk.build_t0, 1)
    log = (Path(tempfile.gettempdir()) / "gsplat_build.log").read_text(errors="replace")
    res["log_tail"] = log[-3000:]
    if rc is None:
        limit = chk.budgets["gsplat_build"]
        res.update(status="failed", reason=f"compile not done within {limit} s (killed)")
        return res
    if rc != 0:
        res.update(status="failed", reason=f"compile exited {rc}")
        return res
    if not _gsplat_ready(chk):
        res.update(status="failed", reason="built, but _C is None in this process")
    return res


# --- b. the CUDA test cases ---------------------------------------------------------------------
def cuda_tests(chk: Check, budget: float) -> dict[str, Any]:
    paths = CUDA_TESTS if chk.cuda else CUDA_TESTS_DRY
    # without gsplat's extension its tests would start the compile again: left out (recorded)
    select = "cuda" if not chk.cuda or chk.gsplat_cuda else "cuda and not gsplat"
    with tempfile.TemporaryDirectory() as tmp:
        xml = Path(tmp) / "junit.xml"
        cmd = [
            sys.executable, "-m", "pytest", *paths, "-q", "-k", select, "--maxfail=10",
            "-p", "no:cacheprovider", "--continue-on-collection-errors", f"--junitxml={xml}",
            "-o", "addopts=",
        ]  # fmt: skip
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
        res: dict[str, Any] = {"command": " ".join(cmd[1:]), "selection": select}
        # on timeout: SIGINT first (pytest stops, still writes its junit XML and summary), then kill
        log = Path(tmp) / "pytest.log"
        with open(log, "w") as f:
            proc = subprocess.Popen(
                cmd, cwd=REPO, stdout=f, stderr=subprocess.STDOUT, env=env, start_new_session=True
            )
            try:
                res["returncode"] = proc.wait(timeout=budget - 15)
            except subprocess.TimeoutExpired:
                res["timed_out"] = True
                os.killpg(proc.pid, signal.SIGINT)
                try:
                    proc.wait(timeout=8)
                except subprocess.TimeoutExpired:
                    os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait()
                res["returncode"] = proc.returncode
        res["tail"] = log.read_text(errors="replace")[-3000:]
        counts = dict(passed=0, failed=0, errors=0, skipped=0)
        failures: list[str] = []
        skip_reasons: dict[str, int] = {}
        if xml.exists():
            for case in ET.parse(xml).getroot().iter("testcase"):
                name = f"{case.get('classname')}::{case.get('name')}"
                if case.find("failure") is not None:
                    counts["failed"] += 1
                    failures.append(name)
                elif case.find("error") is not None:
                    counts["errors"] += 1
                    failures.append(name)
                elif (s := case.find("skipped")) is not None:
                    counts["skipped"] += 1
                    why = (s.get("message") or "")[:120]
                    skip_reasons[why] = skip_reasons.get(why, 0) + 1
                else:
                    counts["passed"] += 1
        res.update(counts=counts, failures=failures, skip_reasons=skip_reasons)
    if not chk.cuda:
        return {"status": "skipped", "reason": "no CUDA device", "dry_run": res}
    if res.get("timed_out"):
        res.update(status="failed", reason=f"pytest stopped at the section's budget; {counts} so far")
    elif counts["failed"] or counts["errors"] or res["returncode"] not in (0, 5):
        res.update(status="failed", reason=f"{counts['failed']} failed, {counts['errors']} errors")
    return res


# --- c. gsplat's CUDA rasterizer against vadgs's pure-torch renderer ---------------------------
def random_scene(n: int, size: tuple[int, int], device: str, seed: int = 0):
    """Seeded Gaussians along a street (x forward, z up), two cameras at ``size`` (60° fov)."""
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g) * torch.tensor([30.0, 12.0, 4.0]) + torch.tensor([3.0, -6.0, -1.5])
    quats = torch.randn(n, 4, generator=g)
    scales = torch.exp(torch.rand(n, 3, generator=g) * 3.0 - 4.0)
    opacities = torch.rand(n, generator=g) * 0.95 + 0.02
    colors = torch.rand(n, 3, generator=g)
    h, w = size
    f = 0.5 * w / math.tan(math.radians(30.0))
    K = torch.tensor([[f, 0, 0.5 * (w - 1) + 3.2], [0, f, 0.5 * (h - 1) - 2.1], [0, 0, 1]])

    def look_at(eye, target):
        eye, target = torch.tensor(eye), torch.tensor(target)
        z = torch.nn.functional.normalize(target - eye, dim=0)
        x = torch.nn.functional.normalize(torch.linalg.cross(z, torch.tensor([0.0, 0, 1])), dim=0)
        rot = torch.stack([x, torch.linalg.cross(z, x), z])
        w2c = torch.eye(4)
        w2c[:3, :3], w2c[:3, 3] = rot, -rot @ eye
        return w2c

    w2c = torch.stack([look_at([0.0, 0, 0.5], [10.0, 0, 0]), look_at([0.0, 0.5, 0.5], [8.0, 5, 0])])
    ts = (means, quats, scales, opacities, colors, w2c, K.expand(2, 3, 3).clone())
    return tuple(t.to(device) for t in ts), (h, w)


def _render_and_grads(fn, scene, size, target):
    from vadgs.render import RasterConfig

    leaves = [t.clone().requires_grad_(True) for t in scene[:5]]
    out = fn(*leaves, *scene[5:], size, config=RasterConfig())
    loss = (out.color - target).square().sum() + 0.1 * out.depth.sum() + out.alpha.sum()
    loss.backward()
    images = {k: getattr(out, k).detach() for k in ("color", "depth", "alpha")}
    return images, dict(zip(("means", "quats", "scales", "opacities", "colors"), (t.grad for t in leaves)))


def gsplat_vs_torch(chk: Check, budget: float) -> dict[str, Any]:
    if not chk.cuda:  # the same comparison with gsplat's pure-torch reference, for the record
        return {**_no_cuda(), "cpu_reference": compare_renderers(chk.sizes, "cpu", "torch")}
    if not chk.gsplat_cuda:
        return {"status": "skipped", "reason": "gsplat's CUDA extension is not available (gsplat_build)"}
    return compare_renderers(chk.sizes, "cuda", "cuda")


def compare_renderers(sizes: dict[str, Any], device: str, impl: str) -> dict[str, Any]:
    """vadgs's renderer against ``rasterize_gaussians_gsplat(..., impl=impl)`` on ``device``
    (``impl="torch"``: gsplat's pure-torch reference, which runs on the CPU: the test's way in)."""
    from vadgs.render import rasterize_gaussians
    from vadgs.render.gsplat_backend import rasterize_gaussians_gsplat

    scene, size = random_scene(sizes["gs_gaussians"], sizes["gs_size"], device)
    target = torch.rand(2, 3, *size, generator=torch.Generator().manual_seed(1)).to(device)
    impls = {
        "torch": rasterize_gaussians,
        "gsplat": lambda *a, **k: rasterize_gaussians_gsplat(*a, **k, impl=impl),
    }
    runs = {name: _render_and_grads(fn, scene, size, target) for name, fn in impls.items()}
    (ref_img, ref_grad), (img, grad) = runs["torch"], runs["gsplat"]

    def err(a, b):
        d = (a - b).abs().max().item()
        return {"max_abs": d, "max_rel": d / max(a.abs().max().item(), 1e-12)}

    res: dict[str, Any] = {
        "gsplat_impl": impl,
        "gaussians": sizes["gs_gaussians"],
        "cameras": 2,
        "image_size_hw": list(size),
        "covered_fraction": float((ref_img["alpha"] > 0.01).float().mean()),
        "images": {k: err(ref_img[k], img[k]) for k in ref_img},
        "gradients": {k: err(ref_grad[k], grad[k]) for k in ref_grad},
        "timing_note": "forward + backward of the loss (colour L2 + 0.1 depth + alpha), 2 views, median",
    }
    for name, fn in impls.items():
        res[f"{name}_ms"] = _median_ms(
            lambda fn=fn: _render_and_grads(fn, scene, size, target), sizes["gs_reps"], device
        )
    res["speedup"] = res["torch_ms"] / res["gsplat_ms"]
    return res


# --- d. the operations of a VAD-GS event --------------------------------------------------------
# (module, function name, label): wrapped while the event runs, at the name the caller looks up
_OPS = [
    ("vadgs.train.vad.visibility", "rasterize_voxels", "zbuffer"),
    ("vadgs.train.vad.reconstruct", "select_views", "selection"),
    ("vadgs.train.vad.matching", "patchmatch", "patchmatch"),
    # an event's (instance, reference) pairs: planned instance by instance, matched together, fused
    # one by one; "reconstruct" (one matched pair's share of the three) is derived from them
    # (_pair_shares)
    ("vadgs.train.vad.event", "plan_matches", "plan"),
    ("vadgs.train.vad.event", "match_plans", "match"),
    ("vadgs.train.vad.event", "finish_match", "finish"),
]
_DERIVED = ("reconstruct",)  # no call of its own: no replay


def _pair_shares(record: dict[str, dict[str, Any]]) -> None:
    """``record["reconstruct"]``: each matched pair's share of its event's plan, match and finish times."""
    pairs = len(record.get("finish", {}).get("calls_ms", []))
    total = sum(sum(record.get(k, {}).get("calls_ms", [])) for k in ("plan", "match", "finish"))
    record["reconstruct"] = {"calls_ms": [total / pairs] * pairs if pairs else [], "first": None}


@contextlib.contextmanager
def _timed_ops(device: str, record: dict[str, dict[str, Any]]):
    """Wrap the event's operations: each call synchronised and timed, the first call's arguments
    kept (for :func:`_replay`)."""
    import importlib

    saved = []
    for mod_name, fn_name, label in _OPS:
        mod = importlib.import_module(mod_name)
        fn = getattr(mod, fn_name)
        rec = record.setdefault(label, {"calls_ms": [], "first": None})

        def wrapped(*args, _fn=fn, _rec=rec, **kwargs):
            _sync(device)
            t = time.perf_counter()
            out = _fn(*args, **kwargs)
            _sync(device)
            _rec["calls_ms"].append(1e3 * (time.perf_counter() - t))
            if _rec["first"] is None:
                _rec["first"] = (_fn, args, kwargs)
            return out

        saved.append((mod, fn_name, fn))
        setattr(mod, fn_name, wrapped)
    try:
        yield record
    finally:
        for mod, fn_name, fn in saved:
            setattr(mod, fn_name, fn)
        _pair_shares(record)


def _vad_config(sizes: dict[str, Any], **changes):
    """VAD-GS settings of the check: no work budget, and ``max_crop`` where the sizes set it."""
    from vadgs.train.vad import ReconstructConfig, VisibilityDensifyConfig

    if sizes["max_crop"] is not None:
        changes["reconstruct"] = ReconstructConfig(max_crop=sizes["max_crop"])
    return VisibilityDensifyConfig(every_cycles=10**6, **changes)


def _vad_trainer(device: str, scale: float, backend: str, sizes: dict[str, Any]):
    from vadgs.data import load_scene, sample_scene_path
    from vadgs.render import RasterConfig
    from vadgs.train.config import TrainConfig
    from vadgs.train.trainer import Trainer

    scene = load_scene(sample_scene_path(), scale=scale)
    vad = _vad_config(sizes, work_budget=None, max_instances=sizes["ops_max_instances"])
    config = TrainConfig(
        iterations=10**6, checkpoint_every=0, device=device, raster=RasterConfig(backend=backend), vad=vad
    )
    return Trainer(scene, config, progress=False)


def _event(trainer) -> dict[str, Any]:
    _sync(trainer.config.device)
    return trainer.strategy.densify(trainer.model.params, trainer.optimizer, trainer.state, trainer.step)


def _cuda_kernels(fn) -> int | None:
    """CUDA kernels one call of ``fn`` launches (the profiler's count), ``None`` without CUDA."""
    if not torch.cuda.is_available():
        return None
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        fn()
        torch.cuda.synchronize()
    return sum(1 for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA)


def _patchmatch_compiled(fn, args, kwargs, reps: int, device: str) -> dict[str, Any]:
    """The event's first PatchMatch call, eager and with ``PatchMatchConfig.compile``: the compile
    (first call) time, ms per call, CUDA kernels per call, and how well the two agree."""
    import dataclasses

    try:
        cfg = args[7]
        fast = (*args[:7], dataclasses.replace(cfg, compile=True), *args[8:])
        eager_call = lambda: fn(*args, **kwargs)  # noqa: E731
        compiled_call = lambda: fn(*fast, **kwargs)  # noqa: E731
        _sync(device)
        t = time.perf_counter()
        got = compiled_call()
        _sync(device)
        first_s = time.perf_counter() - t
        ref = eager_call()
        rel = (got.raw_depth - ref.raw_depth).abs() / ref.raw_depth.clamp_min(1e-12)
        return {
            "first_call_s": first_s,  # the compile, once per process
            "median_ms": _median_ms(compiled_call, reps, device),
            "eager_median_ms": _median_ms(eager_call, reps, device),
            "kernels": _cuda_kernels(compiled_call),
            "eager_kernels": _cuda_kernels(eager_call),
            "depth_within_1e-4": float((rel <= 1e-4).float().mean()),
            "mask_agree": float((got.mask == ref.mask).float().mean()),
        }
    except Exception as exc:  # a failed compile is a figure too, not the end of the check
        return {"status": "failed", "reason": f"{type(exc).__name__}: {exc}"[:500]}


def vad_ops(chk: Check, budget: float) -> dict[str, Any]:
    s = chk.sizes
    trainer = _vad_trainer(chk.device, s["ops_scale"], "torch", s)
    for _ in range(s["ops_steps"]):
        trainer.train_step()
    record: dict[str, dict[str, Any]] = {}
    with _timed_ops(chk.device, record):
        event = _event(trainer)
    h, w = trainer.scene.cameras([0]).image_size
    res: dict[str, Any] = {
        "scene": f"bundled sample at scale {s['ops_scale']} ({w}x{h})",
        "training_views": len(trainer.train_views),
        "raster_backend": "torch",
        "steps_before_event": s["ops_steps"],
        "compiling_meanwhile": chk.build is not None and chk.build.poll() is None,
        "paper_ms_per_operation_rtx4090": PAPER_MS_PER_OP,
        "event": {
            k: event[k] for k in ("total_s", "detect_s", "mvs_s", "attempted", "added", "flagged_instances")
        },
        "ops": {},
    }
    for label, rec in record.items():
        calls = rec["calls_ms"]
        row: dict[str, Any] = {"calls": len(calls)}
        if calls:
            row.update(in_event_median_ms=statistics.median(calls), in_event_total_ms=sum(calls))
            if label not in _DERIVED:  # the replay: the first call again, median after a warm-up
                fn, args, kwargs = rec["first"]
                call = lambda fn=fn, args=args, kwargs=kwargs: fn(*args, **kwargs)  # noqa: E731
                row["replay_median_ms"] = _median_ms(call, s["ops_reps"], chk.device)
                if label == "patchmatch":  # beside it: the same call with the half-sweep compiled
                    row["compiled"] = _patchmatch_compiled(fn, args, kwargs, s["ops_reps"], chk.device)
            if label == "zbuffer":
                row["views_in_first_call"] = len(args[1]) if len(args) > 1 else None
                row["voxels_in_first_call"] = len(args[0]) if args and hasattr(args[0], "__len__") else None
        res["ops"][label] = row
    if not record.get("reconstruct", {}).get("calls_ms"):
        res.update(status="failed", reason="the event reconstructed no instance (nothing flagged)")
    return res


# --- e. one training step ------------------------------------------------------------------------
def train_step(chk: Check, budget: float) -> dict[str, Any]:
    s = chk.sizes
    backends = ["torch"] + (["gsplat"] if chk.gsplat_cuda else [])
    res = chk.partial
    res["backends"] = {}
    if chk.cuda and not chk.gsplat_cuda:
        res["note"] = "gsplat's CUDA extension not available: torch backend only"
    for backend in backends:
        trainer = _vad_trainer(chk.device, s["train_scale"], backend, s)
        h, w = trainer.scene.cameras([0]).image_size
        # steady state: after one full sampling cycle every view's caches are filled (a view's
        # first visit reads its image, LiDAR map and z-buffer from the host)
        warmup = s["train_warmup"] + (len(trainer.train_views) if s["train_cycle"] else 0)
        ms = _median_ms(trainer.train_step, s["train_steps"], chk.device, warmup=warmup)
        row = res["backends"][backend] = {
            "image_size_wh": [w, h],
            "gaussians": trainer.model.num_gaussians,
            "step_ms_median": ms,
            "steps": s["train_steps"],
            "warmup_steps": warmup,
        }
        if s["train_event"]:
            record: dict[str, dict[str, Any]] = {}
            t = time.perf_counter()
            with _timed_ops(chk.device, record):  # after the compile: no build beside it (vad_ops had one)
                event = _event(trainer)
            _sync(chk.device)
            row.update(
                event_s=time.perf_counter() - t,
                event_attempted=event["attempted"],
                event_added=event["added"],
                event_ops_median_ms={
                    label: statistics.median(r["calls_ms"]) for label, r in record.items() if r["calls_ms"]
                },
                event_ops_calls={label: len(r["calls_ms"]) for label, r in record.items()},
                paper_ms_per_operation_rtx4090=PAPER_MS_PER_OP,
            )
        del trainer
    return res


# --- f. the generated segment's peak memory ------------------------------------------------------
def _rss_peak_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux


def segment_memory(chk: Check, budget: float) -> dict[str, Any]:
    try:
        from vadgs.data.synthetic import make_segment
    except ImportError as e:
        return {"status": "skipped", "reason": f"vadgs.data.synthetic.make_segment not importable ({e})"}
    from vadgs.data import load_scene
    from vadgs.data.resolution import working_scale
    from vadgs.render import RasterConfig
    from vadgs.train.config import TrainConfig
    from vadgs.train.trainer import Trainer

    s = chk.sizes
    seg = s["seg"]
    res = chk.partial
    res["segment"] = seg
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "segment"
        t = time.perf_counter()
        make_segment(out, workers=min(16, os.cpu_count() or 1) if chk.cuda else 1, progress=False, **seg)
        res["generate_s"] = time.perf_counter() - t
        res["segment_mib"] = sum(f.stat().st_size for f in out.rglob("*") if f.is_file()) / 2**20
        scale = s["seg_scale"] or working_scale(max(seg["width"], seg["height"]))
        scene = load_scene(out, scale=scale)
        backend = "gsplat" if _gsplat_ready(chk) else "torch"
        vad = _vad_config(s, max_instances=s["seg_max_instances"])
        config = TrainConfig(
            iterations=10**6,
            checkpoint_every=0,
            device=chk.device,
            raster=RasterConfig(backend=backend),
            vad=vad,
        )
        if chk.cuda:
            torch.cuda.reset_peak_memory_stats()
        t = time.perf_counter()
        trainer = Trainer(scene, config, progress=False)
        res.update(scale=scale, raster_backend=backend, setup_s=time.perf_counter() - t)
        res["compiling_meanwhile"] = chk.build is not None and chk.build.poll() is None
        t = time.perf_counter()
        for _ in range(s["seg_steps"]):
            trainer.train_step()
        _sync(chk.device)
        res.update(
            steps=s["seg_steps"], steps_s=time.perf_counter() - t, gaussians=trainer.model.num_gaussians
        )
        if chk.cuda:
            res["peak_gpu_gib_training"] = torch.cuda.max_memory_allocated() / 2**30
        t = time.perf_counter()
        event = _event(trainer)
        _sync(chk.device)
        res.update(
            event_s=time.perf_counter() - t, event_attempted=event["attempted"], event_added=event["added"]
        )
        if chk.cuda:
            res["peak_gpu_gib"] = torch.cuda.max_memory_allocated() / 2**30
            res["peak_gpu_reserved_gib"] = torch.cuda.max_memory_reserved() / 2**30
        res["peak_host_rss_gib"] = _rss_peak_gib()
        del trainer, scene
    return res


# --- f. gsplat's own simple_trainer.py with vadgs's diff -----------------------------------------
def _simple_trainer_inputs(root: Path) -> Path | None:
    """Write the COLMAP sample (text model, its images) under ``root``; gsplat's examples, or None.

    From ``.whl/data`` (``gpu_wheels.sh``) where it is, else ``../shared`` and pycolmap.
    """
    from tests.train import gsplat_simple_trainer as st
    from vadgs.data import sample_scene_path

    data = REPO / ".whl" / "data"
    examples = data / "gsplat-v1.5.3" / "examples"
    examples = examples if examples.is_dir() else st.GSPLAT_EXAMPLES
    if not examples.is_dir():
        return None
    sparse = root / "sparse" / "0"
    if (data / "colmap_sample").is_dir():
        shutil.copytree(data / "colmap_sample" / "sparse" / "0", sparse)
    else:
        from tests.data.colmap_sample import write_sample_colmap

        write_sample_colmap(root, n_points=1500, link_images=False, text=True)
    shutil.copytree(sample_scene_path() / "images", root / "images")
    return examples


def _steady_step_ms(steps: list[list[float]], event_steps: list[int]) -> float | None:
    """Median ms between consecutive steps of the second half of a run, event steps left out.

    ``steps`` are the harness's ``[step, gaussians, seconds]`` records (the time at the end of
    each step; simple_trainer reads the loss every step, so a step's kernels are done by then).
    """
    timed = [r for r in steps if len(r) > 2]
    half = timed[len(timed) // 2 :]
    skip = set(event_steps)
    deltas = [1e3 * (b[2] - a[2]) for a, b in itertools.pairwise(half) if int(b[0]) not in skip]
    return statistics.median(deltas) if deltas else None


def simple_trainer(chk: Check, budget: float) -> dict[str, Any]:
    if str(REPO) not in sys.path:  # the harness is tests/train/gsplat_simple_trainer.py
        sys.path.insert(0, str(REPO))
    from tests.train import gsplat_simple_trainer as st

    if chk.cuda and not _gsplat_ready(chk):
        return {"status": "skipped", "reason": "gsplat's CUDA extension not available"}
    # on the CPU (the test): 3 steps of the vad run alone, with a bare machine's stand-ins
    steps, factor = chk.sizes["st_steps"], chk.sizes["st_factor"]
    every, names = (2, ("default", "vad")) if chk.cuda else (1, ("vad",))
    res = chk.partial
    res.update(steps=steps, every_cycles=every, data_factor=factor, runs={})
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "colmap"
        examples = _simple_trainer_inputs(root)
        if examples is None:
            return {"status": "skipped", "reason": "no gsplat examples (.whl/data or ../shared/third_party)"}
        st.prepare_data(root, factor)
        patched = st.prepare_examples(Path(tmp), src=examples)
        for name in names:
            extra = ["--vad.every-cycles", str(every)] if name == "vad" else []
            out = Path(tmp) / f"results_{name}"
            argv = [
                name, "--data_dir", str(root), "--data_factor", str(factor), "--result_dir", str(out),
                "--max_steps", str(steps), "--eval_steps", str(steps), "--save_steps", str(steps),
                "--disable_viewer", "--disable_video", *extra,
            ]  # fmt: skip
            record, timeout = Path(tmp) / f"{name}.json", max(budget - 10, 10)
            rec = st.run_trainer(patched, argv, record, timeout, device=chk.device, bare=not chk.cuda)
            val = json.loads((out / "stats" / f"val_step{steps - 1:04d}.json").read_text())
            events = rec["events"]
            rows_ok = all(
                set(e["rows"]["params"].values()) | set(e["rows"]["moments"].values()) == {e["n_after"]}
                for e in events
            )
            res["runs"][name] = {
                "wall_s": rec["wall_s"],
                "stand_ins": rec["config"].get("stand_ins"),
                "gaussians": rec["steps"][-1][1] if rec["steps"] else None,
                "events": [{k: e[k] for k in ("step", "attempted", "added", "total_s")} for e in events],
                "rows_consistent": rows_ok,
                "val": {k: val.get(k) for k in ("psnr", "ssim", "num_GS", "ellipse_time")},
                "step_ms_median": _steady_step_ms(rec["steps"], [e["step"] for e in events]),
            }
            if not rows_ok:
                res.update(status="failed", reason=f"{name}: rows of params / moments differ after an event")
    vad = res["runs"]["vad"]
    ours = chk.data["sections"].get("train_step", {}).get("backends", {}).get("gsplat", {})
    theirs = res["runs"].get("default", {}).get("step_ms_median")
    if ours.get("step_ms_median") and theirs:
        # the figure: vadgs's steady-state step (gsplat's rasterizer, VAD-GS attached, no event in
        # the timed steps) over simple_trainer's own at the same scene and size, in the same run
        res["vadgs_step_over_simple_trainer"] = ours["step_ms_median"] / theirs
        res["sizes_wh"] = {"vadgs": ours.get("image_size_wh"), "simple_trainer_factor": factor}
    if chk.cuda and not vad["events"]:
        res.update(status="failed", reason="the vad run held no VAD-GS event")
    return res


SECTIONS = list(BUDGET_S)  # the order they run in: the first three while gsplat compiles


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="the JSON written (after every section)")
    ap.add_argument("--cpu", action="store_true", help="device cpu, reduced sizes")
    ap.add_argument("--tiny", action="store_true", help="with --cpu: the smallest sizes (the test)")
    ap.add_argument("--budget", type=float, default=450.0, help="overall seconds (each section capped)")
    ap.add_argument("--only", nargs="+", choices=SECTIONS, help="run these sections only")
    ap.add_argument("--seg-frames", type=int, help="segment_memory: its frames")
    ap.add_argument("--section-budget", nargs="+", default=[], metavar="NAME=S", help="seconds per section")
    args = ap.parse_args(argv)
    budgets = {}
    for item in args.section_budget:
        name, _, seconds = item.partition("=")
        if name not in BUDGET_S:
            ap.error(f"--section-budget: expected NAME=S with NAME one of {SECTIONS}, got {item!r}")
        budgets[name] = float(seconds)
    if args.cpu:
        device, mode = "cpu", "tiny" if args.tiny else "cpu"
    elif torch.cuda.is_available():
        device, mode = "cuda", "cuda"
    else:
        print("[gpu_check] no CUDA device: running the CPU mode (--cpu)", flush=True)
        device, mode = "cpu", "cpu"
    chk = Check(args.out, device, mode, args.budget)
    chk.budgets.update(budgets)
    if args.seg_frames:
        chk.sizes["seg"] = {**chk.sizes["seg"], "frames": args.seg_frames}
    todo = args.only or SECTIONS
    for name in SECTIONS:
        if name not in todo:
            continue
        chk.run(name, globals()[name])
        if name == "environment" and "gsplat_build" in todo:
            start_gsplat_build(chk)
    if chk.build is not None and chk.build.poll() is None:
        os.killpg(chk.build.pid, signal.SIGKILL)
    chk.data["finished"] = True
    chk.write()
    return chk.data


if __name__ == "__main__":
    main()
