"""A study's report from its result rows: Markdown tables and PNG figures.

:func:`write_report` reads ``RUNS/results/*.json`` (rows alone are enough: the run folders and
their weights need not be on this machine) and writes ``report.md`` and ``figures/GROUP.png``
(default into ``RUNS/report/``). Per group of arms (the sweep's models; the axis, enrichment and
sparse-RD ablations):

* F1 at IoU 0.5 and confidence 0.2 on the evaluation split, per arm and density: the mean and
  sample standard deviation over seeds (and their number);
* the normalized AUC of each arm's mean curve over the group's common density interval
  (:func:`radarpc.eval.curves.normalized_auc`: the mean F1 over the sweep), its difference to the
  group's first arm (the seed's "average F1 gain"), and the lowest density whose mean reaches the
  dense reference's;
* freespace mIoU the same way (the seed's Table 1);
* what the runs read: the achieved density and the calibrated tau per arm and density;
* every run: its scores, steps, training time, whether its time limit cut it, its commit (a run
  that is the same as another's, ``same_as``, is marked);
* a figure of F1 and freespace mIoU against density (log axis), mean, spread and every run, the
  dense reference as a horizontal line.

Everything says what made it: the study command and config file of the rows, the commits of the
code that trained them (and of this report), the report command; the figures carry the same in a
footer and in their metadata (:mod:`radarpc.experiments.study.provenance`). The study config
itself ends the report. The rows of an FPS study make the FPS report instead
(:func:`radarpc.experiments.study.fps_report.write_fps_report`).
"""
from __future__ import annotations

import os
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from radarpc.eval.curves import DensityCurve, normalized_auc, seed_statistics
from radarpc.experiments.study.fps import FPS_ROW_FORMAT
from radarpc.experiments.study.grid import GROUPS
from radarpc.experiments.study.provenance import provenance
from radarpc.experiments.study.results import RESULTS_DIR, read_rows, rows_format
from radarpc.io import atomic_write

__all__ = ["ArmResults", "GroupResults", "collect", "write_report", "REPORT_MD", "GROUP_TITLES"]

REPORT_MD = "report.md"
GROUP_TITLES = {
    "models": "models against density",
    "axes": "point axes (the spectral point-cloud paper's Fig. 5)",
    "enrichments": "spectral enrichments (the paper's Fig. 6)",
    "rd-comparison": "spectral points against sparse RD (the paper's Fig. 7)",
}
_METRICS = {"f1_fixed": "F1 @ 0.2", "freespace_miou": "freespace mIoU"}


@dataclass
class ArmResults:
    """The rows of one arm: per density (None for a dense arm), the runs' rows in seed order."""

    name: str
    label: str
    group: str
    input: str
    rows: dict[float | None, list[dict]] = field(default_factory=dict)

    @property
    def dense(self) -> bool:
        return self.input == "dense"

    @property
    def densities(self) -> list[float]:
        return sorted(d for d in self.rows if d is not None)

    def values(self, metric: str, density: float | None) -> list[float]:
        """The runs' ``metric`` at ``density`` (runs without it left out)."""
        return [float(r["metrics"][metric]) for r in self.rows.get(density, [])
                if r["metrics"].get(metric) is not None]

    def curve(self, metric: str, interval: tuple[float, float] | None) -> DensityCurve:
        """The arm's ``metric`` against density, its normalized AUC over ``interval`` when the arm
        spans it with at least two densities."""
        ds = [d for d in self.densities if self.values(metric, d)]
        runs = tuple(tuple(self.values(metric, d)) for d in ds)
        return DensityCurve(self.label, tuple(ds), runs, _auc(ds, runs, interval))


def _auc(ds: list[float], runs: tuple, interval: tuple[float, float] | None) -> float | None:
    if interval is None or len(ds) < 2 or ds[0] > interval[0] or ds[-1] < interval[1]:
        return None
    return normalized_auc(ds, [seed_statistics(r).mean for r in runs], interval)


@dataclass
class GroupResults:
    """The arms of one group, density arms in their study order, and the dense references."""

    group: str
    arms: list[ArmResults]

    @property
    def curves(self) -> list[ArmResults]:
        return [a for a in self.arms if not a.dense]

    @property
    def references(self) -> list[ArmResults]:
        return [a for a in self.arms if a.dense]

    @property
    def densities(self) -> list[float]:
        return sorted({d for a in self.curves for d in a.densities})

    def interval(self, metric: str = "f1_fixed") -> tuple[float, float] | None:
        """The density interval every curve of the group spans (None when that is empty)."""
        spans = [(a.densities[0], a.densities[-1]) for a in self.curves
                 if len([d for d in a.densities if a.values(metric, d)]) >= 2]
        if not spans or len(spans) != len(self.curves):
            return None
        lo, hi = max(s[0] for s in spans), min(s[1] for s in spans)
        return (lo, hi) if lo < hi else None


