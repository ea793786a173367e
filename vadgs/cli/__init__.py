"""The ``vadgs`` command line: thin adapters over the library, one module per command group.

Every command is a frozen dataclass parsed by tyro (:class:`~vadgs.cli._common.Command`): its
fields are its flags, checked in ``__post_init__``; ``main()`` runs it and returns the exit code.
:data:`COMMANDS` maps the names to them; ``vadgs --help`` lists them, ``vadgs COMMAND --help``
shows a command's flags. ``--threads`` and ``--debug`` go before or after the command's name.

- :mod:`vadgs.cli.train`: ``train`` (every TrainConfig field a flag), ``batch``
- :mod:`vadgs.cli.runs`: ``eval``, ``render``, ``export``, ``view``
- :mod:`vadgs.cli.sfm`: ``sfm`` (photos → a COLMAP project)
- :mod:`vadgs.cli.scenes`: ``check``, ``visibility``, ``convert``
- :mod:`vadgs.cli.demo`: ``demo``

Errors are one line, ``vadgs COMMAND: error: ...`` naming the flag or file, with exit code 2
(3 for a diverged run, 130 when interrupted: Ctrl+C or SIGTERM); ``--debug`` adds the traceback.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import traceback
from typing import Any, Protocol

import torch

from vadgs.cli._common import Command, help_text
from vadgs.cli.demo import DEMO_CONFIG, DEMO_SCALE, DemoCommand  # noqa: F401 (DEMO_*: documented here)
from vadgs.cli.runs import EvalCommand, ExportCommand, RenderCommand, ViewCommand
from vadgs.cli.scenes import CheckCommand, ConvertCommand, VisibilityCommand
from vadgs.cli.sfm import SfmCommand
from vadgs.cli.train import BatchCommand, TrainCommand

__all__ = [
    "COMMANDS",
    "BatchCommand",
    "CheckCommand",
    "Command",
    "ConvertCommand",
    "DemoCommand",
    "EvalCommand",
    "ExportCommand",
    "RenderCommand",
    "SfmCommand",
    "TrainCommand",
    "ViewCommand",
    "VisibilityCommand",
    "main",
    "one_line",
]


class _CommandType(Protocol):
    """A command class: :class:`Command`'s ``parse`` (``vadgs train``'s own, not a subclass)."""

    def parse(self, argv: list[str], prog: str) -> Any: ...


#: The commands by name: a :class:`Command` dataclass each (``vadgs train``'s is
#: :class:`TrainCommand`, whose ``--threads`` is the run's ``TrainConfig.threads``).
COMMANDS: dict[str, _CommandType] = {
    "sfm": SfmCommand,
    "check": CheckCommand,
    "visibility": VisibilityCommand,
    "train": TrainCommand,
    "eval": EvalCommand,
    "render": RenderCommand,
    "export": ExportCommand,
    "view": ViewCommand,
    "demo": DemoCommand,
    "convert": ConvertCommand,
    "batch": BatchCommand,
}

#: The flags every command takes, also before its name.
_GLOBAL_FLAGS = {"--threads": 1, "--debug": 0}  # flag: the number of values it takes


def _interrupt(_signum: int, _frame: Any) -> None:
    raise KeyboardInterrupt


@contextlib.contextmanager
def _sigterm_interrupts() -> Any:
    """While a command runs, SIGTERM raises ``KeyboardInterrupt``: exit 130, every ``finally`` run.

    Without it SIGTERM kills the process at once (exit 143): ``render --video`` left its temporary
    video behind. Only where nobody handles SIGTERM yet (the default), from the main thread; the
    handlers of a command (training's stop at the end of a step) replace it while they run.
    """
    if threading.current_thread() is not threading.main_thread() or (
        signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL
    ):
        yield
        return
    old = signal.signal(signal.SIGTERM, _interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``vadgs`` console script: ``vadgs [--threads N] [--debug] COMMAND ...``."""
    argv = list(sys.argv[1:] if argv is None else argv)
    at = _command_at(argv)
    if at is None:
        if any(a in ("-V", "--version") for a in argv):
            print(_version())
            return 0
        if any(a in ("-h", "--help") for a in argv):
            print(_usage())
            return 0
        given = _first_name(argv)
        what = f"got {given!r}" if given else "got none"
        print(f"vadgs: error: expected a command ({', '.join(COMMANDS)}), {what}", file=sys.stderr)
        return 2
    name = argv[at]
    args = argv[:at] + argv[at + 1 :]  # the global flags given before the name are the command's
    debug = "--debug" in args
    try:
        cmd = COMMANDS[name].parse(args, f"vadgs {name}")
        if cmd is None:  # --help
            return 0
        debug = cmd.debug  # as parsed (until then: "--debug" among the arguments)
        # the whole command runs on --threads: loading, initialisation, training, the final
        # evaluation (train: TrainConfig.threads, also what a --resume keeps or changes)
        threads = (
            cmd.threads if isinstance(cmd, Command) else getattr(getattr(cmd, "train", None), "threads", 0)
        )
        with _torch_threads(threads), _colmap_log_level(0 if debug else None), _sigterm_interrupts():
            return cmd.main()
    except KeyboardInterrupt:
        if debug:
            raise
        print(f"vadgs {name}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the output's reader went away (vadgs ... | head): stop quietly
        with contextlib.suppress(OSError, ValueError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except Exception as e:
        if debug:
            traceback.print_exc()
        print(f"vadgs {name}: error: {one_line(e)}", file=sys.stderr)
        return 3 if isinstance(e, FloatingPointError) else 2


def _command_at(argv: list[str]) -> int | None:
    """The position of the command in ``argv`` (after the global flags), or None."""
    i = 0
    while i < len(argv):
        if argv[i] in COMMANDS:
            return i
        if argv[i] not in _GLOBAL_FLAGS:
            return None
        i += 1 + _GLOBAL_FLAGS[argv[i]]
    return None


def _first_name(argv: list[str]) -> str | None:
    """The first argument that is neither a flag nor a global flag's value (the mistyped command)."""
    i = 0
    while i < len(argv):
        if not argv[i].startswith("-"):
            return argv[i]
        i += 1 + _GLOBAL_FLAGS.get(argv[i], 0)
    return None


def _usage() -> str:
    """``vadgs --help``: the synopsis and the commands with the first line of their help."""
    lines = [f"usage: vadgs [--threads N] [--debug] {{{','.join(COMMANDS)}}} ..."]
    lines += ["", "VAD-GS: visibility-aware densification for 3D Gaussian splatting", "", "commands:"]
    width = max(map(len, COMMANDS))
    for name, cls in COMMANDS.items():
        first = help_text(cls.__doc__ or "").strip().splitlines()[0]
        lines.append(f"  {name:<{width}}  {first}")
    lines += [
        "",
        "flags of every command (before or after its name):",
        "  --threads N  torch CPU threads (0: torch's own count, all cores)",
        "  --debug      show the traceback of an error",
        "",
        "vadgs --version prints the versions of vadgs, torch and python.",
        "vadgs COMMAND --help shows the command's flags.",
    ]
    return "\n".join(lines)


def _version() -> str:
    """``vadgs --version``: vadgs's version, and the torch and Python it runs on (as ``pip`` prints)."""
    import platform

    import vadgs

    device = "cuda" if torch.cuda.is_available() else "cpu"
    return (
        f"vadgs {vadgs.__version__} (torch {torch.__version__}, {device}; python {platform.python_version()})"
    )


@contextlib.contextmanager
def _torch_threads(threads: int | None):
    """``torch.set_num_threads(threads)`` for the command (None: leave it; all cores in a new process).

    The previous count comes back afterwards, so ``main`` called in-process (tests, notebooks,
    ``vadgs batch``) leaves the process as it found it.
    """
    before = torch.get_num_threads()
    if threads:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@contextlib.contextmanager
def _colmap_log_level(level: int | None):
    """The pycolmap log level for the command (``--debug``: everything), restored afterwards."""
    from vadgs.data import colmap_project

    before = colmap_project.COLMAP_LOG_LEVEL
    if level is not None:
        colmap_project.COLMAP_LOG_LEVEL = level
    try:
        yield
    finally:
        colmap_project.COLMAP_LOG_LEVEL = before


def one_line(e: BaseException) -> str:
    """An exception as one line; unexpected kinds keep their type name and point to ``--debug``.

    Notes added to the exception (``add_note``: e.g. the trainer's "last good checkpoint: ...")
    follow, separated by "; ".
    """
    text = " ".join(str(e).split()) or repr(e)
    notes = "".join("; " + " ".join(str(n).split()) for n in getattr(e, "__notes__", None) or ())
    if isinstance(e, (ValueError, FileNotFoundError, FloatingPointError)):
        return text + notes
    if isinstance(e, OSError) and e.filename is not None:
        return f"{e.filename}: {e.strerror or text}{notes}"
    return f"{type(e).__name__}: {text}{notes} (--debug shows the traceback)"


if __name__ == "__main__":
    raise SystemExit(main())
