"""What the ``vadgs`` commands share: the :class:`Command` base, its tyro parser, and helpers.

Every command is a frozen dataclass whose fields are its flags (tyro: ``--no-progress`` for
``no_progress``, positional fields marked :data:`Positional`), checked in ``__post_init__``, with a
``main()`` that runs it and returns the exit code, as nerfstudio's ``ns-export`` commands and
gsplat's ``simple_trainer`` configs are written. :func:`parse_command` parses one and turns tyro's
boxed errors into one line naming the flag.
"""

from __future__ import annotations

import contextlib
import inspect
import io
import os
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, TypeVar

import tyro

from vadgs.checks import MAX_THREADS, Checked, bool_field, checked, int_field

__all__ = [
    "Command",
    "Flag",
    "Positional",
    "as_flag",
    "check_out_dir",
    "help_text",
    "lidar_depth_line",
    "metrics_summary",
    "parse_command",
    "run_dir",
    "scene_arg",
]

#: A flag that is off unless given (``--no-progress``; no ``--no-no-progress`` pair).
Flag = Annotated[bool, tyro.conf.FlagCreatePairsOff]

#: A positional argument shown as ``metavar`` (``Positional[str, "RUN"]``-style use:
#: ``Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="RUN")]``).
Positional = tyro.conf.Positional

C = TypeVar("C")


@dataclass(frozen=True, kw_only=True)
class Command(Checked):
    """A ``vadgs`` command: its fields are the flags, :meth:`main` runs it.

    Two flags every command has (also accepted before the command's name: ``vadgs --threads 2
    check`` is ``vadgs check --threads 2``).
    """

    threads: int = checked(0, int_field(0, MAX_THREADS))
    """torch CPU threads for the command (0: torch's own count, all cores)"""
    debug: Flag = checked(False, bool_field())
    """show the traceback of an error"""

    @classmethod
    def parse(cls: type[C], argv: list[str], prog: str) -> C | None:
        """The command from its arguments (None after ``--help``, which it prints)."""
        return parse_command(cls, argv, prog)

    def main(self) -> int:
        """Run the command; the exit code."""
        raise NotImplementedError


def parse_command(cls: type[C], argv: list[str], prog: str, default: C | None = None) -> C | None:
    """``argv`` → an instance of the dataclass ``cls`` by tyro (None after ``--help``, which it prints).

    Args:
        cls: the command's dataclass.
        argv: its arguments (without the command's name).
        prog: the name shown in the help, e.g. ``"vadgs eval"``.
        default: the instance the flags apply over (e.g. ``vadgs train``'s starting config).

    Raises:
        ValueError: a bad flag or value, as one line naming the flag.
    """
    kwargs: dict[str, Any] = {"default": default, "config": (tyro.conf.AvoidSubcommands,), "prog": prog}
    kwargs["description"] = help_text(cls.__doc__ or "")
    if "-h" in argv or "--help" in argv:
        with contextlib.suppress(SystemExit):
            tyro.cli(cls, args=["--help"], **kwargs)
        return None
    text = io.StringIO()
    try:
        with contextlib.redirect_stderr(text), contextlib.redirect_stdout(text):
            return tyro.cli(cls, args=list(argv), **kwargs)
    except SystemExit:
        raise ValueError(_tyro_error(text.getvalue())) from None
    except ValueError as e:  # a dataclass's own check, not wrapped by tyro
        raise ValueError(_tyro_error(f"Error parsing {cls.__name__}: {e}")) from None


def help_text(doc: str) -> str:
    """A docstring as help text: reST literals and roles as plain text (```--out``` → ``--out``)."""
    doc = re.sub(r":\w+:`~?([^`]+)`", lambda m: m.group(1).rsplit(".", 1)[-1], inspect.cleandoc(doc))
    return doc.replace("``", "")


def as_flag(key: str) -> str:
    """A dotted field name as its flag: ``vad.max_instances`` → ``--vad.max-instances``."""
    return "--" + key.replace("_", "-")


def _tyro_error(text: str) -> str:
    """Tyro's boxed error message as one line (the lines between the title rule and the next).

    A check of a dataclass (``"Error parsing TrainConfig.raster: backend: expected ..."``) names
    its flags (``--raster.backend: expected ...``); a missing argument is ``"missing RUN"``.
    """
    lines = [ln.strip() for ln in text.splitlines()]
    rules = [i for i, ln in enumerate(lines) if ln and set(ln) <= {"-", "─", "━"}]
    body = [ln for ln in (lines[rules[0] + 1 : rules[1]] if len(rules) >= 2 else lines) if ln]
    if body and body[0].startswith("Missing from "):  # "Missing from vadgs eval:", "RUN", "help (required)"
        return "missing " + ", ".join(ln for ln in body[1::2]) + " (see --help)"
    if "Got errors:" in body:  # an optional value: the error of the type it was meant to be
        tried = [ln for ln in body[body.index("Got errors:") + 1 :] if "NoneType" not in ln]
        body = [*body[:1], re.sub(r"^- <class '\w+'>: ", "", " ".join(tried))]
        body[0] = body[0].split(": no type matching")[0] + ":"
    message = " ".join(body) or " ".join(ln for ln in lines if ln) or "bad arguments"
    m = re.match(r"Error parsing (\S+): (.*)", message)
    if m is None:
        return message
    where, rest = m.groups()
    if where.startswith("--"):
        return f"{where}: {rest}"
    # a dataclass's own check, e.g. "Error parsing train.raster: backend: expected ...": name the flags
    prefix = [p for p in where.split(".") if p != "train" and not p[:1].isupper()]
    named = re.match(r"([a-z_.]+(?:, [a-z_.]+)*): (.*)", rest)
    if named is None:
        return rest
    # a message that names its field with its section already ("appearance.lr") keeps it
    flags = [
        as_flag(name if prefix and name.startswith(prefix[-1] + ".") else ".".join([*prefix, name]))
        for name in named.group(1).split(", ")
    ]
    return f"{', '.join(flags)}: {named.group(2)}"