def collect(rows: dict[str, dict]) -> list[GroupResults]:
    """The rows as groups of arms (groups in :data:`GROUPS` order, arms in the study's order)."""
    arms: dict[str, ArmResults] = {}
    order: dict[str, int] = {}
    for run_id, row in sorted(rows.items(), key=lambda kv: (kv[1]["seed"], kv[0])):
        a = row["arm"]
        arm = arms.setdefault(a["name"], ArmResults(a["name"], a["label"], a["group"], a["input"]))
        arm.rows.setdefault(row["density"], []).append(row)
        order.setdefault(a["name"], int(a.get("order", 10**6)))
    for arm in arms.values():
        for runs in arm.rows.values():
            runs.sort(key=lambda r: r["seed"])
    groups = defaultdict(list)
    for arm in sorted(arms.values(), key=lambda a: (order[a.name], a.name)):
        groups[arm.group].append(arm)
    return [GroupResults(g, groups[g]) for g in GROUPS if g in groups] + \
           [GroupResults(g, arms_) for g, arms_ in groups.items() if g not in GROUPS]


def _pct(d: float) -> str:
    return f"{100 * d:.3g} %"


def _cell(values: list[float]) -> str:
    if not values:
        return "-"
    s = seed_statistics(values)
    return f"{s.mean:.3f}" + ("" if s.std is None else f" ± {s.std:.3f}") + f" ({s.n})"


