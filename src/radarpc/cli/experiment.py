"""``radarpc experiment {density-sweep,ablation,fps,rald-ablation} CONFIG --out DIR``: a study of
the spectral point-cloud paper, or RaLD's ablations, resumable.

::

    radarpc experiment density-sweep configs/study/density-sweep.yaml --out runs/sweep
    radarpc experiment ablation configs/study/ablation.yaml --out runs/axes --cache runs/sweep/cache
    radarpc experiment density-sweep configs/study/density-sweep.yaml --out runs/sweep --plan
    radarpc experiment fps configs/study/fps.yaml --out runs/fps

The config names the data (roots, or simulations made once into the cache), the sensor, the
densities, the models (detection experiment configs with overrides and enrichments), the seeds
and the budget of each run (see ``configs/study/``). For every run not finished yet the study
makes its inputs (point stores or sparse-RD roots at the run's density, one CFAR threshold tau per
root calibrated for the target density; cached in ``--cache``, default ``OUT/cache``, and reused
by content), trains it in ``OUT/density-XXX/MODEL/seedN`` (``OUT/dense/...`` for the dense
reference), scores its best-validation weights on the test split (F1 at IoU 0.5 and confidence
0.2, freespace mIoU) and writes its result row ``OUT/results/RUN.json`` (metrics, config, commit,
density, tau, times; no weights). A run whose row is present is finished and never trained again;
commit ``OUT/results/`` and the study resumes on another machine. Run the same command again after
an interruption: finished runs are reused (it says so), a killed run resumes from its last
checkpoint. A row made with another config of the same run is refused, naming what differs, except
a raised ``time_limit_min``: rows it would not have cut are reused, runs the old limit cut train on.
``--plan`` lists the runs and which are finished, and does nothing else. ``--reuse OTHER_OUT``
takes the result row of a run of another study with the same key (model, input, density,
conversion, data, budget, time limit, seed, scoring; the model compared as the network it builds, so
``spectralpillars-s`` is ``pointpillars-s`` with SpectralPillars' point features) instead of
training it: at the densities both list, the short density sweep's PointPillars-s runs are the short
ablation's ``+Ae+d`` arm and its SpectralPillars-s runs the ``rd3 + sector32`` arm, so
``radarpc experiment density-sweep configs/study/density-sweep-short.yaml --out runs/sweep-short
--reuse runs/ablation-short`` trains those once (the row names the run it came from; the other
output's rows are read at the start). ``radarpc report OUT`` makes the tables and figures.

``fps`` times instead of training (the paper's Table 2): every model of the config at every
density (a dense FFTRadNet once), at batch 1, the network alone and with the extraction from the
RD cube (spectral points, or the sparse-RD masking), plain and ``fast_inference``, each row in a
fresh process with the config's thread count after warm-up passes: frames/s as the median and
range of timed sweeps, the parameters and the working memory of one inference (peak resident set
above the warmed-up process's on a CPU, ``torch.cuda.max_memory_allocated`` on a GPU). Each row
records the machine (CPU, instruction sets, threads, load average at its start and end); a
finished row is never timed again unless ``--overwrite`` (which times every row again), and a row
of another config or machine is refused.

``rald-ablation`` runs RaLD's arms (the RaLD paper's Tables 1, 3, 4, 9;
:mod:`radarpc.experiments.rald.ablation`): for each arm without its row, stage 1 and stage 2 through
``radarpc train``'s functions (arms with the same stage-1 config share its run; a finished run is
reused), the generation (or the autoencoder's reconstruction) of the config's split, its CD and
EMD per scene as ``radarpc evaluate-points`` scores them, and its row ``OUT/results/ARM.json``::

    radarpc experiment rald-ablation table3.yaml --out runs/rald-table3
    radarpc experiment rald-ablation generalization.yaml --data /data/sim_colo6 --out runs/rald-generalization
    radarpc experiment rald-ablation table9.yaml --out runs/rald-table9 --cache runs/rald-stages
    radarpc report runs/rald-table3

``--cache DIR`` keeps the stage runs in ``DIR/stage1``, ``DIR/stage2`` instead of ``OUT``: studies
given the same ``--cache`` train an arm's stage runs once (Tables 3, 4, 9 share their reference
arm); predictions and rows stay in ``--out``.

An arm with ``init: ARM`` fine-tunes that earlier arm's weights, and the stage configs' ``scenes``
hold scene types out of training: the RaLD paper's generalization study (Tables 5-8).
"""
from __future__ import annotations

