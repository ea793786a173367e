"""Faults of training runs: kill -9, exceptions, disk full, tampered checkpoints, divergence, reuse."""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from vadgs.cli import main, one_line
from vadgs.io import TMP_GLOB
from vadgs.train.checkpoint import CHECKPOINT_NAME, load_checkpoint
from vadgs.train.divergence import DivergenceError, NonFiniteLossError
from vadgs.train.trainer import Trainer

ROOT = Path(__file__).resolve().parents[2]
TINY = ["--sample", "--scale", "0.25", "--no-progress", "--init.max-points", "400"]
TINY += ["--init.voxel-size", "1.0", "--init.sh-degree", "0"]


def _params(trainer):
    return {k: v.detach().clone() for k, v in trainer.model.params.items()}


def _assert_same(a, b):
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


def _no_auto_checkpoints(config, **changes):
    return dataclasses.replace(config, checkpoint_every=0, checkpoint_minutes=0.0, **changes)


class TestKilledRun:
    def test_kill9_after_the_first_cycle_then_resume_is_exact(self, tiny_scene, tiny_config, tmp_path):
        cycle = len(tiny_scene.train_views)
        config = _no_auto_checkpoints(tiny_config, iterations=cycle + 4)
        script = textwrap.dedent(
            f"""
            import os, signal, sys, torch
            from vadgs.data import load_scene, sample_scene_path
            from vadgs.train.trainer import TrainConfig, Trainer
            torch.set_num_threads({torch.get_num_threads()})  # the parent's: bit-exact needs the same count
            scene = load_scene(sample_scene_path(), scale=0.25)
            config = TrainConfig.from_dict({config.to_dict()!r})
            def kill(trainer, step):
                if step == {cycle + 2}:
                    os.kill(os.getpid(), signal.SIGKILL)
            Trainer(scene, config, out_dir=sys.argv[1], progress=False, callback=kill).train()
            """
        )
        run = tmp_path / "run"
        proc = subprocess.run(
            [sys.executable, "-c", script, str(run)], cwd=ROOT, capture_output=True, text=True, timeout=300
        )
        assert proc.returncode == -signal.SIGKILL, proc.stderr
        # the end of the first sampling cycle always checkpoints (checkpoint_every and _minutes off)
        assert int(load_checkpoint(run).step) == cycle
        stale = run / ".checkpoint.0123abcd.tmp.pt"  # killed mid-write (vadgs.io.atomic_write's name)
        stale.write_bytes(b"half a checkpoint")
        resumed = Trainer.from_checkpoint(run, scene=tiny_scene, progress=False)
        assert resumed.train().completed
        assert not stale.exists()  # stale tmp removed at the start
        full = Trainer(tiny_scene, config, progress=False)
        full.train()
        _assert_same(_params(full), _params(resumed))

    def test_time_and_first_cycle_checkpoints_do_not_change_the_trajectory(
        self, tiny_scene, tiny_config, tmp_path
    ):
        config = dataclasses.replace(tiny_config, checkpoint_every=0, checkpoint_minutes=1e-9)
        saved = []
        tr = Trainer(
            tiny_scene,
            config,
            out_dir=tmp_path,
            progress=False,
            callback=lambda t, s: saved.append(t.checkpoint_step),
        )
        tr.train()
        assert saved[1:] == list(range(1, config.iterations))  # a checkpoint after every step
        ref = Trainer(tiny_scene, config, progress=False)
        ref.train()
        _assert_same(_params(ref), _params(tr))


