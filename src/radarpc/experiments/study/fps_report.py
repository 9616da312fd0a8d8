"""The FPS study's report from its rows: the paper's Table 2 as Markdown, and frames/s against density.

:func:`write_fps_report` reads ``RUNS/results/*.json`` (rows of :data:`~radarpc.experiments.study.fps.FPS_ROW_FORMAT`;
the rows alone are enough) and writes ``report.md`` and ``figures/fps.png`` (default into
``RUNS/report/``; ``radarpc report RUNS`` calls it for an FPS study's output):

* frames/s at batch 1 per model and density: the median of the timed sweeps and their range, of
  the network alone and with the extraction from the RD cube, plain and ``fast_inference``; the
  achieved density and CFAR threshold of the input, the points (or RD cells) a frame, the parameters;
* with a dense model in the study: each model's frames/s with extraction over the dense model's
  (same sensor and mode), the paper's comparison;
* the working memory of one inference per path and mode, and the process's peak resident set;
* the machine (CPU, instruction sets, threads, device) and every row's load average at the start
  and end of its timing: frames/s measured while other processes ran are lower than the machine's;
* a figure of frames/s against density (log axes), one panel per mode, the dense models as lines;
* with ``scores`` (training studies' outputs, e.g. the density sweep): the paper's Table 2 pairing,
  each model's F1 @ 0.2 beside its frames/s, where a training study scored the same model
  (variant and config changes), sensor, input, enrichments and density (:func:`collect_scores`).

Like the training studies' report it states the study command, config file and commits of its
rows and of itself (:mod:`radarpc.experiments.study.provenance`), and ends with the study config.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from radarpc.experiments.study.fps import FPS_REQUIRED, FPS_ROW_FORMAT
from radarpc.experiments.study.provenance import provenance
from radarpc.experiments.study.results import RESULTS_DIR, plain_json, read_rows, row_origin
from radarpc.io import atomic_write
from radarpc.models.complexity import MEMORY_METHODS

__all__ = ["FPSModelRows", "collect_fps", "ScoreKey", "collect_scores", "write_fps_report", "FPS_FIGURE"]

FPS_FIGURE = "fps.png"
_PATH_TITLES = {"network": "network alone", "pipeline": "with extraction"}
_MB = 2 ** 20


@dataclass
class FPSModelRows:
    """The rows of one model: by density (None for a dense model), by mode."""

    name: str
    sensor: str
    input: str
    variant: str
    enrich: tuple[str, ...]
    order: int
    overrides: str = "{}"                   # the model's config changes from the variant's (canonical JSON)
    rows: dict[float | None, dict[str, dict]] = field(default_factory=dict)

    @property
    def dense(self) -> bool:
        return self.input == "dense"

    @property
    def densities(self) -> list[float | None]:
        return sorted(self.rows, key=lambda d: -1.0 if d is None else d)

    def rate(self, density: float | None, mode: str, path: str) -> dict | None:
        """The rate (``median``, ``low``, ``high``) of ``path`` at ``density`` in ``mode``, None if not measured."""
        m = self.rows.get(density, {}).get(mode, {}).get("measurements", {}).get(path)
        return None if not m else m["rate"]


def collect_fps(rows: dict[str, dict]) -> list[FPSModelRows]:
    """The rows as models, in the study's order."""
    models: dict[str, FPSModelRows] = {}
    for row in rows.values():
        a = row["arm"]
        m = models.setdefault(a["name"], FPSModelRows(a["name"], a["sensor"], a["input"], a["variant"],
                                                      tuple(a.get("enrich") or ()), int(a.get("order", 10 ** 6)),
                                                      _canonical(row["key"]["model"].get("overrides") or {})))
        m.rows.setdefault(row["density"], {})[row["mode"]] = row
    return sorted(models.values(), key=lambda m: (m.order, m.name))


ScoreKey = tuple[str, str, str, str, tuple[str, ...], "float | None"]
"""What pairs a training study's score with an FPS row: ``(sensor, variant, overrides, input, enrich,
density)``, ``overrides`` the model config's changes from the variant's as canonical JSON (so an
ablation arm with other point features is not another arm's model)."""


def _canonical(overrides: dict) -> str:
    return json.dumps(plain_json(overrides), sort_keys=True)