import argparse
import shlex

from radarpc.cli.options import RALD_STUDY_KINDS, STUDY_KINDS

__all__ = ["add_parser", "run", "command_line"]


def command_line(args: argparse.Namespace) -> str:
    """The command as a user would type it again (recorded in every result row)."""
    argv = ["radarpc", "experiment", args.kind, str(args.config), "--out", str(args.out)]
    if args.cache is not None:
        argv += ["--cache", str(args.cache)]
    for other in getattr(args, "reuse", None) or ():
        argv += ["--reuse", str(other)]
    if getattr(args, "data", None) is not None:
        argv += ["--data", str(args.data)]
    if args.device is not None:
        argv += ["--device", args.device]
    if getattr(args, "overwrite", False):
        argv.append("--overwrite")
    return shlex.join(argv)


def run(args: argparse.Namespace) -> int:
    import sys

    from radarpc.experiments.study.config import load_study
    from radarpc.experiments.study.grid import study_grid
    from radarpc.experiments.study.results import check_rows, read_rows
    from radarpc.experiments.study.runner import run_grid
    from radarpc.machine import check_device

    reuse = list(getattr(args, "reuse", None) or ())
    if reuse and args.kind not in ("density-sweep", "ablation"):
        raise ValueError(f"--reuse applies to the density-sweep and ablation studies (their result rows), "
                         f"not {args.kind}")
    if args.kind in RALD_STUDY_KINDS:
        return _run_rald(args)
    if args.data is not None:
        raise ValueError(f"--data applies to rald-ablation (the ColoRadar root in place of the study's data:); a "
                         f"{args.kind} study names its data in {args.config}")
    cfg = load_study(args.config, args.kind, notice=lambda s: print(s, file=sys.stderr))
    if args.kind == "fps":
        return _run_fps(cfg, args)
    if args.overwrite:
        raise ValueError(f"--overwrite applies to the fps study; a {args.kind} run whose row is present is finished "
                         f"(remove its row and run folder to train it again)")
    grid = study_grid(cfg)
    if args.plan:
        import json

        from radarpc.experiments.study.results import row_origin, run_key
        from radarpc.experiments.study.runner import rows_elsewhere

        finished = check_rows(grid, args.out, read_rows(args.out))
        elsewhere = rows_elsewhere(grid, reuse, finished)
        print(f"study {grid.name!r} ({grid.kind}): {len(grid.runs)} runs, {len(finished)} finished"
              + (f", {len(elsewhere)} to take from --reuse" if reuse else ""))
        keys = {r.id: json.dumps(run_key(grid, r), sort_keys=True) for r in grid.runs}
        done = {keys[r]: r for r in finished}                        # a finished run's twins take its row
        first: dict[str, str] = {}
        for k, r in enumerate(grid.runs, 1):
            twin = first.setdefault(keys[r.id], r.id)
            hit = elsewhere.get(r.id)
            if r.id in finished:
                state = "finished"
            elif keys[r.id] in done:
                state = f"the same run as {done[keys[r.id]]} (finished), its row reused"
            elif hit:
                origin = row_origin(hit["row"])
                state = f"the same run as {origin['study']}:{origin['run']} ({hit['source']}), its row reused"
            else:
                state = f"the same run as {twin}, trained once" if twin != r.id else "to train"
            print(f"[{k}/{len(grid.runs)}] {r.id}: {r.arm.label}, {r.arm.input}"
                  + (f" +{'+'.join(r.arm.enrich)}" if r.arm.enrich else "") + f" -- {state}")
        return 0
    if args.device is not None:
        check_device(args.device, "--device")
    run_grid(grid, args.out, cache=args.cache, device=args.device, progress=not args.no_progress,
             command=command_line(args), config_file=str(args.config), reuse=reuse)
    return 0


