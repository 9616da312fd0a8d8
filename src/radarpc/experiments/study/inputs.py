"""A study's inputs on this machine, made before its runs train and cached by content.

* **roots** -- the config's roots as given, or its simulations written into
  ``CACHE/roots/sim-SENSOR-seedS-HASH/`` (:func:`radarpc.sim.radial_writer.write_radial_dataset`,
  no camera or laser);
* **point stores** -- every root at a run's density with its arm's enrichments,
  ``CACHE/points/ROOT-XXX-ENRICH-HASH.parquet``
  (:func:`radarpc.pipelines.pointclouds.convert_dataset`; with the ``per-dataset`` density mode
  one CFAR threshold tau per root, calibrated on its training split for the target density);
* **sparse-RD roots** -- every root's cubes masked to the same set at a run's density,
  ``CACHE/sparse-rd/ROOT-XXX-ENRICH-HASH/`` (:func:`radarpc.pipelines.sparse_rd.write_sparse_rd`).

``HASH`` digests the content key: the source (the root's resolved path) and every setting that
shapes the output. Beside each finished output a record ``NAME.done.json`` holds that key and what
was measured (tau, achieved density, frames, time): an output with a matching record is reused
without being opened again (a rerun says so). An output without its record (a killed conversion)
is completed by its own resumable writer.

:meth:`StudyInputs.prepare` makes the inputs of the runs to train root by root, so that with
``data.drop_cubes`` a simulated root's cubes are deleted once its inputs exist (the disk then holds
one root's cubes at a time); a later input that needs them simulates them again, the same frames.
The FPS study makes its inputs with the same class, from an :class:`InputsSpec` (the sensor, data
and conversion of one sensor's models) and :meth:`StudyInputs.input_of`.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

from radarpc.config import to_dict
from radarpc.data.radial import root_sensor
from radarpc.experiments.study.config import ConversionSpec, DataSpec, SimulateSpec
from radarpc.experiments.study.grid import Grid, GridRun, density_folder
from radarpc.io import DataFileError, atomic_write
from radarpc.runs import read_json
from radarpc.sensors.radial import radial_sensor

__all__ = ["InputRecord", "InputsSpec", "Need", "StudyInputs", "content_hash", "DONE_SUFFIX"]

DONE_SUFFIX = ".done.json"
"""The record written beside a finished cached output."""


def content_hash(key: dict) -> str:
    """The first 12 hex digits of the SHA-256 of ``key`` as canonical JSON."""
    text = json.dumps(key, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


@dataclass(frozen=True)
class InputRecord:
    """One root's input of a run, as its result row records it.

    Attributes
    ----------
    root : str
        The dataset root's folder name.
    path : str
        The point store, sparse-RD root or (dense runs) root the run read.
    tau : float or None
        The CFAR threshold: calibrated on the root's training split (per-dataset), or None
        (per frame, or a dense run).
    achieved_density : float or None
        Mean density of the encoded set over the root's frames (None for a dense run).
    peak_density : float or None
        Mean density of the CFAR peaks alone, ``|S(tau)| / (N_r N_D)`` (point stores only).
    reused : bool
        Found in the cache (made by an earlier run of this or another study).
    seconds : float
        Time its making took when it was made.
    """

    root: str
    path: str
    tau: float | None
    achieved_density: float | None
    peak_density: float | None
    reused: bool
    seconds: float

    def row(self) -> dict:
        """The record as a result row holds it (no path: rows are portable)."""
        return {"root": self.root, "tau": self.tau, "achieved_density": self.achieved_density,
                "peak_density": self.peak_density, "seconds": self.seconds}


def _finite_or_none(x) -> float | None:
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _read_done(path: Path, key: dict) -> dict | None:
    """The record of a finished output whose key is ``key`` (None when missing or another's)."""
    rec = read_json(path)
    if isinstance(rec, dict) and rec.get("key") == json.loads(json.dumps(key)):
        return rec
    return None


def _write_done(path: Path, record: dict) -> None:
    with atomic_write(path, "w") as f:
        json.dump(record, f, indent=1, allow_nan=False)


def _tau_text(tau: float | None) -> str:
    return "per frame" if tau is None else f"{tau:.4g}"


Need = tuple[str, float, tuple[str, ...]]
"""What a run reads besides its root: ``(input kind, density, enrichments)``, the kind ``"points"``
(a point store) or ``"sparse-rd"`` (a sparse-RD root)."""


@dataclass(frozen=True)
class InputsSpec:
    """What :class:`StudyInputs` makes inputs from (a :class:`Grid` carries the same three fields)."""

    sensor: str
    data: DataSpec
    conversion: ConversionSpec


class StudyInputs:
    """The roots, point stores and sparse-RD roots of a grid's runs (see the module docstring).

    Parameters
    ----------
    grid : Grid or InputsSpec
        The sensor, data and conversion settings.
    cache : path-like
        Folder of the simulated roots, stores and sparse-RD roots (may be shared between studies).
    device : str, optional
        Torch device of the simulation and the conversions.
    progress : bool
        Progress bars of the simulation and the conversions.
    log : callable
        Where one-line messages go.
    """

    def __init__(self, grid: Grid | InputsSpec, cache: str | os.PathLike, *, device: str | None = None, progress: bool = True,
                 log: Callable[[str], None] = print) -> None:
        self.grid = grid
        self.cache = Path(cache)
        self.device = device
        self.progress = progress
        self.log = log
        self.sensor = radial_sensor(grid.sensor)
        self._announced: set[Path] = set()
        self._made: dict[tuple[int, Need], tuple[Path, InputRecord]] = {}

    # ---- roots ------------------------------------------------------------------------------------
    @property
    def n_roots(self) -> int:
        return len(self.grid.data.roots or self.grid.data.simulate)

    def root(self, k: int, *, cubes: bool) -> Path:
        """Dataset root ``k``: the config's (checked to exist and to be of the study's sensor), or
        its ``k``-th simulation, written now unless the cache holds it (with its cubes when
        ``cubes``: simulated again if they were dropped)."""
        if self.grid.data.roots:
            root = Path(self.grid.data.roots[k])
            if not root.is_dir():
                raise DataFileError(root, "dataset root of the study does not exist (data.roots)")
            sensor, _ = root_sensor(root)
            if sensor.name != self.sensor.name:
                raise ValueError(f"{root}: a root of sensor {sensor.name!r}, but the study is on {self.sensor.name!r} "
                                 f"(sensor)")
            return root
        return self._simulated_root(self.grid.data.simulate[k], cubes)

    def _sim_paths(self, spec: SimulateSpec) -> tuple[Path, Path, dict]:
        key = {"simulate": to_dict(spec), "sensor": self.sensor.name}
        root = self.cache / "roots" / f"sim-{self.sensor.name}-seed{spec.seed}-{content_hash(key)}"
        return root, root.with_name(root.name + DONE_SUFFIX), key

    def _simulated_root(self, spec: SimulateSpec, cubes: bool) -> Path:
        from radarpc.sim.radial_writer import write_radial_dataset
        from radarpc.sim.scenes import scene_mix

        root, done, key = self._sim_paths(spec)
        rec = _read_done(done, key)
        if rec is not None and root.is_dir() and (rec.get("cubes", True) or not cubes):
            if root not in self._announced:
                self._announced.add(root)
                self.log(f"reused simulated root {root} ({spec.frames} frames"
                         + ("" if rec.get("cubes", True) else ", RD cubes dropped") + ")")
            return root
        again = rec is not None and root.is_dir()
        self.log(("simulating again the dropped cubes of " if again else "simulating ")
                 + f"{spec.frames} frames ({spec.sequences} sequences x {spec.frames_per_sequence}, seed {spec.seed}, "
                 f"sensor {self.sensor.name}) into {root}")
        t0 = time.perf_counter()
        counts: dict[str, int] = {}
        write_radial_dataset(root, self.sensor, spec.sequences, spec.frames_per_sequence, spec.seed,
                             progress=self.progress, device=self.device or "cpu",
                             scenes=None if spec.scenes is None else scene_mix(spec.scenes),
                             on_finish=lambda w, k: counts.update(written=w, kept=k), camera=False, laser=False)
        seconds = time.perf_counter() - t0
        _write_done(done, {"key": key, "frames": spec.frames, "cubes": True,
                           "seconds": seconds if rec is None else rec["seconds"]})
        self._announced.add(root)
        self.log(f"simulated {root}: {counts.get('written', 0)} frames now, {counts.get('kept', 0)} kept from an "
                 f"earlier run, {seconds:.0f} s")
        return root

    def _drop_cubes(self, k: int) -> None:
        root, done, key = self._sim_paths(self.grid.data.simulate[k])
        rec = _read_done(done, key)
        if rec is None or not rec.get("cubes", True):
            return
        _write_done(done, {**rec, "cubes": False})          # first: a kill half-way reads as dropped
        shutil.rmtree(root / "radar_FFT", ignore_errors=True)
        self.log(f"deleted the RD cubes of {root} (data.drop_cubes): its stores are made; a later input that "
                 f"needs the cubes simulates them again")

    # ---- the inputs of runs ----------------------------------------------------------------------
    @staticmethod
    def _need(run: GridRun) -> Need | None:
        return None if run.arm.input == "dense" else (run.arm.input, float(run.density), run.arm.enrich)

    def prepare(self, runs: Iterable[GridRun]) -> None:
        """Make (or find in the cache) the inputs of ``runs``, root by root; with
        ``data.drop_cubes`` drop each simulated root's cubes after its inputs when no dense run of
        ``runs`` reads them."""
        runs = list(runs)
        needs = sorted({n for n in map(self._need, runs) if n is not None}, key=lambda n: (n[1], n[0], n[2]))
        dense = any(r.arm.input == "dense" for r in runs)
        if not needs and not dense:
            return
        self.log(f"inputs of {len(runs)} runs: {len(needs)} point stores or sparse-RD roots per root "
                 f"({self.n_roots} roots)")
        for k in range(self.n_roots):
            for need in needs:
                self.input_of(k, need)
            if dense:
                self.root(k, cubes=True)
            elif self.grid.data.drop_cubes:
                self._drop_cubes(k)

    def for_run(self, run: GridRun) -> tuple[list[Path], list[Path] | None, list[InputRecord]]:
        """``(data, points, records)`` of ``run``: the roots to train on (sparse-RD roots for a
        sparse-RD run), the point stores (pillar runs; else None) and one record per root."""
        need = self._need(run)
        if need is None:
            roots = [self.root(k, cubes=True) for k in range(self.n_roots)]
            return roots, None, [InputRecord(r.name, str(r), None, None, None, True, 0.0) for r in roots]
        made = [self.input_of(k, need) for k in range(self.n_roots)]
        roots = [self.root(k, cubes=False) for k in range(self.n_roots)]
        paths = [p for p, _ in made]
        records = [rec for _, rec in made]
        return (roots, paths, records) if need[0] == "points" else (paths, None, records)

    def input_of(self, k: int, need: Need) -> tuple[Path, InputRecord]:
        """Root ``k``'s point store or sparse-RD root for ``need``, made now unless the cache (or this
        object) holds it, and its record."""
        got = self._made.get((k, need))
        if got is None:
            kind, density, enrich = need
            got = (self._store if kind == "points" else self._sparse_root)(k, density, enrich)
            self._made[(k, need)] = got
        return got

    def _key(self, kind: str, root: Path, density: float, enrich: tuple[str, ...]) -> dict:
        settings = self.grid.conversion.settings(density, enrich).output_key()
        settings.pop("beamforming")                  # every mode gives the same points
        return {"kind": kind, "source": str(root.resolve()), "settings": settings}

    def _name(self, root: Path, density: float, enrich: tuple[str, ...], key: dict) -> str:
        return (f"{root.name}-{density_folder(density).removeprefix('density-')}-"
                f"{'-'.join(enrich) if enrich else 'plain'}-{content_hash(key)}")

    def _store(self, k: int, density: float, enrich: tuple[str, ...]) -> tuple[Path, InputRecord]:
        from radarpc.pipelines.pointclouds import convert_dataset

        root = self.root(k, cubes=False)
        key = self._key("points", root, density, enrich)
        store = self.cache / "points" / f"{self._name(root, density, enrich, key)}.parquet"
        done = store.with_name(store.name + DONE_SUFFIX)
        rec = _read_done(done, key)
        if rec is not None and store.is_file():
            self.log(f"reused point store {store} (tau {_tau_text(rec['tau'])}, achieved density "
                     f"{rec['achieved_density']:.5f}, target {density:g})")
            return store, InputRecord(root.name, str(store), rec["tau"], rec["achieved_density"],
                                      rec["peak_density"], True, rec["seconds"])
        root = self.root(k, cubes=True)
        self.log(f"converting {root} to points at density {density:g}" + (f" with {', '.join(enrich)}" if enrich else "")
                 + f" -> {store}")
        t0 = time.perf_counter()
        res = convert_dataset(root, store, self.grid.conversion.settings(density, enrich),
                              batch_size=self.grid.conversion.batch_size, device=self.device, progress=self.progress)
        seconds = time.perf_counter() - t0
        rec = {"key": key, "tau": _finite_or_none(res.tau), "achieved_density": _finite_or_none(res.achieved_density),
               "peak_density": _finite_or_none(res.peak_density), "frames": res.n_frames, "points": res.n_points,
               "seconds": seconds}
        _write_done(done, rec)
        self.log(f"point store {store}: {res.n_points} points in {res.n_frames} frames, tau {_tau_text(rec['tau'])}, "
                 f"achieved density {res.achieved_density:.5f} (target {density:g}), {seconds:.0f} s")
        return store, InputRecord(root.name, str(store), rec["tau"], rec["achieved_density"], rec["peak_density"],
                                  False, seconds)

    def _sparse_root(self, k: int, density: float, enrich: tuple[str, ...]) -> tuple[Path, InputRecord]:
        from radarpc.pipelines.sparse_rd import write_sparse_rd

        root = self.root(k, cubes=False)
        key = self._key("sparse-rd", root, density, enrich)
        out = self.cache / "sparse-rd" / self._name(root, density, enrich, key)
        done = out.with_name(out.name + DONE_SUFFIX)
        rec = _read_done(done, key)
        if rec is not None and out.is_dir():
            self.log(f"reused sparse-RD root {out} (tau {_tau_text(rec['tau'])}, achieved density "
                     f"{rec['achieved_density']:.5f}, target {density:g})")
            return out, InputRecord(root.name, str(out), rec["tau"], rec["achieved_density"], None, True,
                                    rec["seconds"])
        root = self.root(k, cubes=True)
        self.log(f"masking the cubes of {root} to density {density:g}" + (f" with {', '.join(enrich)}" if enrich else "")
                 + f" -> {out}")
        t0 = time.perf_counter()
        res = write_sparse_rd(root, out, self.grid.conversion.settings(density, enrich),
                              batch_size=self.grid.conversion.batch_size, device=self.device, progress=self.progress)
        seconds = time.perf_counter() - t0
        rec = {"key": key, "tau": _finite_or_none(res.tau), "achieved_density": _finite_or_none(res.achieved_density),
               "frames": res.n_frames, "seconds": seconds}
        _write_done(done, rec)
        self.log(f"sparse-RD root {out}: {res.n_frames} frames, tau {_tau_text(rec['tau'])}, achieved density "
                 f"{res.achieved_density:.5f} (target {density:g}), {seconds:.0f} s")
        return out, InputRecord(root.name, str(out), rec["tau"], rec["achieved_density"], None, False, seconds)
