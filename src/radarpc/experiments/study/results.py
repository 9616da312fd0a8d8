"""Result rows: one JSON file per finished run of a study, ``OUT/results/RUN.json``.

A row holds what a run measured (RADIal's metrics of its best-validation weights on the
evaluation split, the frames/s of its model), what it read (per root: the CFAR threshold tau and
the achieved density), how it trained (epochs, steps, time, whether the time limit cut it), the
study config, the command and the software (radarpc version, git commit, torch) -- and not its
weights. Rows are small and portable (no machine paths in what identifies a run), so that the
``results/`` folder can be committed and a study resumed on another machine: **a run is finished
when its row is present with a matching key**, and a finished run is never trained again.

The key (:func:`run_key`) is what makes a run this run: the resolved experiment (the budget's
length and the seed applied), the input kind, the density and the conversion settings, the sensor
and the data (the simulations, or the roots' folder names), the evaluation split, the time limit.
A row whose key differs from the config's is refused, with the fields that differ
(:func:`check_rows`): remove the row (and its run folder) to train that run again. The one
difference allowed is a raised time limit (:func:`under_raised_limit`): a row it would not have cut
stays finished, and a run the old limit cut trains on.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

from radarpc.config import to_dict
from radarpc.experiments.radial_detection.config import canonical_key
from radarpc.experiments.study.grid import Grid, GridRun
from radarpc.io import DataFileError, atomic_write

__all__ = ["ROW_FORMAT", "RESULTS_DIR", "REQUIRED_FIELDS", "run_key", "row_origin", "data_identity", "plain_json",
           "write_row",
           "write_named_row", "read_rows", "rows_format", "flat_differences", "key_differences", "network_identity",
           "same_network_run", "under_raised_limit",
           "cut_by_limit", "check_rows"]

ROW_FORMAT = "radarpc study result row 1"
"""The ``format`` every row states; a row of another format is refused."""
RESULTS_DIR = "results"
"""The rows' folder under a study's output."""
REQUIRED_FIELDS = ("format", "run", "study", "arm", "density", "seed", "key", "metrics")
"""What every row of :data:`ROW_FORMAT` holds."""


def data_identity(grid: Grid) -> dict:
    """The study's data as a run key names it, the same on every machine: the sensor and the
    simulations, or the roots' folder names (not their paths)."""
    if grid.data.simulate:
        return {"sensor": grid.sensor, "simulate": [to_dict(s) for s in grid.data.simulate]}
    return {"sensor": grid.sensor, "roots": [Path(r).name for r in grid.data.roots]}


def run_key(grid: Grid, run: GridRun) -> dict:
    """What identifies ``run`` of ``grid`` (see the module docstring)."""
    conversion = None
    if run.arm.input != "dense":
        conversion = grid.conversion.settings(run.density, run.arm.enrich).output_key()
        conversion.pop("beamforming")              # every mode gives the same points
    return plain_json({"input": run.arm.input, "experiment": to_dict(run.experiment(grid.budget)),
                       "density": run.density, "conversion": conversion, "data": data_identity(grid),
                       "evaluation": {"split": grid.evaluation.split, "weights": "best validation"},
                       "time_limit_min": grid.budget.time_limit_min})


def row_origin(row: dict) -> dict:
    """The training run whose numbers ``row`` holds, ``{"study", "kind", "config_file", "command",
    "run"}``: the row's own study and run, or the run it is the same as (an arm of its study with
    the same key, ``same_as``, or a run of another study taken with ``--reuse``, ``reused_from``)."""
    if row.get("reused_from"):
        return dict(row["reused_from"])
    study = row["study"]
    return {"study": study.get("name"), "kind": study.get("kind"), "config_file": study.get("config_file"),
            "command": row.get("command"), "run": row.get("same_as") or row["run"]}


