"""The training loop's driver: the steps of :meth:`~vadgs.train.trainer.Trainer.train` and around them.

:func:`run_loop` calls :meth:`~vadgs.train.trainer.Trainer.train_step` until ``iterations`` (or a
stop), with the progress bar, the run's ``log.jsonl`` (:class:`~vadgs.train.session.RunLog`), the
stop signals (:func:`~vadgs.train.session.stop_on_signals`), the divergence check, the callback,
the checkpoints on the way (:func:`checkpoint_due`) and at the end, and the failure path
(:func:`save_after_failure`); it returns a :class:`TrainResult`. The trainer holds the model and
the step; this module drives it through its public interface (:class:`LoopTrainer`: ``train_step``,
``snapshot`` / ``restore``, ``save_checkpoint``, ...) and owns what is the loop's: the progress
bar, the undo snapshot of the step in flight and the checkpoint cadence. It does not import
:mod:`vadgs.train.trainer`.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple, Protocol

from vadgs.io import write_json
from vadgs.process import peak_rss_mb
from vadgs.runfolder import record_files, recorded_files
from vadgs.train.checkpoint import CHECKPOINT_NAME, StepSnapshot, clear_run, remove_run_tmp
from vadgs.train.session import RunLog, stop_on_signals

__all__ = [
    "LoopTrainer",
    "TrainResult",
    "add_exception_note",
    "checkpoint_due",
    "run_loop",
    "save_after_failure",
]


class LoopTrainer(Protocol):
    """What :func:`run_loop` uses of a trainer (:class:`~vadgs.train.trainer.Trainer` has it all)."""

    config: Any
    out_dir: Path | None
    scene_ref: dict[str, Any]
    progress: bool
    log: Callable[[str], None] | None
    callback: Callable[[Any, int], None] | None
    clear_previous: bool
    step: int
    train_s: float
    state: dict[str, Any]
    model: Any
    strategy: Any
    sampler: Any

    def train_step(self) -> dict[str, float]:
        """One step; the loss terms as floats."""

    def check_divergence(self, res: dict[str, float]) -> None:
        """Raise when the model diverged."""

    def save_checkpoint(self, path: str | Path | None = None) -> Path:
        """Write the run's state (``out_dir`` by default)."""

    def request_stop(self) -> None:
        """Stop after the current step."""

    def snapshot(self) -> StepSnapshot:
        """What a step consumes before its update (sampler, generators)."""

    def restore(self, snapshot: StepSnapshot) -> None:
        """Put a :meth:`snapshot` back."""

    @property
    def stop_requested(self) -> bool:
        """True once :meth:`request_stop` was called."""

    @property
    def checkpoint_step(self) -> int | None:
        """The step of the last checkpoint in ``out_dir``."""

    @property
    def checkpoint_time(self) -> float | None:
        """``time.monotonic()`` of the last checkpoint in ``out_dir``."""

    @property
    def updating(self) -> bool:
        """True while a step's update is applied (a failure then is not undone)."""


class _Flight:
    """The loop's state of the step in flight: its undo snapshot, and whether it is checking divergence."""

    def __init__(self) -> None:
        self.undo: StepSnapshot | None = None
        self.checking = False


class TrainResult(NamedTuple):
    """What :meth:`~vadgs.train.trainer.Trainer.train` returns.

    Attributes:
        step: steps done in total.
        completed: True when ``iterations`` were reached, False when interrupted / out of time.
        reason: ``"done"``, ``"interrupted"`` or ``"time limit"``.
        train_s: training seconds, all sessions of the run together.
        peak_rss_mb: peak resident memory of the process (MiB).
        num_gaussians: final count.
    """

    step: int
    completed: bool
    reason: str
    train_s: float
    peak_rss_mb: float
    num_gaussians: int


_BAR_STEPS = 10  # the progress bar's loss and PSNR: the mean of this many last steps


