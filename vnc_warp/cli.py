"""The ``vnc-warp`` command line: one sub-command per module in :mod:`vnc_warp.commands`.

Each command module defines ``HELP`` (one line), ``add_arguments(parser)`` and ``run(args) -> int``.
"""

from __future__ import annotations

import argparse
import importlib
import sys

COMMANDS = ["demo", "curvature", "dataset", "evaluate", "train", "generate", "flow", "flow-batch", "experiment"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vnc-warp", description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    for name in COMMANDS:
        mod = importlib.import_module(f"vnc_warp.commands.{name.replace('-', '_')}")
        p = sub.add_parser(name, help=mod.HELP, description=mod.HELP,
                           formatter_class=argparse.ArgumentDefaultsHelpFormatter)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def user_errors() -> tuple[type[BaseException], ...]:
    """The exceptions that mean bad input or an unusable file or folder: a one-line message and exit code 2.

    ValueError covers MeshError, TrajectoryError, DatasetError, CheckpointError and TrainingError; OSError the
    files and folders (missing, unwritable, under a file). Anything else is a bug and keeps its traceback.
    """
    from .flow import FlowError

    return (ValueError, OSError, FlowError)


def main(argv=None) -> int:
    """Run one command: its exit code, 2 on a user error (one line on stderr), 130 when interrupted."""
    args = build_parser().parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt as exc:
        detail = f": {exc}" if str(exc) else ""
        print(f"vnc-warp {args.command}: interrupted{detail}", file=sys.stderr)
        return 130
    except user_errors() as exc:
        print(f"vnc-warp {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