def _trained_model(model: dict) -> tuple[str, str]:
    """``(variant, canonical overrides)`` of a training row's ``key.experiment.model``: the fields its
    resolved config changes from the variant's, as the FPS study records them."""
    from radarpc.models import ModelSpec

    spec = ModelSpec(model["variant"], model.get("overrides") or {})
    return spec.variant, _canonical(ModelSpec.matching(spec.variant, spec.config).overrides)


def collect_scores(studies) -> dict[ScoreKey, list[tuple[str, list[float]]]]:
    """F1 @ 0.2 (``metrics.f1_fixed``) of training studies' rows by :data:`ScoreKey`; a run trained
    once counts once, under the first study given that holds it (two arms of one run, a row taken
    with ``--reuse``: :func:`~radarpc.experiments.study.results.row_origin`).

    Parameters
    ----------
    studies : sequence of path-like
        Training study outputs (``radarpc experiment density-sweep|ablation --out``) or their
        ``results/`` folders.

    Returns
    -------
    dict
        Per key, one ``(study name, values over seeds)`` per study that scored it, in the order given.

    Raises
    ------
    FileNotFoundError
        A study without result rows.
    """
    found: dict[ScoreKey, dict[str, list[float]]] = {}
    counted: set[tuple[str, str]] = set()
    for study in studies:
        rows = read_rows(Path(study))
        if not rows:
            raise FileNotFoundError(f"{study}: no result rows of a training study (no {RESULTS_DIR}/*.json)")
        for row in sorted(rows.values(), key=lambda r: r["seed"]):
            f1 = row["metrics"].get("f1_fixed")
            origin = row_origin(row)
            if f1 is None or (origin["study"], origin["run"]) in counted:
                continue                       # a run trained once counts once (twin arms, --reuse rows)
            counted.add((origin["study"], origin["run"]))
            a = row["arm"]
            variant, overrides = _trained_model(row["key"]["experiment"]["model"])
            key = ((row["key"].get("data") or {}).get("sensor", "?"), variant, overrides, a["input"],
                   tuple(a.get("enrich") or ()), row["density"])
            found.setdefault(key, {}).setdefault(row["study"]["name"], []).append(float(f1))
    return {k: list(v.items()) for k, v in found.items()}


def _score_cell(scores: list[tuple[str, list[float]]]) -> str:
    from radarpc.eval.curves import seed_statistics

    cells = []
    for study, values in scores:
        st = seed_statistics(values)
        cells.append(f"{st.mean:.3f}" + ("" if st.std is None else f" ± {st.std:.3f}") + f" ({st.n}, {study})")
    return "; ".join(cells)


def _score_table(models: list[FPSModelRows], modes: list[str], scores: dict) -> list[str]:
    """F1 @ 0.2 beside frames/s (the model's own path: with extraction, or the network on a dense cube)."""
    head = ["model", "sensor", "density", "F1 @ 0.2 (runs, study)"] + [f"frames/s, {mode}" for mode in modes]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for m in models:
        for d in m.densities:
            got = scores.get((m.sensor, m.variant, m.overrides, m.input, m.enrich, d))
            if not got:
                continue
            path = "network" if m.dense else "pipeline"
            lines.append("| " + " | ".join([m.name, m.sensor, _pct(d), _score_cell(got)]
                                           + [_rate_cell(m.rate(d, mode, path)) for mode in modes]) + " |")
    return lines if len(lines) > 2 else []


def _pct(d: float | None) -> str:
    return "100 % (dense)" if d is None else f"{100 * d:.3g} %"


def _rate_cell(rate: dict | None) -> str:
    if rate is None:
        return "-"
    return f"{rate['median']:.3g} ({rate['low']:.3g}-{rate['high']:.3g})"


def _modes(models: list[FPSModelRows]) -> list[str]:
    found = {mode for m in models for per in m.rows.values() for mode in per}
    return [mode for mode in ("plain", "fast") if mode in found]


def _any_row(m: FPSModelRows, d: float | None) -> dict:
    per = m.rows[d]
    return per.get("plain") or next(iter(per.values()))


def _input_cell(row: dict) -> str:
    rec = row.get("input")
    if not rec:
        return "whole cubes"
    density = rec.get("achieved_density")
    tau = rec.get("tau")
    return (("n/a" if density is None else f"{100 * density:.3g} %") + ", "
            + ("tau per frame" if tau is None else f"tau {tau:.3g}"))


