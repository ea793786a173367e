"""Issue 33, runs and commands: the log after a resume, a full disk as torch reports it, --threads for
the whole command, --out where nothing can be written, the viewer's address and SIGTERM."""

from __future__ import annotations

import dataclasses
import errno
import json
import signal
import socket
import subprocess
import sys
import time
from types import SimpleNamespace

import pytest
import torch

from vadgs.cli import main
from vadgs.cli.__init__ import one_line
from vadgs.train import checkpoint as checkpoint_module
from vadgs.train.checkpoint import CHECKPOINT_NAME, load_checkpoint
from vadgs.train.trainer import Trainer


def _steps(run) -> list[int]:
    lines = (run / "log.jsonl").read_text().splitlines()
    return [json.loads(ln)["step"] for ln in lines if "event" not in json.loads(ln)]


def test_log_has_every_step_once_after_a_resume(tiny_scene, tiny_config, tmp_path):
    config = dataclasses.replace(tiny_config, iterations=4, checkpoint_every=4, checkpoint_minutes=0.0)
    Trainer(tiny_scene, config, out_dir=tmp_path, progress=False).train()
    assert _steps(tmp_path) == [1, 2, 3, 4]
    with (tmp_path / "log.jsonl").open("a") as f:  # a run killed after step 6, before its next checkpoint
        f.write('{"step": 5, "n": 1}\n{"step": 6, "n": 1}\n{"step": 7, "n"')
    resumed = Trainer.from_checkpoint(
        tmp_path, scene=tiny_scene, config_changes={"iterations": 6}, progress=False
    )
    resumed.train()
    assert _steps(tmp_path) == [1, 2, 3, 4, 5, 6]


@pytest.mark.parametrize(
    ("free", "expected"), [(1 << 10, "No space left on device: about"), (1 << 40, "write failed: ")]
)
def test_disk_full_reported_by_torch_zip_writer(
    tiny_scene, tiny_config, tmp_path, monkeypatch, free, expected
):
    """torch reports a full disk as RuntimeError("[enforce fail at inline_container.cc ...")."""
    config = dataclasses.replace(tiny_config, iterations=8, checkpoint_every=4, checkpoint_minutes=0.0)
    real_save = torch.save

    def save(obj, f, *a, **k):
        if obj["step"] == 8:
            raise RuntimeError(
                "[enforce fail at inline_container.cc:778] . PytorchStreamWriter failed writing file"
            )
        return real_save(obj, f, *a, **k)

    monkeypatch.setattr(torch, "save", save)
    monkeypatch.setattr(checkpoint_module.shutil, "disk_usage", lambda path: SimpleNamespace(free=free))
    with pytest.raises(OSError) as e:
        Trainer(tiny_scene, config, out_dir=tmp_path, progress=False).train()
    line = one_line(e.value)
    assert e.value.errno == (errno.ENOSPC if free < 1 << 20 else errno.EIO)
    assert f"{tmp_path / CHECKPOINT_NAME}: cannot write ({expected}" in line and "\n" not in line, line
    assert int(load_checkpoint(tmp_path).step) == 4


