"""The FPS study (the spectral point-cloud paper's Table 2): batch-1 frames/s of every model at
every density, with and without the extraction, plain and fast, each row measured in a fresh process.

A config (:class:`~radarpc.experiments.study.config.FPSConfig`) becomes rows (:func:`fps_plan`):
each model at each density (a dense model once, ``dense/``) in each timing mode, identified as
``density-XXX/MODEL/MODE`` (the density folder of :func:`~radarpc.experiments.study.grid.density_folder`).
:func:`run_fps` makes the inputs as the training studies do (the root of each sensor, simulated once
into the cache; point stores and sparse-RD roots per density, one CFAR threshold per root
calibrated on its training split: :class:`~radarpc.experiments.study.inputs.StudyInputs`), then
for every row not finished starts ``python -m radarpc.experiments.study.fps_worker`` with the
study's thread count, which times (:mod:`radarpc.experiments.study.fps_worker`):

* **network**: the model alone on its stored input (the point store's clouds, the sparse-RD root's
  cubes, the dense cubes), and
* **pipeline** (not for a dense model): the RD cube through the extraction at the row's density
  and then the model: the spectral point cloud for a pillar model, the sparse-RD masking for an
  FFTRadNet,

each at batch 1 after ``warmup`` passes, as the median and range of ``repeats`` sweeps over the
``frames`` first frames of the split, with a CUDA device synchronised around each sweep; and the
memory of the timed sweeps: on a CPU the process's peak resident set above its resident set once
warmed up (the weights, frames and runtime are in that baseline; the free heap is returned to the
system first), on CUDA ``torch.cuda.max_memory_allocated`` above what was allocated
(:class:`~radarpc.models.complexity.PeakMemory`). A fresh process per row keeps one row's
allocations, compiled kernels and thread pools out of the next one's numbers.

Each row is a JSON file ``OUT/results/ROW.json`` (format :data:`FPS_ROW_FORMAT`): the rates and
memory of both paths, the parameters, points (or cells) per frame, the threshold and achieved
density of the input, the machine (CPU model, logical and usable CPUs, vector instruction sets,
torch's kernel level, threads, device, load average at the start and end of the timing), the
config, command and commit. **A row present with its key is finished and never timed again**
unless ``overwrite``; its key holds the model (variant, resolved overrides, weights), input,
density, conversion, data, timing and the machine (CPU model and device): rows of another key are
refused, naming what differs. ``radarpc report OUT`` makes the table and figure
(:mod:`radarpc.experiments.study.fps_report`).
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from radarpc.config import to_dict
from radarpc.experiments.study.config import FPSConfig, FPSModel
from radarpc.experiments.study.grid import density_folder
from radarpc.experiments.study.inputs import InputRecord, InputsSpec, StudyInputs
from radarpc.experiments.study.results import flat_differences, plain_json, read_rows, write_named_row
from radarpc.io import atomic_write
from radarpc.runs import OutputLock, check_writable

__all__ = ["FPS_ROW_FORMAT", "FPS_REQUIRED", "Measurement", "FPSPlan", "FPSOutcome", "fps_plan", "measurement_key",
           "run_fps"]

FPS_ROW_FORMAT = "radarpc fps result row 1"
"""The ``format`` every FPS row states."""
FPS_REQUIRED = ("format", "run", "study", "arm", "density", "mode", "key", "measurements", "parameters", "machine")
"""What every FPS row holds."""
STUDY_JSON = "study.json"
CACHE_DIR = "cache"


@dataclass(frozen=True)
class Measurement:
    """One row: a model at a density (None: dense) in a timing mode.

    Attributes
    ----------
    model : FPSModel
    sensor : str
        The radar the model reads.
    density : float or None
    mode : str
        ``"plain"`` or ``"fast"``.
    order : int
        The model's place in the config (the report's row order).
    """

    model: FPSModel
    sensor: str
    density: float | None
    mode: str
    order: int

    __hash__ = None

    @property
    def id(self) -> str:
        """``density-XXX/MODEL/MODE`` (``dense/MODEL/MODE``): the row's name."""
        return f"{density_folder(self.density)}/{self.model.name}/{self.mode}"

    @property
    def row_name(self) -> str:
        """The row's file name: the id with ``__`` for ``/`` and ``.json``."""
        return self.id.replace("/", "__") + ".json"

    @property
    def need(self) -> tuple[str, float, tuple[str, ...]] | None:
        """The stored input beside the root: ``(kind, density, enrichments)``, None for a dense model."""
        return None if self.density is None else (self.model.input, float(self.density), self.model.enrich)