def _run_rald(args: argparse.Namespace) -> int:
    from radarpc.experiments.rald.ablation import (RALD_ROW_FIELDS, RALD_ROW_FORMAT, load_rald_ablation,
                                                   run_rald_ablation)
    from radarpc.experiments.study.results import read_rows
    from radarpc.machine import check_device

    if args.overwrite:
        raise ValueError("--overwrite does not apply to rald-ablation (an arm whose row is present is finished; "
                         "remove its row to run it again)")
    if args.plan:
        cfg, plans = load_rald_ablation(args.config)
        rows = read_rows(args.out, row_format=RALD_ROW_FORMAT, required=RALD_ROW_FIELDS)
        print(f"RaLD ablation {cfg.name!r}: {len(plans)} arms, {sum(p.arm.name in rows for p in plans)} with a row in "
              f"{args.out} (its key checked when the study runs)")
        for p in plans:
            stages = p.stage1_dir + ("" if p.stage2_dir is None else f" -> {p.stage2_dir}")
            stages += "" if p.init is None else f" (fine-tuned from {p.init.arm.name})"
            print(f"[{p.order + 1}/{len(plans)}] {p.arm.name}: {p.label}; {stages} -- "
                  f"{'row present' if p.arm.name in rows else 'to run'}")
        return 0
    if args.device is not None:
        check_device(args.device, "--device")
    run_rald_ablation(args.config, args.out, data=args.data, stages=args.cache, device=args.device,
                      progress=not args.no_progress, command=command_line(args))
    return 0


def _run_fps(cfg, args: argparse.Namespace) -> int:
    from radarpc.experiments.study.fps import fps_plan, run_fps
    from radarpc.machine import check_device

    if args.plan:
        import torch

        from radarpc.experiments.study.fps import FPS_REQUIRED, FPS_ROW_FORMAT
        from radarpc.experiments.study.results import read_rows

        plan = fps_plan(cfg)
        rows = read_rows(args.out, row_format=FPS_ROW_FORMAT, required=FPS_REQUIRED)
        device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
        print(f"FPS study {cfg.name!r}: {len(plan.measurements)} rows, {sum(m.id in rows for m in plan.measurements)} "
              f"with a row in {args.out} (checked against this config and machine when the study runs); device {device}")
        for k, m in enumerate(plan.measurements, 1):
            print(f"[{k}/{len(plan.measurements)}] {m.id}: {m.model.spec.variant} on {m.model.input}, sensor {m.sensor}"
                  + (f" +{'+'.join(m.model.enrich)}" if m.model.enrich else "")
                  + f" -- {'row present' if m.id in rows else 'to time'}")
        return 0
    if args.device is not None:
        check_device(args.device, "--device")
    run_fps(cfg, args.out, cache=args.cache, device=args.device, overwrite=args.overwrite,
            progress=not args.no_progress, command=command_line(args), config_file=str(args.config))
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("experiment", help="run a study: density sweep, ablations or FPS table (resumable)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("kind", choices=STUDY_KINDS + RALD_STUDY_KINDS,
                   help="the study: density-sweep, ablation, fps, or rald-ablation (RaLD's arms)")
    p.add_argument("config", help="study YAML (see configs/study/)")
    p.add_argument("--out", required=True, help="study output: run folders (training studies), result rows, study.json")
    p.add_argument("--cache", default=None, metavar="DIR",
                   help="simulated roots, point stores and sparse-RD roots (default OUT/cache); share one "
                        "between studies of the same data. rald-ablation: the stage runs (DIR/stage1, DIR/stage2; "
                        "default OUT), shared between studies that train the same configs")
    p.add_argument("--reuse", action="append", default=[], metavar="OUT",
                   help="density-sweep and ablation: another study's output whose result rows are taken for the "
                        "runs with the same key (model, input, density, conversion, data, budget, time limit, seed, "
                        "scoring; the model compared as the network it builds) instead of training them, e.g. the "
                        "short ablation's +Ae+d and rd3 + sector32 arms for the short sweep's PointPillars-s and "
                        "SpectralPillars-s at the densities both list; repeatable")
    p.add_argument("--data", default=None, metavar="ROOT",
                   help="rald-ablation only: this ColoRadar root instead of the study's data: (the same folder "
                        "name: the rows name it)")
    p.add_argument("--device", default=None, help="torch device (default: a GPU when there is one, else the CPU)")
    p.add_argument("--plan", action="store_true", help="list the runs and which are finished; change nothing")
    p.add_argument("--overwrite", action="store_true",
                   help="fps only: time every row again, replacing rows of this or another config")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=run)
