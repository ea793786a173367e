"""What vadgs asks of processes: whether one still runs, and this one's peak memory.

:func:`pid_alive` tells a crashed writer's lock (:class:`vadgs.runlock.RunLock`) or work folder
(``vadgs sfm``) from a live one; :func:`peak_rss_mb` is the peak resident memory a run reports
(``metrics.json``), and :func:`reset_peak_rss` starts it over to measure one stage (benchmarks,
tests).
"""

from __future__ import annotations

import os
import resource
import sys

__all__ = ["peak_rss_mb", "pid_alive", "reset_peak_rss"]


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` of this host is running (one of another user counts as running)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # a process of another user
        return True
    return True


def peak_rss_mb() -> float:
    """The process's peak resident memory in MiB: Linux's ``VmHWM``, else ``ru_maxrss``.

    ``VmHWM`` is this program's own peak. ``ru_maxrss`` survives ``exec`` on Linux: a ``vadgs
    train`` started by a large process (a test runner, a Ray worker) reported its parent's size
    at the fork (1.7 GB measured for a 0.9 GB run).
    """
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / 1024.0 if sys.platform.startswith("linux") else rss / 2**20  # kB on Linux, bytes on macOS


def reset_peak_rss() -> bool:
    """Start :func:`peak_rss_mb` over from the memory resident now (Linux: ``/proc/self/clear_refs``).

    For measuring one stage's peak in a process that did other work before (a benchmark, a test's
    subprocess). Returns False where the peak cannot be reset (not Linux, or not permitted): then
    :func:`peak_rss_mb` keeps the process's whole peak.
    """
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")  # Linux: reset the peak resident set size (VmHWM) to the current one
    except OSError:
        return False
    return True
