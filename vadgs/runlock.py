"""One writer per run folder: :class:`RunLock`, an OS file lock on ``folder/.vadgs.lock``.

``vadgs train``, ``demo``, ``sfm``, and ``eval`` / ``render`` / ``export`` writing into a run take
it; a crashed writer's lock is stale and taken over with a warning (:func:`vadgs.process.pid_alive`
says whether its holder still runs). It sits beside :mod:`vadgs.runfolder` (what vadgs wrote into
a folder), under every package that writes folders (``data``, ``train``, ``cli``).
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import signal
import socket
import threading
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

from vadgs.process import pid_alive

try:
    import fcntl
except ImportError:  # not POSIX: run folders are not locked
    fcntl = None  # type: ignore[assignment]  # the module's stand-in where it is missing

__all__ = ["LOCK_NAME", "RunInUseError", "RunLock"]

_BUSY = (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES)

LOCK_NAME = ".vadgs.lock"
"""The lock file of a run folder (JSON: ``pid``, ``host``, ``started``, ``command``)."""


class RunInUseError(OSError):
    """A run folder is locked by another live process (``filename``: the folder; the message: its pid)."""


class RunLock:
    """One writer per run folder: an exclusive lock on ``folder/.vadgs.lock`` while the block runs.

    The lock is an OS file lock (``flock``) on a file that records the holder (``pid``, ``host``,
    ``started``, ``command``): it is released on any exit of the block (return, exception,
    ``KeyboardInterrupt``), and by the OS when the process dies, so a crashed run's lock is stale:
    the next writer takes it over, with a warning naming the dead pid. While the lock is held a
    SIGTERM that nobody handles raises ``KeyboardInterrupt`` (the block exits through its
    ``finally``; inside the training loop :func:`stop_on_signals` handles it instead). A folder
    the lock created is removed again when the block leaves it empty. Without ``fcntl`` (not
    POSIX), or on a file system that refuses locks (said in a warning), the folder is not locked.

    Args:
        folder: the run folder (created if missing).
        command: who takes it, for the message of the next one (``"vadgs train"``).
        log: a ``print``-like callable for the take-over warning (None: :func:`warnings.warn`).

    Raises:
        RunInUseError: (an ``OSError`` naming the folder) when another live process holds it; the
            message names that process's command, pid, host and start time.

    Example:
        >>> import tempfile
        >>> d = Path(tempfile.mkdtemp())
        >>> with RunLock(d / "run", "doctest"):
        ...     (d / "run" / LOCK_NAME).is_file()
        True
        >>> (d / "run").exists()  # created by the lock, left empty: removed
        False
    """

    def __init__(self, folder: str | Path, command: str = "vadgs", log: Callable[[str], Any] | None = None):
        self.folder = Path(folder)
        self.path = self.folder / LOCK_NAME
        self.command = command
        self._log = log
        self._fd: int | None = None
        self._created: list[Path] = []
        self._sigterm: Any = None

    def _warn(self, message: str) -> None:
        if self._log is not None:
            self._log(f"WARNING: {message}")
        else:
            warnings.warn(message, stacklevel=4)

    def _holder(self) -> dict[str, Any]:
        for _ in range(20):  # the holder writes its record just after taking the lock
            try:
                data = json.loads(self.path.read_text() or "null")
            except (OSError, ValueError):
                data = None
            if isinstance(data, dict):
                return data
            time.sleep(0.05)
        return {}

    def acquire(self) -> RunLock:
        """Take the lock (see the class); the lock itself."""
        if threading.current_thread() is threading.main_thread():
            if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:  # before the file exists
                self._sigterm = signal.signal(signal.SIGTERM, _terminate)
        try:
            self._acquire()
        except BaseException:  # refused, or interrupted on the way: leave nothing behind
            self.release()
            raise
        return self

    def _acquire(self) -> None:
        missing = [p for p in (self.folder, *self.folder.parents) if not p.exists()]
        self.folder.mkdir(parents=True, exist_ok=True)
        self._created = missing  # deepest first
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                if fcntl is not None:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as e:
                if e.errno not in _BUSY:  # a file system without locks: the run goes on unlocked
                    self._warn(f"{self.path}: cannot lock ({e.strerror or e}); the run folder is not locked")
                    break
                os.close(fd)
                raise self._in_use() from None
            try:  # the file may have been removed by its previous holder between open and flock
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        self._fd = fd
        old: Any = {}  # the lock file's JSON: any value (a dict when well formed)
        with contextlib.suppress(OSError, ValueError):
            old = json.loads(os.pread(fd, 1 << 16, 0) or b"null") or {}
        if isinstance(old, dict) and old.get("pid") is not None:
            host = old.get("host")
            dead = host == socket.gethostname() and not pid_alive(int(old["pid"]))
            state = "not running" if dead else "no longer holding it"
            self._warn(
                f"{self.folder}: took over the lock of {old.get('command', 'a vadgs process')} (pid "
                f"{old['pid']} on {host}, since {old.get('started')}): it is {state}, a run that crashed "
                "or was killed; its files are as it left them"
            )
        record = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "started": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
            "command": self.command,
        }
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(record).encode(), 0)

    @classmethod
    def check_free(cls, folder: str | Path) -> None:
        """Raise :class:`RunInUseError` as :meth:`acquire` would when a live process holds the lock.

        Takes nothing and writes nothing: a check before work that would fail anyway (a folder
        that does not exist or has no lock file is free).
        """
        lock = cls(folder)
        if not lock.path.is_file():
            return
        try:
            fd = os.open(lock.path, os.O_RDONLY)
        except OSError:
            return
        try:
            if fcntl is not None:
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError as e:
            if e.errno in _BUSY:
                raise lock._in_use() from None
        finally:
            os.close(fd)

    def _in_use(self) -> RunInUseError:
        h = self._holder()
        who = h.get("command", "a vadgs process")
        who += f" (pid {h.get('pid', '?')} on {h.get('host', '?')}"
        return RunInUseError(
            errno.EBUSY,
            f"in use by {who}, since {h.get('started', '?')}); one process writes a run folder at a "
            "time: wait for it to finish or stop it",
            str(self.folder),
        )

    def _remove_created(self) -> None:
        for p in self._created:  # deepest first; only folders left empty
            with contextlib.suppress(OSError):
                p.rmdir()
        self._created = []

    def release(self) -> None:
        """Remove the lock file and release the lock (idempotent)."""
        if self._fd is not None:
            with contextlib.suppress(OSError):
                self.path.unlink()
            os.close(self._fd)  # closing releases the flock
            self._fd = None
        self._remove_created()
        if self._sigterm is not None:
            with contextlib.suppress(ValueError):
                signal.signal(signal.SIGTERM, self._sigterm)
            self._sigterm = None

    def __enter__(self) -> RunLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def _terminate(_signum: int, _frame: Any) -> None:
    raise KeyboardInterrupt
