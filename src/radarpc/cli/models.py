"""``radarpc models``: the model registry, :data:`radarpc.models.MODELS`, as a table.

::

    radarpc models

One row per size variant: what its forward reads (RD cubes or points), its parameter count
(counted on the meta device: nothing is allocated, so the paper sizes list as fast as the tiny
ones) and the first line of its factory's docstring. An experiment config names one of them
under ``model.variant``; ``radarpc train CONFIG --model NAME`` swaps it.
"""
from __future__ import annotations

import argparse

__all__ = ["add_parser", "run"]


def run(args: argparse.Namespace) -> int:
    from radarpc.cli.options import plain_text
    from radarpc.models import MODELS, build_model

    print("| model | input | parameters | what |")
    print("|---|---|---|---|")
    for name, make in MODELS.items():
        model = build_model(name, device="meta")
        n = sum(p.numel() for p in model.parameters())
        first_paragraph = (make.__doc__ or "").strip().split("\n\n")[0]
        what = plain_text(" ".join(line.strip() for line in first_paragraph.splitlines()))
        print(f"| {name} | {model.input_kind} | {n:,} | {what} |")
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("models", help="list the model registry (variants, inputs, parameter counts)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.set_defaults(func=run)
