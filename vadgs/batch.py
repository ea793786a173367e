"""Batch reconstruction of many scenes on Ray, fault-tolerant through exact resume.

:func:`run_batch` runs one Ray task per scene; each task is a
:func:`vadgs.train.run.train_scene` (:func:`run_scene`) in its own run folder ``out_dir/<name>``,
with the batch's :class:`~vadgs.train.config.TrainConfig`. A task whose worker dies (killed, out of
memory, node lost) is retried by Ray (``BatchConfig.max_retries``) and continues from the run's
last checkpoint (``train_scene(..., resume=True)``), which is exact: the retried run ends with the
same parameters and metrics as an uninterrupted one. A run whose ``metrics.json`` says
``"completed": true`` is skipped, so re-submitting a batch only computes what is missing. A scene
that fails with an error (a bad folder, a corrupt checkpoint, NaNs) is not retried: its error goes
into the summary and the other scenes go on.

The summary (``out_dir/summary.json`` and ``out_dir/summary.md``: scene, PSNR, PSNR*, SSIM, depth
AbsRel against dense ground truth and against the test frames' LiDAR, Gaussians, training seconds,
retries) is rewritten atomically each time a run ends.

Run folders are named after the scene folder (``.../segment-123/`` → ``segment-123``); scenes that
share a folder name get ``<name>-<8 hex digits of the SHA-1 of the scene's absolute path>``, and a
folder already owned by another scene (``batch.json``) is never reused, so the mapping is stable
across re-submissions. ``docs/scale.md`` explains how to run this on a cluster.

Ray is an optional dependency (``pip install vadgs[ray]``); only :func:`run_batch` needs it.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import socket
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import torch

from vadgs.checks import (
    Checked,
    bool_field,
    checked,
    choice_field,
    float_field,
    instance_field,
    int_field,
    nested,
)
from vadgs.io import atomic_write
from vadgs.runfolder import check_output_folder, record_files
from vadgs.train.config import TrainConfig

__all__ = [
    "BatchConfig",
    "BatchSummary",
    "RunInterrupted",
    "SceneResult",
    "check_batch_folder",
    "run_batch",
    "run_names",
    "run_scene",
    "write_summary",
]

#: What a run folder holds for the batch: the scene it belongs to (written by the driver) and the
#: attempts of the current submission (written by each task as it starts).
SCENE_FILE = "batch.json"
TASK_FILE = "batch_task.json"
_INSTALL_HINT = "vadgs batch needs Ray: pip install 'vadgs[ray]' (or pip install ray)"


class RunInterrupted(RuntimeError):
    """A training run stopped by SIGINT / SIGTERM (checkpointed); Ray retries it (``--resume``)."""


@dataclass(frozen=True)
class BatchConfig(Checked):
    """How the scenes of a batch are scheduled and trained.

    Attributes:
        address: Ray cluster to connect to: ``"auto"``, ``"ray://head:10001"``, ``"host:6379"``;
            None starts a local Ray (or joins ``RAY_ADDRESS`` when set). Ignored when Ray is
            already initialised by the caller.
        cpus_per_scene: Ray CPUs reserved by each task (how many scenes share a node).
        gpus_per_scene: Ray GPUs reserved by each task (fractions allowed).
        threads: torch threads of each run (0 = ``cpus_per_scene``, at least 1).
        max_retries: Ray retries of a task whose worker or node died (system failures); each
            retry resumes from the checkpoint. Application errors are never retried.
        train: the :class:`~vadgs.train.config.TrainConfig` of every scene (None: the defaults);
            used when a run starts, a resumed run keeps its own.
        scene_kind: the kind of every scene (``"benchmark"``, ``"dgp"``, ``"colmap"``; None:
            found per folder, :func:`vadgs.train.scenes.scene_ref`).
        scene_options: the options of every scene's reference (``scale``, ``cameras``, ...).
        runtime_env: Ray runtime environment passed to ``ray.init`` when this call starts Ray.
        progress: print a line each time a run ends.
    """

    address: str | None = checked(None, instance_field(str, optional=True))
    cpus_per_scene: float = checked(1.0, float_field(0))
    gpus_per_scene: float = checked(0.0, float_field(0))
    threads: int = checked(0, int_field(0, note=" (0 = cpus_per_scene)"))
    max_retries: int = checked(3, int_field(0))
    train: TrainConfig | None = nested(TrainConfig, optional=True)
    scene_kind: str | None = checked(None, choice_field(("benchmark", "dgp", "colmap", None)))
    scene_options: dict[str, Any] = checked(rule=instance_field(dict), default_factory=dict, hash=False)
    runtime_env: dict[str, Any] | None = checked(None, instance_field(dict, optional=True), hash=False)
    progress: bool = checked(True, bool_field())

    @property
    def torch_threads(self) -> int:
        """Threads of each run: ``threads``, else ``cpus_per_scene`` (at least 1)."""
        return self.threads or max(1, int(self.cpus_per_scene))


@dataclass(frozen=True)
class SceneResult:
    """One scene of a batch (a row of the summary).

    Attributes:
        scene: the scene folder (absolute).
        name: the run folder's name.
        run: the run folder.
        status: ``"done"`` (trained now), ``"skipped"`` (finished before), ``"failed"``,
            ``"stopped"`` (``--max-minutes`` reached; re-submit to continue) or ``"pending"``.
        psnr, psnr_star, ssim, depth_absrel: test metrics from ``metrics.json`` (None when the run
            has none: not finished, or a scene without test views / depth).
        lidar_absrel: depth AbsRel against the test frames' own LiDAR sweeps (``depth["lidar"]``:
            real logs, which have no dense depth; None without LiDAR).
        num_gaussians: Gaussians at the end.
        train_s: training time in seconds (of the steps kept: the part a killed attempt did after
            its last checkpoint is not counted).
        retries: attempts of this submission after the first (Ray retries after a worker died);
            for a skipped run, those of the submission that finished it.
        error: one line, for a failed run.
    """

    scene: str
    name: str
    run: str
    status: str = "pending"
    psnr: float | None = None
    psnr_star: float | None = None
    ssim: float | None = None
    depth_absrel: float | None = None
    lidar_absrel: float | None = None
    num_gaussians: int | None = None
    train_s: float | None = None
    retries: int = 0
    error: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready fields."""
        return asdict(self)


