"""Running ``radarpc`` subcommands from their modules: the parser (plain-text help) and the call that
reports bad input as one line and an interrupt with a resume hint.

:mod:`radarpc.cli` runs every command through it; ``radarpc demo`` (:mod:`radarpc.cli.demo`) the
commands it chains, so that no command module imports the package that lists it. A command module
exposes ``add_parser(subparsers)``, which registers its parser and sets ``func`` (called with the
parsed args, returns an exit code).
"""
from __future__ import annotations

import argparse
import os
import sys
from types import ModuleType
from typing import Sequence

from radarpc import __version__

__all__ = ["RESUMABLE_COMMANDS", "build_parser", "run_command"]

# Commands that keep finished work and resume it when run again.
RESUMABLE_COMMANDS = ("simulate", "pointcloud", "demo", "baseline", "export", "train", "generate", "experiment")


def build_parser(modules: Sequence[ModuleType], description: str | None = None) -> argparse.ArgumentParser:
    """The ``radarpc`` parser with a subcommand for each of ``modules``, every help text plain."""
    parser = argparse.ArgumentParser(prog="radarpc", description=description)
    parser.add_argument("--version", action="version", version=f"radarpc {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for mod in modules:
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


def run_command(parser: argparse.ArgumentParser, argv: list[str] | None = None) -> int:
    """Parse ``argv`` with ``parser`` (:func:`build_parser`) and run the command; its exit code."""
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError, FileExistsError, IsADirectoryError, NotADirectoryError,
            PermissionError, TimeoutError) as e:
        # Bad input is reported as one clear line, not a traceback.
        print(f"radarpc {args.command}: error: {e}", file=sys.stderr)
        return 2
    except FloatingPointError as e:
        # a run that diverged (non-finite loss): the loop says what to change
        print(f"radarpc {args.command}: error: {e}", file=sys.stderr)
        return 1
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
