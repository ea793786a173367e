"""The ``vadgs`` command line: thin adapters over the library, one module per command group.

Subcommands are registered in :data:`COMMANDS`; each is a function ``(argparse.Namespace) -> int``
with an ``add_arguments(parser)`` attribute. ``vadgs --help`` lists them. ``vadgs train`` takes
its arguments through tyro (:mod:`vadgs.cli.train`: every TrainConfig field a flag); the other
commands have a few flags of their own and no configuration dataclass.

- :mod:`vadgs.cli.train`: ``train``, ``batch``
- :mod:`vadgs.cli.runs`: ``eval``, ``render``, ``export``, ``view``
- :mod:`vadgs.cli.scenes`: ``check``, ``visibility``, ``convert``
- :mod:`vadgs.cli.demo`: ``demo``
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import traceback
from collections.abc import Callable

import torch

from vadgs.cli._common import _int_at_least
from vadgs.cli.demo import DEMO_CONFIG, DEMO_SCALE, demo  # noqa: F401 (DEMO_*: documented here)
from vadgs.cli.runs import eval_run, export_run, render_run, view_run
from vadgs.cli.scenes import check, convert, visibility
from vadgs.cli.train import batch, train

__all__ = [
    "COMMANDS",
    "batch",
    "check",
    "convert",
    "demo",
    "eval_run",
    "export_run",
    "main",
    "render_run",
    "train",
    "visibility",
]

COMMANDS: dict[str, Callable[[argparse.Namespace], int]] = {
    "check": check,
    "visibility": visibility,
    "train": train,
    "eval": eval_run,
    "render": render_run,
    "export": export_run,
    "view": view_run,
    "demo": demo,
    "convert": convert,
    "batch": batch,
}


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``vadgs`` console script."""
    parser = argparse.ArgumentParser(
        prog="vadgs", description="VAD-GS: visibility-aware densification for 3DGS"
    )
    parser.add_argument(
        "--threads",
        type=_int_at_least(1),
        default=None,
        help="torch CPU threads (>= 1; default: torch's, all cores)",
    )
    parser.add_argument("--debug", action="store_true", help="show the traceback of an error")
    sub = parser.add_subparsers(dest="command", required=True)
    for name, fn in COMMANDS.items():
        p = sub.add_parser(name, help=(fn.__doc__ or "").strip().splitlines()[0], add_help=name != "train")
        fn.add_arguments(p)  # type: ignore[attr-defined]
    argv = list(sys.argv[1:] if argv is None else argv)
    at = _command_at(argv)
    train_argv: list[str] = []
    if at is not None and argv[at] == "train":  # tyro parses the rest (vadgs.cli.train)
        argv, train_argv = argv[: at + 1], argv[at + 1 :]
    args = parser.parse_args(argv)
    args.train_argv = train_argv
    try:
        with _torch_threads(args.threads), _colmap_log_level(0 if args.debug else None):
            return COMMANDS[args.command](args)
    except KeyboardInterrupt:
        if args.debug:
            raise
        print(f"vadgs {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as e:
        if args.debug:
            traceback.print_exc()
        print(f"vadgs {args.command}: error: {_one_line(e)}", file=sys.stderr)
        return 3 if isinstance(e, FloatingPointError) else 2


def _command_at(argv: list[str]) -> int | None:
    """The position of the command in ``argv`` (after the global options), or None."""
    i = 0
    while i < len(argv):
        if argv[i] in COMMANDS:
            return i
        if not argv[i].startswith("-"):
            return None
        i += 2 if argv[i] == "--threads" else 1
    return None


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
    from vadgs.data import colmap

    before = colmap.COLMAP_LOG_LEVEL
    if level is not None:
        colmap.COLMAP_LOG_LEVEL = level
    try:
        yield
    finally:
        colmap.COLMAP_LOG_LEVEL = before


def _one_line(e: BaseException) -> str:
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