@dataclass(frozen=True)
class BatchSummary:
    """The outcome of :func:`run_batch`.

    Attributes:
        out_dir: the batch folder.
        results: one :class:`SceneResult` per scene, in the order given.
        wall_s: wall-clock seconds of the batch.
    """

    out_dir: str
    results: tuple[SceneResult, ...]
    wall_s: float = 0.0

    @property
    def failed(self) -> tuple[SceneResult, ...]:
        """The scenes that failed."""
        return tuple(r for r in self.results if r.status == "failed")

    def counts(self) -> dict[str, int]:
        """How many scenes per status."""
        out: dict[str, int] = {}
        for r in self.results:
            out[r.status] = out.get(r.status, 0) + 1
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready content of ``summary.json``."""
        return {
            "out_dir": self.out_dir,
            "wall_s": round(self.wall_s, 1),
            "counts": self.counts(),
            "scenes": [r.to_dict() for r in self.results],
        }

    def to_markdown(self) -> str:
        """The summary as a markdown table (``summary.md``)."""

        def fmt(v: Any, spec: str = "") -> str:
            return "" if v is None else format(v, spec)

        lines = [
            "| scene | status | PSNR | PSNR* | SSIM | depth AbsRel | LiDAR AbsRel | Gaussians | train s "
            "| retries | error |",
            "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|",
        ]
        for r in self.results:
            error = (r.error or "").replace("|", "\\|")
            lines.append(
                f"| {r.name} | {r.status} | {fmt(r.psnr, '.2f')} | {fmt(r.psnr_star, '.2f')} "
                f"| {fmt(r.ssim, '.3f')} | {fmt(r.depth_absrel, '.3f')} | {fmt(r.lidar_absrel, '.3f')} "
                f"| {fmt(r.num_gaussians)} "
                f"| {fmt(r.train_s, '.1f')} | {r.retries} | {error} |"
            )
        counts = ", ".join(f"{n} {s}" for s, n in self.counts().items())
        return "\n".join([*lines, "", f"{len(self.results)} scenes: {counts}; {self.wall_s:.0f} s", ""])


# ---------------------------------------------------------------------------------------------------
# run folders


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError):
        return None
    return d if isinstance(d, dict) else None


def _slug(scene: Path) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", scene.name).strip("._") or "scene"


def _owner(run: Path) -> str | None:
    """The scene a run folder belongs to: its ``batch.json``, else its ``vadgs train`` config."""
    d = _read_json(run / SCENE_FILE)
    if d is not None:
        return d.get("scene")
    path = ((_read_json(run / "config.json") or {}).get("scene") or {}).get("path")
    return str(Path(path).resolve()) if path else None


def run_names(scenes: Sequence[str | Path], out_dir: str | Path) -> list[str]:
    """Run folder names of ``scenes`` under ``out_dir`` (unique; stable across re-submissions).

    A scene gets its folder's name, unless that name is shared by another scene of the list or
    the folder ``out_dir/<name>`` holds something else (another scene's run: its ``batch.json`` or
    the scene of its ``config.json``): then it gets
    ``<name>-<hash>``, the hash being the first 8 hex digits of the SHA-1 of its absolute path.
    A scene whose hashed folder exists keeps it.

    Args:
        scenes: scene folders.
        out_dir: the batch folder.

    Returns:
        One name per scene, in order.

    Raises:
        ValueError: if a scene is listed twice.

    Example:
        >>> run_names(["/data/a/scene", "/data/b/scene", "/data/c"], "/nonexistent")  # doctest: +ELLIPSIS
        ['scene-...', 'scene-...', 'c']
    """
    out_dir = Path(out_dir)
    paths = [str(Path(s).expanduser().resolve()) for s in scenes]
    seen: set[str] = set()
    for p in paths:
        if p in seen:
            raise ValueError(f"scenes: {p} is listed twice")
        seen.add(p)
    slugs = [_slug(Path(p)) for p in paths]
    names = []
    for p, slug in zip(paths, slugs):
        hashed = f"{slug}-{hashlib.sha1(p.encode()).hexdigest()[:8]}"
        owner = _owner(out_dir / slug)
        if (out_dir / hashed).is_dir():
            names.append(hashed)
        elif owner == p:
            names.append(slug)
        elif slugs.count(slug) > 1 or owner is not None or (out_dir / slug).exists():
            names.append(hashed)
        else:
            names.append(slug)
    return names


def _finished(run: Path) -> dict[str, Any] | None:
    """The run's ``metrics.json`` if the run completed, else None."""
    metrics = _read_json(run / "metrics.json")
    return metrics if metrics is not None and metrics.get("completed") is True else None


