"""``radarpc report RUNS``: Markdown tables and PNG figures of a study's finished runs.

::

    radarpc report runs/sweep
    radarpc report runs/axes --out docs/results/study-axes

Reads the result rows ``RUNS/results/*.json`` (the rows alone are enough: no weights, no run
folders) and writes ``report.md`` and ``figures/GROUP.png`` into ``--out`` (default
``RUNS/report``): per arm and density the mean and standard deviation over seeds of F1 at IoU 0.5
and confidence 0.2 and of freespace mIoU, each curve's normalized AUC (the mean over the density
interval, ``radarpc.eval.curves``) and its gain over the group's first arm, where it reaches the
dense reference, the achieved densities and CFAR thresholds, and every run; figures of the scores
against density (log axis) with their spread and the dense reference as a line. The report and its
figures name the study command, config file and commits that produced them. The output of
``radarpc experiment fps`` gets the FPS report instead: frames/s per model and density (median and
range, network alone and with extraction, plain and fast), against the dense model, the working
memory, the machine and every row's load, and ``figures/fps.png`` (frames/s against density);
with ``--scores STUDY ...`` (training studies' outputs, e.g. the density sweep), each model's F1 @ 0.2
beside its frames/s where a study scored the same model, sensor, input and density (the paper's
Table 2)::

    radarpc report runs/fps --scores runs/sweep runs/rd

The output of ``radarpc experiment rald-ablation`` gets a Table-3-like table: per arm, CD and EMD
per scene and over all frames (:func:`radarpc.experiments.rald.ablation.write_rald_report`).
"""
from __future__ import annotations

import argparse
import shlex

__all__ = ["add_parser", "run"]


def run(args: argparse.Namespace) -> int:
    from radarpc.experiments.rald.ablation import RALD_ROW_FORMAT, write_rald_report
    from radarpc.experiments.study.report import write_report
    from radarpc.experiments.study.results import rows_format

    argv = ["radarpc", "report", str(args.runs)] + (["--out", str(args.out)] if args.out is not None else [])
    argv += ["--scores", *map(str, args.scores)] if args.scores else []
    if rows_format(args.runs) == RALD_ROW_FORMAT:
        if args.scores:
            raise ValueError(f"{args.runs}: --scores pairs F1 with an FPS study's frames/s; {args.runs} is a RaLD "
                             f"ablation")
        write_rald_report(args.runs, args.out, command=shlex.join(argv))
        return 0
    write_report(args.runs, args.out, command=shlex.join(argv), scores=tuple(args.scores or ()))
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("report", help="tables and figures of a study's finished runs (or of an FPS study's rows)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", help="a study output (radarpc experiment --out) or its results/ folder")
    p.add_argument("--out", default=None, help="where to write report.md and figures/ (default RUNS/report)")
    p.add_argument("--scores", nargs="+", default=None, metavar="STUDY",
                   help="FPS study only: training study outputs whose F1 @ 0.2 goes beside the frames/s")
    p.set_defaults(func=run)
