"""Run a study's grid: for every run not yet finished, its inputs, its training, its evaluation
and its result row. One runner for every study kind.

For each run of the :class:`~radarpc.experiments.study.grid.Grid`, in order:

1. a result row with the run's key in ``OUT/results/``: the run is finished, and reused (a row
   with another key is refused before any work, :func:`~radarpc.experiments.study.results.check_rows`,
   unless only the time limit was raised: a run it did not cut is finished, one it cut trains on);
   else a row of another run of the grid with the same key (two arms that are one run), or a row
   with the same key in another study's output given as ``reuse`` (at the densities both list, the
   short sweep's PointPillars-s runs are the short ablation's ``+Ae+d`` arm): copied as the run's
   row, naming the run that trained it;
2. else its inputs (:class:`~radarpc.experiments.study.inputs.StudyInputs`: roots, point stores,
   sparse-RD roots; those of every run to train are made first, root by root, and cached);
3. training in ``OUT/RUN`` through the detection experiment's
   :func:`~radarpc.experiments.radial_detection.train.train_runs`, which resumes a run folder a
   killed study left (and ends with the same weights as an uninterrupted run); with the budget's
   ``time_limit_min`` the run stops once its wall time (this process's, plus the training time
   its log recorded before) reaches the limit;
4. evaluation of its best-validation weights on the evaluation split
   (:func:`~radarpc.experiments.radial_detection.evaluation.evaluate_run`: RADIal's metrics at
   IoU 0.5, among them F1 at confidence 0.2; ``eval_*`` files in the run folder);
5. its result row, written atomically: from then on the run is finished.

The study output is locked for the whole run (a second study writing the same output is refused).
Every step says what it does, and a run found finished says so.
"""
from __future__ import annotations

import csv
import datetime as _dt
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

from radarpc.experiments.radial_detection.evaluation import evaluate_run
from radarpc.training.loop import training_status
from radarpc.experiments.radial_detection.train import train_runs
from radarpc.experiments.study.grid import Grid, GridRun
from radarpc.experiments.study.inputs import StudyInputs
from radarpc.experiments.study.results import (ROW_FORMAT, check_rows, cut_by_limit, key_differences, read_rows,
                                               row_origin, run_key, same_network_run, under_raised_limit,
                                               write_row)
from radarpc.io import atomic_write
from radarpc.runs import OutputLock, RunMismatchError, check_writable
from radarpc.training.checkpoint import software_record
from radarpc.training.loop import BEST_WEIGHTS, LOG_CSV

__all__ = ["StudyOutcome", "run_grid", "rows_elsewhere", "STUDY_JSON", "CACHE_DIR"]

STUDY_JSON = "study.json"
"""The study's config and command, written into its output at each start (not compared: the
result rows are what a rerun is checked against)."""
CACHE_DIR = "cache"
"""The default cache of simulated roots, stores and sparse-RD roots, under the study output."""


@dataclass
class StudyOutcome:
    """What :func:`run_grid` did: the rows of every run of the grid (grid order), which runs it
    trained now and which it found finished."""

    out: Path
    rows: list[dict]
    trained: list[str] = field(default_factory=list)
    reused: list[str] = field(default_factory=list)


class _TimeLimitReached(Exception):
    """Raised from the loop's ``on_step`` to stop a run at its time limit."""


def _logged_train_time(folder: Path) -> float:
    """Seconds of training the run folder's ``log.csv`` records (0 without one)."""
    path = folder / LOG_CSV
    if not path.is_file():
        return 0.0
    with open(path, newline="", encoding="utf-8") as f:
        return sum(float(r["train_time_s"]) for r in csv.DictReader(f) if r.get("train_time_s"))