def _skipped(base: SceneResult, run: Path, metrics: dict[str, Any]) -> SceneResult:
    """A finished run, with the retries of the submission that finished it."""
    attempts = int((_read_json(run / TASK_FILE) or {}).get("attempts", 1))
    return _from_metrics(base, metrics, status="skipped", retries=max(attempts - 1, 0))


def _from_metrics(base: SceneResult, metrics: dict[str, Any], **changes: Any) -> SceneResult:
    test = metrics.get("test") or {}
    depth = (test.get("depth") or {}).get("all") or {}
    lidar = (test.get("depth") or {}).get("lidar") or {}
    return replace(
        base,
        psnr=test.get("psnr"),
        psnr_star=test.get("psnr_star"),
        ssim=test.get("ssim"),
        depth_absrel=depth.get("absrel"),
        lidar_absrel=lidar.get("absrel"),
        num_gaussians=metrics.get("num_gaussians"),
        train_s=metrics.get("train_s"),
        **changes,
    )


def _one_line(text: str) -> str:
    lines = [line.strip() for line in str(text).strip().splitlines() if line.strip()]
    return lines[-1][:500] if lines else ""


# ---------------------------------------------------------------------------------------------------
# one scene (the body of a Ray task; plain Python)


def run_scene(
    scene: str | Path,
    run_dir: str | Path,
    config: TrainConfig | None = None,
    threads: int = 1,
    submission: str = "",
    scene_kind: str | None = None,
    scene_options: dict[str, Any] | None = None,
) -> SceneResult:
    """Train one scene into ``run_dir`` (:func:`vadgs.train.run.train_scene`): start, resume, or skip.

    The run is skipped when ``run_dir/metrics.json`` says ``"completed": true``; it is resumed
    when ``run_dir/checkpoint.pt`` exists (the stored configuration wins over ``config``);
    otherwise it starts with ``config``. Each call records its attempt, the process id and the
    host in ``run_dir/batch_task.json`` (attempts are counted per ``submission``).

    Args:
        scene: the scene folder.
        run_dir: the run folder.
        config: the :class:`~vadgs.train.config.TrainConfig` of a new run (None: the defaults).
        threads: torch threads.
        submission: an id of the batch submission (attempts are counted per submission).
        scene_kind: the scene's kind (:func:`vadgs.train.scenes.scene_ref`; None: found).
        scene_options: the options of its reference (``scale``, ...).

    Returns:
        The :class:`SceneResult` (status ``done``, ``skipped``, ``stopped`` or ``failed``); errors
        of the run are reported in it, as one line, not raised.

    Raises:
        RunInterrupted: when SIGINT / SIGTERM stopped the run (after a checkpoint), so that Ray
            retries it.
    """
    from vadgs.train.checkpoint import CHECKPOINT_NAME
    from vadgs.train.run import train_scene
    from vadgs.train.scenes import scene_ref

    run = Path(run_dir)
    base = SceneResult(scene=str(scene), name=run.name, run=str(run))
    metrics = _finished(run)
    if metrics is not None:
        return _skipped(base, run, metrics)
    run.mkdir(parents=True, exist_ok=True)
    task = _read_json(run / TASK_FILE) or {}
    attempt = int(task.get("attempts", 0)) + 1 if task.get("submission") == submission else 1
    atomic_write(
        run / TASK_FILE,
        json.dumps(
            {
                "submission": submission,
                "attempts": attempt,
                "pid": os.getpid(),
                "host": socket.gethostname(),
                "started": time.time(),
            }
        ),
    )
    record_files(run, [run / TASK_FILE])
    base = replace(base, retries=attempt - 1)
    threads_before = torch.get_num_threads()
    torch.set_num_threads(max(1, int(threads)))
    try:
        if (run / CHECKPOINT_NAME).is_file():
            outcome = train_scene(None, None, run, resume=True, progress=False)
        else:
            options = dict(scene_options or {})
            if "scale" not in options:  # vadgs train's default: the scene's working resolution
                from vadgs.data.resolution import working_resolution

                kind = scene_ref(scene, scene_kind).kind
                options["scale"] = working_resolution(scene, kind, options.get("cameras")).scale
            ref = scene_ref(scene, scene_kind, **options)
            outcome = train_scene(ref, config, run, progress=False)
    except Exception as e:
        text = " ".join(str(e).split())
        return replace(base, status="failed", error=_one_line(f"{type(e).__name__}: {text}"))
    finally:
        torch.set_num_threads(threads_before)
    if outcome.reason == "interrupted":
        raise RunInterrupted(f"{run}: training interrupted by a signal (checkpointed)")
    metrics = _finished(run)
    if metrics is None:
        return replace(base, status="stopped", error="stopped before the last step; re-submit to continue")
    return _from_metrics(base, metrics, status="done")


