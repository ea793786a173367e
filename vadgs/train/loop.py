"""The training loop's driver: the steps of :meth:`~vadgs.train.trainer.Trainer.train` and around them.

:func:`run_loop` calls :meth:`~vadgs.train.trainer.Trainer.train_step` until ``iterations`` (or a
stop), with the progress bar, the run's ``log.jsonl`` (:class:`~vadgs.train.session.RunLog`), the
stop signals (:func:`~vadgs.train.session.stop_on_signals`), the divergence check, the callback,
the checkpoints on the way (:func:`checkpoint_due`) and at the end, and the failure path
(:func:`save_after_failure`); it returns a :class:`TrainResult`. The trainer holds the model and
the step; this module only drives it (it never imports :mod:`vadgs.train.trainer` at run time).
"""

from __future__ import annotations

import resource
import time
from typing import TYPE_CHECKING, NamedTuple

from vadgs.io import write_json
from vadgs.runfolder import record_files, recorded_files
from vadgs.train.checkpoint import CHECKPOINT_NAME, _remove_stale_tmp, clear_run, restore_rng
from vadgs.train.session import RunLog, stop_on_signals

if TYPE_CHECKING:
    from vadgs.train.trainer import Trainer

__all__ = ["TrainResult", "checkpoint_due", "run_loop", "save_after_failure"]


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


def run_loop(trainer: Trainer) -> TrainResult:
    """Train ``trainer`` to ``config.iterations`` from its current step (the body of its ``train``).

    Prepares the run folder (``config.json``; a previous run's files go with ``overwrite``, a
    killed run's ``.tmp`` files always), then steps (:meth:`~vadgs.train.trainer.Trainer.train_step`) under
    :class:`~vadgs.train.session.RunLog` and :func:`~vadgs.train.session.stop_on_signals`: the
    strategy's pending log lines, a record every ``log_every`` steps, the divergence check, the
    callback, the stop / time limit, the checkpoints on the way (:func:`checkpoint_due`), the
    failure path (:func:`save_after_failure`) and the final checkpoint. The progress bar is
    ``trainer._bar`` while it runs (the VAD-GS event's messages go there).
    """
    from tqdm import tqdm

    cfg = trainer.config
    if trainer.out_dir is not None:
        trainer.out_dir.mkdir(parents=True, exist_ok=True)
        if trainer._clear_previous:
            removed = clear_run(trainer.out_dir)
            trainer._clear_previous = False
            if trainer.log is not None:
                n, where = len(removed), trainer.out_dir
                trainer.log(f"overwrite: removed {n} files of the previous run from {where}")
        _remove_stale_tmp(trainer.out_dir)
        out = trainer.out_dir
        if trainer.step == 0 and "log.jsonl" in {p.name for p in recorded_files(out) if p.parent == out}:
            (out / "log.jsonl").unlink()  # a new run: the log of a run killed before any checkpoint
        write_json(out / "config.json", {"config": cfg.to_dict(), "scene": trainer.scene_ref})
        record_files(out, [out / "config.json", out / "log.jsonl"])
    trainer._saved_at = time.monotonic()
    reason = "done"
    bar = tqdm(
        total=cfg.iterations,
        initial=trainer.step,
        disable=not trainer.progress,
        desc="train",
        dynamic_ncols=True,
        smoothing=0.05,  # the ETA: the rate of the recent steps, VAD-GS events averaged in
    )
    trainer._bar = bar
    recent: list[tuple[float, float]] = []  # (loss, PSNR) of the last steps, shown on the bar
    trainer._undo = None
    trainer._updating = False
    try:
        with (
            RunLog(trainer.out_dir, keep_until=trainer.step) as log,
            stop_on_signals(trainer.request_stop, lambda: trainer._stop),
        ):
            while trainer.step < cfg.iterations:
                t0 = time.perf_counter()
                res = trainer.train_step()
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
                trainer._updating = True  # a diverged state is not saved
                trainer.check_divergence(res)
                trainer._updating = False
                if trainer.callback is not None:
                    trainer.callback(trainer, trainer.step)
                if trainer._stop:
                    reason = "interrupted"
                    break
                if cfg.max_minutes and trainer.train_s > cfg.max_minutes * 60:
                    reason = "time limit"
                    break
                if trainer.out_dir is not None and trainer.step < cfg.iterations and checkpoint_due(trainer):
                    trainer.save_checkpoint()
    except Exception as e:
        save_after_failure(trainer, e)
        raise
    finally:
        bar.close()
        trainer._bar = None
    if trainer.out_dir is not None:
        trainer.save_checkpoint()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    n = trainer.model.num_gaussians
    return TrainResult(trainer.step, trainer.step >= cfg.iterations, reason, trainer.train_s, peak, n)


def checkpoint_due(trainer: Trainer) -> bool:
    """Every ``checkpoint_every`` steps, every ``checkpoint_minutes``, and after the first cycle."""
    cfg = trainer.config
    return bool(
        (cfg.checkpoint_every and trainer.step % cfg.checkpoint_every == 0)
        or trainer.step == len(trainer.sampler)
        or (cfg.checkpoint_minutes and time.monotonic() - trainer._saved_at > cfg.checkpoint_minutes * 60)
    )


def save_after_failure(trainer: Trainer, e: Exception) -> None:
    """Checkpoint the last completed step when an exception stops the loop, and say so on ``e``.

    A step that failed before its optimizer update is undone (the sampler and generators are
    put back), so the saved state is exactly the previous step's; a failure during or after
    the update, a divergence or a non-finite value keeps the previous checkpoint. A failing
    write (disk full) keeps it too.
    """
    if trainer.out_dir is None:
        return
    path = trainer.out_dir / CHECKPOINT_NAME
    saved = False
    failed_write = isinstance(e, OSError) and e.filename == str(path)
    if not trainer._updating and not isinstance(e, FloatingPointError) and not failed_write:
        if trainer._undo is not None:
            sampler, rng = trainer._undo
            trainer.sampler.load_state_dict(sampler)
            restore_rng(rng, trainer.generator)
            trainer._undo = None
        if trainer._saved_step != trainer.step:
            try:
                trainer.save_checkpoint()
                saved = True
            except OSError as se:
                e.add_note(f"(saving the checkpoint failed too: {se})")
        else:
            saved = True
    if saved:
        note = f"checkpoint of step {trainer.step} in {path}"
    elif trainer._saved_step is not None:
        note = f"last good checkpoint: step {trainer._saved_step} in {path}"
    else:
        note = f"no checkpoint was written before step {trainer.step}"
        e.add_note(note)
        return
    e.add_note(f"{note}; continue with: vadgs train --out {trainer.out_dir} --resume")