class TestExceptions:
    def test_exception_mid_step_saves_the_last_completed_step(self, tiny_scene, tiny_config, tmp_path):
        config = _no_auto_checkpoints(tiny_config)

        def corrupt_png_at_7(step, render, view):
            if step == 7:
                raise OSError(errno.EIO, "corrupt PNG", "images/front/000.png")
            return {}

        tr = Trainer(tiny_scene, config, out_dir=tmp_path, extra_losses=corrupt_png_at_7, progress=False)
        with pytest.raises(OSError, match="corrupt PNG") as e:
            tr.train()
        line = one_line(e.value)
        assert "checkpoint of step 7" in line and "--resume" in line, line
        assert int(load_checkpoint(tmp_path).step) == 7
        resumed = Trainer.from_checkpoint(tmp_path, scene=tiny_scene, progress=False)
        resumed.train()
        full = Trainer(tiny_scene, config, progress=False)
        full.train()
        _assert_same(_params(full), _params(resumed))  # the failed step was undone before saving

    def test_non_finite_loss_keeps_the_last_good_checkpoint(self, tiny_scene, tiny_config, tmp_path):
        config = dataclasses.replace(tiny_config, checkpoint_every=2, checkpoint_minutes=0.0)

        def nan_at_3(step, render, view):
            return {"bad": render.color.sum() * (float("nan") if step == 3 else 0.0)}

        tr = Trainer(tiny_scene, config, out_dir=tmp_path, extra_losses=nan_at_3, progress=False)
        with pytest.raises(NonFiniteLossError, match="step 3") as e:
            tr.train()
        assert "last good checkpoint: step 2" in one_line(e.value)
        ckpt = load_checkpoint(tmp_path)
        assert int(ckpt.step) == 2 and bool(torch.isfinite(ckpt.model["params.means"]).all())

    def test_non_finite_loss_is_named_and_changes_no_parameter(self, tiny_scene, tiny_config):
        """The loss is read once, after the update: the fused optimizer skipped it on the device."""

        def nan_at_2(step, render, view):
            return {"bad": render.color.sum() * (float("nan") if step == 2 else 0.0)}

        tr = Trainer(tiny_scene, tiny_config, extra_losses=nan_at_2, progress=False)
        assert all(g["fused"] for g in tr.optimizer.param_groups)
        tr.train_step()
        tr.train_step()
        before = _params(tr)
        moments = [(s["step"].clone(), s["exp_avg"].clone()) for s in tr.optimizer.state.values()]
        with pytest.raises(
            NonFiniteLossError, match=r"step 2: loss terms \{'color': .*'bad': nan, 'total': nan"
        ):
            tr.train_step()
        assert tr.step == 2
        _assert_same(before, _params(tr))  # step 2 refines nothing (refine_start_iter 3)
        for (step, avg), s in zip(moments, tr.optimizer.state.values()):
            assert torch.equal(step, s["step"]) and torch.equal(avg, s["exp_avg"])

    @pytest.mark.parametrize("key", ["log_scales", "sh_dc"])
    def test_non_finite_parameter_after_the_update_is_named(self, tiny_scene, tiny_config, key):
        """A parameter that the optimizer step made NaN: named (all are checked in one device read)."""
        tr = Trainer(tiny_scene, tiny_config, progress=False)
        tr.train_step()
        step = tr.optimizer.step

        def poisoned_step(*a, **k):
            out = step(*a, **k)
            with torch.no_grad():
                tr.model.params[key][0].fill_(float("nan"))
            return out

        tr.optimizer.step = poisoned_step
        with pytest.raises(NonFiniteLossError, match=f"step 1: .*parameter '{key}' after the optimizer step"):
            tr.train_step()

    def test_disk_full_keeps_the_previous_checkpoint(self, tiny_scene, tiny_config, tmp_path, monkeypatch):
        config = dataclasses.replace(tiny_config, checkpoint_every=4, checkpoint_minutes=0.0)
        real_save = torch.save

        def save(obj, f, *a, **k):
            if obj["step"] == 8:
                Path(f).write_bytes(b"x" * 1000)  # part of the file, then the disk is full
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return real_save(obj, f, *a, **k)

        monkeypatch.setattr(torch, "save", save)
        tr = Trainer(tiny_scene, config, out_dir=tmp_path, progress=False)
        with pytest.raises(OSError) as e:
            tr.train()
        assert e.value.errno == errno.ENOSPC and e.value.filename == str(tmp_path / CHECKPOINT_NAME)
        line = one_line(e.value)
        assert "cannot write (No space left on device); the previous file is kept" in line
        assert "last good checkpoint: step 4" in line and "\n" not in line, line
        assert list(tmp_path.glob(TMP_GLOB)) == []
        assert int(load_checkpoint(tmp_path).step) == 4


class TestCheckpointChecksum:
    def test_modified_checkpoint_is_rejected(self, tiny_scene, tiny_config, tmp_path):
        tr = Trainer(
            tiny_scene, dataclasses.replace(tiny_config, iterations=2), out_dir=tmp_path, progress=False
        )
        tr.train()
        path = tmp_path / CHECKPOINT_NAME
        ckpt = torch.load(path, weights_only=True)  # the file's dict
        ckpt["model"]["params.means"][0, 0] += 1.0  # means overwritten, checksum kept
        torch.save(ckpt, path)
        with pytest.raises(ValueError, match="checksum mismatch: the file was modified or is corrupt"):
            load_checkpoint(path)
        assert main(["train", "--out", str(tmp_path), "--resume"]) == 2
        del ckpt["checksum"]  # a checkpoint is verified or refused
        torch.save(ckpt, path)
        with pytest.raises(ValueError, match=r"missing entries \['checksum'\]$"):
            load_checkpoint(path)


class TestDivergence:
    def test_gaussians_flying_away_stop_the_run(self, tiny_scene, tiny_config, tmp_path):
        config = dataclasses.replace(tiny_config, checkpoint_every=1, log_every=2).replace(
            **{"lr.means": 1e8}
        )
        tr = Trainer(tiny_scene, config, out_dir=tmp_path, progress=False)
        with pytest.raises(DivergenceError, match="static Gaussians are farther than") as e:
            tr.train()
        # the diverged state is not saved: the checkpoint is the step before
        assert int(load_checkpoint(tmp_path).step) == e.value.step - 1

    def test_cli_exit_3_with_the_message(self, tmp_path, capsys):
        args = ["train", "--out", str(tmp_path / "r"), "--iterations", "6", *TINY]
        assert main([*args, "--lr.means", "1e8", "--log-every", "2"]) == 3
        err = capsys.readouterr().err
        assert "training diverged at step" in err and "static Gaussians are farther" in err, err
        assert not (tmp_path / "r" / "metrics.json").exists()