# ---------------------------------------------------------------------------------------------------
# the batch (Ray driver)


def check_batch_folder(out_dir: str | Path, flag: str = "--out") -> Path:
    """Refuse a batch folder that is neither new, empty, nor a batch's (its manifest).

    Raises:
        ValueError: from :func:`vadgs.runfolder.check_output_folder`, naming ``flag``.
    """
    out = Path(out_dir)
    return check_output_folder(out, flag, "vadgs batch")


def write_summary(summary: BatchSummary, out_dir: str | Path | None = None) -> Path:
    """Write ``summary.json`` and ``summary.md`` atomically into ``out_dir`` (default its own).

    Returns:
        The path of ``summary.json``.
    """
    out = Path(out_dir if out_dir is not None else summary.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write(out / "summary.json", json.dumps(summary.to_dict(), indent=2))
    atomic_write(out / "summary.md", summary.to_markdown())
    record_files(out, [out / "summary.json", out / "summary.md"])
    return out / "summary.json"


def _progress_line(i: int, total: int, r: SceneResult) -> str:
    head = f"[{i}/{total}] {r.name}: {r.status}"
    if r.status == "failed":
        return f"{head}: {r.error}"
    parts = []
    if r.psnr is not None:
        parts.append(f"PSNR {r.psnr:.2f} dB")
    if r.num_gaussians is not None:
        parts.append(f"{r.num_gaussians} Gaussians")
    if r.train_s is not None:
        parts.append(f"{r.train_s:.0f} s")
    if r.retries:
        parts.append(f"{r.retries} retr{'y' if r.retries == 1 else 'ies'}")
    return f"{head} ({', '.join(parts)})" if parts else head


def run_batch(
    scenes: Sequence[str | Path], out_dir: str | Path, config: BatchConfig | None = None
) -> BatchSummary:
    """Reconstruct many scenes, one Ray task each (see the module docstring).

    Uses Ray as already initialised by the caller, else starts it (``config.address``,
    ``config.runtime_env``) and shuts it down at the end. Scenes and ``out_dir`` must be paths that
    every Ray node can read and write (a shared file system on a cluster).

    Args:
        scenes: scene folders (``vadgs train`` scenes; ``scene_kind="dgp"`` for DGP).
        out_dir: the batch folder: one run folder per scene, ``summary.json``, ``summary.md``.
        config: :class:`BatchConfig`.

    Returns:
        The :class:`BatchSummary` (also written to ``out_dir`` after each run ends).

    Raises:
        ImportError: if Ray is not installed.
        ValueError: if a scene is listed twice.

    Example:
        >>> summary = run_batch(  # doctest: +SKIP
        ...     ["data/seg-0001", "data/seg-0002"], "runs",
        ...     BatchConfig(
        ...         cpus_per_scene=4, train=TrainConfig(iterations=3000, vad=VisibilityDensifyConfig())
        ...     ),
        ... )
        >>> [(r.name, r.status, r.psnr, r.retries) for r in summary.results]  # doctest: +SKIP
        [('seg-0001', 'done', 27.1, 0), ('seg-0002', 'done', 26.4, 1)]
    """
    check_batch_folder(out_dir, "out_dir")
    try:
        import ray
    except ImportError as e:
        raise ImportError(_INSTALL_HINT) from e
    from ray.exceptions import RayError, RayTaskError

    config = config or BatchConfig()
    t0 = time.perf_counter()
    out = Path(out_dir).expanduser().resolve()
    out.mkdir(parents=True, exist_ok=True)
    paths = [str(Path(s).expanduser().resolve()) for s in scenes]
    names = run_names(paths, out)
    submission = f"{time.time():.6f}-{os.getpid()}"
    results: list[SceneResult] = []
    for p, name in zip(paths, names):
        run = out / name
        check_output_folder(run, "out_dir", "vadgs run")  # a folder of another tool's under the batch
        run.mkdir(exist_ok=True)
        if _owner(run) != p:
            atomic_write(run / SCENE_FILE, json.dumps({"scene": p}))
        record_files(run, [run / SCENE_FILE])
        base = SceneResult(scene=p, name=name, run=str(run))
        metrics = _finished(run)
        results.append(base if metrics is None else _skipped(base, run, metrics))

    def summary() -> BatchSummary:
        return BatchSummary(str(out), tuple(results), time.perf_counter() - t0)

    write_summary(summary())
    total, ended = len(results), 0
    for r in results:
        if r.status == "skipped":
            ended += 1
            if config.progress:
                print(_progress_line(ended, total, r), flush=True)
    todo = [i for i, r in enumerate(results) if r.status == "pending"]
    if not todo:
        return summary()

    started = False
    if not ray.is_initialized():
        local = config.address is None and not os.environ.get("RAY_ADDRESS")
        # a local Ray for this batch only: no dashboard (a process and a port fewer)
        extra: dict[str, Any] = {"include_dashboard": False} if local else {}
        ray.init(address=config.address, runtime_env=config.runtime_env, **extra)
        started = True
    try:
        task = ray.remote(run_scene).options(
            num_cpus=config.cpus_per_scene,
            num_gpus=config.gpus_per_scene,
            max_retries=config.max_retries,
            retry_exceptions=[RunInterrupted],
        )
        pending = {
            task.remote(
                results[i].scene,
                results[i].run,
                config.train,
                config.torch_threads,
                submission,
                config.scene_kind,
                config.scene_options,
            ): i
            for i in todo
        }
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                i = pending.pop(ref)
                try:
                    results[i] = ray.get(ref)
                except RayTaskError as e:  # RunInterrupted once the retries are spent
                    results[i] = replace(results[i], status="failed", error=_one_line(str(e)))
                except RayError as e:  # worker / node died max_retries + 1 times
                    results[i] = replace(
                        results[i],
                        status="failed",
                        retries=config.max_retries,
                        error=_one_line(f"{type(e).__name__}: {(str(e).strip().splitlines() or [''])[0]}"),
                    )
                ended += 1
                write_summary(summary())
                if config.progress:
                    print(_progress_line(ended, total, results[i]), flush=True)
    finally:
        if started:
            ray.shutdown()
    final = summary()
    write_summary(final)
    return final
