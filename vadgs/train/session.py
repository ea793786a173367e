"""What a training session does around its loop: its log file and the stop signals.

:class:`RunLog` appends JSON lines to a run folder's ``log.jsonl``; :func:`stop_on_signals` turns
SIGINT / SIGTERM into a request to stop at the end of the current step (a second SIGINT raises
``KeyboardInterrupt`` at once); :func:`reclaim_signals` gives SIGTERM back to Python after pycolmap
took it. The training loop (:func:`~vadgs.train.loop.run_loop`) uses the first two. The run's lock
(one writer per run folder) is :class:`vadgs.runlock.RunLock`.
"""

from __future__ import annotations

import json
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from vadgs.io import atomic_write

__all__ = ["RunLog", "reclaim_signals", "stop_on_signals"]


def reclaim_signals() -> None:
    """Put Python's own SIGINT / SIGTERM handlers back at the C level (main thread only).

    Importing ``pycolmap`` installs glog's failure handler for SIGTERM in C, over Python's: a
    SIGTERM then prints a native stack and kills the process, skipping every ``finally``
    (Python's :func:`signal.getsignal` still reports its own handler). Re-installing the handler
    Python records undoes that.
    """
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in (signal.SIGINT, signal.SIGTERM):
        handler = signal.getsignal(sig)
        if handler is not None:
            signal.signal(sig, handler)


class RunLog:
    """A run's ``log.jsonl``, one JSON object per line, flushed line by line.

    Args:
        folder: the run folder; None writes nothing.
        keep_until: when given, the records of steps after it (written by a run that went on past
            the checkpoint it is resumed from, e.g. killed before its next checkpoint) and any
            line that is not a whole JSON object (cut by a kill) are removed before appending, so
            that a resumed run's log holds every step once.

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as d:
        ...     with RunLog(Path(d)) as log:
        ...         log.write({"step": 1, "loss": 0.5})
        ...     (Path(d) / "log.jsonl").read_text().splitlines()
        ['{"step": 1, "loss": 0.5}']
    """

    def __init__(self, folder: Path | None, keep_until: int | None = None) -> None:
        if folder is not None and keep_until is not None:
            _truncate_log(folder / "log.jsonl", keep_until)
        self._file = (folder / "log.jsonl").open("a") if folder is not None else None

    def write(self, record: dict[str, Any]) -> None:
        """Append ``record`` (values JSON cannot hold are written with ``str``)."""
        if self._file is not None:
            self._file.write(json.dumps(record, default=str) + "\n")
            self._file.flush()

    def close(self) -> None:
        """Close the file (idempotent)."""
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> RunLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _truncate_log(path: Path, keep_until: int) -> None:
    """Keep the lines of ``path`` that are JSON objects of step ``<= keep_until`` (atomically)."""
    if not path.is_file():
        return
    kept, dropped = [], 0
    for line in path.read_text(errors="replace").splitlines():
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            record = None
        if not isinstance(record, dict) or int(record.get("step", 0)) > keep_until:
            dropped += 1
            continue
        kept.append(line)
    if dropped:
        atomic_write(path, "".join(line + "\n" for line in kept))


@contextmanager
def stop_on_signals(request_stop: Callable[[], None], stopping: Callable[[], bool]) -> Iterator[None]:
    """SIGINT / SIGTERM call ``request_stop`` while the block runs; the handlers are put back after.

    A SIGINT while ``stopping()`` is already true raises ``KeyboardInterrupt``. Outside the main
    thread (where Python cannot install handlers) nothing is installed.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, _frame: Any) -> None:
        if stopping() and signum == signal.SIGINT:
            raise KeyboardInterrupt
        request_stop()

    old = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)