def _metric_table(g: GroupResults, metric: str) -> list[str]:
    ds = g.densities
    interval = g.interval(metric)
    refs = g.references
    ref_mean = seed_statistics(refs[0].values(metric, None)).mean if refs and refs[0].values(metric, None) else None
    head = ["arm"] + [_pct(d) for d in ds]
    auc_head = f"AUC_norm {_pct(interval[0])}-{_pct(interval[1])}" if interval else "AUC_norm"
    first = g.curves[0] if g.curves else None
    head += [auc_head] + ([f"Δ AUC vs {first.label}"] if first is not None and len(g.curves) > 1 else [])
    if ref_mean is not None:
        head.append(f"first density reaching {refs[0].label}")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    first_auc = first.curve(metric, interval).auc if first is not None else None
    for arm in g.curves:
        curve = arm.curve(metric, interval)
        cells = [arm.label] + [_cell(arm.values(metric, d)) for d in ds]
        cells.append("-" if curve.auc is None else f"{curve.auc:.3f}")
        if first is not None and len(g.curves) > 1:
            cells.append("-" if curve.auc is None or first_auc is None
                         else ("0 (baseline)" if arm is first else f"{curve.auc - first_auc:+.3f}"))
        if ref_mean is not None:
            reach = [d for d, s in zip(curve.density, curve.statistics) if s.mean >= ref_mean]
            cells.append(_pct(reach[0]) if reach else "not reached")
        lines.append("| " + " | ".join(cells) + " |")
    for ref in refs:
        cells = [f"{ref.label} (dense, every density)"] + [_cell(ref.values(metric, None))] * len(ds)
        cells += ["-"] * (len(head) - len(cells))
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _inputs_table(g: GroupResults) -> list[str]:
    ds = g.densities
    lines = ["| arm | " + " | ".join(_pct(d) for d in ds) + " |", "|" + "---|" * (len(ds) + 1)]
    for arm in g.curves:
        cells = [arm.label]
        for d in ds:
            recs = [rec for r in arm.rows.get(d, [])[:1] for rec in r.get("inputs", [])]   # one seed: the same inputs
            dens = [rec["achieved_density"] for rec in recs if rec.get("achieved_density") is not None]
            taus = [rec["tau"] for rec in recs if rec.get("tau") is not None]
            if not recs:
                cells.append("-")
                continue
            density = _pct(sum(dens) / len(dens)) if dens else "n/a"
            if not taus:
                tau = "tau per frame"
            elif max(taus) == min(taus):
                tau = f"tau {taus[0]:.3g}"
            else:                                          # one tau per root
                tau = f"tau {min(taus):.3g}-{max(taus):.3g}"
            cells.append(f"{density}, {tau}")
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _runs_table(rows: list[dict]) -> list[str]:
    lines = ["| run | F1 @ 0.2 | F1 | freespace mIoU | weights (epoch, step) | training (min) | cut by the time limit "
             "| frames/s (batch 1) | commit |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        m, t, e = r["metrics"], r.get("training", {}), r.get("evaluation", {})
        commit = (r.get("software") or {}).get("commit") or "-"
        fps = e.get("fps_batch1")
        run = f"`{r['run']}`" + (f" (= `{r['same_as']}`)" if r.get("same_as") else "")
        lines.append(f"| {run} | {_num(m.get('f1_fixed'))} | {_num(m.get('f1'))} | "
                     f"{_num(m.get('freespace_miou'))} | {t.get('weights_epoch', '-')}, {t.get('weights_step', '-')} | "
                     f"{(t.get('train_time_s') or 0) / 60:.1f} | {'yes' if t.get('cut_at_time_limit') else 'no'} | "
                     f"{'-' if fps is None else f'{fps:.3g}'} | `{commit[:10]}` |")
    return lines


def _num(x) -> str:
    return "-" if x is None else f"{x:.3f}"


def write_report(runs: str | os.PathLike, out: str | os.PathLike | None = None, *, command: str | None = None,
                 scores: tuple[str | os.PathLike, ...] = (), log: Callable[[str], None] = print) -> Path:
    """Write ``report.md`` and the figures of the study output ``runs`` (see the module docstring).

    Parameters
    ----------
    runs : path-like
        A study output (its ``results/`` folder holds the rows) or the ``results`` folder itself.
    out : path-like, optional
        Where to write (default ``RUNS/report``).
    command : str, optional
        The command that makes the report, stated in it and in its figures.
    scores : sequence of path-like
        An FPS study only: training studies whose F1 @ 0.2 is paired with its frames/s
        (:func:`radarpc.experiments.study.fps_report.collect_scores`).

    Returns
    -------
    Path
        The Markdown file.

    Raises
    ------
    FileNotFoundError
        No result row in ``runs``.
    """
    from radarpc.viz import DensityPanel, plot_density_curves

    runs = Path(runs)
    if rows_format(runs) == FPS_ROW_FORMAT:
        from radarpc.experiments.study.fps_report import write_fps_report

        return write_fps_report(runs, out, command=command, scores=tuple(scores), log=log)
    if scores:
        raise ValueError(f"{runs}: --scores pairs F1 with an FPS study's frames/s; {runs} is a training study "
                         f"(give the output of `radarpc experiment fps`)")
    rows = read_rows(runs)
    if not rows:
        raise FileNotFoundError(f"{runs}: no result rows (no {RESULTS_DIR}/*.json); run `radarpc experiment ...` "
                                f"first, or give the study's output folder")
    base = runs.parent if runs.name == RESULTS_DIR and not (runs / RESULTS_DIR).is_dir() else runs
    out = Path(out) if out is not None else base / "report"
    made = provenance(rows, base / RESULTS_DIR, runs, command)
    made_by, commands, commits, studies = made.made_by, made.commands, made.commits, made.studies
    footer, metadata = made.footer, made.metadata
    splits = sorted({(r.get("evaluation") or {}).get("split", "?") for r in rows.values()})
    easy = sorted({(r.get("evaluation") or {}).get("easy") for r in rows.values()}, key=str)

    lines = made.header(f"Study {', '.join(studies)}", "trained and scored the runs") + [
             f"Scores: RADIal's metrics of each run's best-validation weights on the {'/'.join(splits)} split at IoU "
             f"0.5; **F1 @ 0.2** is F1 at the one confidence threshold 0.2, the spectral point-cloud paper's density-sweep protocol"
             + (", in RADIal's easy mode (Difficult labels dropped)" if easy == [True] else
                "" if easy == [False] else ", easy mode as each run's experiment trains") + ". "
             "A cell is the mean ± sample standard deviation over seeds (the number of runs). Density: the target "
             "fraction of RD cells the input encodes, |S(tau)| / (N_r N_D) (|S*(tau)| with an RD-neighbourhood "
             "enrichment). AUC_norm: the trapezoid area under the mean curve over the density interval every arm "
             "spans, divided by its length (density on a linear scale, as the paper's: `radarpc.eval.curves`), i.e. the "
             "mean score over the sweep; Δ AUC is the average gain over the group's first arm.", ""]
    for g in collect(rows):
        name = g.group
        title = GROUP_TITLES.get(name, name)
        lines += [f"## {title}", ""]
        panels = []
        for metric, what in _METRICS.items():
            if not any(a.values(metric, d) for a in g.arms for d in a.rows):
                continue
            lines += [f"### {what}", ""] + _metric_table(g, metric) + [""]
            interval = g.interval(metric)
            panels.append(DensityPanel(
                ylabel=what + (" (IoU 0.5)" if metric == "f1_fixed" else ""),
                title=f"{what} on the {'/'.join(splits)} split",
                curves=tuple(a.curve(metric, interval) for a in g.curves if a.densities and
                             any(a.values(metric, d) for d in a.densities)),
                references=tuple((a.label, tuple(a.values(metric, None))) for a in g.references
                                 if a.values(metric, None))))
        if g.curves:
            lines += ["### inputs: achieved density and CFAR threshold tau", ""] + _inputs_table(g) + [""]
        if panels:
            fig = out / "figures" / f"{name}.png"
            plot_density_curves(panels, fig, title=f"{', '.join(studies)}: {title}", footer=footer,
                                metadata=metadata)
            lines += [f"![{title}: F1 @ 0.2 and freespace mIoU against density](figures/{fig.name})", "",
                      f"*{title}: mean over seeds (line), ± one standard deviation (band), every run (dots); dense "
                      f"references as horizontal lines. Made by `{made_by}` from the rows of `{commands[0]}`, "
                      f"commit(s) {', '.join(f'`{c[:10]}`' for c in commits)}.*", ""]
        group_rows = [r for a in g.arms for d in sorted(a.rows, key=lambda x: -1 if x is None else x)
                      for r in a.rows[d]]
        lines += ["### runs", ""] + _runs_table(group_rows) + [""]
    lines += made.config_section()
    path = out / REPORT_MD
    with atomic_write(path, "w") as f:
        f.write("\n".join(lines))
    log(f"wrote {path} and {len(list((out / 'figures').glob('*.png')))} figures in {out / 'figures'}")
    return path