@dataclass(frozen=True)
class FPSPlan:
    """The rows of an FPS config, in measuring order (model by model, density by density, each mode)."""

    config: FPSConfig
    measurements: tuple[Measurement, ...]

    __hash__ = None

    @property
    def sensors(self) -> list[str]:
        """The sensors the models read, in config order."""
        return list(dict.fromkeys(m.sensor for m in self.measurements))


def fps_plan(cfg: FPSConfig) -> FPSPlan:
    """The rows of ``cfg``: each model at each density (a dense model once) in each timing mode."""
    out = []
    for k, model in enumerate(cfg.models):
        densities = (None,) if model.input == "dense" else cfg.densities
        for d in densities:
            out += [Measurement(model, cfg.sensor_of(model), d, mode, k) for mode in cfg.timing.modes]
    return FPSPlan(cfg, tuple(out))


def _weights_id(model: FPSModel) -> str:
    """``"random"``, or the SHA-256 of the run's best weights."""
    if model.run is None:
        return "random"
    from radarpc.training.loop import BEST_WEIGHTS

    h = hashlib.sha256()
    with open(Path(model.run) / BEST_WEIGHTS, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return "sha256:" + h.hexdigest()


def _data_identity(cfg: FPSConfig, sensor: str) -> dict:
    if cfg.data.simulate:
        return {"sensor": sensor, "simulate": [to_dict(s) for s in cfg.data.simulate]}
    return {"sensor": sensor, "roots": [Path(r).name for r in cfg.data.roots]}


def _device_id(device: str) -> str:
    import torch

    dev = torch.device(device)
    return f"cuda: {torch.cuda.get_device_name(dev)}" if dev.type == "cuda" else dev.type


def measurement_key(cfg: FPSConfig, m: Measurement, *, weights: str, device: str, cpu: str) -> dict:
    """What makes a row this row (see the module docstring): the model (variant, the fields its
    config changes, ``weights``), input, enrichments, sensor, density, mode, conversion, data,
    timing (but the list of modes) and the machine (``cpu`` model, ``device``)."""
    from radarpc.models import ModelSpec

    spec = m.model.spec
    conversion = None
    if m.density is not None:
        conversion = cfg.conversion.settings(m.density, m.model.enrich).output_key()
        conversion.pop("beamforming")               # every mode gives the same points
    timing = to_dict(cfg.timing)
    timing.pop("modes")
    return plain_json({
        "model": {"variant": spec.variant, "overrides": ModelSpec.matching(spec.variant, spec.config).overrides,
                  "weights": weights},
        "input": m.model.input, "enrich": list(m.model.enrich), "sensor": m.sensor, "density": m.density,
        "mode": m.mode, "conversion": conversion, "data": _data_identity(cfg, m.sensor), "timing": timing,
        "machine": {"cpu": cpu, "device": device}})


@dataclass
class FPSOutcome:
    """What :func:`run_fps` did: every row of the plan (plan order), which it measured now and
    which it found finished."""

    out: Path
    rows: list[dict]
    measured: list[str] = field(default_factory=list)
    reused: list[str] = field(default_factory=list)


def run_fps(cfg: FPSConfig, out: str | os.PathLike, *, cache: str | os.PathLike | None = None,
            device: str | None = None, overwrite: bool = False, progress: bool = True,
            log: Callable[[str], None] = print, command: str | None = None,
            config_file: str | None = None) -> FPSOutcome:
    """Measure every row of ``cfg`` that ``out`` does not hold finished (see the module docstring).

    Parameters
    ----------
    cfg : FPSConfig
    out : path-like
        The study output: rows ``OUT/results/``, ``OUT/study.json``.
    cache : path-like, optional
        Simulated roots, point stores and sparse-RD roots (default ``OUT/cache``); may be shared
        with the training studies of the same data.
    device : str, optional
        Torch device of the timing (default: a GPU when there is one, else the CPU).
    overwrite : bool
        Time every row again (rows of another key included), replacing its row.
    progress : bool
        Progress bars of the simulation and the conversions.
    log : callable
        Where the one-line messages go.
    command, config_file : str, optional
        Recorded in every row.

    Raises
    ------
    ValueError
        A row of the plan holds another key (without ``overwrite``), or a measuring process
        refused its input.
    """
    import torch

    from radarpc.machine import check_device, cpu_model

    out = Path(out)
    check_writable(out, "study output")
    dev = str(check_device(device, "--device")) if device else ("cuda" if torch.cuda.is_available() else "cpu")
    with OutputLock(out, "study output"):
        return _run_locked(cfg, out, Path(cache) if cache is not None else out / CACHE_DIR, dev, _device_id(dev),
                           cpu_model(), overwrite, progress, log, command, config_file)


def _check_rows(plan: FPSPlan, out: Path, rows: dict[str, dict], keys: dict[str, dict],
                overwrite: bool) -> dict[str, dict]:
    finished, bad = {}, []
    for m in plan.measurements:
        row = rows.get(m.id)
        if row is None:
            continue
        diff = flat_differences(row["key"], keys[m.id])
        if not diff:
            finished[m.id] = row
        elif not overwrite:
            more = f" (and {len(diff) - 3} more)" if len(diff) > 3 else ""
            bad.append(f"{m.id}: {'; '.join(diff[:3])}{more}")
    if bad:
        raise ValueError(f"{out / 'results'}: {len(bad)} row(s) were measured with another configuration or on another "
                         "machine, so the study cannot reuse them: " + " | ".join(bad[:5])
                         + (f" | ... {len(bad) - 5} more" if len(bad) > 5 else "")
                         + ". Pass --overwrite to time them again here, or give another --out")
    return {} if overwrite else finished


def _run_locked(cfg: FPSConfig, out: Path, cache: Path, device: str, device_id: str, cpu: str, overwrite: bool,
                progress: bool, log: Callable[[str], None], command: str | None,
                config_file: str | None) -> FPSOutcome:
    plan = fps_plan(cfg)
    weights = {m.name: _weights_id(m) for m in cfg.models}
    keys = {m.id: measurement_key(cfg, m, weights=weights[m.model.name], device=device_id, cpu=cpu)
            for m in plan.measurements}
    rows = read_rows(out, row_format=FPS_ROW_FORMAT, required=FPS_REQUIRED)
    finished = _check_rows(plan, out, rows, keys, overwrite)
    config = to_dict(cfg)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_write(out / STUDY_JSON, "w") as f:
        json.dump({"kind": "fps", "name": cfg.name, "config_file": config_file, "command": command, "config": config},
                  f, indent=1)
    n = len(plan.measurements)
    todo = [m for m in plan.measurements if m.id not in finished]
    threads = cfg.timing.threads
    log(f"FPS study {cfg.name!r}: {n} rows ({len(cfg.models)} models, {len(cfg.densities)} densities, modes "
        f"{', '.join(cfg.timing.modes)}) on {device_id} ({cpu}), "
        + (f"{threads} threads" if threads else "torch's default threads")
        + f"; {len(finished)} finished (rows in {out / 'results'}), {len(todo)} to time"
        + (" (--overwrite: every row timed again)" if overwrite and rows else ""))
    inputs = {s: StudyInputs(InputsSpec(s, cfg.data, cfg.conversion), cache, device=device, progress=progress,
                             log=log) for s in plan.sensors}
    made: dict[tuple, tuple[Path, InputRecord]] = {}
    for m in todo:                                # every input first, then the timing
        inputs[m.sensor].root(0, cubes=True)
        if m.need is not None and (m.sensor, m.need) not in made:
            made[(m.sensor, m.need)] = inputs[m.sensor].input_of(0, m.need)
    outcome = FPSOutcome(out, [])
    for k, m in enumerate(plan.measurements, 1):
        head = f"[{k}/{n}] {m.id}"
        if m.id in finished:
            row = finished[m.id]
            log(f"{head}: finished earlier, row reused ({_summary(row)}); not timed again")
            outcome.rows.append(row)
            outcome.reused.append(m.id)
            continue
        root = inputs[m.sensor].root(0, cubes=True)
        stored, record = made[(m.sensor, m.need)] if m.need is not None else (None, None)
        row = _measure(cfg, m, out, root, stored, record, keys[m.id], device, log, head, command, config_file,
                       config)
        outcome.rows.append(row)
        outcome.measured.append(m.id)
    log(f"FPS study {cfg.name!r}: all {n} rows finished ({len(outcome.measured)} timed now, {len(outcome.reused)} "
        f"reused); `radarpc report {out}` makes the table and figure")
    return outcome


def _summary(row: dict) -> str:
    paths = row["measurements"]
    text = [f"{'network alone' if p == 'network' else 'with extraction'} {paths[p]['rate']['median']:.3g} frames/s"
            for p in ("network", "pipeline") if paths.get(p)]
    return ", ".join(text)


def _worker_env(threads: int | None) -> dict[str, str]:
    """This environment with radarpc's source first on the path (the worker runs this radarpc) and
    the thread count for the libraries that read it when they load."""
    import radarpc

    env = dict(os.environ)
    src = str(Path(radarpc.__file__).resolve().parents[1])
    env["PYTHONPATH"] = src + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    if threads is not None:
        for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
            env[var] = str(threads)
    return env


def _run_worker(job: dict, threads: int | None, head: str, log: Callable[[str], None]) -> dict:
    """Run :mod:`radarpc.experiments.study.fps_worker` on ``job`` in a fresh process; its result."""
    with tempfile.TemporaryDirectory(prefix="radarpc-fps-") as tmp:
        job_path, result_path = Path(tmp) / "job.json", Path(tmp) / "result.json"
        job_path.write_text(json.dumps(job), encoding="utf-8")
        proc = subprocess.run([sys.executable, "-m", "radarpc.experiments.study.fps_worker", str(job_path),
                               str(result_path)], env=_worker_env(threads), stderr=subprocess.PIPE, text=True,
                              check=False)
        said = [line for line in proc.stderr.splitlines() if line.strip()]
        if proc.returncode == 2 and said:
            raise ValueError(f"{head}: {said[-1]}")
        if proc.returncode != 0 or not result_path.is_file():
            tail = "\n".join(said[-20:])
            raise RuntimeError(f"{head}: the measuring process failed (exit status {proc.returncode}):\n{tail}")
        if said:
            log(f"{head}: the measuring process said: " + " | ".join(said[-3:]))
        return json.loads(result_path.read_text(encoding="utf-8"))


def _measure(cfg: FPSConfig, m: Measurement, out: Path, root: Path, stored: Path | None, record: InputRecord | None,
             key: dict, device: str, log: Callable[[str], None], head: str, command: str | None,
             config_file: str | None, config: dict) -> dict:
    from radarpc.training.checkpoint import software_record

    timing = cfg.timing
    job = {"id": m.id, "model": {"variant": m.model.spec.variant, "overrides": m.model.spec.overrides,
                                 "run": None if m.model.run is None else str(Path(m.model.run).resolve())},
           "mode": m.mode, "input": m.model.input, "root": str(root), "stored": None if stored is None else str(stored),
           "settings": None if m.density is None else cfg.conversion.settings(m.density, m.model.enrich).to_dict(),
           "tau": None if record is None else record.tau, "timing": to_dict(timing), "device": device}
    log(f"{head}: timing {m.model.spec.variant} ({m.mode}) on {m.model.input}"
        + ("" if m.density is None else f" at density {m.density:g}")
        + (f" with {'+'.join(m.model.enrich)}" if m.model.enrich else "")
        + f", sensor {m.sensor}, in a fresh process ({timing.warmup} warm-up passes, {timing.repeats} sweeps over "
          f"{timing.frames} {timing.split} frames at most)")
    t0 = time.perf_counter()
    res = _run_worker(job, timing.threads, head, log)
    wall = time.perf_counter() - t0
    row = {
        "format": FPS_ROW_FORMAT,
        "run": m.id,
        "study": {"kind": "fps", "name": cfg.name, "config_file": config_file, "config": config},
        "arm": {"name": m.model.name, "label": m.model.name, "variant": m.model.spec.variant, "input": m.model.input,
                "enrich": list(m.model.enrich), "sensor": m.sensor, "order": m.order,
                "weights": "random" if m.model.run is None else Path(m.model.run).name},
        "density": m.density,
        "mode": m.mode,
        "key": key,
        "input": None if record is None else record.row(),
        "parameters": res["parameters"],
        "measurements": res["paths"],
        "frames": res["frames"],
        "points_per_frame": res.get("points_per_frame"),
        "pipeline_points_per_frame": res.get("pipeline_points_per_frame"),
        "cells_per_frame": res.get("cells_per_frame"),
        "pipeline_cells_per_frame": res.get("pipeline_cells_per_frame"),
        "machine": {**res["machine"], "device": res["device"], "device_name": res["device_name"],
                    "threads": res["threads"], "load_average": res["load_average"]},
        "times": {"timing_s": res["seconds"], "process_s": wall,
                  "finished_at": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")},
        "software": software_record(),
        "command": command,
    }
    path = write_named_row(out, m.row_name, row)
    mem = {p: v["memory"]["working_bytes"] / 2 ** 20 for p, v in res["paths"].items()}
    load = res["load_average"]
    log(f"{head}: " + "; ".join(
        f"{'network alone' if p == 'network' else 'with extraction'} {v['rate']['median']:.3g} frames/s "
        f"({v['rate']['low']:.3g}-{v['rate']['high']:.3g}), {mem[p]:.1f} MB working memory"
        for p, v in res["paths"].items())
        + f" (load {load['start'][0] if load['start'] else '?'} -> {load['end'][0] if load['end'] else '?'}) -> {path}")
    return json.loads(path.read_text(encoding="utf-8"))