def check_out_dir(path: str | Path, flag: str = "--out", create: bool = True) -> Path:
    """Check, before any work, that the output folder ``path`` can be written (and create it).

    Args:
        path: the folder.
        flag: the argument's name, for the message.
        create: create the folder (and parents); when False only check that it could be
            created (its nearest existing ancestor is a writable folder), leaving the disk as it is.

    Raises:
        ValueError: if ``path`` is an existing file, cannot be created, or is not writable; the
            message names ``flag`` and the path.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"{flag} {path}: expected a folder, got an existing file")
    if not path.exists() and not create:
        parent = path.parent
        while not parent.exists() and parent != parent.parent:
            parent = parent.parent
        if not parent.is_dir():
            raise ValueError(f"{flag} {path}: cannot create the folder ({parent} is a file)")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise ValueError(f"{flag} {path}: cannot create the folder ({parent} is not writable)")
        # os.access says yes to root everywhere (/proc, read-only mounts): try it, then undo
        check_out_dir(path, flag, create=True)
        first = path
        while first.parent != parent:
            first = first.parent
        for folder in [path, *path.parents]:
            with contextlib.suppress(OSError):
                folder.rmdir()  # only the empty folders just created, up to ``first``
            if folder == first:
                break
        return path
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ValueError(f"{flag} {path}: cannot create the folder ({e.strerror or e})") from None
    try:
        with tempfile.NamedTemporaryFile(dir=path, prefix=".vadgs-write-test-"):
            pass
    except OSError as e:
        raise ValueError(f"{flag} {path}: folder is not writable ({e.strerror or e})") from None
    return path


def run_dir(run: str | Path) -> Path:
    """The run folder of ``RUN`` given as the folder or as its checkpoint file."""
    run = Path(run)
    return run.parent if run.is_file() else run


def scene_arg(value: str | None) -> Path:
    """The ``SCENE`` argument as a path: the bundled sample scene when it is not given."""
    from vadgs.data import sample_scene_path

    return Path(value) if value else sample_scene_path()


def metrics_summary(metrics: dict) -> str:
    """A run's ``metrics.json`` as the one line the commands print (steps, Gaussians, test metrics).

    PSNR* (moving objects only) is left out for a model without moving objects (a photo collection:
    ``gaussians_per_node`` has no track), and said ``n/a`` where the test views show none.
    """
    t = metrics.get("test")
    nodes = metrics.get("gaussians_per_node")
    static = isinstance(nodes, dict) and not any(k.startswith("track_") for k in nodes)
    parts = [
        f"{metrics['steps']} steps in {metrics['train_s']:.0f} s",
        f"{metrics['num_gaussians']} Gaussians",
    ]
    if t:
        star = t["psnr_star"]
        star = f"{star:.2f} dB" if star is not None else "n/a (no moving-object pixels in the test views)"
        star = "" if static and t["psnr_star"] is None else f", PSNR* {star}"
        parts.append(f"test PSNR {t['psnr']:.2f} dB{star}, SSIM {t['ssim']:.3f}")
        raw = t.get("uncorrected")
        if raw:
            parts.append(
                f"uncorrected (no appearance transform) PSNR {raw['psnr']:.2f} dB, SSIM {raw['ssim']:.3f}"
            )
        if "all" in t["depth"]:
            parts.append(
                f"depth AbsRel {t['depth']['all']['absrel']:.3f}, "
                f"d<1.05 {t['depth']['all']['delta_1.05']:.3f}"
            )
        if "lidar" in t["depth"]:
            parts.append(lidar_depth_line(t["depth"]["lidar"]))
    return "; ".join(parts)


def lidar_depth_line(group: dict) -> str:
    """The ``lidar`` depth group of the test metrics in words: AbsRel, δ<1.05 and its pixels.

    Example:
        >>> lidar_depth_line({"absrel": 0.1234, "delta_1.05": 0.5, "pixels": 1200})
        "depth vs the test frames' LiDAR AbsRel 0.123, d<1.05 0.500 (1200 LiDAR pixels)"
    """
    return (
        f"depth vs the test frames' LiDAR AbsRel {group['absrel']:.3f}, "
        f"d<1.05 {group['delta_1.05']:.3f} ({group['pixels']} LiDAR pixels)"
    )