def run_loop(trainer: LoopTrainer) -> TrainResult:
    """Train ``trainer`` to ``config.iterations`` from its current step (the body of its ``train``).

    Prepares the run folder (``config.json``; a previous run's files go with ``overwrite``, a
    killed run's ``.tmp`` files always), then steps (:meth:`~vadgs.train.trainer.Trainer.train_step`) under
    :class:`~vadgs.train.session.RunLog` and :func:`~vadgs.train.session.stop_on_signals`: the
    strategy's pending log lines, a record every ``log_every`` steps, the divergence check, the
    callback, the stop / time limit, the checkpoints on the way (:func:`checkpoint_due`), the
    failure path (:func:`save_after_failure`) and the final checkpoint. While the bar runs, the
    strategy's ``on_progress`` hook (the VAD-GS event's messages), when it has one, writes to it.
    """
    from tqdm import tqdm

    cfg = trainer.config
    if trainer.out_dir is not None:
        trainer.out_dir.mkdir(parents=True, exist_ok=True)
        if trainer.clear_previous:
            removed = clear_run(trainer.out_dir)
            trainer.clear_previous = False
            if trainer.log is not None:
                n, where = len(removed), trainer.out_dir
                trainer.log(f"overwrite: removed {n} files of the previous run from {where}")
        remove_run_tmp(trainer.out_dir)
        out = trainer.out_dir
        if trainer.step == 0 and "log.jsonl" in {p.name for p in recorded_files(out) if p.parent == out}:
            (out / "log.jsonl").unlink()  # a new run: the log of a run killed before any checkpoint
        write_json(out / "config.json", {"config": cfg.to_dict(), "scene": trainer.scene_ref})
        record_files(out, [out / "config.json", out / "log.jsonl"])
    started = time.monotonic()
    reason = "done"
    bar = tqdm(
        total=cfg.iterations,
        initial=trainer.step,
        disable=not trainer.progress,
        desc="train",
        dynamic_ncols=True,
        smoothing=0.05,  # the ETA: the rate of the recent steps, VAD-GS events averaged in
    )
    hook = getattr(trainer.strategy, "on_progress", False) is not False and trainer.progress
    if hook:
        saved_hook = trainer.strategy.on_progress
        trainer.strategy.on_progress = lambda message: bar.set_description_str(message, refresh=True)
    recent: list[tuple[float, float]] = []  # (loss, PSNR) of the last steps, shown on the bar
    flight = _Flight()
    try:
        with (
            RunLog(trainer.out_dir, keep_until=trainer.step) as log,
            stop_on_signals(trainer.request_stop, lambda: trainer.stop_requested),
        ):
            while trainer.step < cfg.iterations:
                t0 = time.perf_counter()
                flight.undo = trainer.snapshot()  # what a step failing before its update consumed
                res = trainer.train_step()
                flight.undo = None
                trainer.train_s += time.perf_counter() - t0
                events = trainer.state.pop("pending_log", None) or []
                for event in events:
                    log.write({"step": trainer.step, "event": event})
                    if "summary" in event:
                        if trainer.progress:
                            bar.write(f"step {trainer.step}: {event['summary']}")
                        elif trainer.log is not None:
                            trainer.log(f"step {trainer.step}: {event['summary']}")
                if events and trainer.progress:
                    bar.set_description_str("train", refresh=False)
                recent = [*recent[-(_BAR_STEPS - 1) :], (res["total"], res["psnr"])]
                if trainer.progress:  # the mean of the last steps: one view's PSNR is noisy
                    loss, psnr = (sum(x) / len(recent) for x in zip(*recent))
                    n = trainer.model.num_gaussians
                    bar.set_postfix(loss=f"{loss:.4f}", psnr=f"{psnr:.2f}", n=n, refresh=False)
                bar.update(1)
                if trainer.step % cfg.log_every == 0 or trainer.step == 1:
                    n = trainer.model.num_gaussians
                    log.write(
                        {
                            "step": trainer.step,
                            "n": n,
                            "train_s": round(trainer.train_s, 2),
                            "refine": trainer.state.get("last_refine", {}),
                            **{k: round(v, 6) for k, v in res.items()},
                        }
                    )
                flight.checking = True  # a diverged state is not saved
                trainer.check_divergence(res)
                flight.checking = False
                if trainer.callback is not None:
                    trainer.callback(trainer, trainer.step)
                if trainer.stop_requested:
                    reason = "interrupted"
                    break
                if cfg.max_minutes and trainer.train_s > cfg.max_minutes * 60:
                    reason = "time limit"
                    break
                if (
                    trainer.out_dir is not None
                    and trainer.step < cfg.iterations
                    and checkpoint_due(trainer, started)
                ):
                    trainer.save_checkpoint()
    except Exception as e:
        save_after_failure(trainer, e, flight.undo, flight.checking)
        raise
    finally:
        bar.close()
        if hook:
            trainer.strategy.on_progress = saved_hook
    if trainer.out_dir is not None:
        trainer.save_checkpoint()
    peak = peak_rss_mb()
    n = trainer.model.num_gaussians
    return TrainResult(trainer.step, trainer.step >= cfg.iterations, reason, trainer.train_s, peak, n)


