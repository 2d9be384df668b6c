"""The vnc-warp command line: one sub-command per module in vnc_warp/commands.

Each command module defines ``HELP`` (one line), ``add_arguments(parser)`` and ``run(args) -> int``. Every command
also takes the common options of :func:`add_common_options` (``--no-progress``, ``--quiet``, ``--threads``); status
messages go through :mod:`logging` (the ``vnc_warp`` logger), written so that they do not break progress bars.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys

COMMANDS = ["demo", "curvature", "dataset", "evaluate", "train", "generate", "flow", "flow-batch", "experiment"]

DESCRIPTION = ("vnc-warp: the VNC operator, VNC-Flow and the C-VAE of \"VNC: A Scale-Space Foundation for\n"
               "Learnable 3D Surface Evolution\", on NVIDIA Warp.")

log = logging.getLogger("vnc_warp")


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Help with each option's default, "(default: X)", unless the help already says it or there is none to say
    (a flag, an option without a default, a required option)."""

    def _get_help_string(self, action):
        text = action.help or ""
        if ("default" in text.lower() or action.default in (None, False, argparse.SUPPRESS) or action.required
                or not action.option_strings):
            return text
        return text + " (default: %(default)s)"


def add_common_options(p: argparse.ArgumentParser) -> None:
    """Options every command takes, spelled the same everywhere."""
    g = p.add_argument_group("common options")
    g.add_argument("--no-progress", action="store_true", help="no progress bars")
    g.add_argument("-q", "--quiet", action="store_true",
                   help="only warnings and errors on stderr (no progress bars, no status messages)")
    g.add_argument("--threads", type=int, default=None, metavar="N",
                   help="CPU threads of torch; default: the cores not busy now (at least 1), as read from the "
                        "load average: on a small shared machine more threads only slow a small model down")


def build_parser() -> argparse.ArgumentParser:
    from . import __version__

    parser = argparse.ArgumentParser(prog="vnc-warp", description=DESCRIPTION, formatter_class=HelpFormatter,
                                     epilog="`vnc-warp COMMAND -h` describes a command.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        mod = importlib.import_module(f"vnc_warp.commands.{name.replace('-', '_')}")
        p = sub.add_parser(name, help=mod.HELP, description=mod.HELP, formatter_class=HelpFormatter)
        mod.add_arguments(p)
        add_common_options(p)
        p.set_defaults(_run=mod.run)
    return parser


def user_errors() -> tuple[type[BaseException], ...]:
    """The exceptions that mean bad input or an unusable file or folder: a one-line message and exit code 2.

    ValueError covers MeshError, TrajectoryError, DatasetError, CheckpointError and TrainingError; OSError the
    files and folders (missing, unwritable, under a file). Anything else is a bug and keeps its traceback.
    """
    from .flow import FlowError

    return (ValueError, OSError, FlowError)


class _ProgressSafeHandler(logging.Handler):
    """Writes records to stderr through tqdm, so that a line never lands in the middle of a progress bar."""

    def emit(self, record):
        try:
            from tqdm import tqdm

            tqdm.write(self.format(record), file=sys.stderr)
        except Exception:
            self.handleError(record)


def _log_warning(message, category, filename, lineno, file=None, line=None):
    """``warnings.showwarning`` of the command line: one logged line, "warning: ...", not a source excerpt."""
    log.warning("%s", message)


def default_threads() -> int:
    """The cores of this process that are not busy now (affinity minus the 1-minute load average), at least 1."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = os.cpu_count() or 1
    try:
        busy = os.getloadavg()[0]
    except (AttributeError, OSError):
        busy = 0.0
    return max(1, min(cores, int(cores - busy + 0.5)))


def configure(args: argparse.Namespace):
    """Logging, warnings, progress bars and torch threads as the common options ask; returns a function that
    restores what was there before (a command run inside a Python session leaves it as it was)."""
    import warnings

    import torch

    if args.quiet:
        args.no_progress = True
    threads = args.threads if args.threads is not None else default_threads()
    if threads < 1:
        raise ValueError(f"--threads must be >= 1, got {threads}")
    saved = (list(log.handlers), log.level, log.propagate, warnings.showwarning, torch.get_num_threads())
    handler = _ProgressSafeHandler()
    handler.setFormatter(_Formatter(args.command))
    log.handlers[:] = [handler]
    log.setLevel(logging.WARNING if args.quiet else logging.INFO)
    log.propagate = False
    warnings.showwarning = _log_warning
    torch.set_num_threads(threads)

    def restore():
        log.handlers[:] = saved[0]
        log.setLevel(saved[1])
        log.propagate = saved[2]
        warnings.showwarning = saved[3]
        torch.set_num_threads(saved[4])

    return restore


class _Formatter(logging.Formatter):
    """``vnc-warp COMMAND: message`` for information, ``vnc-warp COMMAND: warning: message`` for the rest."""

    def __init__(self, command: str):
        super().__init__()
        self.command = command

    def format(self, record):
        level = "" if record.levelno == logging.INFO else f"{record.levelname.lower()}: "
        return f"vnc-warp {self.command}: {level}{record.getMessage()}"


def main(argv=None) -> int:
    """Run one command: its exit code, 2 on a user error (one line on stderr), 130 when interrupted."""
    args = build_parser().parse_args(argv)
    restore = None
    try:
        restore = configure(args)
        return int(args._run(args) or 0)
    except KeyboardInterrupt as exc:
        detail = f": {exc}" if str(exc) else ""
        print(f"vnc-warp {args.command}: interrupted{detail}", file=sys.stderr)
        return 130
    except user_errors() as exc:
        print(f"vnc-warp {args.command}: error: {exc}", file=sys.stderr)
        return 2
    finally:
        if restore is not None:
            restore()


if __name__ == "__main__":
    sys.exit(main())