def _log_rows(folder: Path) -> list[dict]:
    path = folder / LOG_CSV
    if not path.is_file():
        return []
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def run_grid(grid: Grid, out: str | os.PathLike, *, cache: str | os.PathLike | None = None,
             device: str | None = None, progress: bool = True, log: Callable[[str], None] = print,
             command: str | None = None, config_file: str | None = None,
             on_step: Callable[[GridRun, int], None] | None = None,
             reuse: Sequence[str | os.PathLike] = ()) -> StudyOutcome:
    """Train, score and record every run of ``grid`` that ``out`` does not hold finished.

    Parameters
    ----------
    grid : Grid
    out : path-like
        The study output: run folders ``OUT/RUN``, result rows ``OUT/results/``, ``OUT/study.json``.
    cache : path-like, optional
        Where simulated roots, point stores and sparse-RD roots go (default ``OUT/cache``); share
        one between studies of the same data.
    device : str, optional
        Torch device of training, evaluation and conversion (default: a GPU when there is one).
    progress : bool
        Progress bars.
    log : callable
        Where the one-line messages go.
    command : str, optional
        The command line that runs the study, recorded in every row.
    config_file : str, optional
        The study config's file, recorded in every row.
    on_step : callable, optional
        Called with the run and the global step after each optimizer step (tests interrupt a
        study through it).
    reuse : sequence of path-like
        Outputs (or ``results`` folders) of other studies, read once at the start: a run without
        its own row (or a finished arm of the same run here) takes the row of a run there with the
        same key (:func:`rows_elsewhere`) instead of training; the row names the run that trained
        it (``same_as``, ``reused_from``). Such rows, and the rows of twin arms of finished runs,
        are written before the first training, so a study stopped during it keeps them.

    Returns
    -------
    StudyOutcome

    Raises
    ------
    ValueError
        A result row of a run of the grid holds another key, other than by a raised time limit
        (before any work).
    FileNotFoundError
        An output of ``reuse`` without result rows (before any work).
    """
    out = Path(out)
    check_writable(out, "study output")
    with OutputLock(out, "study output"):
        return _run_locked(grid, out, Path(cache) if cache is not None else out / CACHE_DIR, device, progress, log,
                           command, config_file, on_step, reuse)


def _run_locked(grid: Grid, out: Path, cache: Path, device: str | None, progress: bool, log: Callable[[str], None],
                command: str | None, config_file: str | None,
                on_step: Callable[[GridRun, int], None] | None, reuse: Sequence[str | os.PathLike]) -> StudyOutcome:
    rows = read_rows(out)
    finished = check_rows(grid, out, rows)
    elsewhere = rows_elsewhere(grid, reuse, finished)
    for other in reuse:
        found = sum(1 for r in elsewhere.values() if r["source"] == str(other))
        log(f"--reuse {other}: {found} run(s) of this study not finished here have a row there with the same key "
            f"(its rows are read now, once)")
    out.mkdir(parents=True, exist_ok=True)
    with atomic_write(out / STUDY_JSON, "w") as f:
        json.dump({"kind": grid.kind, "name": grid.name, "config_file": config_file, "command": command,
                   "config": grid.config}, f, indent=1)
    n = len(grid.runs)
    others = sorted(set(rows) - {r.id for r in grid.runs})
    log(f"study {grid.name!r} ({grid.kind}): {n} runs ({len(grid.arms)} arms, {len(grid.densities)} densities, "
        f"{len({r.seed for r in grid.runs})} seeds); {len(finished)} finished (result rows in {out / 'results'}), "
        + (f"{len(elsewhere)} taken from --reuse, " if reuse else "") + f"{n - len(finished) - len(elsewhere)} to train"
        + (f"; {len(others)} rows of runs this config does not list are kept" if others else ""))
    inputs = StudyInputs(grid, cache, device=device, progress=progress, log=log)
    inputs.prepare(r for r in grid.runs if r.id not in finished and r.id not in elsewhere)
    outcome = StudyOutcome(out, [])
    # runs of two arms that build the same model on the same input (the axis arm +Ae+d and the
    # enrichment arm "none") have the same key: the second takes the first's result
    by_key = {_key_text(run_key(grid, r)): finished[r.id] for r in grid.runs if r.id in finished}
    # first what costs nothing (finished rows, twins, rows taken from --reuse), so that a study
    # stopped during its first training keeps every row it could take; then the trainings
    def took_twin(head: str, run: GridRun) -> bool:
        twin = by_key.get(_key_text(run_key(grid, run)))
        if twin is None:
            return False
        row = _twin_row(grid, run, twin)
        write_row(out, run, row)
        log(f"{head}: the same run as {twin['run']} (same model, input and settings), its result row reused")
        outcome.rows.append(row)
        outcome.reused.append(run.id)
        return True

    to_train = []
    for k, run in enumerate(grid.runs, 1):
        head = f"[{k}/{n}] {run.id}"
        if run.id in finished:
            row = finished[run.id]
            limit = row["key"].get("time_limit_min")
            under = (f", under a time limit of {limit:g} min that did not cut it" if limit != grid.budget.time_limit_min
                     else "")
            log(f"{head}: finished earlier{under}, result row reused (F1@0.2 "
                f"{_num(row['metrics'].get('f1_fixed'))}); not trained again")
            outcome.rows.append(row)
            outcome.reused.append(run.id)
            continue
        if took_twin(head, run):
            continue
        if run.id in elsewhere:
            row = _reused_row(grid, run, elsewhere[run.id], command, config_file)
            write_row(out, run, row)
            log(f"{head}: the same run as {row['same_as']} (same model, input and settings; --reuse "
                f"{elsewhere[run.id]['source']}), its result row reused")
            by_key.setdefault(_key_text(run_key(grid, run)), row)
            outcome.rows.append(row)
            outcome.reused.append(run.id)
            continue
        to_train.append((head, run))
    for head, run in to_train:
        if took_twin(head, run):                                    # an arm trained just before
            continue
        if run.id in rows and cut_by_limit(rows[run.id]):
            where = ("from its run folder" if (out / run.id / LOG_CSV).is_file()
                     else "from the start (its run folder is not here)")
            log(f"{head}: its row was cut by the earlier time limit of {rows[run.id]['key']['time_limit_min']:g} "
                f"min; it trains on under this one, {where}")
        row = _train_and_score(grid, run, out, inputs, device, progress, log, head, command, config_file, on_step)
        by_key[_key_text(run_key(grid, run))] = row
        outcome.rows.append(row)
        outcome.trained.append(run.id)
    order = {run.id: k for k, run in enumerate(grid.runs)}         # grid order, as documented
    outcome.rows.sort(key=lambda row: order[row["run"]])
    outcome.trained.sort(key=order.__getitem__)
    outcome.reused.sort(key=order.__getitem__)
    log(f"study {grid.name!r}: all {n} runs finished ({len(outcome.trained)} trained now, {len(outcome.reused)} "
        f"reused); `radarpc report {out}` makes the tables and figures")
    return outcome