def add_exception_note(e: BaseException, note: str) -> None:
    """``e.add_note(note)``; on Python 3.10 (no add_note) the same ``__notes__`` list, which the CLI reads."""
    if sys.version_info >= (3, 11):
        e.add_note(note)
    else:
        e.__notes__ = [*getattr(e, "__notes__", ()), note]  # type: ignore[attr-defined]  # 3.11+ in the stubs


def checkpoint_due(trainer: LoopTrainer, started: float) -> bool:
    """Every ``checkpoint_every`` steps, every ``checkpoint_minutes``, and after the first cycle.

    The minutes count from the last checkpoint written to ``out_dir``, or from ``started``
    (``time.monotonic()`` when the loop started) before one.
    """
    cfg = trainer.config
    last = max(started, trainer.checkpoint_time or started)
    return bool(
        (cfg.checkpoint_every and trainer.step % cfg.checkpoint_every == 0)
        or trainer.step == len(trainer.sampler)
        or (cfg.checkpoint_minutes and time.monotonic() - last > cfg.checkpoint_minutes * 60)
    )


def save_after_failure(
    trainer: LoopTrainer, e: Exception, undo: StepSnapshot | None = None, checking: bool = False
) -> None:
    """Checkpoint the last completed step when an exception stops the loop, and say so on ``e``.

    A step that failed before its optimizer update (``trainer.updating`` False) is undone with
    ``undo``, the snapshot taken before it (the sampler and generators are put back), so the saved
    state is exactly the previous step's; a failure during or after the update, in the divergence
    check (``checking``) or a non-finite value keeps the previous checkpoint. A failing write
    (disk full) keeps it too.
    """
    if trainer.out_dir is None:
        return
    path = trainer.out_dir / CHECKPOINT_NAME
    saved = False
    failed_write = isinstance(e, OSError) and e.filename == str(path)
    updating = trainer.updating or checking
    if not updating and not isinstance(e, FloatingPointError) and not failed_write:
        if undo is not None:
            trainer.restore(undo)
        if trainer.checkpoint_step != trainer.step:
            try:
                trainer.save_checkpoint()
                saved = True
            except OSError as se:
                add_exception_note(e, f"(saving the checkpoint failed too: {se})")
        else:
            saved = True
    if saved:
        note = f"checkpoint of step {trainer.step} in {path}"
    elif trainer.checkpoint_step is not None:
        note = f"last good checkpoint: step {trainer.checkpoint_step} in {path}"
    else:
        note = f"no checkpoint was written before step {trainer.step}"
        add_exception_note(e, note)
        return
    add_exception_note(e, f"{note}; continue with: vadgs train --out {trainer.out_dir} --resume")