def _per_frame(row: dict) -> str:
    if row.get("points_per_frame") is not None:
        return f"{row['points_per_frame']:.0f} points"
    if row.get("cells_per_frame") is not None:
        return f"{row['cells_per_frame']:.0f} cells"
    return "-"


def _rate_table(models: list[FPSModelRows], modes: list[str]) -> list[str]:
    head = ["model", "sensor", "input", "density", "achieved density, tau", "input a frame", "parameters"]
    head += [f"{_PATH_TITLES[p]}, {mode}" for p in ("network", "pipeline") for mode in modes]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for m in models:
        for d in m.densities:
            row = _any_row(m, d)
            what = m.input + (f" +{'+'.join(m.enrich)}" if m.enrich else "")
            cells = [m.name, m.sensor, what, _pct(d), _input_cell(row), _per_frame(row), f"{row['parameters']:,}"]
            for p in ("network", "pipeline"):
                for mode in modes:
                    cells.append("n/a (reads the cube)" if m.dense and p == "pipeline"
                                 else _rate_cell(m.rate(d, mode, p)))
            lines.append("| " + " | ".join(cells) + " |")
    return lines


def _relative_table(models: list[FPSModelRows], modes: list[str]) -> list[str]:
    """Frames/s with extraction over the dense model's network (same sensor and mode)."""
    dense = {m.sensor: m for m in models if m.dense}
    if not dense:
        return []
    head = ["model", "sensor", "density"] + [f"with extraction / dense, {mode}" for mode in modes]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for m in models:
        ref = dense.get(m.sensor)
        if m.dense or ref is None:
            continue
        for d in m.densities:
            cells = [m.name, m.sensor, _pct(d)]
            for mode in modes:
                r, base = m.rate(d, mode, "pipeline"), ref.rate(None, mode, "network")
                cells.append("-" if r is None or base is None else
                             f"{r['median'] / base['median']:.2f}x ({r['median'] - base['median']:+.3g} frames/s)")
            lines.append("| " + " | ".join(cells) + " |")
    names = ", ".join(f"{ref.name} on {s}" for s, ref in dense.items())
    return [f"The dense reference: {names} (network alone: it reads the cube as it is). Above 1x a model with its "
            f"extraction runs faster than the dense model; the difference is in frames/s, as the paper's.", ""] + lines


