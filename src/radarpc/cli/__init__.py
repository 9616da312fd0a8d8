"""The ``radarpc`` command: a thin layer over the package's stages.

Each subcommand lives in its own module of this package and exposes ``add_parser(subparsers)``,
which registers its parser and sets ``func`` (called with the parsed args, returns an exit code).
The list below is explicit: adding a command means importing its module and listing it.
"""
from __future__ import annotations

import argparse
import os
import sys

from radarpc import __version__


# Commands that keep finished work and resume it when run again.
RESUMABLE_COMMANDS = ("simulate", "pointcloud", "demo", "baseline", "export", "train")


def _command_modules():
    # Imported lazily so that `radarpc --help` stays fast and one broken stage cannot hide the others.
    from radarpc.cli import (baseline, demo, evaluate, evaluate_points, export, import_fftradnet, info, models,
                             pointcloud, show, simulate, train)
    return [simulate, info, pointcloud, show, demo, baseline, evaluate_points, export, models, train, evaluate,
            import_fftradnet]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="radarpc", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"radarpc {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for mod in _command_modules():
        mod.add_parser(sub)
    _plain_help(parser)
    return parser


def _plain_help(parser: argparse.ArgumentParser) -> None:
    """Make every description and option help of the parser tree plain text: the descriptions
    come from module docstrings written in reStructuredText (double backticks, ``Example::``)."""
    from radarpc.cli.options import plain_text

    parser.description = plain_text(parser.description)
    parser.epilog = plain_text(parser.epilog)
    for action in parser._actions:
        if isinstance(action.help, str):
            action.help = plain_text(action.help)
        if isinstance(action, argparse._SubParsersAction):
            for choice in action._choices_actions:
                choice.help = plain_text(choice.help)
            for sub in action.choices.values():
                _plain_help(sub)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError, FileExistsError, IsADirectoryError, NotADirectoryError,
            PermissionError, TimeoutError) as e:
        # Bad input is reported as one clear line, not a traceback.
        print(f"radarpc {args.command}: error: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # the reader went away (`radarpc info ROOT | head`): stop quietly, as Unix tools do; stdout
        # points at /dev/null so that Python's flush at exit does not raise again
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except OSError as e:
        # the machine said no (a full disk, a quota, an I/O error): one line, not a traceback
        where = f" ({e.filename})" if e.filename else ""
        hint = ("; finished work is kept: fix it and run the same command again to resume"
                if args.command in RESUMABLE_COMMANDS else "")
        print(f"radarpc {args.command}: error: {e.strerror or e}{where}{hint}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        # The long commands write atomically and resume: say so instead of a traceback.
        hint = ("; finished work is kept, run the same command again to resume"
                if args.command in RESUMABLE_COMMANDS else "")
        print(f"\nradarpc {args.command}: interrupted{hint}", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