def test_threads_cover_loading_and_the_final_evaluation(tmp_path, monkeypatch):
    """metrics.json said "threads": 2 under --threads 1: only the loop ran on 1 thread."""
    import vadgs.cli.train as cli_train

    evaluate_module = sys.modules["vadgs.train.results.evaluate"]

    seen = {}
    real_scene, real_evaluate = cli_train._scene, evaluate_module.evaluate

    def scene(cmd):
        seen["load"] = torch.get_num_threads()
        return real_scene(cmd)

    def evaluate(*a, **k):
        seen["eval"] = torch.get_num_threads()
        return real_evaluate(*a, **k)

    monkeypatch.setattr(cli_train, "_scene", scene)
    monkeypatch.setattr(evaluate_module, "evaluate", evaluate)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        argv = ["train", "--sample", "--out", str(tmp_path / "run"), "--iterations", "1", "--no-progress"]
        assert main([*argv, "--threads", "1", "--init.max-points", "500", "--scale", "0.25"]) == 0
        assert torch.get_num_threads() == 2  # restored
    finally:
        torch.set_num_threads(before)
    assert seen == {"load": 1, "eval": 1}
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["threads"] == 1


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--lr.means", "nan"], "--lr.means: expected a finite number > 0, got nan"),
        (["--lr.means", "inf"], "--lr.means: expected a finite number > 0, got inf"),
        (["--lr.means", "-1"], "--lr.means: expected a finite number > 0, got -1.0"),
        (["--lr.means-final", "0"], "--lr.means-final: expected a finite number > 0, got 0.0"),
        (["--lr.opacity-logits", "-0.1"], "--lr.opacity-logits: expected a finite number >= 0, got -0.1"),
        (["--lr.sh-dc", "nan"], "--lr.sh-dc: expected a finite number >= 0, got nan"),
        (["--lambda-lidar", "nan"], "--lambda-lidar: expected a finite number >= 0, got nan"),
        (["--geometry.lambda-hard", "-1"], "--geometry.lambda-hard: expected a finite number >= 0, got -1.0"),
        (
            ["--geometry.lambda-normal", "inf"],
            "--geometry.lambda-normal: expected a finite number >= 0, got inf",
        ),
        (["--ssim-weight", "2"], "--ssim-weight: expected a finite number in [0, 1], got 2.0"),
        (["--iterations", "0"], "--iterations: expected an integer >= 1, got 0"),
        (
            ["--init.voxel-size", "nan"],
            "--init.voxel-size: expected a finite number >= 0 (0 keeps every point), got nan",
        ),
        (
            ["--init.min-scale", "0"],
            "--init.min-scale: expected a finite number > 0, got 0.0",
        ),
        (
            ["--scale", "1e6"],
            "scale: 1e+06 makes camera 'front' 240000000x144000000 pixels; expected at most",
        ),
        (["--scale", "1e-6"], "scale: 1e-06 makes camera 'front' 0x0 pixels; expected at least 1x1"),
        (["--init.voxel-size", "1e-30"], "voxel_size: 1e-30 makes"),
        (["--out", "/proc/vadgs-run"], "--out /proc/vadgs-run: cannot create the folder"),
    ],
)
def test_train_flags_fail_early_in_one_line(tmp_path, capsys, argv, message):
    out = ["--out", str(tmp_path / "run")] if "--out" not in argv else []
    t0 = time.process_time()  # CPU seconds: a loaded machine does not count against the bound
    assert main(["train", "--sample", *out, "--no-progress", "--threads", "1", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert time.process_time() - t0 < 30  # before any training
    assert not (tmp_path / "run" / CHECKPOINT_NAME).exists()


def _listen_address(port: int) -> str | None:
    """The local address a TCP socket listens on at ``port`` (from /proc/net/tcp), or None."""
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            rows = open(table).read().splitlines()[1:]
        except OSError:
            continue
        for row in rows:
            local, state = row.split()[1], row.split()[3]
            addr, p = local.split(":")
            if int(p, 16) == port and state == "0A":
                if len(addr) == 8:
                    return socket.inet_ntoa(bytes.fromhex(addr)[::-1])
                return addr
    return None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_view_binds_localhost_and_stops_on_sigterm(tiny_scene, tiny_config, tmp_path):
    pytest.importorskip("viser")
    Trainer(
        tiny_scene, dataclasses.replace(tiny_config, iterations=2), out_dir=tmp_path, progress=False
    ).train()
    port = _free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "vadgs.cli", "--threads", "1", "view", str(tmp_path), "--port", str(port),
         "--timeout", "120"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    lines = []
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 90:
            line = proc.stdout.readline()
            lines.append(line)
            if line.startswith("open http") or not line:
                break
        port_used = int(lines[-1].split(":")[2].split()[0])
        assert lines[-1].startswith(f"open http://127.0.0.1:{port_used} (listening on 127.0.0.1 only"), lines
        assert _listen_address(port_used) == "127.0.0.1"
        proc.send_signal(signal.SIGTERM)
        rest, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, "".join(lines) + rest
    assert "Traceback" not in rest and "Fatal" not in rest and "core dumped" not in rest, rest