def plain_json(value: Any) -> Any:
    """``value`` as strict JSON types: NaN and infinities become None (a row is read anywhere)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): plain_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain_json(v) for v in value]
    return value


def write_row(out: str | os.PathLike, run: GridRun, row: dict) -> Path:
    """Write ``row`` as ``out/results/RUN.json``, atomically; returns the path."""
    return write_named_row(out, run.row_name, row)


def write_named_row(out: str | os.PathLike, name: str, row: dict) -> Path:
    """Write ``row`` as ``out/results/NAME``, atomically (strict JSON: :func:`plain_json`); returns the path."""
    path = Path(out) / RESULTS_DIR / name
    with atomic_write(path, "w") as f:
        json.dump(plain_json(row), f, indent=1, allow_nan=False)
        f.write("\n")
    return path


def _rows_folder(out: Path) -> Path:
    return out if out.name == RESULTS_DIR and not (out / RESULTS_DIR).is_dir() else out / RESULTS_DIR


def rows_format(out: str | os.PathLike) -> str | None:
    """The ``format`` the rows of a study output (or of a ``results`` folder) state, None without
    rows; the study kind's reader checks them (a row of another format is refused there)."""
    folder = _rows_folder(Path(out))
    for path in sorted(folder.glob("*.json")) if folder.is_dir() else ():
        try:
            row = json.loads(path.read_text(encoding="utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError):
            continue
        if isinstance(row, dict) and isinstance(row.get("format"), str):
            return row["format"]
    return None


def read_rows(out: str | os.PathLike, *, row_format: str = ROW_FORMAT,
              required: tuple[str, ...] = REQUIRED_FIELDS) -> dict[str, dict]:
    """The result rows of a study output (or of a ``results`` folder), by run id.

    ``row_format`` and ``required``: the format the rows must state and the fields each must hold
    (the training studies' by default; the FPS study passes its own).

    Raises
    ------
    DataFileError
        A row that is not valid JSON, not a result row, or of another format, or two rows of one run.
    """
    folder = _rows_folder(Path(out))
    rows: dict[str, dict] = {}
    if not folder.is_dir():
        return rows
    for path in sorted(folder.glob("*.json")):
        try:
            row = json.loads(path.read_text(encoding="utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise DataFileError(path, f"not a result row (invalid JSON: {e})") from None
        if not isinstance(row, dict) or any(k not in row for k in required):
            raise DataFileError(path, f"not a study result row of format {row_format!r} (needs {', '.join(required)})")
        if row["format"] != row_format:
            raise DataFileError(path, f"a result row of format {row['format']!r}; this study reads {row_format!r} "
                                      f"(rows of two study kinds in one output? give each study its own --out)")
        if row["run"] in rows:
            raise DataFileError(path, f"a second row of run {row['run']!r}")
        if path.name != row["run"].replace("/", "__") + ".json":
            raise DataFileError(path, f"holds run {row['run']!r}, whose row is named "
                                      f"{row['run'].replace('/', '__')}.json")
        rows[row["run"]] = row
    return rows


def _flat(d: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(d, dict) and d:
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(_flat(v, f"{prefix}{k}."))
        return out
    return {prefix.rstrip("."): d}


def _readable(stored: dict, num_workers: int) -> dict:
    """A stored key read through today's config types: experiment fields added since take their
    defaults, and the loader's worker count (which does not change what a run computes) is ours."""
    return plain_json(canonical_key(stored, num_workers=num_workers))


def flat_differences(stored: dict, key: dict) -> list[str]:
    """``"field: stored in the row, wanted in the config"`` for every dotted field where two keys differ."""
    have, want = _flat(plain_json(stored)), _flat(plain_json(key))
    return [f"{k}: {have.get(k, '(missing)')!r} in the row, {want.get(k, '(missing)')!r} in the config"
            for k in sorted(set(have) | set(want)) if have.get(k) != want.get(k)]


def key_differences(stored: dict, key: dict) -> list[str]:
    """:func:`flat_differences` of a training run's stored key, read through today's config types."""
    return flat_differences(_readable(stored, key["experiment"]["train"]["num_workers"]), key)


def network_identity(model: dict) -> dict | None:
    """The network an experiment's model section (``{"variant", "overrides"}``) builds: the class and
    the resolved config of ``MODELS[variant](**overrides)`` (built on the meta device). Two spellings
    of one network, ``spectralpillars-s`` and ``pointpillars-s`` with the point features it sets, have
    one identity: the same modules in the same order, so the same initial weights for a seed. None
    when today's code cannot build the section."""
    import dataclasses

    from radarpc.models import build_model

    try:
        net = build_model(model["variant"], model.get("overrides") or {}, device="meta")
    except (KeyError, TypeError, ValueError):
        return None
    cfg = getattr(net, "cfg", None)
    if cfg is None or not dataclasses.is_dataclass(cfg):
        return None
    return {"class": f"{type(net).__module__}.{type(net).__qualname__}", "config": plain_json(to_dict(cfg))}


def same_network_run(stored: dict, key: dict) -> bool:
    """Whether a stored run key names the run ``key`` names once each experiment's model section is
    read as the network it builds (:func:`network_identity`) and the experiment's name, a label that
    changes no number, is set aside; every other field (data, conversion, loss, training, seed, time
    limit) must be equal, as for :func:`key_differences`."""
    have = _readable(stored, key["experiment"]["train"]["num_workers"])
    nets = [network_identity((k.get("experiment") or {}).get("model") or {}) for k in (have, key)]
    if nets[0] is None or nets[0] != nets[1]:
        return False

    def without_model(k: dict) -> dict:
        return {**k, "experiment": {f: v for f, v in k["experiment"].items() if f not in ("model", "name")}}

    return not flat_differences(without_model(have), without_model(key))


def under_raised_limit(row: dict, key: dict) -> str | None:
    """How a result row whose key differs from ``key`` stands when the only difference is a raised
    time limit (``time_limit_min`` higher, or none): ``"finished"`` if the limit did not cut its run
    (the run under the higher limit is the same run, to the same weights), ``"resume"`` if it did (the
    run trains on, from its folder's checkpoint when there is one). ``None`` for any other difference,
    a lowered limit among them (the run might not have ended within it)."""
    old, new = row["key"].get("time_limit_min"), key.get("time_limit_min")
    raised = old is not None and (new is None or new > old)
    if not raised or key_differences({**row["key"], "time_limit_min": new}, key):
        return None
    return "resume" if cut_by_limit(row) else "finished"


def cut_by_limit(row: dict) -> bool:
    """Whether the study's time limit stopped the run of ``row`` before its last step."""
    return bool(row.get("training", {}).get("cut_at_time_limit"))


def check_rows(grid: Grid, out: str | os.PathLike, rows: dict[str, dict]) -> dict[str, dict]:
    """The rows of ``grid``'s runs that are finished (present with a matching key), by run id.

    A row that differs only by a lower time limit that did not cut its run is finished too; one
    that such a limit cut is left out, so its run trains on (:func:`under_raised_limit`).

    Raises
    ------
    ValueError
        A row of a run of the grid holds another key (other than by a raised time limit): every
        such run is named with its first differing fields, and what to do.
    """
    finished, bad = {}, []
    for run in grid.runs:
        row = rows.get(run.id)
        if row is None:
            continue
        key = run_key(grid, run)
        diff = key_differences(row["key"], key)
        if diff and (raised := under_raised_limit(row, key)) is not None:
            if raised == "finished":
                finished[run.id] = row
            continue
        if diff:
            more = f" (and {len(diff) - 3} more)" if len(diff) > 3 else ""
            bad.append(f"{run.id}: {'; '.join(diff[:3])}{more}")
        else:
            finished[run.id] = row
    if bad:
        rows_dir = Path(out) / RESULTS_DIR
        raise ValueError(f"{rows_dir}: {len(bad)} result row(s) were made by another configuration of the same run, "
                         "so the study cannot resume them: " + " | ".join(bad[:5])
                         + (f" | ... {len(bad) - 5} more" if len(bad) > 5 else "")
                         + ". Remove those rows (and their run folders) to train them again with this config, or "
                         "give another --out")
    return finished
