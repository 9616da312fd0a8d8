"""The ``radarpc`` command: a thin layer over the package's stages.

Each subcommand lives in its own module of this package and exposes ``add_parser(subparsers)``,
which registers its parser and sets ``func`` (called with the parsed args, returns an exit code).
The list below is explicit: adding a command means importing its module and listing it.
:mod:`radarpc.cli.runner` builds the parser and runs the command.
"""
from __future__ import annotations

import argparse
import sys

from radarpc.cli.runner import RESUMABLE_COMMANDS, build_parser as _build_parser, run_command

__all__ = ["RESUMABLE_COMMANDS", "build_parser", "main"]


def _command_modules():
    # Imported lazily so that `radarpc --help` stays fast and one broken stage cannot hide the others.
    from radarpc.cli import (baseline, demo, evaluate, evaluate_points, experiment, export, generate, import_fftradnet,
                             import_rald, info, models, pointcloud, report, show, simulate, train)
    return [simulate, info, pointcloud, show, demo, baseline, evaluate_points, export, models, train, evaluate,
            generate, import_fftradnet, import_rald, experiment, report]


def build_parser() -> argparse.ArgumentParser:
    """The parser of every ``radarpc`` command."""
    return _build_parser(_command_modules(), __doc__.splitlines()[0])


def main(argv: list[str] | None = None) -> int:
    """Run ``radarpc`` with ``argv`` (default ``sys.argv[1:]``); the exit code."""
    return run_command(build_parser(), argv)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