def _key_text(key: dict) -> str:
    return json.dumps(key, sort_keys=True)


def _arm_record(grid: Grid, run: GridRun) -> dict:
    return {"name": run.arm.name, "label": run.arm.label, "group": run.arm.group, "input": run.arm.input,
            "enrich": list(run.arm.enrich), "variant": run.arm.experiment.model.variant,
            "order": [a.name for a in grid.arms].index(run.arm.name)}


def rows_elsewhere(grid: Grid, reuse: Sequence[str | os.PathLike], finished: dict[str, dict]) -> dict[str, dict]:
    """For each run of ``grid`` neither in ``finished`` nor the same run (key) as one in it, the first
    row in the study outputs ``reuse`` that would finish it in its own study (the same key read
    through today's config types, or one that differs only by a raised time limit that did not cut
    it, as :func:`check_rows` decides), or whose key differs only by how it names the same network
    (:func:`~radarpc.experiments.study.results.same_network_run`: ``spectralpillars-s`` is
    ``pointpillars-s`` with SpectralPillars' point features), as ``{"row": row, "source": the output
    as given}`` by run id.

    Raises
    ------
    FileNotFoundError
        An output of ``reuse`` without result rows (a mistyped path would silently train all).
    """
    others: list[tuple[dict, str]] = []
    for other in reuse:
        rows = read_rows(other)
        if not rows:
            raise FileNotFoundError(f"--reuse {other}: no result rows of a training study there (no results/*.json)")
        others += [(row, str(other)) for row in rows.values()]
    done = {_key_text(run_key(grid, r)) for r in grid.runs if r.id in finished}
    found = {}
    for run in grid.runs:
        key = run_key(grid, run)
        if run.id in finished or _key_text(key) in done:
            continue
        for row, source in others:
            if row["density"] == run.density and row["seed"] == run.seed and (
                    not key_differences(row["key"], key) or under_raised_limit(row, key) == "finished"
                    or same_network_run(row["key"], key)):
                found[run.id] = {"row": row, "source": source}
                break
    return found


def _reused_row(grid: Grid, run: GridRun, hit: dict, command: str | None, config_file: str | None) -> dict:
    """The row of another study's run with ``run``'s key, as this study's row of ``run``: this study's
    record, command and key (so that its own check of rows accepts it; the key the run that trained
    stored is kept in ``reused_from``), the metrics, inputs, training, times and software of that run."""
    other = hit["row"]
    origin = row_origin(other)
    origin.setdefault("key", other["key"])         # the key of the run that trained, as it named it
    now = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    return {**other, "run": run.id, "arm": _arm_record(grid, run), "key": run_key(grid, run),
            "study": {"kind": grid.kind, "name": grid.name, "config_file": config_file, "config": grid.config},
            "command": command, "same_as": f"{origin['study']}:{origin['run']}", "reused_from": origin,
            "times": {**(other.get("times") or {}), "reused_at": now}}


def _twin_row(grid: Grid, run: GridRun, twin: dict) -> dict:
    """``twin``'s row as the row of ``run``, which has the same key."""
    return {**twin, "run": run.id, "arm": _arm_record(grid, run), "same_as": twin.get("same_as") or twin["run"]}


def _num(x) -> str:
    return "n/a" if x is None else f"{x:.4f}"