def _memory_table(models: list[FPSModelRows], modes: list[str]) -> list[str]:
    head = ["model", "sensor", "density"] + [f"{_PATH_TITLES[p]}, {mode}" for p in ("network", "pipeline")
                                             for mode in modes] + ["process peak (MB)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for m in models:
        for d in m.densities:
            cells = [m.name, m.sensor, _pct(d)]
            peak = 0
            for p in ("network", "pipeline"):
                for mode in modes:
                    meas = m.rows.get(d, {}).get(mode, {}).get("measurements", {}).get(p)
                    if not meas:
                        cells.append("n/a" if m.dense and p == "pipeline" else "-")
                        continue
                    mem = meas["memory"]
                    peak = max(peak, mem["peak_bytes"])
                    cells.append(f"{mem['working_bytes'] / _MB:.1f}")
            cells.append(f"{peak / _MB:.0f}" if peak else "-")
            lines.append("| " + " | ".join(cells) + " |")
    return lines


def _load_text(load: dict | None) -> str:
    if not load or not load.get("start") or not load.get("end"):
        return "n/a"
    return f"{load['start'][0]:.2f} -> {load['end'][0]:.2f}"


def _rows_table(rows: dict[str, dict]) -> list[str]:
    lines = ["| row | 1-min load average (start -> end) | threads | device | timing (s) | finished at | commit |",
             "|---|---|---|---|---|---|---|"]
    order = {"plain": 0, "fast": 1}
    for run_id in sorted(rows, key=lambda k: (rows[k]["arm"].get("order", 10 ** 6), rows[k]["arm"]["name"],
                                             -1.0 if rows[k]["density"] is None else rows[k]["density"],
                                             order.get(rows[k]["mode"], 2))):
        r = rows[run_id]
        mach, t = r["machine"], r.get("times") or {}
        commit = (r.get("software") or {}).get("commit") or "-"
        lines.append(f"| `{run_id}` | {_load_text(mach.get('load_average'))} | {mach.get('threads', '-')} | "
                     f"{mach.get('device_name') or mach.get('device', '-')} | {t.get('timing_s', 0):.1f} | "
                     f"{t.get('finished_at', '-')} | `{commit[:10]}` |")
    return lines


def _machines(rows: dict[str, dict]) -> list[str]:
    seen: dict[str, int] = {}
    for r in rows.values():
        m = r["machine"]
        text = (f"{m.get('cpu', '?')}, {m.get('usable_cpus', '?')} of {m.get('logical_cpus', '?')} logical CPUs usable, "
                f"{m.get('threads', '?')} torch threads, device {m.get('device_name') or m.get('device', '?')}, "
                f"instruction sets {' '.join(m.get('isa') or []) or 'unknown'}, torch kernels "
                f"{m.get('torch_cpu_capability', '?')}")
        seen[text] = seen.get(text, 0) + 1
    return [f"- {text} ({n} rows)" for text, n in seen.items()]


def _load_range(rows: dict[str, dict]) -> str:
    loads = [x[0] for r in rows.values() for k in ("start", "end")
             for x in [(r["machine"].get("load_average") or {}).get(k)] if x]
    return "not recorded" if not loads else f"{min(loads):.2f} to {max(loads):.2f}"


def _panels(models: list[FPSModelRows], modes: list[str]):
    from radarpc.viz import RateCurve, RatePanel

    sensors = {m.sensor for m in models}
    panels = []
    for mode in modes:
        curves, refs = [], []
        for m in models:
            label = m.name if len(sensors) == 1 else f"{m.name} ({m.sensor})"
            if m.dense:
                r = m.rate(None, mode, "network")
                if r is not None:
                    refs.append((f"{label}, dense", r["median"], r["low"], r["high"]))
                continue
            for p in ("network", "pipeline"):
                pts = [(d, m.rate(d, mode, p)) for d in m.densities if d is not None]
                pts = [(d, r) for d, r in pts if r is not None]
                if pts:
                    curves.append(RateCurve(label + (" + extraction" if p == "pipeline" else ""),
                                            tuple(d for d, _ in pts), tuple(r["median"] for _, r in pts),
                                            tuple(r["low"] for _, r in pts), tuple(r["high"] for _, r in pts),
                                            dashed=p == "pipeline"))
        if curves or refs:
            panels.append(RatePanel(f"{mode}" + (" (fast_inference)" if mode == "fast" else " (as built)"),
                                    tuple(curves), tuple(refs)))
    return panels


def write_fps_report(runs: str | os.PathLike, out: str | os.PathLike | None = None, *, command: str | None = None,
                     scores: tuple[str | os.PathLike, ...] = (), log: Callable[[str], None] = print) -> Path:
    """Write ``report.md`` and ``figures/fps.png`` of the FPS study output ``runs`` (see the module docstring).

    Parameters
    ----------
    runs : path-like
        An FPS study output (its ``results/`` folder holds the rows) or the ``results`` folder itself.
    out : path-like, optional
        Where to write (default ``RUNS/report``).
    command : str, optional
        The command that makes the report, stated in it and in its figure.
    scores : sequence of path-like
        Training study outputs whose F1 @ 0.2 is paired with the frames/s (:func:`collect_scores`).

    Returns
    -------
    Path
        The Markdown file.

    Raises
    ------
    FileNotFoundError
        No row in ``runs``, or a ``scores`` study without rows.
    """
    from radarpc.viz import plot_rate_curves

    runs = Path(runs)
    rows = read_rows(runs, row_format=FPS_ROW_FORMAT, required=FPS_REQUIRED)
    if not rows:
        raise FileNotFoundError(f"{runs}: no result rows (no {RESULTS_DIR}/*.json); run `radarpc experiment fps ...` "
                                f"first, or give the study's output folder")
    base = runs.parent if runs.name == RESULTS_DIR and not (runs / RESULTS_DIR).is_dir() else runs
    out = Path(out) if out is not None else base / "report"
    made = provenance(rows, base / RESULTS_DIR, runs, command)
    models = collect_fps(rows)
    modes = _modes(models)
    any_row = next(iter(rows.values()))
    timing = (any_row["study"].get("config") or {}).get("timing") or {}
    methods = sorted({meas["memory"]["method"] for r in rows.values() for meas in r["measurements"].values() if meas})

    lines = made.header(f"FPS study {', '.join(made.studies)}", "timed the rows") + [
        "Batch-1 inference frames/s (the spectral point-cloud paper's Table 2). Each row (a model at a density in "
        "one mode) was timed in a fresh process: "
        f"{timing.get('warmup', '?')} untimed warm-up pass(es) over the first frame, then {timing.get('repeats', '?')} "
        f"timed sweeps over the first {timing.get('frames', '?')} frames of the {timing.get('split', '?')} split; a "
        "cell is the median sweep's frames/s and, in brackets, the slowest and fastest sweep (a CUDA device is "
        "synchronised around each sweep). **network alone**: the model on its stored input (the point store's "
        "clouds, the sparse-RD root's masked cubes, the dense cubes). **with extraction**: the RD cube through the "
        "extraction at the row's density, then the model: CA-CFAR, beamforming and the enrichments into a spectral "
        "point cloud for a pillar model, the same detection masked onto the cube for sparse-RD FFTRadNet. **plain**: "
        "the model as built (eval mode); **fast**: `radarpc.models.fast.fast_inference`'s exact rewrite of it. "
        + ("Detection head only. " if timing.get("detections_only") else "Both heads (detection and freespace). ")
        + "Density: the target fraction of RD cells the input encodes; the achieved density and the CFAR threshold "
        "tau are those of the input's root (tau calibrated on its training split).", "",
        f"Machine: the 1-minute load average ranged from {_load_range(rows)} over the rows; timings taken while "
        "other processes ran are lower than the machine's speed (see every row's load below).", ""] + _machines(rows) + [""]
    lines += ["## frames/s at batch 1", ""] + _rate_table(models, modes) + [""]
    if scores:
        paired = _score_table(models, modes, collect_scores(scores))
        lines += ["## F1 beside frames/s (the paper's Table 2)", "",
                  "F1 at IoU 0.5 and confidence 0.2 on the test split: mean ± sample standard deviation over the "
                  "runs of the training studies " + ", ".join(f"`{Path(x)}`" for x in scores) + " that trained the "
                  "same model (variant), on the same sensor, input and enrichments, at the same target density "
                  "(their weights were trained, the timed ones are not: speed does not depend on the weights). "
                  "Frames/s: the model's path from the RD cube, with extraction (the network alone for a dense "
                  "model), median (range) of the timed sweeps.", ""]
        lines += paired if paired else ["No FPS row matches a scored run of those studies.", ""]
        lines += [""]
    rel = _relative_table(models, modes)
    if rel:
        lines += ["## with extraction against the dense model", ""] + rel + [""]
    panels = _panels(models, modes)
    if panels:
        fig = out / "figures" / FPS_FIGURE
        plot_rate_curves(panels, fig, title=f"{', '.join(made.studies)}: frames/s against density",
                         footer=made.footer, metadata=made.metadata)
        lines += [f"![frames/s at batch 1 against density, network alone and with extraction](figures/{FPS_FIGURE})",
                  "", f"*Frames/s at batch 1 against density (log axes), one panel per mode: median of the timed sweeps "
                  f"(markers) and their range (bars), the network alone (solid) and with extraction (dashed), dense "
                  f"models as dotted lines. Made by `{made.made_by}` from the rows of `{made.commands[0]}`, commit(s) "
                  f"{', '.join(f'`{c[:10]}`' for c in made.commits)}.*", ""]
    lines += ["## working memory of one inference (MB)", "",
              "What the timed sweeps needed above the process's memory once warmed up (weights, frames, runtime and "
              "buffers kept between passes are in that baseline): " + "; ".join(f"`{k}`: {MEMORY_METHODS.get(k, k)}" for k in methods)
              + ". The last column is the process's highest peak over the row (runtime, weights and frames included).",
              ""] + _memory_table(models, modes) + [""]
    lines += ["## rows", ""] + _rows_table(rows) + [""]
    lines += made.config_section()
    path = out / "report.md"
    with atomic_write(path, "w") as f:
        f.write("\n".join(lines))
    log(f"wrote {path}" + (f" and {out / 'figures' / FPS_FIGURE}" if panels else ""))
    return path