class TestRunFolder:
    def test_overwrite_refused_then_allowed(self, tmp_path, capsys):
        out = tmp_path / "run"
        args = ["train", "--out", str(out), "--iterations", "2", *TINY]
        assert main(args) == 0
        before = (out / "metrics.json").read_text()
        log_lines = len((out / "log.jsonl").read_text().splitlines())
        capsys.readouterr()
        assert main(args) == 2
        err = capsys.readouterr().err
        assert f"{out} holds a run (step 2/2); use --resume to continue or --overwrite to start over" in err
        assert (out / "metrics.json").read_text() == before  # untouched
        (out / "eval.json").write_text("{}")
        assert main([*args[:4], "3", *TINY, "--overwrite"]) == 0
        assert json.loads((out / "metrics.json").read_text())["steps"] == 3
        # the previous run's files are gone; an eval.json vadgs did not write is not its to remove
        assert (out / "eval.json").read_text() == "{}"
        assert len((out / "log.jsonl").read_text().splitlines()) == log_lines  # replaced, not appended

    def test_trainer_api_refuses_an_existing_run(self, tiny_scene, tiny_config, tmp_path):
        config = dataclasses.replace(tiny_config, iterations=2)
        Trainer(tiny_scene, config, out_dir=tmp_path, progress=False).train()
        with pytest.raises(ValueError, match=r"holds a run \(step 2/2\).*overwrite=True"):
            Trainer(tiny_scene, config, out_dir=tmp_path, progress=False)
        (tmp_path / "ply").mkdir()
        (tmp_path / "ply" / "mine.ply").write_text("a user's file")
        tr = Trainer(tiny_scene, config, out_dir=tmp_path, progress=False, overwrite=True)
        assert (tmp_path / CHECKPOINT_NAME).exists()  # removed when training starts, not before
        tr.train()
        assert (tmp_path / "ply" / "mine.ply").read_text() == "a user's file"  # only vadgs's files go

    def test_resume_flags(self, tmp_path, capsys):
        out = tmp_path / "run"
        assert main(["train", "--out", str(out), "--iterations", "2", *TINY]) == 0
        capsys.readouterr()
        for extra, flag in (
            (["--lr.means", "1"], "--lr.means"),
            (["--vad"], "--vad"),
            (["--seed", "3"], "--seed"),
            (["--scale", "0.5"], "--scale"),
        ):
            assert main(["train", "--out", str(out), "--resume", *extra]) == 2
            assert f"--resume: {flag} cannot be honoured" in capsys.readouterr().err
        assert main(["train", "--out", str(out), "--resume", "--iterations", "1"]) == 2
        assert "already at step 2" in capsys.readouterr().err
        assert main(["train", "--out", str(out), "--resume", "--iterations", "3", "--no-progress"]) == 0
        said = capsys.readouterr().out
        assert "NOTE: --iterations changes the run from 2 to 3 steps" in said and "learning-rate" in said
        assert json.loads((out / "metrics.json").read_text())["steps"] == 3
        assert int(load_checkpoint(out).config["iterations"]) == 3


class TestExports:
    def test_poses_json_written_atomically(self, tiny_scene, tiny_config, tmp_path, monkeypatch):
        from vadgs.train.results.export import export_model

        tr = Trainer(tiny_scene, dataclasses.replace(tiny_config, iterations=1), progress=False)
        export_model(tr.model, tmp_path)
        before = (tmp_path / "poses.json").read_text()

        def full(self, *a, **k):
            raise OSError(errno.ENOSPC, "No space left on device")

        monkeypatch.setattr(Path, "write_text", full)
        with pytest.raises(OSError):
            export_model(tr.model, tmp_path)
        monkeypatch.undo()
        assert (tmp_path / "poses.json").read_text() == before
        assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []


def test_failure_notes_on_python_310(monkeypatch):
    """Python 3.10 has no BaseException.add_note: the failure path's notes go to __notes__ all the same.

    (Found by mypy with python_version 3.10: the failure path raised AttributeError there, hiding
    the training error.)
    """
    from vadgs.train.loop import add_exception_note

    e = ValueError("diverged")
    monkeypatch.setattr(sys, "version_info", (3, 10, 13, "final", 0))
    add_exception_note(e, "last good checkpoint: step 2")
    add_exception_note(e, "continue with: vadgs train --resume")
    monkeypatch.undo()
    assert e.__notes__ == ["last good checkpoint: step 2", "continue with: vadgs train --resume"]
    assert one_line(e) == "diverged; last good checkpoint: step 2; continue with: vadgs train --resume"