def _train_and_score(grid: Grid, run: GridRun, out: Path, inputs: StudyInputs, device: str | None, progress: bool,
                     log: Callable[[str], None], head: str, command: str | None, config_file: str | None,
                     on_step: Callable[[GridRun, int], None] | None) -> dict:
    cfg = run.experiment(grid.budget)
    key = run_key(grid, run)
    folder = out / run.id
    data, points, records = inputs.for_run(run)

    length = f"{cfg.train.epochs} epochs" if cfg.train.max_steps == 0 else f"{cfg.train.max_steps} steps"
    limit_s = None if grid.budget.time_limit_min is None else 60.0 * grid.budget.time_limit_min
    log(f"{head}: training {cfg.model.variant} on {run.arm.input}"
        + (f" at density {run.density:g}" if run.density is not None else "")
        + (f" with {'+'.join(run.arm.enrich)}" if run.arm.enrich else "") + f" ({length}, seed {cfg.train.seed}"
        + (f", time limit {grid.budget.time_limit_min:g} min" if limit_s is not None else "") + f") in {folder}")
    earlier = _logged_train_time(folder)
    t0 = time.perf_counter()

    def step_hook(step: int) -> None:
        if on_step is not None:
            on_step(run, step)
        if limit_s is not None and earlier + time.perf_counter() - t0 >= limit_s:
            raise _TimeLimitReached(step)

    cut_at = None
    try:
        train_runs(cfg, data, folder, points=points, runs=1, device=device, progress=progress, log=log,
                   on_step=step_hook)
    except RunMismatchError as e:
        raise RunMismatchError(f"{head}: its run folder {folder} holds a run of other settings or inputs (the "
                               f"inputs are named by their paths: another --cache?): {e}. Give the --cache it "
                               f"started with, or remove the folder to train the run again") from None
    except _TimeLimitReached as stop:
        cut_at = int(stop.args[0])
        log(f"{head}: stopped at the time limit of {grid.budget.time_limit_min:g} min, at step {cut_at}")
    t_train = time.perf_counter() - t0
    if not (folder / BEST_WEIGHTS).is_file():
        raise ValueError(f"{head}: the time limit of {grid.budget.time_limit_min:g} min stopped the run at step "
                         f"{cut_at}, before its first validation: no weights to score. Raise budget.time_limit_min, or "
                         f"validate more often (train.validate_every in the experiment)")

    log(f"{head}: scoring its best-validation weights on the {grid.evaluation.split} split")
    t0 = time.perf_counter()
    ev = evaluate_run(folder, grid.evaluation.split, device=device, fps_frames=max(grid.evaluation.fps_frames, 1),
                      batch_size=grid.evaluation.batch_size, progress=False, log=log,
                      timed=grid.evaluation.fps_frames > 0)[0]
    t_eval = time.perf_counter() - t0
    status = training_status(folder)
    history = _log_rows(folder)
    best = next((r for r in history if r.get("step") and int(r["step"]) == status["weights_step"]), {})
    row = {
        "format": ROW_FORMAT,
        "run": run.id,
        "study": {"kind": grid.kind, "name": grid.name, "config_file": config_file, "config": grid.config},
        "arm": _arm_record(grid, run),
        "density": run.density,
        "seed": run.seed,
        "key": key,
        "inputs": [r.row() for r in records],
        "metrics": ev.metrics,
        "evaluation": {"split": ev.split, "easy": ev.easy, "parameters": ev.parameters,
                       "fps_batch1": ev.fps.median, "fps_batch1_range": [ev.fps.low, ev.fps.high],
                       "device": ev.device, "threads": ev.threads},
        "training": {"epochs": cfg.train.epochs, "max_steps": cfg.train.max_steps,
                     "weights_epoch": status["weights_epoch"], "weights_step": status["weights_step"],
                     "epochs_done": status["epochs_done"], "steps_done": status["steps_done"],
                     "finished": status["finished"], "cut_at_time_limit": cut_at is not None,
                     "train_time_s": sum(float(r["train_time_s"]) for r in history if r.get("train_time_s")),
                     "validations": len(history),
                     "best_validation": {k: float(v) for k, v in best.items() if k.startswith("val_") and v}},
        "times": {"train_s": t_train, "evaluate_s": t_eval,
                  "finished_at": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")},
        "software": software_record(),
        "command": command,
    }
    path = write_row(out, run, row)
    m = ev.metrics
    log(f"{head}: {ev.split} F1@0.2 {_num(m.get('f1_fixed'))} (F1 {_num(m.get('f1'))}, freespace mIoU "
        f"{_num(m.get('freespace_miou'))}) -> {path}")
    return json.loads(path.read_text(encoding="utf-8"))
